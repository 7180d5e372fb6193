"""Clearance queries against placed plant parts: KD-trees on surface samples, grouped per part."""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from flowerpose.sim.pieces import Piece

#: Spacing of the surface samples of placed parts, metres.
SAMPLE_SPACING_M = 0.0015
#: Added to every clearance so that distances between samples, which can exceed the true
#: distance between the surfaces by up to about the sample spacing, stay safe, metres.
SAMPLE_MARGIN_M = 0.001


def surface_samples(piece: Piece, spacing: float, rng: np.random.Generator) -> np.ndarray:
    """(N, 3) points covering `piece`: its vertices plus area-weighted samples `spacing` apart.

    Points are in the piece's frame, metres.
    """
    count = int(np.ceil(piece.area() / spacing ** 2))
    mesh = trimesh.Trimesh(piece.vertices, piece.faces, process=False)
    points, _ = trimesh.sample.sample_surface(mesh, count, seed=rng)
    return np.concatenate([piece.vertices, points])


def curve_samples(path: np.ndarray, spacing: float = SAMPLE_SPACING_M) -> np.ndarray:
    """(M, 3) points along the polyline `path` ((n, 3), metres) at most `spacing` apart."""
    seg = np.diff(path, axis=0)
    steps = np.maximum(np.ceil(np.linalg.norm(seg, axis=1) / spacing).astype(int), 1)
    index = np.repeat(np.arange(len(seg)), steps)
    first = np.repeat(np.cumsum(steps) - steps, steps)
    t = (np.arange(len(index)) - first) / steps[index]
    return np.concatenate([path[index] + t[:, None] * seg[index], path[-1:]])


@dataclass(frozen=True)
class _Group:
    center: np.ndarray
    radius: float
    tree: cKDTree
    pad: float
    kind: str


class Obstacles:
    """Surface samples of the parts placed so far, one KD-tree per part (bed frame, metres).

    A group's `pad` is added to every distance asked of it: a stem is stored as its centre
    line with its radius as pad. Groups whose bounding spheres are out of reach are skipped.
    """

    def __init__(self) -> None:
        self._groups: list[_Group] = []

    def add(self, points: np.ndarray, kind: str, pad: float = 0.0) -> int:
        """Store a part's (N, 3) points under `kind` ("leaf", "stem", "flower", "distractor");
        returns the group id."""
        center = points.mean(0)
        radius = float(np.linalg.norm(points - center, axis=1).max())
        self._groups.append(_Group(center, radius, cKDTree(points), pad, kind))
        return len(self._groups) - 1

    def clear(self, points: np.ndarray, distance: float, kinds: Collection[str] | None = None,
              exclude: Collection[int] = ()) -> bool:
        """True when no stored point of the chosen groups lies within `distance` (+ pad) of
        any of `points` ((N, 3), metres). kinds: only groups of these kinds (None: all);
        exclude: group ids to ignore."""
        center = points.mean(0)
        radius = float(np.linalg.norm(points - center, axis=1).max())
        for index, group in enumerate(self._groups):
            if index in exclude or (kinds is not None and group.kind not in kinds):
                continue
            reach = distance + group.pad
            if np.linalg.norm(group.center - center) > group.radius + radius + reach:
                continue
            nearest, _ = group.tree.query(points, distance_upper_bound=reach)
            if np.isfinite(nearest).any():
                return False
        return True
