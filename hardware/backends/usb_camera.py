"""The head's USB camera through OpenCV's V4L2 backend: fixed mode, locked exposure and focus,
frames saved to the scan folder as they come, each with its time on the bot's clock.

`UsbCamera` opens the device by a stable path (/dev/v4l/by-id/..., which survives
re-plugging, unlike /dev/videoN), asks for MJPG at a fixed resolution and frame rate and
reads them back: a camera that delivers another resolution is refused (CameraError), a
refused pixel format or frame rate is a one-line warning. After `settle_s` of frames it
locks exposure and focus (the values asked for, or where the automatics settled), so every
view of a scan has the same brightness and the calibration's focal length stays valid; a
driver that refuses is a one-line warning.

A capture thread takes frames continuously and stamps each with the bot's clock when it is
dequeued (after read-out: typically one or two frame intervals after the exposure). While
recording, a writer thread saves them as JPEG files (frames/frame_NNNNNN.jpg in the scan
folder, each written whole before it is named) and appends `frame,t` (bot-clock seconds) to
frame_times.csv beside them. Files rather than one video let an interrupted scan resume and
append: the next session numbers its frames after the highest on disk. A 1280 x 720 frame
is about 0.1-0.3 MB, so keeping every frame of a 20-minute scan at 30 fps needs several GB:
with `choose` the writer keeps only the sharpest few of each bin of the scan path as it goes
(`frame_keeper.FrameKeeper`), and the rest are never written. Before every frame it checks
the disk: with less than `disk_reserve_mb` left it stops the recording with a CameraError
that says so, every frame saved until then intact.

Intrinsics come from a calibration (camera.json, flowerpose/scanio.py, at the same
resolution) or, without one, an estimate from the lens's horizontal field of view: square
pixels, the principal point at the image centre, no distortion. Calibrate for accuracy.
"""

from __future__ import annotations

import math
import os
import queue
import shutil
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from flowerpose.atomic import write_bytes
from flowerpose.errors import InputError
from flowerpose.hardware.backends.frame_keeper import FrameKeeper
from flowerpose.hardware.bot import Frame, Recording
from flowerpose.hardware.bot_errors import CameraError
from flowerpose.hardware.trajectory import RecordingCamera, last_recorded
from flowerpose.log import LOG
from flowerpose.scanio import FRAME_PATTERN, Intrinsics, open_rows, read_intrinsics

_MANUAL_EXPOSURE = 1.0
"""V4L2_EXPOSURE_MANUAL: OpenCV's V4L2 backend passes CAP_PROP_AUTO_EXPOSURE on as is."""


@dataclass(frozen=True)
class FrameChoice:
    """Choosing frames while recording: the `keep` sharpest of each of `bins` equal bins of
    the planned scan's bot time (`frame_keeper.FrameKeeper`)."""

    duration_s: float
    """The planned scan's duration on the bot's clock, seconds (`ScanPlan.duration_s`)."""
    bins: int = 200
    """Bins of the scan path (the frame stage's 200 images)."""
    keep: int = 3
    """Frames kept a bin: the frame stage chooses among them."""


#: Upper estimate of a saved 1280 x 720 frame (JPEG quality 95 of a garden scene), bytes.
FRAME_BYTES_720P = 300_000


@dataclass(frozen=True)
class UsbCameraConfig:
    """How the USB camera records."""

    width: int = 1280
    """Frame width, pixels (the paper's 1280 x 720 video)."""
    height: int = 720
    """Frame height, pixels."""
    fps: float = 30.0
    """Frames per second asked of the camera."""
    fourcc: str = "MJPG"
    """Pixel format: MJPG gives 1280 x 720 at 30 fps over USB 2 where raw YUYV cannot."""
    exposure: float | None = None
    """Manual exposure in the driver's units (V4L2 exposure_time_absolute: 100 us); None
    locks the value the automatic exposure settled at."""
    focus: float | None = None
    """Manual focus in the driver's units (V4L2 focus_absolute); None locks where the
    autofocus settled."""
    hfov_deg: float = 62.2
    """Horizontal field of view for the estimated intrinsics, degrees (the Arducam IMX219's
    lens; an estimate: the sensor mode may crop)."""
    calibration: Path | None = None
    """camera.json of a calibration at this resolution; None estimates from `hfov_deg`."""
    settle_s: float = 1.0
    """Seconds of frames before exposure and focus are locked (the automatics settle)."""
    frame_timeout_s: float = 5.0
    """A camera that delivers no frame for this long is busy or stalled: CameraError."""
    jpeg_quality: int = 95
    """Quality of the saved frames (OpenCV's 0-100)."""
    queue_frames: int = 60
    """Frames that may wait for the writer (2 s at 30 fps); more are dropped and counted."""
    choose: FrameChoice | None = None
    """Keep only the sharpest frames of each bin while recording; None: every frame."""
    disk_reserve_mb: float = 500.0
    """Space the recording leaves free on the scan folder's disk, megabytes: it stops with
    a CameraError before a frame would eat into it."""

    def expected_bytes(self, duration_s: float) -> int:
        """Disk a recording of `duration_s` bot seconds takes, about and at most: the kept
        frames with `choose`, else every frame."""
        frame = FRAME_BYTES_720P * self.width * self.height / (1280 * 720)
        frames = (self.choose.bins * self.choose.keep if self.choose is not None
                  else duration_s * self.fps)
        return int(frame * frames)


def check_disk_space(scan_dir: Path, config: UsbCameraConfig, duration_s: float) -> None:
    """InputError naming the scan folder when its disk lacks the room a recording of
    `duration_s` needs (`expected_bytes`) plus the reserve: said before the bot moves."""
    folder = Path(scan_dir)
    while not folder.exists():
        folder = folder.parent
    free = shutil.disk_usage(folder).free
    needed = config.expected_bytes(duration_s) + config.disk_reserve_mb * 1e6
    if free < needed:
        chosen = replace(config, choose=FrameChoice(duration_s)).expected_bytes(duration_s)
        every = "" if config.choose is not None else (
            f"; frames chosen while recording (`choose`) need about "
            f"{(chosen + config.disk_reserve_mb * 1e6) / 1e6:.0f} MB")
        raise InputError(scan_dir, f"{free / 1e6:.0f} MB free on its disk, but the scan needs "
                         f"about {needed / 1e6:.0f} MB ({config.disk_reserve_mb:g} MB of it "
                         f"kept free){every}: free space or record elsewhere")

    def __post_init__(self):
        checks = {"width": self.width >= 16, "height": self.height >= 16,
                  "fps": math.isfinite(self.fps) and self.fps > 0,
                  "fourcc": len(self.fourcc) == 4,
                  "hfov_deg": 0 < self.hfov_deg < 180,
                  "settle_s": math.isfinite(self.settle_s) and self.settle_s >= 0,
                  "frame_timeout_s": math.isfinite(self.frame_timeout_s)
                  and self.frame_timeout_s > 0,
                  "jpeg_quality": 0 <= self.jpeg_quality <= 100,
                  "queue_frames": self.queue_frames >= 1,
                  "disk_reserve_mb": math.isfinite(self.disk_reserve_mb)
                  and self.disk_reserve_mb >= 0}
        bad = [name for name, ok in checks.items() if not ok]
        if bad:
            raise InputError(f"camera {bad[0]}", f"{getattr(self, bad[0])!r} is out of range")


def open_v4l2(device: str) -> Any:
    """cv2.VideoCapture of a V4L2 device path; CameraError when the path does not exist."""
    import cv2

    if not Path(device).exists():
        raise CameraError(f"{device}: no such camera device; list them with "
                          "ls -l /dev/v4l/by-id/ and check the cable")
    return cv2.VideoCapture(str(device), cv2.CAP_V4L2)


def _warn(device: str, message: str) -> None:
    LOG.warning(f"warning: camera {device}: {message}")


def estimated_intrinsics(width: int, height: int, hfov_deg: float, fps: float) -> Intrinsics:
    """Pinhole intrinsics from a horizontal field of view: square pixels, the principal point
    at (width / 2, height / 2) as everywhere in the project, pixels."""
    f = 0.5 * width / math.tan(math.radians(hfov_deg) / 2)
    return Intrinsics(width, height, f, f, width / 2, height / 2, fps)


class UsbCamera(RecordingCamera):
    """A V4L2 USB camera on the head: see the module docstring.

    device: the camera's path, best a stable one under /dev/v4l/by-id/.
    clock: the bot's clock (seconds) that stamps every frame; default time.monotonic.
    capture: opens the device, returning an object with cv2.VideoCapture's isOpened, set,
        get, grab, retrieve and release (tests pass a fake); default `open_v4l2`.
    Raises CameraError when the device is missing, cannot be opened (busy: another program
    holds it, or no permission), delivers no frame within `frame_timeout_s`, or delivers
    another resolution.
    """

    def __init__(self, device: str | Path, clock: Callable[[], float] = time.monotonic,
                 config: UsbCameraConfig = UsbCameraConfig(), *,
                 capture: Callable[[str], Any] | None = None):
        self.device = str(device)
        self.config = config
        self._clock = clock
        self._cap_lock = threading.Lock()
        self._state = threading.Condition()
        self._latest: tuple[np.ndarray, float] | None = None
        self._failure: CameraError | None = None
        self._closing = threading.Event()
        self._recording: _Recording | None = None
        self._session: _Recording | None = None  # the latest, kept for saved_frames()
        self._cap = (capture or open_v4l2)(self.device)
        self._thread: threading.Thread | None = None
        try:
            if not self._cap.isOpened():
                raise CameraError(f"{self.device}: cannot open the camera: another program may "
                                  "hold it (close it), or this user lacks permission (the "
                                  "video group)")
            self._set_mode()
            self._thread = threading.Thread(target=self._capture_loop, name="usb-camera",
                                            daemon=True)
            self._thread.start()
            image, _ = self._wait_frame()
            self._check_size(image.shape[1], image.shape[0])
            time.sleep(config.settle_s)
            self._lock_exposure_and_focus()
            self._intrinsics = self._load_intrinsics()
        except BaseException:
            self.close()
            raise

    def _prop(self, name: str) -> int:
        import cv2

        return getattr(cv2, f"CAP_PROP_{name}")

    def _set(self, name: str, value: float) -> tuple[bool, float]:
        """Set a capture property; (whether the driver took it, the value read back)."""
        with self._cap_lock:
            accepted = bool(self._cap.set(self._prop(name), float(value)))
            return accepted, float(self._cap.get(self._prop(name)))

    def _set_mode(self) -> None:
        """Ask for the pixel format, resolution and frame rate; refuse another resolution."""
        import cv2

        config = self.config
        code = cv2.VideoWriter_fourcc(*config.fourcc)
        _, fourcc = self._set("FOURCC", code)
        self._set("FRAME_WIDTH", config.width)
        self._set("FRAME_HEIGHT", config.height)
        _, fps = self._set("FPS", config.fps)
        with self._cap_lock:
            width = int(self._cap.get(self._prop("FRAME_WIDTH")))
            height = int(self._cap.get(self._prop("FRAME_HEIGHT")))
        self._check_size(width, height)
        if int(fourcc) != code:
            got = int(fourcc).to_bytes(4, "little").decode("ascii", "replace")
            _warn(self.device, f"pixel format {got!r} instead of {config.fourcc!r}; frames "
                  "may come slower")
        if abs(fps - config.fps) > 0.01 * config.fps:
            _warn(self.device, f"frame rate reads {fps:g} fps, not the {config.fps:g} asked for")

    def _check_size(self, width: int, height: int) -> None:
        """Refuse frames of another size than asked for, pixels."""
        if (width, height) != (self.config.width, self.config.height):
            raise CameraError(f"{self.device}: delivers {width} x {height} frames, not the "
                              f"{self.config.width} x {self.config.height} asked for; choose "
                              "a mode it offers (v4l2-ctl --list-formats-ext)")

    def _lock_exposure_and_focus(self) -> None:
        """Turn the automatics off at fixed values (asked for, or what the driver reports
        now), read them back, warn where the driver refused."""
        with self._cap_lock:
            exposure, focus = (self._cap.get(self._prop(name)) if value is None else value
                               for name, value in (("EXPOSURE", self.config.exposure),
                                                   ("FOCUS", self.config.focus)))
        self._lock("AUTO_EXPOSURE", _MANUAL_EXPOSURE, "EXPOSURE", exposure, "brightness")
        self._lock("AUTOFOCUS", 0.0, "FOCUS", focus, "sharpness")

    def _lock(self, auto: str, manual_mode: float, name: str, value: float,
              effect: str) -> None:
        """Switch property `auto` to `manual_mode` and set `name` to `value`; warn unless
        both read back as set."""
        took_mode, mode = self._set(auto, manual_mode)
        took, now = self._set(name, value)
        if not (took_mode and took and mode == manual_mode
                and abs(now - value) <= 1e-6 * max(1.0, abs(value))):
            _warn(self.device, f"the driver did not lock {name.lower()} (asked {value:g}, "
                  f"reads {now:g}; {auto.lower()} reads {mode:g}): views may differ in "
                  f"{effect}")

    def _load_intrinsics(self) -> Intrinsics:
        config = self.config
        if config.calibration is None:
            return estimated_intrinsics(config.width, config.height, config.hfov_deg,
                                        config.fps)
        calibrated = read_intrinsics(Path(config.calibration))
        if (calibrated.width, calibrated.height) != (config.width, config.height):
            raise InputError(config.calibration, f"calibrated at {calibrated.width} x "
                             f"{calibrated.height}, but the camera records {config.width} x "
                             f"{config.height}; calibrate at the recording resolution")
        return Intrinsics(calibrated.width, calibrated.height, calibrated.fx, calibrated.fy,
                          calibrated.cx, calibrated.cy, config.fps)

    def _capture_loop(self) -> None:
        """Take frames until closed; a camera silent for `frame_timeout_s` has failed."""
        last_frame = time.monotonic()
        while not self._closing.is_set():
            image = None
            with self._cap_lock:
                ok = bool(self._cap.grab())
                t = self._clock()
                if ok:
                    ok, image = self._cap.retrieve()
            if not ok or image is None:
                if time.monotonic() - last_frame > self.config.frame_timeout_s:
                    self._fail(CameraError(f"{self.device}: no frame for "
                                           f"{self.config.frame_timeout_s:g} s: the camera "
                                           "is busy, stalled or unplugged"))
                    return
                time.sleep(0.005)
                continue
            last_frame = time.monotonic()
            with self._state:
                self._latest = (image, t)
                recording = self._recording
                self._state.notify_all()
            if recording is not None:
                recording.offer(image, t)

    def _fail(self, error: CameraError) -> None:
        with self._state:
            if self._failure is None:
                self._failure = error
            self._state.notify_all()

    def _wait_frame(self) -> tuple[np.ndarray, float]:
        """The newest frame (BGR) and its bot-clock time, waiting for the first."""
        deadline = time.monotonic() + self.config.frame_timeout_s
        with self._state:
            while True:
                if self._failure is not None:
                    raise self._failure
                if self._latest is not None:
                    return self._latest
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    # Worded as the capture thread's own timeout, which may win the race.
                    raise CameraError(f"{self.device}: no frame for "
                                      f"{self.config.frame_timeout_s:g} s: the camera is "
                                      "busy, stalled or unplugged")
                self._state.wait(remaining)

    def intrinsics(self) -> dict[str, float]:
        return self._intrinsics.to_json()

    def frame(self) -> Frame:
        image, t = self._wait_frame()
        return Frame(np.ascontiguousarray(image[:, :, ::-1]), t)

    def choose_frames(self, choice: FrameChoice | None) -> None:
        """How the next recordings choose their frames (a bed's plants each have their own
        scan's duration); None: every frame is kept."""
        if self._recording is not None:
            raise CameraError(f"{self.device}: the frame choice cannot change while "
                              f"recording to {self._recording.folder}")
        self.config = replace(self.config, choose=choice)

    def start_recording(self, path: str | Path) -> None:
        if self._recording is not None:
            raise CameraError(f"{path}: already recording to {self._recording.folder}; stop "
                              "that recording first")
        self.check()
        scan_dir = Path(path).parent
        recording = _Recording(scan_dir, last_recorded(scan_dir)[0], self.config, self._fail)
        with self._state:
            # Started under the capture thread's lock: every frame stamped after the start
            # is offered to this recording, however long opening its files took.
            recording.begin(self._clock())
            self._recording = self._session = recording

    def stop_recording(self) -> Recording:
        if self._recording is None:
            raise CameraError("stop_recording: not recording; start a recording first")
        with self._state:
            recording, self._recording = self._recording, None
        recording.finish()
        if recording.dropped:
            _warn(self.device, f"dropped {recording.dropped} frames the disk or the processor "
                  "could not keep up with")
        self.check()
        return Recording(recording.folder, recording.start, self._clock(), self.config.fps,
                         recording.count)

    def recorded_until(self) -> float:
        session = self._session
        return session.recorded_until if session is not None else math.inf

    def saved_frames(self) -> list[tuple[int, float]]:
        session = self._session
        return session.take_saved() if session is not None else []

    def check(self) -> None:
        with self._state:
            if self._failure is not None:
                raise self._failure

    def close(self) -> None:
        if self._recording is not None:
            with self._state:
                recording, self._recording = self._recording, None
            recording.finish()
        self._closing.set()
        if self._thread is not None:
            # grab() returns within a frame interval, or the driver's own timeout.
            self._thread.join(timeout=self.config.frame_timeout_s + 1.0)
        with self._cap_lock:
            self._cap.release()

    def __enter__(self) -> UsbCamera:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class _Recording:
    """One recording session: a writer thread saving queued frames to `folder`/frames and
    their times to frame_times.csv, numbered from `first_index`."""

    def __init__(self, scan_dir: Path, first_index: int, config: UsbCameraConfig,
                 fail: Callable[[CameraError], None]):
        self.folder = scan_dir / "frames"
        self.folder.mkdir(parents=True, exist_ok=True)
        self.start = math.nan
        self.count = self.dropped = 0
        self._choose = config.choose
        self._keeper: FrameKeeper | None = None
        self._reserve = int(config.disk_reserve_mb * 1e6)
        self._next = first_index
        self._quality = config.jpeg_quality
        self._fail = fail
        self._queue: queue.Queue = queue.Queue(config.queue_frames)
        self._saved: list[tuple[int, float]] = []
        self._lock = threading.Lock()
        self.recorded_until = -math.inf
        """Bot-clock seconds before which every frame to keep is saved (`Camera`'s): it
        trails the queue and the keeper's open bin, and stops where a save failed."""
        self._times_file, self._times = open_rows(scan_dir / "frame_times.csv", ("frame", "t"))
        self._thread = threading.Thread(target=self._write_loop, name="usb-camera-writer",
                                        daemon=True)
        self._thread.start()

    def begin(self, start: float) -> None:
        """Start at bot-clock `start` (seconds), before the first frame is offered: the
        frame choice's bins count from it."""
        self.start = start
        if self._choose is not None:
            self._keeper = FrameKeeper(start, self._choose.duration_s, self._choose.bins,
                                       self._choose.keep)

    def offer(self, image: np.ndarray, t: float) -> None:
        """Queue a frame for saving; count it as dropped when the writer is behind."""
        try:
            self._queue.put_nowait((image, t))
        except queue.Full:
            self.dropped += 1

    def _write_loop(self) -> None:
        failed = False
        while (item := self._queue.get()) is not None:
            if failed:
                continue  # keep draining so the capture thread never blocks
            chosen = [item] if self._keeper is None else self._keeper.offer(*item)
            failed = not all(self._save(image, t) for image, t in chosen)
            if not failed:
                self.recorded_until = min(item[1], self._keeper.open_since
                                          if self._keeper is not None else math.inf)
        if not failed and (self._keeper is None
                           or all(self._save(image, t) for image, t in self._keeper.flush())):
            self.recorded_until = math.inf

    def _save(self, image: np.ndarray, t: float) -> bool:
        """Write one frame whole and its time; False (and the camera failed) when it
        cannot, or when it would leave less than the disk reserve."""
        import cv2

        path = self.folder / FRAME_PATTERN.format(self._next)
        try:
            ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, self._quality])
            if not ok:
                raise OSError("JPEG encoding failed")
            free = shutil.disk_usage(self.folder).free
            if free - len(jpeg) < self._reserve:
                self._fail(CameraError(
                    f"{self.folder}: the disk is nearly full ({free / 1e6:.0f} MB left, "
                    f"{self._reserve / 1e6:.0f} MB kept free): the recording stopped with "
                    f"{self.count} frames saved; free space, then run the scan again to "
                    "resume it"))
                return False
            write_bytes(path, jpeg.tobytes())  # whole and on disk before its row
            self._times.writerow((self._next, f"{t:.6f}"))
            self._times_file.flush()
            os.fsync(self._times_file.fileno())
        except (OSError, InputError) as err:
            self._fail(CameraError(f"{path}: cannot save the frame "
                                   f"({getattr(err, 'strerror', None) or err}); check the "
                                   "disk"))
            return False
        with self._lock:
            self._saved.append((self._next, t))
        self._next += 1
        self.count += 1
        return True

    def take_saved(self) -> list[tuple[int, float]]:
        with self._lock:
            saved, self._saved = self._saved, []
        return saved

    def finish(self) -> None:
        """Save what is queued, then stop the writer and close frame_times.csv."""
        self._queue.put(None)
        self._thread.join()
        self._times_file.close()
