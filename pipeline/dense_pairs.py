"""Dense stereo, step 2: which views pair up, and the geometry it needs (depth ranges, the
scene centre, angles). Poses are camera-to-bed (4, 4) matrices, metres, OpenCV camera axes."""

from __future__ import annotations

import numpy as np

from flowerpose.pipeline.dense_config import DenseConfig


def apply_matrix(points: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """points (..., m) @ matrix (m, n) in the points' dtype. einsum, not `@`: OpenBLAS's
    product of a tall array with a 3-wide one is several times slower on a busy 2-core
    machine."""
    return np.einsum("...i,ij->...j", points, matrix.astype(points.dtype))


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between unit vectors along the last axis, degrees."""
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=-1), -1.0, 1.0)))


def scene_centre(centres: np.ndarray, axes: np.ndarray) -> np.ndarray | None:
    """The point nearest (least squares) all optical axes; None when they are parallel."""
    projector = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]
    a = projector.sum(axis=0)
    b = np.einsum("nij,nj->i", projector, centres)
    if np.linalg.cond(a) > 1e6:
        return None
    return np.linalg.solve(a, b)


def depth_ranges(centres: np.ndarray, axes: np.ndarray, config: DenseConfig
                  ) -> tuple[np.ndarray, np.ndarray | None]:
    """(N, 2) depth search range per view, metres, and the scene centre (None: unknown or
    not used)."""
    lo, hi = config.depth_range_m
    ranges = np.tile([lo, hi], (len(centres), 1)).astype(float)
    if config.scene_radius_m is None or len(centres) < 2:
        return ranges, None
    centre = scene_centre(centres, axes)
    if centre is None:
        return ranges, None
    depth = np.sum((centre - centres) * axes, axis=1)
    near = np.clip(depth - config.scene_radius_m, lo, hi)
    far = np.clip(depth + config.scene_radius_m, lo, hi)
    ok = far > near
    ranges[ok] = np.c_[near, far][ok]
    return ranges, centre


def narrow_to_points(ranges: np.ndarray, poses: np.ndarray, k: np.ndarray,
                     size: tuple[int, int], points: np.ndarray, stretch: float,
                     min_points: int = 20) -> np.ndarray:
    """(N, 2) depth ranges cut to what each view sees of `points`: the 1st and 99th
    percentile of the depths of the points in its image, times (1 - stretch) and
    (1 + stretch), intersected with `ranges` (COLMAP's rule for its own stereo, with
    stretch 0.25). A view with fewer than `min_points` points in its image, or whose cut
    would leave nothing, keeps its range.

    ranges: (N, 2) metres; poses: (N, 4, 4) camera-to-bed, metres, OpenCV axes; k: (3, 3)
    OpenCV camera matrix at `size` (width, height) pixels; points: (M, 3) bed frame, metres
    (the sparse model's).
    """
    narrowed = ranges.copy()
    points = np.asarray(points, float).reshape(-1, 3)
    width, height = size
    for n, pose in enumerate(poses):
        camera = (points - pose[:3, 3]) @ pose[:3, :3]
        depth = camera[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = k[0, 0] * camera[:, 0] / depth + k[0, 2]
            v = k[1, 1] * camera[:, 1] / depth + k[1, 2]
        seen = depth[(depth > 0) & (u >= 0) & (u < width) & (v >= 0) & (v < height)]
        if len(seen) < min_points:
            continue
        low, high = np.percentile(seen, [1, 99])
        near = max(ranges[n, 0], low * (1 - stretch))
        far = min(ranges[n, 1], high * (1 + stretch))
        if far > near:
            narrowed[n] = near, far
    return narrowed


def select_pairs(poses: np.ndarray, config: DenseConfig | None = None,
                 expected_depth: np.ndarray | None = None) -> tuple[list[tuple[int, int]], dict]:
    """Stereo pairs among views with (N, 4, 4) camera-to-bed poses.

    Returns (pairs (i, j) with i < j, counts): counts["candidates"] are the pairs near enough
    in position and viewing direction, counts["degenerate"] those of them skipped for a
    baseline that is too short or along an optical axis. expected_depth (N,): the depth of
    the scene along each view's axis (default: the middle of `depth_range_m`). config:
    default DenseConfig().
    """
    config = config or DenseConfig()
    poses = np.asarray(poses, float)
    n = len(poses)
    centres, axes = poses[:, :3, 3], poses[:, :3, 2]
    if expected_depth is None:
        expected_depth = np.full(n, np.mean(config.depth_range_m))
    offset = centres[None, :, :] - centres[:, None, :]  # [i, j] = C_j - C_i
    baseline = np.linalg.norm(offset, axis=-1)
    view_angle = angle_deg(axes[:, None], axes[None, :])
    near = (view_angle <= config.max_view_angle_deg) & (baseline <= config.baseline_m[1])
    np.fill_diagonal(near, False)
    direction = offset / np.maximum(baseline, 1e-12)[..., None]

    def from_axis(axis):  # angle between the baseline's line and an optical axis, degrees
        angle = angle_deg(direction, axis)
        return np.minimum(angle, 180.0 - angle)

    epipole = np.minimum(from_axis(axes[:, None]), from_axis(axes[None, :]))
    degenerate = near & ((baseline < max(config.baseline_m[0], 1e-9))
                         | (epipole < config.min_epipole_angle_deg))
    usable = near & ~degenerate
    scene = centres + axes * expected_depth[:, None]  # what view i looks at
    to_scene_i = scene[:, None, :] - centres[:, None, :]
    to_scene_j = scene[:, None, :] - centres[None, :, :]
    to_scene_i = to_scene_i / np.linalg.norm(to_scene_i, axis=-1, keepdims=True)
    to_scene_j = to_scene_j / np.maximum(np.linalg.norm(to_scene_j, axis=-1, keepdims=True),
                                         1e-12)
    triangulation = angle_deg(to_scene_i, to_scene_j)
    chosen: set[tuple[int, int]] = set()
    min_cos = np.cos(np.radians(config.min_pair_direction_deg))
    for i in range(n):
        candidates = np.flatnonzero(usable[i])
        if len(candidates) == 0:
            continue
        order = candidates[np.argsort(np.abs(triangulation[i, candidates]
                                             - config.target_triangulation_deg),
                                      kind="stable")]
        in_image = offset[i, order] @ poses[i, :3, :3]  # baselines in camera i's frame
        in_image = in_image[:, :2] / np.maximum(np.linalg.norm(in_image[:, :2], axis=1,
                                                               keepdims=True), 1e-12)
        picked: list[np.ndarray] = []
        for j, d in zip(order, in_image, strict=True):
            if any(float(d @ p) > min_cos for p in picked):
                continue
            picked.append(d)
            chosen.add((min(i, int(j)), max(i, int(j))))
            if len(picked) >= config.max_pairs_per_image:
                break
    counts = {"candidates": int(np.triu(near).sum()), "degenerate": int(np.triu(degenerate).sum())}
    return sorted(chosen), counts
