import csv
import json

import cv2
import numpy as np
import pytest

from flowerpose.errors import InputError
from flowerpose.jsonio import write_json
from flowerpose.pipeline.frames import (
    FrameSelectConfig,
    bin_edges,
    distinct_views,
    frame_score,
    read_frames,
    select_frames,
)
from flowerpose.scanio import (
    FRAME_PATTERN,
    TRAJECTORY_COLUMNS,
    Intrinsics,
    read_trajectory,
    trajectory_row,
)


def _scan(path, blur_px, texture_seed=0, video=False):
    """A scan folder whose frame k is a textured image blurred by blur_px[k] pixels."""
    rng = np.random.default_rng(texture_seed)
    base = cv2.resize(rng.integers(0, 256, (60, 80, 3)).astype(np.uint8), (320, 240),
                      interpolation=cv2.INTER_NEAREST)
    (path / "frames").mkdir(parents=True)
    rows = []
    writer = None
    if video:
        writer = cv2.VideoWriter(str(path / "video.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 30,
                                 (320, 240))
    for k, blur in enumerate(blur_px):
        image = cv2.GaussianBlur(base, (0, 0), blur) if blur > 0 else base
        if video:
            writer.write(image)
        else:
            cv2.imwrite(str(path / "frames" / FRAME_PATTERN.format(k)), image,
                        [cv2.IMWRITE_JPEG_QUALITY, 95])
        angle = k * 0.01
        rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0],
                             [0, 0, 1]])
        rows.append(trajectory_row(k, k / 30, np.array([1.0, 0.5, 0.3]), angle, 0.1,
                                   np.array([1.0, 0.5 + k * 1e-3, 0.2]), rotation))
    if writer is not None:
        writer.release()
    with open(path / "trajectory.csv", "w", newline="") as handle:
        csv.writer(handle).writerows([TRAJECTORY_COLUMNS, *rows])
    write_json(path / "camera.json", Intrinsics(320, 240, 300, 300, 160, 120).to_json())
    return path


@pytest.mark.parametrize("video", [False, True], ids=["frames", "video"])
def test_the_sharpest_frame_of_each_bin_is_chosen(tmp_path, video):
    rng = np.random.default_rng(1)
    blur = rng.uniform(1.0, 4.0, 60)
    sharp = [int(b * 10 + rng.integers(0, 10)) for b in range(6)]
    blur[sharp] = 0.0
    scan = _scan(tmp_path / "scan", blur, video=video)
    result = select_frames(scan, tmp_path / "out", FrameSelectConfig(count=6), progress=False)
    assert [f["index"] for f in result["frames"]] == sharp
    assert all((tmp_path / "out" / f["file"]).exists() for f in result["frames"])
    assert (tmp_path / "out" / "camera.json").exists()
    np.testing.assert_allclose(result["frames"][0]["pose"]["position"], [1.0, 0.5 + sharp[0] * 1e-3,
                                                                         0.2], atol=1e-9)


def test_score_falls_with_blur_and_brightness_penalty_prefers_105():
    rng = np.random.default_rng(2)
    image = rng.integers(0, 256, (200, 200, 3)).astype(np.uint8)
    config = FrameSelectConfig()
    scores = [frame_score(cv2.GaussianBlur(image, (0, 0), s), config)[0] for s in (0.5, 1, 2, 4)]
    assert scores == sorted(scores, reverse=True)
    flat = FrameSelectConfig(brightness_penalty=True)
    dark, mid = np.full((50, 50, 3), 20, np.uint8), np.full((50, 50, 3), 105, np.uint8)
    assert frame_score(mid, flat)[0] > frame_score(dark, flat)[0]


def test_bins_are_equal_and_sequential():
    edges = bin_edges(1000, 200)
    assert edges[0] == 0 and edges[-1] == 1000 and set(np.diff(edges)) == {5}


def test_trajectory_round_trip_keeps_the_pose(tmp_path):
    scan = _scan(tmp_path / "scan", [0.0, 1.0, 2.0])
    trajectory = read_trajectory(scan / "trajectory.csv")
    assert len(trajectory) == 3
    angle = 0.02
    np.testing.assert_allclose(trajectory.camera_rotation[2][:2, :2],
                               [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]],
                               atol=1e-8)


def test_errors_name_the_problem(tmp_path):
    scan = _scan(tmp_path / "scan", [0.0] * 5)
    with pytest.raises(InputError, match="fewer than the 10 bins"):
        select_frames(scan, tmp_path / "o", FrameSelectConfig(count=10), progress=False)
    with pytest.raises(InputError, match="scan folder not found"):
        select_frames(tmp_path / "nope", tmp_path / "o", FrameSelectConfig(), progress=False)
    (scan / "trajectory.csv").write_text("a,b\n1,2\n")
    with pytest.raises(InputError, match="header"):
        select_frames(scan, tmp_path / "o", FrameSelectConfig(count=2), progress=False)


def test_a_second_selection_replaces_the_first_and_short_rows_are_refused(tmp_path):
    scan = _scan(tmp_path / "scan", [0.0] * 12)
    select_frames(scan, tmp_path / "out", FrameSelectConfig(count=6), progress=False)
    select_frames(scan, tmp_path / "out", FrameSelectConfig(count=3), progress=False)
    assert len(list((tmp_path / "out" / "frames").glob("*.jpg"))) == 3
    for out in (scan, scan / "frames", tmp_path):  # the scan, its frames, holding it
        with pytest.raises(InputError, match="must not be the scan folder"):
            select_frames(scan, out, FrameSelectConfig(count=3), progress=False)
    lines = (scan / "trajectory.csv").read_text().splitlines()
    (scan / "trajectory.csv").write_text("\n".join([lines[0], "0,0,1,1,1,0,0", "1,0,1,1,1,1,0"]))
    with pytest.raises(InputError, match="row 1 has 7 values"):
        read_trajectory(scan / "trajectory.csv")


def test_frames_json_is_read_once_with_every_check(tmp_path):
    """The one reader of frames.json, as structure from motion and dense stereo use it."""
    scan = _scan(tmp_path / "scan", np.zeros(6))
    select_frames(scan, tmp_path / "out", FrameSelectConfig(count=3), progress=False)
    frames = read_frames(tmp_path / "out")
    assert [f.index for f in frames] == [0, 2, 4]  # equal scores: the first of each bin
    assert frames[0].pose.shape == (4, 4) and np.allclose(frames[0].pose[:3, :3],
                                                          frames[0].rotation)
    path = tmp_path / "out" / "frames.json"
    good = json.loads(path.read_text())

    def fails(change, words, need_poses=True):
        data = json.loads(json.dumps(good))
        change(data["frames"][1])
        path.write_text(json.dumps(data))
        with pytest.raises(InputError, match=words):
            read_frames(tmp_path / "out", need_poses)

    fails(lambda f: f.update(index="1"), 'needs an integer "index"')
    fails(lambda f: f.update(file="frames/none.jpg"), "image listed in frames.json not found")
    fails(lambda f: f["pose"].update(rotation=np.diag([1, 1, -1]).tolist()), "proper rotation")
    fails(lambda f: f["pose"].update(position=[0, float("nan")]), "holds NaN")
    fails(lambda f: f.pop("pose"), '"pose" with "position"')
    data = json.loads(json.dumps(good))
    data["frames"][1].pop("pose")
    path.write_text(json.dumps(data))
    assert read_frames(tmp_path / "out", need_poses=False)[1].pose is None


def test_a_frame_of_another_size_than_the_camera_is_one_clear_error(tmp_path):
    scan = _scan(tmp_path / "scan", [0.0] * 6)
    small = cv2.imread(str(scan / "frames" / FRAME_PATTERN.format(0)))[:120, :160]
    cv2.imwrite(str(scan / "frames" / FRAME_PATTERN.format(0)), small)
    with pytest.raises(InputError, match=r"is 160x120 pixels but the scan's camera.json says "
                       r"320x240"):
        select_frames(scan, tmp_path / "out", FrameSelectConfig(count=3), progress=False)
    assert not (tmp_path / "out").exists()


def test_damaged_frames_are_left_out_and_the_rest_of_the_scan_kept(tmp_path, capsys):
    scan = _scan(tmp_path / "scan", [0.0] * 8)
    (scan / "frames" / FRAME_PATTERN.format(1)).write_bytes(b"")  # empty
    whole = (scan / "frames" / FRAME_PATTERN.format(2)).read_bytes()
    (scan / "frames" / FRAME_PATTERN.format(2)).write_bytes(whole[: len(whole) // 2])  # cut
    result = select_frames(scan, tmp_path / "out", FrameSelectConfig(count=4), progress=False)
    assert [f["index"] for f in result["frames"]] == [0, 3, 4, 6]
    assert "2 damaged frames" in capsys.readouterr().err


def test_of_views_at_one_spot_looking_one_way_only_the_first_in_priority_counts():
    centres = np.array([[0, 0, 0], [0.003, 0, 0], [0.006, 0, 0], [0.003, 0, 0], [1, 0, 0]])
    axes = np.array([[0, 0, 1]] * 5, float)
    axes[3] = [0, np.sin(0.1), np.cos(0.1)]  # 5.7 degrees off: another view
    # Greedy: view 1 drops 0 and 2 (3 mm either side), though they are 6 mm apart.
    np.testing.assert_array_equal(
        distinct_views(centres, axes, np.array([0, 9, 1, 5, 2]), 0.004, 2.0),
        [False, True, False, True, True])
    # A dropped view drops nothing: in index order 1 goes, and 2 stays.
    np.testing.assert_array_equal(
        distinct_views(centres, axes, -np.arange(5), 0.004, 2.0),
        [True, False, True, True, True])
