"""How far a number can be trusted: every interval, accuracy curve and paired comparison the
reports print, and the tests the guard decides by.

Angle errors are degrees, one value a scored flower. A run's values come in groups, one an
independent unit: a plant where a run has several (flowers of one plant share its scan and
are not independent), else a flower, carrying every repeat of it (a `stress` level draws
its perturbation several times over the same flowers: those repeats are one flower seen
again, not new plants). Intervals are 95 % and seeded, so a report made twice prints the
same bounds:

- a mean (of errors, of paired differences, of the accuracy curve's scores): the symmetric
  studentised bootstrap (bootstrap-t) over the units, then each drawn unit's values, the
  standard error of each resample the units' (cluster-robust); chosen by its coverage: on
  errors shaped like the real plants' (7, 11 and 40 flowers) its 95 % interval covers the
  true mean 94-96 % of the time, where the percentile bootstrap covers 87-93 % and the t
  interval 93 % (`tests/eval/test_stats.py` simulates it). One-sided bounds (the guard's)
  come from the same resamples;
- a median or 90th percentile: the percentile bootstrap over the same two stages;
- a share (recall, precision, errors over 20 degrees): the Wilson score interval, which
  holds at 0 and 1 where the normal approximation fails, over the flowers, each counted
  once however many repeats saw it;
- a paired comparison of two settings on the flowers both scored: the mean difference's
  interval (above), wins, ties and losses, Wilcoxon's signed-rank test; found flowers by
  McNemar's exact test, a flower found where most of its repeats found it; false
  positives by the exact conditional test of two counts.

A comparison on fewer than MIN_PAIRED flowers says "too few flowers to tell". A difference
whose interval lies within MARGIN_DEG of zero is "within the margin", one whose interval
leaves out zero beyond that is "worse" or "better", anything else "no difference shown".
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
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
#: Paired differences within this many degrees count as ties in wins/ties/losses, and a
#: mean difference whose interval lies within it is "within the margin" (well under a hand
#: label's own error of about 5 degrees).
TIE_DEG = 0.5
MARGIN_DEG = TIE_DEG
#: A comparison on fewer paired flowers than this shows nothing: "too few flowers to tell".
MIN_PAIRED = 10
#: P-values below this print as "< 0.0001".
P_FLOOR = 1e-4
#: Resamples drawn at once (memory: RESAMPLES_AT_ONCE x units x values a unit).
_CHUNK_VALUES = 2_000_000

#: An interval that cannot be had (fewer than two values, no trials).
NO_INTERVAL: dict[str, float | None] = {"low": None, "high": None}
TOO_FEW = "too few flowers to tell"

Groups = Sequence[Sequence[float]]


def _rounded(low: float, high: float, digits: int = 4) -> dict[str, float]:
    return {"low": round(float(low), digits), "high": round(float(high), digits)}


def wilson(successes: float, trials: float) -> dict[str, float | None]:
    """The Wilson score interval of a share `successes` of `trials` ({"low", "high"},
    None without trials). Either may be fractional: a flower seen in several repeats counts
    once, its share of them a fraction of a success."""
    if trials <= 0:
        return dict(NO_INTERVAL)
    z = stats.norm.ppf(1 - (1 - CONFIDENCE) / 2)
    share = min(max(successes / trials, 0.0), 1.0)
    scale = 1 + z * z / trials
    centre = (share + z * z / (2 * trials)) / scale
    half = z / scale * math.sqrt(share * (1 - share) / trials + z * z / (4 * trials * trials))
    return _rounded(max(0.0, centre - half), min(1.0, centre + half))


def _units(groups: Groups) -> list[np.ndarray]:
    """The independent units of `groups`: the groups themselves where there are several,
    else each value of the one group (a plant's flowers)."""
    kept = [np.asarray(g, float) for g in groups if len(g)]
    if len(kept) == 1:
        return [np.array([v]) for v in kept[0]]
    return kept


def _padded(units: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    sizes = np.array([len(u) for u in units])
    padded = np.full((len(units), sizes.max()), np.nan)
    for k, values in enumerate(units):
        padded[k, :len(values)] = values
    return padded, sizes


def _mean_and_se(values: np.ndarray, present: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mean of all values and its cluster-robust standard error over the units (axis
    -2; values along -1, `present` marking them), for any leading resample axes."""
    totals = np.where(present, values, 0.0).sum(-1)
    counts = present.sum(-1)
    n = counts.sum(-1)
    mean = totals.sum(-1) / n
    k = values.shape[-2]
    residual = totals - mean[..., None] * counts
    se = np.sqrt(k / (k - 1) * (residual ** 2).sum(-1)) / n
    return mean, se


def _resampled(units: list[np.ndarray], rng: np.random.Generator
               ) -> list[tuple[np.ndarray, np.ndarray]]:
    """RESAMPLES two-stage resamples, in chunks: units drawn with replacement, then each
    drawn unit's values; (values, present) of shape (resamples, units, values a unit)."""
    padded, sizes = _padded(units)
    k, m = padded.shape
    per = max(1, _CHUNK_VALUES // (k * m))
    chunks = []
    for start in range(0, RESAMPLES, per):
        count = min(per, RESAMPLES - start)
        drawn = rng.integers(0, k, size=(count, k))
        lengths = sizes[drawn]
        if m == 1:  # units of one value each: nothing to draw within them
            values = padded[drawn]
        else:
            picks = (rng.random((count, k, m)) * lengths[..., None]).astype(int)
            values = padded[drawn[..., None], picks]
        present = np.arange(m) < lengths[..., None]
        chunks.append((values, present))
    return chunks


@dataclass(frozen=True)
class Studentized:
    """A mean over independent units with its cluster-robust standard error and the
    bootstrap distribution of |T| = |mean* - mean| / se* (sorted)."""

    mean: float
    se: float
    t: np.ndarray
    units: int
    values: int

    def interval(self, confidence: float = CONFIDENCE) -> dict[str, float]:
        """The symmetric two-sided interval."""
        half = self._quantile(confidence) * self.se
        return _rounded(self.mean - half, self.mean + half)

    def upper(self, confidence: float = CONFIDENCE) -> float:
        """The one-sided upper bound at `confidence` (the symmetric interval's at twice
        the tail)."""
        return round(self.mean + self._quantile(2 * confidence - 1) * self.se, 4)

    def p_below(self, margin: float) -> float:
        """The one-sided p-value of "the mean is at least `margin`" (small: the mean is
        shown below it), from the same resamples."""
        if self.se == 0 or not len(self.t):
            return 0.0 if self.mean < margin else 1.0
        t_obs = (self.mean - margin) / self.se
        beyond = (np.count_nonzero(self.t >= abs(t_obs)) + 1) / (len(self.t) + 1)
        return float(beyond / 2 if t_obs < 0 else 1 - beyond / 2)

    def _quantile(self, confidence: float) -> float:
        if self.se == 0 or not len(self.t):
            return 0.0
        return float(np.quantile(self.t, confidence))


def studentized(groups: Groups, seed: int = SEED) -> Studentized | None:
    """The studentised bootstrap of the mean of `groups` (module docstring); None with
    fewer than two values. Resamples whose standard error is 0 (every value drawn alike)
    say nothing of the spread and are left out."""
    units = _units(groups)
    total = sum(len(u) for u in units)
    if total < 2 or len(units) < 2:
        return None
    padded, _ = _padded(units)
    mean, se = _mean_and_se(padded, ~np.isnan(padded))
    # A standard error this small is rounding of values all alike: none.
    tiny = 1e-12 * max(1.0, float(np.nanmax(np.abs(padded))))
    if se <= tiny:
        return Studentized(float(mean), 0.0, np.zeros(0), len(units), total)
    rng = np.random.default_rng(seed)
    t = []
    for values, present in _resampled(units, rng):
        means, ses = _mean_and_se(values, present)
        kept = ses > tiny
        t.append(np.abs(means[kept] - mean) / ses[kept])
    return Studentized(float(mean), float(se), np.sort(np.concatenate(t)), len(units), total)


#: The quantile of each statistic the percentile bootstrap bounds.
_QUANTILES = {"median": 0.5, "p90": 0.9}


def _padded_quantile(q: float, values: np.ndarray) -> np.ndarray:
    """The q-quantile of each row of `values`, padded with nan past its own count (linear
    interpolation between order statistics, as numpy's quantile)."""
    counts = (~np.isnan(values)).sum(axis=1)
    ordered = np.sort(values, axis=1)  # nan sorts last
    position = q * (counts - 1)
    below = np.floor(position).astype(int)
    above = np.minimum(below + 1, counts - 1)
    low = np.take_along_axis(ordered, below[:, None], axis=1)[:, 0]
    high = np.take_along_axis(ordered, above[:, None], axis=1)[:, 0]
    return low + (high - low) * (position - below)


#: The range an angle error takes, degrees: a mean's interval is kept inside it.
ANGLE_RANGE = (0.0, 180.0)


def bootstrap_interval(groups: Groups, statistic: str = "mean", seed: int = SEED,
                       within: tuple[float, float] | None = None) -> dict[str, float | None]:
    """The 95 % interval of `statistic` ("mean", "median", "p90") of the values of all
    `groups` together (module docstring). Groups without values are left out; None bounds
    with fewer than two values. `within`: the range the values take (angle errors 0-180°),
    which a mean's symmetric interval is cut to."""
    return bootstrap_intervals(groups, (statistic,), seed, within)[statistic]


def bootstrap_intervals(groups: Groups, statistics: tuple[str, ...], seed: int = SEED,
                        within: tuple[float, float] | None = None
                        ) -> dict[str, dict[str, float | None]]:
    """`bootstrap_interval` of several statistics at once."""
    units = _units(groups)
    if sum(len(u) for u in units) < 2 or len(units) < 2:
        return {name: dict(NO_INTERVAL) for name in statistics}
    found = {}
    if "mean" in statistics:
        interval = studentized(groups, seed).interval()
        if within is not None:  # the mean cannot leave the values' range
            interval = _rounded(max(interval["low"], within[0]),
                                min(interval["high"], within[1]))
        found["mean"] = interval
    quantiles = [name for name in statistics if name != "mean"]
    if quantiles:
        estimates: dict[str, list[np.ndarray]] = {name: [] for name in quantiles}
        for values, present in _resampled(units, np.random.default_rng(seed)):
            flat = np.where(present, values, np.nan).reshape(len(values), -1)
            for name in quantiles:
                estimates[name].append(_padded_quantile(_QUANTILES[name], flat))
        tail = 100 * (1 - CONFIDENCE) / 2
        for name in quantiles:
            drawn = np.concatenate(estimates[name])
            found[name] = _rounded(np.percentile(drawn, tail), np.percentile(drawn, 100 - tail))
    return {name: found[name] for name in statistics}


def error_summary(groups: Groups, intervals: bool = True, weight: float = 1.0
                  ) -> dict[str, Any]:
    """The statistics of one fit's angle errors (degrees), one group a unit (module
    docstring): count, mean, median and population std, the 90th percentile, the shares
    over GROSS_DEG and FLIP_DEG, each with its 95 % interval (None where there are no
    errors, or, for speed, without `intervals`). `weight`: what one value counts for in a
    share's interval (1 / the repeats that saw each flower)."""
    values = np.asarray([e for g in groups for e in g], float)
    if len(values) == 0:
        return {"mean": None, "median": None, "std": None, "n": 0,
                "mean_ci95": dict(NO_INTERVAL), "median_ci95": dict(NO_INTERVAL),
                "p90": None, "p90_ci95": dict(NO_INTERVAL),
                "over_20": None, "over_20_ci95": dict(NO_INTERVAL),
                "over_90": None, "over_90_ci95": dict(NO_INTERVAL)}
    over = {threshold: int((values > threshold).sum()) for threshold in (GROSS_DEG, FLIP_DEG)}
    found = (bootstrap_intervals(groups, ("mean", "median", "p90"), within=ANGLE_RANGE)
             if intervals
             else {name: dict(NO_INTERVAL) for name in ("mean", "median", "p90")})

    def share_interval(count: int) -> dict[str, float | None]:
        return wilson(count * weight, len(values) * weight) if intervals else dict(NO_INTERVAL)

    return {"mean": round(float(values.mean()), 4),
            "median": round(float(np.median(values)), 4),
            "std": round(float(values.std()), 4), "n": int(len(values)),
            "mean_ci95": found["mean"], "median_ci95": found["median"],
            "p90": round(float(np.percentile(values, 90)), 4), "p90_ci95": found["p90"],
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
                   intervals: bool = True, scores: Groups | None = None) -> dict[str, Any]:
    """The accuracy curve of one fit, as pose benchmarks report it: of the flowers that
    count (`flowers[k]` in group k: the visible ones), the share whose error is within each
    of ACCURACY_THRESHOLDS_DEG, a missed flower or a failed fit counting as a failure at
    every threshold; and its area from 0 to ACCURACY_LIMIT_DEG normalised to 0-1 (`auc`),
    with its interval (without `intervals`, for speed, none), over `scores` (each unit's
    flowers' scores, `accuracy_scores`) where given, else over the groups. None where no
    flower counts."""
    total = int(sum(flowers))
    if total == 0:
        return {"thresholds_deg": list(ACCURACY_THRESHOLDS_DEG), "share": None, "n": 0,
                "auc": None, "auc_ci95": dict(NO_INTERVAL)}
    values = np.asarray([e for g in groups for e in g], float)
    share = [round(float((values <= t).sum()) / total, 4) for t in ACCURACY_THRESHOLDS_DEG]
    if scores is None:
        scores = [accuracy_scores(g, n) for g, n in zip(groups, flowers, strict=True)]
    return {"thresholds_deg": list(ACCURACY_THRESHOLDS_DEG), "share": share, "n": total,
            "auc": round(float(np.concatenate([np.asarray(s, float) for s in scores]).mean()), 4),
            "auc_ci95": (bootstrap_interval(scores, "mean", within=(0.0, 1.0)) if intervals
                         else dict(NO_INTERVAL))}


def margin_verdict(interval: Mapping[str, float | None], margin: float, flowers: int) -> str:
    """A difference's verdict from its 95 % interval (positive: worse) on `flowers`
    distinct flowers: "too few flowers to tell" under MIN_PAIRED, "within the margin" where
    the interval lies within ±margin, "worse" or "better" where it leaves out zero, else
    "no difference shown"."""
    low, high = interval.get("low"), interval.get("high")
    if flowers < MIN_PAIRED or low is None:
        return TOO_FEW
    if -margin <= low and high <= margin:
        return "within the margin"
    if low > 0:
        return "worse"
    if high < 0:
        return "better"
    return "no difference shown"


def paired_errors(ours: Mapping[tuple, float], theirs: Mapping[tuple, float],
                  units: Mapping[tuple, Any] | None = None) -> dict[str, Any]:
    """Two settings' angle errors on the flowers both scored (keys: (plant, flower), a
    repeat's plant named by it too): the mean difference ours - theirs (degrees; positive:
    ours is worse) with its interval over the independent units (`units`: each key's unit,
    by default its plant where there are several, else the flower), wins/ties/losses (ties
    within TIE_DEG), the Wilcoxon signed-rank p-value (1.0 when every difference is 0), the
    verdict ("identical" where every difference is 0, else `margin_verdict` on the distinct
    flowers), whether a difference is shown and which way."""
    common = sorted(set(ours) & set(theirs), key=str)
    differences = np.array([ours[k] - theirs[k] for k in common], float)
    if len(differences) == 0:
        return {"n": 0, "flowers": 0, "mean_difference": None, "ci95": dict(NO_INTERVAL),
                "wins": 0, "ties": 0, "losses": 0, "p_wilcoxon": None, "verdict": TOO_FEW,
                "margin": MARGIN_DEG, "shown": False, "direction": "none"}
    unit_of = dict(units) if units is not None else default_units(common)
    by_unit: dict[Any, list[float]] = {}
    for key, difference in zip(common, differences, strict=True):
        by_unit.setdefault(unit_of[key], []).append(float(difference))
    flowers = len({flower_of(key, unit_of) for key in common})
    interval = bootstrap_interval(list(by_unit.values()), "mean")
    verdict = ("identical" if not differences.any()
               else margin_verdict(interval, MARGIN_DEG, flowers))
    shown = verdict in ("worse", "better")
    return {"n": int(len(differences)), "flowers": flowers,
            "mean_difference": round(float(differences.mean()), 4),
            "ci95": interval, "wins": int((differences < -TIE_DEG).sum()),
            "ties": int((np.abs(differences) <= TIE_DEG).sum()),
            "losses": int((differences > TIE_DEG).sum()),
            "p_wilcoxon": wilcoxon_p(differences), "verdict": verdict, "margin": MARGIN_DEG,
            "shown": shown, "direction": verdict if shown else "none"}


def default_units(keys: Sequence[tuple]) -> dict[tuple, Any]:
    """Each (plant, flower) key's independent unit: its plant where the keys hold several
    plants, else the flower itself."""
    plants = {key[0] for key in keys}
    return {key: key[0] if len(plants) > 1 else key for key in keys}


def flower_of(key: tuple, unit_of: Mapping[tuple, Any]) -> Any:
    """The flower a key is an observation of: its unit where the unit is a flower, else
    the key (a plant's flower)."""
    unit = unit_of[key]
    return unit if isinstance(unit, tuple) else key


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
        return float(stats.wilcoxon(nonzero).pvalue)


def mcnemar(ours: set, theirs: set, flowers: int | None = None) -> dict[str, Any]:
    """McNemar's exact test on the flowers one setting found and the other did not (the
    sets hold flower keys, each flower once): how many only ours found, only theirs, and
    the two-sided p-value (the binomial test of one against their sum). `flowers`: the
    flowers compared, found or not; under MIN_PAIRED nothing is shown."""
    only_ours, only_theirs = len(ours - theirs), len(theirs - ours)
    discordant = only_ours + only_theirs
    p = 1.0 if discordant == 0 else float(stats.binomtest(only_ours, discordant).pvalue)
    enough = flowers is None or flowers >= MIN_PAIRED
    return {"both": len(ours & theirs), "only_ours": only_ours, "only_theirs": only_theirs,
            "flowers": flowers, "p": p, "shown": enough and p < 1 - CONFIDENCE,
            "too_few": not enough}


def count_test(ours: int, theirs: int) -> dict[str, Any]:
    """Two counts of events on the same data (false positives): the exact conditional test
    that they share one rate (binomial, ours of the sum, at one half)."""
    total = ours + theirs
    p = 1.0 if total == 0 else float(stats.binomtest(ours, total).pvalue)
    return {"ours": ours, "theirs": theirs, "p": p, "shown": p < 1 - CONFIDENCE}


def holm(p_values: Mapping[Any, float]) -> dict[Any, float]:
    """Holm's step-down adjusted p-values: rejecting where an adjusted p is below 1 -
    CONFIDENCE holds the family-wise error of the whole family at that level."""
    ordered = sorted(p_values.items(), key=lambda item: item[1])
    count = len(ordered)
    adjusted, running = {}, 0.0
    for rank, (key, p) in enumerate(ordered):
        running = max(running, min(1.0, (count - rank) * p))
        adjusted[key] = running
    return adjusted


def p_text(p: float | None) -> str:
    """A p-value as printed: "< 0.0001" below P_FLOOR (never 0), else 2 significant
    digits (3 under 0.01); "-" for none."""
    if p is None or (isinstance(p, float) and math.isnan(p)):
        return "-"
    if p < P_FLOOR:
        return f"< {P_FLOOR:g}"
    return f"{p:.2g}" if p >= 0.01 else f"{p:.3g}"


def interval_text(interval: Mapping[str, float | None], digits: int = 1, unit: str = "") -> str:
    """"[lo, hi]" with a unit, or "" where there is no interval."""
    if interval.get("low") is None:
        return ""
    return f"[{interval['low']:.{digits}f}, {interval['high']:.{digits}f}]{unit}"


def difference_verdict(paired: Mapping[str, Any], what: str = "plane") -> str:
    """A paired comparison in words: "plane: worse, +4.2° [0.2, 10.5] on 17 flowers",
    "plane: within the margin (±0.5°), +0.1° [0.0, 0.2] on 40 flowers", "plane: no
    difference shown on 19 flowers" or "plane: too few flowers to tell (2)"."""
    n = paired["n"]
    if n == 0:
        return f"{what}: no flower both scored"
    verdict = paired["verdict"]
    if verdict == TOO_FEW:
        return f"{what}: {TOO_FEW} ({paired['flowers']})"
    if verdict in ("no difference shown", "identical"):
        return f"{what}: {verdict} on {n} flowers"
    said = "within the margin (±" + f"{paired['margin']:g}°)" if verdict.startswith(
        "within") else verdict
    return (f"{what}: {said}, {paired['mean_difference']:+.1f}° "
            f"{interval_text(paired['ci95'])} on {n} flowers")
