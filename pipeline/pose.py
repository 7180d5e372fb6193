"""Per-flower pose: split a flower crop into petals and pistil, fit three surfaces, orient them.

A flower normal is a unit vector from the flower centre along the axis the corolla opens
toward (away from the peduncle), in the crop's frame (the bed frame: metres, z up).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Literal

import numpy as np

from flowerpose.cloudio import Cloud
from flowerpose.config import require
from flowerpose.errors import InputError
from flowerpose.pipeline.cluster_config import ClusterConfig
from flowerpose.pipeline.colour import (
    ColourConfig,
    petal_mask,
    pistil_mask,
    rgb_to_hsv,
    support_mask,
)
from flowerpose.pipeline.fit import (
    EXPONENT_BOUNDS,
    MAX_EVALUATIONS,
    MAX_FLATNESS,
    MIN_FIT_POINTS,
    SIZE_BOUNDS,
    FitInit,
    fit_paraboloid,
    fit_plane,
    fit_superellipsoid,
    principal_axes,
)
from flowerpose.pipeline.limits import Density, sized_count
from flowerpose.pipeline.methods import METHODS
from flowerpose.pipeline.segment import corolla, the_pistil

DirectionReference = Literal["combined", "crop", "petal_base", "petal_surface"]


@dataclass
class PoseConfig:
    """Per-flower pose estimation: colour split, pistil clustering, surface fits, direction."""

    petal_max_radius: float | None = 1.5
    """Petal points lie within this many typical flower radii of the pistil centroid; None:
    no limit. The typical radius comes from the data (the cluster stage's median corolla
    radius over the cloud's flowers, or the crop's own), never from a flower size assumed
    in metres. Deviation: upstream fitted every petal-coloured point of the crop, so the
    pale peduncle under a flower and the petals of a touching neighbour tilted the fits.
    This was 20 mm, which cut the rims of the authors' 40-50 mm flowers (1.5 radii is
    about 34 mm there, 19 mm on the realistic synthetic plants). It matters where a crop
    holds leaves: crops boxed round plant 3's labels from its candidates, 7.49 degrees
    with the limit, 12.82 without (`--set pose.petal_max_radius=none`); after clustering
    the candidates or a synthetic cloud it changes nothing measurable (README)."""
    petal_trim_factor: float | None = 3.0
    """Petal points farther from the petals' least-squares plane than this many times their
    median distance (and than `petal_trim_min`) are dropped, twice: what is left of a
    stem or a leaf edge inside `petal_max_radius` lies off the corolla. None: no trim."""
    petal_trim_min: float = 0.25
    """The trim never drops points nearer the plane than this many typical flower radii (a
    cupped corolla's rim rises up to half a radius above its base)."""
    direction_reference: DirectionReference = "combined"
    """What orients the normals, given a pistil. "crop" (upstream): the pistil against the
    centroid of the whole crop, which a cupped corolla lifts above the receptacle and so
    flips the normal. "petal_base": against the petal points round the pistil, which the
    receptacle protrudes from whether the petals cup up or curl down. "petal_surface":
    against the petal surface extended to the pistil axis by a paraboloid fit. "combined"
    (default): the sum of four offsets along the axis, each a vote (`_combined`): the
    pistil above the petal surface extended to it, above the crop's centroid near it,
    above its own petals' centroid (`petal_vote`), and the petals above the sepals and
    stems behind them.
    Each fails somewhere: on real photogrammetry the receptacle often does not protrude
    from the petals, so the petal surface alone flips normals of the authors' plant 3;
    the crop centroid and the petals' flip cupped flowers; sepals are often missing, and
    leaves near a flower are of their colour. Plane error, petal surface / crop / combined
    (`flowerpose eval --source real paper-plant-3 --set
    pose.direction_reference=...`): 36.3 / 21.3 / 7.35 degrees (two and one flipped
    normals); hard oracle preset, 10 plants: 2.58 / 5.99 / 2.58; realistic: 1.93 all."""
    offset_clip: float | None = 0.15
    """"combined": each of the three offsets counts at most this many corolla radii either
    way (about a receptacle's protrusion, and the offsets' typical size), so one pulled far
    off (a crop centroid dragged by a neighbour's petals in front of the flower) is one
    vote, not a veto. Measured on reconstructed scans (226 matched flowers): a crop offset
    of 0.45 radii the wrong way outvoted the other two and flipped a flower; clipped at
    0.15, no flip there and none added on the oracle, hard, field or real data; at 0.07
    the hard preset lost 3. None: no clip."""
    crop_reach: float | None = 1.0
    """"combined": the crop's centroid is taken over its points within this many corolla
    radii of the pistil (the receptacle, sepals and petal base), so a leaf above or beside
    the flower that its crop took in does not vote. None: the whole crop (upstream's
    rule). On a full-loop reconstruction (`eval --suite scan-3`, seed 0) a leaf above a
    face-up flower pulled both the whole crop's centroid and the support offset the wrong
    way and flipped it; at 1.0 it is right. The oracle, hard and field presets (at their
    own densities and fixed at 116 and 706 points a flower) and the authors' plant 3 with
    its thinned copies score the same either way."""
    up_prior: float = 0.2
    """"combined", in a bed frame only (a whole plant's cloud, z up; never for candidates
    or crops, whose frame is arbitrary): the bed's up direction counts as this many corolla
    radii of evidence times the cosine of the axis with up (to `up_prior_power`). It
    decides only where the flower's own offsets are weaker: a flat flower facing the
    cameras above it, whose receptacle a reconstruction flattened into the petals and
    whose underside it never saw. Measured on reconstructed
    scans (209 matched flowers): the four flipped normals were such flowers, facing within
    8 degrees of up, with offsets of 0.04 to 0.2 radii the wrong way; correct normals of
    downward-facing flowers (hard oracle preset, 150 flowers) had at least 0.22 radii of
    evidence. 0: no prior."""
    up_prior_power: float = 3.0
    """The up prior's weight falls with the axis's tilt from vertical as the cosine to this
    power. The flowers it is for face the cameras above them; a tilted flower shows its
    side to the scan, and its own offsets decide. Measured on the `field` preset (10
    plants, seed 0: the field-10 suite and the same plants fixed at 116 and 706 points a
    flower, 400 flowers): 7 flipped normals with the plain cosine (power 1), 5 with the
    prior cut off beyond 25 degrees of vertical, 2 at power 3; the hard preset (151
    flowers, many facing down) and oracle-10 unchanged. 1: the plain cosine."""
    pistil_core: float | None = 0.3
    """"combined" and `pistil_max_height`: the pistil's position is that of its core, the
    pistil points within this many corolla radii (about a receptacle's radius) across the
    petals' axis of the pistil point nearest that axis, so a yellowish stalk joined to the
    receptacle in one pistil cluster does not drag it behind the petals. On the authors'
    plant 3 thinned to 20 %, one flower's pistil cluster ran 22 mm out and 10 mm back
    along its stalk and flipped its normal (170 degrees); with the core, 10.3. The oracle,
    hard and field presets score the same either way. None: the whole pistil cluster."""
    pistil_max_height: float | None = 0.5
    """The pistil (its core, `pistil_core`) lies within this many corolla radii of its
    petals' centroid along their plane's axis, either way: the receptacle sits in the
    corolla. A pistil-coloured cluster farther off is a yellowed sepal or stem behind the
    flower or something in front of it, neither its pistil nor its support: the flower is
    posed as one without a pistil (its centre the petals', its sign the sepals'), which on a
    cloud dense enough to need a pistil (`cluster.require_pistil`) is no flower. The radii
    are the 90th percentile distance of the petals from the pistil, as "combined" measures
    them. Measured on 981 flowers (the guard battery's scan, oracle, field and hard entries,
    591; the authors' plant 3 as it is, thinned to 50-3 % and cut by a quarter and a half, 5
    repeats, 390): every pistil of a rightly signed flower lay between 0.09 radii below and
    0.43 above its petals' centroid, and the one pistil beyond 0.45, two dark yellow-green
    points 0.61 radii behind the petals of a flower thinned to 3 %, flipped its normal (155
    degrees; 24.5 without that pistil, as the published method). No other flower of the 981
    moved. None: any pistil is taken (upstream)."""
    base_radius_factor: float = 1.5
    """Petal points within this many pistil radii of the pistil centroid form the petal
    base ("petal_base" reference, and "petal_surface" where too few petals are left); the
    pistil radius is the 90th percentile distance of its
    points from their centroid, the stamen ring included. At 2.0 the base reached the rim of
    a strongly cupped flower with a low receptacle and flipped it (hard preset, seeds 0-9:
    plane mean 4.12 at 2.0, 2.94 at 1.5; realistic unchanged: `flowerpose sweep --preset
    hard --grid pose.base_radius_factor=2.0,1.5,1.2,1.0 --plants 10`)."""
    base_min_points: int = 10
    """Fewest petal base points: when fewer lie within the radius, the nearest this many."""
    support_min_points: int = 10
    """Fewest sepal or peduncle points that may orient the normals (without a pistil, or
    as the third offset of "combined"); without a pistil and with fewer, every normal is
    None."""
    support_reach: float = 0.75
    """"combined": sepal and stem points count within this many corolla radii of the
    pistil along the axis (and one across it): a leaf 15 mm above an upward flower of a
    photogrammetry plant is not its support."""
    support_from_cloud: bool = True
    """The support vote ("combined"'s, and a flower's without a pistil) also takes the sepal
    and stem points of the cloud round the flower that its crop left out (within the same
    reach; `estimate_pose`'s `support_round`). A crop is the points within
    `cluster.crop_margin_m` of the flower's cluster, and on a sparse cloud the cluster
    shrinks to the corolla and its crop leaves out the sepals behind it: on the authors'
    plant 3 thinned to 7 %, one flower's crop held no sepal point where the cloud round it
    held 19-26 (a quarter radius behind the petals), and a two-point pistil below the petal
    surface flipped it (166 degrees). A flower without a pistil reads them too (within the
    same reach of its petals' centroid): on plant 3 thinned to 10-3 % (5 repeats), 15 such
    flowers whose crops held too few sepal points had no normal and were dropped; they are
    found now, their normals flagged uncertain, none flipped. False: the crop's points only
    (`pose_crops` has no cloud round its crops)."""
    plane_robust_iterations: int = 5
    """Reweighted refits of the plane (Tukey's biweight, from the least-median plane;
    `fit.fit_plane`); 0: the paper's plain least-squares plane. On two full-loop runs of
    `eval --suite scan-3` (6 reconstructions, 64 flowers) the least-median start took the
    plane mean from 7.17 to 2.95 degrees: three flowers whose crops held a leaf's sheen
    above or a stem below were 55-166 degrees off, none over 20 after."""
    plane_min_scale: float = 0.35
    """The robust plane's reweighting never drops petal points nearer the plane than this
    many typical flower radii (`fit.fit_plane`'s `min_scale`): about the cut-off a clean
    corolla's 1 mm surface noise gives anyway (4.7 x 1 mm of a 13 mm radius). The cut-off
    otherwise follows the points' own spread about the plane, which on a sparse corolla
    is a few points' and drops whole petals of a cupped flower: on the authors' plant 3
    thinned to 5 %, one flower's plane was 18 degrees off where the plain plane was 4
    (10 at 0.35). A leaf or stem a radius or more off still goes. At 0.5 the field preset
    (`flowerpose guard`'s field-10) was worse by 0.3 degrees [0.1, 0.6] on 123 flowers;
    at 0.35, +0.1 [-0.1, 0.3]. 0: the cut-off follows the spread alone."""
    min_fit_points: int = MIN_FIT_POINTS
    """Fewest petal points a fit accepts; with fewer it gives None."""
    max_fit_points: int = 400
    """Most petal points the superellipsoid and paraboloid fits use (a seeded random
    subsample above this, for speed; the plane always uses all)."""
    seed: int = 0
    """Seed of the petal subsample."""
    superellipsoid_init: FitInit = "pca"
    """Superellipsoid start: "pca" (deviation: rotation and half-axes from the petals'
    principal axes) or "upstream" (5 mm half-axes along the bed axes, which the paper
    found stuck in local minima)."""
    paraboloid_init: FitInit = "pca"
    """Paraboloid start: "pca" (deviation: the petals' principal axes) or "upstream" (the
    frame's own axes at the petal centroid)."""
    superellipsoid_size_bounds: tuple[float, float] = SIZE_BOUNDS
    """Bounds (metres) of the half-axes a, b, c. Upstream's lower bound is 0, which divides
    by zero; 0.1 m reflects real flowers."""
    superellipsoid_exponent_bounds: tuple[float, float] = EXPONENT_BOUNDS
    """Bounds of the shape exponents e1, e2 (the paper's)."""
    superellipsoid_max_flatness: float = MAX_FLATNESS
    """Largest ratio of the half-axis across the petals to the lesser one along them, at
    the "pca" start (deviation: upstream bounds only by 0.1 m). A corolla is flatter than
    wide; unbounded, a fit with a centre prefers a cap of a long ellipsoid whose shortest
    axis lies in the petal plane."""
    axis_through_pistil: bool = True
    """Make the superellipsoid and paraboloid axes pass through the pistil centroid when a
    pistil is found, leaving free only the centre's (vertex's) position along the axis
    (deviation: upstream fixes it at the petal centroid). A sideways shift of a shallow
    cap mimics a tilt, so with a free 3-D centre the axes of a clean 3 mm cup are off by
    1.6 degrees on average and up to 4 (0.15 through a point on the axis)."""
    max_evaluations: int = MAX_EVALUATIONS
    """Most residual evaluations one nonlinear fit may spend."""
    petal_vote: float = 0.5
    """"combined": the weight of the fourth vote, the pistil above its own petals'
    centroid (the other three count 1). It holds on thinned and partly seen real flowers,
    where the surface's extrapolation and the sepals (a leaf of their colour beside the
    flower) each turn; like the crop's centroid it is wrong for a strongly cupped corolla,
    whose rim rises past the receptacle, so it counts half. Axes turned, on the authors'
    plant 3 thinned to 50-3 % and cut by a quarter and a half (5 seeded repeats, 389
    flowers with a pistil) / the oracle, field, hard and reconstructed synthetic flowers
    (743) / 48 drawn test flowers, cupped, curled and facing down: 6 / 0 / 8 at weight 0,
    3 / 0 / 8 at 0.5, 2 / 0 / 9 at 1 (and more near ties on the test flowers)."""
    uncertain_margin: float = 0.05
    """A flower whose "combined" votes sum to less than this many corolla radii either way
    is `uncertain`: its sign is a near tie."""
    uncertain_pistil_points: int = 3
    """A flower whose pistil (its core) has fewer points than this, or none (its sepals
    sign it), is `uncertain`: a speck of yellow or a few green points decided it."""

    def __post_init__(self):
        require(self.petal_max_radius is None or self.petal_max_radius > 0,
                "pose.petal_max_radius", "must be positive (flower radii) or unset")
        require(self.petal_trim_factor is None or self.petal_trim_factor > 0,
                "pose.petal_trim_factor", "must be positive or unset")
        require(self.petal_trim_min >= 0, "pose.petal_trim_min", "must be 0 or more (flower radii)")
        for name in ("base_min_points", "support_min_points"):
            require(getattr(self, name) >= 1, f"pose.{name}", "must be at least 1")
        require(self.base_radius_factor > 0, "pose.base_radius_factor", "must be positive")
        require(self.support_reach > 0, "pose.support_reach", "must be positive")
        require(self.plane_min_scale >= 0, "pose.plane_min_scale",
                "must be 0 or more (flower radii)")
        require(self.up_prior >= 0, "pose.up_prior", "must be 0 or more (corolla radii)")
        require(self.up_prior_power >= 0, "pose.up_prior_power", "must be 0 or more")
        require(self.crop_reach is None or self.crop_reach > 0, "pose.crop_reach",
                "must be positive (corolla radii) or unset")
        require(self.pistil_core is None or self.pistil_core > 0, "pose.pistil_core",
                "must be positive (corolla radii) or none")
        require(self.pistil_max_height is None or self.pistil_max_height > 0,
                "pose.pistil_max_height", "must be positive (corolla radii) or unset")
        require(self.offset_clip is None or self.offset_clip > 0, "pose.offset_clip",
                "must be positive (corolla radii) or unset")
        require(self.plane_robust_iterations >= 0, "pose.plane_robust_iterations",
                "must be 0 or more")
        require(3 <= self.min_fit_points <= self.max_fit_points, "pose.max_fit_points",
                "needs 3 <= pose.min_fit_points <= pose.max_fit_points")
        require(self.max_evaluations >= 1, "pose.max_evaluations", "must be at least 1")
        require(self.petal_vote >= 0, "pose.petal_vote", "must be 0 or more")
        require(self.uncertain_margin >= 0, "pose.uncertain_margin",
                "must be 0 or more (corolla radii)")
        require(self.uncertain_pistil_points >= 0, "pose.uncertain_pistil_points",
                "must be 0 or more")


def pose_for_density(pose: PoseConfig, density: Density) -> PoseConfig:
    """The pose settings with their point counts sized to the cloud's density."""
    if density.factor == 1.0:
        return pose
    return replace(pose, base_min_points=sized_count(pose.base_min_points, "base_min_points",
                                                     density),
                   support_min_points=sized_count(pose.support_min_points, "support_min_points",
                                                  density))


@dataclass
class FlowerPose:
    """One flower's pose.

    center: (3,) float64, metres, crop frame: the flower centre on its axis. With a pistil
    it is the pistil centroid, which sits on the axis a little (about half the receptacle's
    height) above the petal base; else the petal centroid; else the crop centroid.
    normals: per method in METHODS, a unit (3,) float64 normal, or None when that fit
    failed or nothing could orient it.
    """

    center: np.ndarray
    normals: dict[str, np.ndarray | None]
    pistil_found: bool
    n_points: int
    n_petal_points: int
    orientation_margin: float | None = None
    """How clearly the votes that sign the normals decided ("combined": their sum's size in
    corolla radii); None where another rule signed them."""
    uncertain: bool = False
    """The normals' sign cannot be trusted (`PoseConfig.uncertain_margin`): the
    pollination planner leaves such a flower alone unless told otherwise."""

    def to_json(self) -> dict[str, Any]:
        """The DESIGN.md flowers.json entry fields, as plain lists, numbers and None."""
        return {
            "center": [float(v) for v in self.center],
            "normals": {m: None if n is None else [float(v) for v in n]
                        for m, n in self.normals.items()},
            "points": self.n_points,
            "petal_points": self.n_petal_points,
            "pistil_found": self.pistil_found,
            "orientation_margin": (None if self.orientation_margin is None
                                   else round(float(self.orientation_margin), 4)),
            "uncertain": self.uncertain,
        }


@dataclass(frozen=True)
class CropColours:
    """A crop's colour classes by the colour model, each (N,) bool, found once per crop."""

    petal: np.ndarray
    pistil: np.ndarray
    """Pistil-coloured points (candidates; `the_pistil` picks the pistil among them)."""
    support: np.ndarray

    @classmethod
    def of(cls, crop: Cloud, colour: ColourConfig) -> CropColours:
        hsv = rgb_to_hsv(crop.colors)
        return cls(petal_mask(hsv, colour), pistil_mask(hsv, colour), support_mask(hsv, colour))


def _split(points: np.ndarray, colours: CropColours,
           cluster: ClusterConfig) -> tuple[np.ndarray, np.ndarray]:
    pistil = np.zeros(len(points), dtype=bool)
    chosen = the_pistil(points, colours.petal, colours.pistil, cluster)
    if chosen is not None:
        pistil[chosen] = True
    return colours.petal, pistil


def split_petals_pistil(crop: Cloud, colour: ColourConfig,
                        cluster: ClusterConfig) -> tuple[np.ndarray, np.ndarray]:
    """Petal and pistil masks of a flower crop by colour; the pistil picked by DBSCAN.

    The pistil is the candidate cluster (`pistil_clusters`) whose centroid is nearest the
    petal centroid (the crop centroid when there are no petal points). crop: points (N, 3)
    metres, colors (N, 3) uint8. Returns (petal_mask, pistil_mask), both (N,) bool;
    pistil_mask is all False when no candidate cluster exists.
    """
    return _split(crop.points, CropColours.of(crop, colour), cluster)


@dataclass(frozen=True)
class Orientation:
    """What signs a flower's normals, and how surely."""

    reference: np.ndarray
    """A vector (the crop's frame and unit) the normals must agree with."""
    margin: float | None
    """"combined": the votes' sum, corolla radii (`_combined`); None for another reference
    or without a pistil."""
    pistil_points: int
    """The pistil points (its core, for "combined") behind it; 0 without a pistil."""

    def uncertain(self, config: PoseConfig) -> bool:
        """Whether the sign cannot be trusted (`PoseConfig.uncertain_margin`)."""
        return (self.pistil_points < config.uncertain_pistil_points
                or (self.margin is not None and self.margin < config.uncertain_margin))


def _orientation(crop: Cloud, petal: np.ndarray, pistil: np.ndarray,
                 plane: np.ndarray | None, config: PoseConfig,
                 colours: CropColours, up: np.ndarray | None,
                 support_round: np.ndarray | None) -> Orientation | None:
    """What the normals must agree with (`Orientation`), or None if nothing is known.

    With a pistil it points from a reference to the pistil centroid: the pistil sits on the
    side the corolla opens to. "crop" uses the crop centroid (upstream). "petal_base" uses
    the petals nearest the pistil: the receptacle dome protrudes from the petal base along
    the normal whatever the petals do further out, while a cupped corolla lifts the crop
    centroid above the receptacle and reverses upstream's vector. "petal_surface" signs
    the petals' plane axis `plane` by the side of the petal surface the pistil is on.
    Without a pistil, the sepals and peduncle lie behind the flower, so the normal points
    away from them: the crop's, and those of `support_round` within the support vote's
    reach of the petals' centroid (`support_reach`).
    """
    points = crop.points
    if pistil.any():
        pistil_points = points[pistil]
        pistil_centroid = pistil_points.mean(axis=0)
        found = int(pistil.sum())
        if config.direction_reference == "crop" or not petal.any():
            return Orientation(pistil_centroid - points.mean(axis=0), None, found)
        if config.direction_reference == "petal_surface" and plane is not None:
            return Orientation(_above_petal_surface(points[petal], pistil_centroid, plane),
                               None, found)
        if config.direction_reference == "combined" and plane is not None:
            return Orientation(*_combined(crop, petal, pistil, plane, config, colours, up,
                                          support_round))
        radius = np.percentile(np.linalg.norm(pistil_points - pistil_centroid, axis=1), 90)
        petal_points = points[petal]
        distance = np.linalg.norm(petal_points - pistil_centroid, axis=1)
        base = distance <= config.base_radius_factor * radius
        if base.sum() < config.base_min_points:
            base = np.argsort(distance)[:config.base_min_points]
        return Orientation(pistil_centroid - petal_points[base].mean(axis=0), None, found)
    if not petal.any():
        return None
    petal_points = points[petal]
    support_points = points[~petal & colours.support]
    if support_round is not None and len(support_round) and plane is not None:
        centroid = petal_points.mean(axis=0)
        radius = _corolla_radius(petal_points, centroid)
        nearby = _within_reach(support_round, centroid, plane, radius, config.support_reach)
        support_points = np.concatenate([support_points, support_round[nearby]])
    if len(support_points) < config.support_min_points:
        return None
    return Orientation(petal_points.mean(axis=0) - support_points.mean(axis=0), None, 0)


def _corolla_radius(petal_points: np.ndarray, centre: np.ndarray) -> float:
    """The corolla radius the orientation votes count in: the 90th percentile distance of
    the petal points (K, 3) from `centre` (3,), their unit."""
    return float(np.percentile(np.linalg.norm(petal_points - centre, axis=1), 90))


def _within_reach(at: np.ndarray, centre: np.ndarray, axis: np.ndarray, radius: float,
                  reach: float) -> np.ndarray:
    """Which of the points `at` (K, 3) lie within `radius` of `centre` across the unit
    `axis` and within `reach` times `radius` along it (the support vote's reach)."""
    height = (at - centre) @ axis
    across = np.linalg.norm(at - centre - np.outer(height, axis), axis=1)
    return (across <= radius) & (np.abs(height) <= reach * radius)


def _combined(crop: Cloud, petal: np.ndarray, pistil: np.ndarray, plane: np.ndarray,
              config: PoseConfig, colours: CropColours, up: np.ndarray | None,
              support_round: np.ndarray | None) -> tuple[np.ndarray, float, int]:
    """The plane axis signed by the sum of four offsets along it (the cloud's unit): the
    pistil (its core, `pistil_core`) above the petal surface extended to it, above the
    crop's centroid near it (`crop_reach`), above its own petals' centroid, and the petals
    above the sepals and stems near the flower (support colours of the crop and of
    `support_round` within `support_reach` corolla radii of the pistil along the axis and
    one across it; left out when fewer than `support_min_points`), each clipped to
    `offset_clip` corolla radii; plus, with a known `up`, the prior `up_prior` corolla
    radii times the axis's cosine with up to `up_prior_power`. Also returns the sum's
    size in corolla radii (how clearly the votes decided) and the pistil core's points.

    The petals' own centroid (weighed by `petal_vote`) is the vote that holds on thinned
    and partly seen real flowers, where the surface's extrapolation and the sepals (a leaf
    of their colour beside the flower) each turn."""
    points = crop.points
    petal_points = points[petal]
    if config.pistil_core is not None:
        pistil = _pistil_core(points, pistil, petal_points, plane, config.pistil_core)
    pistil_centroid = points[pistil].mean(axis=0)
    offset = points - pistil_centroid
    radius = _corolla_radius(petal_points, pistil_centroid)

    def within_reach(at: np.ndarray) -> np.ndarray:
        return _within_reach(at, pistil_centroid, plane, radius, config.support_reach)

    support_points = points[colours.support & ~colours.petal & ~pistil & within_reach(points)]
    if support_round is not None and len(support_round):
        support_points = np.concatenate([support_points,
                                         support_round[within_reach(support_round)]])
    near = (np.ones(len(points), bool) if config.crop_reach is None
            else np.linalg.norm(offset, axis=1) <= config.crop_reach * radius)
    offsets = [float(_above_petal_surface(petal_points, pistil_centroid, plane) @ plane),
               float((pistil_centroid - points[near].mean(axis=0)) @ plane)]
    petals_below = float((pistil_centroid - petal_points.mean(axis=0)) @ plane)
    if len(support_points) >= config.support_min_points:
        offsets.append(float((petal_points.mean(axis=0) - support_points.mean(axis=0))
                             @ plane))
    if config.offset_clip is not None:
        limit = config.offset_clip * radius
        offsets = [min(max(o, -limit), limit) for o in offsets]
        petals_below = min(max(petals_below, -limit), limit)
    evidence = sum(offsets) + config.petal_vote * petals_below
    if up is not None:
        cosine = float(plane @ up)
        weight = np.sign(cosine) * abs(cosine) ** config.up_prior_power
        evidence += config.up_prior * radius * weight
    margin = abs(evidence) / radius if radius > 0 else 0.0
    return (plane if evidence >= 0 else -plane), margin, int(pistil.sum())


def _pistil_core(points: np.ndarray, pistil: np.ndarray, petal_points: np.ndarray,
                 axis: np.ndarray, reach: float) -> np.ndarray:
    """The pistil mask cut to its core: the pistil points within `reach` corolla radii,
    across `axis`, of the pistil point nearest the petals' axis (through their centroid)."""
    centroid = petal_points.mean(axis=0)

    def across(at: np.ndarray) -> np.ndarray:
        offset = at - centroid
        return offset - np.outer(offset @ axis, axis)

    radius = float(np.percentile(np.linalg.norm(across(petal_points), axis=1), 90))
    index = np.flatnonzero(pistil)
    spread = across(points[index])
    nearest = np.argmin(np.linalg.norm(spread, axis=1))
    core = np.zeros(len(points), bool)
    core[index] = np.linalg.norm(spread - spread[nearest], axis=1) <= reach * radius
    return core


def _above_petal_surface(petal_points: np.ndarray, pistil_centroid: np.ndarray,
                         axis: np.ndarray) -> np.ndarray:
    """The petals' plane axis, signed towards the pistil's side of the petal surface
    extended to the pistil (a paraboloid h = h0 + k r^2 about the pistil axis, least
    squares). metres, crop frame."""
    offset = petal_points - pistil_centroid
    height = offset @ axis
    radius_sq = np.einsum("ij,ij->i", offset, offset) - height ** 2
    design = np.column_stack([np.ones(len(height)), radius_sq])
    surface_at_pistil = np.linalg.lstsq(design, height, rcond=None)[0][0]
    return -surface_at_pistil * axis


def estimate_pose(crop: Cloud, config: PoseConfig | None = None,
                  colour: ColourConfig | None = None, cluster: ClusterConfig | None = None,
                  flower_radius: float | None = None,
                  up: np.ndarray | None = None,
                  support_round: np.ndarray | None = None) -> FlowerPose:
    """Normals of one flower by the plane, superellipsoid and paraboloid fits.

    crop: the cloud points of one flower, points (N, 3) float64 in the cloud's frame and
    unit (metres, bed frame, in the pipeline), colors (N, 3) uint8. flower_radius: the
    typical flower radius of the cloud, same unit (`segment.typical_radius`); None: this
    crop's own corolla radius. up: the frame's unit up vector where the frame is a bed's
    (z up) and so known, else None (`up_prior`). support_round: (K, 3) points of sepal and
    stem colour (`colour.sepal_mask`) of the cloud round the crop and not in it, same frame
    and unit, for the support vote (`support_from_cloud`); None: the crop's own only.
    Normals come back in the same frame,
    each oriented by the pistil (or, without one, away from the sepals and peduncle), or
    None: for a failed fit, or for all three when nothing orients them (the fits are then
    skipped).
    """
    config = config or PoseConfig()
    colour = colour or ColourConfig()
    cluster = cluster or ClusterConfig()
    if len(crop) == 0:
        raise InputError("flower crop", "the crop has no points")
    colours = CropColours.of(crop, colour)
    _, pistil = _split(crop.points, colours, cluster)
    found = bool(pistil.any())
    own_radius = flower_radius is None
    if own_radius:
        flower_radius = corolla(crop.points, colours.petal, colours.pistil, cluster).radius
    petal, plane = _petals_and_plane(crop.points, colours.petal, pistil, config, flower_radius)
    if found and plane is not None and not _pistil_in_corolla(crop.points, pistil,
                                                              crop.points[petal], plane, config):
        # The refused cluster is neither pistil nor support: in front of the flower it
        # would sign the normal backwards.
        colours = replace(colours, pistil=colours.pistil & ~pistil,
                          support=colours.support & ~pistil)
        found, pistil = False, np.zeros_like(pistil)
        if own_radius:
            flower_radius = corolla(crop.points, colours.petal, colours.pistil, cluster).radius
        petal, plane = _petals_and_plane(crop.points, colours.petal, pistil, config,
                                         flower_radius)
    if found:
        center = crop.points[pistil].mean(axis=0)
    elif petal.any():
        center = crop.points[petal].mean(axis=0)
    else:
        center = crop.points.mean(axis=0)
    petal_points = crop.points[petal]
    normals: dict[str, np.ndarray | None] = dict.fromkeys(METHODS)
    if not config.support_from_cloud:
        support_round = None
    orientation = _orientation(crop, petal, pistil, plane, config, colours, up, support_round)
    if orientation is not None:
        axes = _fit_axes(petal_points, plane, center if found else None, config)
        reference = orientation.reference
        normals = {m: None if axis is None else (axis if axis @ reference >= 0.0 else -axis)
                   for m, axis in axes.items()}
    return FlowerPose(center=center, normals=normals, pistil_found=found,
                      n_points=len(crop), n_petal_points=len(petal_points),
                      orientation_margin=None if orientation is None else orientation.margin,
                      uncertain=bool(orientation is None or orientation.uncertain(config)))


def _petals_and_plane(points: np.ndarray, petal: np.ndarray, pistil: np.ndarray,
                      config: PoseConfig, flower_radius: float
                      ) -> tuple[np.ndarray, np.ndarray | None]:
    """The corolla's petal mask (`_corolla`) and its plane's unit axis (`fit.fit_plane`;
    None with too few petals)."""
    petal = _corolla(points, petal, pistil, config, flower_radius)
    return petal, fit_plane(points[petal], config.min_fit_points,
                            config.plane_robust_iterations,
                            config.plane_min_scale * flower_radius)


def _pistil_in_corolla(points: np.ndarray, pistil: np.ndarray, petal_points: np.ndarray,
                       axis: np.ndarray, config: PoseConfig) -> bool:
    """Whether the pistil (its core) lies within `pistil_max_height` corolla radii (the
    90th percentile distance of the petals from it) of the petals' centroid along their
    plane's unit `axis`."""
    if config.pistil_max_height is None:
        return True
    if config.pistil_core is not None:
        pistil = _pistil_core(points, pistil, petal_points, axis, config.pistil_core)
    centre = points[pistil].mean(axis=0)
    radius = _corolla_radius(petal_points, centre)
    height = abs(float((centre - petal_points.mean(axis=0)) @ axis))
    return height <= config.pistil_max_height * radius


def _corolla(points: np.ndarray, petal: np.ndarray, pistil: np.ndarray,
             config: PoseConfig, flower_radius: float) -> np.ndarray:
    """The petal mask without what only looks like petals: points beyond
    `petal_max_radius` flower radii of the pistil, then points far off the petals' plane
    (`petal_trim_factor`, twice)."""
    if pistil.any() and config.petal_max_radius is not None and flower_radius > 0:
        offset = points - points[pistil].mean(axis=0)
        limit = config.petal_max_radius * flower_radius
        petal = petal & (np.einsum("ij,ij->i", offset, offset) <= limit ** 2)
    for _ in range(2 if config.petal_trim_factor is not None else 0):
        if petal.sum() < config.min_fit_points:
            break
        centroid, _, vectors = principal_axes(points[petal])
        distance = np.abs((points - centroid) @ vectors[:, 2])
        limit = max(config.petal_trim_factor * float(np.median(distance[petal])),
                    config.petal_trim_min * flower_radius)
        petal = petal & (distance <= limit)
    return petal


def _fit_axes(petal_points: np.ndarray, plane: np.ndarray | None,
              pistil_centroid: np.ndarray | None,
              config: PoseConfig) -> dict[str, np.ndarray | None]:
    """Unoriented unit axes (or None) of the three fits, keyed by METHODS; `plane` is the
    plane fit's, already made."""
    fit_points = petal_points
    if len(petal_points) > config.max_fit_points:
        rng = np.random.default_rng(config.seed)
        fit_points = petal_points[rng.choice(len(petal_points), config.max_fit_points,
                                             replace=False)]
    axis_point = pistil_centroid if config.axis_through_pistil else None
    return {
        "plane": plane,
        "superellipsoid": fit_superellipsoid(
            fit_points, axis_point=axis_point, init=config.superellipsoid_init,
            size_bounds=config.superellipsoid_size_bounds,
            exponent_bounds=config.superellipsoid_exponent_bounds,
            max_flatness=config.superellipsoid_max_flatness,
            max_evaluations=config.max_evaluations, min_points=config.min_fit_points),
        "paraboloid": fit_paraboloid(fit_points, axis_point=axis_point,
                                     max_evaluations=config.max_evaluations,
                                     min_points=config.min_fit_points,
                                     init=config.paraboloid_init),
    }
