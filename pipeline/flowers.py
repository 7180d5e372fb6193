"""The detect stage: a cloud in, flowers with their normals out (`flowers.json`).

    ground removal -> translating occupancy grid -> 2D detection -> back-projection
    -> outlier removal + DBSCAN -> whiteness filter -> split touching flowers
    -> oriented boxes -> crops -> petal / pistil split -> plane, superellipsoid, paraboloid
"""

from __future__ import annotations

from collections.abc import Collection, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from scipy.spatial import cKDTree

from flowerpose.cloudio import Cloud, empty_ply
from flowerpose.config import to_dict
from flowerpose.errors import InputError
from flowerpose.jsonio import object_list, read_json, unit3, vector3, write_json
from flowerpose.log import LOG, open3d
from flowerpose.pipeline.cluster_config import ClusterConfig, OutlierConfig, for_cloud
from flowerpose.pipeline.colour import (
    ColourConfig,
    petal_mask,
    pistil_mask,
    rgb_to_hsv,
    sepal_mask,
    white_balanced,
)
from flowerpose.pipeline.detect import DetectConfig, backproject, make_detector
from flowerpose.pipeline.detection import Detection
from flowerpose.pipeline.envelope import CloudMeasure
from flowerpose.pipeline.grid import GridConfig, Projection, project_all
from flowerpose.pipeline.ground import GroundConfig, remove_ground
from flowerpose.pipeline.limits import Density, Sizing, sized_to_cloud
from flowerpose.pipeline.pose import FlowerPose, PoseConfig, estimate_pose, pose_for_density
from flowerpose.pipeline.segment import (
    OrientedBox,
    cloud_spacing,
    cluster_flowers,
    corolla,
    crop_flowers,
    near_voxels,
    typical_radius,
)
from flowerpose.srgb import relight
from flowerpose.stopwatch import Stopwatch

#: Up in the bed frame a whole plant's cloud is in (DESIGN.md: metres, z up).
BED_UP = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class PipelineConfig:
    """Every setting of the field pipeline, one section per stage."""

    colour: ColourConfig = field(default_factory=ColourConfig)
    ground: GroundConfig = field(default_factory=GroundConfig)
    grid: GridConfig = field(default_factory=GridConfig)
    detect: DetectConfig = field(default_factory=DetectConfig)
    outliers: OutlierConfig = field(default_factory=OutlierConfig)
    cluster: ClusterConfig = field(default_factory=ClusterConfig)
    pose: PoseConfig = field(default_factory=PoseConfig)


#: Where the pipeline starts: a whole cloud, a detector's candidate points (the cluster
#: stage), or one flower's crop a file (the pose stage).
Start = Literal["cloud", "candidates", "crops"]

#: The config sections each start reads: the stages that run from there.
SECTIONS_FROM: dict[str, tuple[str, ...]] = {
    "cloud": ("colour", "ground", "grid", "detect", "outliers", "cluster", "pose"),
    "candidates": ("colour", "outliers", "cluster", "pose"),
    "crops": ("colour", "cluster", "pose"),
}


def sections_run(config: PipelineConfig, starts: Iterable[Start]) -> dict:
    """The config's sections that runs from these starts read, JSON-ready, in the
    config's order: what a report records of the settings (a skipped stage's are not)."""
    read = {name for start in starts for name in SECTIONS_FROM[start]}
    return {name: value for name, value in to_dict(config).items() if name in read}


@dataclass
class Flower:
    """One detected flower."""

    id: int
    pose: FlowerPose
    box: OrientedBox
    crop: np.ndarray
    """Indices of the flower's points in the input cloud."""

    def to_json(self) -> dict:
        entry = {"id": self.id}
        entry.update(self.pose.to_json())
        entry["box"] = self.box.to_json()
        return entry


@dataclass
class FlowerResult:
    """Everything the detect stage found, with what it saw on the way."""

    flowers: list[Flower]
    projections: list[Projection]
    detections: list[list[Detection]]
    timing_s: dict[str, float]
    detection_flowers: list[list[int | None]] = field(default_factory=list)
    """Per view, per detection: the id of the flower most of its points went to, or None
    (its points were no flower's), so the views can number their boxes as flowers.json."""
    measure: CloudMeasure | None = None
    """What the run measured of its cloud against the operating envelope."""

    def to_json(self) -> dict:
        body = {"flowers": [f.to_json() for f in self.flowers], "timing_s": self.timing_s}
        if self.measure is not None:
            body["cloud"] = self.measure.to_json()
        return body


def find_flowers(cloud: Cloud, config: PipelineConfig = PipelineConfig(),
                 up: np.ndarray | None = BED_UP, drop_views: Collection[int] = ()
                 ) -> FlowerResult:
    """Flowers and their normals in a whole plant's coloured cloud (metres, bed frame, z up).
    up: the frame's up, for the direction prior (`PoseConfig.up_prior`); None for a cloud
    whose up is not known (a phone scan's own frame). drop_views: positions of grid views
    whose detections are left out (a robustness test: a view the detector missed)."""
    timer = Stopwatch()
    colors, gain = white_balanced(cloud.colors, config.colour)
    cloud = Cloud(cloud.points, colors)
    above_ground, projections = grid_views(cloud, config, timer, balance=False)
    plant = cloud.subset(above_ground)
    detector = make_detector(config.detect, config.colour)
    detections = [[] if k in drop_views else detector(p.image, p.occupied, p.pixel_size_m)
                  for k, p in enumerate(projections)]
    timer.lap("detect")
    picked = [backproject(d, p.index, config.detect.backproject)
              for d, p in zip(detections, projections, strict=True)]
    candidates = np.unique(np.concatenate([np.zeros(0, np.int64)] + [i for v in picked for i in v]))
    timer.lap("backproject")
    flowers, radius = _flowers_among(plant, candidates, above_ground, config, timer, up)
    owner = np.full(len(cloud), -1, np.int64)
    for flower in flowers:
        owner[flower.crop] = flower.id
    return FlowerResult(flowers, projections, detections, timer.report(digits=6),
                        [[_owner_of(owner[above_ground[points]]) for points in view]
                         for view in picked], _measured("detect", flowers, radius, gain))


def grid_views(cloud: Cloud, config: PipelineConfig, timer: Stopwatch | None = None,
               balance: bool = True) -> tuple[np.ndarray, list[Projection]]:
    """The views the detector sees: the indices of `cloud`'s points above the ground (metres,
    bed frame, z up), and the grid's projections of those points (their `index` maps pixels
    into them), in white-balanced colours (`colour.white_balance`; `balance` False: the
    cloud's colours are balanced already)."""
    if balance:
        cloud = Cloud(cloud.points, white_balanced(cloud.colors, config.colour)[0])
    above_ground = remove_ground(cloud, config.ground)
    if timer is not None:
        timer.lap("ground")
    projections = project_all(cloud.subset(above_ground), config.grid)
    if timer is not None:
        timer.lap("grid")
    return above_ground, projections


def _owner_of(ids: np.ndarray) -> int | None:
    """The flower id most of these points belong to (-1: none), or None."""
    ids = ids[ids >= 0]
    return int(np.bincount(ids).argmax()) if len(ids) else None


def find_flowers_in_candidates(candidates: Cloud,
                               config: PipelineConfig = PipelineConfig()) -> FlowerResult:
    """Flowers and their normals among points already taken out of grid views (a
    detector's crops, merged): outlier removal, clustering and pose, no ground removal,
    grid or detection. candidates: metres (or the cloud's unit), any frame; a point that
    several views took counts once (crops index the first copy)."""
    timer = Stopwatch()
    first = candidates.first_copies()
    points = candidates.subset(first)
    colors, gain = white_balanced(points.colors, config.colour)
    points = Cloud(points.points, colors)
    flowers, radius = _flowers_among(points, np.arange(len(points)), first, config, timer, None)
    return FlowerResult(flowers, [], [], timer.report(digits=6),
                        measure=_measured("detect", flowers, radius, gain))


def _measured(stage: str, flowers: list[Flower], radius: float | None,
              gain: np.ndarray) -> CloudMeasure:
    """The cloud's measure against the operating envelope; a warning for each bound the
    cloud crosses."""
    points = [len(f.crop) for f in flowers]
    measure = CloudMeasure(float(np.median(points)) if points else None,
                           None if radius is None else 2 * radius,
                           tuple(float(g) for g in gain))  # type: ignore[arg-type]
    for line in measure.outside(metric=True):
        LOG.warning(f"{stage}: the cloud is outside the operating envelope: {line}")
    return measure


def _flowers_among(plant: Cloud, candidates: np.ndarray, original: np.ndarray,
                   config: PipelineConfig, timer: Stopwatch, up: np.ndarray | None
                   ) -> tuple[list[Flower], float | None]:
    """Clusters, crops and poses of the flowers among `candidates` (indices into `plant`),
    and the cloud's typical flower radius; `original` maps plant indices to those of the
    caller's cloud; `up` is the frame's up where it is known (`PoseConfig.up_prior`)."""
    grouping = cluster_flowers(plant, candidates, config.outliers, config.cluster,
                               config.colour)
    boxes, crops = crop_flowers(plant, grouping.clusters, grouping.config)
    timer.lap("cluster")
    flowers = []
    crop_clouds = [plant.subset(crop) for crop in crops]
    # The crops hold every cloud point near a flower, the candidates only those that owned
    # a pixel of some view: the pose stage's counts follow the crops' own density.
    _, pose_cluster, density = for_cloud(config.outliers, config.cluster, grouping.scale,
                                         crops_spacing(crop_clouds, config))
    pose_config = pose_for_density(config.pose, density)
    sepals_round = _sepals_round(plant, crops, config, grouping.typical_radius)
    for box, crop, crop_cloud, sepals in zip(boxes, crops, crop_clouds, sepals_round,
                                             strict=True):
        pose = estimate_pose(crop_cloud, pose_config, config.colour, pose_cluster,
                             grouping.typical_radius, up, sepals)
        if not pose.pistil_found and config.cluster.require_pistil and (
                density.factor >= config.cluster.pistil_optional_density
                or all(normal is None for normal in pose.normals.values())):
            continue
        flowers.append(Flower(len(flowers), pose, box, original[crop]))
    timer.lap("pose")
    _say_sizes("detect", grouping.size, grouping.scale, config.cluster)
    _say_density("detect", grouping.density)
    LOG.debug(f"detect: {len(candidates)} candidate points, {len(grouping.clusters)} clusters, "
              f"{len(flowers)} flowers")
    return flowers, grouping.typical_radius


#: The cloud round a crop that its support vote may read: within this many typical flower
#: radii of the crop's points (the vote reaches a corolla radius across the flower's axis
#: and `pose.support_reach` along it from the pistil: 1.25 radii).
SUPPORT_ROUND_RADII = 1.5


def _sepals_round(plant: Cloud, crops: list[np.ndarray], config: PipelineConfig,
                  radius: float | None) -> list[np.ndarray | None]:
    """For each crop (indices into `plant`), the points of sepal and stem colour
    (`colour.sepal_mask`) round it and not in it, for the pose's support vote
    (`PoseConfig.support_from_cloud`); None where the vote cannot use them. Only the cloud
    near the crops is looked at: a whole plant's leaves are most of its points."""
    if (not radius or not crops or not config.pose.support_from_cloud
            or config.pose.direction_reference != "combined"):
        return [None] * len(crops)
    reach = SUPPORT_ROUND_RADII * radius
    near = near_voxels(plant.points, plant.points[np.concatenate(crops)], reach)
    near = near[sepal_mask(rgb_to_hsv(plant.colors[near]), config.colour)]
    tree = cKDTree(plant.points[near], balanced_tree=False, compact_nodes=False)
    found = []
    for crop in crops:
        points = plant.points[crop]
        centre = points.mean(axis=0)
        extent = float(np.linalg.norm(points - centre, axis=1).max())
        ball = near[np.asarray(tree.query_ball_point(centre, extent + reach), dtype=np.int64)]
        found.append(plant.points[np.setdiff1d(ball, crop)])
    return found


#: Limits rescaled by more than this factor either way are said at the info level: the
#: cloud is probably not in metres (smaller rescales are routine: debug).
NOTABLE_RESCALE = 2.0


def _say_sizes(stage: str, size: float | None, scale: float, config: ClusterConfig) -> None:
    """Say the flower size measured and how the metric limits were scaled to it; a user
    should know when the cloud is far from the size the limits are stated for."""
    if scale == 1.0:
        LOG.debug(f"{stage}: flower radius {size}")
        return
    low, high = config.size_band_m
    line = (f"{stage}: the flowers' radius is {size:.4g} in the cloud's unit, outside the "
            f"{low:g}-{high:g} the limits are stated for (cluster.size_band_m): limits in "
            f"metres scaled by {scale:.3g}")
    notable = not 1 / NOTABLE_RESCALE <= scale <= NOTABLE_RESCALE
    (LOG.info if notable else LOG.debug)(line)


def _say_density(stage: str, density: Density) -> None:
    """Say how the cloud's density sized the point counts, where it did."""
    if density.factor < 1.0:
        LOG.debug(f"{stage}: {density.neighbours:.3g} points within eps of a flower point, "
                  f"below cluster.density_reference: point counts scaled by "
                  f"{density.factor:.2f}")


def crops_spacing(crops: list[Cloud], config: PipelineConfig) -> float | None:
    """The point spacing of flower crops (`segment.cloud_spacing` of their flower-coloured
    points together), which sizes the pose stage's counts; None: none to measure."""
    hsv = rgb_to_hsv(np.concatenate([np.zeros((0, 3), np.uint8)] + [c.colors for c in crops]))
    coloured = petal_mask(hsv, config.colour) | pistil_mask(hsv, config.colour)
    points = np.concatenate([np.zeros((0, 3))] + [c.points for c in crops])[coloured]
    return cloud_spacing(points, config.cluster)


def pose_crops(crops: list[Cloud], config: PipelineConfig = PipelineConfig()
               ) -> tuple[list[FlowerPose], dict[str, float]]:
    """The pose of each flower crop (one flower a crop, as a detector cut it out), sized by
    the crops' typical flower (`segment.typical_radius`, their median corolla radius when
    none passes the coverage test); returns the poses and the stage timings."""
    timer = Stopwatch()
    _, gain = white_balanced(np.concatenate([c.colors for c in crops]) if crops
                             else np.zeros((0, 3), np.uint8), config.colour)
    if not np.allclose(gain, 1.0):
        crops = [Cloud(c.points, relight(c.colors, gain)) for c in crops]
    masks = []
    for crop in crops:
        hsv = rgb_to_hsv(crop.colors)
        masks.append((petal_mask(hsv, config.colour), pistil_mask(hsv, config.colour)))

    spacing = crops_spacing(crops, config)

    def pistil_limits(sizing: Sizing) -> tuple[tuple[ClusterConfig, Density], float | None,
                                               float | None]:
        _, cluster, density = for_cloud(config.outliers, config.cluster, sizing.scale,
                                        sizing.spacing)
        shapes = [corolla(crop.points, petal, pistil, cluster)
                  for crop, (petal, pistil) in zip(crops, masks, strict=True)]
        radius = typical_radius(shapes, cluster)
        if radius is None and shapes:
            radius = float(np.median([s.radius for s in shapes]))
        return (cluster, density), radius, spacing

    # The pistil search's limits are metric and counts: sized to the crops' flowers and
    # density as the cluster stage sizes its limits (`limits`).
    sizing, (cluster, density), radius = sized_to_cloud(pistil_limits,
                                                        config.cluster.size_band_m,
                                                        lambda: spacing)
    _say_sizes("pose", radius, sizing.scale, config.cluster)
    _say_density("pose", density)
    pose_config = pose_for_density(config.pose, density)
    poses = [estimate_pose(crop, pose_config, config.colour, cluster, radius) for crop in crops]
    timer.lap("pose")
    return poses, timer.report(digits=6)


Frame = Literal["bed", "cloud"]


def write_flowers(path: Path, result: FlowerResult, source: str | Path | None = None,
                  frame: Frame = "bed", notes: Sequence[str] = ()) -> Path:
    """Write `flowers.json` (DESIGN.md's format): the flowers, with the unit (metres), the
    frame their centres and normals are in ("bed": the bed frame, z up; "cloud": the
    input cloud's own, e.g. a Polycam scan's), the cloud they came from and the warnings
    said while reading and detecting (`notes`: what the run assumed of the cloud)."""
    return write_json(path, flowers_document(result.to_json(), source, frame, notes))


def flowers_document(body: dict, source: str | Path | None, frame: Frame,
                     notes: Sequence[str] = ()) -> dict:
    """flowers.json's content: `body` ({"flowers": [...], "timing_s": {...}}) under the
    unit, frame, source and notes that every flowers.json states."""
    return {"units": "m", "frame": frame, "source": None if source is None else str(source),
            "notes": list(notes), **body}


#: Colour of the estimated normals in the PLY exports (MeshLab and CloudCompare show it).
NORMAL_COLOUR = (230, 40, 40)


def write_normals_ply(folder: Path, flowers: list[Flower], method: str = "plane"
                      ) -> tuple[Path, Path]:
    """The flowers' `method` normals for MeshLab and CloudCompare: `flowers.ply`, one point
    per flower at its centre with the normal as nx ny nz, and `normals.ply`, a mesh of one
    arrow per flower from its centre along the normal, as long as the flower's box (the
    cloud's frame and unit, as flowers.json). Flowers without that normal are left out."""
    o3d = open3d()
    from flowerpose.atomic import write_file, write_text

    oriented = [f for f in flowers if f.pose.normals.get(method) is not None]
    centres = np.array([f.pose.center for f in oriented], np.float64).reshape(-1, 3)
    normals = np.array([f.pose.normals[method] for f in oriented], np.float64).reshape(-1, 3)
    points = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(centres))
    points.normals = o3d.utility.Vector3dVector(normals)
    points.colors = o3d.utility.Vector3dVector(np.tile(np.array(NORMAL_COLOUR) / 255.0,
                                                       (len(centres), 1)))
    arrows = o3d.geometry.TriangleMesh()
    for flower, centre, normal in zip(oriented, centres, normals, strict=True):
        length = float(np.max(flower.box.extent))
        arrow = o3d.geometry.TriangleMesh.create_arrow(
            cylinder_radius=0.03 * length, cone_radius=0.07 * length,
            cylinder_height=0.75 * length, cone_height=0.25 * length)
        arrow.rotate(_rotation_from_z(normal), center=(0.0, 0.0, 0.0))
        arrows += arrow.translate(centre)
    if not oriented:  # Open3D writes no empty geometry; an empty PLY still says "none"
        return (write_text(folder / "flowers.ply", empty_ply()),
                write_text(folder / "normals.ply", empty_ply(faces=True)))
    arrows.paint_uniform_color(np.array(NORMAL_COLOUR) / 255.0)
    arrows.compute_vertex_normals()
    cloud_path = write_file(folder / "flowers.ply", lambda tmp: o3d.io.write_point_cloud(
        str(tmp), points, write_ascii=False))
    mesh_path = write_file(folder / "normals.ply", lambda tmp: o3d.io.write_triangle_mesh(
        str(tmp), arrows, write_ascii=False))
    return cloud_path, mesh_path


def _rotation_from_z(direction: np.ndarray) -> np.ndarray:
    """(3, 3) the rotation taking +z to the unit vector `direction` (Rodrigues)."""
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, direction)
    sine, cosine = float(np.linalg.norm(axis)), float(z @ direction)
    if sine < 1e-12:
        return np.eye(3) if cosine > 0 else np.diag([1.0, -1.0, -1.0])
    k = axis / sine
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + sine * cross + (1 - cosine) * cross @ cross


def read_flower_notes(path: Path) -> list[str]:
    """What the detection that wrote a `flowers.json` assumed of its cloud (its "notes";
    none in a file written before they were recorded, or by another tool)."""
    document = read_json(path)
    notes = document.get("notes", []) if isinstance(document, dict) else []
    return [str(note) for note in notes] if isinstance(notes, list) else []


def read_flowers(path: Path) -> list[dict]:
    """The flower entries of a `flowers.json`, checked: a 3D centre and, per method, a
    normal that is `null` or 3 finite numbers (normalised here); centres in metres (a file
    in "mm" is converted, another unit refused). Errors name the file and the flower."""
    document = read_json(path)
    units = document.get("units", "m") if isinstance(document, dict) else "m"
    if units not in ("m", "mm"):
        raise InputError(path, f'"units" must be "m" or "mm", got {units!r}')
    scale = 1e-3 if units == "mm" else 1.0
    checked = []
    for k, entry in enumerate(object_list(document, "flowers", path, "flower")):
        where = f"flower {entry.get('id', k)}"
        normals = entry.get("normals")
        if not isinstance(normals, dict):
            raise InputError(path, f"{where}: 'normals' must be an object of method: "
                             "normal or null")
        box = entry.get("box")
        if isinstance(box, dict) and "extent" in box:
            box = {**box, "extent": scale * vector3(box["extent"], path, f"{where}: box.extent")}
        checked.append({**entry, **({"box": box} if box is not None else {}),
                        "center": scale * vector3(entry.get("center"), path,
                                                  f"{where}: center"),
                        "normals": {m: None if n is None else
                                    unit3(vector3(n, path, f"{where}: normals.{m}"), path,
                                          f"{where}: normals.{m}")
                                    for m, n in normals.items()}})
    return checked
