"""What a job runs on: a set of plants, seeded synthetic plants of a source and preset or
labelled real folders (`PlantSet`), and the one list of the sources their clouds come
from. Light, so the command line reads its choices without importing the harness.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from flowerpose.config import DEFAULT_PRESET, load_suite, suite_names
from flowerpose.errors import InputError

if TYPE_CHECKING:
    from flowerpose.eval.scoring.real_source import RealPlant

#: Where the clouds come from: simulated scans reconstructed by photogrammetry, the
#: plant's surfaces sampled directly, a simulated depth camera's frames fused, or real
#: labelled plants (`scoring/real_source.py`).
SOURCES = ("scan", "oracle", "rgbd", "real")
#: ... those of synthetic plants, with exact truth.
SYNTHETIC_SOURCES = tuple(s for s in SOURCES if s != "real")


@dataclass(frozen=True)
class PlantSet:
    """Seeded synthetic plants (`plants` of `source` and `preset` from `seed`) or labelled
    real plant `folders` (their truth scale from each folder's source.json unless
    `truth_scale`); `label` names the set in reports."""

    source: str
    preset: str = DEFAULT_PRESET
    plants: int = 0
    seed: int = 0
    folders: tuple[Path, ...] = ()
    truth_scale: float | None = None
    label: str = ""

    def __post_init__(self):
        if self.source not in SOURCES:
            raise InputError("source", f"'{self.source}': one of {', '.join(SOURCES)}")
        if self.real and not self.folders:
            raise InputError("source", "real needs at least one labelled plant folder: "
                             "--source real DIR [DIR ...]")
        if not self.real and self.plants < 1:
            raise InputError("plants", f"must be at least 1, got {self.plants}")
        if not self.label:
            object.__setattr__(self, "label", ", ".join(Path(f).name for f in self.folders)
                               if self.real else f"{self.preset} {self.source} seeds "
                               f"{self.seed}-{self.seed + self.plants - 1}")

    @property
    def real(self) -> bool:
        return self.source == "real"

    @property
    def seeds(self) -> list[int]:
        return list(range(self.seed, self.seed + self.plants))

    def describe(self) -> dict[str, Any]:
        """The plants as every run records them (report.json's and stress.json's `config`,
        tune's sets): a synthetic set's source, preset, plant count and first seed; a real
        set's source and each folder as read and checked (`RealPlant.describe`)."""
        if self.real:
            return {"source": "real", "folders": [p.describe() for p in self.real_plants()]}
        return {"source": self.source, "preset": self.preset, "plants": self.plants,
                "seed": self.seed}

    def real_plants(self) -> list[RealPlant]:
        """A real set's folders read and checked (`read_real_plant`), each named uniquely
        (`real_names`)."""
        from flowerpose.eval.scoring.real_source import read_real_plant

        plants = [read_real_plant(folder, self.truth_scale) for folder in self.folders]
        return [dataclasses.replace(plant, name=name)
                for name, plant in zip(real_names(self.folders), plants, strict=True)]

    def following(self) -> PlantSet:
        """The same kind of plants, the seeds after these (a synthetic set's validation)."""
        after = PlantSet(self.source, self.preset, self.plants, self.seed + self.plants)
        return dataclasses.replace(after, label=f"{after.label} (after {self.label})")


def parse_sets(items: list[str]) -> list[PlantSet]:
    """Plant sets from the command line: each a suite's name (assets/suites/), a suite
    file (TOML with [eval]: source, preset, plants, seed) or a real plant folder; real
    folders given one after another form one set."""
    sets: list[PlantSet] = []
    folders: list[Path] = []
    for item in items:
        path = Path(item)
        if item in suite_names() or path.suffix == ".toml":
            sets.append(suite_set(load_suite(item)))
        elif path.is_dir():
            folders.append(path)
        else:
            raise InputError(item, f"neither a suite ({', '.join(suite_names())}), a suite "
                             "file (.toml) nor a real plant folder")
    if folders:
        sets.append(PlantSet("real", folders=tuple(folders)))
    return sets


def suite_set(suite: dict) -> PlantSet:
    """A suite's plants (`config.load_suite`), labelled by the suite's name."""
    fixed = suite["eval"]
    if fixed["source"] == "real":
        raise InputError(suite["name"], "a suite of real plants: give their folders instead")
    return PlantSet(fixed["source"], fixed["preset"], fixed["plants"], fixed["seed"],
                    label=suite["name"])


def real_names(folders: Iterable[Path]) -> list[str]:
    """Each real plant folder's name in a report: its own, or, where two folders share
    it, with its parent's before it (PARENT-NAME); a folder given twice is refused."""
    given = [Path(f) for f in folders]
    resolved = [f.resolve() for f in given]
    for k, folder in enumerate(resolved):
        if folder in resolved[:k]:
            raise InputError(given[k], "is given twice: each plant counts once")
    names = [f.name for f in resolved]
    return _unique([f"{f.parent.name}-{f.name}" if names.count(f.name) > 1 else f.name
                    for f in resolved])


def _unique(names: list[str]) -> list[str]:
    """Folder names made unique by a count: a, a-2, a-3."""
    seen: dict[str, int] = {}
    unique = []
    for name in names:
        seen[name] = seen.get(name, 0) + 1
        unique.append(name if seen[name] == 1 else f"{name}-{seen[name]}")
    return unique
