"""Dense reconstruction on a synthetic scene rendered with homographies (no simulator).

The scene: a textured ground plane (z = 0, reddish) and a textured plate floating above it
(z = PLATE_Z, greenish), seen by cameras on a ring above, all aimed at the origin, some
rolled upside down (as the scan head's yaw flip does), so the pairs' baselines point every
way in their images. A plate floating above the ground needs no walls, so painting the
ground and then the plate renders every view exactly.
"""

from __future__ import annotations

import json
from dataclasses import replace

import cv2
import numpy as np
import pytest

from flowerpose.errors import InputError
from flowerpose.jsonio import write_json
from flowerpose.pipeline.dense import (
    DenseConfig,
    reconstruct_dense,
    select_pairs,
)
from flowerpose.pipeline.dense_pairs import narrow_to_points
from flowerpose.pipeline.dense_stereo import _match_both_ways, _matcher
from flowerpose.pipeline.frames import read_frames
from flowerpose.scanio import FRAME_PATTERN, Intrinsics

WIDTH, HEIGHT, FOCAL = 320, 240, 300.0
INTRINSICS = Intrinsics(WIDTH, HEIGHT, FOCAL, FOCAL, WIDTH / 2, HEIGHT / 2)
PLATE_Z = 0.05
PLATE_HALF = 0.06
GROUND_HALF = 0.3
TEXTURE_M = 0.0005  # metres per texture pixel


def _texture(size: int, tint: tuple[float, float, float], seed: int) -> np.ndarray:
    """RGB uint8 texture: multi-scale noise (matchable at any scale) in one tint."""
    rng = np.random.default_rng(seed)
    grey = np.zeros((size, size), np.float32)
    for cells, weight in ((8, 0.5), (32, 0.3), (128, 0.2)):
        noise = rng.random((cells, cells)).astype(np.float32)
        grey += weight * cv2.resize(noise, (size, size), interpolation=cv2.INTER_CUBIC)
    grey = cv2.GaussianBlur(grey, (0, 0), 1.0)
    grey = (grey - grey.min()) / (np.ptp(grey) + 1e-9)
    shade = 0.35 + 0.65 * grey
    return np.clip(shade[..., None] * np.array(tint) * 255, 0, 255).astype(np.uint8)


GROUND = _texture(int(2 * GROUND_HALF / TEXTURE_M), (0.9, 0.35, 0.25), 1)
PLATE = _texture(int(2 * PLATE_HALF / TEXTURE_M), (0.3, 0.85, 0.35), 2)


def _look_at(position, target, roll_flip=False) -> np.ndarray:
    """Camera-to-bed pose (4, 4), OpenCV axes, looking from position at target."""
    position, target = np.asarray(position, float), np.asarray(target, float)
    z = target - position
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    if np.linalg.norm(x) < 1e-6:
        x = np.array([1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    if roll_flip:
        x, y = -x, -y
    pose = np.eye(4)
    pose[:3, :3] = np.c_[x, y, z]
    pose[:3, 3] = position
    return pose


def _render(pose: np.ndarray) -> np.ndarray:
    """RGB image of the scene from a camera-to-bed pose (exact planar homographies)."""
    k = INTRINSICS.matrix.copy()
    k[0, 2] -= 0.5  # OpenCV's pixel centres (the project's convention is COLMAP's)
    k[1, 2] -= 0.5
    rotation, centre = pose[:3, :3], pose[:3, 3]
    image = np.zeros((HEIGHT, WIDTH, 3), np.uint8)
    for texture, half, height in ((GROUND, GROUND_HALF, 0.0), (PLATE, PLATE_HALF, PLATE_Z)):
        plane = np.c_[np.eye(3)[:, 0], np.eye(3)[:, 1], [-centre[0], -centre[1],
                                                           height - centre[2]]]
        to_texture = np.array([[TEXTURE_M, 0, -half + TEXTURE_M / 2],
                               [0, TEXTURE_M, -half + TEXTURE_M / 2], [0, 0, 1.0]])
        homography = k @ rotation.T @ plane @ to_texture
        warped = cv2.warpPerspective(texture, homography, (WIDTH, HEIGHT), flags=cv2.INTER_LINEAR)
        mask = cv2.warpPerspective(np.full(texture.shape[:2], 255, np.uint8), homography,
                                   (WIDTH, HEIGHT), flags=cv2.INTER_NEAREST)
        image[mask > 0] = warped[mask > 0]
    return image


def _ring_poses(count=8, radius=0.15, height=0.45, flip_every=3):
    poses = []
    for n in range(count):
        angle = 2 * np.pi * n / count
        position = [radius * np.cos(angle), radius * np.sin(angle), height]
        poses.append(_look_at(position, [0, 0, 0], roll_flip=(n % flip_every == 1)))
    return poses


def _write_frames(path, poses, images=None):
    (path / "frames").mkdir(parents=True)
    entries = []
    for n, pose in enumerate(poses):
        image = _render(pose) if images is None else images[n]
        name = FRAME_PATTERN.format(n)
        cv2.imwrite(str(path / "frames" / name), cv2.cvtColor(image, cv2.COLOR_RGB2BGR),
                    [cv2.IMWRITE_JPEG_QUALITY, 95])
        entries.append({"index": n, "file": f"frames/{name}", "t": float(n),
                        "pose": {"position": pose[:3, 3].tolist(),
                                 "rotation": pose[:3, :3].tolist()}})
    write_json(path / "frames.json", {"frames": entries})
    write_json(path / "camera.json", INTRINSICS.to_json())
    return path


#: Small images, so match at full size; a 2 mm voxel keeps the test quick.
CONFIG = DenseConfig(image_scale=1.0, voxel_size_m=0.002)


def _surface_distance(points: np.ndarray) -> np.ndarray:
    """Distance of each point to the true surface (ground or plate)."""
    outside = np.maximum(np.abs(points[:, :2]) - PLATE_HALF, 0.0)
    to_plate = np.hypot(np.linalg.norm(outside, axis=1), points[:, 2] - PLATE_Z)
    return np.minimum(np.abs(points[:, 2]), to_plate)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    path = tmp_path_factory.mktemp("dense_scene")
    poses = _ring_poses()
    # A ninth frame moved straight along the first camera's optical axis: the pair it makes
    # with that camera has its epipole in the middle of the image (degenerate).
    forward = poses[0].copy()
    forward[:3, 3] += 0.05 * forward[:3, 2]
    return _write_frames(path, poses + [forward])


@pytest.fixture(scope="module")
def result(scene):
    return reconstruct_dense(scene, config=CONFIG)


@pytest.mark.slow
def test_points_lie_on_the_true_surfaces(result):
    cloud, report = result
    assert len(cloud) > 5000, report["points"]
    distance = _surface_distance(cloud.points)
    assert np.median(distance) < 0.0005
    assert np.percentile(distance, 95) < 0.002
    on_plate = (np.abs(cloud.points[:, 2] - PLATE_Z) < 0.003) & np.all(
        np.abs(cloud.points[:, :2]) < PLATE_HALF - 0.005, axis=1)
    on_ground = (np.abs(cloud.points[:, 2]) < 0.003) & np.any(
        np.abs(cloud.points[:, :2]) > PLATE_HALF + 0.01, axis=1)
    assert on_plate.sum() > 500 and on_ground.sum() > 2000
    # The plate covers most of its square.
    cells = np.unique(np.floor(cloud.points[on_plate, :2] / 0.01), axis=0)
    assert len(cells) >= 0.8 * (2 * PLATE_HALF / 0.01 - 1) ** 2


def test_colours_come_from_the_right_surface(result):
    cloud, _ = result
    colours = cloud.colors.astype(float)
    on_plate = (np.abs(cloud.points[:, 2] - PLATE_Z) < 0.003) & np.all(
        np.abs(cloud.points[:, :2]) < PLATE_HALF - 0.005, axis=1)
    on_ground = (np.abs(cloud.points[:, 2]) < 0.003) & np.any(
        np.abs(cloud.points[:, :2]) > PLATE_HALF + 0.01, axis=1)
    assert np.mean(colours[on_plate, 1] > colours[on_plate, 0]) > 0.95  # green plate
    assert np.mean(colours[on_ground, 0] > colours[on_ground, 1]) > 0.95  # red ground
    assert cloud.colors.dtype == np.uint8 and cloud.points.dtype == np.float64


def test_depth_search_spans_the_scene_sphere(scene):
    """With a tight scene sphere the plate lies near its front and the ground near its
    back: both are found (the disparity search covers the whole depth range), and nothing
    outside the sphere is kept."""
    config = replace(CONFIG, scene_radius_m=0.12)
    cloud, _ = reconstruct_dense(scene, config=config)
    assert np.linalg.norm(cloud.points, axis=1).max() <= 0.12 + 1e-9  # centre: the origin
    on_plate = (np.abs(cloud.points[:, 2] - PLATE_Z) < 0.003) & np.all(
        np.abs(cloud.points[:, :2]) < PLATE_HALF - 0.005, axis=1)
    on_ground = np.abs(cloud.points[:, 2]) < 0.003
    assert on_plate.sum() > 500 and on_ground.sum() > 500
    assert np.percentile(_surface_distance(cloud.points), 95) < 0.002


def _surface_samples(count: int, seed: int = 0) -> np.ndarray:
    """Points on the ground (inside the ring's view) and on the plate, bed frame."""
    rng = np.random.default_rng(seed)
    ground = np.c_[rng.uniform(-0.15, 0.15, (count, 2)), np.zeros(count)]
    plate = np.c_[rng.uniform(-PLATE_HALF, PLATE_HALF, (count, 2)), np.full(count, PLATE_Z)]
    return np.r_[ground, plate]


def test_scene_points_narrow_the_depth_search():
    """A view searches the 1st-99th percentile of the depths at which it sees the points,
    widened by the stretch, within its range; points behind it or outside its image do not
    count, and a view that sees too few keeps its range."""
    k = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])
    looking_up = np.eye(4)  # OpenCV axes: the optical axis is the bed's +z
    rng = np.random.default_rng(1)
    seen = np.c_[rng.uniform(-0.05, 0.05, (400, 2)), rng.uniform(0.4, 0.6, 400)]
    behind = seen * [1, 1, -1]
    beside = seen + [2.0, 0, 0]  # far outside the image
    ranges = np.array([[0.08, 1.5], [0.08, 0.5]])
    narrowed = narrow_to_points(ranges, np.stack([looking_up, looking_up]), k, (320, 240),
                                np.r_[seen, behind, beside], stretch=0.25)
    low, high = np.percentile(seen[:, 2], [1, 99])
    assert narrowed[0] == pytest.approx([0.75 * low, 1.25 * high])
    assert narrowed[1] == pytest.approx([0.75 * low, 0.5])  # kept within the range given
    few = narrow_to_points(ranges, np.stack([looking_up, looking_up]), k, (320, 240),
                           seen[:5], stretch=0.25)
    assert np.array_equal(few, ranges)


def test_scene_points_keep_every_surface(scene, result):
    """Given the scene's points, the search narrows and the cloud still lies on the true
    surfaces, the plate and the ground both found."""
    cloud, report = reconstruct_dense(scene, config=CONFIG, scene_points=_surface_samples(500))
    wide = result[1]["depth_search_m"]
    narrow = report["depth_search_m"]
    assert narrow["near_median"] > wide["near_median"]
    assert narrow["far_median"] < wide["far_median"]
    assert np.percentile(_surface_distance(cloud.points), 95) < 0.002
    on_plate = np.abs(cloud.points[:, 2] - PLATE_Z) < 0.003
    on_ground = np.abs(cloud.points[:, 2]) < 0.003
    assert on_plate.sum() > 500 and on_ground.sum() > 2000


def test_each_matching_pass_sees_only_its_columns():
    """Cropping each SGM pass to the columns it can use gives the disparities the full
    padded grid gives, away from the crop's edge."""
    rng = np.random.default_rng(2)
    texture = cv2.GaussianBlur(rng.integers(1, 255, (120, 400)).astype(np.uint8), (3, 3), 0)
    num, shift, pad = 32, 12, 48
    left = np.zeros((120, 400 + 2 * pad), np.uint8)
    right = np.zeros_like(left)
    left[:, pad + num:pad + 400] = texture[:, num:]
    right[:, pad + num - shift:pad + 400 - shift] = texture[:, num:]
    matcher = _matcher(DenseConfig(), num)
    raw_l, raw_r = _match_both_ways(left, right, matcher, pad + 400, pad + num - shift)
    full_l = matcher.compute(left, right)
    full_r = cv2.flip(matcher.compute(cv2.flip(right, 1), cv2.flip(left, 1)), 1)
    inner = np.s_[10:-10, pad + 2 * num:pad + 400 - num]
    assert np.median(raw_l[inner]) == 16 * shift
    assert np.mean(raw_l[inner] == full_l[inner]) > 0.99
    inner_r = np.s_[10:-10, pad + 2 * num - shift:pad + 400 - num - shift]
    assert np.median(raw_r[inner_r]) == 16 * shift
    assert np.mean(raw_r[inner_r] == full_r[inner_r]) > 0.99


def test_report(result):
    _, report = result
    pairs = report["pairs"]
    assert pairs["used"] >= 8 and pairs["used"] == pairs["selected"]
    assert pairs["skipped"]["degenerate_geometry"] >= 1  # the forward-moving pair
    points = report["points"]
    assert points["fused"] >= points["in_scene"] >= points["voxel"] >= points["final"] > 0
    assert report["depth_search_m"]["near_median"] < report["depth_search_m"]["far_median"]
    assert set(report["seconds"]) >= {"load", "pairs", "stereo", "fusion", "voxel",
                                      "free_space", "outliers", "total"}
    json.dumps(report)  # a report must be writable as JSON


def test_forward_motion_is_degenerate_not_paired():
    pose = _look_at([0.0, 0.0, 0.45], [0.0, 0.01, 0.0])
    forward = pose.copy()
    forward[:3, 3] += 0.06 * forward[:3, 2]
    sideways = pose.copy()
    sideways[:3, 3] += 0.06 * forward[:3, 0]
    pairs, counts = select_pairs(np.stack([pose, forward, sideways]), CONFIG)
    assert pairs == [(0, 2)] or set(pairs) == {(0, 2), (1, 2)}
    assert (0, 1) not in pairs
    assert counts["degenerate"] >= 1


def test_degenerate_frames_only_raise_a_clear_error(tmp_path):
    pose = _look_at([0.0, 0.0, 0.45], [0.0, 0.01, 0.0])
    forward = pose.copy()
    forward[:3, 3] += 0.06 * forward[:3, 2]
    same = pose.copy()  # no baseline at all
    path = _write_frames(tmp_path, [pose, forward, same])
    with pytest.raises(InputError, match="no usable stereo pairs"):
        reconstruct_dense(path, config=CONFIG)


def test_too_few_frames(tmp_path):
    path = _write_frames(tmp_path, _ring_poses(count=3))
    with pytest.raises(InputError, match="at least 2 frames with a pose"):
        reconstruct_dense(path, poses={0: read_frames(path)[0].pose}, config=CONFIG)
    with pytest.raises(InputError, match="poses"):
        reconstruct_dense(path, poses=[np.eye(4)], config=CONFIG)  # 1 pose for 3 frames


def test_bad_inputs(tmp_path):
    with pytest.raises(InputError, match="not found"):
        reconstruct_dense(tmp_path / "missing", config=CONFIG)
    path = _write_frames(tmp_path / "scan", _ring_poses(count=3))
    bad = [np.eye(4)] * 3
    bad[1] = np.diag([1.0, 1.0, -1.0, 1.0])  # a reflection, not a rotation
    with pytest.raises(InputError, match="not a rotation"):
        reconstruct_dense(path, poses=bad, config=CONFIG)
    with pytest.raises(InputError, match="block_size"):
        replace(CONFIG, block_size=4)
    small = Intrinsics(160, 120, 150, 150, 80, 60)
    with pytest.raises(InputError, match="intrinsics are for 160x120"):
        reconstruct_dense(path, intrinsics=small, config=CONFIG)


def test_stereo_sizes_are_checked_before_any_image_is_loaded(scene, monkeypatch):
    from flowerpose import memory

    # SGM's whole cost volume ("hh") at 4096 disparities: an array OpenCV cannot index
    huge = DenseConfig(image_scale=1.0, sgbm_mode="hh", max_disparities=4096)
    with pytest.raises(InputError, match=r"dense.image_scale.*more than OpenCV takes"):
        reconstruct_dense(scene, config=huge)
    # the default settings on a machine with 1 MB free: refused naming the settings
    monkeypatch.setattr(memory, "available_bytes", lambda: 1_000_000)
    with pytest.raises(InputError, match=r"needs .* GB, more than this machine has free"):
        reconstruct_dense(scene, config=CONFIG)
