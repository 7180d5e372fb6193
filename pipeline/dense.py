"""Dense reconstruction on the CPU: calibrated two-view stereo on neighbouring frames, fused.

pycolmap has no dense stereo without CUDA (DESIGN.md), so this stage is built from
well-kept parts instead, given the frames and their camera poses (the bot's, or refined ones):

1. Views: frames with a pose; a frame taken from the same spot as a sharper one is dropped.
2. Pairs: for each view, up to `max_pairs_per_image` neighbours whose optical axes differ by
   at most `max_view_angle_deg`, with a baseline in `baseline_m`, ranked by how close the
   triangulation angle at the scene is to `target_triangulation_deg`, with their baselines
   in different image directions (so an edge parallel to one baseline is matched across
   another). Pairs with a degenerate geometry (no baseline, or one along the optical axis,
   which puts the epipole in the image) are skipped and counted.
3. Stereo, per pair: calibrated rectification (`cv2.stereoRectify`'s rotations from the
   known relative pose, with x, y swapped when the baseline is vertical in the image; the
   rectified extents are chosen here so neither image is shrunk; rows only one image has
   are dropped), semi-global
   matching (`cv2.StereoSGBM`) of left on right and right on left over the disparity range
   the scene's depth range allows, a texture mask (no matches in the middle of the sky), a
   left-right consistency check, and both disparity maps turned into depth maps on the two
   original (scaled) image grids.
4. Per view: the median of its pairs' depth maps, without the pixels coloured like the
   unmatched background round them (the fringe SGM smears onto the sky round every edge).
5. Fusion: a view's pixel becomes a 3D point only when at least `min_consistent_views` other
   views see a surface at the same depth there (the point projected into them lands where
   their depth agrees within `depth_tolerance`): the main defence against the noisy matches
   on white, nearly textureless petals. The point is the mean of the agreeing views'
   estimates; its colour the brightest they see (the surface's best-lit look).
6. The cloud: cropped to the scene sphere, voxel down-sampled, cleared of points that some
   view sees straight through (free space), and of statistical outliers (Open3D).

Everything is vectorised NumPy/OpenCV; pairs run on a thread pool (OpenCV releases the GIL).

Frames (`frames/*.jpg`, `frames.json`, `camera.json`) are what `flowerpose frames` writes.
Intrinsics follow the project's pixel convention (COLMAP's: pixel centres at +0.5); inside
this module every camera matrix is OpenCV's (centres at integers), at the matching scale.
Poses are camera-to-bed (4, 4) matrices in metres with OpenCV camera axes.
"""

from __future__ import annotations

import os
import time
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from flowerpose.cloudio import Cloud
from flowerpose.config import require
from flowerpose.errors import InputError
from flowerpose.log import LOG, open3d
from flowerpose.pipeline.frames import ChosenFrame, distinct_views, is_rotation, read_frames
from flowerpose.scanio import Intrinsics, read_intrinsics

__all__ = ["DenseConfig", "reconstruct_dense", "select_pairs"]

Poses = Mapping[int | str, np.ndarray] | Sequence[np.ndarray | None] | np.ndarray


@dataclass(frozen=True)
class DenseConfig:
    """Dense reconstruction from posed frames (multi-view stereo on the CPU)."""

    # --- views and pairs ---
    max_view_angle_deg: float = 30.0
    """Two views can pair when their optical axes differ by at most this, degrees. The scan
    path's neighbours differ by 20 degrees (azimuth and dome steps)."""
    baseline_m: tuple[float, float] = (0.03, 0.2)
    """Camera-centre distance of a pair, metres (min, max). Shorter pairs triangulate poorly
    (2 cm at 0.5 m is 2 degrees); the scan path's horizontal neighbours are 0.17 m apart."""
    target_triangulation_deg: float = 14.0
    """A view's candidate partners are ranked by how close the angle between the two rays to
    the scene (at the view's expected depth) comes to this, degrees: a wider angle measures
    depth more finely, a narrower one makes the two images look more alike."""
    max_pairs_per_image: int = 4
    """Pairs each view asks for (it can take part in more: the pairs its neighbours chose).
    On the development scan 2, 3 and 4 gave 195, 294 and 344 pairs, 50, 61 and 77 s of
    matching on 2 cores, and plant F-scores at 5 mm of 0.87, 0.89 and 0.92 (more can rarely
    be had: the baselines must point 60 degrees apart)."""
    min_pair_direction_deg: float = 60.0
    """The baselines of one view's pairs must point at least this far apart in its image,
    degrees, so they match edges of different orientations (opposite directions count as
    different: they see round different sides of an occluder)."""
    min_epipole_angle_deg: float = 50.0
    """A pair is degenerate (skipped) when its baseline lies within this angle of either
    optical axis, degrees: the epipole then falls in or near the image and planar
    rectification stretches it without bound (forward motion)."""
    duplicate_distance_m: float = 0.005
    """Frames within this distance of a sharper frame, looking the same way (within
    `duplicate_angle_deg`), add nothing but time: they are dropped, metres."""
    duplicate_angle_deg: float = 2.0
    """The viewing directions of such duplicates differ by at most this, degrees."""
    # --- matching ---
    image_scale: float = 0.5
    """Images are resized by this before matching (1280 x 720 -> 640 x 360): SGM's time grows
    with the pixel count times the disparity range, so four times the pixels cost about
    eight times the time."""
    sgbm_mode: Literal["sgbm", "3way", "hh4", "hh"] = "3way"
    """cv2.StereoSGBM mode: "3way" (the fastest: half the time of "sgbm", as accurate on
    the development scan), "sgbm" (5 paths), "hh4", "hh" (full 8 paths, slow)."""
    block_size: int = 5
    """SGBM matching block side, pixels (odd)."""
    p1: int | None = None
    """SGBM penalty for a disparity change of 1 between neighbours; None: block_size^2.
    OpenCV suggests 8 and 32 block_size^2 for P1 and P2; the gentler 1 and 12 gave 14 %
    more pair depths within 5 mm of the truth on the development scan, and more of them
    right (the smooth petals and leaves are slanted, not fronto-parallel)."""
    p2: int | None = None
    """SGBM penalty for larger disparity changes; None: 12 * block_size^2."""
    uniqueness_ratio: int = 20
    """SGBM: the best cost must beat the second best by this percentage, else no match
    (OpenCV suggests 5-15; 20 took the share of pair depths within 5 mm of the truth from
    0.82 to 0.92 on the development scan, for 15 % fewer of them)."""
    speckle_window_px: int = 300
    """SGBM speckle filter: disparity blobs smaller than this (pixels) are removed (0: no
    filter). Small blobs are mostly mismatches on the smooth petals and in the sky."""
    speckle_range: int = 1
    """SGBM speckle filter: largest disparity step within one blob (OpenCV multiplies by 16)."""
    pre_filter_cap: int = 31
    """SGBM: clip of the x-derivative prefilter."""
    max_disparities: int = 256
    """Largest disparity search range of a pair, pixels (a multiple of 16); a pair that the
    depth range would give more loses the nearest depths."""
    min_texture: float = 2.5
    """Grey-level standard deviation (0-255) over a matching block that counts as texture;
    0: no texture mask."""
    texture_radius_px: float = 4.0
    """Pixels farther than this from any textured pixel are left unmatched (see
    `min_texture`): SGM would fill them with the disparity of what surrounds them, which
    puts the sky round every leaf's edge."""
    lr_max_diff_px: float = 1.0
    """Left-right check: a disparity is kept when the other image's disparity at its match
    differs by at most this, pixels."""
    # --- depth ---
    depth_range_m: tuple[float, float] = (0.08, 1.5)
    """Depths (along the optical axis) any view may see, metres (min, max)."""
    scene_radius_m: float | None = 0.3
    """The scene (the plant and the soil round it) lies within this distance of the scene
    centre, the point nearest all optical axes (the scan looks at the plant), metres: each
    view searches only depths within it of the centre's depth, and the cloud is cropped to
    this sphere (the bed and sky beyond are not the plant). The paper's plants, 0.3 m tall
    and 0.4 m wide, fit with a margin (the development plant reaches 0.24 m). None: no
    crop, `depth_range_m` alone."""
    # --- fusion ---
    min_pair_support: int = 1
    """A view's pixel needs this many of its pairs' depth maps agreeing (within
    `depth_tolerance`) with their median."""
    background_window_px: int = 11
    """A matched pixel whose colour is nearer the mean colour of the unmatched pixels in
    this window round it than that of the matched ones is dropped (0: no such check). SGM
    smears a surface's disparity a few pixels onto a textureless background (the sky round
    every leaf seen from the side), and those pixels have the background's colour. On the
    development scan: sky-coloured points 4.4 % -> 2.5 %, petal precision at 2 mm 0.91 ->
    0.98, flowers the colour detector finds 7 -> 11 of 18."""
    fusion_neighbours: int = 16
    """Views a view's depths are checked against: the nearest in viewing direction among
    those within `fusion_max_angle_deg` and `fusion_max_distance_m` (16 rather than 10:
    plant F-score at 5 mm 0.92 -> 0.93, 2 s more)."""
    fusion_max_angle_deg: float = 45.0
    """Largest optical-axis difference of a view checked against, degrees."""
    fusion_max_distance_m: float = 0.4
    """Largest camera-centre distance of a view checked against, metres."""
    min_consistent_views: int = 2
    """A pixel becomes a point when at least this many other views agree with its depth."""
    depth_tolerance: float = 0.01
    """Relative depth difference under which two views agree (0.01: 5 mm at 0.5 m)."""
    max_free_space_violations: int | None = 0
    """After voxel down-sampling, a point is dropped when more than this many views (all of
    them are checked) see past it: their depth where it projects is larger by over
    `free_space_tolerance`, so it floats in empty space. This removes the fringe matching
    smears from every edge into a textureless background (the sky, a wall): views near the
    one that made it agree with it, but views from elsewhere see through it. On the
    development scan: sky-coloured points 10 % -> 0.8 %, petal precision at 2 mm 0.71 ->
    0.90. None: no check."""
    free_space_tolerance: float = 0.03
    """Relative depth excess that counts as seeing past a point (0.03: 15 mm at 0.5 m)."""
    free_space_window_px: int = 3
    """A view sees past a point only when its depths over this window (pixels, odd) round
    where the point lands all do: thin stems and edges survive a pixel's misalignment."""
    # --- cloud ---
    voxel_size_m: float = 0.001
    """Voxel down-sampling edge, metres (one point per voxel, its points' mean); 0: none.
    1 mm is the detect stage's grid pixel (`GridConfig.pixel_size_m`)."""
    brightest_view_colour: bool = True
    """A fused point takes the second-brightest colour among its own view and the views
    that agree on it: a well-lit look of the surface. Only 29 % of the petal pixels in the
    development scan's images are bright (value >= 0.70); the rest are petals seen edge-on
    or from their shaded side. Not the brightest: at an edge, one view a pixel off sees
    the bright sky past a dark leaf, and that sheen made leaves look like petals (seed 1 of
    the benchmark: plane errors of 39 and 50 degrees with the brightest, 5.9 at most with
    the second). False: the point's own view's colour."""
    voxel_colour_quantile: float | None = 0.75
    """A voxel's colour is that of its point at this brightness quantile (None: the mean
    colour). A petal's lit face and its shaded back (or its shaded look from the side)
    share voxels, and the mean greys white petals below what the colour detector takes for
    white; the brightest point (1.0) would let one sky-coloured point from an edge colour a
    dark stem's voxel; 0.75 keeps the well-lit look of most voxels."""
    outlier_neighbours: int = 20
    """Statistical outlier removal: neighbours averaged (0: no removal)."""
    outlier_std_ratio: float = 2.0
    """Statistical outlier removal: points farther than the mean neighbour distance plus this
    many standard deviations are removed."""
    threads: int = 0
    """Worker threads for the pairs; 0: one per CPU core."""

    def __post_init__(self):
        checks = [
            (0 < self.image_scale <= 1, "image_scale", "must be in (0, 1]"),
            (self.block_size >= 1 and self.block_size % 2 == 1, "block_size",
             "must be a positive odd number"),
            (self.max_disparities >= 16 and self.max_disparities % 16 == 0, "max_disparities",
             "must be a positive multiple of 16"),
            (0 <= self.baseline_m[0] < self.baseline_m[1], "baseline_m", "needs 0 <= min < max"),
            (0 < self.depth_range_m[0] < self.depth_range_m[1], "depth_range_m",
             "needs 0 < min < max"),
            (self.max_pairs_per_image >= 1, "max_pairs_per_image", "must be at least 1"),
            (self.min_pair_support >= 1, "min_pair_support", "must be at least 1"),
            (self.min_consistent_views >= 0, "min_consistent_views", "must be 0 or more"),
            (self.fusion_neighbours >= 1, "fusion_neighbours", "must be at least 1"),
            (self.depth_tolerance > 0, "depth_tolerance", "must be positive"),
            (self.lr_max_diff_px >= 0, "lr_max_diff_px", "must be 0 or more"),
            (self.free_space_tolerance > 0, "free_space_tolerance", "must be positive"),
            (self.free_space_window_px >= 1 and self.free_space_window_px % 2 == 1,
             "free_space_window_px", "must be a positive odd number"),
            (self.scene_radius_m is None or self.scene_radius_m > 0, "scene_radius_m",
             "must be positive (metres) or unset"),
            (self.voxel_size_m >= 0, "voxel_size_m", "must be 0 or more (metres)"),
            (self.voxel_colour_quantile is None or 0 <= self.voxel_colour_quantile <= 1,
             "voxel_colour_quantile", "must be within 0-1 or unset"),
            (self.threads >= 0, "threads", "must be 0 (every core) or more"),
            (self.sgbm_mode in _SGBM_MODES, "sgbm_mode", f"one of {', '.join(_SGBM_MODES)}"),
        ]
        for ok, key, problem in checks:
            require(ok, f"dense.{key}", problem)


_SGBM_MODES = {"sgbm": cv2.STEREO_SGBM_MODE_SGBM, "3way": cv2.STEREO_SGBM_MODE_SGBM_3WAY,
               "hh4": cv2.STEREO_SGBM_MODE_HH4, "hh": cv2.STEREO_SGBM_MODE_HH}


# ----------------------------------------------------------------------------- inputs

def _resolve_poses(frames_dir: Path, frames: list[ChosenFrame], poses: Poses | None
                   ) -> list[np.ndarray | None]:
    """One (4, 4) pose or None per frames.json frame, checked."""
    source: str | Path = "poses"
    if poses is None:
        poses, source = {f.index: f.pose for f in frames}, frames_dir / "frames.json"
    if isinstance(poses, Mapping):
        resolved = [poses.get(f.index, poses.get(f.file)) for f in frames]
    else:
        if len(poses) != len(frames):
            raise InputError("poses", f"{len(poses)} poses for {len(frames)} frames in "
                             f"{frames_dir / 'frames.json'}")
        resolved = list(poses)
    out: list[np.ndarray | None] = []
    for frame, pose in zip(frames, resolved, strict=True):
        if pose is None:
            out.append(None)
            continue
        pose = np.asarray(pose, float)
        if pose.shape != (4, 4) or not np.isfinite(pose).all():
            raise InputError(source, f"frame {frame.index}: expected a finite (4, 4) "
                             "camera-to-bed matrix")
        if not is_rotation(pose[:3, :3]):
            raise InputError(source, f"frame {frame.index}: the rotation is not a rotation")
        out.append(pose)
    return out


def _opencv_matrix(intrinsics: Intrinsics) -> np.ndarray:
    """K with OpenCV's pixel centres (integers)."""
    k = intrinsics.matrix.copy()
    k[0, 2] -= 0.5
    k[1, 2] -= 0.5
    return k


def _load_image(path: Path, size: tuple[int, int], expected: tuple[int, int]
                ) -> tuple[np.ndarray, np.ndarray, float]:
    """(grey uint8, RGB uint8, sharpness) at the matching size."""
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise InputError(path, "unreadable image (missing or not an image)")
    if (bgr.shape[1], bgr.shape[0]) != expected:
        raise InputError(path, f"image is {bgr.shape[1]}x{bgr.shape[0]} but the intrinsics are "
                         f"for {expected[0]}x{expected[1]}")
    if (bgr.shape[1], bgr.shape[0]) != size:
        bgr = cv2.resize(bgr, size, interpolation=cv2.INTER_AREA)
    grey = np.maximum(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY), 1)  # 0: outside, when rectified
    sharpness = float(cv2.Laplacian(grey, cv2.CV_32F).var())
    return grey, cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), sharpness


# ----------------------------------------------------------------------------- geometry

def _times(points: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """points (..., m) @ matrix (m, n) in the points' dtype. einsum, not `@`: OpenBLAS's
    product of a tall array with a 3-wide one is several times slower on a busy 2-core
    machine."""
    return np.einsum("...i,ij->...j", points, matrix.astype(points.dtype))


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between unit vectors along the last axis, degrees."""
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=-1), -1.0, 1.0)))


def _scene_centre(centres: np.ndarray, axes: np.ndarray) -> np.ndarray | None:
    """The point nearest (least squares) all optical axes; None when they are parallel."""
    projector = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]
    a = projector.sum(axis=0)
    b = np.einsum("nij,nj->i", projector, centres)
    if np.linalg.cond(a) > 1e6:
        return None
    return np.linalg.solve(a, b)


def _depth_ranges(centres: np.ndarray, axes: np.ndarray, config: DenseConfig
                  ) -> tuple[np.ndarray, np.ndarray | None]:
    """(N, 2) depth search range per view, metres, and the scene centre (None: unknown or
    not used)."""
    lo, hi = config.depth_range_m
    ranges = np.tile([lo, hi], (len(centres), 1)).astype(float)
    if config.scene_radius_m is None or len(centres) < 2:
        return ranges, None
    centre = _scene_centre(centres, axes)
    if centre is None:
        return ranges, None
    depth = np.sum((centre - centres) * axes, axis=1)
    near = np.clip(depth - config.scene_radius_m, lo, hi)
    far = np.clip(depth + config.scene_radius_m, lo, hi)
    ok = far > near
    ranges[ok] = np.c_[near, far][ok]
    return ranges, centre


def select_pairs(poses: np.ndarray, config: DenseConfig = DenseConfig(),
                 expected_depth: np.ndarray | None = None) -> tuple[list[tuple[int, int]], dict]:
    """Stereo pairs among views with (N, 4, 4) camera-to-bed poses.

    Returns (pairs (i, j) with i < j, counts): counts["candidates"] are the pairs near enough
    in position and viewing direction, counts["degenerate"] those of them skipped for a
    baseline that is too short or along an optical axis. expected_depth (N,): the depth of
    the scene along each view's axis (default: the middle of `depth_range_m`).
    """
    poses = np.asarray(poses, float)
    n = len(poses)
    centres, axes = poses[:, :3, 3], poses[:, :3, 2]
    if expected_depth is None:
        expected_depth = np.full(n, np.mean(config.depth_range_m))
    offset = centres[None, :, :] - centres[:, None, :]  # [i, j] = C_j - C_i
    baseline = np.linalg.norm(offset, axis=-1)
    view_angle = _angle_deg(axes[:, None], axes[None, :])
    near = (view_angle <= config.max_view_angle_deg) & (baseline <= config.baseline_m[1])
    np.fill_diagonal(near, False)
    direction = offset / np.maximum(baseline, 1e-12)[..., None]

    def from_axis(axis):  # angle between the baseline's line and an optical axis, degrees
        angle = _angle_deg(direction, axis)
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
    triangulation = _angle_deg(to_scene_i, to_scene_j)
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


# ----------------------------------------------------------------------------- stereo

@dataclass
class _View:
    grey: np.ndarray
    rgb: np.ndarray
    pose: np.ndarray
    depth_range: tuple[float, float]
    depths: list[tuple[int, np.ndarray]] = field(default_factory=list)
    """(partner view, depth map on this view's grid) per stereo pair."""


_PERMUTATIONS = {
    # rectified-frame axis changes that put the second camera on the +x side: identity,
    # a half turn about z, and the two axis swaps (a vertical baseline made horizontal).
    "right": np.eye(3),
    "left": np.diag([-1.0, -1.0, 1.0]),
    "down": np.array([[0.0, 1, 0], [1, 0, 0], [0, 0, 1]]),
    "up": np.array([[0.0, -1, 0], [-1, 0, 0], [0, 0, 1]]),
}


def _rectify(k: np.ndarray, size: tuple[int, int], pose_i: np.ndarray, pose_j: np.ndarray,
             max_extent: float = 2.5):
    """Rectifying rotations (original camera -> rectified frame) of views i and j, with
    camera j on the rectified +x side; the baseline (m); the rectified focal length; and the
    rectified extents (u_min, u_max) of both images and their shared rows (v_min, v_max) at a
    zero principal point; and the range (min, max) over both images of a pixel ray's
    rectified z per unit of original depth (rectified depth = original depth * that). None
    when the rectification is degenerate."""
    width, height = size
    r_i, c_i = pose_i[:3, :3], pose_i[:3, 3]
    r_j, c_j = pose_j[:3, :3], pose_j[:3, 3]
    rotation = r_j.T @ r_i  # camera i -> camera j
    translation = (r_j.T @ (c_i - c_j)).reshape(3, 1)
    if np.linalg.norm(translation) < 1e-9:
        return None
    rect_i, rect_j, *_ = cv2.stereoRectify(k, None, k, None, size, rotation, translation,
                                           flags=cv2.CALIB_ZERO_DISPARITY, alpha=-1)
    if not (np.isfinite(rect_i).all() and np.isfinite(rect_j).all()):
        return None
    # stereoRectify puts the baseline on x or, when it is mostly vertical, on y; an axis
    # change puts camera j on +x (a swap of x and y is a mirror, which matching ignores).
    t = rect_i @ (r_i.T @ (c_j - c_i))
    name = ("right" if t[0] > 0 else "left") if abs(t[0]) >= abs(t[1]) else (
        "down" if t[1] > 0 else "up")
    perm = _PERMUTATIONS[name]
    rect_i, rect_j = perm @ rect_i, perm @ rect_j
    common_i, common_j = rect_i @ r_i.T, rect_j @ r_j.T  # bed -> rectified frame
    t = common_i @ (c_j - c_i)
    baseline = float(t[0])
    if (baseline <= 0 or np.abs(common_i - common_j).max() > 1e-5
            or np.hypot(t[1], t[2]) > 1e-4 * baseline):
        return None
    focal = float(k[0, 0] + k[1, 1]) / 2
    edge = np.linspace(0.0, 1.0, 9)
    border = np.concatenate([np.c_[edge * (width - 1), np.zeros(9)],
                             np.c_[edge * (width - 1), np.full(9, height - 1.0)],
                             np.c_[np.zeros(9), edge * (height - 1)],
                             np.c_[np.full(9, width - 1.0), edge * (height - 1)]])
    pixels = np.c_[border, np.ones(len(border))]
    boxes, ray_z = [], []
    for rect in (rect_i, rect_j):
        # The border includes the corners, where z (linear in the pixel) is extreme.
        rays = (rect @ np.linalg.solve(k, pixels.T)).T
        if (rays[:, 2] <= 1e-3).any():
            return None
        uv = focal * rays[:, :2] / rays[:, 2:3]
        boxes.append((uv[:, 0].min(), uv[:, 0].max(), uv[:, 1].min(), uv[:, 1].max()))
        ray_z += [rays[:, 2].min(), rays[:, 2].max()]
    rows = (max(boxes[0][2], boxes[1][2]), min(boxes[0][3], boxes[1][3]))
    if (rows[1] - rows[0] < 16 or rows[1] - rows[0] > max_extent * height
            or any(b[1] - b[0] > max_extent * width for b in boxes)):
        return None
    return (rect_i, rect_j, baseline, focal, boxes[0][:2], boxes[1][:2], rows,
            (float(min(ray_z)), float(max(ray_z))))


def _rectify_maps(k: np.ndarray, rect: np.ndarray, focal: float, cx: float, cy: float,
                  out_size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """cv2.remap maps from the rectified image back into the original one."""
    new_k = np.array([[focal, 0, cx], [0, focal, cy], [0, 0, 1.0]])
    return cv2.initUndistortRectifyMap(k, None, rect, new_k, out_size, cv2.CV_32FC1)


def _sample_rectified(k: np.ndarray, rect: np.ndarray, focal: float, cx: float, cy: float,
                      size: tuple[int, int], values: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Per original pixel: the nearest rectified value (NaN outside) and the z of its ray
    (z = 1 in the original camera) in the rectified frame."""
    width, height = size
    u, v = np.meshgrid(np.arange(width, dtype=np.float32), np.arange(height, dtype=np.float32))
    rays = np.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1],
                     np.ones_like(u)], axis=-1)
    rays = _times(rays, rect.T)
    z = rays[..., 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        iu = np.rint(focal * rays[..., 0] / z + cx)
        iv = np.rint(focal * rays[..., 1] / z + cy)
    inside = (iu >= 0) & (iu < values.shape[1]) & (iv >= 0) & (iv < values.shape[0]) & (z > 0)
    sampled = np.full((height, width), np.nan, np.float32)
    sampled[inside] = values[iv[inside].astype(np.int64), iu[inside].astype(np.int64)]
    return sampled, z


def _matcher(config: DenseConfig, num_disparities: int):
    area = config.block_size ** 2
    return cv2.StereoSGBM.create(
        minDisparity=0, numDisparities=num_disparities, blockSize=config.block_size,
        P1=config.p1 if config.p1 is not None else area,
        P2=config.p2 if config.p2 is not None else 12 * area,
        disp12MaxDiff=-1, preFilterCap=config.pre_filter_cap,
        uniquenessRatio=config.uniqueness_ratio, speckleWindowSize=config.speckle_window_px,
        speckleRange=config.speckle_range, mode=_SGBM_MODES[config.sgbm_mode])


def _stereo_pair(view_i: _View, view_j: _View, k: np.ndarray, config: DenseConfig
                 ) -> tuple[np.ndarray, np.ndarray, float] | str:
    """Depth maps (on the two original image grids, NaN where unknown) of one pair, with the
    share of left pixels matched; or the reason it was skipped."""
    height, width = view_i.grey.shape
    geometry = _rectify(k, (width, height), view_i.pose, view_j.pose)
    if geometry is None:
        return "degenerate"
    (rect_i, rect_j, baseline, focal, (umin_i, umax_i), (umin_j, umax_j), rows,
     (z_low, z_high)) = geometry
    # Disparity follows the rectified depth: the views' depth range times the rays' z.
    near = min(view_i.depth_range[0], view_j.depth_range[0]) * z_low
    far = max(view_i.depth_range[1], view_j.depth_range[1]) * z_high
    # With principal points cx_i, cx_j the disparity is focal * baseline / z + cx_i - cx_j.
    # SGBM searches [0, num) and leaves the first `num` columns of its left image unmatched,
    # so the left image starts `num` columns in and the right one is placed for the
    # farthest depth to give disparity 0 (and `num` columns of room on its right, for the
    # right-on-left pass on mirrored images).
    span = focal * baseline * (1.0 / (near * 0.95) - 1.0 / (far * 1.05))
    num = int(min(config.max_disparities, max(16, np.ceil(span / 16.0) * 16)))
    cx_i = num - umin_i
    cx_j = cx_i + focal * baseline / (far * 1.05)  # disparity 0 at the far limit
    shift = cx_i - cx_j
    out_w = int(np.ceil(max(cx_i + umax_i, cx_j + umax_j + num))) + 1
    cy = -rows[0]
    out_size = (out_w, int(np.ceil(rows[1] - rows[0])) + 1)
    if out_w > 4 * width:
        return "degenerate"
    left = cv2.remap(view_i.grey, *_rectify_maps(k, rect_i, focal, cx_i, cy, out_size),
                     cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    right = cv2.remap(view_j.grey, *_rectify_maps(k, rect_j, focal, cx_j, cy, out_size),
                      cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    matcher = _matcher(config, num)
    raw_l = matcher.compute(left, right)
    raw_r = cv2.flip(matcher.compute(cv2.flip(right, 1), cv2.flip(left, 1)), 1)
    # Pixels outside an image (0 after the remap; images hold 1..255) and a block's width
    # round them match the image border itself, not the scene.
    grow = np.ones((config.block_size + 2, config.block_size + 2), np.uint8)
    outside_l = cv2.dilate((left == 0).astype(np.uint8), grow) > 0
    outside_r = cv2.dilate((right == 0).astype(np.uint8), grow) > 0
    if config.min_texture > 0:
        outside_l |= _textureless(left, config)
        outside_r |= _textureless(right, config)
    disp_l = np.where((raw_l >= 0) & ~outside_l, raw_l.astype(np.float32) / 16.0, np.nan)
    disp_r = np.where((raw_r >= 0) & ~outside_r, raw_r.astype(np.float32) / 16.0, np.nan)
    disp_l, disp_r = _left_right_check(disp_l, disp_r, config.lr_max_diff_px)
    matched = float(np.isfinite(disp_l).sum() / max(1, (~outside_l).sum()))
    depths = []
    for view, rect, cx, disp in ((view_i, rect_i, cx_i, disp_l), (view_j, rect_j, cx_j, disp_r)):
        sampled, ray_z = _sample_rectified(k, rect, focal, cx, cy, (width, height), disp)
        with np.errstate(invalid="ignore", divide="ignore"):
            depth = focal * baseline / (sampled - shift) / ray_z
            depth[~((depth >= view.depth_range[0]) & (depth <= view.depth_range[1]))] = np.nan
        depths.append(depth.astype(np.float32))
    return depths[0], depths[1], matched


def _textureless(grey: np.ndarray, config: DenseConfig) -> np.ndarray:
    """Pixels farther than `texture_radius_px` from any pixel whose block has a grey-level
    standard deviation of at least `min_texture`: SGM fills such regions (the sky) with
    the disparity of their surroundings."""
    size = (config.block_size, config.block_size)
    values = grey.astype(np.float32)
    mean = cv2.blur(values, size)
    std = np.sqrt(np.maximum(cv2.blur(values * values, size) - mean * mean, 0.0))
    textured = (std >= config.min_texture).astype(np.uint8)
    distance = cv2.distanceTransform(1 - textured, cv2.DIST_L2, 3)
    return distance > config.texture_radius_px


def _left_right_check(disp_l: np.ndarray, disp_r: np.ndarray, max_diff: float
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Disparities kept where the other image's disparity at the match agrees."""
    height, width = disp_l.shape
    cols = np.arange(width, dtype=np.float32)[None, :]

    def check(disp, other, sign):
        with np.errstate(invalid="ignore"):
            target = np.rint(cols + sign * disp)
        ok = np.isfinite(target) & (target >= 0) & (target < width)
        index = np.where(ok, target, 0).astype(np.int64)
        theirs = np.take_along_axis(other, index, axis=1)
        with np.errstate(invalid="ignore"):
            ok &= np.abs(theirs - disp) <= max_diff
        return np.where(ok, disp, np.nan)

    return check(disp_l, disp_r, -1.0), check(disp_r, disp_l, 1.0)


# ----------------------------------------------------------------------------- fusion

def _merge_depths(depths: list[np.ndarray], tolerance: float, min_support: int
                  ) -> np.ndarray | None:
    """The per-pixel median of a view's depth maps, kept where at least `min_support` of
    them agree with it (within `tolerance`, relative)."""
    if not depths:
        return None
    shape = depths[0].shape
    stack = np.stack(depths).reshape(len(depths), -1)
    valid = np.isfinite(stack)
    count = valid.sum(axis=0)
    merged = np.full(stack.shape[1], np.nan, np.float32)
    single = np.flatnonzero(count == 1)
    merged[single] = np.nanmax(stack[:, single], axis=0) if len(single) else []
    multi = np.flatnonzero(count > 1)
    if len(multi):
        values = np.sort(np.where(valid[:, multi], stack[:, multi], np.inf), axis=0)
        n = count[multi]
        columns = np.arange(len(multi))
        median = (values[(n - 1) // 2, columns] + values[n // 2, columns]) / 2
        merged[multi] = median
        # Two depths far apart have a median neither supports: that pixel is dropped.
        with np.errstate(invalid="ignore"):
            support = (np.abs(values - median) <= tolerance * median).sum(axis=0)
        merged[multi[support < min_support]] = np.nan
    if min_support > 1:
        merged[single] = np.nan
    return merged.reshape(shape)


def _drop_background_coloured(depth: np.ndarray, rgb: np.ndarray, window: int
                              ) -> np.ndarray:
    """The depth map without the pixels whose colour is nearer the mean colour of the
    unmatched pixels round them than that of the matched ones: the fringe of background
    (sky) that matching smears onto the edge of a surface in front of it."""
    known = np.isfinite(depth).astype(np.float32)
    colour = rgb.astype(np.float32)
    size = (window, window)
    count_known = cv2.boxFilter(known, -1, size, normalize=False)
    count_unknown = float(window * window) - count_known
    sum_all = cv2.boxFilter(colour, -1, size, normalize=False)
    sum_known = cv2.boxFilter(colour * known[..., None], -1, size, normalize=False)
    boundary = (known > 0) & (count_unknown > 0.5) & (count_known > 0.5)
    mean_known = sum_known / np.maximum(count_known, 1.0)[..., None]
    mean_unknown = (sum_all - sum_known) / np.maximum(count_unknown, 1.0)[..., None]
    nearer = (np.square(colour - mean_unknown).sum(axis=2)
              < np.square(colour - mean_known).sum(axis=2))
    depth = depth.copy()
    depth[boundary & nearer] = np.nan
    return depth


def _fusion_neighbours(poses: np.ndarray, config: DenseConfig) -> list[np.ndarray]:
    centres, axes = poses[:, :3, 3], poses[:, :3, 2]
    angle = _angle_deg(axes[:, None], axes[None, :])
    distance = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    allowed = (angle <= config.fusion_max_angle_deg) & (distance <= config.fusion_max_distance_m)
    np.fill_diagonal(allowed, False)
    out = []
    for i in range(len(poses)):
        candidates = np.flatnonzero(allowed[i])
        out.append(candidates[np.argsort(angle[i, candidates], kind="stable")]
                   [:config.fusion_neighbours])
    return out


def _fuse_view(i: int, depth_maps: list[np.ndarray | None], views: list[_View],
               neighbours: np.ndarray, k: np.ndarray, config: DenseConfig
               ) -> tuple[np.ndarray, np.ndarray]:
    """Points (bed frame) and colours from view i's depth map, kept where enough
    neighbouring views agree; each point the mean of the agreeing views' estimates."""
    depth = depth_maps[i]
    rows, cols = np.nonzero(np.isfinite(depth))
    if len(rows) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    z = depth[rows, cols].astype(np.float64)
    pose = views[i].pose
    rays = np.stack([(cols - k[0, 2]) / k[0, 0], (rows - k[1, 2]) / k[1, 1],
                     np.ones(len(rows))], axis=1)
    points = _times(rays * z[:, None], pose[:3, :3].T) + pose[:3, 3]
    total = points.copy()
    agree = np.zeros(len(rows), np.int32)
    # The brightest and second-brightest looks of each point: the second is kept, so one
    # view that sees past an edge onto the bright sky cannot colour a dark leaf.
    colour = views[i].rgb[rows, cols]
    brightness = colour.max(axis=1).astype(np.int16)
    second_colour = colour.copy()
    second = np.full(len(rows), -1, np.int16)
    height, width = depth.shape
    for n in neighbours:
        other = depth_maps[n]
        if other is None:
            continue
        rotation, centre = views[n].pose[:3, :3], views[n].pose[:3, 3]
        local = _times(points - centre, rotation)
        zn = local[:, 2]
        with np.errstate(invalid="ignore", divide="ignore"):
            u = np.rint(k[0, 0] * local[:, 0] / zn + k[0, 2])
            v = np.rint(k[1, 1] * local[:, 1] / zn + k[1, 2])
        ok = (zn > 0) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
        found = np.full(len(rows), np.nan)
        found[ok] = other[v[ok].astype(np.int64), u[ok].astype(np.int64)]
        with np.errstate(invalid="ignore"):
            ok = np.abs(found - zn) <= config.depth_tolerance * zn
        agree += ok
        # The agreeing view's estimate: the point moved along that view's ray to its depth.
        scale = found[ok] / zn[ok]
        total[ok] += centre + (points[ok] - centre) * scale[:, None]
        if config.brightest_view_colour:
            index = np.flatnonzero(ok)
            seen = views[n].rgb[v[index].astype(np.int64), u[index].astype(np.int64)]
            level = seen.max(axis=1).astype(np.int16)
            top = level > brightness[index]
            runner_up = ~top & (level > second[index])
            demoted = index[top]
            second_colour[demoted] = colour[demoted]
            second[demoted] = brightness[demoted]
            colour[demoted] = seen[top]
            brightness[demoted] = level[top]
            second_colour[index[runner_up]] = seen[runner_up]
            second[index[runner_up]] = level[runner_up]
    keep = agree >= config.min_consistent_views
    fused = total[keep] / (agree[keep] + 1)[:, None]
    if config.brightest_view_colour:
        colour = np.where((second >= 0)[:, None], second_colour, colour)
    return fused, colour[keep]


# ----------------------------------------------------------------------------- the stage

def reconstruct_dense(frames_dir: str | Path, poses: Poses | None = None,
                      intrinsics: Intrinsics | None = None,
                      config: DenseConfig = DenseConfig(),
                      progress: bool = False) -> tuple[Cloud, dict]:
    """A dense coloured cloud (bed frame, metres) from posed frames, and a report.

    frames_dir holds frames.json (frame "index" and "file" per frame) and the images;
    poses: camera-to-bed (4, 4) matrices, metres, as a mapping from the frame's "index" or
    its "file" (as frames.json names it: "frames/frame_000012.jpg", COLMAP's image name) to
    its pose, frames without one left out; or one pose (or None) per frames.json entry in
    its order; None: frames.json's own poses (the bot's).
    intrinsics: None reads frames_dir/camera.json (the project's pixel convention).
    The report: views, pairs (candidates, used, skipped with reasons), points before and
    after fusion and filtering, seconds per step, and the config.
    """
    start = time.perf_counter()
    seconds: dict[str, float] = {}
    lap = [start]

    def step(name: str) -> None:
        now = time.perf_counter()
        seconds[name] = round(now - lap[0], 3)
        lap[0] = now

    def say(message: str) -> None:
        if progress:
            LOG.info(f"dense: {message} ({time.perf_counter() - start:.1f} s)")

    frames_dir = Path(frames_dir)
    if not frames_dir.is_dir():
        raise InputError(frames_dir, "frames folder not found")
    frames = read_frames(frames_dir, need_poses=poses is None)
    frame_poses = _resolve_poses(frames_dir, frames, poses)
    if intrinsics is None:
        intrinsics = read_intrinsics(frames_dir / "camera.json")
    posed = [n for n, p in enumerate(frame_poses) if p is not None]
    if len(posed) < 2:
        raise InputError(frames_dir, f"dense reconstruction needs at least 2 frames with a "
                         f"pose, got {len(posed)}")
    size = (max(16, round(intrinsics.width * config.image_scale)),
            max(16, round(intrinsics.height * config.image_scale)))
    k = _opencv_matrix(intrinsics.scaled(*size))
    threads = config.threads or os.cpu_count() or 1

    with ThreadPoolExecutor(threads) as pool:
        loaded = list(pool.map(
            lambda n: _load_image(frames_dir / frames[n].file, size,
                                  (intrinsics.width, intrinsics.height)), posed))
    step("load")
    say(f"loaded {len(posed)} frames at {size[0]}x{size[1]}")

    pose_array = np.stack([frame_poses[n] for n in posed])
    keep = _drop_duplicates(pose_array, np.array([s for *_, s in loaded]), config)
    pose_array = pose_array[keep]
    loaded = [loaded[n] for n in keep]
    centres, axes = pose_array[:, :3, 3], pose_array[:, :3, 2]
    ranges, scene_centre = _depth_ranges(centres, axes, config)
    views = [_View(grey, rgb, pose, (float(r[0]), float(r[1])))
             for (grey, rgb, _), pose, r in zip(loaded, pose_array, ranges, strict=True)]
    del loaded
    pairs, counts = select_pairs(pose_array, config, expected_depth=ranges.mean(axis=1))
    step("pairs")
    if not pairs:
        raise InputError(frames_dir, f"no usable stereo pairs among {len(views)} views "
                         f"({counts['candidates']} neighbouring pairs, {counts['degenerate']} "
                         f"degenerate: baselines under {config.baseline_m[0]} m or along the "
                         "view); the frames need camera centres apart across the view")
    say(f"{len(pairs)} pairs from {len(views)} views")

    skipped, matched = _stereo_all(views, pairs, k, config, threads, say)
    skipped["degenerate_geometry"] = counts["degenerate"]
    step("stereo")
    used = len(matched)
    if used == 0:
        raise InputError(frames_dir, f"all {len(pairs)} stereo pairs were degenerate")
    cloud, point_counts, fusion_seconds = _fuse_and_filter(views, k, config, threads,
                                                           scene_centre)
    if len(cloud) == 0:
        raise InputError(frames_dir, f"no point passed fusion and filtering (points after "
                         f"each step: {point_counts}); the frames overlap too little or "
                         "their poses are wrong")
    seconds.update(fusion_seconds)
    seconds["total"] = round(time.perf_counter() - start, 3)
    say(f"{len(cloud)} points")
    report = {
        "frames": len(frames), "posed": len(posed), "views": len(views),
        "duplicate_views": len(posed) - len(views),
        "image_size": list(size),
        "pairs": {"candidates": counts["candidates"], "selected": len(pairs), "used": used,
                  "skipped": skipped,
                  "matched_fraction_mean": round(float(np.mean(matched)), 4)},
        "points": point_counts,
        "seconds": seconds, "threads": threads, "config": asdict(config)}
    return cloud, report


def _stereo_all(views: list[_View], pairs: list[tuple[int, int]], k: np.ndarray,
                config: DenseConfig, threads: int, say) -> tuple[dict[str, int], list[float]]:
    """Every pair's two depth maps appended to its views' `depths` (with the partner's
    index); returns (skipped pairs by reason, matched share per used pair)."""
    skipped: dict[str, int] = {}
    matched: list[float] = []
    with ThreadPoolExecutor(threads) as pool:
        results = pool.map(lambda p: _stereo_pair(views[p[0]], views[p[1]], k, config), pairs)
        for done, ((i, j), result) in enumerate(zip(pairs, results, strict=True), 1):
            if isinstance(result, str):
                reason = f"{result}_rectification"
                skipped[reason] = skipped.get(reason, 0) + 1
                continue
            views[i].depths.append((j, result[0]))
            views[j].depths.append((i, result[1]))
            matched.append(result[2])
            if done % 50 == 0:
                say(f"stereo {done}/{len(pairs)} pairs")
    return skipped, matched


def _fuse_all(views: list[_View], k: np.ndarray, config: DenseConfig, threads: int
              ) -> tuple[list[tuple[np.ndarray, np.ndarray]], list[np.ndarray | None], int]:
    """Per view: (points, colours) that pass the multi-view check; the views' merged depth
    maps; and the count of depth pixels before the check."""
    def merged(view: _View) -> np.ndarray | None:
        depth = _merge_depths([d for _, d in view.depths], config.depth_tolerance,
                              config.min_pair_support)
        if depth is not None and config.background_window_px > 0:
            depth = _drop_background_coloured(depth, view.rgb, config.background_window_px)
        return depth

    with ThreadPoolExecutor(threads) as pool:
        depth_maps = list(pool.map(merged, views))
    depth_pixels = int(sum(np.isfinite(d).sum() for d in depth_maps if d is not None))
    for view in views:
        view.depths = []  # merged: the pair maps are no longer needed
    neighbours = _fusion_neighbours(np.stack([v.pose for v in views]), config)
    empty = (np.zeros((0, 3)), np.zeros((0, 3), np.uint8))
    with ThreadPoolExecutor(threads) as pool:
        fused = list(pool.map(
            lambda i: _fuse_view(i, depth_maps, views, neighbours[i], k, config)
            if depth_maps[i] is not None else empty, range(len(views))))
    return fused, depth_maps, depth_pixels


def _voxel_down_sample(points: np.ndarray, colors: np.ndarray, voxel: float,
                       quantile: float | None) -> tuple[np.ndarray, np.ndarray]:
    """One point per occupied voxel: the mean position, and the colour of the point at that
    brightness quantile among the voxel's points (None: the mean colour)."""
    cells = np.floor(points / voxel).astype(np.int64)
    cells -= cells.min(axis=0)
    span = cells.max(axis=0) + 1
    keys = (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]
    _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    means = np.stack([np.bincount(inverse, weights=points[:, a]) for a in range(3)], axis=1)
    means /= counts[:, None]
    if quantile is None:
        mean_colours = np.stack([np.bincount(inverse, weights=colors[:, a]) for a in range(3)],
                                axis=1) / counts[:, None]
        return means, np.clip(mean_colours + 0.5, 0, 255).astype(np.uint8)
    order = np.lexsort((colors.max(axis=1), inverse))  # by voxel, then by brightness
    first = np.cumsum(counts) - counts
    return means, colors[order[first + np.floor(quantile * (counts - 1)).astype(np.int64)]]


def _free_space_violations(points: np.ndarray, views: list[_View],
                           depth_maps: list[np.ndarray | None], k: np.ndarray,
                           tolerance: float, window: int, threads: int) -> np.ndarray:
    """(N,) how many views see past each point (their depth there exceeds the point's by
    more than `tolerance`, relative)."""
    homogeneous = np.c_[np.asarray(points, np.float32), np.ones(len(points), np.float32)]
    kernel = np.ones((window, window), np.uint8)

    def count(n: int) -> np.ndarray:
        # The nearest depth within the window: a point is seen past only when the whole
        # window lies beyond it (unknown depths count as near), so a thin stem or an edge
        # that lands a pixel off in another view is not removed.
        depth = cv2.erode(np.nan_to_num(depth_maps[n], nan=0.0), kernel)
        height, width = depth.shape
        rotation, centre = views[n].pose[:3, :3], views[n].pose[:3, 3]
        projection = k @ np.c_[rotation.T, -rotation.T @ centre]  # bed -> (u z, v z, z)
        uvz = _times(homogeneous, projection.T)
        z = uvz[:, 2]
        with np.errstate(invalid="ignore", divide="ignore"):
            u = (uvz[:, 0] / z + 0.5).astype(np.int32)  # z > 0 and u >= 0 checked below
            v = (uvz[:, 1] / z + 0.5).astype(np.int32)
        inside = (z > 1e-3) & (u >= 0) & (u < width) & (v >= 0) & (v < height) & (
            uvz[:, 0] > -0.5 * z) & (uvz[:, 1] > -0.5 * z)
        index = np.flatnonzero(inside)
        seen = depth[v[index], u[index]]
        out = np.zeros(len(z), np.bool_)
        out[index] = seen > z[index] * (1.0 + tolerance)
        return out

    total = np.zeros(len(homogeneous), np.int32)
    with ThreadPoolExecutor(threads) as pool:
        for part in pool.map(count, [n for n, d in enumerate(depth_maps) if d is not None]):
            total += part
    return total


def _fuse_and_filter(views: list[_View], k: np.ndarray, config: DenseConfig, threads: int,
                     scene_centre: np.ndarray | None = None
                     ) -> tuple[Cloud, dict[str, int], dict[str, float]]:
    """The views' depth maps to one cloud: multi-view fusion, the crop to the scene sphere,
    voxel down-sampling, the free-space check, statistical outlier removal. Returns (cloud,
    point counts after each step, seconds per step)."""
    o3d = open3d()
    seconds: dict[str, float] = {}
    last = [time.perf_counter()]

    def step(name: str) -> None:
        now = time.perf_counter()
        seconds[name] = round(now - last[0], 3)
        last[0] = now

    fused, depth_maps, depth_pixels = _fuse_all(views, k, config, threads)
    points = np.concatenate([f[0] for f in fused])
    colors = np.concatenate([f[1] for f in fused])
    del fused
    step("fusion")
    fused_count = len(points)
    if scene_centre is not None and config.scene_radius_m is not None:
        inside = np.einsum("ij,ij->i", points - scene_centre, points - scene_centre) <= (
            config.scene_radius_m ** 2)
        points, colors = points[inside], colors[inside]
    scene_count = len(points)
    if config.voxel_size_m > 0 and scene_count:
        points, colors = _voxel_down_sample(points, colors, config.voxel_size_m,
                                            config.voxel_colour_quantile)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pcd.colors = o3d.utility.Vector3dVector(colors.astype(np.float64) / 255.0)
    del points, colors
    voxel_count = len(pcd.points)
    step("voxel")
    if config.max_free_space_violations is not None and voxel_count:
        violations = _free_space_violations(np.asarray(pcd.points), views, depth_maps, k,
                                            config.free_space_tolerance,
                                            config.free_space_window_px, threads)
        pcd = pcd.select_by_index(
            np.flatnonzero(violations <= config.max_free_space_violations).tolist())
    free_count = len(pcd.points)
    del depth_maps
    step("free_space")
    if config.outlier_neighbours > 0 and free_count > config.outlier_neighbours:
        pcd, _ = pcd.remove_statistical_outlier(config.outlier_neighbours,
                                                config.outlier_std_ratio)
    cloud = Cloud(np.asarray(pcd.points, np.float64).copy(),
                  np.clip(np.asarray(pcd.colors) * 255.0 + 0.5, 0, 255).astype(np.uint8))
    step("outliers")
    counts = {"depth_pixels": depth_pixels, "fused": fused_count, "in_scene": scene_count,
              "voxel": voxel_count,
              "free_space": free_count, "final": len(cloud)}
    return cloud, counts, seconds


def _drop_duplicates(poses: np.ndarray, sharpness: np.ndarray, config: DenseConfig
                     ) -> np.ndarray:
    """Indices of the views kept: of frames taken from the same spot looking the same way,
    the sharpest (`frames.distinct_views`)."""
    return np.flatnonzero(distinct_views(poses[:, :3, 3], poses[:, :3, 2], sharpness,
                                         config.duplicate_distance_m,
                                         config.duplicate_angle_deg))
