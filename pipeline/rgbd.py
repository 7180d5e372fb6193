"""RGB-D fusion: depth frames from a camera on the head, fused into one coloured cloud.

The paper's suggested future work. An RGB-D scan folder is a scan folder (flowerpose.scanio)
with `depth/depth_NNNNNN.png` beside each `frames/frame_NNNNNN.jpg`: 16-bit depth along the
optical axis in units of `depth_unit_m` (camera.json; 0 = no measurement), aligned pixel for
pixel with the colour image, whose intrinsics camera.json gives. Every valid pixel is lifted
into the bed frame with its frame's pose from trajectory.csv; the union is voxel-averaged
and cleaned of stray points.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from flowerpose.cloudio import Cloud
from flowerpose.config import require
from flowerpose.errors import InputError
from flowerpose.jsonio import read_json
from flowerpose.log import open3d
from flowerpose.scanio import Intrinsics, read_intrinsics, read_trajectory
from flowerpose.stopwatch import Stopwatch

DEPTH_PATTERN = "depth_{:06d}.png"


@dataclass(frozen=True)
class FusionConfig:
    """How RGB-D frames become one cloud."""

    voxel_m: float = 0.0015
    """Voxel edge of the fused cloud, metres: points in a voxel are averaged (position and
    colour). About the oracle clouds' spacing on flowers."""
    max_depth_m: float = 0.8
    """Depths beyond this are dropped, metres: the bed beyond the plant."""
    min_views: int = 6
    """A voxel is kept when at least this many frames put a point in it. A surface is seen
    from many views; a flying pixel (a depth between two surfaces at an edge) lands
    somewhere different in each view, and without this test their sum outweighs the
    surface (realistic seed 0: median error 10.8 mm with no test, 0.27 mm at 3 views, 0.18
    mm at 6, completeness at 5 mm 1.0 and 0.999)."""
    crop_radius_m: float = 0.35
    """Points farther than this from the scanned plant's axis (scan.json's plan) are left
    out, metres: the bed around it is neither plant nor needed."""
    outlier_neighbours: int = 20
    """Statistical outlier removal after fusion: neighbours averaged (0: off)."""
    outlier_std_ratio: float = 2.0
    """... and the spread beyond which a point is dropped."""

    def __post_init__(self):
        require(self.voxel_m > 0, "fusion.voxel_m", "must be positive (metres)")
        require(self.max_depth_m > 0, "fusion.max_depth_m", "must be positive (metres)")
        require(self.outlier_neighbours >= 0, "fusion.outlier_neighbours", "must be 0 or more")
        require(self.min_views >= 1, "fusion.min_views", "must be at least 1")


def lift(depth: np.ndarray, rgb: np.ndarray, camera_to_bed: np.ndarray, intrinsics: Intrinsics,
         max_depth_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Bed-frame points (N, 3) and colours (N, 3) uint8 of a depth image's valid pixels.

    depth: (H, W) metres along the optical axis, 0 = none; rgb: (H, W, 3) uint8 aligned;
    camera_to_bed: (4, 4), OpenCV axes. Pixel centres at +0.5 (camera.json's convention).
    """
    rows, cols = np.nonzero((depth > 0) & (depth <= max_depth_m))
    z = depth[rows, cols].astype(np.float64)
    x = (cols + 0.5 - intrinsics.cx) / intrinsics.fx * z
    y = (rows + 0.5 - intrinsics.cy) / intrinsics.fy * z
    local = np.stack([x, y, z], axis=1)
    points = local @ camera_to_bed[:3, :3].T + camera_to_bed[:3, 3]
    return points, rgb[rows, cols]


def voxel_fuse(points: np.ndarray, colours: np.ndarray, views: np.ndarray, voxel_m: float,
               min_views: int) -> tuple[np.ndarray, np.ndarray]:
    """Average the points (N, 3) and colours (N, 3) of each voxel seen by >= min_views
    distinct views (views: (N,) frame index of each point). Returns (M, 3) points and
    (M, 3) float colours 0-255."""
    cells = np.floor(points / voxel_m).astype(np.int64)
    cells -= cells.min(axis=0)
    size = cells.max(axis=0) + 1
    # One integer per voxel (and per voxel and view): 1-D unique is far faster than rows.
    keys = (cells[:, 0] * size[1] + cells[:, 1]) * size[2] + cells[:, 2]
    voxel, inverse = np.unique(keys, return_inverse=True)
    pairs = np.unique(inverse * (int(views.max()) + 1) + views)
    support = np.bincount(pairs // (int(views.max()) + 1), minlength=len(voxel))
    count = np.bincount(inverse, minlength=len(voxel)).astype(np.float64)
    kept = support >= min_views

    def mean(values: np.ndarray) -> np.ndarray:
        sums = np.stack([np.bincount(inverse, weights=values[:, i], minlength=len(voxel))
                         for i in range(3)], axis=1)
        return (sums / count[:, None])[kept]

    return mean(points), mean(colours.astype(np.float64))


def fuse_rgbd_scan(scan_dir: Path, config: FusionConfig = FusionConfig()) -> tuple[Cloud, dict]:
    """The fused cloud of an RGB-D scan folder (bed frame, metres) and a report."""
    o3d = open3d()
    watch = Stopwatch()
    scan_dir = Path(scan_dir)
    intrinsics = read_intrinsics(scan_dir / "camera.json")
    unit = float(read_json(scan_dir / "camera.json").get("depth_unit_m", 0.001))
    trajectory = read_trajectory(scan_dir / "trajectory.csv")
    plan = read_json(scan_dir / "scan.json").get("plan", {}) if (scan_dir / "scan.json").exists() \
        else {}
    center = np.asarray(plan.get("plant_center", [np.nan, np.nan]), float)[:2]
    points, colours, views, used = [], [], [], 0
    for row, index in enumerate(trajectory.frame):
        depth_path = scan_dir / "depth" / DEPTH_PATTERN.format(int(index))
        colour_path = scan_dir / "frames" / f"frame_{int(index):06d}.jpg"
        if not depth_path.exists():
            continue
        depth = cv2.imread(str(depth_path), cv2.IMREAD_UNCHANGED)
        bgr = cv2.imread(str(colour_path), cv2.IMREAD_COLOR)
        if depth is None or bgr is None or depth.shape != bgr.shape[:2]:
            raise InputError(depth_path, "unreadable, or not the size of its colour frame")
        if depth.shape != (intrinsics.height, intrinsics.width):
            raise InputError(depth_path, "not the size camera.json gives")
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = trajectory.camera_rotation[row], trajectory.camera_position[row]
        p, c = lift(depth.astype(np.float32) * unit, cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), pose,
                    intrinsics, config.max_depth_m)
        if np.isfinite(center).all():
            near = np.linalg.norm(p[:, :2] - center, axis=1) <= config.crop_radius_m
            p, c = p[near], c[near]
        points.append(p)
        colours.append(c)
        views.append(np.full(len(p), used, np.int64))
        used += 1
    if used == 0:
        raise InputError(scan_dir, "no depth/ frames: not an RGB-D scan")
    fused, fused_colours = voxel_fuse(np.concatenate(points), np.concatenate(colours),
                                      np.concatenate(views), config.voxel_m, config.min_views)
    raw = sum(len(p) for p in points)
    if raw and not len(fused):
        # Each pixel's footprint wider than a voxel: no voxel gathers min_views frames.
        raise InputError(scan_dir, f"no {config.voxel_m * 1000:g} mm voxel holds points of "
                         f"{config.min_views} frames (fusion.min_views) among {raw} points of "
                         f"{used} frames: each pixel covers more than a voxel; raise "
                         "fusion.voxel_m or lower fusion.min_views, or record larger frames")
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(fused))
    pcd.colors = o3d.utility.Vector3dVector(fused_colours / 255.0)
    if config.outlier_neighbours and len(pcd.points) > config.outlier_neighbours:
        pcd, _ = pcd.remove_statistical_outlier(config.outlier_neighbours,
                                                config.outlier_std_ratio)
    cloud = Cloud(np.asarray(pcd.points), np.clip(np.asarray(pcd.colors) * 255 + 0.5, 0,
                                                  255).astype(np.uint8))
    report = {"frames": used, "raw_points": raw, "points": len(cloud),
              "seconds": round(watch.elapsed(), 3)}
    return cloud, report
