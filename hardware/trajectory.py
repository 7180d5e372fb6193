"""Where the camera was when each frame was taken: the bot's Activities -> trajectory.csv rows.

A bot reports every move, head turn and dwell as an `Activity` (bot.py) on its own clock. The
gantry follows FarmBot's motion profile during a move, the head turns at servo speed from
the start of a head activity, and between activities nothing moves. `pose_at` gives the
gantry and head angles at any time within one activity; `Timeline` does it for any time of a
whole session; `camera_poses` turns them into the camera's pose as the servos take it. The
simulated camera (sim_bot.py) and `TrajectoryRecorder`, which pairs a real camera's frame
timestamps with a bot's Activities, both use these.

A recorded scan folder (flowerpose/scanio.py) holds frames/frame_NNNNNN.jpg and one
trajectory.csv row per frame whose pose is known, written after its image. A resumed
recording continues after the highest frame index on disk (`last_recorded`), so nothing
recorded is overwritten, and its times continue after the last recorded time.

Frames and units: bed frame, metres, radians, seconds on the bot's clock (trajectory.csv's
`t` counts from the start of the scan's first session instead).
"""

from __future__ import annotations

import math
import os
import threading
from abc import abstractmethod
from collections.abc import Callable
from pathlib import Path

import numpy as np

from flowerpose.hardware.bot import Activity, Camera, Frame, Recording
from flowerpose.hardware.geometry import PAPER_BOT, BotGeometry
from flowerpose.hardware.kinematics import HeadPose, forward, joint_positions
from flowerpose.hardware.motion import move_trajectory
from flowerpose.scanio import TRAJECTORY_COLUMNS, open_rows, trajectory_row

SERVO_SPEED_RAD_S = 6.0
"""Head turning speed, radians per second (35 kg servos: about 0.17 s per 60 degrees)."""


def head_turn_time(activity: Activity, servo_speed_rad_s: float = SERVO_SPEED_RAD_S) -> float:
    """Seconds the head turns at the start of a "head" activity: the larger angle change at
    servo speed, at most the activity's duration; the whole activity when the start angles
    are unknown (NaN: after connecting or an emergency stop, servos give no feedback)."""
    start = np.asarray(activity.head_start, np.float64)
    end = np.asarray(activity.head_end, np.float64)
    if not np.all(np.isfinite(start)):
        return activity.elapsed
    return min(float(np.abs(end - start).max()) / servo_speed_rad_s, activity.elapsed)


def pose_at(activity: Activity, t, servo_speed_rad_s: float = SERVO_SPEED_RAD_S
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gantry and head angles during `activity` at times `t`.

    t: (T,) seconds on the bot's clock; times before the activity give its start state,
    times after it the state it ended in (where a cut-short move stopped).
    Returns gantry (T, 3) metres, bed frame, and yaw, pitch (T,) radians; angles are NaN
    while a turn from unknown angles is under way.
    """
    t = np.atleast_1d(np.asarray(t, np.float64))
    local = np.clip(t - activity.t0, 0.0, activity.elapsed)
    start = np.asarray(activity.head_start, np.float64)
    end = np.asarray(activity.head_end, np.float64)
    if activity.kind == "move":
        gantry = move_trajectory(local, activity.gantry_start, activity.gantry_end,
                                 activity.profile)
        head = np.broadcast_to(start, (len(t), 2))
    else:
        gantry = np.broadcast_to(np.asarray(activity.gantry_end, np.float64), (len(t), 3))
        if activity.kind == "head":
            turn = head_turn_time(activity, servo_speed_rad_s)
            f = np.ones_like(local) if turn <= 0 else np.minimum(local / turn, 1.0)
            # Exactly the end angles once turned (also when the start is unknown).
            head = np.where(f[:, None] >= 1.0, end, start + f[:, None] * (end - start))
        else:
            head = np.broadcast_to(end, (len(t), 2))
    return np.array(gantry), head[:, 0].copy(), head[:, 1].copy()


def camera_poses(gantry, yaw, pitch, geometry: BotGeometry = PAPER_BOT
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Camera pose of head poses as the servos take them (a yaw beyond the yaw servo's reach
    by upstream's flip, which turns the image by 180 degrees), as MuJoCo's model poses it.

    gantry: (N, 3) metres, bed frame; yaw, pitch: (N,) radians. Returns positions (N, 3),
    metres, bed frame, and camera-to-bed rotations (N, 3, 3), OpenCV camera axes.
    """
    pose = HeadPose(np.atleast_2d(gantry), yaw, pitch)
    taken = joint_positions(pose, geometry)
    return forward(HeadPose(pose.gantry, taken[:, 3], taken[:, 4]), geometry)


class Timeline:
    """A bot's Activities of one session, in the order they happened; pass `add` to the bot
    as its observer (it is safe to call from the bot's thread while another reads)."""

    def __init__(self, servo_speed_rad_s: float = SERVO_SPEED_RAD_S):
        self._servo_speed = float(servo_speed_rad_s)
        self._activities: list[Activity] = []
        self._lock = threading.Lock()

    def add(self, activity: Activity) -> None:
        with self._lock:
            self._activities.append(activity)

    def __len__(self) -> int:
        return len(self._activities)

    def activities(self) -> list[Activity]:
        """The activities so far, in the order they happened."""
        with self._lock:
            return list(self._activities)

    @property
    def end(self) -> float:
        """Bot-clock seconds up to which the timeline is known (-inf when empty)."""
        with self._lock:
            return max((a.t0 + a.elapsed for a in self._activities), default=-math.inf)

    def poses(self, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Gantry (T, 3) metres and yaw, pitch (T,) radians at bot-clock times t (T,).

        A time falls to the latest activity started by then (its end state once it is
        over); times before the first activity take its start state. Needs at least one
        activity.
        """
        t = np.atleast_1d(np.asarray(t, np.float64))
        with self._lock:
            activities = list(self._activities)
        if not activities:
            raise ValueError("Timeline.poses: no activity yet")
        starts = np.array([a.t0 for a in activities])
        owner = np.maximum(np.searchsorted(starts, t, side="right") - 1, 0)
        gantry = np.empty((len(t), 3))
        yaw, pitch = np.empty(len(t)), np.empty(len(t))
        for k in np.unique(owner):
            rows = owner == k
            gantry[rows], yaw[rows], pitch[rows] = pose_at(activities[k], t[rows],
                                                           self._servo_speed)
        return gantry, yaw, pitch


def last_recorded(scan_dir: Path) -> tuple[int, float | None]:
    """(index for the next frame, time of the last trajectory row) of a scan folder: the
    next index follows both the last trajectory row and the highest frame image (an image
    whose row an interruption cut off is kept, not overwritten). (0, None) when empty."""
    scan_dir = Path(scan_dir)
    next_index, last_t = 0, None
    path = scan_dir / "trajectory.csv"
    if path.exists():
        with open(path) as handle:
            rows = [line for line in handle if line.strip()][1:]
        complete = [row.split(",") for row in rows if row.endswith("\n")
                    and len(row.split(",")) == len(TRAJECTORY_COLUMNS)]
        if complete:
            next_index, last_t = int(complete[-1][0]) + 1, float(complete[-1][1])
    images = [int(p.stem.split("_")[-1]) for p in (scan_dir / "frames").glob("frame_*.jpg")
              if p.stem.split("_")[-1].isdigit()]
    return max([next_index, *(i + 1 for i in images)]), last_t


class TrajectoryWriter:
    """Appends rows to a scan folder's trajectory.csv (the header when it is new) and
    flushes after each batch. A row cut off by an interruption is dropped first, so the
    file stays readable."""

    def __init__(self, path: Path, geometry: BotGeometry = PAPER_BOT):
        self.path = Path(path)
        self._geometry = geometry
        self._file, self._csv = open_rows(self.path, TRAJECTORY_COLUMNS)

    def write(self, frames, t, gantry, yaw, pitch) -> int:
        """Append one row per frame whose pose is known (finite); returns the rows written.

        frames: (N,) indices; t: (N,) seconds since the scan started; gantry (N, 3) metres,
        bed frame; yaw, pitch (N,) radians.
        """
        gantry = np.atleast_2d(np.asarray(gantry, np.float64))
        yaw, pitch = np.asarray(yaw, np.float64), np.asarray(pitch, np.float64)
        if len(gantry) == 0:
            return 0
        positions, rotations = camera_poses(gantry, yaw, pitch, self._geometry)
        known = np.isfinite(gantry).all(1) & np.isfinite(yaw) & np.isfinite(pitch)
        for k in np.flatnonzero(known):
            self._csv.writerow(trajectory_row(int(frames[k]), float(t[k]), gantry[k],
                                              float(yaw[k]), float(pitch[k]), positions[k],
                                              rotations[k]))
        self._file.flush()
        os.fsync(self._file.fileno())  # the rows on disk, as the frames they describe are
        return int(known.sum())

    def close(self) -> None:
        self._file.close()


class RecordingCamera(Camera):
    """A camera that saves every recorded frame to the scan folder as it comes:
    `start_recording(path)` records into path's folder, frames/frame_NNNNNN.jpg from
    `last_recorded(folder)`'s index on, with the times the frames were taken."""

    @abstractmethod
    def saved_frames(self) -> list[tuple[int, float]]:
        """(index, bot-clock seconds) of the frames saved since the last call, in order."""

    @abstractmethod
    def check(self) -> None:
        """Raise CameraError when the camera has stopped delivering or saving frames."""

    def close(self) -> None:
        """Release the device; calling it again does nothing."""


class TrajectoryRecorder(Camera):
    """A recording camera plus the bot's Activities: writes a trajectory.csv row for every
    frame the camera saves, once the bot has reported what it did at that time.

    Give the bot `recorder.bind` as its camera factory and `recorder.observe` as its
    observer:

        recorder = TrajectoryRecorder(lambda clock: UsbCamera(device, clock))
        bot = FarmbotCloudBot(camera=recorder.bind, observer=recorder.observe)

    camera: makes the recording camera from the bot's clock. A frame's row is written when
    an activity reported after it shows where the camera was (at the latest when the
    recording stops: the bot stood still since its last activity). Frames taken while the
    head's angles are unknown get no row; the pipeline skips frames without one. A camera
    that failed raises its CameraError from `observe`, so the bot's command raises it and an
    interrupted scan can resume.
    """

    def __init__(self, camera: Callable[[Callable[[], float]], RecordingCamera], *,
                 servo_speed_rad_s: float = SERVO_SPEED_RAD_S,
                 geometry: BotGeometry = PAPER_BOT):
        self._make = camera
        self._geometry = geometry
        self._timeline = Timeline(servo_speed_rad_s)
        self._camera: RecordingCamera | None = None
        self._clock: Callable[[], float] | None = None
        self._writer: TrajectoryWriter | None = None
        self._pending: list[tuple[int, float]] = []
        self._offset = 0.0
        self._rows_until = math.inf
        self.rows = 0
        """trajectory.csv rows written in this session."""

    def bind(self, clock: Callable[[], float]) -> TrajectoryRecorder:
        """Make the camera on the bot's clock; returns the recorder (a bot's camera factory)."""
        self._clock = clock
        self._camera = self._make(clock)
        return self

    @property
    def camera(self) -> RecordingCamera:
        if self._camera is None:
            raise RuntimeError("TrajectoryRecorder: bind it to a bot's clock first")
        return self._camera

    def observe(self, activity: Activity) -> None:
        """Take a bot's activity; write the rows of the frames it accounts for."""
        self._timeline.add(activity)
        if self._writer is not None:
            self._flush(self._timeline.end)
            self.camera.check()

    def intrinsics(self) -> dict[str, float]:
        return self.camera.intrinsics()

    def frame(self) -> Frame:
        return self.camera.frame()

    def recorded_until(self) -> float:
        """Frames are on disk with their rows up to the camera's saved frames as of the
        latest batch of rows, and the bot's activities reported by then."""
        return self._rows_until

    def start_recording(self, path: str | Path) -> None:
        scan_dir = Path(path).parent
        scan_dir.mkdir(parents=True, exist_ok=True)
        _, last_t = last_recorded(scan_dir)
        fps = float(self.camera.intrinsics().get("fps", 30.0))
        start = self._clock()
        # trajectory.csv's t counts from the scan's start; a resumed session continues it.
        self._offset = (0.0 if last_t is None else last_t + 1.0 / fps) - start
        self.camera.start_recording(path)
        self._pending, self.rows, self._rows_until = [], 0, -math.inf
        self._writer = TrajectoryWriter(scan_dir / "trajectory.csv", self._geometry)

    def stop_recording(self) -> Recording:
        if self._writer is None:
            return self.camera.stop_recording()
        try:
            return self.camera.stop_recording()
        finally:
            try:
                self._flush(math.inf)
            finally:
                self._writer.close()
                self._writer = None

    def _flush(self, until: float) -> None:
        """Write the rows of the saved frames taken up to `until` (bot clock)."""
        saved_before = self.camera.recorded_until()  # first: those frames are in the list
        self._pending += self.camera.saved_frames()
        if not len(self._timeline):
            return
        if self._pending:
            times = np.array([t for _, t in self._pending])
            ready = int(np.searchsorted(times, until, side="right"))
            if ready:
                frames = np.array([index for index, _ in self._pending[:ready]])
                gantry, yaw, pitch = self._timeline.poses(times[:ready])
                self.rows += self._writer.write(frames, times[:ready] + self._offset, gantry,
                                                yaw, pitch)
                self._pending = self._pending[ready:]
        self._rows_until = max(self._rows_until, min(saved_before, until))

    def close(self) -> None:
        """Stop a recording still running and release the camera."""
        if self._camera is None:
            return
        try:
            if self._writer is not None:
                self.stop_recording()
        finally:
            self._camera.close()
