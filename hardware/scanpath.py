"""The paper's scan path, planned and checked before the bot moves.

A cylinder around the plant (rings of level views aimed at the plant's axis), then a dome
over it (views aimed at the dome centre), as waypoints in travel order: rings bottom to top,
each ring turning the other way from the last, then the dome from its lowest ring to its
highest. Every waypoint is solved to a head pose (inverse kinematics with the yaw flip),
checked against the bot's reach, and checked for collisions with the plant along the moves
between waypoints, each axis on FarmBot's own motion profile.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.spatial import cKDTree

from flowerpose.errors import InputError
from flowerpose.hardware.geometry import PAPER_BOT, BotGeometry
from flowerpose.hardware.kinematics import HeadPose, check_reachable, forward, look_at
from flowerpose.hardware.motion import MotionProfile, move_duration, move_trajectory


@dataclass(frozen=True)
class ScanPathConfig:
    """The cylinder + dome scan path (upstream.md, "Scan path"), in metres and degrees."""

    cylinder_radius_m: float = 0.5
    """Distance of the cylinder's cameras from the plant axis (the paper: 500 mm)."""
    cylinder_bottom_m: float = 0.16
    """Height of the lowest ring above the soil. The paper's bot, with its Z travel, takes a
    level camera no lower than about 0.158 m (hardware/geometry.py)."""
    cylinder_top_margin_m: float = 0.0
    """The highest ring sits this far above the plant's top."""
    cylinder_step_m: float = 0.02
    """Height between rings (the paper: 20 mm)."""
    azimuth_step_deg: float = 20.0
    """Angle between neighbouring views on a ring or dome circle (the paper: 20 degrees)."""
    dome_radius_m: float = 0.3
    """Radius of the dome (the paper: 300 mm)."""
    dome_center: Literal["half", "top"] = "half"
    """The dome's centre on the plant axis: at half the plant's height (default) or at its
    top. The paper does not say; over a 0.3 m plant a dome centred on its top puts the
    highest views beyond the paper's Z travel."""
    dome_polar_deg: tuple[float, ...] = (70.0, 50.0, 30.0, 10.0)
    """Polar angles of the dome's rings from the vertical, lowest ring first (the paper)."""
    pause_s: float = 3.0
    """Stop at each waypoint so the autofocus settles (the paper: about 3 s)."""
    head_clearance_m: float = 0.04
    """Least distance between the plant and the camera head (the camera's optical centre and
    the pitch axis) anywhere along the path, metres."""


@dataclass(frozen=True)
class Waypoint:
    """One stop of the scan: where the camera goes and what it looks at (bed frame, m)."""

    index: int
    kind: Literal["cylinder", "dome"]
    camera: np.ndarray
    """(3,) wanted optical centre."""
    target: np.ndarray
    """(3,) the point it looks at."""
    pose: HeadPose
    """The head pose that takes it there (one pose)."""


@dataclass(frozen=True)
class ScanPlan:
    """A checked scan path around one plant."""

    plant_center: np.ndarray
    """(2,) plant axis x, y, metres, bed frame."""
    plant_height: float
    waypoints: list[Waypoint]
    config: ScanPathConfig
    duration_s: float
    """Moves plus pauses on the motion profile, seconds."""

    def to_json(self) -> dict:
        return {"plant_center": self.plant_center.tolist(), "plant_height": self.plant_height,
                "waypoints": len(self.waypoints), "duration_s": round(self.duration_s, 2),
                "config": {k: (list(v) if isinstance(v, tuple) else v)
                           for k, v in self.config.__dict__.items()}}


def _ring_order(count: int, reverse: bool) -> np.ndarray:
    order = np.arange(count)
    return order[::-1] if reverse else order


def plan_cameras(plant_center: np.ndarray, plant_height: float,
                 config: ScanPathConfig) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(kind, camera position (3,), target (3,)) in travel order, metres, bed frame."""
    if plant_height <= 0 or not np.isfinite(plant_height):
        raise InputError("plant height", f"must be positive, got {plant_height}")
    center = np.asarray(plant_center, float)
    azimuths = np.radians(np.arange(0.0, 360.0, config.azimuth_step_deg))
    top = plant_height + config.cylinder_top_margin_m
    heights = np.arange(config.cylinder_bottom_m, top + 1e-9, config.cylinder_step_m)
    if len(heights) == 0:
        heights = np.array([config.cylinder_bottom_m])
    stops = []
    for ring, z in enumerate(heights):
        for k in _ring_order(len(azimuths), reverse=ring % 2 == 1):
            a = azimuths[k]
            camera = np.array([center[0] + config.cylinder_radius_m * np.cos(a),
                               center[1] + config.cylinder_radius_m * np.sin(a), z])
            stops.append(("cylinder", camera, np.array([center[0], center[1], z])))
    dome_z = plant_height / 2 if config.dome_center == "half" else plant_height
    dome = np.array([center[0], center[1], dome_z])
    for ring, polar in enumerate(np.radians(config.dome_polar_deg)):
        reverse = (len(heights) + ring) % 2 == 1
        for k in _ring_order(len(azimuths), reverse):
            a = azimuths[k]
            offset = config.dome_radius_m * np.array(
                [np.sin(polar) * np.cos(a), np.sin(polar) * np.sin(a), np.cos(polar)])
            stops.append(("dome", dome + offset, dome))
    return stops


def _head_points(pose: HeadPose, geometry: BotGeometry) -> np.ndarray:
    """(N, 2, 3) the camera's optical centre and the pitch axis of poses, metres."""
    camera, _ = forward(pose, geometry)
    axis = pose.gantry - np.array([0.0, 0.0, geometry.pitch_axis_below_utm_m])
    return np.stack([np.atleast_2d(camera), np.atleast_2d(axis)], axis=1)


def plan_scan(plant_center, plant_height: float, config: ScanPathConfig = ScanPathConfig(),
              geometry: BotGeometry = PAPER_BOT, profile: MotionProfile | None = None,
              obstacles: np.ndarray | None = None, samples_per_move: int = 16) -> ScanPlan:
    """Plan and check the cylinder + dome path around a plant.

    plant_center: (2,) metres, bed frame. obstacles: (M, 3) points on the plant's surfaces
    (the simulator's mesh samples, or a plant envelope for a real bot), metres. Raises
    UnreachableError for a waypoint the bot cannot take and InputError naming the waypoint
    where the head would pass closer than `head_clearance_m` to the plant.
    """
    profile = profile or MotionProfile()
    stops = plan_cameras(np.asarray(plant_center, float)[:2], plant_height, config)
    cameras = np.array([c for _, c, _ in stops])
    targets = np.array([t for _, _, t in stops])
    poses = look_at(cameras, targets, geometry)
    check_reachable(poses, geometry, name="scan waypoint")
    waypoints = [Waypoint(i, kind, cameras[i], targets[i],
                          HeadPose(poses.gantry[i], poses.yaw[i], poses.pitch[i]))
                 for i, (kind, _, _) in enumerate(stops)]
    duration = len(waypoints) * config.pause_s + sum(
        move_duration(a.pose.gantry, b.pose.gantry, profile)
        for a, b in zip(waypoints, waypoints[1:], strict=False))
    if obstacles is not None and len(obstacles):
        _check_collisions(waypoints, np.asarray(obstacles, float), config, geometry, profile,
                          samples_per_move)
    return ScanPlan(np.asarray(plant_center, float)[:2], float(plant_height), waypoints,
                    config, float(duration))


def _check_collisions(waypoints: list[Waypoint], obstacles: np.ndarray,
                      config: ScanPathConfig, geometry: BotGeometry, profile: MotionProfile,
                      samples: int) -> None:
    """Refuse a path whose head passes too close to the plant at a waypoint or on a move.

    Along a move the gantry follows the motion profile and the head is taken to turn
    linearly in time (the servos are much faster than the gantry, so this is conservative
    only in where the turn happens)."""
    tree = cKDTree(obstacles)
    fractions = np.linspace(0.0, 1.0, samples)
    for a, b in zip([None] + waypoints[:-1], waypoints, strict=True):
        if a is None:
            pose = b.pose
        else:
            duration = max(move_duration(a.pose.gantry, b.pose.gantry, profile), 1e-9)
            gantry = move_trajectory(fractions * duration, a.pose.gantry, b.pose.gantry, profile)
            pose = HeadPose(gantry, a.pose.yaw + fractions * (b.pose.yaw - a.pose.yaw),
                            a.pose.pitch + fractions * (b.pose.pitch - a.pose.pitch))
        points = _head_points(pose, geometry).reshape(-1, 3)
        distance, _ = tree.query(points)
        if distance.min() < config.head_clearance_m:
            where = "at" if a is None else f"on the move from waypoint {a.index} to"
            raise InputError(f"scan waypoint {b.index}",
                             f"the camera head passes {distance.min() * 1000:.0f} mm from the "
                             f"plant {where} waypoint {b.index} (least "
                             f"{config.head_clearance_m * 1000:.0f} mm): widen the cylinder "
                             "or the dome")
