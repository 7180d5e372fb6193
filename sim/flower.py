"""Open flowers, buds and fruit, each built in its own local frame.

Open flower frame: origin at the receptacle's base centre (the base of the petals), +z the
flower normal (the axis the corolla opens toward); the pedicel arrives along -z. Rotating
and translating the piece therefore carries the exact truth with it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flowerpose.sim import plant_colours as colours
from flowerpose.sim.pieces import Part, Piece, merge
from flowerpose.sim.shapes import blade, lathe
from flowerpose.sim.world_config import PlantConfig

#: Depth below the flower origin where the pedicel enters the calyx, metres.
PEDICEL_ENTRY_M = 0.003
#: Vertical spacing of overlapping petals (alternate petals lie this much apart), metres.
PETAL_STAGGER_M = 0.0002
#: Gap between the lowest petal and the sepals under it, metres.
SEPAL_GAP_M = 0.001


@dataclass(frozen=True)
class LocalFlower:
    """An open flower in its local frame (see the module docstring)."""

    piece: Piece
    """Petals, receptacle, stamens, sepals and calyx; flower ids still -1."""
    radius: float
    """Projected corolla radius (petal tip distance from the axis), metres."""
    petals: int
    """Number of petals."""
    rim_height: float
    """Height of the petal tips along +z, metres."""


@dataclass(frozen=True)
class LocalDistractor:
    """A bud or a fruit in its local frame; its stem leaves the origin along `stem_dir`."""

    piece: Piece
    stem_dir: np.ndarray
    """(3,) unit vector from the attachment point back along the stem, local frame."""


def _rotz(angle: np.ndarray) -> np.ndarray:
    """(n, 3, 3) rotations about +z by `angle` (n,) radians."""
    c, s = np.cos(angle), np.sin(angle)
    z, o = np.zeros_like(angle), np.ones_like(angle)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1),
                     np.stack([z, z, o], -1)], -2)


def _copies(vertices: np.ndarray, faces: np.ndarray, angle: np.ndarray) -> tuple[np.ndarray,
                                                                                np.ndarray]:
    """Copies of one template rotated about +z by each of `angle` (radians), concatenated."""
    verts = np.einsum("kij,nj->kni", _rotz(angle), vertices).reshape(-1, 3)
    offsets = (np.arange(len(angle)) * len(vertices))[:, None, None]
    return verts, (faces[None] + offsets).reshape(-1, 3)


def open_flower(rng: np.random.Generator, config: PlantConfig) -> LocalFlower:
    """Sample one open flower's shape and colours and build it in its local frame."""
    radius = 0.5 * rng.uniform(*config.flower_diameter_m)
    weights = np.asarray(config.petal_count_weights, np.float64)
    n_petals = int(rng.choice(np.asarray(config.petal_counts), p=weights / weights.sum()))
    cup = rng.uniform(*config.cup)
    rec_radius = rng.uniform(*config.receptacle_radius_m)
    rec_height = rng.uniform(0.002, 0.003)
    base = 0.7 * rec_radius
    length = radius - base
    start = rng.uniform(0.0, 2.0 * np.pi)
    petal_cups = cup + rng.normal(0.0, config.petal_cup_jitter, n_petals)
    levels = np.arange(n_petals) % 2
    if n_petals % 2:
        levels[-1] = 2

    def petal_z(u: np.ndarray, level: np.ndarray, petal_cup: np.ndarray) -> np.ndarray:
        return petal_cup * length * u ** 2 - PETAL_STAGGER_M * (1 + level)

    pieces = []
    nu, nv = 8, 5
    u = np.sin(0.5 * np.pi * np.linspace(0.0, 1.0, nu))
    widest = 0.68
    rho_widest = base + widest * length
    max_half = rng.uniform(0.95, 1.15) * rho_widest * np.sin(np.pi / n_petals)
    claw = 0.3 * max_half
    half = np.where(
        u <= widest,
        claw + (max_half - claw) * np.sin(0.5 * np.pi * np.minimum(u / widest, 1.0)),
        max_half * np.sqrt(np.clip(1.0 - ((u - widest) / (1.0 - widest)) ** 2, 0.0, 1.0)))
    verts, faces, _ = blade(base + u * length, half, nv)
    uu = np.repeat(u, nv)
    edge_lift = rng.uniform(0.0, 0.25, n_petals)
    angles = start + 2.0 * np.pi * np.arange(n_petals) / n_petals + rng.normal(0, 0.05, n_petals)
    petal_verts = np.repeat(verts[None], n_petals, 0)
    petal_verts[..., 2] = (petal_z(uu[None], levels[:, None], petal_cups[:, None])
                           + edge_lift[:, None] * verts[None, :, 1] ** 2 / max_half)
    petal_verts = np.einsum("kij,knj->kni", _rotz(angles), petal_verts).reshape(-1, 3)
    petal_faces = (faces[None] + (np.arange(n_petals) * len(verts))[:, None, None]).reshape(-1, 3)
    tone = colours.PETAL_PINK if rng.random() < 0.2 else colours.PETAL_CREAM
    base_tint = np.zeros((len(petal_verts), 3))
    base_tint[:, 1] = 0.04 * np.tile(np.repeat(1.0 - u, nv), n_petals) ** 3
    pieces.append(Piece.of(petal_verts, petal_faces,
                           colours.tone_colors(rng, tone, len(petal_verts), base_tint), Part.PETAL))

    rings = np.linspace(0.0, 1.0, 6)
    rec_rho = rec_radius * (1.0 - rings)
    rec_z = rec_height * (1.0 - (rec_rho / rec_radius) ** 2) ** 0.7
    verts, faces = lathe(rec_rho, rec_z, 14)
    pieces.append(Piece.of(verts, faces, colours.tone_colors(rng, colours.RECEPTACLE, len(verts)),
                           Part.RECEPTACLE))

    n_stamens = int(rng.integers(16, 25))
    stamen_angles = np.linspace(0.0, 2.0 * np.pi, n_stamens, endpoint=False) + rng.uniform(0, 1)
    foot = np.array([rec_radius + 0.0006, 0.0, 0.0003])
    tip = np.array([rec_radius + 0.0014, 0.0, rng.uniform(0.0015, 0.0022)])
    filament = np.array([foot - [0, 1.5e-4, 0], foot + [0, 1.5e-4, 0],
                         tip - [0, 1.5e-4, 0], tip + [0, 1.5e-4, 0]])
    verts, faces = _copies(filament, np.array([[0, 1, 2], [1, 3, 2]]), stamen_angles)
    pieces.append(Piece.of(verts, faces, colours.tone_colors(rng, colours.FILAMENT, len(verts)),
                           Part.STAMEN))
    anther_v, anther_f = lathe(np.array([0.0, 0.0005, 0.0]), np.array([-0.0004, 0.0, 0.0004]), 4)
    verts, faces = _copies(anther_v + tip, anther_f, stamen_angles)
    pieces.append(Piece.of(verts, faces, colours.tone_colors(rng, colours.ANTHER, len(verts)),
                           Part.STAMEN))

    lowest = petal_z(np.array([0.0]), np.array([2]), np.array([0.0]))[0]
    sepal_pieces = []
    for offset, reach, width in ((np.pi / 5, (0.6, 0.75), 0.22), (0.0, (0.45, 0.6), 0.12)):
        end = rng.uniform(*reach) * radius
        t = np.linspace(0.0, 1.0, 5)
        rho = 0.9 * base + t * (end - 0.9 * base)
        verts, faces, _ = blade(rho, width * radius * np.sin(np.pi * t ** 0.6), 3)
        u_rho = np.clip((rho - base) / length, 0.0, 1.0)
        low_cup = min(cup, petal_cups.min())
        verts[:, 2] = np.repeat(low_cup * length * u_rho ** 2 + lowest - SEPAL_GAP_M
                                - rng.uniform(0.0, 0.3) * (end - base) * t ** 2, 3)
        sepal_pieces.append(_copies(verts, faces, start + offset + 2.0 * np.pi * np.arange(5) / 5))
    calyx_v, calyx_f = lathe(np.array([base, 0.0022, 0.0012]),
                             np.array([lowest - 0.001, -0.0022, -PEDICEL_ENTRY_M - 0.0005]), 12)
    sepal_pieces.append((calyx_v, calyx_f))
    verts = np.concatenate([v for v, _ in sepal_pieces])
    offsets = np.cumsum([0] + [len(v) for v, _ in sepal_pieces[:-1]])
    faces = np.concatenate([f + o for (_, f), o in zip(sepal_pieces, offsets, strict=True)])
    pieces.append(Piece.of(verts, faces, colours.tone_colors(rng, colours.SEPAL, len(verts)),
                           Part.SEPAL))
    rim_height = cup * length - 1.5 * PETAL_STAGGER_M
    return LocalFlower(merge(pieces), radius, n_petals, rim_height)


def bud(rng: np.random.Generator) -> LocalDistractor:
    """A closed green bud standing on +z from its stem at the origin."""
    half = rng.uniform(0.003, 0.0045)
    length = 2.0 * half * rng.uniform(1.1, 1.4)
    t = np.linspace(0.0, 1.0, 8)
    verts, faces = lathe(half * np.sin(np.pi * t) ** 0.75, t * length, 10)
    piece = Piece.of(verts, faces, colours.tone_colors(rng, colours.BUD, len(verts)), Part.BUD)
    return LocalDistractor(piece, np.array([0.0, 0.0, -1.0]))


def fruit(rng: np.random.Generator, config: PlantConfig) -> LocalDistractor:
    """A strawberry hanging along -z from its calyx at the origin, red or green."""
    half = rng.uniform(0.007, 0.012)
    length = half * rng.uniform(2.0, 2.6)
    t = np.linspace(0.0, 1.0, 10)
    verts, faces = lathe(half * np.sin(np.pi * t ** 0.55) ** 0.8, -t * length, 12)
    ripe = rng.random() < config.ripe_fruit_probability
    tone = colours.FRUIT_RED if ripe else colours.FRUIT_GREEN
    body = Piece.of(verts, faces, colours.tone_colors(rng, tone, len(verts)), Part.FRUIT)
    n_sepals = int(rng.integers(6, 9))
    t = np.linspace(0.0, 1.0, 4)
    reach = half * rng.uniform(1.0, 1.4)
    verts, faces, _ = blade(0.002 + t * (reach - 0.002), 0.0025 * np.sin(np.pi * t ** 0.6), 3)
    verts[:, 2] = np.repeat(0.0006 + 0.2 * (reach - 0.002) * t ** 2, 3)
    angles = rng.uniform(0.0, 1.0) + 2.0 * np.pi * np.arange(n_sepals) / n_sepals
    verts, faces = _copies(verts, faces, angles)
    calyx = Piece.of(verts, faces, colours.tone_colors(rng, colours.SEPAL, len(verts)), Part.SEPAL)
    return LocalDistractor(merge([body, calyx]), np.array([0.0, 0.0, 1.0]))
