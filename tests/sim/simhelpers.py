"""Helpers for the sim tests: cached generated plants and hand-made plants with known layout."""

from __future__ import annotations

import functools

import numpy as np
import trimesh

from flowerpose.sim.flower import open_flower
from flowerpose.sim.pieces import Part, Piece, merge
from flowerpose.sim.plant import FlowerTruth, Plant, generate_plant
from flowerpose.sim.plant_colours import rgba8
from flowerpose.sim.shapes import frame
from flowerpose.sim.world_config import PlantConfig, preset


@functools.cache
def cached_plant(seed: int, name: str) -> Plant:
    return generate_plant(seed, preset(name))


def box(center, extents, part: Part = Part.LEAF) -> Piece:
    """A closed, opaque box (metres, bed frame)."""
    mesh = trimesh.creation.box(extents=extents)
    colors = rgba8(np.tile([0.2, 0.5, 0.2], (len(mesh.vertices), 1)))
    return Piece.of(mesh.vertices + np.asarray(center), mesh.faces, colors, part)


def handmade_plant(flowers: list[tuple[np.ndarray, np.ndarray]], extra: list[Piece],
                   seed: int = 0) -> Plant:
    """A plant of open flowers at (center, normal) poses plus `extra` pieces."""
    rng = np.random.default_rng(seed)
    config = PlantConfig(cup=(0.0, 0.0), petal_counts=(5,), petal_count_weights=(1.0,))
    pieces, truth = [], []
    for index, (center, normal) in enumerate(flowers):
        local = open_flower(rng, config)
        pieces.append(local.piece.moved(frame(normal, 0.0), center).with_flower(index))
        truth.append(FlowerTruth(index, np.asarray(center, float), np.asarray(normal, float),
                                 local.radius, local.petals))
    whole = merge(pieces + extra)
    mesh = trimesh.Trimesh(whole.vertices, whole.faces, vertex_colors=whole.colors, process=False)
    return Plant(mesh, whole.part, whole.flower, truth, seed, config,
                 float(whole.vertices[:, 2].max()))
