"""How far a number can be trusted: every interval, accuracy curve and paired comparison the
reports print.

Angle errors are degrees, one value a scored flower; a run's flowers come in groups, one a
plant (a stress row's: one a plant and repeat). Intervals are 95 % and seeded, so a report
made twice prints the same bounds:

- a statistic of angle errors (mean, median, 90th percentile): a percentile bootstrap over
  the flowers (`scipy.stats.bootstrap`) for one plant; for several, a two-stage bootstrap,
  plants drawn with replacement and then each drawn plant's flowers, because flowers of
  one plant share its scan and are not independent (scipy has no hierarchical bootstrap);
- a share (recall, precision, errors over 20 degrees): the Wilson score interval
  (`scipy.stats.binomtest`), which holds at 0 and 1 where the normal approximation fails;
- a paired comparison of two settings on the flowers both scored: the bootstrap of the
  per-flower differences (as above), their wins, ties and losses, and the Wilcoxon
  signed-rank test; found flowers by McNemar's exact test on the flowers one setting found
  and the other missed, false positives by the exact conditional test of two counts.

A difference is "shown" when its interval leaves out zero; otherwise the comparison says
"no difference shown" and on how many flowers.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from scipy import stats

#: Confidence of every interval.
CONFIDENCE = 0.95
#: Bootstrap resamples (the bounds move by well under 0.1 degrees between seeds at this
#: many on a real plant's 11 flowers).
RESAMPLES = 4000
#: Seed of every bootstrap, so a report made twice prints the same bounds.
SEED = 20261205
#: The accuracy curve's thresholds, degrees: the share of flowers within each.
ACCURACY_THRESHOLDS_DEG = tuple(range(5, 50, 5))
#: The accuracy curve's area runs from 0 to this many degrees (normalised to 0-1).
ACCURACY_LIMIT_DEG = 45.0
#: A normal this far off is a gross error; past FLIP_DEG it points the wrong way.
GROSS_DEG = 20.0
FLIP_DEG = 90.0
#: Paired differences within this many degrees count as ties in wins/ties/losses (well
#: under a hand label's own error of about 5 degrees).
TIE_DEG = 0.5

#: An interval that cannot be had (fewer than two values, no trials).
NO_INTERVAL: dict[str, float | None] = {"low": None, "high": None}

Groups = Sequence[Sequence[float]]


def _rounded(low: float, high: float, digits: int = 4) -> dict[str, float]:
    return {"low": round(float(low), digits), "high": round(float(high), digits)}


def wilson(successes: int, trials: int) -> dict[str, float | None]:
    """The Wilson score interval of a share `successes` of `trials` ({"low", "high"},
    None without trials)."""
    if trials <= 0:
        return dict(NO_INTERVAL)
    interval = stats.binomtest(int(successes), int(trials)).proportion_ci(
        confidence_level=CONFIDENCE, method="wilson")
    return _rounded(interval.low, interval.high)


#: The quantile of each statistic a bootstrap bounds (the mean is not one).
_QUANTILES = {"median": 0.5, "p90": 0.9}


def _statistic(name: str):
    """`name`'s statistic along an axis, as scipy's bootstrap calls it."""
    if name == "mean":
        return np.mean
    if name in _QUANTILES:
        return lambda values, axis=-1: np.quantile(values, _QUANTILES[name], axis=axis)
    raise ValueError(name)


def _padded_statistic(name: str, values: np.ndarray) -> np.ndarray:
    """`name`'s statistic of each row of `values`, padded with nan past its own count
    (linear interpolation between order statistics, as numpy's quantile)."""
    present = ~np.isnan(values)
    counts = present.sum(axis=1)
    if name == "mean":
        return np.where(present, values, 0.0).sum(axis=1) / counts
    ordered = np.sort(values, axis=1)  # nan sorts last
    position = _QUANTILES[name] * (counts - 1)
    below = np.floor(position).astype(int)
    above = np.minimum(below + 1, counts - 1)
    low = np.take_along_axis(ordered, below[:, None], axis=1)[:, 0]
    high = np.take_along_axis(ordered, above[:, None], axis=1)[:, 0]
    return low + (high - low) * (position - below)


def bootstrap_interval(groups: Groups, statistic: str = "mean",
                       seed: int = SEED) -> dict[str, float | None]:
    """The 95 % interval of `statistic` ("mean", "median", "p90") of the values of all
    `groups` together: over the values for one group, over groups then values for several
    (module docstring). Groups without values are left out; None bounds with fewer than two
    values."""
    return bootstrap_intervals(groups, (statistic,), seed)[statistic]


def bootstrap_intervals(groups: Groups, statistics: tuple[str, ...],
                        seed: int = SEED) -> dict[str, dict[str, float | None]]:
    """`bootstrap_interval` of several statistics at once, all from the same resamples."""
    kept = [np.asarray(g, float) for g in groups if len(g)]
    if sum(len(g) for g in kept) < 2:
        return {name: dict(NO_INTERVAL) for name in statistics}
    rng = np.random.default_rng(seed)
    if len(kept) > 1:
        bounds = _two_stage(kept, statistics, rng)
    else:
        functions = [_statistic(name) for name in statistics]

        def statistic(values: np.ndarray, axis: int = -1) -> np.ndarray:
            return np.stack([f(values, axis=axis) for f in functions])

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # a degenerate sample has a point interval
            result = stats.bootstrap((kept[0],), statistic, n_resamples=RESAMPLES,
                                     confidence_level=CONFIDENCE, method="percentile",
                                     vectorized=True, rng=rng)
        bounds = list(zip(result.confidence_interval.low, result.confidence_interval.high,
                          strict=True))
    return {name: _rounded(*b) for name, b in zip(statistics, bounds, strict=True)}


def _two_stage(groups: list[np.ndarray], statistics: tuple[str, ...],
               rng: np.random.Generator) -> list[tuple[float, float]]:
    """Percentile intervals of `statistics` over one two-stage bootstrap: groups drawn
    with replacement, then each drawn group's values, all resamples at once."""
    sizes = np.array([len(g) for g in groups])
    padded = np.full((len(groups), sizes.max()), np.nan)
    for k, values in enumerate(groups):
        padded[k, :len(values)] = values
    drawn = rng.integers(0, len(groups), size=(RESAMPLES, len(groups)))
    counts = sizes[drawn]
    picks = (rng.random((*drawn.shape, sizes.max())) * counts[..., None]).astype(int)
    values = padded[drawn[..., None], picks]
    values[np.arange(sizes.max()) >= counts[..., None]] = np.nan
    values = values.reshape(RESAMPLES, -1)
    tail = 100 * (1 - CONFIDENCE) / 2
    bounds = []
    for name in statistics:
        estimates = _padded_statistic(name, values)
        bounds.append((float(np.percentile(estimates, tail)),
                       float(np.percentile(estimates, 100 - tail))))
    return bounds


def error_summary(groups: Groups, intervals: bool = True) -> dict[str, Any]:
    """The statistics of one fit's angle errors (degrees), one group a plant: count, mean,
    median and population std, the 90th percentile, the shares over GROSS_DEG and
    FLIP_DEG, each with its 95 % interval (None where there are no errors, or, for speed,
    without `intervals`)."""
    values = np.asarray([e for g in groups for e in g], float)
    if len(values) == 0:
        return {"mean": None, "median": None, "std": None, "n": 0,
                "mean_ci95": dict(NO_INTERVAL), "median_ci95": dict(NO_INTERVAL),
                "p90": None, "p90_ci95": dict(NO_INTERVAL),
                "over_20": None, "over_20_ci95": dict(NO_INTERVAL),
                "over_90": None, "over_90_ci95": dict(NO_INTERVAL)}
    over = {threshold: int((values > threshold).sum()) for threshold in (GROSS_DEG, FLIP_DEG)}

    found = (bootstrap_intervals(groups, ("mean", "median", "p90")) if intervals
             else {name: dict(NO_INTERVAL) for name in ("mean", "median", "p90")})

    def interval(statistic: str) -> dict[str, float | None]:
        return found[statistic]

    def share_interval(count: int) -> dict[str, float | None]:
        return wilson(count, len(values)) if intervals else dict(NO_INTERVAL)

    return {"mean": round(float(values.mean()), 4),
            "median": round(float(np.median(values)), 4),
            "std": round(float(values.std()), 4), "n": int(len(values)),
            "mean_ci95": interval("mean"), "median_ci95": interval("median"),
            "p90": round(float(np.percentile(values, 90)), 4), "p90_ci95": interval("p90"),
            "over_20": round(over[GROSS_DEG] / len(values), 4),
            "over_20_ci95": share_interval(over[GROSS_DEG]),
            "over_90": round(over[FLIP_DEG] / len(values), 4),
            "over_90_ci95": share_interval(over[FLIP_DEG])}


def accuracy_scores(errors: Sequence[float], flowers: int) -> np.ndarray:
    """Each of `flowers` flowers' share of the accuracy curve's area: 1 - error /
    ACCURACY_LIMIT_DEG, 0 beyond it; a flower without an error (missed, or its fit failed)
    scores 0. Their mean is the curve's normalised area."""
    scores = np.zeros(max(flowers, len(errors)))
    scores[:len(errors)] = np.clip(1 - np.asarray(errors, float) / ACCURACY_LIMIT_DEG, 0, 1)
    return scores


def accuracy_curve(groups: Groups, flowers: Sequence[int],
                   intervals: bool = True) -> dict[str, Any]:
    """The accuracy curve of one fit, as pose benchmarks report it: of the flowers that
    count (`flowers[k]` in group k: the visible ones), the share whose error is within each
    of ACCURACY_THRESHOLDS_DEG, a missed flower or a failed fit counting as a failure at
    every threshold; and its area from 0 to ACCURACY_LIMIT_DEG normalised to 0-1 (`auc`),
    with its interval (without `intervals`, for speed, none). None where no flower
    counts."""
    total = int(sum(flowers))
    if total == 0:
        return {"thresholds_deg": list(ACCURACY_THRESHOLDS_DEG), "share": None, "n": 0,
                "auc": None, "auc_ci95": dict(NO_INTERVAL)}
    values = np.asarray([e for g in groups for e in g], float)
    share = [round(float((values <= t).sum()) / total, 4) for t in ACCURACY_THRESHOLDS_DEG]
    scores = [accuracy_scores(g, n) for g, n in zip(groups, flowers, strict=True)]
    return {"thresholds_deg": list(ACCURACY_THRESHOLDS_DEG), "share": share, "n": total,
            "auc": round(float(np.concatenate(scores).mean()), 4),
            "auc_ci95": (bootstrap_interval(scores, "mean") if intervals
                         else dict(NO_INTERVAL))}


def paired_errors(ours: Mapping[tuple, float], theirs: Mapping[tuple, float]
                  ) -> dict[str, Any]:
    """Two settings' angle errors on the flowers both scored (keys: (plant, flower)): the
    mean difference ours - theirs (degrees; positive: ours is worse) with its interval
    (over plants then flowers), wins/ties/losses (ties within TIE_DEG), the Wilcoxon
    signed-rank p-value (1.0 when every difference is 0), and whether a difference is
    shown (its interval leaves out 0) and which way."""
    common = sorted(set(ours) & set(theirs), key=str)
    differences = np.array([ours[k] - theirs[k] for k in common], float)
    by_plant: dict[Any, list[float]] = {}
    for key, difference in zip(common, differences, strict=True):
        by_plant.setdefault(key[0], []).append(float(difference))
    if len(differences) == 0:
        return {"n": 0, "mean_difference": None, "ci95": dict(NO_INTERVAL), "wins": 0,
                "ties": 0, "losses": 0, "p_wilcoxon": None, "shown": False,
                "direction": "none"}
    interval = bootstrap_interval(list(by_plant.values()), "mean")
    low, high = interval["low"], interval["high"]
    shown = low is not None and (low > 0 or high < 0)
    return {"n": int(len(differences)), "mean_difference": round(float(differences.mean()), 4),
            "ci95": interval, "wins": int((differences < -TIE_DEG).sum()),
            "ties": int((np.abs(differences) <= TIE_DEG).sum()),
            "losses": int((differences > TIE_DEG).sum()),
            "p_wilcoxon": wilcoxon_p(differences), "shown": bool(shown),
            "direction": ("worse" if low > 0 else "better") if shown else "none"}


def wilcoxon_p(differences: np.ndarray) -> float | None:
    """Two-sided Wilcoxon signed-rank p-value of paired differences (zeros dropped); 1.0
    when every difference is zero, None for none."""
    nonzero = differences[differences != 0]
    if len(differences) == 0:
        return None
    if len(nonzero) == 0:
        return 1.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return round(float(stats.wilcoxon(nonzero).pvalue), 4)


def mcnemar(ours: set, theirs: set) -> dict[str, Any]:
    """McNemar's exact test on the flowers one setting found and the other did not (the
    sets hold flower keys): how many only ours found, only theirs, and the two-sided
    p-value (the binomial test of one against their sum)."""
    only_ours, only_theirs = len(ours - theirs), len(theirs - ours)
    discordant = only_ours + only_theirs
    p = 1.0 if discordant == 0 else round(float(
        stats.binomtest(only_ours, discordant).pvalue), 4)
    return {"both": len(ours & theirs), "only_ours": only_ours, "only_theirs": only_theirs,
            "p": p, "shown": p < 1 - CONFIDENCE}


def count_test(ours: int, theirs: int) -> dict[str, Any]:
    """Two counts of events on the same data (false positives): the exact conditional test
    that they share one rate (binomial, ours of the sum, at one half)."""
    total = ours + theirs
    p = 1.0 if total == 0 else round(float(stats.binomtest(ours, total).pvalue), 4)
    return {"ours": ours, "theirs": theirs, "p": p, "shown": p < 1 - CONFIDENCE}


def interval_text(interval: Mapping[str, float | None], digits: int = 1, unit: str = "") -> str:
    """"[lo, hi]" with a unit, or "" where there is no interval."""
    if interval.get("low") is None:
        return ""
    return f"[{interval['low']:.{digits}f}, {interval['high']:.{digits}f}]{unit}"


def difference_verdict(paired: Mapping[str, Any], what: str = "plane") -> str:
    """A paired comparison in words: "plane: worse, +4.2° [0.2, 10.5] on 7 flowers" or
    "plane: no difference shown on 9 flowers"."""
    n = paired["n"]
    if n == 0:
        return f"{what}: no flower both scored"
    if not paired["shown"]:
        return f"{what}: no difference shown on {n} flowers"
    return (f"{what}: {paired['direction']}, {paired['mean_difference']:+.1f}° "
            f"{interval_text(paired['ci95'])} on {n} flowers")
