import csv

import cv2
import numpy as np
import pytest

from flowerpose.errors import InputError
from flowerpose.jsonio import write_json
from flowerpose.pipeline.rgbd import DEPTH_PATTERN, FusionConfig, fuse_rgbd_scan, voxel_fuse
from flowerpose.scanio import FRAME_PATTERN, TRAJECTORY_COLUMNS, Intrinsics, trajectory_row

K = Intrinsics(80, 60, 70.0, 70.0, 40.0, 30.0)
PLANE_Z = 0.2


def _look_down(position):
    rotation = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])  # camera z looks down -z
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = rotation, position
    return pose


def _rgbd_scan(folder, views=12, flying=200, seed=0):
    """A flat textured sheet at z = PLANE_Z seen from above; every view also has `flying`
    random depths (flying pixels) at its own random pixels."""
    rng = np.random.default_rng(seed)
    (folder / "frames").mkdir(parents=True)
    (folder / "depth").mkdir()
    rows = []
    for k in range(views):
        position = np.array([1.5 + 0.05 * np.cos(k), 0.75 + 0.05 * np.sin(k), 0.5])
        pose = _look_down(position)
        depth = np.full((K.height, K.width), position[2] - PLANE_Z)
        pixels = rng.integers(0, K.width * K.height, flying)
        depth.flat[pixels] = rng.uniform(0.1, 0.28, flying)
        colour = np.full((K.height, K.width, 3), 200, np.uint8)
        cv2.imwrite(str(folder / "frames" / FRAME_PATTERN.format(k)), colour)
        cv2.imwrite(str(folder / "depth" / DEPTH_PATTERN.format(k)),
                    np.round(depth / 0.001).astype(np.uint16))
        rows.append(trajectory_row(k, k, position, 0.0, 0.0, position, pose[:3, :3]))
    with open(folder / "trajectory.csv", "w", newline="") as handle:
        csv.writer(handle).writerows([TRAJECTORY_COLUMNS, *rows])
    write_json(folder / "camera.json", {**K.to_json(), "depth_unit_m": 0.001})
    write_json(folder / "scan.json", {"plan": {"plant_center": [1.5, 0.75]}})
    return folder


def test_fused_cloud_lies_on_the_surface_and_flying_pixels_are_gone(tmp_path):
    cloud, report = fuse_rgbd_scan(_rgbd_scan(tmp_path / "scan"), FusionConfig(voxel_m=0.002))
    assert report["frames"] == 12 and len(cloud) > 500
    assert np.abs(cloud.points[:, 2] - PLANE_Z).max() < 0.0015
    assert (cloud.colors == 200).all()


def test_without_the_view_test_flying_pixels_stay(tmp_path):
    scan = _rgbd_scan(tmp_path / "scan")
    cloud, _ = fuse_rgbd_scan(scan, FusionConfig(voxel_m=0.002, min_views=1,
                                                 outlier_neighbours=0))
    assert np.sum(np.abs(cloud.points[:, 2] - PLANE_Z) > 0.01) > 100


def test_voxel_fuse_averages_and_counts_distinct_views():
    points = np.array([[0.0001, 0, 0], [0.0003, 0, 0], [0.0002, 0, 0], [0.5, 0.5, 0.5]])
    colours = np.array([[0, 0, 0], [100, 100, 100], [200, 200, 200], [9, 9, 9]])
    fused, fused_colours = voxel_fuse(points, colours, np.array([0, 1, 1, 0]), 0.001, 2)
    np.testing.assert_allclose(fused, [[0.0002, 0, 0]])
    np.testing.assert_allclose(fused_colours, [[100, 100, 100]])


def test_a_scan_without_depth_is_refused(tmp_path):
    scan = _rgbd_scan(tmp_path / "scan", views=2)
    for path in (scan / "depth").glob("*.png"):
        path.unlink()
    with pytest.raises(InputError, match="not an RGB-D scan"):
        fuse_rgbd_scan(scan)


def test_frames_too_coarse_for_the_voxel_are_refused_naming_the_settings(tmp_path):
    # Three views: no voxel can gather the six that fusion.min_views asks for.
    scan = _rgbd_scan(tmp_path / "scan", views=3)
    with pytest.raises(InputError, match="fusion.voxel_m or lower fusion.min_views"):
        fuse_rgbd_scan(scan, FusionConfig(voxel_m=0.002))
