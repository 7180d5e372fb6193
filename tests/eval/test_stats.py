"""The numbers' uncertainty: seeded intervals whose coverage is measured, Wilson intervals,
accuracy curves, paired comparisons that say "identical" for a method against itself, find
a worse one worse and say "too few flowers to tell" on too few; repeats counted as the
flowers they repeat."""

import numpy as np
import pytest

from flowerpose.eval.reports.report import summarise
from flowerpose.eval.scoring import stats
from flowerpose.eval.scoring.paired import compare_runs


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
    assert paired["verdicts"][0] == "plane: identical on 17 flowers"


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


#: Angle errors shaped like the real plants': gamma distributions with the measured mean
#: and standard deviation of the plane error on the authors' plant 3 (11 flowers, 7.49 and
#: 3.55 degrees) and on the field preset's 10 plants (123 flowers, 8.58 and 4.81;
#: `flowerpose eval --source oracle --preset field --plants 10 --seed 100`).
REAL_SHAPES = {"plant 3": (7.49, 3.55), "field": (8.58, 4.81)}


@pytest.mark.slow
@pytest.mark.parametrize("shape", sorted(REAL_SHAPES))
def test_the_mean_interval_covers_the_true_mean_95_percent_of_the_time(shape):
    mean, sd = REAL_SHAPES[shape]
    k, theta = (mean / sd) ** 2, sd * sd / mean
    rng = np.random.default_rng(20261206)
    trials = 1500
    for n in (7, 11, 40):
        covered = 0
        for trial in range(trials):
            interval = stats.studentized([rng.gamma(k, theta, n)], seed=trial).interval()
            covered += interval["low"] <= mean <= interval["high"]
        assert 0.94 <= covered / trials <= 0.96, (shape, n, covered / trials)
    # The same test tells the methods apart: the percentile bootstrap, which the reports
    # used before, covers 7 flowers' mean far less often.
    samples = rng.gamma(k, theta, (trials, 7))
    resampled = np.take_along_axis(samples[:, None, :], rng.integers(0, 7, (trials, 2000, 7)),
                                   axis=2).mean(axis=2)
    low, high = np.percentile(resampled, [2.5, 97.5], axis=1)
    assert ((low <= mean) & (mean <= high)).mean() < 0.92


def test_a_comparison_on_two_flowers_is_too_few_to_tell():
    ours = {("p", "0"): 5.0, ("p", "1"): 6.0}
    theirs = {("p", "0"): 3.0, ("p", "1"): 4.0}
    paired = stats.paired_errors(ours, theirs)
    assert paired["verdict"] == stats.TOO_FEW and not paired["shown"]
    assert stats.difference_verdict(paired) == "plane: too few flowers to tell (2)"
    assert stats.mcnemar({1}, {1, 2}, flowers=2)["too_few"]


def test_a_uniform_small_shift_is_within_the_margin_and_its_p_value_never_prints_zero():
    theirs = {("p", str(k)): float(k % 7) for k in range(40)}
    ours = {key: value + 0.05 for key, value in theirs.items()}
    paired = stats.paired_errors(ours, theirs)
    assert paired["verdict"] == "within the margin" and not paired["shown"]
    assert (paired["wins"], paired["ties"], paired["losses"]) == (0, 40, 0)
    assert paired["p_wilcoxon"] < 1e-4 and stats.p_text(paired["p_wilcoxon"]) == "< 0.0001"
    assert stats.difference_verdict(paired).startswith("plane: within the margin (±0.5°)")
    # Worse by more than the margin on 40 flowers is shown worse.
    worse = {key: value + 2.0 + 0.1 * (hash(key) % 3) for key, value in theirs.items()}
    assert stats.paired_errors(worse, theirs)["verdict"] == "worse"


def test_p_values_print_as_values_or_below_the_floor():
    assert [stats.p_text(p) for p in (0.5, 0.0312, 0.0012, 3e-5, 0.0, None)] == [
        "0.5", "0.031", "0.0012", "< 0.0001", "< 0.0001", "-"]


def test_holm_adjusts_in_order_and_keeps_the_adjusted_values_monotone():
    adjusted = stats.holm({"a": 0.01, "b": 0.04, "c": 0.03, "d": 0.5})
    assert adjusted == pytest.approx({"a": 0.04, "c": 0.09, "b": 0.09, "d": 0.5})
    assert stats.holm({}) == {}


def test_the_one_sided_bound_and_its_p_value_agree():
    boot = stats.studentized([_errors(4, 12), _errors(5, 12), _errors(6, 12)])
    upper = boot.upper()
    assert boot.interval()["low"] < boot.mean < upper < boot.interval()["high"]
    assert boot.p_below(upper + 0.01) < 0.05 < boot.p_below(upper - 0.01)
    flat = stats.studentized([[0.2] * 30])
    assert flat.upper() == 0.2 and flat.p_below(0.5) == 0.0 and flat.p_below(0.1) == 1.0


def _repeated(errors: list[float], repeats: int) -> list[dict]:
    """A plant's flowers seen in `repeats` perturbed repeats, the errors unchanged."""
    entries = []
    for r in range(repeats):
        matches = [{"detection": k, "truth": k, "distance_m": 0.001,
                    "error_deg": dict.fromkeys(("plane", "superellipsoid", "paraboloid"), e)}
                   for k, e in enumerate(errors)]
        entries.append({"plant": "p" if r == 0 else f"p r{r}", "repeat_of": "p",
                        "gt": len(errors), "visible": len(errors), "detections": len(errors),
                        "found": len(errors), "found_visible": len(errors) - 1, "extra": 0,
                        "fp": 0, "error_deg": dict.fromkeys(("plane", "superellipsoid",
                                                             "paraboloid"), errors),
                        "failed": dict.fromkeys(("plane", "superellipsoid", "paraboloid"), 0),
                        "matches": matches})
    return entries


def test_repeats_of_the_same_flowers_do_not_narrow_an_interval():
    errors = _errors(8, 11)
    once, five = summarise(_repeated(errors, 1)), summarise(_repeated(errors, 5))
    width = lambda i: i["high"] - i["low"]  # noqa: E731
    for key in ("mean_ci95", "p90_ci95", "over_20_ci95"):
        assert width(five["error_deg"]["plane"][key]) >= 0.95 * width(
            once["error_deg"]["plane"][key]), key
    assert five["recall_visible_ci95"] == once["recall_visible_ci95"]
    # Counted as 55 independent flowers, the interval would be a third as wide.
    pooled = stats.bootstrap_interval([[e] for e in errors * 5])
    assert width(pooled) < 0.6 * width(five["error_deg"]["plane"]["mean_ci95"])


def test_mcnemar_counts_a_flower_once_across_its_repeats():
    ours, theirs = _repeated([3.0] * 12, 5), _repeated([3.0] * 12, 5)
    for entry in ours[:3]:  # flower 0 lost in 3 of 5 repeats: lost once
        entry["matches"] = entry["matches"][1:]
    found = compare_runs(ours, theirs)["found"]
    assert (found["only_ours"], found["only_theirs"], found["flowers"]) == (0, 1, 12)
    # Lost in 2 of 5 repeats: still found in most, so not lost.
    fewer = _repeated([3.0] * 12, 5)
    for entry in fewer[:2]:
        entry["matches"] = entry["matches"][1:]
    assert compare_runs(fewer, theirs)["found"]["only_theirs"] == 0


def test_pollinated_flowers_compared_in_words_say_too_few_under_ten():
    from flowerpose.eval.scoring.paired import pollinated_verdict

    flowers = {(0, k) for k in range(40)}
    ours = {(0, k) for k in range(30)}
    theirs = {(0, k) for k in range(18)}
    assert pollinated_verdict(stats.mcnemar(ours, theirs, len(flowers))).endswith(
        ", pollinates more")
    assert pollinated_verdict(stats.mcnemar(theirs, ours, len(flowers))).endswith(
        ", pollinates fewer")
    assert pollinated_verdict(stats.mcnemar(ours, ours, len(flowers))).endswith(
        "no difference shown")
    few = pollinated_verdict(stats.mcnemar({(0, 1)}, set(), 5))
    assert "too few" in few and few.startswith("pollinated: 1 only by this run, 0 only by")
