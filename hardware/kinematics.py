"""Forward and inverse kinematics of the gantry and the yaw / pitch camera head.

Frames, units and angle conventions are those of `flowerpose.hardware.geometry` (bed frame,
metres, radians; yaw 0 along +x, counter-clockwise from above; pitch 0 level, positive
down). The camera frame follows OpenCV: +z along the optical axis (forward), +x to the
image's right, +y to the image's bottom. A rotation `R` maps camera-frame vectors into the
bed frame (its columns are the camera's x, y, z axes in bed coordinates), so a bed point p
is at ``R.T @ (p - position)`` in the camera frame.

The optical axis passes through the pitch axis and the yaw axis, so the inverse kinematics
is closed form: the look direction gives yaw and pitch, and the UTM sits at the camera
position moved back along the optical axis to the pitch axis and up to the UTM.

All functions take one pose (gantry (3,), angles scalars) or a batch (gantry (N, 3),
angles (N,)) and work on the whole batch at once.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flowerpose.errors import InputError
from flowerpose.hardware.geometry import PAPER_BOT, PAPER_TOOL, BotGeometry, PollinatorTool

JOINT_NAMES = ("x", "y", "z", "yaw", "pitch")
"""Joints (and their position actuators) of assets/farmbot/farmbot.xml, in qpos order."""

_ANGLE_TOL = 1e-9
"""Slack on angle limits, radians: a look direction exactly on a limit stays direct."""
_TRAVEL_TOL = 1e-6
"""Slack on the gantry travel, metres (FarmBot takes 0.01 mm)."""


class UnreachableError(InputError):
    """A waypoint the bot cannot take: outside the gantry travel, the servo range or too
    close to the soil.

    `waypoint` is its index in the checked batch (None for a single pose) and `limits`
    names every limit it breaks: "gantry X", "gantry Y", "gantry Z", "yaw servo",
    "pitch servo", "soil clearance", "finite" (a NaN or infinite coordinate or angle).
    """

    def __init__(self, source: str, problem: str, waypoint: int | None,
                 limits: tuple[str, ...]):
        super().__init__(source, problem)
        self.waypoint = waypoint
        self.limits = limits


@dataclass(frozen=True, eq=False)
class HeadPose:
    """Where the gantry and the head joints are: one pose or a batch.

    gantry: (3,) or (N, 3) float64, metres, bed frame: the UTM bottom centre.
    yaw, pitch: () or (N,) float64, radians: the geometric head angles (geometry.py); a yaw
    the yaw servo cannot reach is taken by upstream's flip (see `servo_commands`). Angles
    broadcast against the gantry's leading shape.
    """

    gantry: np.ndarray
    yaw: np.ndarray
    pitch: np.ndarray

    def __post_init__(self):
        gantry = np.asarray(self.gantry, np.float64)
        if gantry.ndim not in (1, 2) or gantry.shape[-1] != 3:
            raise ValueError(f"gantry must be (3,) or (N, 3), got {gantry.shape}")
        shape = gantry.shape[:-1]
        object.__setattr__(self, "gantry", gantry)
        object.__setattr__(self, "yaw", np.broadcast_to(np.asarray(self.yaw, np.float64),
                                                        shape).copy())
        object.__setattr__(self, "pitch", np.broadcast_to(np.asarray(self.pitch, np.float64),
                                                          shape).copy())


def forward(pose: HeadPose, geometry: BotGeometry = PAPER_BOT) -> tuple[np.ndarray, np.ndarray]:
    """Camera pose of a head pose: optical centre and camera-to-bed rotation.

    Returns position (3,) or (N, 3), metres, bed frame, and rotation (3, 3) or (N, 3, 3)
    whose columns are the OpenCV camera axes (x right, y down, z forward) in the bed frame.
    """
    ahead, down = _head_axes(pose.yaw, pose.pitch)
    right = np.cross(down, ahead)
    rotation = np.stack([right, down, ahead], -1)
    pitch_axis = pose.gantry - np.array([0.0, 0.0, geometry.pitch_axis_below_utm_m])
    return pitch_axis + geometry.camera_forward_of_pitch_m * ahead, rotation


def _look_angles(ahead: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Geometric yaw in [0, pi] and pitch, radians, that point the head along unit
    vectors `ahead` (..., 3): a yaw in (pi, 2 pi) takes upstream's flip (yaw - pi,
    pi - pitch), the same axis with the image turned by 180 degrees."""
    yaw = np.arctan2(ahead[..., 1], ahead[..., 0])
    pitch = np.arctan2(-ahead[..., 2], np.hypot(ahead[..., 0], ahead[..., 1]))
    flip = yaw < -_ANGLE_TOL
    return np.where(flip, yaw + np.pi, yaw), np.where(flip, np.pi - pitch, pitch)


def look_at(camera_position, target, geometry: BotGeometry = PAPER_BOT) -> HeadPose:
    """Head pose that puts the optical centre at `camera_position`, looking at `target`.

    camera_position: (3,) or (N, 3), metres, bed frame. target: (3,) or (N, 3), metres,
    bed frame (one target for all cameras, or one each). Yaw comes out in [0, pi] as
    upstream drives it: a look direction with yaw in (pi, 2 pi) takes upstream's flip
    (yaw - pi, pi - pitch), the same optical axis and camera position with the image turned
    by 180 degrees. Straight down (or up) the yaw is 0. The pose is not checked against the
    bot's limits: see `check_reachable`.
    """
    camera = np.asarray(camera_position, np.float64)
    offset = np.asarray(target, np.float64) - camera
    distance = np.linalg.norm(offset, axis=-1, keepdims=True)
    if np.any(distance < 1e-9):
        raise InputError("look_at", "a camera position equals its look-at target")
    ahead = offset / distance
    yaw, pitch = _look_angles(ahead)
    gantry = (camera - geometry.camera_forward_of_pitch_m * ahead
              + np.array([0.0, 0.0, geometry.pitch_axis_below_utm_m]))
    return HeadPose(gantry, yaw, pitch)


def _servo_angles(pose: HeadPose,
                  geometry: BotGeometry) -> tuple[np.ndarray, np.ndarray]:
    """Joint angles the servos take for a pose, radians: yaw wrapped into the yaw servo's
    reach, or upstream's flip (yaw - pi, pi - pitch) where no turn of it is in reach."""
    low, high = geometry.yaw_range_rad
    yaw = low + np.mod(pose.yaw - low, 2.0 * np.pi)
    flip = yaw > high + _ANGLE_TOL
    return np.where(flip, yaw - np.pi, yaw), np.where(flip, np.pi - pose.pitch, pose.pitch)


def servo_commands(pose: HeadPose,
                   geometry: BotGeometry = PAPER_BOT) -> tuple[np.ndarray, np.ndarray]:
    """Yaw and pitch servo commands, degrees 0-180, of a head pose (upstream's mapping).

    The yaw is taken modulo a full turn into what the yaw servo reaches (geometric -30 to
    240 degrees); where no turn of it is in reach, upstream's flip (yaw - pi, pi - pitch)
    gives the same optical axis and camera position with the image turned by 180 degrees,
    and the head takes `from_servo_commands` of the result, not `pose`. Returns two () or
    (N,) float64 arrays, degrees. Raises UnreachableError when the pitch (after any flip)
    is outside the pitch servo's reach.
    """
    check_reachable(pose, geometry, name="servo command for pose", servos_only=True)
    yaw, pitch = _servo_angles(pose, geometry)
    return (geometry.angle_to_command(yaw, geometry.yaw_command_offset_deg),
            geometry.angle_to_command(pitch, geometry.pitch_command_offset_deg))


def from_servo_commands(yaw_command, pitch_command, gantry,
                        geometry: BotGeometry = PAPER_BOT) -> HeadPose:
    """Head pose of servo commands: the inverse of `servo_commands`.

    yaw_command, pitch_command: () or (N,), degrees 0-180. gantry: (3,) or (N, 3), metres,
    bed frame, the UTM bottom centre. Raises InputError for a command outside 0-180.
    """
    low, high = geometry.servo_command_range_deg
    for servo, command in (("yaw", yaw_command), ("pitch", pitch_command)):
        bad = np.asarray(command, np.float64)
        if np.any((bad < low) | (bad > high) | ~np.isfinite(bad)):
            raise InputError(f"{servo} servo command",
                             f"{np.ravel(bad).tolist()} is outside {low:g}-{high:g} degrees")
    return HeadPose(gantry,
                    geometry.command_to_angle(yaw_command, geometry.yaw_command_offset_deg),
                    geometry.command_to_angle(pitch_command, geometry.pitch_command_offset_deg))


def joint_positions(pose: HeadPose, geometry: BotGeometry = PAPER_BOT) -> np.ndarray:
    """MuJoCo qpos (and position-actuator ctrl) of a pose, in `JOINT_NAMES` order.

    Returns (5,) or (N, 5) float64: FarmBot X, Y, Z in metres from home (Z <= 0), then the
    yaw and pitch the servos take, radians (as `servo_commands` turns and flips them).
    """
    yaw, pitch = _servo_angles(pose, geometry)
    slides = pose.gantry - geometry.home
    return np.concatenate([slides, yaw[..., None], pitch[..., None]], -1)


def head_angles(pose: HeadPose, geometry: BotGeometry = PAPER_BOT) -> tuple[float, float]:
    """The yaw and pitch the head's servos take for one `pose`, radians (its yaw wrapped into
    the servo's reach, or flipped: the solution the tool's positions assume)."""
    yaw, pitch = joint_positions(pose, geometry)[3:]
    return float(yaw), float(pitch)


def _head_axes(yaw: np.ndarray, pitch: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The head's forward (optical axis) and the image's down, (..., 3) unit vectors in
    the bed frame, of head angles, radians."""
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    return np.stack([cp * cy, cp * sy, -sp], -1), np.stack([-sp * cy, -sp * sy, -cp], -1)


def head_boxes(pose: HeadPose, geometry: BotGeometry = PAPER_BOT
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The head's housings as boxes (the yaw servo's, then the pitch servo's with the camera),
    at the servo solution the head takes. Returns centres (..., 2, 3) metres, bed frame,
    rotations (..., 2, 3, 3) (columns: the box's axes in the bed frame) and half sizes
    (2, 3), metres."""
    yaw, pitch = _servo_angles(pose, geometry)
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    zero, one = np.zeros_like(cy), np.ones_like(cy)
    turn = np.stack([np.stack([cy, -sy, zero], -1), np.stack([sy, cy, zero], -1),
                     np.stack([zero, zero, one], -1)], -2)
    tilt = np.stack([np.stack([cp, zero, sp], -1), np.stack([zero, one, zero], -1),
                     np.stack([-sp, zero, cp], -1)], -2)
    aim = turn @ tilt
    gantry = np.asarray(pose.gantry, np.float64)
    pitch_axis = gantry - np.array([0.0, 0.0, geometry.pitch_axis_below_utm_m])
    (yaw_centre, yaw_half), (pitch_centre, pitch_half) = (geometry.head_yaw_box_m,
                                                          geometry.head_pitch_box_m)
    centres = np.stack([gantry + turn @ np.asarray(yaw_centre),
                        pitch_axis + aim @ np.asarray(pitch_centre)], -2)
    return centres, np.stack([turn, aim], -3), np.array([yaw_half, pitch_half])


def tool_forward(pose: HeadPose, tool: PollinatorTool = PAPER_TOOL,
                 geometry: BotGeometry = PAPER_BOT) -> tuple[np.ndarray, np.ndarray]:
    """Where the pollinator's tip is and where its shaft points, for a head pose.

    The shaft sits under the optical axis, so unlike the camera's centre the tip depends
    on which of the two servo solutions (`servo_commands`' flip) the head takes: this uses
    the one it does take. Returns tip (3,) or (N, 3), metres, bed frame, and the shaft's
    direction, unit (3,) or (N, 3), from the bracket towards the tip.
    """
    yaw, pitch = _servo_angles(pose, geometry)
    ahead, down = _head_axes(yaw, pitch)
    pitch_axis = pose.gantry - np.array([0.0, 0.0, geometry.pitch_axis_below_utm_m])
    return pitch_axis + tool.reach_m * ahead + tool.offset_down_m * down, ahead


def tool_at(tip, direction, tool: PollinatorTool = PAPER_TOOL,
            geometry: BotGeometry = PAPER_BOT, flip: bool = False) -> HeadPose:
    """The head pose that puts the pollinator's tip at `tip` with its shaft along
    `direction` (the way it moves to touch): the inverse of `tool_forward`.

    tip: (3,) or (N, 3), metres, bed frame. direction: (3,) or (N, 3), any length but 0.
    flip: the head's other solution for the same shaft direction (yaw + pi, pi - pitch:
    the head upside down, its housings and the shaft's offset on the other side), where the
    servos reach it without their own flip (else the same pose). Like `look_at`, the pose
    is not checked against the bot's limits.
    """
    direction = np.asarray(direction, np.float64)
    length = np.linalg.norm(direction, axis=-1, keepdims=True)
    if np.any(length < 1e-12):
        raise InputError("tool_at", "the tool's direction is a zero vector")
    ahead = direction / length
    yaw, pitch = _look_angles(ahead)
    if flip:
        yaw, pitch = yaw + np.pi, np.pi - pitch
    # The image's down is that of the angles the servos will take, which may be flipped.
    servo_yaw, servo_pitch = _servo_angles(HeadPose(np.zeros(yaw.shape + (3,)), yaw, pitch),
                                           geometry)
    _, down = _head_axes(servo_yaw, servo_pitch)
    pitch_axis = np.asarray(tip, np.float64) - tool.reach_m * ahead - tool.offset_down_m * down
    return HeadPose(pitch_axis + np.array([0.0, 0.0, geometry.pitch_axis_below_utm_m]), yaw,
                    pitch)


def tool_points(pose: HeadPose, tool: PollinatorTool = PAPER_TOOL,
                geometry: BotGeometry = PAPER_BOT, samples: int = 6) -> np.ndarray:
    """(..., samples, 3) points along the pollinator's shaft, from the bracket to the tip,
    metres, bed frame: what must keep clear of what it should not touch."""
    tip, ahead = tool_forward(pose, tool, geometry)
    along = np.linspace(tool.shaft_start_m - tool.reach_m, 0.0, samples)
    return tip[..., None, :] + along[:, None] * ahead[..., None, :]


def check_reachable(pose: HeadPose, geometry: BotGeometry = PAPER_BOT, *,
                    name: str = "waypoint", servos_only: bool = False) -> None:
    """Refuse a pose (or any pose of a batch) the bot cannot take, before it moves.

    Checks the gantry travel on X, Y and Z, both servos' command range (after the yaw flip
    `servo_commands` applies) and the soil clearance of the camera's optical centre and the
    pitch axis. `name` starts the error's source ("waypoint 12"); `servos_only` skips the
    gantry travel and the soil clearance. Raises UnreachableError for the first bad pose,
    naming every limit it breaks and how many poses of the batch are bad.
    """
    gantry_xyz = np.atleast_2d(pose.gantry)
    yaw, pitch = (np.atleast_1d(a) for a in _servo_angles(pose, geometry))
    yaw_low, yaw_high = geometry.yaw_range_rad
    pitch_low, pitch_high = geometry.pitch_range_rad
    camera_z = np.atleast_1d(forward(pose, geometry)[0][..., 2])
    axis_z = gantry_xyz[:, 2] - geometry.pitch_axis_below_utm_m
    checks = {
        "finite": ~(np.isfinite(gantry_xyz).all(1) & np.isfinite(yaw) & np.isfinite(pitch)),
        "yaw servo": (yaw < yaw_low - _ANGLE_TOL) | (yaw > yaw_high + _ANGLE_TOL),
        "pitch servo": (pitch < pitch_low - _ANGLE_TOL) | (pitch > pitch_high + _ANGLE_TOL),
    }
    if not servos_only:
        outside = ((gantry_xyz < geometry.gantry_min - _TRAVEL_TOL)
                   | (gantry_xyz > geometry.gantry_max + _TRAVEL_TOL))
        for axis, label in enumerate("XYZ"):
            checks[f"gantry {label}"] = outside[:, axis]
        checks["soil clearance"] = np.minimum(camera_z, axis_z) < geometry.soil_clearance_m
    bad = np.logical_or.reduce(list(checks.values()))
    if not bad.any():
        return
    i = int(np.flatnonzero(bad)[0])
    limits = tuple(limit for limit, broken in checks.items() if broken[i])
    low, high = geometry.servo_command_range_deg
    commands = {"yaw": (yaw[i], geometry.yaw_command_offset_deg),
                "pitch": (pitch[i], geometry.pitch_command_offset_deg)}
    text = {"finite": "a coordinate or angle is not finite",
            "soil clearance": f"camera {camera_z[i]:.3f} m and pitch axis {axis_z[i]:.3f} m "
                              f"above the soil, the least is {geometry.soil_clearance_m:.3f} m"}
    for servo, (angle, offset) in commands.items():
        text[f"{servo} servo"] = (f"{servo} servo command "
                                  f"{geometry.angle_to_command(angle, offset):.1f} (geometric "
                                  f"{servo} {np.degrees(angle):.1f} degrees) is outside "
                                  f"{low:g}-{high:g} degrees")
    farmbot = np.atleast_2d(pose.gantry - geometry.home)[i] * 1000.0
    travel = np.asarray(geometry.travel_m) * 1000.0
    bounds = {"X": (0.0, travel[0]), "Y": (0.0, travel[1]), "Z": (-travel[2], 0.0)}
    for axis, label in enumerate("XYZ"):
        text[f"gantry {label}"] = (f"gantry {label} travel: FarmBot {label} "
                                   f"{farmbot[axis]:.2f} mm is outside "
                                   f"{bounds[label][0]:.2f} to {bounds[label][1]:.2f} mm")
    problem = "; ".join(text[limit] for limit in limits)
    count = int(bad.sum())
    if count > 1:
        problem += f" ({count} of {bad.size} poses unreachable)"
    waypoint = i if pose.gantry.ndim == 2 else None
    source = name if waypoint is None else f"{name} {i}"
    raise UnreachableError(source, f"unreachable: {problem}", waypoint, limits)
