"""Limits sized to the cloud: the settings stated in metres and in points, made to hold for
the cloud at hand (DESIGN.md, "The operating envelope").

Two measurements of the cloud size them:

- **its flowers' radius**: the limits stated in metres (`ClusterConfig.eps` and the other
  lengths of the cluster stage, `OutlierConfig.radius_m`) hold for flowers of
  `cluster.size_band_m`; a cloud whose flowers measure outside the band (another unit, a
  phone scan's own scale, bigger or smaller flowers) has them multiplied by its flowers'
  radius over the band's nearer edge (`limit_scale`, `sized_to_band`);
- **its point density**: the median surface area a flower-coloured candidate point stands
  for (`area_per_point`). The point counts (`cluster.min_points`, `pistil_min_points`,
  `outliers.radius_points`, `pose.base_min_points`, `support_min_points`) hold for clouds
  with at least `cluster.density_reference` points within `eps` of such a point; a sparser
  cloud has them multiplied by its density over that, never below `COUNT_FLOORS`
  (`sized_count`). Lengths that must span several points (a surface link, the crop
  margin, the pistil's DBSCAN radius) are at least `SPACING_FLOORS` point spacings.

Counts are never raised for a denser cloud: the stated ones are the paper's, and more
points only make a flower easier to find. The settings that own the limits apply this
module's rules to themselves: `cluster_config.for_cloud` (the outlier and cluster
settings) and `pose.pose_for_density` (the pose stage's counts).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
from scipy.spatial import cKDTree

#: Neighbours of the k-nearest-neighbour estimate of the surface area each point stands for.
AREA_NEIGHBOURS = 8

#: Least value of each point count however sparse the cloud, and why. DBSCAN's core count
#: on a surface: 4, Ester et al.'s rule for two-dimensional data (2 x dimension). A radius
#: outlier needs 2 neighbours: one would keep isolated pairs. A pistil of 2 points: a
#: receptacle seen as a handful of points at 50 points a flower. The petal base needs 3
#: points for a centroid that is not one point's noise. The sepals that sign a flower
#: without a pistil need 5: on the authors' plant 3 thinned to 3-10 % (5 seeded repeats),
#: such flowers signed by 3 or 4 green points were turned over 4 times in 16, by 5 or more
#: once in 20 (a leaf beside a flower is of the sepals' colour).
COUNT_FLOORS = {"min_points": 4, "radius_points": 2, "pistil_min_points": 2,
                "base_min_points": 3, "support_min_points": 5}

#: Least length of each limit in point spacings (the square root of the area a point
#: stands for), and why: DBSCAN's radius and the radius outlier's must hold about
#: 2.5^2 pi = 20 points of a surface to count 4; the geodesic split's link joins a point
#: to its neighbours on the surface (twice the spacing, as the setting says); the pistil's
#: DBSCAN radius joins a receptacle's few points (1.5); the crop margin takes in the ring
#: of points round a cluster (1).
SPACING_FLOORS = {"eps": 2.5, "radius_m": 2.5, "split_link_m": 2.0, "pistil_eps": 1.5,
                  "crop_margin_m": 1.0}


#: Most points whose neighbours a density estimate looks at (an even subsample: the median
#: of 1,000 is within a few per cent of the whole's).
DENSITY_SAMPLE = 1000


def area_per_point(points: np.ndarray, neighbours: int = AREA_NEIGHBOURS,
                   tree: cKDTree | None = None) -> float | None:
    """The median surface area one point of a sampled surface stands for, pi r_k^2 / k with
    r_k the distance to its k-th neighbour (over DENSITY_SAMPLE of the points, evenly
    chosen): the inverse of the surface's point density. points: (N, 3), any unit; the
    result in that unit squared, None for fewer than 2 points; `tree`: their KD-tree, if
    made. Position noise comparable to r_k inflates it (the points fill a slab, not a
    surface): `surface_area_per_point` counts at a radius that spans the noise."""
    if len(points) < 2:
        return None
    k = min(neighbours, len(points) - 1)
    tree = cKDTree(points) if tree is None else tree
    reach = tree.query(_sample(points), k=k + 1)[0][:, -1]
    return float(np.median(np.pi * reach ** 2 / k))


def _sample(points: np.ndarray) -> np.ndarray:
    return points[::max(1, len(points) // DENSITY_SAMPLE)]
#: ... at a radius of at least this many k-nearest-neighbour spacings.
DENSITY_RADIUS_SPACINGS = 2.5


def surface_area_per_point(points: np.ndarray, radius: float) -> float | None:
    """The area a point of a sampled surface stands for, counted at a surface scale: pi R^2
    over the median number of points within R of a point, R the larger of `radius` and
    DENSITY_RADIUS_SPACINGS k-nearest-neighbour spacings. Unlike the k-nearest-neighbour
    estimate at the scale of one spacing (`area_per_point`), position noise thinner than
    R does not change it: what lies within R is the same surface, thickened. points: (N, 3),
    any unit; None for fewer than 2 points."""
    if len(points) < 2:
        return None
    tree = cKDTree(points)
    nearest = area_per_point(points, tree=tree)
    reach = max(radius, DENSITY_RADIUS_SPACINGS * float(np.sqrt(nearest)))
    counts = tree.query_ball_point(_sample(points), reach, return_length=True)
    return float(np.pi * reach ** 2 / max(float(np.median(counts)), 1.0))


def limit_scale(typical: float | None, band: tuple[float, float] | None) -> float:
    """What the metric limits are multiplied by for flowers of this typical radius: the
    radius over the band's nearer edge outside the band, 1 inside it (or without a band or
    a measured radius)."""
    if band is None or typical is None:
        return 1.0
    low, high = band
    return typical / high if typical > high else typical / low if typical < low else 1.0


@dataclass(frozen=True)
class Density:
    """How a cloud's density sized the count limits."""

    spacing: float | None
    """Square root of the area a flower-coloured candidate point stands for (the cloud's
    unit; None: too few points to measure)."""
    neighbours: float | None
    """Points within the applied `eps` of such a point on its surface (pi eps^2 / area)."""
    factor: float
    """What the point counts were multiplied by (1: as stated)."""


def measured_density(eps: float, spacing: float | None, reference: float | None) -> Density:
    """How a cloud of this point `spacing` sizes the counts stated for `reference` points
    within `eps` of a point (`ClusterConfig.density_reference`; eps and spacing in one
    unit): the factor is the neighbours within eps over the reference, at most 1."""
    if spacing is None or reference is None or spacing <= 0:
        return Density(spacing, None, 1.0)
    neighbours = np.pi * eps ** 2 / spacing ** 2
    return Density(spacing, float(neighbours), float(min(1.0, neighbours / reference)))


def sized_count(stated: int, name: str, density: Density) -> int:
    """A point count sized to the density: stated x factor, at least its floor (or the
    stated count, where that is lower), rounded."""
    if density.factor >= 1.0 or stated == 0:
        return stated
    return int(max(min(stated, COUNT_FLOORS[name]), round(stated * density.factor)))


#: Most times the limits are re-sized to a cloud's flowers, each at the typical radius and
#: point spacing the grouping before measured on them.
SIZE_PASSES = 3
#: Point spacings within this ratio of each other size the counts alike (no regrouping).
SPACING_TOLERANCE = 1.15

Result = TypeVar("Result")


@dataclass(frozen=True)
class Sizing:
    """What a stage's limits are sized to: its flowers' size and its points' spacing."""

    scale: float
    """The metric limits' factor (`limit_scale`)."""
    spacing: float | None
    """The point spacing the counts and spacing floors follow (None: as stated)."""

    def close_to(self, other: Sizing) -> bool:
        if not np.isclose(self.scale, other.scale, rtol=1e-3):
            return False
        if self.spacing is None or other.spacing is None:
            return self.spacing is other.spacing
        ratio = self.spacing / other.spacing
        return 1 / SPACING_TOLERANCE <= ratio <= SPACING_TOLERANCE


def sized_to_cloud(run: Callable[[Sizing], tuple[Result, float | None, float | None]],
                   band: tuple[float, float] | None,
                   spacing: Callable[[], float | None] = lambda: None
                   ) -> tuple[Sizing, Result, float | None]:
    """`run(sizing)` (a stage at its limits sized so, returning its result, the flower
    radius it measured and the point spacing of the flowers it found) at the limits as
    stated (or, where that finds no flower, at the whole cloud's `spacing()`: a sparse
    cloud), then again at what its flowers measured: the scale their radius asks for
    (`limit_scale`) and their own spacing (a cloud's flowers are sampled more densely than
    the specks of flower colour round them, which the whole cloud's spacing counts too),
    up to SIZE_PASSES times; a rerun that finds no flower keeps the run before. Returns
    the sizing, the result and its radius."""
    sizing = Sizing(1.0, None)
    result, size, measured = run(sizing)
    whole = spacing() if size is None else None
    if whole is not None:
        sizing = Sizing(1.0, whole)
        result, size, measured = run(sizing)
    for _ in range(SIZE_PASSES):
        wanted = Sizing(limit_scale(size, band), measured if measured is not None
                        else sizing.spacing)
        if wanted.close_to(sizing):
            break
        resized, resized_size, resized_spacing = run(wanted)
        if resized_size is None:
            break
        sizing, result, size, measured = wanted, resized, resized_size, resized_spacing
    return sizing, result, size
