"""The crown and the trifoliate leaves on their petioles, in the bed frame (metres)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from flowerpose.sim import plant_colours as colours
from flowerpose.sim.pieces import Part, Piece
from flowerpose.sim.shapes import blade, cubic_bezier, lathe, tube
from flowerpose.sim.world_config import PlantConfig

#: Height of the crown top where petioles and peduncles start, metres.
CROWN_TOP_M = 0.017
PETIOLE_RADIUS_M = 0.0016


class Leaf(NamedTuple):
    """One trifoliate leaf, bed frame."""

    blade: Piece
    """The three leaflets."""
    petiole: Piece
    """The petiole tube from the crown to the leaflets."""
    petiole_path: np.ndarray
    """(n, 3) centre line of the petiole, metres."""


def crown(rng: np.random.Generator, center: np.ndarray) -> Piece:
    """The short reddish-brown crown standing on the soil at `center` ((3,), bed frame)."""
    scale = rng.uniform(0.9, 1.1)
    verts, faces = lathe(scale * np.array([0.014, 0.015, 0.012, 0.006, 0.0]),
                         np.array([-0.002, 0.006, 0.013, 0.018, 0.021]), 12)
    return Piece.of(verts + center, faces, colours.tone_colors(rng, colours.CROWN, len(verts)),
                    Part.CROWN)


def _leaflet(rng: np.random.Generator, length: float, config: PlantConfig) -> tuple[np.ndarray,
                                                                                  np.ndarray,
                                                                                  np.ndarray]:
    """One serrated ovate leaflet: midrib along +x from the origin, blade facing +z.

    Returns vertices (metres, leaflet frame), faces and s (lateral position in [-1, 1]).
    """
    teeth = int(rng.integers(config.leaflet_teeth[0], config.leaflet_teeth[1] + 1))
    step = 0.75 / teeth
    notch = 0.25 + step * np.arange(teeth)
    t = np.concatenate([np.linspace(0.0, 0.25, 3, endpoint=False),
                        np.stack([notch, notch + 0.7 * step], 1).ravel(), [1.0]])
    serration = np.concatenate([np.zeros(3), np.tile([-1.0, 1.0], teeth), [0.0]])
    half = (0.5 * rng.uniform(*config.leaflet_aspect) * length
            * np.sin(np.pi * t ** rng.uniform(0.9, 1.3)) ** 0.7
            * (1.0 + rng.uniform(0.05, 0.1) * serration))
    verts, faces, s = blade(t * length, half, 5)
    fold = np.tan(np.radians(rng.uniform(*config.leaf_fold_deg)))
    droop = rng.uniform(*config.leaf_droop)
    verts[:, 2] = fold * np.abs(verts[:, 1]) - droop * verts[:, 0] ** 2 / length
    return verts, faces, s


def leaf(rng: np.random.Generator, config: PlantConfig, center: np.ndarray, azimuth: float,
         age: float, height: float, spread: float) -> Leaf:
    """A trifoliate leaf (three leaflets on a petiole from the crown), bed frame.

    center: (3,) crown base; azimuth: radians; age in [0, 1]: young leaves stand tall
    near the axis and tilt up, old ones spread low and flat; height, spread: the plant's
    target height and diameter, metres.
    """
    length = rng.uniform(*config.leaflet_length_m)
    outward = np.array([np.cos(azimuth), np.sin(azimuth), 0.0])
    up = np.array([0.0, 0.0, 1.0])
    pitch = np.radians(35.0 - 50.0 * age + rng.normal(0.0, 8.0))
    reach = 0.03 + age * max(0.5 * spread - 0.9 * length - 0.03, 0.01)
    top = height - 0.03 - age ** 1.2 * (height - 0.1)
    z_end = max(min(top * rng.uniform(0.92, 1.04), height - length * max(np.sin(pitch), 0.0)
                    - 0.005), 0.05)
    end = center + reach * rng.uniform(0.85, 1.05) * outward + z_end * up

    lateral = np.radians(rng.uniform(60.0, 80.0))
    leaflets = []
    for beta, scale, roll in ((0.0, 1.0, rng.normal(0.0, 0.08)),
                              (lateral, rng.uniform(0.85, 0.95), rng.uniform(0.1, 0.35)),
                              (-lateral, rng.uniform(0.85, 0.95), -rng.uniform(0.1, 0.35))):
        verts, faces, s = _leaflet(rng, scale * length, config)
        direction = np.array([np.cos(azimuth + beta), np.sin(azimuth + beta), 0.0])
        p = pitch - (abs(beta) > 0) * rng.uniform(0.0, 0.17)
        x_axis = np.cos(p) * direction + np.sin(p) * up
        side = np.cross(up, direction)
        normal = np.cross(x_axis, side)
        y_axis = np.cos(roll) * side + np.sin(roll) * normal
        rotation = np.stack([x_axis, y_axis, np.cross(x_axis, y_axis)], 1)
        leaflets.append((verts @ rotation.T + end + 0.002 * x_axis, faces, s))
    verts = np.concatenate([v for v, _, _ in leaflets])
    offsets = np.cumsum([0, len(leaflets[0][0]), len(leaflets[1][0])])
    faces = np.concatenate([f + o for (_, f, _), o in zip(leaflets, offsets, strict=True)])
    s = np.concatenate([s for _, _, s in leaflets])
    midrib = (1.0 - np.abs(s)) ** 4
    shade = np.stack([-4.0 * midrib, -0.05 * midrib, 0.06 * midrib + 0.06 * (1.0 - age)], 1)
    blade_piece = Piece.of(verts, faces, colours.tone_colors(rng, colours.LEAF, len(verts), shade),
                           Part.LEAF)

    start = center + np.array([0.0, 0.0, CROWN_TOP_M]) + 0.005 * outward
    span = np.linalg.norm(end - start)
    chord = end - start
    path = cubic_bezier(start, start + 0.35 * chord + 0.1 * span * up,
                        start + 0.7 * chord + 0.1 * span * up, end, 16)
    verts, faces = tube(path, PETIOLE_RADIUS_M)
    petiole = Piece.of(verts, faces, colours.tone_colors(rng, colours.PETIOLE, len(verts)),
                       Part.PETIOLE)
    return Leaf(blade_piece, petiole, path)


def leaves(rng: np.random.Generator, config: PlantConfig, center: np.ndarray, height: float,
           spread: float) -> list[Leaf]:
    """All leaves of a plant, spiralling at the golden angle."""
    n = int(rng.integers(config.leaves[0], config.leaves[1] + 1))
    start = rng.uniform(0.0, 2.0 * np.pi)
    ages = np.clip((np.arange(n) + 0.5) / n + rng.normal(0.0, 0.08, n), 0.0, 1.0)
    return [leaf(rng, config, center, start + np.radians(137.5 * k + rng.normal(0.0, 12.0)),
                 float(ages[k]), height, spread) for k in range(n)]
