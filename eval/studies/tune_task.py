"""What `flowerpose tune` searches for, task by task: the pose task's detection F1 and plane
error, or the pollination task's share of flowers pollinated and share of visits that
collided (`eval --task pollinate`), each with the numbers a trial records, the objectives
by default, the columns of tune.md and the rule the chosen trial is picked by.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

#: The summary numbers every trial records for training and validation (with their 95 %
#: bounds; `f1_low` is the F1 of the recall's and precision's lower bounds).
POSE_RECORDED = ("f1", "recall_visible", "precision", "fp", "found_visible", "visible",
                 "error_deg.plane.mean", "error_deg.plane.median", "recall_visible_ci95.low",
                 "precision_ci95.low", "error_deg.plane.mean_ci95.low",
                 "error_deg.plane.mean_ci95.high", "error_deg.plane.p90",
                 "error_deg.plane.p90_ci95.high", "error_deg.plane.over_90")
#: And a pollination trial's, from its visits (`pollinated.summarise_pollination`).
POLLINATION_RECORDED = ("pollination.success_rate", "pollination.success_rate_ci95.low",
                        "pollination.success_rate_ci95.high", "pollination.successes",
                        "pollination.flowers", "pollination.visits",
                        "pollination.collision_share", "pollination.collision_share_ci95.high",
                        "pollination.failures.collision", "pollination.failures.unreachable",
                        "pollination.failures.pose off", "pollination_ceiling.success_rate",
                        "pollination_ceiling.success_rate_ci95.low")


@dataclass(frozen=True)
class Measure:
    """A recorded number as tune.md shows it: its key, its words, whether more is better."""

    key: str
    label: str
    higher_is_better: bool
    degrees: bool = False
    said: str = ""
    """Its name in a warning (default: `label`)."""

    def cell(self, scores: dict | None) -> str:
        if not scores or scores.get(self.key) is None:
            return "-"
        value = scores[self.key]
        return f"{value:.2f}°" if self.degrees else f"{value:.3f}"


@dataclass(frozen=True)
class TuneTask:
    """One task's study: `shown` are the point values tune.md gives for training and
    validation (the first also as the gap between them); `ranked` the validation bounds
    the chosen trial is picked by, in order."""

    name: str
    objectives: tuple[str, ...]
    recorded: tuple[str, ...]
    shown: tuple[Measure, ...]
    ranked: tuple[Measure, ...]
    rule: str

    def rank(self, scores: dict) -> tuple[float, ...]:
        """A trial's place by its validation scores (lower is better): each ranked bound in
        turn, a missing one last."""
        return tuple(-value if m.higher_is_better else value
                     for m in self.ranked
                     for value in [scores.get(m.key) if scores.get(m.key) is not None
                                   else (-math.inf if m.higher_is_better else math.inf)])

    def worse(self, mine: dict, theirs: dict) -> list[str]:
        """Where the chosen settings' validation point values are worse than the
        defaults', in words."""
        said = []
        for m in self.shown:
            ours, base = mine.get(m.key), theirs.get(m.key)
            if ours is None or base is None or ours == base or (ours > base) == m.higher_is_better:
                continue
            shown = (lambda v: f"{v:.2f}°") if m.degrees else (lambda v: f"{v:.3f}")
            said.append(f"the chosen settings' validation {m.said or m.label} ({shown(ours)}) "
                        f"is {'below' if m.higher_is_better else 'above'} the defaults' "
                        f"({shown(base)})")
        return said


POSE = TuneTask(
    "pose", ("max:f1", "min:error_deg.plane.mean"), POSE_RECORDED,
    (Measure("f1", "f1", True, said="F1"),
     Measure("error_deg.plane.mean", "error_deg.plane.mean", False, True, "plane error")),
    (Measure("f1_low", "validate F1, lower bound", True),
     Measure("error_deg.plane.mean_ci95.high", "validate plane mean, upper bound", False,
             True)),
    "the chosen trial: among the training front (trials that flip no normal the defaults "
    "did not), none that flips one on the validation plants; the highest lower bound of the "
    "validation F1 (the F1 of the 95 % lower bounds of the recall of visible flowers and of "
    "the precision), ties broken by the lower upper bound of the validation plane error's "
    "mean")
POLLINATE = TuneTask(
    "pollinate", ("max:pollination.success_rate", "min:pollination.collision_share"),
    POSE_RECORDED + POLLINATION_RECORDED,
    (Measure("pollination.success_rate", "share pollinated", True),
     Measure("pollination.collision_share", "share of visits that collided", False)),
    (Measure("pollination.success_rate_ci95.low", "validate pollinated, lower bound", True),
     Measure("pollination.collision_share_ci95.high", "validate collisions, upper bound",
             False)),
    "the chosen trial: among the training front (trials that flip no normal the defaults "
    "did not), none that flips one on the validation plants; the highest lower bound of the "
    "share of validation flowers pollinated (from the estimated poses, with the close look "
    "where it runs), ties broken by the lower upper bound of the share of validation visits "
    "that collided or pushed a leaf past the limit")
TASKS = {task.name: task for task in (POSE, POLLINATE)}

