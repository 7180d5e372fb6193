"""One call from a seed to everything the harness needs of a synthetic plant."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from flowerpose.cloudio import Cloud
from flowerpose.config import DEFAULT_PRESET
from flowerpose.scan_geometry import path_cameras
from flowerpose.sim.degrade import degrade
from flowerpose.sim.export import write_plant
from flowerpose.sim.oracle import sample_oracle_cloud
from flowerpose.sim.plant import Plant, generate_plant
from flowerpose.sim.visibility import flower_visibility
from flowerpose.sim.world_config import PresetName, SimConfig, sim_preset

#: Streams of the seed's random numbers used for the oracle cloud and its degradation (the
#: plant uses the seed).
ORACLE_STREAM = 1
DEGRADE_STREAM = 2


@dataclass(frozen=True)
class PlantBundle:
    """A plant with its scan viewpoints, flower visibility and oracle cloud."""

    plant: Plant
    viewpoints: np.ndarray
    """(V, 3) scan camera positions, metres, bed frame."""
    visible: np.ndarray
    """(n_flowers,) bool: at least half the petals seen from one viewpoint."""
    fraction: np.ndarray
    """(n_flowers,) float: largest share of petal samples seen from one viewpoint."""
    cloud: Cloud
    """Oracle cloud, bed frame, metres."""
    point_part: np.ndarray
    """(N,) int8 `Part` of each cloud point."""
    point_flower: np.ndarray
    """(N,) int32 open-flower id of each cloud point, or -1."""
    config: SimConfig
    paths: dict[str, Path] | None = None
    """Files written (see `write_plant`), when an output folder was given."""


def make_plant(seed: int, preset: PresetName = DEFAULT_PRESET, points: int | None = None,
               out_dir: str | Path | None = None, *,
               config: SimConfig | None = None) -> PlantBundle:
    """Generate plant `seed`, its viewpoints, visibility and oracle cloud; write them to
    `out_dir` when given.

    preset: plant preset used when `config` is None; points: overrides
    `config.oracle.points`; config: the whole sim config (its `plant` field replaces the
    preset). The cloud is seeded from `seed` too, so the bundle is reproducible.
    """
    config = config or sim_preset(preset)
    if points is not None:
        config = dataclasses.replace(config,
                                     oracle=dataclasses.replace(config.oracle, points=points))
    plant = generate_plant(seed, config.plant)
    _, viewpoints, _ = path_cameras(plant.center[:2], plant.height, config.viewpoints)
    visible, fraction = flower_visibility(plant, viewpoints)
    rng = np.random.default_rng([seed, ORACLE_STREAM])
    cloud, point_part, point_flower = sample_oracle_cloud(plant, config.oracle, viewpoints, rng)
    cloud, point_part, point_flower, degradation = degrade(
        cloud, point_part, point_flower, visible, config.degrade,
        np.random.default_rng([seed, DEGRADE_STREAM]))
    paths = (write_plant(plant, out_dir, cloud, visible, fraction, degradation)
             if out_dir is not None else None)
    return PlantBundle(plant, viewpoints, visible, fraction, cloud, point_part, point_flower,
                       config, paths)
