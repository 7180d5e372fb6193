"""The serial Farmduino backend: the bot on FarmBot's own firmware over USB serial (pyserial).

`FarmduinoBot` speaks the Farmduino protocol (docs/guides/physical-bot.md, "The wire
protocol") defensively:

- One command at a time, each with a Q number (1-999, cycling), sent once the previous one
  got its final reply: `R02` done, or `R03 V<code>` (a typed error from `error_for_code`),
  `R09` (unknown), `R87` (locked), `R88` (not configured), the refusals that come without
  an `R03`. Everything else (echo, busy, idle, position reports, debug text, line noise) is
  read and set aside. The firmware discards input that arrives while a command runs, so
  nothing else is sent meanwhile but the emergency stop.
- Numbers in fixed point ("%.2f"): the firmware takes any `e` or `E` byte as an emergency
  stop, so no line but the emergency stop itself may hold one (`protocol.checked_line`).
  Every G00 names all three axes (a missing axis means 0). Servo angles are whole degrees,
  as the firmware reads them, on pins 6 (yaw) and 5 (pitch) only.
- At connect: wait for `R99 ARDUINO TEXT COMPLETE` (opening the port resets the board)
  or an idle report, read the version (F83) and the parameters the motion model needs
  (F21: 11-13 timeouts, 41-44 ramps, 55-57 steps/mm, 61-64 and 71-74 speeds, 5 retries,
  141-143 axis lengths), approve the configuration (`F22 P2 V1`) when the firmware has not,
  re-send the servo angles, read the position (F82). The gantry moves on
  `MotionProfile.from_firmware` of these parameters, the travel is cut to the calibrated
  axis lengths, and command timeouts follow the firmware's own: a move may last its
  axes' timeout (parameters 11-13) for each of its attempts (parameter 5) plus
  `MOVE_SLACK_S`; anything else gets `REPLY_TIMEOUT_S`.
- The position: a board that starts counts from 0 wherever the gantry stands, so after
  connecting `move_to` refuses (`PositionLostError`) until `home()` has found home on all
  three axes (Z first).
- Homing that cannot hang: an axis whose parameters (read at connect) enable neither its
  endstops (25-27) nor its encoder (101-103) is refused in one line before anything moves
  (`HomingError`): the firmware would drive it into the frame, time out, back off and try
  again for good. A homing the firmware reports as timed out (R71-R73) or displaced is
  aborted at once (`@`, then `E` if that goes unanswered) and fails with that reason.
  `home_here()` takes where the gantry stands for home (F84, for a bot put there by hand).
- The bot's own settings: without FarmBot OS nobody writes them, and a board that starts
  runs on its defaults unless they were stored in EEPROM; `settings` (the web app's export,
  `protocol.read_settings`) are written after every start and read back, and one
  that did not take fails the connect.
- A dropped port (SerialException, EIO) is recovered: the same path is reopened with
  backoff for up to `connect_timeout_s`, the firmware brought up again as at connect,
  homed when the reopening restarted the board (Z first, away from the plant), and the
  interrupted command sent again, so a scan goes on where it was. A board that restarts
  while the port stays open (a brown-out, a watchdog) is not retried: the command raises
  `PositionLostError` for a person to look at the bot, then `home()`.
- `emergency_stop()` may be called from any thread at any time: it writes `E` at once,
  under the write lock; the command blocked in the owner thread raises
  `EmergencyStopError`; motion raises `LockedError` until `unlock()` (F09), which re-sends
  the servo angles (the firmware cuts their pulses). The firmware's stop takes time: it
  answers `R87` at once but goes on reporting while it stops and ends with `R03 V1` about
  a quarter of a second later, discarding every byte before that. So after an `E` the
  `R87` of the stopped command is not its final reply, the position is the last report
  before the `R03`, and nothing is sent until the stop has ended (`R03`, or an idle
  report; `STOP_SETTLE_S` at most).

The observer gets an `Activity` for every move, head turn and dwell as `KinematicBot`
gives one: a move follows `move_trajectory(t - t0, start, target, profile)` with the
profile from the firmware's parameters, `elapsed` measured on the bot's clock until the
final reply. The bot's clock is the wall clock times `clock_scale` (1 for a real bot).

Units: the `Bot` interface is SI in the bed frame; millimetres, steps and servo degrees
appear only in the lines this module sends and reads (geometry.py converts).
"""

from __future__ import annotations

import contextlib
import functools
import math
import queue
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from flowerpose.errors import InputError
from flowerpose.hardware.backends.farmduino_connection import (
    MAX_RECOVERIES,
    REPLY_TIMEOUT_S,
    BoardStarted,
    Connection,
)
from flowerpose.hardware.backends.serial_link import Dropped, LinkDropped, SerialLink
from flowerpose.hardware.bot import (
    Activity,
    Bot,
    BotInfo,
    Camera,
    check_axes,
    check_head,
    check_target,
)
from flowerpose.hardware.bot_errors import (
    BotError,
    CameraError,
    CommandTimeoutError,
    ConnectionLostError,
    EmergencyStopError,
    HomingError,
    LockedError,
    NotConfiguredError,
    PositionLostError,
    UnknownCommandError,
    error_for_code,
)
from flowerpose.hardware.geometry import (
    PITCH_PIN,
    YAW_PIN,
    bed_to_farmbot_mm,
    farmbot_mm_to_bed,
)
from flowerpose.hardware.kinematics import HeadPose, from_servo_commands, servo_commands
from flowerpose.hardware.motion import MotionProfile, move_trajectory
from flowerpose.hardware.protocol import (
    ABORT,
    DONE,
    EMERGENCY_STOP,
    ENCODERS,
    ENDSTOPS,
    ERROR,
    FINAL_REPLIES,
    HOME_LINES,
    HOMING_TIMEOUTS,
    IDLE,
    LOCKED,
    MOVEMENT_RETRIES,
    NOT_CONFIGURED,
    POSITION,
    STARTUP_TEXT,
    TEXT,
    UNLOCK_LINE,
    ZERO_LINE,
    Reply,
    checked_line,
    describe,
    move_line,
    parse_reply,
    servo_line,
)

MOVE_SLACK_S = 15.0
"""Wall seconds a move may take beyond the firmware's own timeouts (the link, the retries'
start-up, the board's reports)."""
ESTOP_GRACE_S = 2.0
"""Wall seconds the command that an emergency stop ended waits for the stop's end (`R03
V1`; the real firmware sends it 220-250 ms after the `E`)."""
STOP_SETTLE_S = 6.0
"""Wall seconds, at most, that the next command waits after an emergency stop for the
firmware to end it (`R03`, or an idle report: every 5 s on the slowest boards), since the
firmware discards what arrives before."""
HEAD_SETTLE_S = 0.5
"""Bot seconds `set_head` waits after the servo commands: servos give no feedback."""


def _ends_stop(reply: Reply) -> bool:
    """Whether a reply says an emergency stop is over: the stopped command's `R03`, or an
    idle report (`R00` or `R87` with Q0) from a board with nothing left to stop."""
    return reply.code == ERROR or (reply.code in (IDLE, LOCKED) and reply.q == 0)


@dataclass(frozen=True)
class _Exchange:
    """A command and what came back with its Q, the final reply last; `stopped` when an
    emergency stop was sent meanwhile."""

    line: str
    replies: list[Reply]
    stopped: bool
    failure: str | None = None
    """What made the client abort the command (a homing the firmware cannot finish)."""

    def position_mm(self) -> np.ndarray | None:
        """The last position (R82) the firmware reported with this command, millimetres."""
        for reply in reversed(self.replies):
            if reply.code == POSITION and {"X", "Y", "Z"} <= reply.values.keys():
                return np.array([reply.values[a] for a in "XYZ"])
        return None


class FarmduinoBot(Connection, Bot):
    """A FarmBot on its Farmduino over USB serial: see the module docstring.

    port: the serial device (prefer the stable /dev/serial/by-id/... path: it survives a
        reconnect).
    camera: makes the camera from the bot's clock (`now`); None gives a camera that raises
        CameraError.
    observer: called with an `Activity` after every move, head turn and dwell.
    info: the bot's limits (default the paper's bot); its motion profile and firmware come
        from the firmware, its travel is cut to the calibrated axis lengths.
    clock_scale: bot-clock seconds per wall second: 1 on a real bot, the device's time
        scale on a virtual one that runs faster.
    connect_timeout_s: wall seconds to wait for the firmware at connect, and to get the
        port back after it drops.
    settings: the bot's own firmware parameters {id: value} (`protocol.read_settings`
        of the web app's export), written after every start of the board as FarmBot OS
        does, each read back: one that did not take fails the connect (BotError), so
        nothing moves on settings the board does not hold. None: the board runs on what it
        holds (its defaults, unless stored in EEPROM).
    wall_clock: the seconds the bot's clock scales (a simulation pauses it while it
        renders, and while the board waits for the host); command timeouts always run on
        the real monotonic clock.
    skip_time: moves `wall_clock` on by this many of its seconds at once; a simulation
        whose clock stands still while the board waits for the host passes its clock's,
        so a dwell or the head's settling takes exactly its time. None (a real bot): they
        are waited out.
    """

    def __init__(self, port: str, *,
                 camera: Callable[[Callable[[], float]], Camera] | None = None,
                 observer: Callable[[Activity], None] | None = None,
                 info: BotInfo | None = None, clock_scale: float = 1.0,
                 connect_timeout_s: float = 15.0, settings: dict[int, float] | None = None,
                 wall_clock: Callable[[], float] = time.monotonic,
                 skip_time: Callable[[float], None] | None = None):
        if not (math.isfinite(clock_scale) and clock_scale > 0):
            raise InputError("clock_scale", f"must be a positive number, got {clock_scale!r}")
        if not (math.isfinite(connect_timeout_s) and connect_timeout_s > 0):
            raise InputError("connect_timeout_s", f"must be positive, got {connect_timeout_s!r}")
        self._port = str(port)
        self._settings = dict(settings or {})
        self._base_info = info or BotInfo.from_geometry(f"serial {self._port}")
        self._info = self._base_info
        self._observer = observer
        self._scale = float(clock_scale)
        self._connect_timeout_s = float(connect_timeout_s)
        self._wall_clock = wall_clock
        self._skip_time = skip_time
        self._origin = wall_clock()
        self._state_lock = threading.Lock()
        self._busy = threading.Lock()
        self._locked = threading.Event()
        self._estops = 0
        self._stop_sent: float | None = None
        """Monotonic time of the last `E` whose end the firmware has not yet reported."""
        self._closed = False
        self._link: SerialLink | None = None
        self._lines: queue.Queue = queue.Queue()
        self._q = 0
        self._params: dict[int, float] = {}
        self._firmware: str | None = None
        self._xyz = self._info.home
        self._moving: tuple[float, np.ndarray, np.ndarray, MotionProfile] | None = None
        self._head = (0.0, 0.0)
        self._servo: tuple[int, int] | None = None
        self._homed: set[str] = set()
        self._recovering = False
        try:
            self._connect(first=True, deadline=time.monotonic() + self._connect_timeout_s)
            self._camera = camera(self.now) if camera is not None else None
        except BaseException:
            self._disconnect()
            raise

    # --- the interface ----------------------------------------------------------------

    @property
    def info(self) -> BotInfo:
        return self._info

    @property
    def camera(self) -> Camera:
        if self._camera is None:
            raise CameraError(f"serial {self._port}: the bot was given no camera; pass "
                              "camera= (a factory that takes the bot's clock)")
        return self._camera

    def now(self) -> float:
        return (self._wall_clock() - self._origin) * self._scale

    def position(self) -> np.ndarray:
        with self._state_lock:
            if self._moving is None:
                return self._xyz.copy()
            t0, start, end, profile = self._moving
        return move_trajectory([self.now() - t0], start, end, profile)[0]

    def head(self) -> tuple[float, float]:
        return self._head

    def describe(self) -> dict:
        """The backend's settings, for scan.json."""
        return {"backend": "farmduino", "port": self._port, "firmware": self._firmware,
                "clock_scale": self._scale}

    def move_to(self, xyz, speed_fraction: float = 1.0) -> None:
        target = check_target(self._info, xyz)
        profile = self._info.motion.at_speed(speed_fraction)
        line = move_line(bed_to_farmbot_mm(target), profile.override)
        x, y, z = target
        with self._one_command(f"move_to({x:.4f}, {y:.4f}, {z:.4f})") as command:
            self._move(line, target, profile, "xyz", command, homing=None)

    def home(self, axes: str = "xyz") -> None:
        order = check_axes(axes)
        with self._one_command(f"home({axes})") as command:
            for name in order:
                self._check_homeable(name, command)
            for name in order:
                self._home_axis(name)

    def home_here(self) -> None:
        """Take where the gantry stands for home on every axis (F84, the firmware's set
        zero): for a bot a person has put at home by hand whose firmware cannot find home
        (no endstops or encoders). Wrong if the gantry is elsewhere: every move is then
        offset by as much."""
        with self._one_command("home_here") as command:
            if self._locked.is_set():
                raise LockedError(command)
            self._command(ZERO_LINE)
            with self._state_lock:
                self._xyz = self._info.home
            self._homed = {"x", "y", "z"}

    def _check_homeable(self, name: str, command: str) -> None:
        """HomingError, before anything moves, for an axis whose firmware parameters (read
        at connect) say it has neither endstops nor an encoder: the firmware would drive it
        into the frame until it times out, back off and try again for good."""
        endstops, encoder = ENDSTOPS[name], ENCODERS[name]
        if endstops in self._params and encoder in self._params and not (
                self._params[endstops] or self._params[encoder]):
            raise HomingError(
                f"{command}: the firmware cannot find home on {name.upper()}: neither its "
                f"endstops (parameter {describe(endstops)}) nor its encoder "
                f"({describe(encoder)}) is enabled; load the bot's firmware settings "
                "(`settings`, as the FarmBot web app exports them), or put the gantry at home "
                "by hand and take it as home (`home_here`)")

    def set_head(self, yaw_rad: float, pitch_rad: float) -> None:
        yaw, pitch = check_head(self._info, yaw_rad, pitch_rad)
        with self._one_command(f"set_head({yaw:.4f}, {pitch:.4f})") as command:
            if self._locked.is_set():
                raise LockedError(command)
            commands = servo_commands(HeadPose(self._xyz, yaw, pitch))
            servo = (round(float(commands[0])), round(float(commands[1])))
            t0, head_start, xyz = self.now(), self._head, self.position()
            self._send_servos(servo)
            # The head takes the whole-degree commands, not the angles asked for.
            pose = from_servo_commands(servo[0], servo[1], xyz)
            self._head = (float(pose.yaw), float(pose.pitch))
            stopped = self._hold(HEAD_SETTLE_S)
            self._notify(Activity("head", t0, self.now() - t0, xyz, xyz, head_start,
                                  self._head))
            if stopped:
                raise EmergencyStopError(command, 1)

    def dwell(self, seconds: float) -> None:
        seconds = max(0.0, float(seconds))
        with self._one_command(f"dwell({seconds:.3f})") as command:
            if self._locked.is_set():
                raise LockedError(command)
            t0, xyz = self.now(), self.position()
            stopped = self._hold(seconds)
            self._notify(Activity("dwell", t0, self.now() - t0, xyz, xyz, self._head,
                                  self._head))
            if stopped:
                raise EmergencyStopError(command, 1)

    def _hold(self, seconds: float) -> bool:
        """Let `seconds` of the bot's clock pass with the gantry still; returns whether an
        emergency stop came meanwhile."""
        if self._skip_time is not None:
            if not self._locked.is_set():
                self._skip_time(seconds / self._scale)
            return self._locked.is_set()
        return self._locked.wait(seconds / self._scale)

    def emergency_stop(self) -> None:
        with self._state_lock:
            if self._closed:
                return
            self._estops += 1
        # The link may be gone: then only the bot's own stop button stops it, and the
        # firmware is locked again as soon as the port is back (_initialise).
        link = self._link
        if link is not None and link.try_write(EMERGENCY_STOP):
            self._stop_sent = time.monotonic()
        self._locked.set()

    def unlock(self) -> None:
        with self._one_command("unlock"):
            self._command(UNLOCK_LINE)
            self._locked.clear()
            if self._servo is not None:
                self._send_servos(self._servo)

    def close(self) -> None:
        with self._state_lock:
            if self._closed:
                return
            self._closed = True
            moving = self._moving is not None
        link = self._link
        if moving and link is not None:
            link.try_write(ABORT)  # stop the move the owner thread waits for (not a lock)
        self._disconnect()

    # --- commands ---------------------------------------------------------------------

    @contextlib.contextmanager
    def _one_command(self, command: str) -> Iterator[str]:
        """Hold the bot for one public command; BotError when closed or busy."""
        if self._closed:
            raise BotError(f"{command}: {self._info.name} is closed; open a new bot")
        if not self._busy.acquire(blocking=False):
            raise BotError(f"{command}: {self._info.name} is busy with another command; "
                           "send one command at a time")
        try:
            yield command
        finally:
            self._busy.release()

    def _notify(self, activity: Activity) -> None:
        if self._observer is not None:
            self._observer(activity)

    def _send_servos(self, servo: tuple[int, int]) -> None:
        self._command(servo_line(YAW_PIN, servo[0]))
        self._command(servo_line(PITCH_PIN, servo[1]))
        self._servo = servo

    def _move_timeout(self, axes: str) -> float:
        """Wall seconds a movement of `axes` may take: every attempt (parameter 5) may run
        to the slowest axis's firmware timeout (parameters 11-13)."""
        timeout = max(getattr(self._info.motion, a).timeout_s for a in axes)
        attempts = max(1, int(self._params.get(MOVEMENT_RETRIES, 1)))
        return attempts * timeout / self._scale + MOVE_SLACK_S

    def _home_axis(self, name: str) -> None:
        """F11-F13: one axis to its home, which the firmware's counter then calls 0."""
        i = "xyz".index(name)
        target = self.position()
        target[i] = self._info.home[i]
        self._move(HOME_LINES[name], target, self._info.motion, name, f"home({name})", homing=name)
        self._homed.add(name)

    def _homing_failure(self, reply: Reply) -> str | None:
        """What in a reply says a homing will never finish: an axis timeout (R71-R73) or the
        firmware's own timeout or displaced-home message."""
        if reply.code in HOMING_TIMEOUTS:
            return f"a {HOMING_TIMEOUTS[reply.code].upper()} axis timeout ({reply.code})"
        if reply.code == TEXT and ("timeout" in reply.text or "displaced" in reply.text):
            return f"'{reply.text.strip()}' ({TEXT})"
        return None

    def _move(self, line: str, target: np.ndarray, profile: MotionProfile, axes: str,
              command: str, homing: str | None) -> None:
        """One movement command to its end, told to the observer; after a dropped link, the
        link is recovered and the command sent again from where the gantry is."""
        for attempt in range(MAX_RECOVERIES + 1):
            if self._locked.is_set():
                raise LockedError(command)
            if homing is None and self._homed != {"x", "y", "z"}:
                raise PositionLostError(command, f"{self._info.name} has not been homed "
                                        "since the Farmduino started")
            start, t0 = self._xyz.copy(), self.now()
            with self._state_lock:
                self._moving = (t0, start, target, profile)
            try:
                exchange = self._transact(line, self._move_timeout(axes),
                                          self._homing_failure if homing else None)
            except LinkDropped as drop:
                # The board goes on moving until reopening the port resets it.
                self._recover(command, drop, attempt, interrupted=functools.partial(
                    self._moved, t0, start, target, profile, None))
                continue
            except BoardStarted:
                self._moved(t0, start, target, profile, None)
                self._restarted(command)
            except BaseException:
                self._moved(t0, start, target, profile, None)
                raise
            final = exchange.replies[-1] if exchange.replies else None
            done = final is not None and final.code == DONE and not exchange.stopped
            reported = exchange.position_mm()
            if homing:
                # A homed axis sits exactly at home; the other counters may still be lost.
                end = target.copy() if done else None
            else:
                end = None if reported is None else farmbot_mm_to_bed(reported)
            self._moved(t0, start, target, profile, end)
            if exchange.failure is not None:
                stopped = ("it was stopped with an emergency stop: unlock, then"
                           if exchange.stopped else "it was stopped;")
                raise HomingError(f"{command}: the firmware cannot find home: it reports "
                                  f"{exchange.failure}; {stopped} check the endstops and "
                                  "encoders and their settings (`settings`), or put "
                                  "the gantry at home by hand and take it as home "
                                  "(`home_here`)")
            self._raise_for(exchange)
            return
        raise ConnectionLostError(self._port, f"{command}: the link kept dropping")

    def _moved(self, t0: float, start: np.ndarray, target: np.ndarray,
               profile: MotionProfile, end: np.ndarray | None) -> None:
        """A movement that began at bot time t0 ended: the gantry at `end` ((3,) metres, bed
        frame) or, when None (not reported), where the motion profile puts it by now."""
        elapsed = self.now() - t0
        xyz = move_trajectory([elapsed], start, target, profile)[0] if end is None else end
        with self._state_lock:
            self._moving = None
            self._xyz = xyz
        self._notify(Activity("move", t0, elapsed, start, target, self._head, self._head,
                              profile))

    def _command(self, body: str, timeout_s: float = REPLY_TIMEOUT_S) -> _Exchange:
        """A command that does not move, sent again after a recovered link drop."""
        for attempt in range(MAX_RECOVERIES + 1):
            try:
                exchange = self._transact(body, timeout_s)
            except LinkDropped as drop:
                self._recover(body, drop, attempt)
                continue
            except BoardStarted:
                self._restarted(body)
            self._raise_for(exchange)
            return exchange
        raise ConnectionLostError(self._port, f"{body}: the link kept dropping")

    def _raise_for(self, exchange: _Exchange) -> None:
        """The typed error of a command's outcome; nothing when it succeeded."""
        if exchange.stopped:
            self._locked.set()
            raise EmergencyStopError(exchange.line, 1)
        final = exchange.replies[-1]
        if final.code == DONE:
            return
        if final.code == ERROR:
            code = int(final.values.get("V", 0))
            if code == 1:
                self._locked.set()
            raise error_for_code(code, exchange.line)
        if final.code == LOCKED:
            self._locked.set()
            raise LockedError(exchange.line)
        if final.code == NOT_CONFIGURED:
            raise NotConfiguredError(exchange.line)
        raise UnknownCommandError(exchange.line)

    def _transact(self, body: str, timeout_s: float,
                  watch: Callable[[Reply], str | None] | None = None) -> _Exchange:
        """Send `body` with the next Q and collect the replies with that Q up to the final
        one. Raises LinkDropped, BoardStarted or CommandTimeoutError; an emergency stop
        sent meanwhile gives `stopped` (waiting ESTOP_GRACE_S at most for the reply). When
        `watch` names a failure in any reply, the command is aborted (`@`, then `E` if no
        final reply comes within ESTOP_GRACE_S) and the exchange carries the failure."""
        self._q = self._q % 999 + 1
        q = self._q
        line = checked_line(f"{body} Q{q}")
        lines = self._lines
        self._await_stop_end(lines)
        self._drain(lines)
        estops = self._estops
        self._write(line.encode("ascii") + b"\r\n")
        deadline = time.monotonic() + timeout_s
        stop_deadline = math.inf
        replies: list[Reply] = []
        failure: str | None = None
        while True:
            now = time.monotonic()
            if self._closed:
                raise BotError(f"{line}: {self._info.name} was closed")
            if self._estops != estops and stop_deadline == math.inf:
                stop_deadline = now + ESTOP_GRACE_S
            if now >= min(deadline, stop_deadline):
                if failure is not None and self._estops == estops:
                    self.emergency_stop()  # the abort went unanswered: never leave it homing
                    deadline = now + ESTOP_GRACE_S
                    continue
                if stop_deadline != math.inf:
                    return _Exchange(line, replies, True, failure)
                raise CommandTimeoutError(line, timeout_s)
            try:
                item = lines.get(timeout=min(min(deadline, stop_deadline) - now, 0.05))
            except queue.Empty:
                continue
            reply = self._reply(item)
            stopped = self._estops != estops
            if reply is not None and stopped and _ends_stop(reply):
                self._stop_sent = None
            if reply is not None and watch is not None and failure is None:
                failure = watch(reply)
                if failure is not None:
                    self._write(ABORT)
                    deadline = min(deadline, now + ESTOP_GRACE_S)
            if reply is None or reply.q != q:
                continue
            replies.append(reply)
            # After an E, the R87 only says the firmware is stopping: R03 V1 ends it.
            if reply.code in FINAL_REPLIES and not (stopped and reply.code == LOCKED):
                return _Exchange(line, replies, stopped, failure)

    def _await_stop_end(self, lines: queue.Queue) -> None:
        """After an emergency stop, read until the firmware has ended it (it discards
        what arrives before): `R03`, or an idle report, or `STOP_SETTLE_S` after the E."""
        while self._stop_sent is not None:
            remaining = self._stop_sent + STOP_SETTLE_S - time.monotonic()
            if remaining <= 0 or self._closed:
                self._stop_sent = None
                return
            try:
                item = lines.get(timeout=min(remaining, 0.05))
            except queue.Empty:
                continue
            reply = self._reply(item)
            if reply is not None and _ends_stop(reply):
                self._stop_sent = None

    def _reply(self, item) -> Reply | None:
        """A queued line as a reply; raises for a dropped link or the startup banner."""
        if isinstance(item, Dropped):
            raise LinkDropped(self._port, item.detail)
        reply = parse_reply(item)
        if reply is not None and reply.code == TEXT and STARTUP_TEXT in reply.text:
            raise BoardStarted("Farmduino", "the board restarted (R99 ARDUINO TEXT "
                                "COMPLETE)")
        return reply

    def _drain(self, lines: queue.Queue) -> None:
        """Read what came in since the last command (reports, noise): a dropped link or a
        restart shows before anything is sent."""
        while True:
            try:
                self._reply(lines.get_nowait())
            except queue.Empty:
                return

    def _write(self, data: bytes) -> None:
        link = self._link
        if link is None:
            raise LinkDropped(self._port, "the port is not open")
        link.write(data)
