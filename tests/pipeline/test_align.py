"""Similarity alignment: exact recovery, robustness to gross outliers, clear refusals."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from flowerpose.errors import InputError
from flowerpose.pipeline.align import (
    Similarity,
    level_similarity,
    residuals,
    robust_similarity,
    rotation_onto,
    umeyama,
)


def known_similarity(seed: int = 1) -> Similarity:
    rng = np.random.default_rng(seed)
    rotation = Rotation.random(random_state=seed).as_matrix()
    return Similarity(float(rng.uniform(0.05, 20.0)), rotation, rng.normal(0, 2.0, 3))


def test_umeyama_recovers_a_known_similarity_exactly():
    truth = known_similarity()
    source = np.random.default_rng(2).normal(0, 1.0, (40, 3))
    found = umeyama(source, truth.apply(source))
    assert found.scale == pytest.approx(truth.scale, rel=1e-9)
    np.testing.assert_allclose(found.rotation, truth.rotation, atol=1e-9)
    np.testing.assert_allclose(found.translation, truth.translation, atol=1e-9)
    np.testing.assert_allclose(found.apply(source), truth.apply(source), atol=1e-9)


def test_umeyama_minimal_and_without_scale():
    truth = Similarity(1.0, Rotation.from_euler("zyx", [30, -20, 75], degrees=True)
                       .as_matrix(), np.array([1.5, 0.75, 0.3]))
    source = np.array([[0.0, 0, 0], [1, 0, 0], [0, 2, 0]])
    found = umeyama(source, truth.apply(source), with_scale=False)
    assert found.scale == 1.0
    np.testing.assert_allclose(found.matrix, truth.matrix, atol=1e-12)


def test_inverse_and_apply_round_trip():
    truth = known_similarity(3)
    points = np.random.default_rng(4).uniform(-1, 1, (10, 3))
    np.testing.assert_allclose(truth.inverse().apply(truth.apply(points)), points, atol=1e-12)
    np.testing.assert_allclose(truth.inverse().matrix, np.linalg.inv(truth.matrix),
                               atol=1e-12)
    np.testing.assert_allclose(truth.apply(points[0]), truth.apply(points)[0])


def test_robust_similarity_ignores_30_percent_gross_outliers():
    rng = np.random.default_rng(5)
    truth = known_similarity(6)
    source = rng.uniform(-1, 1, (100, 3))
    target = truth.apply(source) + rng.normal(0, 0.002, (100, 3))
    outliers = rng.permutation(100)[:30]
    target[outliers] += rng.uniform(0.5, 3.0, (30, 3)) * rng.choice([-1, 1], (30, 3))
    found, inliers = robust_similarity(source, target, threshold_m=0.02, seed=0)
    expected = np.ones(100, bool)
    expected[outliers] = False
    np.testing.assert_array_equal(inliers, expected)
    assert found.scale == pytest.approx(truth.scale, rel=1e-3)
    angle = Rotation.from_matrix(found.rotation @ truth.rotation.T).magnitude()
    assert np.degrees(angle) < 0.1
    clean = source[expected]
    assert np.abs(found.apply(clean) - truth.apply(clean)).max() < 0.003
    stats = residuals(found, source, target, inliers)
    assert stats["inliers"] == 70 and stats["points"] == 100
    assert 0.001 < stats["rms_m"] < 0.006 and stats["median_m"] <= stats["max_m"] < 0.02
    # A plain least-squares fit is pulled away by the same outliers.
    assert residuals(umeyama(source, target), source, target, expected)["rms_m"] > 0.05
    again, again_inliers = robust_similarity(source, target, threshold_m=0.02, seed=0)
    np.testing.assert_array_equal(again.matrix, found.matrix)
    np.testing.assert_array_equal(again_inliers, inliers)


@pytest.mark.parametrize("points, message", [
    (np.zeros((0, 3)), "at least 3 point pairs, got 0"),
    (np.array([[0.0, 0, 0], [1, 1, 1]]), "at least 3 point pairs, got 2"),
    (np.outer(np.arange(6.0), [1.0, 2.0, 0.5]), "collinear"),
    (np.ones((5, 3)), "collinear"),
])
def test_degenerate_input_is_refused_clearly(points, message):
    for fit in (lambda s, t: umeyama(s, t),
                lambda s, t: robust_similarity(s, t, threshold_m=0.01)):
        with pytest.raises(InputError, match=message) as caught:
            fit(points, points + 1.0)
        assert caught.value.source == "alignment"


def test_mismatched_or_bad_values_are_refused():
    with pytest.raises(InputError, match="equal length"):
        umeyama(np.zeros((4, 3)), np.zeros((5, 3)))
    bad = np.random.default_rng(0).normal(size=(5, 3))
    bad[2, 1] = np.nan
    with pytest.raises(InputError, match="NaN"):
        umeyama(bad, bad)
    with pytest.raises(InputError, match="no similarity brings 3"):
        rng = np.random.default_rng(1)
        robust_similarity(rng.normal(size=(20, 3)), rng.normal(size=(20, 3)) * 10,
                          threshold_m=1e-6)


@pytest.mark.parametrize("ring", [True, False], ids=["ring", "arc"])
def test_a_posed_less_model_is_levelled_by_its_cameras(ring):
    """Cameras round a plant in a model frame turned and shifted at random: levelling gives
    back z up, from the ring's plane (cameras tilted down at the plant), or from the
    cameras' image-up on a short arc at two heights (cameras held level)."""
    rng = np.random.default_rng(3)
    angles = np.linspace(0, 2 * np.pi if ring else 0.6, 24, endpoint=False)
    centres = np.c_[0.3 * np.cos(angles), 0.3 * np.sin(angles), 0.1 + 0.02 * np.sin(3 * angles)]
    if not ring:  # cameras at two heights on the arc: no plane of their own is level
        centres[::2, 2] += 0.15
    # Ring: cameras looking at the plant's centre, tilted down; arc: held level.
    forward = -centres if ring else -centres * [1, 1, 0]
    forward = forward / np.linalg.norm(forward, axis=1, keepdims=True)
    right = np.cross(forward, [0, 0, 1.0])
    right /= np.linalg.norm(right, axis=1, keepdims=True)
    image_up = np.cross(right, forward)
    turn = Rotation.random(random_state=rng).as_matrix()
    model = Similarity(2.5, turn, np.array([4.0, -1.0, 7.0]))
    similarity, how = level_similarity(model.apply(centres), image_up @ turn.T)
    assert ("plane" in how) == ring
    up = similarity.rotation @ turn @ np.array([0, 0, 1.0])
    assert np.degrees(np.arccos(np.clip(up[2], -1, 1))) < 0.5
    assert similarity.scale == 1.0
    assert np.allclose(similarity.apply(model.apply(centres)).mean(axis=0), 0, atol=1e-9)


def test_rotation_onto_takes_one_direction_onto_another():
    rng = np.random.default_rng(0)
    for a in [*rng.normal(size=(5, 3)), np.array([0, 0, -1.0])]:
        a = a / np.linalg.norm(a)
        rotation = rotation_onto(a, np.array([0, 0, 1.0]))
        assert np.allclose(rotation @ a, [0, 0, 1]) and np.isclose(np.linalg.det(rotation), 1)
        assert np.allclose(rotation.T @ rotation, np.eye(3))


def test_a_ground_plane_is_up_where_the_cameras_agree():
    """A table's plane under the plant gives up, turned to the cameras' side; a plane the
    cameras' own up contradicts (a wall behind the plant) is not taken for the ground."""
    angles = np.linspace(0, 1.0, 12)  # a short arc at two heights: no level ring
    centres = np.c_[0.3 * np.cos(angles), 0.3 * np.sin(angles), 0.2 + 0.1 * (np.arange(12) % 2)]
    tilt = Rotation.from_euler("x", 8, degrees=True).as_matrix()
    image_up = np.tile(tilt @ [0, 0, 1.0], (12, 1))  # held a little off upright
    similarity, how = level_similarity(centres, image_up, ground=np.array([0, 0, -1.0]))
    assert how == "the ground's plane"
    assert np.allclose(similarity.rotation @ [0, 0, 1.0], [0, 0, 1.0])
    _, how = level_similarity(centres, image_up, ground=np.array([1.0, 0, 0]))
    assert how == "the cameras' mean image-up direction"
