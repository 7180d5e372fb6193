"""Removing the soil: a tilted, offset soil plane under a plant."""

import numpy as np

from flowerpose.cloudio import Cloud
from flowerpose.pipeline.ground import GroundConfig, remove_ground


def test_ground_plane_is_removed_even_when_tilted_and_offset():
    rng = np.random.default_rng(0)
    soil = np.c_[rng.uniform(-0.3, 0.3, (20000, 2)), np.zeros(20000)]
    tilt = np.radians(5)
    soil[:, 2] = 0.03 + np.tan(tilt) * soil[:, 0] + rng.normal(0, 0.001, 20000)
    plant = np.c_[rng.uniform(-0.1, 0.1, (3000, 2)), rng.uniform(0.08, 0.3, 3000)]
    points = np.vstack([soil, plant])
    cloud = Cloud(points, np.full((len(points), 3), 120, np.uint8))
    kept = remove_ground(cloud, GroundConfig(method="plane"))
    assert set(kept) == set(range(20000, 23000))
    # The bed-frame rule keeps the soil, which sits 3 cm up here.
    assert len(remove_ground(cloud, GroundConfig(method="height"))) > 20000
