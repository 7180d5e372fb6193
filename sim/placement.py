"""Placing flowers, buds and fruit on inflorescences, clear of leaves and of each other.

Every candidate pose is checked against the parts already placed (`Obstacles`, KD-trees on
surface samples) and rejected when anything but its own pedicel comes within the flower
clearance; touching clusters are the one deliberate exception, placed with a small gap at
the rims. Bed frame, metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from flowerpose.sim import plant_colours as colours
from flowerpose.sim.flower import PEDICEL_ENTRY_M, LocalFlower, bud, fruit, open_flower
from flowerpose.sim.foliage import CROWN_TOP_M
from flowerpose.sim.obstacles import (
    SAMPLE_MARGIN_M,
    SAMPLE_SPACING_M,
    Obstacles,
    curve_samples,
    surface_samples,
)
from flowerpose.sim.pieces import Part, Piece
from flowerpose.sim.shapes import cubic_bezier, frame, spherical, tube
from flowerpose.sim.world_config import PlantConfig

PEDUNCLE_RADIUS_M = 0.0018
PEDICEL_RADIUS_M = 0.0011
#: Straight pedicel behind a flower beyond its radius, metres: the stem leaves the flower
#: along -normal before it bends, so it never sweeps past the petals.
STRAIGHT_BEYOND_RADIUS_M = 0.008
#: Sample spacing used to find the touching position of two flowers, metres.
TOUCH_SPACING_M = 0.0004
#: Lowest point allowed for flowers and distractors above z = 0, metres (soil is uneven).
LOWEST_M = 0.008
TRIES = 60
UP = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class PlacedFlower:
    """An open flower at its pose: local frame mapped by x -> rotation @ x + center."""

    id: int
    """Flower id: its index in the placement order."""
    local: LocalFlower
    rotation: np.ndarray
    """(3, 3) columns: the flower's local x, y, z (= normal) in the bed frame."""
    center: np.ndarray
    """(3,) receptacle base centre, metres, bed frame."""
    group: int
    """Obstacle group id of the flower's samples."""

    @property
    def normal(self) -> np.ndarray:
        return self.rotation[:, 2]


@dataclass
class Placement:
    """The result of placing one plant's flowers and distractors."""

    flowers: list[PlacedFlower]
    stems: list[Piece]
    distractors: list[Piece]
    touching: list[tuple[int, int]]
    buds: int = 0
    fruit: int = 0


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _perpendicular(rng: np.random.Generator, axis: np.ndarray) -> np.ndarray:
    """A random unit vector perpendicular to the unit vector `axis`."""
    v = rng.normal(size=3)
    return _unit(v - (v @ axis) * axis)


def _stem(branch: np.ndarray, end: np.ndarray, back: np.ndarray, straight: float,
          outward: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pedicel from `branch` to the attachment point `end` ((3,), metres).

    The last `straight` metres run along -`back` (the unit vector from `end` back along the
    stem), so the stem arrives from behind the organ; it leaves `branch` upward and along
    `outward` (a horizontal unit vector). Returns the whole path and its curved part (the
    part that may come near other organs).
    """
    start = end + straight * back
    span = np.linalg.norm(start - branch)
    curve = cubic_bezier(branch, branch + 0.35 * span * _unit(0.7 * UP + 0.3 * outward),
                         start + 0.35 * span * back, start, 14)
    return np.concatenate([curve, np.linspace(start, end, 4)[1:]]), curve


class Placer:
    """Places one plant's inflorescences: flowers first, then buds and fruit.

    center: (3,) crown base; height, spread: the plant's target height and diameter;
    obstacles: leaves, petioles and crown already stored; canopy: (M, 3) leaf-blade samples
    (flowers hidden under leaves are placed below them). Metres, bed frame.
    """

    def __init__(self, rng: np.random.Generator, config: PlantConfig, center: np.ndarray,
                 height: float, spread: float, obstacles: Obstacles, canopy: np.ndarray):
        self.rng = rng
        self.config = config
        self.center = center
        self.height = height
        self.spread = spread
        self.obstacles = obstacles
        inner = np.linalg.norm(canopy[:, :2] - center[:2], axis=1) < 0.35 * spread
        self.canopy = canopy[inner & (canopy[:, 2] > 0.08)]
        self.crown_top = center + CROWN_TOP_M * UP
        self.branches: list[np.ndarray] = []
        self.result = Placement([], [], [], [])

    # -- poses ---------------------------------------------------------------------------

    def _position(self, hidden: bool, radius: float) -> np.ndarray:
        rng = self.rng
        if hidden and len(self.canopy):
            above = self.canopy[rng.integers(len(self.canopy))]
            return above + np.array([rng.normal(0, 0.01), rng.normal(0, 0.01),
                                     -rng.uniform(0.015, 0.06)])
        reach = max(0.5 * self.spread - radius - 0.01, 0.06)
        r = reach * rng.uniform(0.3, 1.0)
        phi = rng.uniform(0.0, 2.0 * np.pi)
        z = self.height * rng.uniform(0.3, 1.0) - radius
        return self.center + np.array([r * np.cos(phi), r * np.sin(phi), z])

    def _normal(self, position: np.ndarray) -> np.ndarray:
        cfg, rng = self.config, self.rng
        offset = position[:2] - self.center[:2]
        outward = np.arctan2(offset[1], offset[0])
        weights = np.asarray(cfg.polar_bin_weights, np.float64)
        k = rng.choice(len(weights), p=weights / weights.sum())
        polar = rng.uniform(cfg.polar_bins_deg[k], cfg.polar_bins_deg[k + 1])
        azimuth = outward + np.radians(rng.normal(0.0, cfg.azimuth_spread_deg))
        return spherical(np.radians(polar), azimuth)

    # -- checks --------------------------------------------------------------------------

    def _organ_fits(self, points: np.ndarray, exclude: tuple[int, ...] = ()) -> bool:
        clearance = self.config.flower_clearance_m + SAMPLE_MARGIN_M
        return (points[:, 2].min() >= LOWEST_M
                and self.obstacles.clear(points, clearance, exclude=exclude))

    def _stem_fits(self, curve: np.ndarray, radius: float, own: np.ndarray | None) -> bool:
        """A stem's curved part keeps the clearance from every flower (and `own` samples)."""
        points = curve_samples(curve)
        reach = self.config.flower_clearance_m + SAMPLE_MARGIN_M + radius
        if points[:, 2].min() < radius + 0.002:
            return False
        if own is not None:
            nearest, _ = cKDTree(own).query(points, distance_upper_bound=reach)
            if np.isfinite(nearest).any():
                return False
        return self.obstacles.clear(points, reach, kinds=("flower",))

    # -- flowers -------------------------------------------------------------------------

    def _accept(self, local: LocalFlower, rotation: np.ndarray, center: np.ndarray,
                samples: np.ndarray, stems: list[tuple[np.ndarray, float]]) -> PlacedFlower:
        group = self.obstacles.add(samples, "flower")
        placed = PlacedFlower(len(self.result.flowers), local, rotation, center, group)
        self.result.flowers.append(placed)
        for path, radius in stems:
            self._add_stem(path, radius)
        return placed

    def _add_stem(self, path: np.ndarray, radius: float) -> None:
        verts, faces = tube(path, radius)
        colors = colours.tone_colors(self.rng, colours.PEDUNCLE, len(verts))
        self.result.stems.append(Piece.of(verts, faces, colors, Part.PEDUNCLE))
        self.obstacles.add(curve_samples(path), "stem", pad=radius)

    def _pedicel(self, local: LocalFlower, rotation: np.ndarray, center: np.ndarray,
                 branch: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        normal = rotation[:, 2]
        straight = local.radius + STRAIGHT_BEYOND_RADIUS_M - PEDICEL_ENTRY_M
        return _stem(branch, center - PEDICEL_ENTRY_M * normal, -normal, straight,
                     self._outward(branch))

    def _outward(self, point: np.ndarray) -> np.ndarray:
        """Horizontal unit vector from the plant axis through `point`."""
        offset = point[:2] - self.center[:2]
        if np.linalg.norm(offset) < 1e-6:
            return np.array([1.0, 0.0, 0.0])
        return np.array([*_unit(offset), 0.0])

    def _peduncle(self, branch: np.ndarray) -> np.ndarray:
        start = self.crown_top + 0.006 * self._outward(branch)
        chord = branch - start
        span = np.linalg.norm(chord)
        return cubic_bezier(start, start + 0.35 * chord + 0.1 * span * UP,
                            start + 0.7 * chord + 0.1 * span * UP, branch, 14)

    def _first(self, local: LocalFlower, samples_local: np.ndarray,
               hidden: bool) -> tuple[PlacedFlower, np.ndarray] | None:
        """The first flower of a new inflorescence, its pedicel and the main peduncle."""
        rng = self.rng
        for attempt in range(TRIES):
            center = self._position(hidden and attempt < TRIES // 2, local.radius)
            normal = self._normal(center)
            rotation = frame(normal, rng.uniform(0.0, 2.0 * np.pi))
            samples = samples_local @ rotation.T + center
            if not self._organ_fits(samples):
                continue
            behind = center - (local.radius + STRAIGHT_BEYOND_RADIUS_M) * normal
            if behind[2] < 0.01:
                continue
            branch = self.crown_top + (behind - self.crown_top) * rng.uniform(0.35, 0.6)
            branch[:2] += rng.normal(0.0, 0.01, 2)
            branch[2] = max(branch[2], 0.03)
            pedicel, curve = self._pedicel(local, rotation, center, branch)
            peduncle = self._peduncle(branch)
            if not (self._stem_fits(curve, PEDICEL_RADIUS_M, samples)
                    and self._stem_fits(peduncle, PEDUNCLE_RADIUS_M, samples)):
                continue
            placed = self._accept(local, rotation, center, samples,
                                  [(peduncle, PEDUNCLE_RADIUS_M), (pedicel, PEDICEL_RADIUS_M)])
            self.branches.append(branch)
            return placed, branch
        return None

    def _sibling(self, local: LocalFlower, samples_local: np.ndarray, first: PlacedFlower,
                 branch: np.ndarray) -> PlacedFlower | None:
        """Another flower of an inflorescence, a few centimetres from its first flower."""
        rng = self.rng
        for _ in range(TRIES):
            direction = _unit(rng.normal(size=3) * np.array([1.0, 1.0, 0.5]))
            center = first.center + rng.uniform(0.03, 0.07) * direction
            if np.linalg.norm(center[:2] - self.center[:2]) > 0.5 * self.spread:
                continue
            normal = self._normal(center)
            rotation = frame(normal, rng.uniform(0.0, 2.0 * np.pi))
            placed = self._try_pose(local, samples_local, rotation, center, branch, ())
            if placed is not None:
                return placed
        return None

    def _try_pose(self, local: LocalFlower, samples_local: np.ndarray, rotation: np.ndarray,
                  center: np.ndarray, branch: np.ndarray,
                  exclude: tuple[int, ...]) -> PlacedFlower | None:
        samples = samples_local @ rotation.T + center
        if not self._organ_fits(samples, exclude):
            return None
        pedicel, curve = self._pedicel(local, rotation, center, branch)
        if not self._stem_fits(curve, PEDICEL_RADIUS_M, samples):
            return None
        return self._accept(local, rotation, center, samples, [(pedicel, PEDICEL_RADIUS_M)])

    def _touching(self, local: LocalFlower, samples_local: np.ndarray, partner: PlacedFlower,
                  branch: np.ndarray) -> PlacedFlower | None:
        """A flower whose rim touches `partner`'s rim with a gap of `touch_gap_m`."""
        rng, gap = self.rng, self.config.touch_gap_m
        partner_tree = cKDTree(surface_samples(partner.local.piece, TOUCH_SPACING_M, rng)
                               @ partner.rotation.T + partner.center)
        dense = surface_samples(local.piece, TOUCH_SPACING_M, rng)
        spread = np.radians(self.config.cluster_normal_spread_deg)
        for _ in range(TRIES):
            toward = _perpendicular(rng, partner.normal)
            tilt = rng.uniform(0.0, spread)
            normal = (np.cos(tilt) * partner.normal
                      + np.sin(tilt) * _perpendicular(rng, partner.normal))
            rotation = frame(normal, rng.uniform(0.0, 2.0 * np.pi))
            away = _unit(toward - (toward @ normal) * normal)
            base = (partner.center + partner.local.radius * toward
                    + partner.local.rim_height * partner.normal
                    + local.radius * away - local.rim_height * normal)
            moved = dense @ rotation.T + base

            def clear(s: float, reach: float, moved: np.ndarray = moved,
                      toward: np.ndarray = toward) -> bool:
                nearest, _ = partner_tree.query(moved + s * toward, distance_upper_bound=reach)
                return not np.isfinite(nearest).any()

            low, high = -0.5 * min(local.radius, partner.local.radius), local.radius
            if clear(low, gap) or not clear(high, gap):
                continue
            # The gap grows as the flower slides away along `toward`: bisect for the
            # position where it first reaches `gap`.
            for _ in range(12):
                mid = 0.5 * (low + high)
                low, high = (low, mid) if clear(mid, gap) else (mid, high)
            if clear(high, gap + 0.001):
                continue
            placed = self._try_pose(local, samples_local, rotation, base + high * toward, branch,
                                    (partner.group,))
            if placed is not None:
                return placed
        return None

    def place_flowers(self, count: int) -> None:
        """Place `count` open flowers on inflorescences of 1-3 (fewer only if no room)."""
        rng, cfg = self.rng, self.config
        weights = np.asarray(cfg.flowers_per_inflorescence_weights, np.float64)
        for _ in range(4 * count):
            remaining = count - len(self.result.flowers)
            if remaining <= 0:
                return
            size = min(int(rng.choice(3, p=weights / weights.sum())) + 1, remaining)
            local = open_flower(rng, cfg)
            samples_local = surface_samples(local.piece, SAMPLE_SPACING_M * 0.8, rng)
            placed = self._first(local, samples_local, rng.random() < cfg.hidden_probability)
            if placed is None:
                continue
            first, branch = placed
            previous = first
            for _ in range(size - 1):
                local = open_flower(rng, cfg)
                samples_local = surface_samples(local.piece, SAMPLE_SPACING_M * 0.8, rng)
                sibling = None
                if rng.random() < cfg.cluster_probability:
                    sibling = self._touching(local, samples_local, previous, branch)
                    if sibling is not None:
                        self.result.touching.append((previous.id, sibling.id))
                if sibling is None:
                    sibling = self._sibling(local, samples_local, first, branch)
                if sibling is not None:
                    previous = sibling

    # -- distractors ---------------------------------------------------------------------

    def place_distractors(self) -> None:
        """Place the config's buds and fruit on existing inflorescences (or new ones)."""
        rng, cfg = self.rng, self.config
        kinds = (["bud"] * int(rng.integers(cfg.buds[0], cfg.buds[1] + 1))
                 + ["fruit"] * int(rng.integers(cfg.fruit[0], cfg.fruit[1] + 1)))
        for kind in kinds:
            local = bud(rng) if kind == "bud" else fruit(rng, cfg)
            samples_local = surface_samples(local.piece, SAMPLE_SPACING_M, rng)
            for _ in range(TRIES):
                if self.branches:
                    branch = self.branches[rng.integers(len(self.branches))]
                else:
                    branch = self._position(False, 0.01)
                    branch[2] = max(0.5 * branch[2], 0.03)
                if kind == "bud":
                    direction = _unit(rng.normal(size=3) + np.array([0.0, 0.0, 1.0]))
                    center = branch + rng.uniform(0.02, 0.05) * direction
                    axis = _unit(direction + rng.normal(0.0, 0.3, 3))
                else:
                    center = branch + np.array([*rng.normal(0.0, 0.02, 2), -rng.uniform(0.0, 0.04)])
                    axis = spherical(np.radians(rng.uniform(0.0, 50.0)), rng.uniform(0, 2 * np.pi))
                rotation = frame(axis, rng.uniform(0.0, 2.0 * np.pi))
                samples = samples_local @ rotation.T + center
                clearance = cfg.flower_clearance_m + SAMPLE_MARGIN_M
                if (samples[:, 2].min() < LOWEST_M
                        or not self.obstacles.clear(samples, clearance, kinds=("flower",))
                        or not self.obstacles.clear(samples, SAMPLE_MARGIN_M,
                                                    kinds=("leaf", "distractor"))):
                    continue
                path, curve = _stem(branch, center, rotation @ local.stem_dir, 0.006,
                                    self._outward(branch))
                if not self._stem_fits(curve, PEDICEL_RADIUS_M, None):
                    continue
                if not self.branches:
                    peduncle = self._peduncle(branch)
                    if not self._stem_fits(peduncle, PEDUNCLE_RADIUS_M, None):
                        continue
                    self._add_stem(peduncle, PEDUNCLE_RADIUS_M)
                    self.branches.append(branch)
                self.obstacles.add(samples, "distractor")
                self.result.distractors.append(local.piece.moved(rotation, center))
                self._add_stem(path, PEDICEL_RADIUS_M)
                if kind == "bud":
                    self.result.buds += 1
                else:
                    self.result.fruit += 1
                break
