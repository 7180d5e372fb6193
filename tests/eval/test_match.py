import numpy as np
import pytest

from flowerpose.eval.scoring.match import angle_error_deg, match_flowers, score_plant
from flowerpose.eval.scoring.truth import TruthFlower
from flowerpose.pipeline.pose import FlowerPose

UP = np.array([0.0, 0.0, 1.0])


def on_x(*xs_cm):
    """Centres along x at the given positions (centimetres), in metres."""
    return np.array([[x / 100.0, 0.0, 0.3] for x in xs_cm])


def test_one_truth_takes_one_of_two_nearby_estimates():
    assert match_flowers(on_x(0.3, -0.5), on_x(0.0)) == [(0, 0)]


def test_pairs_beyond_two_centimetres_never_match():
    assert match_flowers(on_x(2.01), on_x(0.0)) == []
    assert match_flowers(on_x(1.99), on_x(0.0)) == [(0, 0)]
    assert match_flowers(on_x(1.0), on_x(0.0), max_distance=0.005) == []


def test_hungarian_keeps_the_match_that_greedy_loses():
    # Greedy takes the closest pair (estimate 0, truth 0) and strands both others;
    # the assignment matches estimate 0 to truth 1 and estimate 1 to truth 0.
    estimates, truth = on_x(0.5, -1.0), on_x(0.0, 2.0)
    assert match_flowers(estimates, truth) == [(0, 1), (1, 0)]


def test_the_matching_minimises_total_distance():
    assert match_flowers(on_x(0.0, 1.0), on_x(1.2, 0.1)) == [(0, 1), (1, 0)]


def test_empty_sides_match_nothing():
    assert match_flowers(np.zeros((0, 3)), on_x(0.0)) == []
    assert match_flowers(on_x(0.0), np.zeros((0, 3))) == []
    assert match_flowers([], []) == []


def test_angle_error():
    assert angle_error_deg(UP, UP) == 0.0
    assert angle_error_deg(UP, -UP) == pytest.approx(180.0)
    assert angle_error_deg(np.array([1.0, 0.0, 0.0]), UP) == pytest.approx(90.0)
    tilted = np.array([np.sin(np.radians(10)), 0.0, np.cos(np.radians(10))])
    assert angle_error_deg(2.0 * tilted, UP) == pytest.approx(10.0)


def test_score_counts_found_extra_and_false_positives():
    truth = [TruthFlower(0, on_x(0.0)[0], UP),
             TruthFlower(1, on_x(10.0)[0], UP, visible=False),
             TruthFlower(2, on_x(20.0)[0], UP),
             TruthFlower(3, on_x(30.0)[0], UP, visible=False)]
    tilted = np.array([np.sin(np.radians(5)), 0.0, np.cos(np.radians(5))])
    estimates = [
        FlowerPose(on_x(0.4)[0], {"plane": tilted, "superellipsoid": None, "paraboloid": -UP},
                   True, 400, 300),
        {"center": list(on_x(10.2)[0]), "normals": {"plane": [0.0, 0.0, 1.0],
                                                     "superellipsoid": None, "paraboloid": None}},
        {"center": list(on_x(19.0)[0]), "normals": {"plane": [0.0, 0.0, 1.0],
                                                     "superellipsoid": [0.0, 0.0, 1.0],
                                                     "paraboloid": None}},
        {"center": list(on_x(0.9)[0]), "normals": {"plane": None, "superellipsoid": None,
                                                    "paraboloid": None}},
        {"center": list(on_x(50.0)[0]), "normals": {"plane": None, "superellipsoid": None,
                                                     "paraboloid": None}},
    ]
    score = score_plant(estimates, truth)
    assert (score.gt, score.visible, score.detections) == (4, 2, 5)
    assert (score.found, score.found_visible, score.extra, score.fp) == (3, 2, 1, 2)
    assert score.pairs == [(0, 0), (1, 1), (2, 2)]
    assert score.error_deg["plane"] == pytest.approx([5.0, 0.0])
    assert score.error_deg["superellipsoid"] == pytest.approx([0.0])
    assert score.error_deg["paraboloid"] == pytest.approx([180.0])
    assert score.failed == {"plane": 0, "superellipsoid": 1, "paraboloid": 1}


def test_score_of_nothing():
    score = score_plant([], [])
    assert (score.gt, score.found, score.fp, score.pairs) == (0, 0, 0, [])
    assert score.error_deg == {"plane": [], "superellipsoid": [], "paraboloid": []}


def test_a_report_says_what_made_it():
    from flowerpose import __version__
    from flowerpose.eval.reports.report import build_report

    report = build_report({}, [], {"total": 0.0})
    assert report["run"]["flowerpose"] == __version__
    assert report["run"]["date"].endswith("+00:00") and report["run"]["command"].startswith(
        "flowerpose")
    # Run from this checkout: its commit (40 hex digits, "+dirty" with local changes).
    commit = report["run"]["commit"]
    assert commit is None or len(commit.removesuffix("+dirty")) == 40


def test_scoring_against_another_plants_truth_at_the_same_place_warns(tmp_path, caplog):
    import json

    from flowerpose.eval.reports.score_report import score_files

    rng = np.random.default_rng(3)
    truth = rng.uniform(-0.1, 0.1, (18, 3)) + [0, 0, 0.3]
    elsewhere = truth + rng.choice([-1, 1], (18, 3)) * 0.03  # another plant's flowers
    normal = [0.0, 0.0, 1.0]
    (tmp_path / "plant.json").write_text(json.dumps({"flowers": [
        {"id": k, "center": c.tolist(), "normal": normal, "visible": True}
        for k, c in enumerate(truth)]}))
    (tmp_path / "flowers.json").write_text(json.dumps({"units": "m", "flowers": [
        {"id": k, "center": c.tolist(), "normals": {"plane": normal}}
        for k, c in enumerate(elsewhere)]}))
    report = score_files(tmp_path / "flowers.json", tmp_path / "plant.json")
    notes = report["plants"][0]["notes"]
    assert any("is this the right plant's truth" in note for note in notes)
    assert "is this the right plant's truth" in caplog.text
    # The same plant: no word.
    (tmp_path / "flowers.json").write_text(json.dumps({"units": "m", "flowers": [
        {"id": k, "center": c.tolist(), "normals": {"plane": normal}}
        for k, c in enumerate(truth)]}))
    assert not any("right plant" in n for n in score_files(
        tmp_path / "flowers.json", tmp_path / "plant.json")["plants"][0]["notes"])
