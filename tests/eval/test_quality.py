import numpy as np
import pytest

from flowerpose.eval.capture.quality import reconstruction_quality


def test_the_truth_surface_itself_scores_perfectly_and_noise_lowers_the_scores(plant0):
    bundle, _ = plant0
    plant = bundle.plant
    rng = np.random.default_rng(0)
    points, _ = __import__("trimesh").sample.sample_surface(plant.mesh, 150_000, seed=1)
    exact = reconstruction_quality(points, plant.mesh, plant.face_part, samples=20_000)
    assert exact["plant"]["accuracy_m"] < 1e-6
    assert exact["plant"]["fscore_2mm"] > 0.95 and exact["petals"]["fscore_5mm"] > 0.95
    noisy = points + rng.normal(0, 0.003, points.shape)
    worse = reconstruction_quality(noisy, plant.mesh, plant.face_part, samples=20_000)
    assert worse["plant"]["accuracy_m"] == pytest.approx(0.003 * 0.67, rel=0.3)
    assert worse["plant"]["fscore_2mm"] < exact["plant"]["fscore_2mm"] - 0.2
    half = points[points[:, 0] < np.median(points[:, 0])]
    partial = reconstruction_quality(half, plant.mesh, plant.face_part, samples=20_000)
    assert 0.3 < partial["plant"]["completeness_2mm"] < 0.75
