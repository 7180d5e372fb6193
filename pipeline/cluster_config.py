"""The cluster stage's settings (`outliers`, `cluster`: `segment.cluster_flowers`),
checked when made, and the same settings sized to a cloud (`for_cloud`).

Lengths are in metres, or in the cloud's own unit once `for_cloud` has scaled them to its
flowers; counts are in points. The rules that size them are `limits.py`'s.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal

from flowerpose.config import require
from flowerpose.pipeline.limits import (
    SPACING_FLOORS,
    Density,
    measured_density,
    sized_count,
)


@dataclass(frozen=True)
class OutlierConfig:
    """Outlier removal on the merged candidate points (before DBSCAN)."""

    statistical_neighbours: int = 20
    """Statistical outlier removal: neighbours averaged. Deviation: upstream's 100 span
    several flowers at the paper's density (a flower gives 60-90 candidate points), so an
    isolated flower is removed whole: on 10 realistic plants upstream's (100, 0.5) found
    0.888 of visible flowers, (20, 2.0) 0.9925 (`flowerpose sweep --grid
    outliers.statistical_neighbours=100,30,20,0 --grid outliers.statistical_std_ratio=0.5,2.0
    --plants 10`)."""
    statistical_std_ratio: float = 2.0
    """Statistical outlier removal: points whose mean neighbour distance exceeds the mean by
    this many standard deviations are dropped (upstream: 0.5, see above)."""
    radius_points: int = 15
    """Radius outlier removal: neighbours needed within `radius_m` (upstream: 15)."""
    radius_m: float = 0.01
    """Radius outlier removal: radius, metres (upstream: 0.01; 0.1 in the notebook that
    matches the paper's DBSCAN)."""
    order: Literal["statistical_first", "radius_first"] = "statistical_first"
    """Which removal runs first (upstream's notebooks differ; the one that matches the
    paper's DBSCAN runs the radius removal first)."""

    def __post_init__(self):
        require(self.statistical_neighbours >= 0, "outliers.statistical_neighbours",
                "must be 0 (off) or more")
        require(self.statistical_std_ratio > 0, "outliers.statistical_std_ratio",
                "must be positive")
        require(self.radius_points >= 0, "outliers.radius_points", "must be 0 (off) or more")
        require(self.radius_m > 0, "outliers.radius_m", "must be positive (metres)")


@dataclass(frozen=True)
class ClusterConfig:
    """Grouping candidate points into flowers."""

    candidates: Literal["flower_colour", "all"] = "flower_colour"
    """Which candidate points are clustered: "flower_colour" (deviation: only those of a
    petal's or a pistil's colour, `colour`) or "all" (upstream). A box or a real
    detector's crop takes in the leaves and stems behind each flower; clustered with the
    flower they join it into one blob that the colour test below rejects. On the merged
    candidates of the authors' plant 3: 6 of 11 labelled flowers with "all", 11 with
    "flower_colour" (docs/guides/own-scan.md)."""
    eps: float = 0.01
    """DBSCAN neighbourhood radius, metres (the paper: 0.01)."""
    min_points: int = 20
    """DBSCAN core-point neighbour count (the paper: 20)."""
    min_flower_fraction: float = 0.7
    """A cluster is a flower when more than this share of its points has a petal's or a
    pistil's colour (`colour`; deviation: upstream counted whitish points alone, which
    rejects flowers seen face-on, where the yellow centre is a third of the points)."""
    min_white_fraction: float = 0.35
    """... and at least this share has a petal's colour: a flower has petals."""
    white_rule: Literal["petal", "saturation"] = "petal"
    """What counts as white in these two shares and the corolla test: "petal", the petal
    band of `colour` (deviation), or "saturation", its saturation limit alone (upstream's
    whitish rule, which counts pale green leaves in shade as white)."""
    min_coverage: float = 0.35
    """A flower's petals must cover at least this share of the disc they span round its
    pistil (`corolla_coverage`: scale-free, so it holds in any unit and density).
    Deviation, not in upstream: bits of stem and leaf that pass the colour test with a few
    yellow points are strips, 0.12-0.17 on the authors' plant 3, where its flowers,
    labelled or not, reach 0.67-1.2 and those of 10 synthetic plants 0.57-0.80."""
    min_size_ratio: float = 0.5
    """... and span at least this share of the typical flower's radius in the same cloud
    (the median over the flowers that pass the coverage test), so a speck of flower colour
    with a yellow dot is not a flower: sizes come from the data, not from a flower size
    assumed in metres. Deviation, not in upstream."""
    sparse_flower_ratio: float = 2.0
    """A corolla's coverage counts each of its points for the area it stands for by its own
    spacing, but at most this many times the area a point of the cloud's flowers stands
    for where it has a pistil and at least the operating envelope's fewest points a flower
    (`envelope.POINTS_PER_FLOWER`, 50), and at most as much otherwise: a few
    flower-coloured points far apart are a speck, not a sparsely sampled flower, and below
    the envelope the two cannot be told apart. Flowers of one cloud are sampled unevenly: a
    flower seen by one view keeps a tenth of its points when each view's candidates are
    thinned to a tenth, one seen by three about a quarter, and the k-nearest estimate of a
    flower of 40-60 points is inflated by its rim. On the authors' plant 3 the labelled
    flowers' own spacing is 0.74-1.26 times the cloud's at full density and 0.61-3.05 times
    at 10 %, where three of them (coverage 0.25-0.31 at 1) were lost. Measured (`flowerpose
    stress`, 3 seeded repeats; 1 -> 2, with `pose.pistil_core`): thinned to 20 % 30 -> 32
    of 33 found, no false positive, plane 7.53 -> 7.77 degrees; 10 % 28 -> 31, 1 false
    positive either way, 7.13 -> 7.87, no flipped normal; 5 % and full density unchanged;
    the oracle, hard and field presets (10 plants; field also fixed at 111 and 882 points a
    flower) unchanged. Without the envelope's bound, 10 % found 33 but turned a flower of
    38 points over (its stalk's 3 pistil-coloured points outnumber its receptacle's 2) and
    20 % found a flower twice; without the pistil's condition, the field preset at 111
    points gained 2 false positives (sheen). 1: the cloud's spacing caps every corolla."""
    reach_ratio: float = 1.5
    """A flower's part with a pistil that fails the coverage test and reaches beyond this
    many typical radii of its pistil (a flower among sheened leaves of petal colour,
    touching a pale leaf, or joined to a neighbour's petals) keeps only what lies within
    them, and is judged again. Judged by the part's reach, not its disc radius: a small
    flower joined to such a patch measures a disc no bigger than the typical flower's and
    would otherwise be lost (the guard battery's full loop, seeds 100-105: 63 of 73
    visible flowers found with the disc radius's condition, 72 with the reach). A part
    without a pistil that is no flower and lies wholly within this many typical radii of
    a flower's centre, nearer it than any other's, joins that flower: on a sparse cloud a
    gap between petals wider than `eps` cuts a corolla in two (`_with_fragments`)."""
    require_pistil: bool = True
    """A flower's crop must hold a pistil (a cluster of yellow points), else it is dropped.
    Deviation: upstream's detector was a trained network; with colour detection, leaves
    sheened with sky colour and stereo fringe floating in the sky are whitish too, and on
    a reconstructed cloud none of them has a pistil, while a flower's receptacle is seen
    from some view of the scan. It also leaves no flower without a normal."""
    pistil_optional_density: float = 0.3
    """... except in a cloud this sparse: where its density sized the point counts by a
    factor below this (`density_reference`), a corolla that passes every other test is a
    flower without a pistil too where its sepals and stem orient it
    (`pose.support_min_points`); a flower is never kept without a normal. A receptacle is a tenth
    of a flower's points or less: at a fifth of the reference density a shaded one shows
    as none. Measured on the authors' plant 3 thinned to 10 % (3 seeded repeats): 28 of
    33 labelled flowers found, 1 false positive and no flipped normal, against 24 of 33
    and 1 when the pistil is always required; at full density and at 20 % and 50 %
    unchanged; `require_pistil=false` everywhere costs 1 false positive at full
    density and 4 at 20 %. 0: a pistil is always required."""
    split_touching: bool = True
    """Split a cluster that holds several pistils between them (deviation: upstream kept
    touching flowers as one)."""
    split_min_separation_m: float = 0.012
    """Flower centres (pistil clusters) this far apart inside one cluster split it into one
    flower per centre, metres: touching flowers merge under DBSCAN."""
    split_link_m: float = 0.004
    """Points closer than this are neighbours on the surface when a cluster is split between
    its flower centres, metres: about twice the point spacing."""
    pistil_eps: float = 0.005
    """DBSCAN neighbourhood radius (metres) grouping pistil-coloured points into candidate
    pistils, which split touching flowers here and orient each flower in the pose stage
    (upstream: 0.005)."""
    pistil_min_points: int = 5
    """DBSCAN least points per core neighbourhood of a candidate pistil (upstream: 5)."""
    crop: Literal["near", "box"] = "near"
    """A flower's crop: "near", every cloud point within `crop_margin_m` of its cluster
    (deviation), or "box", every cloud point in the cluster's oriented box (upstream), which
    on tilted or touching flowers takes in a neighbour's petals and the leaves behind."""
    crop_margin_m: float = 0.004
    """"near" crops: the margin, metres, so the receptacle, sepals and petal parts hidden
    in every view come along."""
    size_band_m: tuple[float, float] | None = (0.017, 0.035)
    """Flower radii (`Grouping.size`) for which the limits above stated in metres (`eps`,
    `split_min_separation_m`, `split_link_m`, `pistil_eps`, `crop_margin_m`, and
    `outliers.radius_m`) hold as they stand. A cloud whose flowers measure outside the band
    (a phone scan's own scale, another unit, bigger or smaller flowers) has those limits
    scaled by its flowers' radius over the nearer edge and is grouped again, so sizes come
    from the data. Measured on the authors' plant 3 (0.025 in its Polycam unit) scaled by
    0.4-2: 11 of 11 flowers found at every scale, plane error 7.47-7.50°; without the band
    a flower flipped at 0.4-0.5 (21.3°) and at 2 one was lost and one flipped (10 of 11,
    22.4°). The 10 synthetic plants are grouped at 0.82-0.97 times the limits (1.93° as
    before); the `field` preset's flowers (0.027-0.031) stay inside, where an upper edge
    of 0.03 rescaled them by 1-4% and flipped flowers (8.8° against 7.2°). The first
    grouping runs at the limits as stated, so a cloud about three times too large for
    them (its flowers cut into pieces of about the band's size) still needs its unit said
    (`units`) or the limits set. Deviation: upstream used its limits as stated (none)."""

    density_reference: float | None = 100.0
    """Points within `eps` of a flower-coloured candidate on its surface (the cloud's
    measured density: pi eps^2 over the median area a point stands for) at which the
    point counts (`min_points`, `pistil_min_points`, `outliers.radius_points`,
    `pose.base_min_points`, `pose.support_min_points`) hold as stated. A sparser cloud (a
    faster scan, fewer frames, a phone scan) has them multiplied by its density over this,
    never below their floors (`limits.COUNT_FLOORS`), and the lengths that must span
    several points at least so many point spacings (`limits.SPACING_FLOORS`). The authors'
    plant 3 measures about 110. Deviation: upstream stated its counts for one density
    (none)."""

    def __post_init__(self):
        require(self.eps > 0, "cluster.eps", "must be positive (metres)")
        require(self.density_reference is None or self.density_reference > 0,
                "cluster.density_reference", "must be positive (points) or none")
        require(self.min_points >= 1, "cluster.min_points", "must be at least 1")
        require(self.reach_ratio > 0, "cluster.reach_ratio", "must be positive")
        for name in ("min_flower_fraction", "min_white_fraction", "min_size_ratio"):
            require(0 <= getattr(self, name) <= 1, f"cluster.{name}", "must be within 0-1")
        require(self.min_coverage >= 0, "cluster.min_coverage", "must be 0 or more")
        require(self.sparse_flower_ratio >= 1, "cluster.sparse_flower_ratio",
                "must be 1 or more (a ratio of areas)")
        require(self.pistil_min_points >= 1, "cluster.pistil_min_points", "must be at least 1")
        require(0 <= self.pistil_optional_density <= 1, "cluster.pistil_optional_density",
                "must be within 0-1 (a share of the reference density)")
        for name in ("split_min_separation_m", "split_link_m", "crop_margin_m", "pistil_eps"):
            require(getattr(self, name) > 0, f"cluster.{name}", "must be positive (metres)")
        require(self.size_band_m is None or 0 < self.size_band_m[0] <= self.size_band_m[1],
                "cluster.size_band_m", "must be two radii, 0 < low <= high (metres), or none")


def for_cloud(outliers: OutlierConfig, cluster: ClusterConfig, scale: float,
              spacing: float | None) -> tuple[OutlierConfig, ClusterConfig, Density]:
    """The outlier and cluster settings for a cloud: every limit in metres multiplied by
    `scale` (the flowers' size), lengths raised to SPACING_FLOORS point spacings, and point
    counts sized to the density (`cluster.density_reference`, COUNT_FLOORS)."""
    lengths = {"eps": cluster.eps, "split_link_m": cluster.split_link_m,
               "pistil_eps": cluster.pistil_eps, "crop_margin_m": cluster.crop_margin_m,
               "split_min_separation_m": cluster.split_min_separation_m}
    lengths = {name: value * scale for name, value in lengths.items()}
    radius_m = outliers.radius_m * scale
    if spacing is not None:
        lengths = {name: max(value, SPACING_FLOORS.get(name, 0.0) * spacing)
                   for name, value in lengths.items()}
        radius_m = max(radius_m, SPACING_FLOORS["radius_m"] * spacing)
    density = measured_density(lengths["eps"], spacing, cluster.density_reference)
    outliers = replace(outliers, radius_m=radius_m,
                       radius_points=sized_count(outliers.radius_points, "radius_points",
                                                 density))
    cluster = replace(cluster, **lengths,
                      min_points=sized_count(cluster.min_points, "min_points", density),
                      pistil_min_points=sized_count(cluster.pistil_min_points,
                                                    "pistil_min_points", density))
    return outliers, cluster, density
