"""Synthetic truth end to end (pycolmap's pattern): a seeded plant in, its exact normals back."""

import numpy as np

from flowerpose.config import apply_overrides
from flowerpose.eval.match import score_plant
from flowerpose.eval.truth import read_plant_truth
from flowerpose.pipeline.flowers import PipelineConfig, find_flowers


def test_seeded_plant_flowers_and_normals_come_back(plant0):
    bundle, plant_dir = plant0
    result = find_flowers(bundle.cloud, PipelineConfig())
    truth = read_plant_truth(plant_dir / "plant.json")
    score = score_plant([f.pose for f in result.flowers], truth)
    assert score.found == score.gt == 6 and score.fp == 0
    for method in ("plane", "superellipsoid", "paraboloid"):
        errors = np.array(score.error_deg[method])
        assert len(errors) == 6 and score.failed[method] == 0
        assert errors.mean() < 3.0 and errors.max() < 8.0, (method, errors)


def test_masks_find_at_least_what_boxes_find(plant0):
    # The paper's suggested improvement: a box carries leaves into the flower's cluster.
    bundle, plant_dir = plant0
    truth = read_plant_truth(plant_dir / "plant.json")
    found = {}
    for mode in ("mask", "box"):
        config = apply_overrides(PipelineConfig(), {"detect.backproject": mode})
        result = find_flowers(bundle.cloud, config)
        found[mode] = score_plant([f.pose for f in result.flowers], truth).found
    assert found["box"] >= 1
    assert found["mask"] >= found["box"]
