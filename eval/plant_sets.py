"""Sets of plants to score a configuration on: seeded synthetic plants of a source and
preset (or a suite's), or real labelled plant folders; `tune` trains and validates on
them, `sweep` scores its settings on them.

A synthetic set's plants are generated and captured once per world (the `sim.*` settings
and, for the scan and RGB-D sources, the capture's) and taken from the stage cache after
that; a configuration that changes only the pipeline's settings reuses them.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from flowerpose.config import DEFAULT_PRESET, load_suite, load_toml, suite_names, to_dict
from flowerpose.errors import InputError

#: The sections of the configuration each synthetic source's plants and clouds depend on.
WORLD_SECTIONS = {"oracle": ("sim",), "scan": ("sim", "scan"), "rgbd": ("sim", "rgbd", "fusion")}


@dataclass(frozen=True)
class PlantSet:
    """Seeded synthetic plants (`source`, `preset`, `plants` from `seed`) or real plant
    `folders`."""

    label: str
    source: str = "oracle"
    preset: str = DEFAULT_PRESET
    plants: int = 0
    seed: int = 0
    folders: tuple[Path, ...] = ()

    @property
    def real(self) -> bool:
        return self.source == "real"

    def describe(self) -> dict[str, Any]:
        if self.real:
            return {"label": self.label, "source": "real",
                    "folders": [str(f) for f in self.folders]}
        return {"label": self.label, "source": self.source, "preset": self.preset,
                "plants": self.plants, "seed": self.seed}

    def following(self) -> PlantSet:
        """The same kind of plants, the seeds after these (a synthetic set's validation)."""
        after = synthetic_set(self.source, self.preset, self.plants, self.seed + self.plants)
        return dataclasses.replace(after, label=f"{after.label} (after {self.label})")


def synthetic_set(source: str, preset: str, plants: int, seed: int) -> PlantSet:
    if plants < 1:
        raise InputError("plants", f"must be at least 1, got {plants}")
    return PlantSet(f"{preset} {source} seeds {seed}-{seed + plants - 1}", source, preset,
                    plants, seed)


def parse_sets(items: list[str]) -> list[PlantSet]:
    """Plant sets from the command line: each a suite's name (assets/suites/), a suite
    file (TOML) or a real plant folder; real folders given one after another form one set."""
    sets: list[PlantSet] = []
    folders: list[Path] = []
    for item in items:
        path = Path(item)
        if item in suite_names():
            sets.append(_suite_set(load_suite(item), item))
        elif path.suffix == ".toml":
            data = load_toml(path)
            fixed = data.get("eval")
            if not isinstance(fixed, dict) or not {"source", "preset", "plants",
                                                     "seed"} <= set(fixed):
                raise InputError(path, "a suite file needs [eval] with source, preset, plants "
                                 "and seed")
            sets.append(_suite_set({"eval": fixed}, path.stem))
        elif path.is_dir():
            folders.append(path)
        else:
            raise InputError(item, f"neither a suite ({', '.join(suite_names())}), a suite "
                             "file (.toml) nor a real plant folder")
    if folders:
        sets.append(PlantSet(", ".join(f.name for f in folders), "real",
                             folders=tuple(folders)))
    return sets


def _suite_set(suite: dict, name: str) -> PlantSet:
    fixed = suite["eval"]
    if fixed["source"] == "real":
        raise InputError(name, "a suite of real plants: give their folders instead")
    return dataclasses.replace(synthetic_set(fixed["source"], fixed["preset"], int(fixed["plants"]),
                                             int(fixed["seed"])), label=name)


#: A configuration of the harness as it applies to any set: the preset's config (an
#: EvalConfig) in, with the user's and a trial's settings applied, out.
Configure = Callable[[Any], Any]


class SetScorer:
    """Scores configurations on plant sets: each set's config is its preset's with the
    settings applied (`Configure`); captures are made once per world and detections come
    from the stage cache where the same cloud was detected with the same settings."""

    def __init__(self, out_dir: Path, cache: Path | None, workers: int | None = 1):
        self.out_dir, self.cache, self.workers = out_dir, cache, workers
        self._clouds: dict[str, dict[int, tuple[Path, Path]]] = {}

    def config(self, plant_set: PlantSet, configure: Configure) -> Any:
        """The set's configuration: its preset's (a real set: the defaults') with the
        settings applied."""
        from flowerpose.eval.harness import eval_config

        return eval_config(DEFAULT_PRESET if plant_set.real else plant_set.preset,  # type: ignore[arg-type]
                           configure)

    def score(self, plant_set: PlantSet, configure: Configure, out_dir: Path) -> list[dict]:
        """Report.json plant entries of the configured settings on every plant of the set
        (scored into out_dir/NAME/)."""
        from flowerpose.eval.harness import evaluate_cloud, pipeline_part, real_plants

        config = self.config(plant_set, configure)
        if plant_set.real:
            from flowerpose.eval.real_source import evaluate_real_plant

            return [evaluate_real_plant(plant, pipeline_part(config), out_dir / plant.name,
                                        config.score.max_distance_m)[0]
                    for plant in real_plants(list(plant_set.folders), None)]
        clouds = self._captured(plant_set, config)
        return [evaluate_cloud(*clouds[s], config, out_dir / f"seed-{s}", f"seed-{s}",
                               self.cache)[0] for s in sorted(clouds)]

    def _captured(self, plant_set: PlantSet, config: Any) -> dict[int, tuple[Path, Path]]:
        """The set's plants generated and captured for `config`'s world, once per world."""
        sections = {name: to_dict(getattr(config, name))
                    for name in WORLD_SECTIONS[plant_set.source]}
        digest = hashlib.sha256(json.dumps(sections, sort_keys=True).encode()).hexdigest()[:12]
        world = f"{plant_set.source}-{plant_set.preset}-{digest}"
        key = f"{world}/{plant_set.seed}+{plant_set.plants}"
        if key not in self._clouds:
            from flowerpose.eval.harness import capture_clouds, generate_plants

            seeds = list(range(plant_set.seed, plant_set.seed + plant_set.plants))
            base = self.out_dir / "plants" / world
            generate_plants(seeds, config.sim, base, self.workers, self.cache)
            self._clouds[key] = capture_clouds(config, plant_set.source,
                                               {s: base / f"seed-{s}" for s in seeds},
                                               self.workers, self.cache)[0]
        return self._clouds[key]
