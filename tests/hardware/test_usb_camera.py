"""The USB camera against a fake V4L2 capture: mode checks, locked exposure and focus, frames
saved with their times, resumed recordings that append, and one-line errors."""

import csv
import dataclasses
import itertools
import math
import time

import cv2
import numpy as np
import pytest
from cloud_fakes import FakeCapture

from flowerpose.errors import InputError
from flowerpose.hardware.backends import usb_camera
from flowerpose.hardware.backends.usb_camera import (
    FrameChoice,
    UsbCamera,
    UsbCameraConfig,
    check_disk_space,
    estimated_intrinsics,
)
from flowerpose.hardware.bot_errors import CameraError
from flowerpose.jsonio import write_json
from flowerpose.scanio import frame_files

SMALL = UsbCameraConfig(width=64, height=48, settle_s=0.0, frame_timeout_s=0.5)


def _camera(capture=None, config=SMALL, clock=time.monotonic):
    capture = capture or FakeCapture()
    return UsbCamera("/dev/v4l/by-id/fake-video-index0", clock, config,
                     capture=lambda device: capture), capture


class TickingClock:
    """A bot clock that moves on `step_s` at every reading: the camera stamps each frame a
    step after the one before, however fast or slowly this machine takes them."""

    def __init__(self, step_s: float):
        self.step_s = step_s
        self._ticks = itertools.count()

    def __call__(self) -> float:
        return next(self._ticks) * self.step_s


def _failure(camera, what: str) -> str:
    """The CameraError `check()` raises once the camera's threads have failed (30 s at most:
    a hang guard)."""
    deadline = time.monotonic() + 30.0
    while time.monotonic() < deadline:
        try:
            camera.check()
        except CameraError as err:
            return str(err)
        time.sleep(0.02)
    pytest.fail(f"{what} was never reported")


def _saved(camera, frames: int) -> list[tuple[int, float]]:
    """`camera.saved_frames()` gathered until it has given `frames` (30 s at most: a hang
    guard), so a recording holds that many however slowly this machine saves them."""
    saved, deadline = [], time.monotonic() + 30.0
    while len(saved) < frames:
        assert time.monotonic() < deadline, f"hung: {len(saved)} of {frames} frames saved"
        saved += camera.saved_frames()
        time.sleep(0.01)
    return saved


def _times(scan_dir):
    with open(scan_dir / "frame_times.csv", newline="") as handle:
        rows = list(csv.reader(handle))
    assert rows[0] == ["frame", "t"]
    return np.array(rows[1:], dtype=float)


def test_opens_in_the_asked_mode_locks_exposure_and_focus_and_gives_frames(capsys):
    camera, capture = _camera(clock=lambda: 1234.5)
    assert capture.get(cv2.CAP_PROP_FOURCC) == cv2.VideoWriter_fourcc(*"MJPG")
    assert capture.get(cv2.CAP_PROP_AUTO_EXPOSURE) == 1.0  # V4L2's manual exposure
    assert capture.get(cv2.CAP_PROP_AUTOFOCUS) == 0.0
    assert capture.get(cv2.CAP_PROP_EXPOSURE) == 156.0  # where the automatics settled
    assert capsys.readouterr().err == ""
    frame = camera.frame()
    assert frame.image.shape == (48, 64, 3) and frame.image.dtype == np.uint8
    assert frame.t_s == 1234.5  # stamped with the bot's clock
    intrinsics = camera.intrinsics()
    assert intrinsics["fx"] == pytest.approx(32 / math.tan(math.radians(62.2) / 2))
    assert (intrinsics["cx"], intrinsics["cy"], intrinsics["fps"]) == (32, 24, 30.0)
    camera.close()
    assert capture.released


def test_a_driver_that_refuses_settings_gives_one_warning_line_each(capsys):
    capture = FakeCapture(refuse={cv2.CAP_PROP_AUTO_EXPOSURE, cv2.CAP_PROP_FOCUS,
                                  cv2.CAP_PROP_FOURCC})
    camera, _ = _camera(capture, UsbCameraConfig(width=64, height=48, settle_s=0.0,
                                                 exposure=80.0, focus=10.0))
    camera.close()
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 3 and all(line.startswith("warning: camera /dev/v4l/") for line in lines)
    assert "pixel format" in lines[0] and "exposure" in lines[1] and "focus" in lines[2]
    assert capture.get(cv2.CAP_PROP_EXPOSURE) == 80.0


@pytest.mark.parametrize("capture, words", [
    (FakeCapture(opened=False), "cannot open the camera"),
    (FakeCapture(deliver=(640, 480)), "delivers 640 x 480 frames, not the 64 x 48"),
    (FakeCapture(frames=0), "no frame for 0.5 s"),
])
def test_a_busy_silent_or_wrong_mode_camera_is_one_clear_error(capture, words):
    with pytest.raises(CameraError) as raised:
        _camera(capture)
    assert words in str(raised.value) and "\n" not in str(raised.value)
    assert str(raised.value).startswith("/dev/v4l/by-id/fake-video-index0")
    assert capture.released


def test_a_missing_device_is_named():
    with pytest.raises(CameraError, match="no-such-camera: no such camera device"):
        UsbCamera("/dev/v4l/by-id/no-such-camera", config=SMALL)


def test_intrinsics_from_a_calibration_at_the_same_resolution(tmp_path):
    path = write_json(tmp_path / "camera.json", {"model": "PINHOLE", "width": 64, "height": 48,
                                                 "fx": 70.5, "fy": 71.0, "cx": 31.0,
                                                 "cy": 25.5})
    camera, _ = _camera(config=UsbCameraConfig(width=64, height=48, settle_s=0.0,
                                               calibration=path))
    assert camera.intrinsics() == {"model": "PINHOLE", "width": 64, "height": 48, "fx": 70.5,
                                   "fy": 71.0, "cx": 31.0, "cy": 25.5, "fps": 30.0}
    camera.close()
    with pytest.raises(InputError, match="calibrated at 64 x 48"):
        _camera(config=UsbCameraConfig(width=32, height=24, settle_s=0.0, calibration=path))
    assert estimated_intrinsics(1280, 720, 90.0, 30.0).fx == pytest.approx(640.0)


def test_recording_saves_every_frame_with_its_time_and_a_resumed_one_appends(tmp_path):
    camera, capture = _camera()
    camera.start_recording(tmp_path / "video.mp4")
    saved = _saved(camera, 10)
    recording = camera.stop_recording()
    saved += camera.saved_frames()
    first = len(saved)
    assert recording.frames == first >= 10 and recording.path == tmp_path / "frames"
    times = _times(tmp_path)
    np.testing.assert_array_equal(times[:, 0], np.arange(first))
    np.testing.assert_allclose(times[:, 1], [t for _, t in saved], atol=1e-6)
    assert np.all(np.diff(times[:, 1]) > 0)
    # Each file holds its frame, in order: the fake's grey level counts frames up (by one
    # a frame; more where a loaded machine's reader skipped some, as a live camera's does;
    # JPEG may move a level by one).
    levels = [int(cv2.imread(str(p))[0, 0, 0]) for p in frame_files(tmp_path)]
    assert np.all(np.diff(levels) >= -1) and levels[-1] - levels[0] >= len(levels) - 3

    camera.start_recording(tmp_path / "video.mp4")  # a second session in the same folder
    later = _saved(camera, 1)
    camera.stop_recording()
    later += camera.saved_frames()
    assert later[0][0] == first and len(frame_files(tmp_path)) == first + len(later)
    np.testing.assert_array_equal(_times(tmp_path)[:, 0], np.arange(first + len(later)))
    camera.close()


def test_a_camera_that_stops_mid_recording_fails_the_check(tmp_path):
    camera, capture = _camera()
    camera.start_recording(tmp_path / "video.mp4")
    # The camera goes silent 20 frames into the recording, however late the recording began.
    capture.frames = last = capture.count + 20
    assert "no frame for 0.5 s" in _failure(camera, "the stalled camera")
    with pytest.raises(CameraError):
        camera.stop_recording()
    # Every frame it delivered while recording is kept, up to its last.
    levels = [int(cv2.imread(str(p))[0, 0, 0]) for p in frame_files(tmp_path)]
    assert levels and levels == [k % 256 for k in range(last - len(levels) + 1, last + 1)]
    camera.close()


def test_choosing_while_recording_writes_only_the_kept_frames(tmp_path, monkeypatch):
    # Room to queue every frame: none is dropped, however slowly this machine saves them.
    config = dataclasses.replace(SMALL, choose=FrameChoice(duration_s=0.2, bins=4, keep=2),
                                 queue_frames=1000)
    # The recording's files open slowly, as on a loaded machine: the frames taken meanwhile
    # are before its start, not lost from its first bin.
    open_rows = usb_camera.open_rows

    def slow_open_rows(*args):
        time.sleep(0.2)
        return open_rows(*args)

    monkeypatch.setattr(usb_camera, "open_rows", slow_open_rows)
    # Bot time by frames, not by the wall clock: 10 frames a bin of 0.05 s.
    camera, capture = _camera(FakeCapture(fps=200.0), config, clock=TickingClock(0.005))
    camera.start_recording(tmp_path / "video.mp4")
    first = capture.count
    deadline = time.monotonic() + 30.0
    while capture.count < first + 120:  # 0.6 s of bot time: past the planned 0.2 s
        assert time.monotonic() < deadline, "hung: the camera stopped delivering frames"
        time.sleep(0.01)
    recording = camera.stop_recording()
    offered = capture.count - first
    assert recording.frames == len(frame_files(tmp_path))
    assert np.all(np.diff(_times(tmp_path)[:, 1]) > 0)  # numbered in time order
    # Two of each bin (binned as the keeper does); past the planned end, more bins of the
    # same 0.05 s; the last one may have closed after a single frame.
    width = config.choose.duration_s / config.choose.bins
    kept = np.bincount([max(int((t - recording.start_s) // width), 0)
                        for _, t in camera.saved_frames()]).tolist()
    assert len(kept) >= 10 and kept[:-1] == [2] * (len(kept) - 1) and kept[-1] in (1, 2)
    assert recording.frames == sum(kept) < offered / 2
    camera.close()


def test_a_disk_without_room_stops_the_recording_with_a_clear_error(tmp_path):
    full = dataclasses.replace(SMALL, disk_reserve_mb=1e12)  # more than any disk holds
    camera, _ = _camera(config=full)
    camera.start_recording(tmp_path / "video.mp4")
    failure = _failure(camera, "the full disk")
    assert "the disk is nearly full" in failure and "resume" in failure
    with pytest.raises(CameraError):
        camera.stop_recording()
    assert frame_files(tmp_path) == [] and not list((tmp_path / "frames").glob("*.tmp"))
    with pytest.raises(InputError, match="MB free on its disk, but the scan needs about"):
        check_disk_space(tmp_path / "scan", full, 1200.0)
    check_disk_space(tmp_path / "scan", SMALL, 1.0)  # a second of 64 x 48 frames fits
    camera.close()
