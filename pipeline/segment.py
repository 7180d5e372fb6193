"""From back-projected candidate points to one point set per flower.

Statistical then radius outlier removal, DBSCAN, the whiteness filter, splitting clusters
that hold several flower centres (touching flowers), and an oriented box per flower whose
contents in the full cloud become the flower's crop. The soil is removed before
(`ground.py`). The stage's settings, and how they are sized to a cloud, are
`cluster_config.py`'s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree

from flowerpose.cloudio import Cloud
from flowerpose.log import open3d
from flowerpose.pipeline.cluster_config import ClusterConfig, OutlierConfig, for_cloud
from flowerpose.pipeline.colour import ColourConfig, petal_mask, pistil_mask, rgb_to_hsv
from flowerpose.pipeline.envelope import POINTS_PER_FLOWER
from flowerpose.pipeline.fit import principal_axes
from flowerpose.pipeline.limits import (
    Density,
    Sizing,
    area_per_point,
    sized_to_cloud,
    surface_area_per_point,
)


@dataclass(frozen=True)
class OrientedBox:
    """An oriented box in the bed frame, metres."""

    center: np.ndarray
    """(3,) box centre."""
    rotation: np.ndarray
    """(3, 3) columns are the box axes (a right-handed rotation)."""
    extent: np.ndarray
    """(3,) full edge lengths along the box axes."""

    def contains(self, points: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """(N,) bool: points (N, 3) inside the box grown by `margin` metres."""
        local = (points - self.center) @ self.rotation
        return np.all(np.abs(local) <= self.extent / 2 + margin + 1e-9, axis=1)

    def to_json(self) -> dict:
        return {"center": self.center.tolist(), "R": self.rotation.tolist(),
                "extent": self.extent.tolist()}


def oriented_box(points: np.ndarray) -> OrientedBox:
    """PCA-aligned box around points (N, 3), metres."""
    mean, _, vectors = principal_axes(points)
    local = (points - mean) @ vectors
    low, high = local.min(axis=0), local.max(axis=0)
    return OrientedBox(mean + vectors @ ((low + high) / 2), vectors, high - low)


def remove_outliers(points: np.ndarray, config: OutlierConfig) -> np.ndarray:
    """Indices of points (N, 3) kept by statistical and radius outlier removal, in the
    configured order."""
    o3d = open3d()

    def statistical(keep: np.ndarray) -> np.ndarray:
        if len(keep) <= 2 or config.statistical_neighbours == 0:
            return keep
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points[keep]))
        neighbours = min(config.statistical_neighbours, len(keep) - 1)
        _, kept = pcd.remove_statistical_outlier(neighbours, config.statistical_std_ratio)
        return keep[np.asarray(kept, dtype=np.int64)]

    def radius(keep: np.ndarray) -> np.ndarray:
        if len(keep) == 0 or config.radius_points == 0:
            return keep
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points[keep]))
        _, kept = pcd.remove_radius_outlier(config.radius_points, config.radius_m)
        return keep[np.asarray(kept, dtype=np.int64)]

    steps = (statistical, radius) if config.order == "statistical_first" else (radius, statistical)
    keep = np.arange(len(points))
    for step in steps:
        keep = step(keep)
    return keep


def dbscan(points: np.ndarray, eps: float, min_points: int) -> np.ndarray:
    """(N,) int cluster labels of points (N, 3), -1 for noise (Open3D's DBSCAN)."""
    o3d = open3d()
    if len(points) == 0:
        return np.zeros(0, np.int64)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    return np.asarray(pcd.cluster_dbscan(eps, min_points, print_progress=False), np.int64)


def pistil_clusters(points: np.ndarray, is_pistil: np.ndarray,
                    config: ClusterConfig) -> list[np.ndarray]:
    """Candidate pistils: the pistil-coloured points grouped by DBSCAN.

    points: (N, 3) metres; is_pistil: (N,) bool, the points of pistil colour. Returns one
    index array into `points` per cluster (DBSCAN noise left out); empty when none.
    """
    index = np.flatnonzero(is_pistil)
    if len(index) < config.pistil_min_points:
        return []
    labels = dbscan(points[index], config.pistil_eps, config.pistil_min_points)
    order = np.argsort(labels, kind="stable")
    edges = np.searchsorted(labels[order], np.arange(labels.max(initial=-1) + 2))
    return [index[order[edges[k]:edges[k + 1]]] for k in range(len(edges) - 1)]


#: A candidate pistil with fewer points than this share of the largest among its
#: neighbours is a fleck of yellow (a petal fold, a shaded rim, a yellowed sepal), not a
#: receptacle: it neither splits a cluster nor orients a flower.
MIN_PISTIL_SHARE = 0.1


def substantial(pistils: list[np.ndarray]) -> list[np.ndarray]:
    """The candidate pistils with at least MIN_PISTIL_SHARE of the largest one's points."""
    largest = max((len(c) for c in pistils), default=0)
    return [c for c in pistils if len(c) >= MIN_PISTIL_SHARE * largest]


#: Candidate pistils within this share of the petals' spread (their 90th percentile
#: distance from the petal centroid) of that centroid are the flower's own centre; the
#: largest of them is its receptacle.
CENTRE_REACH = 0.5


def the_pistil(points: np.ndarray, petal: np.ndarray, is_pistil: np.ndarray,
               config: ClusterConfig) -> np.ndarray | None:
    """The flower's pistil among the candidates (`pistil_clusters`, flecks beside a
    receptacle left out: `substantial`), as indices into points (N, 3); None when there is
    no candidate. The largest candidate within CENTRE_REACH of the petal centroid (the
    centroid of all the points when there are no petals), else the nearest one: a
    yellowed sepal or stem a few millimetres behind a cupped corolla can lie nearer the
    petal centroid than the receptacle, and taken for the pistil it flips the normal,
    while a touching neighbour's pistil lies a flower's width away. petal, is_pistil: (N,)
    bool colour masks."""
    pistils = substantial(pistil_clusters(points, is_pistil, config))
    if not pistils:
        return None
    body = points[petal] if petal.any() else points
    anchor = body.mean(axis=0)
    spread = float(np.percentile(np.linalg.norm(body - anchor, axis=1), 90))
    distance = np.linalg.norm(np.array([points[c].mean(axis=0) for c in pistils]) - anchor,
                              axis=1)
    central = np.flatnonzero(distance <= CENTRE_REACH * spread)
    if len(central) == 0:
        return pistils[int(np.argmin(distance))]
    return pistils[int(central[np.argmax([len(pistils[k]) for k in central])])]


@dataclass(frozen=True)
class Corolla:
    """A flower's petal disc round its centre, in the unit of the cloud."""

    centre: np.ndarray
    """(3,) the pistil cluster nearest the petal centroid, or the petal centroid."""
    has_pistil: bool
    radius: float
    """The flower's radius: how far from the centre the petal points stay as dense as a
    disc's (`disc_radius`), so a stem or leaf beyond the rim does not count."""
    coverage: float
    """Share of the disc round the centre that the petal points cover: the petal count
    times the area each point stands for (the median k-nearest-neighbour estimate,
    pi r_k^2 / k) over pi R^2, R the 90th percentile petal distance. Near 1 for a whole,
    evenly sampled corolla whatever the density or unit, about half for half a corolla,
    near 0 for a strip."""


#: A disc's petal density (points per squared distance) within this share of its value at
#: the median petal distance still counts as the corolla (`disc_radius`).
DISC_DENSITY_SHARE = 0.8


def disc_radius(distances: np.ndarray) -> float:
    """The radius out to which points at these distances from a centre are as dense as a
    disc's: the largest distance beyond the median at which the count within it, over its
    square, is still DISC_DENSITY_SHARE of its value at the median. A disc of radius R gives
    R; a stem or a leaf edge reaching beyond it adds points in proportion to the distance,
    not its square, so it ends the disc. distances: (N,) any unit, N >= 1."""
    ordered = np.sort(np.asarray(distances, np.float64))
    middle = len(ordered) // 2
    if ordered[middle] <= 0:
        return float(ordered[-1])
    density = np.arange(1, len(ordered) + 1) / np.maximum(ordered, 1e-300) ** 2
    thin = np.flatnonzero(density[middle:] < DISC_DENSITY_SHARE * density[middle])
    return float(ordered[middle + thin[0] - 1] if len(thin) else ordered[-1])


def corolla(points: np.ndarray, petal: np.ndarray, pistil: np.ndarray,
            config: ClusterConfig, cloud_area: float | None = None) -> Corolla:
    """The corolla of one flower's points (N, 3), any unit; petal, pistil: (N,) bool colour
    masks. cloud_area: the area a point of the whole cloud stands for (`area_per_point`),
    the most a point of this flower may stand for in its coverage: a few points far apart
    are a speck of flower colour, not a sparsely sampled flower. A flower without three
    petal points has radius and coverage 0."""
    petal_points = points[petal]
    chosen = the_pistil(points, petal, pistil, config)
    if chosen is not None:
        anchor = points[chosen].mean(axis=0)
    else:
        anchor = petal_points.mean(axis=0) if len(petal_points) else points.mean(axis=0)
    if len(petal_points) < 3:
        return Corolla(anchor, chosen is not None, 0.0, 0.0)
    distance = np.linalg.norm(petal_points - anchor, axis=1)
    spanned = float(np.percentile(distance, 90))
    area = area_per_point(points)
    if cloud_area is not None:
        sampled = chosen is not None and len(points) >= POINTS_PER_FLOWER[0]
        area = min(area, (config.sparse_flower_ratio if sampled else 1.0) * cloud_area)
    coverage = len(petal_points) * area / (np.pi * spanned ** 2) if spanned > 0 else 0.0
    return Corolla(anchor, chosen is not None, disc_radius(distance), coverage)


def typical_radius(corollas: list[Corolla], config: ClusterConfig,
                   points: list[int] | None = None) -> float | None:
    """The median radius of the corollas that pass the coverage test and, where a flower
    needs one (`require_pistil`), have a pistil (all that pass, where none has), each
    counted by its `points` (once each without): the flower size of this cloud, in its unit
    (None when none passes). Counted by points, the typical flower is the one a typical
    flower point belongs to, so a cloud's many specks of sheen, each a dozen points, do not
    outvote its flowers of hundreds; and a blob of sheen or stereo fringe, which has no
    pistil, does not count at all."""
    passed = [k for k, c in enumerate(corollas) if c.coverage >= config.min_coverage]
    with_pistil = [k for k in passed if corollas[k].has_pistil]
    if config.require_pistil and with_pistil:
        passed = with_pistil
    weights = [1 if points is None else points[k] for k in passed]
    return _weighted_median([corollas[k].radius for k in passed], weights)


@dataclass(frozen=True)
class Grouping:
    """The cluster stage's result: the flowers' points and the sizes that grouped them."""

    clusters: list[np.ndarray]
    """Per flower, indices into the cloud."""
    typical_radius: float | None
    """The cloud's typical flower radius (`typical_radius`, its unit; None: no flower)."""
    size: float | None
    """The flowers' radius, each counted by its points (its unit; None: no flower): what
    the limits are sized by."""
    scale: float
    """What the metric limits were multiplied by (`ClusterConfig.size_band_m`)."""
    density: Density
    """How the cloud's density sized the point counts (`ClusterConfig.density_reference`)."""
    config: ClusterConfig
    """The cluster settings as applied, sized to the cloud (`cluster_config.for_cloud`): the crops
    and the pose stage's pistil search use them too."""


def cluster_flowers(plant: Cloud, candidates: np.ndarray, outliers: OutlierConfig,
                    config: ClusterConfig, colour: ColourConfig) -> Grouping:
    """Candidate points grouped into one index array per flower, at limits sized to the
    cloud's own flowers and density (`limits`: `ClusterConfig.size_band_m`,
    `density_reference`).

    plant: the cloud (metres, or the unit its flowers are measured in); candidates:
    indices into it of the points taken from the detections (or given as candidates).
    Those of a flower's colour (`config.candidates`) lose their outliers, DBSCAN groups
    them, a group is kept when its colours are a flower's (`min_flower_fraction`,
    `min_white_fraction`), a group holding several pistils is split between them, and each
    part must be a corolla round a centre (`min_coverage`) of about the cloud's typical
    size (`min_size_ratio`). A part with a pistil that fails the coverage test and reaches
    farther than `reach_ratio` typical radii from it (a flower among sheened leaves of
    petal colour) keeps what lies within them. When the flowers so found measure
    outside the size band, the limits are scaled to them and the grouping runs again.
    """
    # Colour classes of the candidates only (the rest of the cloud is never clustered),
    # held in cloud-sized masks so every later step indexes them by cloud index.
    hsv = rgb_to_hsv(plant.colors[candidates])
    white, centre = np.zeros(len(plant), bool), np.zeros(len(plant), bool)
    white[candidates] = (hsv[:, 1] <= colour.petal_max_saturation
                         if config.white_rule == "saturation" else petal_mask(hsv, colour))
    centre[candidates] = pistil_mask(hsv, colour)
    flower_coloured = candidates[white[candidates] | centre[candidates]]
    if config.candidates == "flower_colour":
        candidates = flower_coloured
    flower = white | centre
    candidates = _thinned_to_reference(plant.points, candidates, flower_coloured, config)

    # Parts depend on the applied limits alone: a pass whose sizing leaves them as they
    # were (a dense cloud's, at its counts as stated) reuses them.
    parts_at: dict[tuple[OutlierConfig, ClusterConfig], list[np.ndarray]] = {}

    def at(sizing: Sizing) -> tuple[tuple[list[np.ndarray], float | None, ClusterConfig,
                                          Density], float | None, float | None]:
        sized_outliers, sized, density = for_cloud(outliers, config, sizing.scale,
                                                   sizing.spacing)
        area = None if sizing.spacing is None else sizing.spacing ** 2
        key = (sized_outliers, sized)
        if key not in parts_at:
            parts_at[key] = _parts(plant, candidates, white, centre, sized_outliers, sized)
        clusters, typical, size, joined = _group(plant, parts_at[key], white, centre, sized,
                                                 area)
        # The flowers' spacing sizes the next pass without the pieces joined to them.
        members = np.concatenate([np.zeros(0, np.int64), *clusters])
        return ((joined, typical, sized, density), size,
                cloud_spacing(plant.points[members[flower[members]]], sized))

    sizing, (clusters, typical, applied, density), size = sized_to_cloud(
        at, config.size_band_m, lambda: cloud_spacing(plant.points[flower_coloured], config))
    return Grouping(clusters, typical, size, sizing.scale, density, applied)


#: Candidates denser than this many times `density_reference` are grouped from a seeded
#: uniform subsample at the reference density: the flowers are the same, the grouping's
#: cost grows with the points each one has within `eps` (a million-point cloud: 5 times
#: the reference).
DENSE_GROUPING = 2.0


def _thinned_to_reference(points: np.ndarray, candidates: np.ndarray,
                          flower_coloured: np.ndarray, config: ClusterConfig) -> np.ndarray:
    """The candidates a grouping uses: all of them, or, in a cloud denser than
    DENSE_GROUPING times the reference, a seeded uniform share of them at the reference
    density (crops are then taken from the whole cloud)."""
    if config.density_reference is None or len(flower_coloured) < 2:
        return candidates
    area = surface_area_per_point(points[flower_coloured], config.eps)
    neighbours = np.pi * config.eps ** 2 / area
    if neighbours <= DENSE_GROUPING * config.density_reference:
        return candidates
    keep = np.random.default_rng(0).random(len(candidates)) < (config.density_reference
                                                               / neighbours)
    return candidates[keep]


def cloud_spacing(points: np.ndarray, config: ClusterConfig) -> float | None:
    """The point spacing of a cloud's flower-coloured points (N, 3) that sizes the limits
    (`cluster_config.for_cloud`): the square root of the area each stands for; None where the
    density is not to size them (`density_reference` unset) or too few points measure it."""
    if config.density_reference is None:
        return None
    area = surface_area_per_point(points, config.eps)
    return None if area is None or area <= 0 else float(np.sqrt(area))


def _parts(plant: Cloud, candidates: np.ndarray, white: np.ndarray, centre: np.ndarray,
           outliers: OutlierConfig, config: ClusterConfig) -> list[np.ndarray]:
    """The candidate flowers of one grouping at these limits (indices into the cloud):
    outliers removed, DBSCAN clusters of a flower's colours (`min_flower_fraction`,
    `min_white_fraction`), each split between its pistils. white, centre: cloud-sized
    masks of petal and pistil colour."""
    if len(candidates) == 0:
        return []
    kept = candidates[remove_outliers(plant.points[candidates], outliers)]
    labels = dbscan(plant.points[kept], config.eps, config.min_points)
    order = np.argsort(labels, kind="stable")
    edges = np.searchsorted(labels[order], np.arange(labels.max(initial=-1) + 2))
    parts = []
    for k in range(len(edges) - 1):
        members = kept[order[edges[k]:edges[k + 1]]]
        if ((white[members] | centre[members]).mean() <= config.min_flower_fraction
                or white[members].mean() < config.min_white_fraction):
            continue
        points = plant.points[members]
        split = (split_by_centres(points, substantial(pistil_clusters(points, centre[members],
                                                                      config)),
                                  config.split_min_separation_m, config.split_link_m)
                 if config.split_touching else np.zeros(len(members), np.int64))
        parts.extend(part for part in (members[split == j] for j in range(split.max() + 1))
                     if len(part) >= config.min_points)
    return parts


def _group(plant: Cloud, parts: list[np.ndarray], white: np.ndarray, centre: np.ndarray,
           config: ClusterConfig, cloud_area: float | None
           ) -> tuple[list[np.ndarray], float | None, float | None, list[np.ndarray]]:
    """The flowers among one grouping's parts (`_parts`): their typical radius
    (`typical_radius`), their size: the median radius of the flowers kept, each counted by
    its points, so that a cloud's small fragments, which shrink with the limits, do not
    decide how big its flowers are; and the flowers each joined by the pieces of its
    corolla a gap cut off (`_with_fragments`)."""
    if not parts:
        return [], None, None, []

    def analyse(part: np.ndarray) -> Corolla:
        return corolla(plant.points[part], white[part], centre[part], config, cloud_area)

    corollas = [analyse(part) for part in parts]
    counts = [len(part) for part in parts]
    typical = typical_radius(corollas, config, counts)
    if typical is None:
        return [], None, None, []
    flowers, radii, centres, fragments = [], [], [], []
    for part, shape in zip(parts, corollas, strict=True):
        if shape.coverage < config.min_coverage and shape.has_pistil:
            within = (np.linalg.norm(plant.points[part] - shape.centre, axis=1)
                      <= config.reach_ratio * typical)
            if within.all() or within.sum() < config.min_points:
                continue
            part = part[within]
            shape = analyse(part)
        if (shape.coverage >= config.min_coverage
                and shape.radius >= config.min_size_ratio * typical):
            flowers.append(part)
            radii.append(shape.radius)
            centres.append(shape.centre)
        elif not shape.has_pistil:
            fragments.append(part)
    return (flowers, typical, _weighted_median(radii, [len(f) for f in flowers]),
            _with_fragments(plant.points, flowers, centres, fragments,
                            config.reach_ratio * typical))


def _with_fragments(points: np.ndarray, flowers: list[np.ndarray], centres: list[np.ndarray],
                    fragments: list[np.ndarray], reach: float) -> list[np.ndarray]:
    """The flowers (indices into `points`, with their `centres`) each joined by the
    fragments without a pistil that lie wholly within `reach` (the cloud's unit) of its
    centre, nearer it than any other's: on a sparse cloud a gap between petals wider than
    DBSCAN's radius cuts a corolla in two, and the piece without the pistil, too small to
    be a flower, would leave the crop a one-sided corolla (the authors' plant 3 thinned to
    7 %: a flower's 12 of 36 petal points, its plane 16 degrees off where the whole
    corolla's was 6)."""
    if not flowers or not fragments:
        return flowers
    joined = [[flower] for flower in flowers]
    centre = np.asarray(centres)
    for fragment in fragments:
        offset = points[fragment][:, None, :] - centre[None, :, :]
        farthest = np.linalg.norm(offset, axis=2).max(axis=0)
        nearest = int(np.argmin(np.linalg.norm(offset.mean(axis=0), axis=1)))
        if farthest[nearest] <= reach:
            joined[nearest].append(fragment)
    return [np.concatenate(parts) for parts in joined]


def _weighted_median(values: list[float], weights: list[int]) -> float | None:
    """The median of values counted `weights` times each (None when there are none)."""
    if not values:
        return None
    order = np.argsort(values)
    cumulative = np.cumsum(np.asarray(weights, np.float64)[order])
    return float(np.asarray(values)[order][np.searchsorted(cumulative, cumulative[-1] / 2)])


def split_by_centres(points: np.ndarray, centres: list[np.ndarray], min_separation: float,
                     link_m: float) -> np.ndarray:
    """(N,) labels assigning points (N, 3) to the geodesically nearest flower centre.

    centres: per candidate centre, indices into `points` of its pistil points. A centre
    whose centroid lies within `min_separation` metres of an earlier one joins it, so one
    flower with a patchy centre never splits. Distances run along the surface, through a
    graph linking points closer than `link_m` metres: touching flowers meet only at their
    rims, so each petal reaches its own pistil first, which a straight-line (Voronoi) split
    gets wrong when the flowers tilt against each other.
    """
    groups: list[list[np.ndarray]] = []
    for centre in centres:
        centroid = points[centre].mean(axis=0)
        for group in groups:
            if np.linalg.norm(points[group[0]].mean(axis=0) - centroid) < min_separation:
                group.append(centre)
                break
        else:
            groups.append([centre])
    if len(groups) <= 1:
        return np.zeros(len(points), np.int64)
    sources = np.concatenate([np.concatenate(g) for g in groups])
    source_group = np.repeat(np.arange(len(groups)), [sum(len(c) for c in g) for g in groups])
    tree = cKDTree(points)
    graph = tree.sparse_distance_matrix(tree, link_m, output_type="coo_matrix")
    _, _, nearest_source = dijkstra(graph.tocsr(), directed=False, indices=sources,
                                    min_only=True, return_predecessors=True)
    labels = np.empty(len(points), np.int64)
    reached = nearest_source >= 0
    position = np.searchsorted(np.sort(sources), nearest_source[reached])
    labels[reached] = source_group[np.argsort(sources)][position]
    if not reached.all():
        centroids = np.array([points[np.concatenate(g)].mean(axis=0) for g in groups])
        _, labels[~reached] = cKDTree(centroids).query(points[~reached])
    return labels


#: Most voxels `near_voxels` looks up in a table (a byte each) rather than by sorting.
LOOKUP_VOXELS = 1 << 24


def near_voxels(points: np.ndarray, around: np.ndarray, margin: float) -> np.ndarray:
    """Indices of `points` (N, 3) in a voxel of edge `margin` next to (or holding) a voxel
    of `around` (M, 3): every point within `margin` of one of them, and a few more, found
    without a distance per point."""
    low = around.min(axis=0) - 2 * margin
    shape = np.floor((around.max(axis=0) + 2 * margin - low) / margin).astype(np.int64) + 1
    inside = np.flatnonzero(np.all((points >= low + margin) & (points < low + (shape - 1)
                                                                      * margin), axis=1))

    def keys(cells: np.ndarray) -> np.ndarray:
        return (cells[:, 0] * shape[1] + cells[:, 1]) * shape[2] + cells[:, 2]

    # A key is linear in the cell, so a neighbour's key is the cell's plus the step's.
    cells = np.unique(keys(np.floor((around - low) / margin).astype(np.int64)))
    steps = keys(np.array(np.meshgrid(*[(-1, 0, 1)] * 3, indexing="ij")).reshape(3, -1).T)
    occupied = np.unique((cells[:, None] + steps[None]).ravel())
    found = keys(np.floor((points[inside] - low) / margin).astype(np.int64))
    if np.prod(shape) > LOOKUP_VOXELS:
        return inside[np.isin(found, occupied)]
    table = np.zeros(int(np.prod(shape)), bool)
    table[occupied] = True
    return inside[table[found]]


def crop_flowers(cloud: Cloud, clusters: list[np.ndarray],
                 config: ClusterConfig) -> tuple[list[OrientedBox], list[np.ndarray]]:
    """Each cluster's oriented box, and its crop (`config.crop`): the cloud points within
    `crop_margin_m` metres of the cluster's points, or those in its box.

    clusters: per flower, indices into `cloud`. Near a cluster, every point goes to the
    flower with the nearest cluster point, so touching flowers never share points.
    """
    if not clusters:
        return [], []
    boxes = [oriented_box(cloud.points[idx]) for idx in clusters]
    if config.crop == "box":
        return boxes, [np.flatnonzero(box.contains(cloud.points)) for box in boxes]
    margin = config.crop_margin_m
    members = np.concatenate(clusters)
    labels = np.repeat(np.arange(len(clusters)), [len(c) for c in clusters])
    near = near_voxels(cloud.points, cloud.points[members], margin)
    distance, nearest = cKDTree(cloud.points[members]).query(
        cloud.points[near], distance_upper_bound=margin)
    hit = np.isfinite(distance)
    owner = labels[nearest[hit]]
    order = np.argsort(owner, kind="stable")
    bounds = np.searchsorted(owner[order], np.arange(len(clusters) + 1))
    picked = near[hit][order]
    return boxes, [picked[bounds[k]:bounds[k + 1]] for k in range(len(clusters))]
