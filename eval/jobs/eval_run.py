"""What an eval run is (`EvalRun`): what it runs on and what it measures, beside its
settings (`config.py`); light, so the command line offers its choices without importing
the harness."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from flowerpose.errors import InputError
from flowerpose.eval.jobs.plant_set import SYNTHETIC_SOURCES, PlantSet

if TYPE_CHECKING:
    from flowerpose.eval.jobs.config import EvalConfig
    from flowerpose.eval.scoring.methods import ExternalMethod


#: Where an eval's clouds come from when not told.
DEFAULT_SOURCE = "scan"
#: What an eval measures: the poses (Table I), or pollination visits with them as well.
TASKS = ("pose", "pollinate")

#: Synthetic plants an eval makes when not told: a scan takes about 5 minutes a plant here.
DEFAULT_PLANTS = {**dict.fromkeys(SYNTHETIC_SOURCES, 10), "scan": 2}


@dataclass(frozen=True)
class EvalRun:
    """What `run_eval` runs, besides the settings: the plants (`PlantSet`), the task
    ("pose", or "pollinate": plan, fly and score pollination visits too), the other
    settings (by name) and external methods compared on the same clouds, and the suite and
    the preset and profile files (`report.assets_record`) to record."""

    plants: PlantSet
    task: str = "pose"
    compare: dict[str, EvalConfig] = field(default_factory=dict)
    methods: tuple[ExternalMethod, ...] = ()
    suite: dict | None = None
    assets: dict[str, dict[str, str]] | None = None

    def __post_init__(self):
        if self.task not in TASKS:
            raise InputError("task", f"'{self.task}': one of {', '.join(TASKS)}")
        if self.task == "pollinate" and self.plants.real:
            raise InputError("task", "pollinate needs synthetic plants, whose geometry "
                             "judges the visits: not --source real")
