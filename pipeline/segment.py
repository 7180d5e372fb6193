"""From back-projected candidate points to one point set per flower.

Ground removal, statistical then radius outlier removal, DBSCAN, the whiteness filter,
splitting clusters that hold several flower centres (touching flowers), and an oriented box
per flower whose contents in the full cloud become the flower's crop.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.spatial import cKDTree

from flowerpose.cloudio import Cloud
from flowerpose.pipeline.colour import rgb_to_hsv


@dataclass(frozen=True)
class GroundConfig:
    """Removing the soil before projection (the paper cropped it by hand)."""

    method: Literal["plane", "height", "none"] = "plane"
    """"plane": RANSAC the soil plane, falling back to "height" when no near-horizontal plane
    lies under the plant; "height": the bed frame's z = 0 is the soil; "none": keep all."""
    clearance_m: float = 0.01
    """Points closer than this above the soil are removed, metres."""
    plane_distance_m: float = 0.005
    """RANSAC inlier distance, metres."""
    max_tilt_deg: float = 15.0
    """A fitted plane more tilted than this from horizontal is not the soil, degrees."""
    min_inlier_fraction: float = 0.15
    """A plane holding fewer of the points than this is not the soil."""
    sample_points: int = 30_000
    """Points used for the RANSAC fit (a random subset, for speed)."""


@dataclass(frozen=True)
class OutlierConfig:
    """Outlier removal on the merged candidate points (before DBSCAN)."""

    statistical_neighbours: int = 100
    """Statistical outlier removal: neighbours averaged (upstream: 100)."""
    statistical_std_ratio: float = 0.5
    """Statistical outlier removal: points whose mean neighbour distance exceeds the mean by
    this many standard deviations are dropped (upstream: 0.5)."""
    radius_points: int = 15
    """Radius outlier removal: neighbours needed within `radius_m` (upstream: 15)."""
    radius_m: float = 0.01
    """Radius outlier removal: radius, metres (upstream: 0.01)."""


@dataclass(frozen=True)
class ClusterConfig:
    """Grouping candidate points into flowers."""

    eps: float = 0.01
    """DBSCAN neighbourhood radius, metres (the paper: 0.01)."""
    min_points: int = 20
    """DBSCAN core-point neighbour count (the paper: 20)."""
    min_flower_fraction: float = 0.7
    """A cluster is a flower when more than this share of its points is whitish or has the
    pistil's yellow (deviation: upstream counted whitish points alone, which rejects flowers
    seen face-on, where the yellow centre is a third of the points)."""
    min_white_fraction: float = 0.35
    """... and at least this share is whitish: a flower has petals."""
    white_max_saturation: float = 0.39
    """Whitish: saturation at most this (upstream)."""
    split_min_separation_m: float = 0.012
    """Flower centres (pistil clusters) this far apart inside one cluster split it into one
    flower per centre, metres: touching flowers merge under DBSCAN."""
    box_margin_m: float = 0.004
    """Each flower's oriented box grows by this on every side before cropping the full
    cloud, metres, so the receptacle, sepals and petal edges come along."""


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
    mean = points.mean(axis=0)
    _, vectors = np.linalg.eigh(np.cov((points - mean).T) if len(points) > 1 else np.eye(3))
    if np.linalg.det(vectors) < 0:
        vectors[:, 0] = -vectors[:, 0]
    local = (points - mean) @ vectors
    low, high = local.min(axis=0), local.max(axis=0)
    return OrientedBox(mean + vectors @ ((low + high) / 2), vectors, high - low)


def remove_ground(cloud: Cloud, config: GroundConfig, seed: int = 0) -> np.ndarray:
    """Indices of the points that are not soil. cloud in metres, bed frame (z up)."""
    if config.method == "none" or len(cloud) == 0:
        return np.arange(len(cloud))
    points = cloud.points
    height = points[:, 2]
    if config.method == "plane" and len(cloud) >= 100:
        plane = _soil_plane(points, config, seed)
        if plane is not None:
            normal, offset = plane
            height = points @ normal + offset
    return np.flatnonzero(height >= config.clearance_m)


def _soil_plane(points: np.ndarray, config: GroundConfig, seed: int):
    """(unit normal pointing up, offset) of the soil plane, or None when there is none."""
    import open3d as o3d

    rng = np.random.default_rng(seed)
    sample = points if len(points) <= config.sample_points else points[
        rng.choice(len(points), config.sample_points, replace=False)]
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(sample))
    o3d.utility.random.seed(seed)
    (a, b, c, d), inliers = pcd.segment_plane(config.plane_distance_m, 3, 500)
    normal = np.array([a, b, c])
    scale = np.linalg.norm(normal)
    if scale == 0:
        return None
    normal, offset = normal / scale, d / scale
    if normal[2] < 0:
        normal, offset = -normal, -offset
    tilt = np.degrees(np.arccos(np.clip(normal[2], -1, 1)))
    if tilt > config.max_tilt_deg or len(inliers) < config.min_inlier_fraction * len(sample):
        return None
    # The soil lies under the plant: a leaf-sized plane with most points below it is not soil.
    if np.mean(sample @ normal + offset < -config.plane_distance_m) > 0.1:
        return None
    return normal, offset


def remove_outliers(points: np.ndarray, config: OutlierConfig) -> np.ndarray:
    """Indices of points (N, 3) kept by statistical then radius outlier removal."""
    import open3d as o3d

    keep = np.arange(len(points))
    if len(points) > 2 and config.statistical_neighbours > 0:
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        neighbours = min(config.statistical_neighbours, len(points) - 1)
        _, kept = pcd.remove_statistical_outlier(neighbours, config.statistical_std_ratio)
        keep = keep[np.asarray(kept, dtype=np.int64)]
    if len(keep) and config.radius_points > 0:
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points[keep]))
        _, kept = pcd.remove_radius_outlier(config.radius_points, config.radius_m)
        keep = keep[np.asarray(kept, dtype=np.int64)]
    return keep


def dbscan(points: np.ndarray, eps: float, min_points: int) -> np.ndarray:
    """(N,) int cluster labels of points (N, 3), -1 for noise (Open3D's DBSCAN)."""
    import open3d as o3d

    if len(points) == 0:
        return np.zeros(0, np.int64)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    return np.asarray(pcd.cluster_dbscan(eps, min_points, print_progress=False), np.int64)


def is_whitish(colors: np.ndarray, max_saturation: float) -> np.ndarray:
    """(N,) bool: colours (N, 3) uint8 with saturation at most `max_saturation`."""
    return rgb_to_hsv(colors)[:, 1] <= max_saturation


def split_by_centres(points: np.ndarray, centres: np.ndarray,
                     min_separation: float) -> np.ndarray:
    """(N,) labels assigning points (N, 3) to the nearest of well-separated centres (K, 3).

    Centres closer than `min_separation` metres to an earlier one are merged into it, so a
    single flower with a patchy centre never splits.
    """
    kept: list[np.ndarray] = []
    for centre in centres:
        if all(np.linalg.norm(centre - k) >= min_separation for k in kept):
            kept.append(centre)
    if len(kept) <= 1:
        return np.zeros(len(points), np.int64)
    _, nearest = cKDTree(np.array(kept)).query(points)
    return nearest.astype(np.int64)


def crop_flowers(cloud: Cloud, clusters: list[np.ndarray],
                 margin: float) -> tuple[list[OrientedBox], list[np.ndarray]]:
    """Each cluster's oriented box and the full-cloud points inside it.

    clusters: per flower, indices into `cloud`. A point inside several grown boxes goes to
    the flower whose cluster has the nearest point, so touching flowers do not share points.
    """
    boxes = [oriented_box(cloud.points[idx]) for idx in clusters]
    if not boxes:
        return [], []
    inside = np.stack([box.contains(cloud.points, margin) for box in boxes])
    owner = np.argmax(inside, axis=0)
    shared = inside.sum(axis=0) > 1
    if shared.any():
        members = np.concatenate(clusters)
        labels = np.repeat(np.arange(len(clusters)), [len(c) for c in clusters])
        _, nearest = cKDTree(cloud.points[members]).query(cloud.points[shared])
        owner[shared] = labels[nearest]
    any_inside = inside.any(axis=0)
    crops = [np.flatnonzero(any_inside & (owner == k)) for k in range(len(boxes))]
    return boxes, crops
