"""Pollination outcomes counted: a plant's flowers by outcome, and report.json's summary
sections of a run's visits (from the estimated poses, from the scan's poses alone, from the
true ones), with their Wilson intervals. The outcomes themselves are judged in
`eval/pollination/visits.py`.
"""

from __future__ import annotations

from flowerpose.eval.scoring.stats import wilson

#: The causes a visit fails for, in the order they are looked at.
CAUSES = ("missed", "no pose", "uncertain", "unreachable", "pose off", "collision")
#: A plant entry's pollination sections (report.json), each summarised alike.
SECTIONS = ("pollination", "pollination_ceiling", "pollination_scan_pose")


def tally(outcomes: list[dict]) -> dict:
    """Successes, their rate and the failures by cause of a list of flower outcomes."""
    successes = sum(o["outcome"] == "success" for o in outcomes)
    return {"successes": successes, "success_rate": round(successes / len(outcomes), 4)
            if outcomes else None,
            "failures": {cause: sum(o["outcome"] == cause for o in outcomes)
                         for cause in CAUSES}}


def summarise_pollination(plants: list[dict]) -> dict:
    """report.json's `summary.pollination` from the plants' sections: visits, flowers,
    successes, their rate with its Wilson interval, the failures by cause, and the share of
    visits that collided or pushed a leaf with its Wilson interval."""
    outcomes = [o for p in plants for o in p["flowers"]]
    counted = tally(outcomes)
    visits = sum(p["visits"] for p in plants)
    collisions = counted["failures"]["collision"]
    return {"visits": visits, "flowers": len(outcomes), **counted,
            "success_rate_ci95": wilson(counted["successes"], len(outcomes)),
            "collision_share": round(collisions / visits, 4) if visits else None,
            "collision_share_ci95": wilson(collisions, visits)}


def pollination_sections(entries: list[dict]) -> dict:
    """The summary's sections of the plant entries' visits: each section every entry has
    (`SECTIONS`), summarised over them."""
    return {key: summarise_pollination([e[key] for e in entries]) for key in SECTIONS
            if entries and all(key in e for e in entries)}
