"""Two runs on the same plants compared flower by flower (`eval --compare`, `--method`,
`sweep`, `tune`, `stress --compare`): per fit the paired angle-error difference, found
flowers by McNemar's test, false positives by the counts' exact test (`eval/stats.py`).

A flower is keyed by its plant and its truth flower; runs compare on the flowers both
scored, so a setting that finds fewer, easier flowers gains nothing by it.
"""

from __future__ import annotations

from typing import Any

from flowerpose.eval.stats import (
    count_test,
    difference_verdict,
    interval_text,
    mcnemar,
    paired_errors,
)
from flowerpose.pipeline.methods import METHODS

FlowerKey = tuple[str, str]


def flower_errors(plants: list[dict], fit: str) -> dict[FlowerKey, float]:
    """A run's angle errors of `fit` (degrees) by (plant, truth flower), over the visible
    flowers it found with a normal for that fit (report.json's plant entries)."""
    return {(p["plant"], str(m["truth"])): m["error_deg"][fit]
            for p in plants for m in p.get("matches", [])
            if m.get("error_deg", {}).get(fit) is not None}


def found_flowers(plants: list[dict]) -> set[FlowerKey]:
    """The visible flowers a run found, by (plant, truth flower) (a match to a visible
    flower carries its errors)."""
    return {(p["plant"], str(m["truth"])) for p in plants for m in p.get("matches", [])
            if "error_deg" in m}


def compare_runs(ours: list[dict], theirs: list[dict]) -> dict[str, Any]:
    """`ours` against `theirs` (report.json plant entries of the same plants): per fit the
    paired error difference ours - theirs (`stats.paired_errors`), found flowers by
    McNemar (`stats.mcnemar`), false positives by their counts (`stats.count_test`), and
    the verdicts in words."""
    fits = {fit: paired_errors(flower_errors(ours, fit), flower_errors(theirs, fit))
            for fit in METHODS}
    found = mcnemar(found_flowers(ours), found_flowers(theirs))
    false = count_test(sum(p["fp"] for p in ours), sum(p["fp"] for p in theirs))
    return {"fits": fits, "found": found, "fp": false,
            "verdicts": [*(difference_verdict(fits[fit], fit) for fit in METHODS),
                         found_verdict(found), fp_verdict(false)]}


def found_verdict(found: dict) -> str:
    """McNemar's comparison of found flowers in words."""
    said = (f"found: {found['only_ours']} only by this run, {found['only_theirs']} only by "
            f"the other (McNemar p = {found['p']:.3g})")
    if not found["shown"]:
        return said + ", no difference shown"
    return said + (", finds more" if found["only_ours"] > found["only_theirs"]
                   else ", finds fewer")


def fp_verdict(false: dict) -> str:
    """The false positives' comparison in words."""
    said = f"false positives: {false['ours']} against {false['theirs']} (p = {false['p']:.3g})"
    if not false["shown"]:
        return said + ", no difference shown"
    return said + (", fewer" if false["ours"] < false["theirs"] else ", more")


def difference_cell(paired: dict) -> str:
    """A paired difference as a table cell: "+4.2° [0.2, 10.5] on 7"."""
    if not paired["n"]:
        return "-"
    return f"{paired['mean_difference']:+.1f}° {interval_text(paired['ci95'])} on {paired['n']}"


def record_cell(paired: dict) -> str:
    """Wins, ties and losses of a paired difference, and its Wilcoxon p-value."""
    if not paired["n"]:
        return "-"
    p = paired["p_wilcoxon"]
    return (f"{paired['wins']}/{paired['ties']}/{paired['losses']}, "
            f"p = {'-' if p is None else f'{p:.3g}'}")
