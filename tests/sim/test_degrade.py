"""A plant's oracle cloud degraded like a field scan: seeded per plant, recorded, and at the
density asked for."""

import dataclasses
import json

import numpy as np
import pytest

from flowerpose.sim.bundle import make_plant
from flowerpose.sim.degrade import points_per_flower
from flowerpose.sim.world_config import DegradeConfig, sim_preset


@pytest.mark.slow
def test_a_fixed_density_is_what_the_flowers_hold_and_plant_json_records_the_draw(tmp_path):
    config = dataclasses.replace(sim_preset("easy"), degrade=DegradeConfig(
        points_per_flower=(60.0, 60.0), exposure=(0.7, 0.7), cast=0.1, noise_m=(5e-4, 5e-4)))
    plain = make_plant(1, config=sim_preset("easy"))
    degraded = make_plant(1, config=config, out_dir=tmp_path)
    assert points_per_flower(plain.point_flower, plain.visible) > 150
    assert abs(points_per_flower(degraded.point_flower, degraded.visible) - 60) <= 10
    drawn = json.loads((tmp_path / "plant.json").read_text())["degradation"]
    assert drawn["points_per_flower"] == 60 and drawn["exposure"] == 0.7
    assert drawn["cast"]["channel"] in "rgb" and abs(drawn["cast"]["change"]) <= 0.1
    # Darker: exposure 0.7 on linear light, whatever the cast.
    assert degraded.cloud.colors.mean() < plain.cloud.colors.mean()
    # The same seed draws the same degradation.
    again = make_plant(1, config=config)
    assert np.array_equal(again.cloud.points, degraded.cloud.points)


def test_the_default_degrades_nothing(tmp_path):
    make_plant(2, config=sim_preset("easy"), out_dir=tmp_path)
    assert "degradation" not in json.loads((tmp_path / "plant.json").read_text())
