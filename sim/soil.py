"""The soil bed: a slightly uneven brown disc around the crown with a patchy texture."""

from __future__ import annotations

import numpy as np

from flowerpose.sim import plant_colours as colours
from flowerpose.sim.pieces import Part, Piece
from flowerpose.sim.shapes import grid_faces

#: Vertex spacing of the soil mesh, metres.
SOIL_SPACING_M = 0.01


def _waves(rng: np.random.Generator, xy: np.ndarray, wavelength: tuple[float, float],
           count: int) -> np.ndarray:
    """A smooth random field on (N, 2) points (metres): unit-variance sum of plane waves."""
    angle = rng.uniform(0.0, 2.0 * np.pi, count)
    k = 2.0 * np.pi / rng.uniform(*wavelength, count)
    vectors = np.stack([np.cos(angle), np.sin(angle)], 1) * k[:, None]
    field = np.sin(xy @ vectors.T + rng.uniform(0.0, 2.0 * np.pi, count)).sum(1)
    return field / np.sqrt(0.5 * count)


def soil(rng: np.random.Generator, radius: float, roughness: float, center: np.ndarray) -> Piece:
    """A soil disc of `radius` (metres) centred on `center` ((3,), bed frame).

    The height is a smooth field of standard deviation `roughness` (metres) with zero
    mean, so z ~ 0 on the soil as the bed frame promises.
    """
    n = int(round(2.0 * radius / SOIL_SPACING_M)) + 1
    a, b = np.meshgrid(np.linspace(-1.0, 1.0, n), np.linspace(-1.0, 1.0, n), indexing="ij")
    # Square grid to disc (elliptical mapping): a regular topology without a ragged rim.
    xy = radius * np.stack([(a * np.sqrt(1.0 - 0.5 * b ** 2)).ravel(),
                            (b * np.sqrt(1.0 - 0.5 * a ** 2)).ravel()], 1)
    z = roughness * (0.8 * _waves(rng, xy, (0.04, 0.2), 10) + 0.6 * rng.normal(size=len(xy)))
    z -= z.mean()
    patches = _waves(rng, xy, (0.03, 0.12), 8)
    shift = np.stack([2.0 * patches, 0.03 * patches, -0.04 * patches], 1)
    colors = colours.tone_colors(rng, colours.SOIL, len(xy), shift)
    vertices = np.column_stack([xy, z]) + center
    return Piece.of(vertices, grid_faces(n, n), colors, Part.SOIL)
