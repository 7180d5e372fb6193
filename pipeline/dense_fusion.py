"""Dense stereo, steps 4-6: each view's depth maps merged, the multi-view consistency
check that makes points, and the cloud's crop, voxels, free-space and outlier filters.
Points are metres, bed frame."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np

from flowerpose.cloudio import Cloud
from flowerpose.log import open3d
from flowerpose.pipeline.dense_config import DenseConfig
from flowerpose.pipeline.dense_pairs import angle_deg, apply_matrix
from flowerpose.pipeline.dense_stereo import View
from flowerpose.stopwatch import Stopwatch


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
    angle = angle_deg(axes[:, None], axes[None, :])
    distance = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    allowed = (angle <= config.fusion_max_angle_deg) & (distance <= config.fusion_max_distance_m)
    np.fill_diagonal(allowed, False)
    out = []
    for i in range(len(poses)):
        candidates = np.flatnonzero(allowed[i])
        out.append(candidates[np.argsort(angle[i, candidates], kind="stable")]
                   [:config.fusion_neighbours])
    return out


def _fuse_view(i: int, depth_maps: list[np.ndarray | None], views: list[View],
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
    points = apply_matrix(rays * z[:, None], pose[:3, :3].T) + pose[:3, 3]
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
        local = apply_matrix(points - centre, rotation)
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



def _fuse_all(views: list[View], k: np.ndarray, config: DenseConfig, threads: int
              ) -> tuple[list[tuple[np.ndarray, np.ndarray]], list[np.ndarray | None], int]:
    """Per view: (points, colours) that pass the multi-view check; the views' merged depth
    maps; and the count of depth pixels before the check."""
    def merged(view: View) -> np.ndarray | None:
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


def _free_space_violations(points: np.ndarray, views: list[View],
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
        uvz = apply_matrix(homogeneous, projection.T)
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


def fuse_and_filter(views: list[View], k: np.ndarray, config: DenseConfig, threads: int,
                     scene_centre: np.ndarray | None = None
                     ) -> tuple[Cloud, dict[str, int], dict[str, float]]:
    """The views' depth maps to one cloud: multi-view fusion, the crop to the scene sphere,
    voxel down-sampling, the free-space check, statistical outlier removal. Returns (cloud,
    point counts after each step, seconds per step)."""
    o3d = open3d()
    watch = Stopwatch()
    fused, depth_maps, depth_pixels = _fuse_all(views, k, config, threads)
    points = np.concatenate([f[0] for f in fused])
    colors = np.concatenate([f[1] for f in fused])
    del fused
    watch.lap("fusion")
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
    watch.lap("voxel")
    if config.max_free_space_violations is not None and voxel_count:
        violations = _free_space_violations(np.asarray(pcd.points), views, depth_maps, k,
                                            config.free_space_tolerance,
                                            config.free_space_window_px, threads)
        pcd = pcd.select_by_index(
            np.flatnonzero(violations <= config.max_free_space_violations).tolist())
    free_count = len(pcd.points)
    del depth_maps
    watch.lap("free_space")
    if config.outlier_neighbours > 0 and free_count > config.outlier_neighbours:
        pcd, _ = pcd.remove_statistical_outlier(config.outlier_neighbours,
                                                config.outlier_std_ratio)
    cloud = Cloud(np.asarray(pcd.points, np.float64).copy(),
                  np.clip(np.asarray(pcd.colors) * 255.0 + 0.5, 0, 255).astype(np.uint8))
    watch.lap("outliers")
    counts = {"depth_pixels": depth_pixels, "fused": fused_count, "in_scene": scene_count,
              "voxel": voxel_count,
              "free_space": free_count, "final": len(cloud)}
    return cloud, counts, watch.report(digits=3, total=None)
