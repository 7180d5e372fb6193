"""Dense stereo, step 3: one pair's calibrated rectification, semi-global matching both
ways, the texture mask and the left-right check, back to depth maps on the two views' grids;
and every pair on a thread pool. Camera matrices are OpenCV's (pixel centres at integers)."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import cv2
import numpy as np

from flowerpose.log import Tally
from flowerpose.pipeline.dense_config import SGBM_MODES, DenseConfig


@dataclass
class View:
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
    # The rotated ray of pixel (u, v) is linear in its column's x and its row's y: built
    # from a row and a column, never as an (H, W, 3) array: four times faster, and the
    # same sums in the same order as the (H, W, 3) product gave, so the same depths.
    x = (np.arange(width, dtype=np.float32) - k[0, 2]) / k[0, 0]
    y = (np.arange(height, dtype=np.float32) - k[1, 2]) / k[1, 1]
    m = rect.T
    ray_x, ray_y, z = ((m[2, j] + x[None, :] * m[0, j]) + y[:, None] * m[1, j]
                       for j in range(3))
    with np.errstate(invalid="ignore", divide="ignore"):
        iu = np.rint(focal * ray_x / z + cx)
        iv = np.rint(focal * ray_y / z + cy)
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
        speckleRange=config.speckle_range, mode=SGBM_MODES[config.sgbm_mode])


#: Widest rectified canvas of a pair, in image widths: a pair that needs more is skipped
#: as degenerate (`_stereo_pair`).
MAX_CANVAS_WIDTHS = 4


def pair_bytes(size: tuple[int, int], config: DenseConfig) -> tuple[int, int]:
    """(bytes one pair's matching may hold at most, its largest single OpenCV array) for
    images of `size` (width, height) pixels: the rectified images and disparity maps of a
    canvas up to `MAX_CANVAS_WIDTHS` wide, and SGM's cost buffers: the whole cost volume
    (int16, twice) in the "hh" modes, a few rows of it in the others."""
    width, height = size
    canvas = MAX_CANVAS_WIDTHS * width * height
    disparities = config.max_disparities
    if config.sgbm_mode.startswith("hh"):
        volume = 2 * canvas * disparities
        return 2 * volume + 16 * canvas, volume
    rows = 2 * MAX_CANVAS_WIDTHS * width * disparities * 16
    return rows + 16 * canvas, max(rows, 2 * canvas)


def _stereo_pair(view_i: View, view_j: View, k: np.ndarray, config: DenseConfig
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
    if out_w > MAX_CANVAS_WIDTHS * width:
        return "degenerate"
    left = cv2.remap(view_i.grey, *_rectify_maps(k, rect_i, focal, cx_i, cy, out_size),
                     cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    right = cv2.remap(view_j.grey, *_rectify_maps(k, rect_j, focal, cx_j, cy, out_size),
                      cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    raw_l, raw_r = _match_both_ways(left, right, _matcher(config, num),
                                    int(np.ceil(cx_i + umax_i)) + 1,
                                    max(0, int(np.floor(cx_j + umin_j))))
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


def _match_both_ways(left: np.ndarray, right: np.ndarray, matcher, left_end: int,
                     right_start: int) -> tuple[np.ndarray, np.ndarray]:
    """SGBM's raw disparities (int16, 16ths of a pixel, -16 unmatched) of the rectified
    left image on the right one, and of the right on the left (on mirrored images), on the
    full rectified grid.

    Each pass sees only the columns it can use: the left-on-right pass those before the
    left image's content ends (`left_end`), the right-on-left pass those from where the
    right image's content starts (`right_start`). The grid pads each image with the other
    pass's search room; SGM's time grows with the width, so this saves about a fifth of it.
    """
    unmatched = np.int16(-16)  # (minDisparity - 1) * 16
    raw_l = np.full(left.shape, unmatched, np.int16)
    raw_r = np.full(left.shape, unmatched, np.int16)
    raw_l[:, :left_end] = matcher.compute(np.ascontiguousarray(left[:, :left_end]),
                                          np.ascontiguousarray(right[:, :left_end]))
    raw_r[:, right_start:] = cv2.flip(matcher.compute(
        cv2.flip(right[:, right_start:], 1), cv2.flip(left[:, right_start:], 1)), 1)
    return raw_l, raw_r


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



def stereo_all(views: list[View], pairs: list[tuple[int, int]], k: np.ndarray,
               config: DenseConfig, threads: int, progress: bool = False
               ) -> tuple[dict[str, int], list[float]]:
    """Every pair's two depth maps appended to its views' `depths` (with the partner's
    index); returns (skipped pairs by reason, matched share per used pair). `progress`:
    the pairs counted, with the time left."""
    skipped: dict[str, int] = {}
    matched: list[float] = []
    with ThreadPoolExecutor(threads) as pool, \
            Tally(len(pairs) if progress else 0, "stereo") as tally:
        results = pool.map(lambda p: _stereo_pair(views[p[0]], views[p[1]], k, config), pairs)
        for done, ((i, j), result) in enumerate(zip(pairs, results, strict=True), 1):
            tally.advance(1, f"dense: stereo {done}/{len(pairs)} pairs"
                          if progress and done % 50 == 0 else None)
            if isinstance(result, str):
                reason = f"{result}_rectification"
                skipped[reason] = skipped.get(reason, 0) + 1
                continue
            views[i].depths.append((j, result[0]))
            views[j].depths.append((i, result[1]))
            matched.append(result[2])
    return skipped, matched
