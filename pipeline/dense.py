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
This module reads the inputs, picks the views (step 1) and runs the stage; the settings are
`dense_config.py`, step 2 `dense_pairs.py`, step 3 `dense_stereo.py`, steps 4-6
`dense_fusion.py`.

Frames (`frames/*.jpg`, `frames.json`, `camera.json`) are what `flowerpose frames` writes.
Intrinsics follow the project's pixel convention (COLMAP's: pixel centres at +0.5); inside
this module every camera matrix is OpenCV's (centres at integers), at the matching scale.
Poses are camera-to-bed (4, 4) matrices in metres with OpenCV camera axes.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np

from flowerpose.cloudio import Cloud
from flowerpose.errors import InputError
from flowerpose.log import LOG
from flowerpose.memory import require_fits
from flowerpose.pipeline.dense_config import DenseConfig
from flowerpose.pipeline.dense_fusion import fuse_and_filter
from flowerpose.pipeline.dense_pairs import depth_ranges, narrow_to_points, select_pairs
from flowerpose.pipeline.dense_stereo import View, pair_bytes, stereo_all
from flowerpose.pipeline.frames import ChosenFrame, distinct_views, is_rotation, read_frames
from flowerpose.scanio import Intrinsics, read_intrinsics
from flowerpose.stopwatch import Stopwatch

#: Bytes a view's pixel holds through dense reconstruction: its grey and RGB images, its
#: depth map and confidence, and its fused points' coordinates.
VIEW_BYTES_PER_PIXEL = 1 + 3 + 4 + 4 + 12

__all__ = ["DenseConfig", "reconstruct_dense", "select_pairs"]

Poses = Mapping[int | str, np.ndarray] | Sequence[np.ndarray | None] | np.ndarray


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


def reconstruct_dense(frames_dir: str | Path, poses: Poses | None = None,
                      intrinsics: Intrinsics | None = None,
                      config: DenseConfig | None = None,
                      progress: bool = False,
                      scene_points: np.ndarray | None = None) -> tuple[Cloud, dict]:
    """A dense coloured cloud (bed frame, metres) from posed frames, and a report.

    frames_dir holds frames.json (frame "index" and "file" per frame) and the images;
    poses: camera-to-bed (4, 4) matrices, metres, as a mapping from the frame's "index" or
    its "file" (as frames.json names it: "frames/frame_000012.jpg", COLMAP's image name) to
    its pose, frames without one left out; or one pose (or None) per frames.json entry in
    its order; None: frames.json's own poses (the bot's).
    intrinsics: None reads frames_dir/camera.json (the project's pixel convention).
    config: default DenseConfig().
    scene_points: (M, 3) points of the scene, bed frame, metres (the sparse model's): each
    view searches only the depths at which it sees them (`DenseConfig.scene_points_stretch`).
    The report: views, pairs (candidates, used, skipped with reasons), points before and
    after fusion and filtering, seconds per step, and the config.
    """
    config = config or DenseConfig()
    watch = Stopwatch()

    def say(message: str) -> None:
        if progress:
            LOG.info(f"dense: {message} ({watch.elapsed():.1f} s)")

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
    pair_total, pair_array = pair_bytes(size, config)
    require_fits(len(posed) * size[0] * size[1] * VIEW_BYTES_PER_PIXEL + threads * pair_total,
                 "dense.image_scale (or dense.max_disparities, dense.sgbm_mode, dense.threads)",
                 f"dense stereo of {len(posed)} frames at {size[0]}x{size[1]}",
                 opencv_array=pair_array)

    with ThreadPoolExecutor(threads) as pool:
        loaded = list(pool.map(
            lambda n: _load_image(frames_dir / frames[n].file, size,
                                  (intrinsics.width, intrinsics.height)), posed))
    watch.lap("load")
    say(f"loaded {len(posed)} frames at {size[0]}x{size[1]}")

    pose_array = np.stack([frame_poses[n] for n in posed])
    keep = _drop_duplicates(pose_array, np.array([s for *_, s in loaded]), config)
    pose_array = pose_array[keep]
    loaded = [loaded[n] for n in keep]
    centres, axes = pose_array[:, :3, 3], pose_array[:, :3, 2]
    ranges, scene_centre = depth_ranges(centres, axes, config)
    pairs, counts = select_pairs(pose_array, config, expected_depth=ranges.mean(axis=1))
    if scene_points is not None and config.scene_points_stretch is not None:
        ranges = narrow_to_points(ranges, pose_array, k, size, scene_points,
                                  config.scene_points_stretch)
    views = [View(grey, rgb, pose, (float(r[0]), float(r[1])))
             for (grey, rgb, _), pose, r in zip(loaded, pose_array, ranges, strict=True)]
    del loaded
    watch.lap("pairs")
    if not pairs:
        raise InputError(frames_dir, f"no usable stereo pairs among {len(views)} views "
                         f"({counts['candidates']} neighbouring pairs, {counts['degenerate']} "
                         f"degenerate: baselines under {config.baseline_m[0]} m or along the "
                         "view); the frames need camera centres apart across the view")
    say(f"{len(pairs)} pairs from {len(views)} views")

    skipped, matched = stereo_all(views, pairs, k, config, threads, progress)
    skipped["degenerate_geometry"] = counts["degenerate"]
    watch.lap("stereo")
    used = len(matched)
    if used == 0:
        raise InputError(frames_dir, f"all {len(pairs)} stereo pairs were degenerate")
    cloud, point_counts, fusion_seconds = fuse_and_filter(views, k, config, threads,
                                                           scene_centre)
    if len(cloud) == 0:
        raise InputError(frames_dir, f"no point passed fusion and filtering (points after "
                         f"each step: {point_counts}); the frames overlap too little or "
                         "their poses are wrong")
    seconds = {**watch.report(digits=3, total=None), **fusion_seconds,
               "total": round(watch.elapsed(), 3)}
    say(f"{len(cloud)} points")
    report = {
        "frames": len(frames), "posed": len(posed), "views": len(views),
        "duplicate_views": len(posed) - len(views),
        "image_size": list(size),
        "depth_search_m": {"near_median": round(float(np.median(ranges[:, 0])), 4),
                           "far_median": round(float(np.median(ranges[:, 1])), 4)},
        "pairs": {"candidates": counts["candidates"], "selected": len(pairs), "used": used,
                  "skipped": skipped,
                  "matched_fraction_mean": round(float(np.mean(matched)), 4)},
        "points": point_counts,
        "seconds": seconds, "threads": threads, "config": asdict(config)}
    return cloud, report



def _drop_duplicates(poses: np.ndarray, sharpness: np.ndarray, config: DenseConfig
                     ) -> np.ndarray:
    """Indices of the views kept: of frames taken from the same spot looking the same way,
    the sharpest (`frames.distinct_views`)."""
    return np.flatnonzero(distinct_views(poses[:, :3, 3], poses[:, :3, 2], sharpness,
                                         config.duplicate_distance_m,
                                         config.duplicate_angle_deg))
