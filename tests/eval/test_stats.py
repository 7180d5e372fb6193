"""The numbers' uncertainty: seeded bootstrap intervals, Wilson intervals, accuracy curves and
paired comparisons that say "no difference shown" for a method against itself and find a
worse one worse."""

import numpy as np
import pytest

from flowerpose.eval import stats
from flowerpose.eval.paired import compare_runs
from flowerpose.eval.report import summarise


def _errors(seed: int, count: int) -> list[float]:
    return list(np.random.default_rng(seed).gamma(2.0, 3.0, count))


def test_a_bootstrap_interval_is_seeded_reproducible_and_holds_its_estimate():
    one = [_errors(1, 11)]
    first, again = stats.bootstrap_interval(one), stats.bootstrap_interval(one)
    assert first == again
    assert first["low"] < np.mean(one[0]) < first["high"]
    several = [_errors(k, 12) for k in range(6)]
    for statistic, value in (("mean", np.mean), ("median", np.median),
                             ("p90", lambda v: np.percentile(v, 90))):
        interval = stats.bootstrap_interval(several, statistic)
        assert interval == stats.bootstrap_interval(several, statistic)
        assert interval["low"] <= value(np.concatenate(several)) <= interval["high"]
    # Another seed draws other resamples: close bounds, not the same ones.
    assert stats.bootstrap_interval(several, seed=1) != stats.bootstrap_interval(several)


def test_plants_that_differ_widen_the_interval_over_plants_then_flowers():
    alike = [list(np.full(10, 5.0) + np.arange(10) * 0.1) for _ in range(4)]
    apart = [list(np.full(10, base) + np.arange(10) * 0.1) for base in (1.0, 3.0, 7.0, 9.0)]
    width = lambda i: i["high"] - i["low"]  # noqa: E731
    assert width(stats.bootstrap_interval(apart)) > 5 * width(stats.bootstrap_interval(alike))


def test_no_interval_without_two_values():
    assert stats.bootstrap_interval([[3.0]]) == stats.NO_INTERVAL
    assert stats.bootstrap_interval([[], []]) == stats.NO_INTERVAL
    assert stats.wilson(0, 0) == stats.NO_INTERVAL


def test_the_wilson_interval_matches_its_formula_and_holds_at_the_ends():
    z = 1.959964
    for found, trials in ((11, 11), (0, 9), (46, 48), (3, 7)):
        p = found / trials
        centre = (p + z * z / (2 * trials)) / (1 + z * z / trials)
        half = z / (1 + z * z / trials) * np.sqrt(p * (1 - p) / trials
                                                  + z * z / (4 * trials * trials))
        interval = stats.wilson(found, trials)
        assert interval["low"] == pytest.approx(max(0.0, centre - half), abs=1e-4)
        assert interval["high"] == pytest.approx(min(1.0, centre + half), abs=1e-4)


def test_the_accuracy_curve_counts_a_missed_flower_as_a_failure_at_every_angle():
    # Two plants: four visible flowers, two found (3 and 12 degrees off); one of 2 found.
    curve = stats.accuracy_curve([[3.0, 12.0], [50.0]], [4, 2])
    assert curve["n"] == 6
    share = dict(zip(curve["thresholds_deg"], curve["share"], strict=True))
    assert share[5] == pytest.approx(1 / 6, abs=1e-4)
    assert share[15] == pytest.approx(2 / 6, abs=1e-4)
    assert share[45] == pytest.approx(2 / 6, abs=1e-4)  # 50 degrees is past every threshold
    assert curve["auc"] == pytest.approx(((1 - 3 / 45) + (1 - 12 / 45)) / 6, abs=1e-4)
    assert curve["auc_ci95"]["low"] <= curve["auc"] <= curve["auc_ci95"]["high"]


def test_error_summary_counts_gross_errors_and_flips():
    summary = stats.error_summary([[2.0, 4.0, 25.0], [170.0, 6.0]])
    assert (summary["n"], summary["over_20"], summary["over_90"]) == (5, 0.4, 0.2)
    assert summary["p90"] == pytest.approx(np.percentile([2, 4, 25, 170, 6], 90))
    assert summary["over_90_ci95"] == stats.wilson(1, 5)


def _plants(errors_by_plant: dict[str, list[float | None]], fp: int = 0) -> list[dict]:
    """report.json plant entries with one visible flower a value; None: missed."""
    plants = []
    for name, errors in errors_by_plant.items():
        matches = [{"detection": k, "truth": k, "distance_m": 0.001,
                    "error_deg": dict.fromkeys(("plane", "superellipsoid", "paraboloid"), e)}
                   for k, e in enumerate(errors) if e is not None]
        found = [e for e in errors if e is not None]
        plants.append({"plant": name, "gt": len(errors), "visible": len(errors),
                       "detections": len(found) + fp, "found": len(found),
                       "found_visible": len(found), "extra": 0, "fp": fp,
                       "error_deg": {m: found for m in ("plane", "superellipsoid", "paraboloid")},
                       "failed": dict.fromkeys(("plane", "superellipsoid", "paraboloid"), 0),
                       "matches": matches})
    return plants


def test_a_method_compared_with_itself_shows_no_difference():
    runs = _plants({"a": _errors(2, 9), "b": _errors(3, 8)}, fp=1)
    paired = compare_runs(runs, runs)
    for fit in ("plane", "superellipsoid", "paraboloid"):
        result = paired["fits"][fit]
        assert (result["n"], result["mean_difference"], result["shown"]) == (17, 0.0, False)
        assert (result["wins"], result["ties"], result["losses"]) == (0, 17, 0)
        assert result["p_wilcoxon"] == 1.0
    assert paired["found"]["p"] == 1.0 and not paired["fp"]["shown"]
    assert paired["verdicts"][0] == "plane: no difference shown on 17 flowers"


def test_a_known_worse_method_is_shown_worse_and_a_lost_flower_counted():
    ours = {"a": _errors(4, 12), "b": _errors(5, 12)}
    worse = {name: [e + 4.0 + 2.0 * np.sin(k) for k, e in enumerate(errors)]
             for name, errors in ours.items()}
    worse["a"][0] = None  # the worse method misses a flower too
    paired = compare_runs(_plants(worse, fp=3), _plants(ours))
    plane = paired["fits"]["plane"]
    assert plane["shown"] and plane["direction"] == "worse" and plane["n"] == 23
    assert plane["ci95"]["low"] > 0 and plane["p_wilcoxon"] < 0.001
    assert plane["losses"] == 23
    assert (paired["found"]["only_ours"], paired["found"]["only_theirs"]) == (0, 1)
    assert not paired["found"]["shown"]  # one flower is no evidence
    assert paired["fp"]["shown"] and paired["fp"]["ours"] == 6
    assert paired["verdicts"][0].startswith("plane: worse, +")


def test_the_summary_carries_counts_and_intervals_for_every_number():
    summary = summarise(_plants({"a": [3.0, None, 5.0], "b": [8.0, 2.0]}, fp=1))
    assert summary["recall_visible_ci95"] == stats.wilson(4, 5)
    assert summary["precision_ci95"] == stats.wilson(4, 6)
    plane = summary["error_deg"]["plane"]
    assert plane["n"] == 4 and plane["mean_ci95"]["low"] <= plane["mean"]
    assert summary["accuracy"]["plane"]["n"] == 5
    quick = summarise(_plants({"a": [3.0, None, 5.0]}), intervals=False)
    assert quick["error_deg"]["plane"]["mean_ci95"] == stats.NO_INTERVAL
