"""Two runs on the same plants compared flower by flower (`eval --compare`, `--method`,
`sweep`, `tune`, `stress --compare`, `guard`): per fit the paired angle-error difference,
found flowers by McNemar's test, false positives by the counts' exact test
(`eval/scoring/stats.py`).

A flower is keyed by its plant and its truth flower; runs compare on the flowers both
scored, so a setting that finds fewer, easier flowers gains nothing by it. A plant entry
that is one repeat of a perturbed plant names the plant it repeats (`repeat_of`): its
flowers are that plant's flowers seen again, so the statistics nest the repeats inside
their flower (a flower's repeats are one unit) and McNemar counts each flower once.
"""

from __future__ import annotations

from typing import Any

from flowerpose.eval.scoring.stats import (
    FLIP_DEG,
    GROSS_DEG,
    TOO_FEW,
    count_test,
    difference_verdict,
    interval_text,
    mcnemar,
    p_text,
    paired_errors,
)
from flowerpose.eval.scoring.units import found_once, keyed_units, visible_flowers
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


def newly_beyond(ours: list[dict], theirs: list[dict], limit: float,
                 fit: str = "plane") -> list[dict]:
    """The flowers `ours` sends past `limit` degrees where `theirs` did not (it had it
    within the limit, or did not find it): each {plant, flower, error_deg, base_deg}."""
    before = flower_errors(theirs, fit)
    return [{"plant": plant, "flower": truth, "error_deg": error,
             "base_deg": before.get((plant, truth))}
            for (plant, truth), error in flower_errors(ours, fit).items()
            if error > limit and not (before.get((plant, truth)) or 0.0) > limit]


def compare_runs(ours: list[dict], theirs: list[dict]) -> dict[str, Any]:
    """`ours` against `theirs` (report.json plant entries of the same plants): per fit the
    paired error difference ours - theirs (`stats.paired_errors`, repeats nested in their
    flower), found flowers by McNemar, each flower once (`stats.mcnemar`), false positives
    by their counts (`stats.count_test`), the plane normals this run flips or sends over
    20° where the other did not (`newly_beyond`), and the verdicts in words."""
    unit_of = keyed_units(ours) | keyed_units(theirs)
    fits = {fit: paired_errors(flower_errors(ours, fit), flower_errors(theirs, fit), unit_of)
            for fit in METHODS}
    found = mcnemar(found_once(ours), found_once(theirs), visible_flowers(ours))
    false = count_test(sum(p["fp"] for p in ours), sum(p["fp"] for p in theirs))
    new = {"flipped": newly_beyond(ours, theirs, FLIP_DEG),
           "over_20": newly_beyond(ours, theirs, GROSS_DEG)}
    return {"fits": fits, "found": found, "fp": false, "new": new,
            "verdicts": [*(difference_verdict(fits[fit], fit) for fit in METHODS),
                         found_verdict(found), fp_verdict(false), tails_verdict(new)]}


def tails_verdict(new: dict) -> str:
    """The flowers newly flipped or sent over 20° in words."""
    return (f"tails: {len(new['flipped'])} normals newly flipped (over {FLIP_DEG:g}°), "
            f"{len(new['over_20'])} flowers newly over {GROSS_DEG:g}°")


def found_verdict(found: dict) -> str:
    """McNemar's comparison of found flowers in words."""
    return mcnemar_verdict(found, "found", "finds")


def pollinated_verdict(pollinated: dict) -> str:
    """McNemar's comparison of flowers pollinated (`sweep.pollinated_against`) in words."""
    return mcnemar_verdict(pollinated, "pollinated", "pollinates")


def mcnemar_verdict(test: dict, what: str, does: str) -> str:
    """McNemar's comparison (`stats.mcnemar`) of the flowers `what` ("found") in words,
    `does` ("finds") saying which side does more."""
    said = (f"{what}: {test['only_ours']} only by this run, {test['only_theirs']} only by "
            f"the other (McNemar p {_p(test['p'])})")
    if test.get("too_few"):
        return said + f", {TOO_FEW} ({test['flowers']})"
    if not test["shown"]:
        return said + ", no difference shown"
    return said + (f", {does} more" if test["only_ours"] > test["only_theirs"]
                   else f", {does} fewer")


def fp_verdict(false: dict) -> str:
    """The false positives' comparison in words."""
    said = f"false positives: {false['ours']} against {false['theirs']} (p {_p(false['p'])})"
    if not false["shown"]:
        return said + ", no difference shown"
    return said + (", fewer" if false["ours"] < false["theirs"] else ", more")


def _p(p: float) -> str:
    """"= 0.5" or "< 0.0001"."""
    text = p_text(p)
    return text if text.startswith("<") else f"= {text}"


def difference_cell(paired: dict) -> str:
    """A paired difference as a table cell: "+4.2° [0.2, 10.5] on 7"."""
    if not paired["n"]:
        return "-"
    return f"{paired['mean_difference']:+.1f}° {interval_text(paired['ci95'])} on {paired['n']}"


def record_cell(paired: dict) -> str:
    """Wins, ties and losses of a paired difference, and its Wilcoxon p-value."""
    if not paired["n"]:
        return "-"
    return (f"{paired['wins']}/{paired['ties']}/{paired['losses']}, "
            f"p {_p(paired['p_wilcoxon'])}" if paired["p_wilcoxon"] is not None else
            f"{paired['wins']}/{paired['ties']}/{paired['losses']}, p = -")
