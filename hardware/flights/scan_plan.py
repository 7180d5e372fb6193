"""The paper's scan path, planned and checked before the bot moves.

A cylinder around the plant (rings of level views aimed at the plant's axis), then a dome
over it (views aimed at the dome centre), as waypoints in travel order: rings bottom to top,
each ring turning the other way from the last, then the dome from its lowest ring to its
highest. Every waypoint is solved to a head pose (inverse kinematics with the yaw flip),
checked against the bot's reach, and checked for collisions with the plant along the moves
between waypoints, each axis on FarmBot's own motion profile.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Literal

import numpy as np
from scipy.spatial import cKDTree

from flowerpose.errors import InputError
from flowerpose.hardware.geometry import PAPER_BOT, BotGeometry
from flowerpose.hardware.kinematics import (
    HeadPose,
    UnreachableError,
    check_reachable,
    forward,
    look_at,
)
from flowerpose.hardware.motion import (
    END_OF_MOVE_S,
    MotionProfile,
    move_duration,
    move_trajectory,
)
from flowerpose.scan_geometry import ScanPathConfig, path_cameras


@dataclass(frozen=True)
class ScanConfig:
    """A scan: the path's geometry plus how the bot flies it."""

    path: ScanPathConfig = field(default_factory=ScanPathConfig)
    """Where the camera stops and what it looks at."""
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
    config: ScanConfig
    duration_s: float
    """Moves plus pauses on the motion profile, seconds."""

    def to_json(self) -> dict:
        return {"plant_center": self.plant_center.tolist(), "plant_height": self.plant_height,
                "waypoints": len(self.waypoints), "duration_s": round(self.duration_s, 2),
                "config": asdict(self.config)}


def head_points(pose: HeadPose, geometry: BotGeometry = PAPER_BOT) -> np.ndarray:
    """(N, 2, 3) the camera's optical centre and the pitch axis of poses, metres."""
    camera, _ = forward(pose, geometry)
    axis = pose.gantry - np.array([0.0, 0.0, geometry.pitch_axis_below_utm_m])
    return np.stack([np.atleast_2d(camera), np.atleast_2d(axis)], axis=1)


def plan_plant_scan(plant_center, plant_height: float, obstacles: np.ndarray,
                    path: ScanPathConfig | None = None) -> ScanPlan:
    """The scan path round a plant whose surfaces are known (a simulated plant's mesh
    samples, `sim.export.plant_obstacles`), reach and collisions checked: `path` (the
    synthetic world's `sim.viewpoints`, the same cameras that decide the oracle's
    visibility) or the default. plant_center: (2,) metres, bed frame; plant_height: metres."""
    return plan_scan(plant_center, plant_height, ScanConfig(path=path or ScanPathConfig()),
                     obstacles=obstacles)


def plan_scan(plant_center, plant_height: float, config: ScanConfig = ScanConfig(),
              geometry: BotGeometry = PAPER_BOT, profile: MotionProfile | None = None,
              obstacles: np.ndarray | None = None, samples_per_move: int = 16) -> ScanPlan:
    """Plan and check the cylinder + dome path around a plant.

    plant_center: (2,) metres, bed frame. obstacles: (M, 3) points on the plant's surfaces
    (the simulator's mesh samples, or a plant envelope for a real bot), metres. Raises
    UnreachableError for a waypoint the bot cannot take and InputError naming the waypoint
    where the head would pass closer than `head_clearance_m` to the plant.
    """
    profile = profile or MotionProfile()
    kinds, cameras, targets = path_cameras(plant_center, plant_height, config.path)
    poses = look_at(cameras, targets, geometry)
    try:
        check_reachable(poses, geometry, name="scan waypoint")
    except UnreachableError as error:
        if not {"gantry X", "gantry Y"} & set(error.limits):
            raise
        # The path is the same round any plant: say where a plant fits it.
        reach = poses.gantry[:, :2] - np.asarray(plant_center, np.float64)[:2]
        low = np.asarray(geometry.gantry_min)[:2] - reach.min(axis=0)
        high = np.asarray(geometry.gantry_max)[:2] - reach.max(axis=0)
        fits = (f"this path fits a plant with its stem at x {low[0]:.2f}-{high[0]:.2f} m and "
                f"y {low[1]:.2f}-{high[1]:.2f} m" if (low <= high).all()
                else "no plant position on this bed fits this path")
        raise UnreachableError(error.source, f"{error.problem}; {fits}", error.waypoint,
                               error.limits) from None
    waypoints = [Waypoint(i, kind, cameras[i], targets[i],
                          HeadPose(poses.gantry[i], poses.yaw[i], poses.pitch[i]))
                 for i, kind in enumerate(kinds)]
    duration = len(waypoints) * config.pause_s + sum(
        move_duration(a.pose.gantry, b.pose.gantry, profile) + END_OF_MOVE_S
        for a, b in zip(waypoints, waypoints[1:], strict=False))
    if obstacles is not None and len(obstacles):
        _check_collisions(waypoints, np.asarray(obstacles, float), config, geometry, profile,
                          samples_per_move)
    return ScanPlan(np.asarray(plant_center, float)[:2], float(plant_height), waypoints,
                    config, float(duration))


def poses_along(a: HeadPose, b: HeadPose, profile: MotionProfile, samples: int) -> HeadPose:
    """`samples` poses along the move from a to b: the gantry on the motion profile, the
    head taken to turn linearly in time (the servos are much faster than the gantry, so
    this is conservative only in where the turn happens)."""
    fractions = np.linspace(0.0, 1.0, samples)
    duration = max(move_duration(a.gantry, b.gantry, profile), 1e-9)
    gantry = move_trajectory(fractions * duration, a.gantry, b.gantry, profile)
    return HeadPose(gantry, a.yaw + fractions * (b.yaw - a.yaw),
                    a.pitch + fractions * (b.pitch - a.pitch))


def check_clearance(plan: ScanPlan, obstacles: np.ndarray, what: str, advice: str,
                    geometry: BotGeometry = PAPER_BOT, profile: MotionProfile | None = None,
                    samples_per_move: int = 16) -> None:
    """Refuse a planned scan whose head passes closer than its `head_clearance_m` to
    `obstacles` ((M, 3) points, metres, bed frame) at a waypoint or on a move; InputError
    names the waypoint, `what` the obstacles are ("plant north-2") and `advice`."""
    _check_collisions(plan.waypoints, np.asarray(obstacles, float), plan.config, geometry,
                      profile or MotionProfile(), samples_per_move, what, advice)


def _check_collisions(waypoints: list[Waypoint], obstacles: np.ndarray,
                      config: ScanConfig, geometry: BotGeometry, profile: MotionProfile,
                      samples: int, what: str = "the plant",
                      advice: str = "widen the cylinder or the dome") -> None:
    """Refuse a path whose head passes too close to `what` at a waypoint or on a move
    (`poses_along`)."""
    tree = cKDTree(obstacles)
    for a, b in zip([None] + waypoints[:-1], waypoints, strict=True):
        pose = b.pose if a is None else poses_along(a.pose, b.pose, profile, samples)
        points = head_points(pose, geometry).reshape(-1, 3)
        distance, _ = tree.query(points)
        if distance.min() < config.head_clearance_m:
            where = "at" if a is None else f"on the move from waypoint {a.index} to"
            raise InputError(f"scan waypoint {b.index}",
                             f"the camera head passes {distance.min() * 1000:.0f} mm from "
                             f"{what} {where} waypoint {b.index} (least "
                             f"{config.head_clearance_m * 1000:.0f} mm): {advice}")


def plant_envelope(center, height: float, radius: float, spacing: float = 0.01) -> np.ndarray:
    """(N, 3) points on the side and top of a cylinder standing for a real plant whose
    stem is at `center` (x, y), `height` and `radius` in metres, bed frame, `spacing`
    apart: what the scan path keeps clear of."""
    x, y = float(center[0]), float(center[1])
    angles = np.linspace(0.0, 2 * np.pi, max(12, int(np.ceil(2 * np.pi * radius / spacing))),
                         endpoint=False)
    heights = np.linspace(0.0, height, max(2, int(np.ceil(height / spacing)) + 1))
    radii = np.linspace(0.0, radius, max(2, int(np.ceil(radius / spacing)) + 1))
    side = np.stack(np.broadcast_arrays(x + radius * np.cos(angles), y + radius * np.sin(angles),
                                        heights[:, None]), -1)
    top = np.stack(np.broadcast_arrays(x + radii[:, None] * np.cos(angles),
                                       y + radii[:, None] * np.sin(angles), height), -1)
    return np.concatenate([side.reshape(-1, 3), top.reshape(-1, 3)])


def check_plant_position(plant_at, plant_height: float, plant_radius: float,
                         geometry: BotGeometry = PAPER_BOT) -> tuple[float, float]:
    """A real plant's stem position (x, y), metres, bed frame, checked to be on the bed,
    and its height and radius to be positive; InputError names the argument."""
    x, y = (float(v) for v in plant_at)
    length, width = geometry.bed_size_m
    if not (0 <= x <= length and 0 <= y <= width):
        raise InputError("plant_at", f"({x:g}, {y:g}) m is outside the bed: x 0..{length:g} m "
                         f"along it, y 0..{width:g} m across")
    for name, value in (("plant_height", plant_height), ("plant_radius", plant_radius)):
        if not (np.isfinite(value) and value > 0):
            raise InputError(name, f"must be a positive number of metres, got {value:g}")
    return x, y


def plan_field_scan(plant_at, plant_height: float, plant_radius: float,
                    config: ScanConfig | None = None,
                    geometry: BotGeometry = PAPER_BOT) -> ScanPlan:
    """The scan of a real plant whose stem stands at `plant_at` (x, y, metres, bed frame),
    its reach a cylinder of `plant_height` x `plant_radius` metres the head keeps clear of.
    InputError names the argument that is out of range."""
    x, y = check_plant_position(plant_at, plant_height, plant_radius, geometry)
    return plan_scan(np.array([x, y]), plant_height, config or ScanConfig(), geometry,
                     obstacles=plant_envelope((x, y), plant_height, plant_radius))


def pose_header(index_name: str) -> str:
    """The header of `pose_row`'s lines, their first column named `index_name`."""
    return (f"{index_name:>8s} {'kind':8s} {'X mm':>8s} {'Y mm':>8s} {'Z mm':>8s} "
            f"{'yaw cmd':>8s} {'pitch cmd':>9s}")


def pose_row(index: int, kind: str, pose: HeadPose) -> str:
    """A pose in FarmBot's own units, as a physical bot is sent it: millimetres from home
    and the servos' commands, after `index` and `kind`."""
    from flowerpose.hardware.geometry import bed_to_farmbot_mm
    from flowerpose.hardware.kinematics import servo_commands

    x, y, z = bed_to_farmbot_mm(pose.gantry)
    yaw, pitch = servo_commands(pose)
    return (f"{index:8d} {kind:8s} {x:8.2f} {y:8.2f} {z:8.2f} {float(yaw):8.1f} "
            f"{float(pitch):9.1f}")


def plan_table(plan: ScanPlan) -> list[str]:
    """The planned moves in FarmBot's own units, a line each (`pose_row`)."""
    return [pose_header("waypoint")] + [pose_row(w.index, w.kind, w.pose)
                                        for w in plan.waypoints]
