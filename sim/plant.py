"""Seeded procedural strawberry plants with exactly known flower poses.

A plant is a crown on a soil disc, trifoliate leaves on petioles, inflorescences of 1-3
open flowers on yellow-green peduncles, and buds and fruit as distractors. Each flower is
built in its local frame (z = normal, origin = receptacle base centre) and moved into
place, so its truth is exact. Bed frame: metres, x along the bed, y across, z up, z = 0 on
the soil surface.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh

from flowerpose.sim.foliage import PETIOLE_RADIUS_M, crown, leaves
from flowerpose.sim.obstacles import (
    SAMPLE_SPACING_M,
    Obstacles,
    curve_samples,
    surface_samples,
)
from flowerpose.sim.pieces import Part, merge
from flowerpose.sim.placement import Placer
from flowerpose.sim.soil import soil
from flowerpose.sim.world_config import PlantConfig


@dataclass(frozen=True)
class FlowerTruth:
    """The exact pose of one open flower (bed frame, metres)."""

    id: int
    center: np.ndarray
    """(3,) centre on the flower axis at the base of the petals (receptacle base centre)."""
    normal: np.ndarray
    """(3,) unit vector along the axis the corolla opens toward (away from the peduncle)."""
    radius: float
    """Projected corolla radius (axis to petal tips), metres."""
    petals: int
    stage: str = "open"


@dataclass(frozen=True)
class Plant:
    """A generated plant: labelled mesh and truth."""

    mesh: trimesh.Trimesh
    """Whole plant and soil, bed frame, metres, per-vertex RGBA colours."""
    face_part: np.ndarray
    """(F,) int8 `Part` of each face."""
    face_flower: np.ndarray
    """(F,) int32 open-flower id of petal, receptacle, stamen and sepal faces, else -1."""
    flowers: list[FlowerTruth]
    seed: int
    config: PlantConfig
    height: float
    """Highest point of the plant above the soil (z = 0), metres."""
    touching: list[tuple[int, int]] = field(default_factory=list)
    """Pairs of flower ids placed touching at the rims on purpose (clusters)."""
    buds: int = 0
    """Number of closed buds (distractors)."""
    fruit: int = 0
    """Number of fruit (distractors)."""

    @property
    def center(self) -> np.ndarray:
        """(3,) crown position on the soil, metres, bed frame."""
        return np.array([*self.config.center_xy_m, 0.0])


def generate_plant(seed: int, config: PlantConfig) -> Plant:
    """Generate the plant of `seed` (the same seed and config give identical output)."""
    rng = np.random.default_rng(seed)
    center = np.array([*config.center_xy_m, 0.0])
    height = rng.uniform(*config.height_m)
    spread = rng.uniform(*config.spread_m)

    ground = soil(rng, config.soil_radius_m, config.soil_roughness_m, center)
    base = crown(rng, center)
    foliage = leaves(rng, config, center, height, spread)

    obstacles = Obstacles()
    obstacles.add(surface_samples(base, SAMPLE_SPACING_M, rng), "leaf")
    canopy = []
    for leaf in foliage:
        samples = surface_samples(leaf.blade, SAMPLE_SPACING_M, rng)
        canopy.append(samples)
        obstacles.add(samples, "leaf")
        obstacles.add(curve_samples(leaf.petiole_path), "leaf", pad=PETIOLE_RADIUS_M)

    placer = Placer(rng, config, center, height, spread, obstacles, np.concatenate(canopy))
    placer.place_flowers(int(rng.integers(config.flowers[0], config.flowers[1] + 1)))
    placer.place_distractors()
    placed = placer.result

    flower_pieces = [f.local.piece.moved(f.rotation, f.center).with_flower(f.id)
                     for f in placed.flowers]
    whole = merge([ground, base, *[p for leaf in foliage for p in (leaf.blade, leaf.petiole)],
                   *flower_pieces,
                   *placed.stems, *placed.distractors])
    mesh = trimesh.Trimesh(whole.vertices, whole.faces, vertex_colors=whole.colors, process=False)
    plant_vertices = np.unique(whole.faces[whole.part != Part.SOIL])
    flowers = [FlowerTruth(f.id, f.center.copy(), f.normal.copy(), float(f.local.radius),
                           f.local.petals) for f in placed.flowers]
    return Plant(mesh, whole.part, whole.flower, flowers, seed, config,
                 float(whole.vertices[plant_vertices, 2].max()), placed.touching, placed.buds,
                 placed.fruit)
