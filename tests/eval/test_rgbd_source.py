"""The RGB-D source, small: a depth camera films one easy plant from a coarse scan path,
the frames are fused, the pipeline runs on the fused cloud and is scored against the truth
with the capture's own visibility."""

import pytest

from flowerpose.config import apply_overrides
from flowerpose.eval.jobs.config import eval_config
from flowerpose.eval.jobs.eval_run import EvalRun
from flowerpose.eval.jobs.plant_set import PlantSet
from flowerpose.eval.pool import Execution
from flowerpose.eval.studies.eval_recipe import run_eval

#: 18 views of 640 x 360 (a ring every 8 cm, one every 60 degrees, one dome ring).
SMALL = {"sim.viewpoints.azimuth_step_deg": 60.0, "sim.viewpoints.cylinder_step_m": 0.08,
         "sim.viewpoints.dome_polar_deg": [50.0]}


@pytest.mark.slow
def test_a_small_rgbd_scan_is_fused_and_its_flowers_found(tmp_path):
    config = apply_overrides(eval_config("easy"), SMALL)
    report = run_eval(config, EvalRun(PlantSet("rgbd", plants=1, seed=2)), tmp_path, Execution(1))
    summary = report["summary"]
    # Seed 2 has 5 open flowers; 18 views leave one of them too thinly seen to pass.
    assert summary["gt"] == 5 and summary["found"] >= 4 and summary["fp"] == 0
    assert summary["error_deg"]["plane"]["mean"] < 10.0
    petals = report["reconstruction"]["seed-2"]["petals"]
    assert petals["precision_5mm"] > 0.95 and petals["completeness_5mm"] > 0.9
    # The run's settings are the RGB-D source's: no scan or photogrammetry sections.
    assert {"rgbd", "fusion"} <= set(report["config"]) and "scan" not in report["config"]
    plant = tmp_path / "plants" / "seed-2"
    assert (plant / "rgbd" / "cloud.ply").stat().st_size > 0
    assert (plant / "rgbd" / "plant.json").exists()
