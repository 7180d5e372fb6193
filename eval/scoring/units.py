"""What is independent in a run's flowers: the units every interval resamples.

A run's plant entries (report.json's `plants`) score one plant or several; a perturbed
plant's repeats are entries too, each naming the plant it repeats (`repeat_of`). Plants are
independent of each other; flowers of one plant share its scan, so where a run holds
several plants a plant is the unit. Where it holds one, its flowers are the units, each
carrying every repeat of it: a flower thinned five times is one flower seen five times,
not five plants (`eval/scoring/stats.py`).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from typing import Any


def plant_of(entry: dict) -> str:
    """The plant a report.json plant entry scores: the one it repeats, else its own."""
    return entry.get("repeat_of", entry["plant"])


def repeats(entries: list[dict]) -> Counter:
    """How many entries score each plant (its repeats; 1 for a plant run once)."""
    return Counter(plant_of(e) for e in entries)


def share_weight(entries: list[dict]) -> float:
    """What one observation counts for in a share's interval: 1 over the entries a plant
    has (its repeats), so a flower counts once however often it was seen."""
    if not entries:
        return 1.0
    return len(repeats(entries)) / len(entries)


def visible_flowers(entries: list[dict]) -> int:
    """The visible flowers of the plants the entries score, each once."""
    return sum({plant_of(e): e["visible"] for e in entries}.values())


def several_plants(entries: list[dict]) -> bool:
    return len(repeats(entries)) > 1


def unit_of(entry: dict, truth: Any, several: bool) -> Any:
    """A flower observation's unit: its plant (`several` plants), else its flower."""
    return plant_of(entry) if several else (plant_of(entry), str(truth))


def flower_groups(entries: list[dict], value: Callable[[dict], float | None],
                  missed: float | None = None) -> list[list[float]]:
    """Per unit, the values of its visible flowers in every entry: `value(match)` of each
    flower found (None: left out), `missed` for each visible flower an entry did not find
    (None: left out). One plant's flowers that no entry found are units of `missed` values
    too, one per entry."""
    return paired_groups(entries, entries, lambda ours, _: missed if ours is None
                         else value(ours))


def paired_groups(ours: list[dict], theirs: list[dict],
                  value: Callable[[dict | None, dict | None], float | None]
                  ) -> list[list[float]]:
    """Per unit, a value of each visible flower of each plant entry, from the two runs'
    matches of it (report.json plant entries of the same plants, paired by name): `value(
    our match, their match)`, None for a run that did not find it; a None value is left out.
    A flower neither run found anywhere is valued `value(None, None)` too, in a unit of its
    own where the units are flowers."""
    by_name = {e["plant"]: e for e in theirs}
    if set(by_name) != {e["plant"] for e in ours}:
        raise ValueError("the two runs scored different plants")
    several = several_plants(ours)
    groups: dict[Any, list[float]] = {}
    known: dict[str, set[str]] = {}
    for entry in (*ours, *theirs):
        known.setdefault(plant_of(entry), set()).update(_found(entry))
    for entry in ours:
        plant = plant_of(entry)
        mine, other = _found(entry), _found(by_name[entry["plant"]])
        flowers = known[plant] if not several else set(mine) | set(other)
        for truth in sorted(flowers):
            got = value(mine.get(truth), other.get(truth))
            if got is not None:
                groups.setdefault(unit_of(entry, truth, several), []).append(got)
        unseen = value(None, None)
        if unseen is not None:
            for k in range(max(0, entry["visible"] - len(flowers))):
                unit = plant if several else (plant, f"unseen {k}")
                groups.setdefault(unit, []).append(unseen)
    return list(groups.values())


def _found(entry: dict) -> dict[str, dict]:
    """An entry's matches to visible flowers, by truth flower."""
    return {str(m["truth"]): m for m in entry.get("matches", []) if "error_deg" in m}


def keyed_units(entries: list[dict]) -> dict[tuple[str, str], Any]:
    """Each (plant entry, truth flower) key's unit (`unit_of`)."""
    several = several_plants(entries)
    return {(e["plant"], str(m["truth"])): unit_of(e, m["truth"], several)
            for e in entries for m in e.get("matches", [])}


def found_once(entries: list[dict]) -> set[tuple[str, str]]:
    """The flowers found, each once by (plant, truth flower): found in most of the entries
    that score its plant (a perturbed plant's repeats)."""
    seen = repeats(entries)
    counts = Counter((plant_of(e), str(m["truth"])) for e in entries
                     for m in e.get("matches", []) if "error_deg" in m)
    return {flower for flower, found in counts.items() if 2 * found > seen[flower[0]]}

