"""Photographs and videos in (`flowerpose frames --images`): small synthetic inputs."""

import json

import cv2  # before pycolmap (pipeline/sfm.py)
import numpy as np
import pycolmap
import pytest

from flowerpose.errors import InputError
from flowerpose.jsonio import write_json
from flowerpose.pipeline.frames import read_frames
from flowerpose.pipeline.photos import (
    PhotoImportConfig,
    import_photos,
    list_photos,
    pan_tilt_rotation,
    read_pose_table,
)
from flowerpose.scanio import read_intrinsics
from tests.cli_run import run_cli

WIDTH, HEIGHT = 160, 120


def _photo(seed: int) -> np.ndarray:
    """A textured RGB image, different for each seed."""
    rng = np.random.default_rng(seed)
    return cv2.resize(rng.integers(0, 256, (30, 40, 3)).astype(np.uint8), (WIDTH, HEIGHT),
                      interpolation=cv2.INTER_NEAREST)


def _photos(folder, count=5, names=None):
    folder.mkdir(parents=True, exist_ok=True)
    names = names or [f"img{k + 1}.png" for k in range(count)]
    for k, name in enumerate(names):
        cv2.imwrite(str(folder / name), cv2.cvtColor(_photo(k), cv2.COLOR_RGB2BGR))
    return folder


def _colmap_model(folder, names, camera_model="OPENCV", params=(150, 150, 80, 60, -0.1, 0.02,
                                                                 0, 0)):
    """A COLMAP text model of `names` on a circle of radius 300 (millimetres), looking in."""
    folder.mkdir(parents=True)
    (folder / "cameras.txt").write_text(
        f"1 {camera_model} {WIDTH} {HEIGHT} {' '.join(map(str, params))}\n")
    lines = []
    for k, name in enumerate(names):
        angle = 2 * np.pi * k / len(names)
        centre = 300 * np.array([np.cos(angle), np.sin(angle), 0.0])
        rotation = pan_tilt_rotation(np.array([np.degrees(angle) + 180]), np.array([0.0]))[0]
        cam_from_world = rotation.T
        quaternion = pycolmap.Rotation3d(cam_from_world).quat  # x, y, z, w
        t = -cam_from_world @ centre
        lines.append(f"{k + 1} {quaternion[3]} {quaternion[0]} {quaternion[1]} {quaternion[2]} "
                     f"{t[0]} {t[1]} {t[2]} 1 {name}\n\n")
    (folder / "images.txt").write_text("".join(lines))
    (folder / "points3D.txt").write_text("")
    return folder


def test_photos_are_listed_in_natural_order(tmp_path):
    folder = _photos(tmp_path / "p", names=["img10.png", "img2.png", "img1.jpg"])
    (folder / "notes.txt").write_text("not a photo")
    assert [p.name for p in list_photos(folder)] == ["img1.jpg", "img2.png", "img10.png"]


def test_photos_become_a_frames_folder_with_an_estimated_camera(tmp_path):
    folder = _photos(tmp_path / "p", count=4)
    result = import_photos(folder, tmp_path / "frames")
    frames = read_frames(tmp_path / "frames", need_poses=False)
    assert [f.file for f in frames] == [f"frames/img{k}.png" for k in range(1, 5)]
    assert all(f.pose is None for f in frames) and result["poses"] == "none"
    camera = read_intrinsics(tmp_path / "frames" / "camera.json")
    # COLMAP's own default: 1.2 times the longer side, the centre; refined later.
    assert camera.estimated and camera.fx == pytest.approx(1.2 * WIDTH)
    assert (camera.cx, camera.cy) == (WIDTH / 2, HEIGHT / 2)
    # Copied as they were (nothing to undistort or scale).
    assert (tmp_path / "frames/frames/img1.png").read_bytes() == (folder / "img1.png").read_bytes()


def test_a_colmap_model_gives_undistorted_pinhole_frames_and_metric_poses(tmp_path):
    names = [f"img{k + 1}.png" for k in range(6)]
    folder = _photos(tmp_path / "p", names=names)
    model = _colmap_model(tmp_path / "model", names)
    result = import_photos(folder, tmp_path / "frames", PhotoImportConfig(units="mm"),
                           colmap=model)
    assert result["poses"] == "calibrated" and result["undistorted"]
    camera = json.loads((tmp_path / "frames" / "camera.json").read_text())
    assert camera["model"] == "PINHOLE" and "estimated" not in camera
    expected = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(),
                                         pycolmap.Reconstruction(str(model)).cameras[1])
    assert (camera["width"], camera["height"]) == (expected.width, expected.height)
    assert camera["fx"] == pytest.approx(expected.focal_length_x)
    frames = read_frames(tmp_path / "frames")
    assert np.allclose(frames[0].position, [0.3, 0, 0])  # millimetres to metres
    assert np.allclose(frames[0].rotation[:, 2], [-1, 0, 0], atol=1e-9)  # looking in
    assert result["up_check_deg"] == pytest.approx(0, abs=1e-6)
    image = cv2.imread(str(tmp_path / "frames" / frames[0].file))
    assert image.shape[:2] == (expected.height, expected.width)
    assert not np.array_equal(image[:HEIGHT, :WIDTH], cv2.imread(str(folder / names[0])))


def test_downscaling_scales_the_camera(tmp_path):
    folder = _photos(tmp_path / "p", count=3)
    write_json(tmp_path / "cam.json", {"model": "PINHOLE", "width": WIDTH, "height": HEIGHT,
                                       "fx": 140.0, "fy": 140.0, "cx": 80.0, "cy": 60.0})
    import_photos(folder, tmp_path / "frames", PhotoImportConfig(max_size=80),
                  calibration=tmp_path / "cam.json")
    camera = read_intrinsics(tmp_path / "frames" / "camera.json")
    assert (camera.width, camera.height, camera.fx, camera.cx) == (80, 60, 70.0, 40.0)
    assert not camera.estimated
    assert cv2.imread(str(tmp_path / "frames/frames/img1.jpg")).shape == (60, 80, 3)


def test_rough_poses_read_from_a_table(tmp_path):
    (tmp_path / "poses.csv").write_text("file,x,y,z,pan,tilt\nimg1.png,100,0,80,180,20\n"
                                        "sub/img2.png,0,100,80,270,0\n")
    poses = read_pose_table(tmp_path / "poses.csv", "mm")
    assert np.allclose(poses["img1.png"].position, [0.1, 0, 0.08])
    forward = poses["img1.png"].rotation[:, 2]
    assert np.allclose(forward, [-np.cos(np.radians(20)), 0, -np.sin(np.radians(20))])
    assert np.allclose(poses["img2.png"].rotation[:, 2], [0, -1, 0], atol=1e-12)
    for pose in poses.values():  # level: image x horizontal, image up with +z
        assert abs(pose.rotation[2, 0]) < 1e-12 and pose.rotation[2, 1] < 0
        assert np.allclose(pose.rotation.T @ pose.rotation, np.eye(3))
        assert np.linalg.det(pose.rotation) == pytest.approx(1)


def test_a_video_gives_the_frames_a_photo_folder_does(tmp_path):
    folder = _photos(tmp_path / "p", count=6)
    video = tmp_path / "plant.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10, (WIDTH, HEIGHT))
    for photo in list_photos(folder):
        writer.write(cv2.imread(str(photo)))
    writer.release()
    from_photos = import_photos(folder, tmp_path / "a")
    from_video = import_photos(video, tmp_path / "b", PhotoImportConfig(count=6))
    assert len(from_video["frames"]) == len(from_photos["frames"]) == 6
    assert [f["index"] for f in from_video["frames"]] == [f["index"] for f in
                                                          from_photos["frames"]]
    images_a = [cv2.imread(str(tmp_path / "a" / f["file"])).astype(float)
                for f in from_photos["frames"]]
    images_b = [cv2.imread(str(tmp_path / "b" / f["file"])).astype(float)
                for f in from_video["frames"]]
    difference = np.array([[np.abs(a - b).mean() for a in images_a] for b in images_b])
    # Each video frame is its photo, up to the video's compression, and no other photo.
    assert list(difference.argmin(axis=1)) == list(range(6))
    assert difference.diagonal().max() < difference[~np.eye(6, dtype=bool)].min() / 2
    camera_a = read_intrinsics(tmp_path / "a" / "camera.json")
    camera_b = read_intrinsics(tmp_path / "b" / "camera.json")
    assert camera_a.fx == camera_b.fx and camera_a.estimated and camera_b.estimated
    assert camera_b.fps == pytest.approx(10)


@pytest.mark.parametrize("case", ["empty", "unreadable", "mixed", "model-names-others",
                                  "video-undecodable", "unposed"])
def test_bad_input_is_one_line_and_writes_nothing(tmp_path, capsys, case):
    folder = _photos(tmp_path / "p", count=3)
    extra = []
    if case == "empty":
        folder = tmp_path / "empty"
        folder.mkdir()
        expected = "no photographs"
    elif case == "unreadable":
        (folder / "img2.png").write_bytes(b"not an image at all")
        expected = "unreadable image"
    elif case == "mixed":
        cv2.imwrite(str(folder / "img3.png"), np.zeros((50, 70, 3), np.uint8))
        expected = "one camera at one resolution"
    elif case == "model-names-others":
        model = _colmap_model(tmp_path / "model", ["img1.png", "img2.png", "img3.png",
                                                   "other.png"])
        extra = ["--colmap", model, "--pose-units", "mm"]
        expected = "names 1 images not in"
    elif case == "video-undecodable":
        folder = tmp_path / "plant.mp4"
        folder.write_bytes(b"\x00" * 1000)
        expected = "video"
    else:
        (tmp_path / "poses.csv").write_text("file,x,y,z,pan,tilt\nimg1.png,0,0,0,0,0\n")
        extra = ["--poses", tmp_path / "poses.csv"]
        expected = "no pose for 2 of the 3 photos"
    code, out, err = run_cli(capsys, "frames", "--images", folder, *extra, "--out",
                             tmp_path / "out")
    assert code == 2, err
    assert len(err.strip().splitlines()) == 1 and expected in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()


def test_frames_takes_a_scan_or_images_not_both(tmp_path, capsys):
    folder = _photos(tmp_path / "p", count=3)
    code, _, err = run_cli(capsys, "frames", "--out", tmp_path / "out")
    assert code == 2 and "one of them" in err
    code, _, err = run_cli(capsys, "frames", tmp_path, "--images", folder, "--out",
                           tmp_path / "out")
    assert code == 2 and "one of them" in err
    code, _, err = run_cli(capsys, "frames", tmp_path, "--colmap", tmp_path, "--out",
                           tmp_path / "out")
    assert code == 2 and "--colmap is for --images" in err


def test_a_camera_json_of_a_distorted_model_is_refused_as_a_frames_camera(tmp_path):
    write_json(tmp_path / "camera.json", {"model": "OPENCV", "width": 10, "height": 10,
                                          "fx": 1, "fy": 1, "cx": 5, "cy": 5})
    with pytest.raises(InputError, match="a frames folder's camera is a pinhole"):
        read_intrinsics(tmp_path / "camera.json")


def test_an_image_that_fails_to_decode_midway_leaves_the_earlier_folder_whole(tmp_path, capsys):
    folder = _photos(tmp_path / "p", count=3)
    import_photos(folder, tmp_path / "frames")
    before = sorted(p.name for p in (tmp_path / "frames" / "frames").iterdir())
    write_json(tmp_path / "cam.json", {"model": "OPENCV", "width": WIDTH, "height": HEIGHT,
                                       "params": [150, 150, 80, 60, -0.1, 0, 0, 0]})
    data = (folder / "img3.png").read_bytes()
    (folder / "img3.png").write_bytes(data[:len(data) // 2])  # its header still reads
    code, _, err = run_cli(capsys, "frames", "--images", folder, "--calibration",
                           tmp_path / "cam.json", "--out", tmp_path / "frames", "--overwrite")
    assert code == 2 and "img3.png" in err and len(err.strip().splitlines()) == 1
    assert sorted(p.name for p in (tmp_path / "frames" / "frames").iterdir()) == before
    assert json.loads((tmp_path / "frames" / "frames.json").read_text())["poses"] == "none"
    assert not list(tmp_path.glob(".frames.partial-*"))


def test_a_focal_length_in_exif_seeds_the_camera(tmp_path):
    from PIL import Image

    folder = tmp_path / "p"
    folder.mkdir()
    for k in range(3):
        image = Image.fromarray(_photo(k))
        exif = Image.Exif()
        exif.get_ifd(0x8769)[0xA405] = 27  # FocalLengthIn35mmFilm: a phone's main camera
        image.save(folder / f"img{k}.jpg", exif=exif)
    result = import_photos(folder, tmp_path / "frames")
    camera = read_intrinsics(tmp_path / "frames" / "camera.json")
    assert result["camera"] == "exif" and camera.estimated
    assert camera.fx == pytest.approx(27 / 36 * WIDTH)
