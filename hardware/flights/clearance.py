"""How far the head and the pollinator pass from the plant's points over a move.

A move is checked at poses, and the shaft at points along it; both are spaced by distance,
not by count, so that nothing between two checked places can touch unseen. With every
point of the head and the pollinator moving at most `step_m` from one checked pose to the
next, and the shaft's checked points `step_m` apart, a plant point that touches them lies
within about `step_m` of a checked place, so a clearance check of at least that much fails
for it. A fixed count is not enough: twelve poses along a 40 cm descent are 3.5 cm apart,
and a petal between two of them went unseen.

Metres and radians, bed frame.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from flowerpose.hardware.flights.scan_plan import poses_along
from flowerpose.hardware.geometry import BotGeometry, PollinatorTool
from flowerpose.hardware.kinematics import HeadPose, head_boxes, tool_points
from flowerpose.hardware.motion import MotionProfile

#: Fewest points checked along the shaft, whatever its length.
LEAST_SHAFT_POINTS = 6


def lever_m(geometry: BotGeometry, tool: PollinatorTool) -> float:
    """Farthest any point of the head's housings or the pollinator lies from the UTM's
    bottom centre, where the yaw axis meets the gantry, metres: how far a radian of turn
    moves it at most (the pitch axis is nearer to all of them)."""
    boxes = [np.linalg.norm(centre) + np.linalg.norm(half)
             for centre, half in (geometry.head_yaw_box_m, geometry.head_pitch_box_m)]
    tool_end = np.hypot(tool.reach_m + tool.tip_radius_m, tool.offset_down_m)
    return float(geometry.pitch_axis_below_utm_m + max(max(boxes), tool_end))


def checked_poses(a: HeadPose, b: HeadPose, profile: MotionProfile, step_m: float,
                  geometry: BotGeometry, tool: PollinatorTool, least: int = 2) -> HeadPose:
    """Poses along the move from a to b (`scan_plan.poses_along`: the gantry on its motion
    profile, the head turning linearly in time), at least `least` of them and as many more
    as keep every point of the head and the pollinator within `step_m` of where it was at
    the pose before (a gantry step plus the turn times `lever_m`)."""
    lever = lever_m(geometry, tool)
    count = max(least, 2)
    while True:
        poses = poses_along(a, b, profile, count)
        moved = (np.linalg.norm(np.diff(poses.gantry, axis=0), axis=1)
                 + lever * (np.abs(np.diff(poses.yaw)) + np.abs(np.diff(poses.pitch))))
        worst = float(moved.max(initial=0.0))
        if worst <= step_m:
            return poses
        # The profile's speed varies along the move, so the first guess may fall short.
        count = int(np.ceil((count - 1) * worst / step_m)) + 2


def shaft_points(poses: HeadPose, tool: PollinatorTool, geometry: BotGeometry,
                 step_m: float) -> np.ndarray:
    """(..., K, 3) points along the pollinator's shaft from the bracket to the tip, at most
    `step_m` apart (`kinematics.tool_points`), metres, bed frame."""
    length = tool.reach_m - tool.shaft_start_m
    samples = max(LEAST_SHAFT_POINTS, int(np.ceil(length / step_m)) + 1)
    return tool_points(poses, tool, geometry, samples)


def gap(poses: HeadPose, tree: cKDTree, shaft_tree: cKDTree | None, reach_m: float,
        geometry: BotGeometry, tool: PollinatorTool, step_m: float) -> tuple[float, str]:
    """Least distance, metres, from the plant to the head's housings (any point of `tree`)
    or the pollinator's shaft (any point of `shaft_tree`, checked `step_m` apart) over
    `poses`, and which of the two it is ("camera head" or "pollinator")."""
    head = head_gap(poses, tree, reach_m, geometry)
    shaft = (shaft_tree.query(shaft_points(poses, tool, geometry, step_m).reshape(-1, 3))[0]
             .min() if shaft_tree is not None else np.inf)
    return (head, "camera head") if head <= shaft else (float(shaft), "pollinator")


def head_gap(poses: HeadPose, tree: cKDTree, reach_m: float, geometry: BotGeometry
             ) -> float:
    """Least distance, metres, between the plant's points (`tree`) and the head's housings
    (`kinematics.head_boxes`) over `poses`: 0 for a point inside one, inf when none is
    within reach_m of them."""
    centres, rotations, half = head_boxes(poses, geometry)
    centres, rotations = centres.reshape(-1, 3), rotations.reshape(-1, 3, 3)
    box = np.tile(np.arange(len(half)), len(centres) // len(half))
    near = tree.query_ball_point(centres, np.linalg.norm(half, axis=1).max() + reach_m)
    counts = np.array([len(n) for n in near])
    if not counts.sum():
        return np.inf
    owner = np.repeat(np.arange(len(near)), counts)
    points = tree.data[np.concatenate([np.asarray(n, int) for n in near])]
    local = np.einsum("kji,kj->ki", rotations[owner], points - centres[owner])
    outside = np.maximum(np.abs(local) - half[box[owner]], 0.0)
    return float(np.sqrt((outside ** 2).sum(axis=1)).min())
