"""The bot behind one interface: the gantry, the 2-DOF camera head and the camera.

Every backend (simulated on MuJoCo, serial Farmduino, FarmBot cloud) implements `Bot`, and
the scan executor sees nothing else. `KinematicBot` here is an in-memory bot on FarmBot's
motion profile and a simulated clock, for tests and for planning scans.

Contract
--------
Units and frames: the bed frame, SI units. A gantry position is a (3,) float64 array in
metres: x along the bed (FarmBot X), y across it, z up, z = 0 on the soil; it locates the
UTM bottom centre. Head angles are the geometric yaw and pitch, radians. hardware/geometry.py
defines both and converts them to FarmBot's millimetres (z running down from 0 at the top)
and servo degrees, which appear only inside backends. Times are seconds on the bot's clock,
`now()`, which frame timestamps and recordings use too.

Blocking: `move_to`, `home` and `set_head` return when the motion has finished (the gantry
arrived; the head had its settle time, as servos give no feedback) or raise; nothing is
queued. After a failure the gantry stays where it stopped: `position()` tells where.

Errors (flowerpose.hardware.bot_errors):
- `OutOfRangeError` (an InputError, the user's to fix) before anything moves: a target
  outside the travel limits, a head angle outside its limits, a speed fraction outside
  (0, 1], an unknown axis.
- `FirmwareError` subclasses for what the firmware reports: `EmergencyStopError` (an
  emergency stop ended the command), `StallError` (with `.axis`), `MoveTimeoutError`,
  `AbortedError`, ...; `LockedError` for any motion while locked after an emergency stop;
  `UnknownCommandError`, `NotConfiguredError`.
- `CommandTimeoutError` (no final reply in time), `ConnectionLostError` (the link dropped),
  `CameraError`; a plain `BotError` for use after `close()` or a second command while one
  runs.

Threads: one thread owns the bot and calls it one command at a time. `emergency_stop()` may
be called from any thread at any time, including while `move_to` blocks in the owner: it
returns promptly, the blocked command raises `EmergencyStopError`, and every later motion
raises `LockedError` until `unlock()`. `position()` and `now()` may be read from any
thread; they never raise for the lock. Servos lose their pulses on an emergency stop:
`unlock()` re-sends the head's last angles.

Lifecycle: `close()` releases the bot (port, link, renderer); a bot is a context manager
that closes on exit. After `close()`, `emergency_stop()` does nothing and the commands
(moves, head, unlock) raise `BotError`.
"""

from __future__ import annotations

import math
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from flowerpose.errors import InputError
from flowerpose.hardware.bot_errors import (
    BotError,
    CameraError,
    EmergencyStopError,
    LockedError,
    MoveTimeoutError,
    OutOfRangeError,
    error_for_code,
)
from flowerpose.hardware.geometry import PAPER_BOT, BotGeometry
from flowerpose.hardware.motion import (
    END_OF_MOVE_S,
    MotionProfile,
    axis_durations,
    axis_motions,
    move_trajectory,
)

_AXIS_NAMES = "xyz"


@dataclass(frozen=True)
class BotInfo:
    """What a bot is and what it can do (bed frame, SI units).

    name: the backend and device, for messages (e.g. "serial /dev/ttyACM0").
    firmware: the firmware version string (F83), None where there is none.
    travel_min, travel_max: gantry travel limits per axis, metres.
    yaw_limits, pitch_limits: geometric head angle limits, radians.
    motion: the motion profile the gantry moves with (read from the firmware where there
        is one).
    """

    name: str
    firmware: str | None
    travel_min: tuple[float, float, float]
    travel_max: tuple[float, float, float]
    yaw_limits: tuple[float, float]
    pitch_limits: tuple[float, float]
    motion: MotionProfile = field(default_factory=MotionProfile)

    @classmethod
    def from_geometry(cls, name: str, geometry: BotGeometry = PAPER_BOT,
                      firmware: str | None = None,
                      motion: MotionProfile | None = None) -> BotInfo:
        """The limits of a bot built as `geometry` (default: the paper's bot)."""
        return cls(name, firmware, tuple(map(float, geometry.gantry_min)),
                   tuple(map(float, geometry.gantry_max)), geometry.yaw_range_rad,
                   geometry.pitch_range_rad, motion or MotionProfile())

    @property
    def home(self) -> np.ndarray:
        """(3,) the home position, metres: min X, min Y and the top of Z."""
        return np.array([self.travel_min[0], self.travel_min[1], self.travel_max[2]])


@dataclass(frozen=True)
class Frame:
    """One camera image: `image` (H, W, 3) uint8 RGB, taken at `t_s` on the bot's clock."""

    image: np.ndarray
    t_s: float


@dataclass(frozen=True)
class Recording:
    """A finished video recording: frame i was taken at `start_s + i / fps` (bot's clock,
    seconds) until `stop_s`; `frames` is the number written."""

    path: Path
    start_s: float
    stop_s: float
    fps: float
    frames: int


class Camera(ABC):
    """The head's camera. Methods block until done and raise CameraError on a fault."""

    @abstractmethod
    def intrinsics(self) -> dict[str, float]:
        """Pinhole intrinsics of the images: width, height (pixels), fx, fy, cx, cy
        (pixels; x right, y down, the centre of the top-left pixel at (0, 0))."""

    @abstractmethod
    def frame(self) -> Frame:
        """The newest image, with its time."""

    @abstractmethod
    def start_recording(self, path: str | Path) -> None:
        """Start recording video to `path`."""

    @abstractmethod
    def stop_recording(self) -> Recording:
        """Stop recording; the video is complete at `Recording.path` on return."""

    def recorded_until(self) -> float:
        """Bot-clock seconds before which every frame this recording keeps is on disk with
        its pose, so a power cut now loses nothing taken earlier: what a scan may call done.
        This default is for cameras that write each frame, whole, as they take it."""
        return math.inf


class Bot(ABC):
    """A FarmBot-like bot: see the module docstring for the contract."""

    @property
    @abstractmethod
    def info(self) -> BotInfo:
        """Name, firmware, limits and motion profile."""

    @property
    @abstractmethod
    def camera(self) -> Camera:
        """The camera on the head."""

    @abstractmethod
    def now(self) -> float:
        """Seconds on the bot's clock (monotonic; simulated in simulated backends)."""

    @abstractmethod
    def move_to(self, xyz, speed_fraction: float = 1.0) -> None:
        """Move the gantry to `xyz` ((3,) metres, bed frame) and return on arrival.

        speed_fraction: (0, 1], the fraction of each axis's maximum speed, sent as G00's
        speed override (firmware 6.6 applies it to moves away from home only).
        """

    @abstractmethod
    def home(self, axes: str = "xyz") -> None:
        """Find home on `axes` (any of "x", "y", "z"; Z first): min X, min Y, top of Z."""

    @abstractmethod
    def position(self) -> np.ndarray:
        """(3,) the gantry's last known position, metres, bed frame."""

    @abstractmethod
    def emergency_stop(self) -> None:
        """Stop everything now and lock; safe from any thread at any time."""

    @abstractmethod
    def unlock(self) -> None:
        """Release the lock of an emergency stop and re-send the head's angles."""

    @abstractmethod
    def set_head(self, yaw_rad: float, pitch_rad: float) -> None:
        """Turn the head to (yaw, pitch) radians and return once it has settled."""

    @abstractmethod
    def head(self) -> tuple[float, float]:
        """(yaw, pitch) radians last set."""

    def dwell(self, seconds: float) -> None:
        """Stay still for `seconds` on the bot's clock while the camera records: the pause at
        a waypoint while the autofocus settles. A physical bot sleeps; simulated bots advance
        their clock."""
        time.sleep(max(0.0, float(seconds)))

    @abstractmethod
    def close(self) -> None:
        """Release the bot; calling it again does nothing."""

    def __enter__(self) -> Bot:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def check_target(info: BotInfo, xyz) -> np.ndarray:
    """`xyz` as a (3,) float64 array, metres, after checking it is finite and inside the
    travel limits; OutOfRangeError otherwise."""
    target = np.asarray(xyz, dtype=np.float64)
    if target.shape != (3,) or not np.all(np.isfinite(target)):
        raise OutOfRangeError(f"{info.name} target", f"need 3 finite coordinates (m), got {xyz!r}")
    for i, name in enumerate(_AXIS_NAMES):
        low, high = info.travel_min[i], info.travel_max[i]
        if not low - 1e-9 <= target[i] <= high + 1e-9:
            raise OutOfRangeError(f"{info.name} target", f"{name} = {target[i]:.4f} m is outside "
                                  f"the travel {low:.4f}..{high:.4f} m")
    return target


def check_head(info: BotInfo, yaw_rad: float, pitch_rad: float) -> tuple[float, float]:
    """(yaw, pitch) as floats after checking them against the head limits."""
    angles = (float(yaw_rad), float(pitch_rad))
    for name, value, (low, high) in zip(("yaw", "pitch"), angles,
                                        (info.yaw_limits, info.pitch_limits), strict=True):
        if not (math.isfinite(value) and low - 1e-12 <= value <= high + 1e-12):
            raise OutOfRangeError(f"{info.name} head", f"{name} = {value!r} rad is outside "
                                  f"{low:.4f}..{high:.4f} rad")
    return angles


def check_axes(axes: str) -> str:
    """The axes named in `axes` in homing order (z, y, x); OutOfRangeError for anything
    else or none."""
    if not axes or set(axes) - set(_AXIS_NAMES):
        raise OutOfRangeError("home axes", f"need some of 'x', 'y', 'z', got {axes!r}")
    return "".join(name for name in "zyx" if name in axes)


class SolidCamera(Camera):
    """A camera that sees one solid colour: the in-memory bot's camera.

    clock: the bot's clock for timestamps. Default intrinsics: the IMX219's 1280x720 video
    (62.2 degrees horizontal field of view) at half size, 640x360. Recordings are written
    when stopped, a solid frame every 1 / fps seconds of the bot's clock, as .mp4 (mp4v)
    or .avi (MJPG).
    """

    def __init__(self, clock: Callable[[], float], width: int = 640, height: int = 360,
                 hfov_deg: float = 62.2, fps: float = 30.0,
                 rgb: tuple[int, int, int] = (90, 140, 60)):
        self._clock = clock
        self._width, self._height, self._fps = int(width), int(height), float(fps)
        self._f = 0.5 * width / math.tan(math.radians(hfov_deg) / 2)
        self._rgb = np.asarray(rgb, dtype=np.uint8)
        self._recording: tuple[Path, float] | None = None

    def intrinsics(self) -> dict[str, float]:
        return {"width": self._width, "height": self._height, "fx": self._f, "fy": self._f,
                "cx": self._width / 2, "cy": self._height / 2}

    def _image(self) -> np.ndarray:
        return np.broadcast_to(self._rgb, (self._height, self._width, 3)).copy()

    def frame(self) -> Frame:
        return Frame(self._image(), self._clock())

    def start_recording(self, path: str | Path) -> None:
        path = Path(path)
        if path.suffix.lower() not in (".mp4", ".avi"):
            raise InputError(path, "a video needs the suffix .mp4 or .avi")
        if self._recording is not None:
            raise CameraError(f"{path}: already recording to {self._recording[0]}; "
                              "stop that recording first")
        self._recording = (path, self._clock())

    def recorded_until(self) -> float:
        """Nothing while recording: the video is written when it stops."""
        return -math.inf if self._recording is not None else math.inf

    def stop_recording(self) -> Recording:
        import cv2

        if self._recording is None:
            raise CameraError("stop_recording: not recording; start a recording first")
        (path, start), stop = self._recording, self._clock()
        self._recording = None
        frames = int(math.floor((stop - start) * self._fps + 1e-9)) + 1
        codec = "mp4v" if path.suffix.lower() == ".mp4" else "MJPG"
        path.parent.mkdir(parents=True, exist_ok=True)
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*codec), self._fps,
                                 (self._width, self._height))
        if not writer.isOpened():
            raise CameraError(f"{path}: cannot write a video there; check the folder")
        image = np.ascontiguousarray(self._image()[:, :, ::-1])
        for _ in range(frames):
            writer.write(image)
        writer.release()
        return Recording(path, start, stop, self._fps, frames)


@dataclass(frozen=True)
class _Activity:
    """A command in progress since `real0` (wall clock, time.monotonic) for `duration`
    simulated seconds; a gantry move when `profile` is set."""

    real0: float
    duration: float
    start: np.ndarray | None = None
    end: np.ndarray | None = None
    profile: MotionProfile | None = None


@dataclass(frozen=True)
class Activity:
    """What a simulated bot just did, for observers such as a simulated camera.

    kind: "move", "head" or "dwell". t0: bot-clock seconds at its start; elapsed: seconds it
    lasted (less than planned when a fault or an emergency stop cut it short). A move
    follows `move_trajectory(t - t0, gantry_start, gantry_end, profile)`; the gantry is
    still otherwise. head_start / head_end: (yaw, pitch) radians before and after.
    """

    kind: str
    t0: float
    elapsed: float
    gantry_start: np.ndarray
    gantry_end: np.ndarray
    head_start: tuple[float, float]
    head_end: tuple[float, float]
    profile: MotionProfile | None = None


class KinematicBot(Bot):
    """An in-memory bot: the gantry follows FarmBot's motion profile (`motion.py`) on a
    simulated clock, the head settles in `head_settle_s`, the camera sees a solid colour.

    info: limits and motion profile; default the paper's bot
        (`BotInfo.from_geometry("kinematic")`), at home at the start.
    head_settle_s: simulated seconds `set_head` takes.
    camera: makes the camera from the bot's clock; default `SolidCamera` (pass e.g.
        `functools.partial(SolidCamera, width=64, height=48)` for another one).
    observer: called with an `Activity` after every move, head turn and dwell, from the
        thread that commanded it (a simulated camera renders what happened from it).
    time_scale: wall seconds per simulated second that commands block for. 0 (default)
        completes them at once; a positive scale makes them take real time so that
        `emergency_stop()` from another thread can land in the middle of a move.
    Faults: `fail_next_move` makes the next gantry command stop part way with an error,
    as the firmware would. Moves longer than an axis's firmware timeout stop at the
    timeout with MoveTimeoutError, as the firmware does.
    Homing moves each named axis, Z first, to its home coordinate on the motion profile
    (a real bot's F11-F13 also ends slowly against the endstop).
    """

    def __init__(self, info: BotInfo | None = None, *, time_scale: float = 0.0,
                 head_settle_s: float = 0.5,
                 camera: Callable[[Callable[[], float]], Camera] = SolidCamera,
                 observer: Callable[[Activity], None] | None = None):
        self._info = info or BotInfo.from_geometry("kinematic")
        self._observer = observer
        self._time_scale = float(time_scale)
        self._settle_s = float(head_settle_s)
        self._camera = camera(self.now)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._t = 0.0
        self._xyz = self._info.home
        self._head = (0.0, 0.0)
        self._activity: _Activity | None = None
        self._locked = self._closed = False
        self._fault: tuple[BotError | int, float] | None = None

    @property
    def info(self) -> BotInfo:
        return self._info

    @property
    def camera(self) -> Camera:
        return self._camera

    def _elapsed(self, activity: _Activity) -> float:
        """Simulated seconds of `activity` done so far (none yet when not time-scaled)."""
        if self._time_scale <= 0:
            return 0.0
        return min(activity.duration, (time.monotonic() - activity.real0) / self._time_scale)

    def now(self) -> float:
        with self._lock:
            activity = self._activity
            return self._t + (self._elapsed(activity) if activity else 0.0)

    def position(self) -> np.ndarray:
        with self._lock:
            activity = self._activity
            if activity is None or activity.profile is None:
                return self._xyz.copy()
            return move_trajectory([self._elapsed(activity)], activity.start, activity.end,
                                   activity.profile)[0]

    def head(self) -> tuple[float, float]:
        return self._head

    def fail_next_move(self, error: BotError | int, at_fraction: float = 0.5) -> None:
        """Make the next gantry command (move_to, or home's first axis) stop after
        `at_fraction` (0..1) of its duration and raise `error`: a BotError, or an R03 code
        turned into its error (31 is a stall on X, 1 an emergency stop that also locks)."""
        if not 0.0 <= at_fraction <= 1.0:
            raise OutOfRangeError("at_fraction", f"must be in [0, 1], got {at_fraction!r}")
        self._fault = (error, float(at_fraction))

    def _begin(self, command: str) -> None:
        """Refuse `command` unless the bot is open, idle and unlocked (lock held)."""
        if self._closed:
            raise BotError(f"{command}: {self._info.name} is closed; open a new bot")
        if self._activity is not None:
            raise BotError(f"{command}: {self._info.name} is busy with another command; "
                           "send one command at a time")
        if self._locked:
            raise LockedError(command)

    def _run(self, activity: _Activity) -> tuple[float, bool]:
        """Let `activity` happen: (simulated seconds it lasted, whether an emergency stop
        cut it short). It is registered as in progress until the caller clears it."""
        if self._time_scale > 0:
            stopped = self._stop.wait(activity.duration * self._time_scale)
        else:
            stopped = self._stop.is_set()
        with self._lock:
            return (self._elapsed(activity) if stopped else activity.duration), stopped

    def _move(self, target: np.ndarray, profile: MotionProfile, command: str) -> None:
        """One gantry command from the current position to `target` (checked)."""
        with self._lock:
            self._begin(command)
            start = self._xyz.copy()
            fault, self._fault = self._fault, None
            durations = axis_durations(start, target, profile)
            axes = axis_motions(start, target, profile)
            stop_at, error = float(durations.max()), None
            late = [i for i in range(3) if durations[i] > axes[i].timeout_s]
            if late:
                first = min(late, key=lambda i: axes[i].timeout_s)
                stop_at = axes[first].timeout_s
                error = MoveTimeoutError(command, 2, axis=_AXIS_NAMES[first])
            if fault is not None and fault[1] * durations.max() <= stop_at:
                injected, fraction = fault
                stop_at = fraction * float(durations.max())
                if isinstance(injected, BotError):
                    error = injected
                else:
                    error = error_for_code(injected, command)
            # A move that arrives ends as the firmware's do: END_OF_MOVE_S at the target.
            ending = END_OF_MOVE_S if error is None else 0.0
            activity = _Activity(time.monotonic(), stop_at + ending, start, target, profile)
            self._activity = activity
        elapsed, stopped = self._run(activity)
        with self._lock:
            t0 = self._t
            self._xyz = move_trajectory([elapsed], start, target, profile)[0]
            self._t += elapsed
            self._activity = None
            if stopped:
                error = EmergencyStopError(command, 1)
            if isinstance(error, EmergencyStopError):
                self._locked = True
        self._notify(Activity("move", t0, elapsed, start, target, self._head, self._head,
                              profile))
        if error is not None:
            raise error

    def _notify(self, activity: Activity) -> None:
        if self._observer is not None:
            self._observer(activity)

    def _still(self, kind: str, command: str, seconds: float,
               head_end: tuple[float, float] | None = None) -> None:
        """A command that leaves the gantry still for `seconds`: a head turn or a dwell."""
        with self._lock:
            self._begin(command)
            head_start = self._head
            if head_end is not None:
                self._head = head_end
            self._activity = _Activity(time.monotonic(), seconds)
            activity = self._activity
        elapsed, stopped = self._run(activity)
        with self._lock:
            t0 = self._t
            self._t += elapsed
            self._activity = None
            if stopped:
                self._locked = True
        self._notify(Activity(kind, t0, elapsed, self._xyz.copy(), self._xyz.copy(),
                              head_start, self._head))
        if stopped:
            raise EmergencyStopError(command, 1)

    def dwell(self, seconds: float) -> None:
        self._still("dwell", f"dwell({seconds:.3f})", max(0.0, float(seconds)))

    def move_to(self, xyz, speed_fraction: float = 1.0) -> None:
        target = check_target(self._info, xyz)
        profile = self._info.motion.at_speed(speed_fraction)
        x, y, z = target
        self._move(target, profile, f"move_to({x:.4f}, {y:.4f}, {z:.4f})")

    def home(self, axes: str = "xyz") -> None:
        for name in check_axes(axes):
            i = _AXIS_NAMES.index(name)
            target = self.position()
            target[i] = self._info.home[i]
            self._move(target, self._info.motion, f"home({name})")

    def emergency_stop(self) -> None:
        with self._lock:
            if not self._closed:
                self._locked = True
                self._stop.set()

    def unlock(self) -> None:
        with self._lock:
            if self._closed:
                raise BotError(f"unlock: {self._info.name} is closed; open a new bot")
            self._locked = False
            self._stop.clear()

    def set_head(self, yaw_rad: float, pitch_rad: float) -> None:
        angles = check_head(self._info, yaw_rad, pitch_rad)
        self._still("head", f"set_head({angles[0]:.4f}, {angles[1]:.4f})", self._settle_s,
                    head_end=angles)

    def close(self) -> None:
        with self._lock:
            self._closed = True
            # A command still running ends now, as an emergency stop would end it.
            self._stop.set()
