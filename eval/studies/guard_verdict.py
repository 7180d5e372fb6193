"""The guard's verdict on one change: the working tree against its base, run on the same
fresh plants, judged flower by flower for non-inferiority within stated margins.

Each measure is a loss, positive where the change is worse: the plane error (change minus
base on the flowers both found, degrees), the recall of visible flowers (base minus change,
points), false positives (change minus base per 100 visible flowers) and, for a pollination
entry, the share of flowers pollinated (base minus change, points). A measure is within its
margin where the one-sided 95 % upper bound of its loss is below the margin (the studentised
bootstrap over the independent units, `eval/scoring/stats.py`), with Holm's correction over every
measure of every entry the run judged, so that no claim of "within the margin" in the whole
run is wrong more than 5 % of the time. Under MIN_PAIRED flowers nothing is within: "too
few flowers to tell". Where both sides scored every flower alike the entry is "identical"
and nothing is tested.

The tails are judged flower by flower, not by statistics: a flower whose normal the change
flips (over 90 degrees) or sends over 20 degrees, and a pollination visit that collides or
pushes a leaf, where the base's did not, is a loss of its own, whatever the means say.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

from flowerpose.eval.reports.report import summarise
from flowerpose.eval.scoring.paired import newly_beyond
from flowerpose.eval.scoring.stats import (
    CONFIDENCE,
    FLIP_DEG,
    GROSS_DEG,
    MIN_PAIRED,
    TOO_FEW,
    holm,
    studentized,
)
from flowerpose.eval.scoring.units import paired_groups, plant_of, visible_flowers

#: What two runs' plant entries must agree in to be identical: the counts, and each
#: flower's match and plane error (what the guard judges; the superellipsoid and paraboloid
#: fits are not judged, and a local optimiser's may differ in its last digits).
COMPARED = ("plant", "gt", "visible", "detections", "found", "found_visible", "extra", "fp")
WITHIN = "within the margin"
NOT_WITHIN = "not shown within the margin"


@dataclass(frozen=True)
class Margins:
    """How much worse a change may be on each measure (the battery's [margins])."""

    plane_mean_deg: float
    recall_points: float
    fp_per_100_flowers: float
    pollinated_points: float
    new_flipped: int
    new_over_20: int
    new_collisions: int

    def of(self, measure: str) -> float:
        return {"plane": self.plane_mean_deg, "recall": self.recall_points,
                "fp": self.fp_per_100_flowers, "pollinated": self.pollinated_points}[measure]


#: The measures, the last for pollination entries only.
MEASURES = ("plane", "recall", "fp", "pollinated")
#: Each measure's unit, as reports print it.
UNITS = {"plane": "°", "recall": " points", "fp": " per 100 flowers", "pollinated": " points"}


def identical(change: list[dict], base: list[dict]) -> bool:
    """Whether both sides scored every plant alike on what the guard judges: the same
    counts, the same flowers matched with the same plane errors and, where flown, the same
    pollination outcomes."""
    def canonical(plants: list[dict]) -> str:
        return json.dumps([{**{k: p.get(k) for k in COMPARED},
                            "plane": p["error_deg"]["plane"],
                            "failed": p["failed"]["plane"],
                            "matches": [(m["detection"], str(m["truth"]),
                                         (m.get("error_deg") or {}).get("plane"))
                                        for m in p.get("matches", [])],
                            "pollination": [(o["flower"], o["outcome"]) for o in
                                            p.get("pollination", {}).get("flowers", [])]}
                           for p in plants], sort_keys=True)
    return canonical(change) == canonical(base)


def _plane(change: dict | None, base: dict | None) -> float | None:
    if change is None or base is None:
        return None
    ours, theirs = change["error_deg"].get("plane"), base["error_deg"].get("plane")
    return None if ours is None or theirs is None else ours - theirs


def _lost(change: dict | None, base: dict | None) -> float:
    return 100.0 * ((base is not None) - (change is not None))


def losses(change: list[dict], base: list[dict], pollinate: bool
           ) -> dict[str, tuple[list[list[float]], int]]:
    """Each measure's loss values grouped by independent unit (module docstring), and the
    distinct flowers it stands on."""
    visible = visible_flowers(change)
    paired = {(plant_of(p), str(m["truth"])) for p in change for m in p.get("matches", [])
              if (m.get("error_deg") or {}).get("plane") is not None
              and _plane(m, _match(base, p["plant"], m["truth"])) is not None}
    measures = {"plane": (paired_groups(change, base, _plane), len(paired)),
                "recall": (paired_groups(change, base, _lost), visible)}
    by_name = {p["plant"]: p for p in base}
    measures["fp"] = ([[100.0 * (p["fp"] - by_name[p["plant"]]["fp"]) / p["visible"]]
                       * p["visible"] for p in change if p["visible"]], visible)
    if pollinate:
        groups: dict[str, list[float]] = {}
        for plant in change:
            theirs = {o["flower"]: o["outcome"] for o in by_name[plant["plant"]]["pollination"]
                      ["flowers"]}
            groups.setdefault(plant_of(plant), []).extend(
                100.0 * ((theirs.get(o["flower"]) == "success") - (o["outcome"] == "success"))
                for o in plant["pollination"]["flowers"])
        measures["pollinated"] = (list(groups.values()),
                                  sum(len(g) for g in groups.values()))
    return measures


def _match(plants: list[dict], plant: str, truth: Any) -> dict | None:
    """A run's match to a visible flower of a plant entry, None where it did not find it."""
    for entry in plants:
        if entry["plant"] == plant:
            return next((m for m in entry.get("matches", [])
                         if str(m["truth"]) == str(truth) and "error_deg" in m), None)
    return None


def measure(groups: list[list[float]], margin: float, flowers: int) -> dict[str, Any]:
    """One measure's loss: its mean, standard error, the one-sided 95 % upper bound, the
    two-sided interval and the p-value of "the loss reaches the margin"."""
    values = sum(len(g) for g in groups)
    mean = sum(sum(g) for g in groups) / values if values else None
    boot = studentized(groups) if values else None
    if boot is None:
        same = values > 0 and all(v == mean for g in groups for v in g)
        return {"loss": None if mean is None else round(mean, 4), "se": 0.0 if same else None,
                "upper": None if mean is None or not same else round(mean, 4),
                "ci95": {"low": None, "high": None}, "n": values, "flowers": flowers,
                "margin": margin, "p": (0.0 if mean < margin else 1.0) if same else 1.0}
    return {"loss": round(boot.mean, 4), "se": round(boot.se, 4), "upper": boot.upper(),
            "ci95": boot.interval(), "n": values, "flowers": flowers, "margin": margin,
            "p": boot.p_below(margin)}


def tails(plants: list[dict]) -> dict[str, Any]:
    """One side's tails as `eval` prints them: flipped normals and errors over 20°
    (shares with intervals, each flower counted once), the plane error's 90th percentile
    with its interval, and the worst flower (which, how far)."""
    plane = summarise(plants)["error_deg"]["plane"]
    worst = max(((m["error_deg"]["plane"], p["plant"], str(m["truth"])) for p in plants
                 for m in p.get("matches", []) if m.get("error_deg", {}).get("plane")
                 is not None), default=None)
    return {"flipped": sum(e > FLIP_DEG for p in plants for e in p["error_deg"]["plane"]),
            "over_20": sum(e > GROSS_DEG for p in plants for e in p["error_deg"]["plane"]),
            "n": plane["n"], "over_90_share": plane["over_90"],
            "over_90_ci95": plane["over_90_ci95"], "over_20_share": plane["over_20"],
            "over_20_ci95": plane["over_20_ci95"], "p90": plane["p90"],
            "p90_ci95": plane["p90_ci95"],
            "worst": None if worst is None else {"plant": worst[1], "flower": worst[2],
                                                 "error_deg": worst[0]}}


def new_collisions(change: list[dict], base: list[dict]) -> list[dict]:
    """The flowers whose visit collides or pushes a leaf in the change and not in the
    base."""
    by_name = {p["plant"]: p for p in base}
    found = []
    for plant in change:
        theirs = {o["flower"]: o["outcome"] for o in by_name[plant["plant"]]["pollination"]
                  ["flowers"]}
        found += [{"plant": plant["plant"], "flower": str(o["flower"]),
                   "reason": o.get("reason", o["outcome"]), "base": theirs.get(o["flower"])}
                  for o in plant["pollination"]["flowers"]
                  if o["outcome"] == "collision" and theirs.get(o["flower"]) != "collision"]
    return found


def judge_entry(change: list[dict], base: list[dict], margins: Margins,
                pollinate: bool) -> dict[str, Any]:
    """One entry's comparison: identical, or each measure's loss (before Holm, `decide`)
    and the new tails."""
    result: dict[str, Any] = {"identical": identical(change, base),
                              "applies": list(MEASURES[:4 if pollinate else 3]),
                              "tails": {"change": tails(change), "base": tails(base)}}
    if result["identical"]:
        return {**result, "measures": {}, "new": {"flipped": [], "over_20": [],
                                                  "collisions": []}}
    result["measures"] = {name: measure(groups, margins.of(name), flowers)
                          for name, (groups, flowers) in
                          losses(change, base, pollinate).items()}
    result["new"] = {"flipped": newly_beyond(change, base, FLIP_DEG),
                     "over_20": newly_beyond(change, base, GROSS_DEG),
                     "collisions": new_collisions(change, base) if pollinate else []}
    return result


def decide(entries: dict[str, dict], margins: Margins) -> bool:
    """Holm's correction over every tested measure of every entry, then each measure's
    verdict and each entry's (in place); whether every entry passed."""
    tested = {(name, key): m["p"] for name, entry in entries.items()
              for key, m in entry["measures"].items() if m["flowers"] >= MIN_PAIRED}
    adjusted = holm(tested)
    alpha = 1 - CONFIDENCE
    passed = True
    for name, entry in entries.items():
        reasons = []
        for key, m in entry["measures"].items():
            m["p_holm"] = adjusted.get((name, key))
            if m["flowers"] < MIN_PAIRED:
                m["verdict"] = TOO_FEW
            else:
                m["verdict"] = WITHIN if m["p_holm"] < alpha else NOT_WITHIN
            if m["verdict"] != WITHIN:
                reasons.append(f"{key}: {m['verdict']}" + (
                    "" if m["upper"] is None else
                    f" (loss {m['loss']:+.2f}, upper bound {m['upper']:+.2f} against "
                    f"{m['margin']:g}{UNITS[key]}, n = {m['n']})"))
        for key, allowed in (("flipped", margins.new_flipped),
                             ("over_20", margins.new_over_20),
                             ("collisions", margins.new_collisions)):
            new = entry["new"][key]
            if len(new) > allowed:
                reasons.append(f"{len(new)} new {_TAIL_WORDS[key]}: " + ", ".join(
                    _flower_text(f) for f in new[:5]) + (" ..." if len(new) > 5 else ""))
        entry["verdict"] = "identical" if entry["identical"] else (
            "fail" if reasons else "pass")
        entry["reasons"] = reasons
        passed &= not reasons
    return passed


_TAIL_WORDS = {"flipped": "flipped normals (over 90°)", "over_20": "flowers over 20°",
               "collisions": "collisions or leaf pushes"}


def _flower_text(flower: dict) -> str:
    """"seed-7 flower 3: 2.1° -> 171.0°" or a visit's reason."""
    if "reason" in flower:
        return f"{flower['plant']} flower {flower['flower']} ({flower['reason']})"
    before = "not found" if flower["base_deg"] is None else f"{flower['base_deg']:.1f}°"
    return f"{flower['plant']} flower {flower['flower']}: {before} -> {flower['error_deg']:.1f}°"
