"""Sparse reconstruction: a rendered scene of known geometry and poses comes back, in the bed
frame; bad input is refused clearly; the pycolmap-before-cv2 crash stays caught."""

import cv2  # noqa: I001  (before pycolmap, see flowerpose.pipeline.sfm)

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import map_coordinates

from flowerpose.errors import InputError
from flowerpose.pipeline.frames import read_frames
from flowerpose.pipeline.sfm import distinct_poses, reconstruct_sparse
from flowerpose.pipeline.sfm_config import SfmConfig
from flowerpose.pipeline.sfm_matching import epipolar_matches, pairs_from_poses, sequential_pairs

# A textured bed patch with three blocks on it: (min xyz, max xyz), metres, bed frame.
BOXES = np.array([
    [[-0.25, -0.25, -0.02], [0.25, 0.25, 0.0]],
    [[-0.06, -0.04, 0.0], [0.06, 0.04, 0.10]],
    [[0.08, 0.02, 0.0], [0.14, 0.10, 0.05]],
    [[-0.15, -0.16, 0.0], [-0.09, -0.08, 0.07]],
])
WIDTH, HEIGHT, FOCAL = 480, 360, 380.0
K = np.array([[FOCAL, 0, WIDTH / 2], [0, FOCAL, HEIGHT / 2], [0, 0, 1]])
VIEWS = 12


def look_at(position: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Camera-to-bed rotation (OpenCV axes) of a camera at position looking at target."""
    z = (target - position) / np.linalg.norm(target - position)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=1)


def ring_poses() -> tuple[np.ndarray, np.ndarray]:
    """(VIEWS, 3) centres and (VIEWS, 3, 3) rotations round the blocks, two heights."""
    angles = 2 * np.pi * np.arange(VIEWS) / VIEWS
    positions = np.stack([0.32 * np.cos(angles), 0.32 * np.sin(angles),
                          0.18 + 0.08 * (np.arange(VIEWS) % 2)], axis=1)
    rotations = np.array([look_at(p, np.array([0.0, 0.0, 0.03])) for p in positions])
    return positions, rotations


def render(position: np.ndarray, rotation: np.ndarray, texture: list[np.ndarray]
           ) -> np.ndarray:
    """BGR image of the boxes (ray casting, the nearest box face wins, grey sky)."""
    u, v = np.meshgrid(np.arange(WIDTH) + 0.5, np.arange(HEIGHT) + 0.5)
    rays = np.stack([(u - K[0, 2]) / FOCAL, (v - K[1, 2]) / FOCAL, np.ones_like(u)], -1)
    directions = rays.reshape(-1, 3) @ rotation.T
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (BOXES[:, None, 0] - position) / directions
        t2 = (BOXES[:, None, 1] - position) / directions
    near = np.nanmax(np.minimum(t1, t2), axis=2)
    far = np.nanmin(np.maximum(t1, t2), axis=2)
    t = np.where((far >= near) & (far > 0), near, np.inf).min(axis=0)
    image = np.full((len(directions), 3), 190.0)
    hit = np.isfinite(t)
    grid = ((position + directions[hit] * t[hit, None]) - BOXES[0, 0] + 0.01) / 0.003
    fine = map_coordinates(texture[0], grid.T, order=1, mode="nearest")
    coarse = map_coordinates(texture[1], grid.T / 4, order=1, mode="nearest")
    image[hit] = 40 + 170 * np.stack([fine, 0.5 * fine + 0.5 * coarse, coarse], axis=1)
    return image.reshape(HEIGHT, WIDTH, 3).astype(np.uint8)


def render_scene(folder: Path) -> Path:
    """folder/frames/*.jpg: the boxes from ring_poses()."""
    rng = np.random.default_rng(0)
    shape = (190, 190, 50)
    texture = [rng.random(shape, np.float32),
               rng.random(tuple(s // 4 + 2 for s in shape), np.float32)]
    (folder / "frames").mkdir(parents=True)
    for k, (position, rotation) in enumerate(zip(*ring_poses(), strict=True)):
        cv2.imwrite(str(folder / f"frames/frame_{k:06d}.jpg"),
                    render(position, rotation, texture), [cv2.IMWRITE_JPEG_QUALITY, 95])
    return folder / "frames"


def frames_folder(folder: Path, images: Path, positions: np.ndarray, rotations: np.ndarray,
                  camera: bool = True) -> Path:
    """A frames folder as `flowerpose frames` writes it, on the images of render_scene,
    with positions (N, 3) and rotations (N, 3, 3) as the recorded poses."""
    folder.mkdir(parents=True)
    (folder / "frames").symlink_to(images)
    entries = [{"index": k, "file": f"frames/frame_{k:06d}.jpg", "t": float(k),
                "pose": {"position": p.tolist(), "rotation": r.tolist()}}
               for k, (p, r) in enumerate(zip(positions, rotations, strict=True))]
    (folder / "frames.json").write_text(json.dumps({"frames": entries}))
    if camera:
        (folder / "camera.json").write_text(json.dumps({
            "model": "PINHOLE", "width": WIDTH, "height": HEIGHT, "fx": FOCAL, "fy": FOCAL,
            "cx": WIDTH / 2, "cy": HEIGHT / 2}))
    return folder


def surface_distance(points: np.ndarray) -> np.ndarray:
    """(N,) distance from points (N, 3) to the nearest box surface, metres."""
    lo, hi = BOXES[:, None, 0], BOXES[:, None, 1]
    outside = np.linalg.norm(np.maximum(np.maximum(lo - points, points - hi), 0), axis=2)
    inside = np.minimum(points - lo, hi - points).min(axis=2)
    return np.where(outside > 0, outside, np.maximum(inside, 0)).min(axis=0)


@pytest.fixture(scope="module")
def images(tmp_path_factory) -> Path:
    return render_scene(tmp_path_factory.mktemp("scene"))


@pytest.fixture
def scene(images, tmp_path) -> tuple[Path, np.ndarray]:
    positions, rotations = ring_poses()
    return frames_folder(tmp_path / "scene", images, positions, rotations), positions


def centre_errors(result, positions: np.ndarray) -> np.ndarray:
    images = sorted(result.reconstruction.images.values(), key=lambda im: im.name)
    return np.linalg.norm(np.array([im.projection_center() for im in images]) - positions,
                          axis=1)


def check_reconstruction(result, workdir: Path, positions: np.ndarray) -> None:
    report = result.report
    assert report["images_given"] == report["images_registered"] == VIEWS
    assert report["points"] > 300 and report["mean_track_length"] >= 3
    assert report["mean_reprojection_error_px"] < 1.0
    assert report["alignment_rms_m"] < 0.003
    assert centre_errors(result, positions).max() < 0.003
    assert len(result.cloud) == report["points"]
    assert np.median(surface_distance(result.cloud.points)) < 0.001
    assert np.percentile(surface_distance(result.cloud.points), 90) < 0.004
    assert result.cloud.colors.dtype == np.uint8 and result.cloud.colors.std() > 10
    for name in ("sparse/cameras.bin", "sparse/images.bin", "sparse/points3D.bin",
                 "sparse.ply", "sparse.json", "database.db", "pairs.txt"):
        assert (workdir / name).is_file(), name
    written = json.loads((workdir / "sparse.json").read_text())
    assert written["points"] == report["points"]
    assert written["config"]["mode"] == result.report["config"]["mode"]
    assert set(written["seconds"]) >= {"features", "matching", "alignment", "total"}


@pytest.mark.slow
def test_a_rendered_scene_comes_back_in_the_bed_frame(scene, tmp_path):
    frames_dir, positions = scene
    result = reconstruct_sparse(frames_dir, tmp_path / "work", SfmConfig())
    assert result.report["mode"] == "poses" and result.report["intrinsics"] == "camera.json"
    check_reconstruction(result, tmp_path / "work", positions)


@pytest.mark.slow
def test_incremental_mapping_with_estimated_intrinsics(images, tmp_path):
    positions, rotations = ring_poses()
    frames_dir = frames_folder(tmp_path / "scene", images, positions, rotations, camera=False)
    # "poses" mode (the default) needs the intrinsics: without them it maps incrementally.
    result = reconstruct_sparse(frames_dir, tmp_path / "work", SfmConfig())
    assert result.report["mode"] == "incremental"
    assert result.report["intrinsics"] == "estimated"
    assert result.report["camera"]["params"][0] == pytest.approx(FOCAL, rel=0.01)
    check_reconstruction(result, tmp_path / "work", positions)


@pytest.mark.slow
def test_refined_poses_stay_in_the_bed_frame_when_recorded_positions_are_noisy(
        images, tmp_path):
    positions, rotations = ring_poses()
    noisy = positions + np.random.default_rng(3).normal(0, 0.002, positions.shape)
    frames_dir = frames_folder(tmp_path / "scene", images, noisy, rotations)
    result = reconstruct_sparse(frames_dir, tmp_path / "work", SfmConfig())
    assert result.report["images_registered"] == VIEWS
    # The refined cameras agree with the images, so they move back towards the truth.
    errors = centre_errors(result, positions)
    assert np.sqrt(np.mean(errors ** 2)) < 0.7 * np.sqrt(np.mean(
        np.sum((noisy - positions) ** 2, axis=1)))
    assert 0.0005 < result.report["alignment_rms_m"] < 0.005


class _Extracted(Exception):
    """Raised by a stand-in for pycolmap's feature extraction, carrying its options."""


@pytest.mark.parametrize("camera, mode, size", [(True, "poses", 640),
                                                (False, "incremental", 1280)])
def test_sift_sees_the_frames_at_the_size_each_mode_needs(images, tmp_path, monkeypatch,
                                                           camera, mode, size):
    """Unset, SIFT's image size follows the mode: 640 px where the recorded poses guide
    matching, the frames' 1280 where incremental mapping finds the poses from the
    features; a size given is used in either."""
    from flowerpose.pipeline import sfm_matching

    def extract(*args, extraction_options, **kwargs):
        raise _Extracted(extraction_options.max_image_size)

    monkeypatch.setattr(sfm_matching.pycolmap, "extract_features", extract)
    positions, rotations = ring_poses()
    frames_dir = frames_folder(tmp_path / "scene", images, positions, rotations, camera=camera)
    for config, expected in ((SfmConfig(), size), (SfmConfig(max_image_size=800), 800)):
        with pytest.raises(_Extracted) as caught:
            reconstruct_sparse(frames_dir, tmp_path / f"work-{expected}", config)
        assert caught.value.args == (expected,), mode


def test_too_few_images_is_a_clear_error(scene, tmp_path):
    frames_dir, _ = scene
    data = json.loads((frames_dir / "frames.json").read_text())
    small = tmp_path / "small"
    small.mkdir()
    (small / "frames.json").write_text(json.dumps({"frames": data["frames"][:2]}))
    (small / "frames").symlink_to(frames_dir / "frames")
    with pytest.raises(InputError, match="2 images: structure from motion needs at "
                       "least 3") as caught:
        reconstruct_sparse(small, tmp_path / "work")
    assert caught.value.source == str(small)


def test_images_that_do_not_register_are_a_clear_error(tmp_path):
    positions, rotations = ring_poses()
    blank = tmp_path / "blank"
    blank.mkdir()
    for k in range(4):
        cv2.imwrite(str(blank / f"frame_{k:06d}.jpg"), np.full((HEIGHT, WIDTH, 3), 128,
                                                               np.uint8))
    folder = frames_folder(tmp_path / "scene", blank, positions[:4], rotations[:4])
    for mode in ("poses", "incremental"):
        with pytest.raises(InputError, match=r"only 0 of 4 images registered") as caught:
            reconstruct_sparse(folder, tmp_path / mode, SfmConfig(mode=mode))
        assert caught.value.source == str(folder)


def test_missing_folder_or_image_is_a_clear_error(scene, tmp_path):
    with pytest.raises(InputError, match="frames folder not found"):
        reconstruct_sparse(tmp_path / "nowhere", tmp_path / "work")
    frames_dir, _ = scene
    data = json.loads((frames_dir / "frames.json").read_text())
    data["frames"][1]["file"] = "frames/missing.jpg"
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "frames.json").write_text(json.dumps(data))
    (broken / "frames").symlink_to(frames_dir / "frames")
    with pytest.raises(InputError, match="image listed in frames.json not found"):
        reconstruct_sparse(broken, tmp_path / "work")
    first = data["frames"][0]["file"]
    (broken / "frames.json").write_text(json.dumps({"frames": [{"index": 0, "file": first}]}))
    with pytest.raises(InputError, match='no frame has a "pose": mark such a folder'):
        reconstruct_sparse(broken, tmp_path / "work")


def test_pairs_for_an_ordered_scan():
    assert sequential_pairs(4, 2) == {(0, 1), (0, 2), (1, 2), (1, 3), (2, 3)}
    positions, rotations = ring_poses()
    pairs = pairs_from_poses(positions, rotations, neighbours=2, max_angle_deg=60)
    assert {(0, 1), (0, VIEWS - 1)} <= pairs
    assert all(min(abs(i - j), VIEWS - abs(i - j)) <= 2 for i, j in pairs)
    opposite = pairs_from_poses(positions[[0, 6]], rotations[[0, 6]], 3, 60)
    assert opposite == set()


def test_frames_at_an_earlier_frames_pose_are_left_out():
    positions, rotations = ring_poses()
    positions = np.concatenate([positions[:3], positions[1:2] + 0.0002, positions[3:4]])
    rotations = np.concatenate([rotations[:3], rotations[1:2], rotations[3:4]])
    np.testing.assert_array_equal(distinct_poses(positions, rotations),
                                  [True, True, True, False, True])
    turned = rotations.copy()
    turned[3] = turned[3] @ cv2.Rodrigues(np.array([0.0, 0.05, 0.0]))[0]
    assert distinct_poses(positions, turned).all()


def test_epipolar_matching_keeps_true_matches_and_refuses_lookalikes():
    rng = np.random.default_rng(0)
    points = rng.uniform([-0.1, -0.1, -0.05], [0.1, 0.1, 0.05], (300, 3))
    c1, c2 = np.array([0.0, -0.3, 0.1]), np.array([0.1, -0.28, 0.12])
    r1, r2 = look_at(c1, np.zeros(3)), look_at(c2, np.zeros(3))

    def project(centre, rotation):
        camera = (points - centre) @ rotation
        return (camera / camera[:, 2:]) @ K.T

    x1, x2 = project(c1, r1)[:, :2], project(c2, r2)[:, :2]
    descriptors = rng.integers(0, 120, (300, 128)).astype(np.uint8)
    noisy = np.clip(descriptors + rng.integers(-6, 7, descriptors.shape), 0, 255)
    order = rng.permutation(300)
    rotation, translation = r2.T @ r1, r2.T @ (c1 - c2)
    skew = np.array([[0, -translation[2], translation[1]], [translation[2], 0, -translation[0]],
                     [-translation[1], translation[0], 0]])
    fundamental = np.linalg.inv(K).T @ skew @ rotation @ np.linalg.inv(K)
    found = epipolar_matches(x1, x2[order], descriptors, noisy[order].astype(np.uint8),
                             fundamental, max_px=2.0)
    assert len(found) >= 290
    np.testing.assert_array_equal(order[found[:, 1]], found[:, 0])
    # Features whose descriptors all look alike are ambiguous along the line: refused.
    alike = np.repeat(descriptors[:1], 300, axis=0)
    assert len(epipolar_matches(x1, x2, alike, alike, fundamental, max_px=50.0)) < 30
    assert epipolar_matches(x1[:0], x2, descriptors[:0], descriptors, fundamental,
                            2.0).shape == (0, 2)


@pytest.mark.parametrize("module", ["sfm", "sfm_matching"])
def test_importing_sfm_first_keeps_png_writing_alive(tmp_path, module):
    """pycolmap imported before cv2 aborts the process on cv2.imwrite(.png) (libpng double
    free): each module of the sparse stage that imports pycolmap must import cv2 first
    (sys.modules keeps the order imports began in; the crash alone depends on what else
    loaded libpng first)."""
    script = (f"import sys, flowerpose.pipeline.{module}\n"
              "names = list(sys.modules)\n"
              "assert names.index('cv2') < names.index('pycolmap'), 'pycolmap before cv2'\n"
              "import cv2, numpy as np\n"
              f"assert cv2.imwrite({str(tmp_path / 'x.png')!r}, np.zeros((8, 8, 3), np.uint8))\n")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert (tmp_path / "x.png").stat().st_size > 0


def test_config_is_documented_and_overridable():
    from flowerpose.config import apply_overrides

    config = apply_overrides(SfmConfig(), {"mode": "incremental", "max_features": "2048"})
    assert config == replace(SfmConfig(), mode="incremental", max_features=2048)
    with pytest.raises(InputError, match="must be one of"):
        apply_overrides(SfmConfig(), {"mode": "global"})


@pytest.mark.slow
def test_refined_poses_for_dense_stereo_match_the_recorded_ones(scene, tmp_path):
    from flowerpose.pipeline.reconstruct import refined_poses, sparse_intrinsics

    frames_dir, positions = scene
    result = reconstruct_sparse(frames_dir, tmp_path / "work", SfmConfig())
    poses = refined_poses(result)
    recorded = {f.file: f for f in read_frames(frames_dir)}
    assert set(poses) == set(recorded) and len(poses) == VIEWS
    for name, pose in poses.items():
        assert np.linalg.norm(pose[:3, 3] - recorded[name].position) < 0.003
        turn = pose[:3, :3].T @ recorded[name].rotation
        assert np.degrees(np.arccos(np.clip((np.trace(turn) - 1) / 2, -1, 1))) < 0.3
    intrinsics = sparse_intrinsics(result)
    assert (intrinsics.width, intrinsics.height) == (WIDTH, HEIGHT)
    assert intrinsics.fx == pytest.approx(FOCAL) and intrinsics.cx == pytest.approx(WIDTH / 2)


def test_the_same_frames_give_the_same_model(scene, tmp_path):
    """Images are numbered in the frames' order, not as extraction's threads finish them,
    so matching and triangulation (which follow the numbers) repeat: the same points twice."""
    import pycolmap

    folder, _ = scene
    first = reconstruct_sparse(folder, tmp_path / "one", SfmConfig(num_threads=2))
    again = reconstruct_sparse(folder, tmp_path / "two", SfmConfig(num_threads=2))
    database = pycolmap.Database.open(tmp_path / "one" / "database.db")
    try:
        numbered = sorted(database.read_all_images(), key=lambda image: image.image_id)
    finally:
        database.close()
    assert [image.name for image in numbered] == [f.file for f in read_frames(folder)]
    assert np.array_equal(first.cloud.points, again.cloud.points)
