"""Removing the soil from a plant's cloud before projection (the paper cropped it by hand):
the soil plane found by RANSAC, or the bed frame's z = 0."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from flowerpose.cloudio import Cloud
from flowerpose.config import require
from flowerpose.log import open3d


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
    sample_points: int = 10_000
    """Points used for the RANSAC fit (a random subset, for speed: 10,000 find the same soil
    as 30,000 on the benchmark plants in a third of the time)."""

    def __post_init__(self):
        require(self.clearance_m >= 0, "ground.clearance_m", "must be 0 or more")
        require(self.plane_distance_m > 0, "ground.plane_distance_m", "must be positive")
        require(0 <= self.max_tilt_deg <= 90, "ground.max_tilt_deg", "must be 0-90 degrees")
        require(0 <= self.min_inlier_fraction <= 1, "ground.min_inlier_fraction",
                "must be within 0-1")
        require(self.sample_points >= 100, "ground.sample_points", "must be at least 100")


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
    o3d = open3d()
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
