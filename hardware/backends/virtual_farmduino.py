"""A virtual Farmduino: FarmBot's firmware protocol on a pseudo-terminal, over a simulated gantry.

`VirtualFarmduino` answers on a real device path that pyserial opens (`os.openpty`), and
keeps a stable symlink to it (`path`, like /dev/serial/by-id) that survives a simulated
reconnect. It behaves as farmbot-arduino-firmware 6.6 does (docs/guides/physical-bot.md,
"The wire protocol"):

- Opening the port resets the board (as DTR does on a real one): `R99 ARDUINO STARTUP
  COMPLETE` after the boot time, the position counters at 0 wherever the gantry stands
  (the position is lost), the parameters reloaded from "EEPROM" (the `params` given) with
  the configuration not approved, no servo pulses, no emergency stop.
- Every line is echoed (`R08 *line*`); a command starts with `R01` and ends with `R02`, or
  `R03 V<code>`; a reply repeats the command's `Q<n>`. Refusals send one reply only:
  `R87` while locked (every command but F09, F20-F22, F81-F83), `R88` for a movement
  before `F22 P2 V1`, `R09` for a command the firmware does not know.
- At boot, after the banner, every parameter (`R21 P.. V.. Q0`), as the real firmware
  prints them. The echo keeps the sender's carriage return inside it (`R08 *F82 Q3\r*`).
  A move ends as on the real board: `R99 stopped` and motor, endstop and encoder reports
  (R05, R81, R84, R85), then after `END_OF_MOVE_S` its R82 and R02.
- Periodic reports every `report_period_s` simulated seconds (0.5; 5 on the ATmega2560
  build): idle `R00` (`R87` while locked) with the
  position `R82` and `R88` until configured, all with `Q0`; `R04` and `R82` with the
  command's Q during a move.
- There is no queue: bytes that arrive while a command runs are discarded, except `E` / `e`
  (emergency stop, at any time, anywhere in a line) and `@` (abort the move); what is left
  of the input when a command ends is discarded too.
- An emergency stop during a command takes as long as on the real board: the motors run on
  for `STOP_ACK_S`, then `R87 Q<n>`; position reports with the command's Q follow every
  `STOP_REPORT_S` while it stops, and `R03 V1 Q<n>` ends it `STOP_DONE_S` after the `E`.
  Every byte before that `R03` is discarded, so a client that takes the `R87` as the end
  and sends `F09` at once loses it. An `E` while idle locks at once.
- G00 / G01 (axes left out go to 0, A/B/C lower the maximum speed of moves away from
  home), G28 (Z, then Y, then X to 0), F11-F13 (home one axis: with its endstops or encoder
  on, parameters 25-27 and 101-103, the gantry drives to its physical home and the axis's
  counter becomes 0; with neither, as the real firmware does, it drives into the home end
  until the axis times out, `R71`-`R73` and `R99 timeout`, reports `R99 homing displaced`
  and tries again, for good, until `@` or `E`; the firmware's defaults have both off),
  F09 unlock, F21 / F22 parameters (every id of `protocol.PARAMETERS`; another gets
  `R02` and nothing else), F41 / F42 pins, F61 servos (only pins 4, 5, 6,
  11 drive servos; 0-180 degrees, >= 544 microseconds; other pins get `R02` and nothing
  happens), F82 position, F83 version, F20 every parameter, F43 / F44 pin mode and pulse, F81
  endstops (none pressed), F84 set zero (the named axes' counters become 0 there), F14-F16
  (measure an axis: home, then the far end at the homing speed, parameters 65-67, without
  the axis timeout; `R23 P21-23 V0` and `R23 P801-803 V<steps>`, and the counter reads the
  length; with neither endstops nor encoders it drives into the home end until `E`, as the
  real calibration loop does), F31 / F32 (a status value: `R31 P.. V0`).
- Moves follow FarmBot's motion profile (`motion.py`) with the device's own parameters,
  in whole motor steps; an axis still moving after its timeout (parameters 11-13) stops
  the move with `R03 V2`. The board keeps the gantry's joints (`joints`, as the MuJoCo
  model's: assets/farmbot/farmbot.xml, over `geometry.PAPER_BOT`'s travel) along the
  profile as simulated time passes, and `R82` reports them (in the firmware's counts:
  millimetres from where the board last started or homed); pins 6 and 5 drive the yaw and
  pitch joints. It needs only numpy: a simulated bot sets its MuJoCo model from `joints`.

Simulated time runs `time_scale` times faster than the wall clock (1 for a bench test with
a person, large for tests and simulated scans); periodic reports and the boot time are
scaled with it, but never come more often than every `MIN_REPORT_WALL_S` wall seconds,
so a large scale cannot flood the line.

Faults for tests: `stall_next_move` (R03 V31-33 part way, after the firmware's retries,
each announced by `R07`), `drop_next_move` / `drop_connection` (the pty closes and the
symlink disappears; the board keeps power and the move goes on; a fresh pty appears
behind the same symlink after a while, and opening it resets the board),
`inject_garbage` (bytes on the line), `reset_next_move` / `reset` (the board restarts:
the banner again, the position lost).

Units: the protocol is in FarmBot millimetres (Z <= 0 downward from the top); the slide
joints are metres from the physical home; servo joints are radians.
"""

from __future__ import annotations

import contextlib
import math
import os
import re
import select
import shutil
import tempfile
import threading
import time
import tty
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from flowerpose.errors import InputError
from flowerpose.hardware.geometry import PAPER_BOT
from flowerpose.hardware.motion import (
    END_OF_MOVE_S,
    MotionProfile,
    axis_durations,
    axis_motions,
    move_trajectory,
)
from flowerpose.hardware.protocol import (
    BANNER,
    ENCODERS,
    ENDSTOPS,
    FIRMWARE_DEFAULTS,
    PARAMETERS,
    SERVO_PINS,
)

FIRMWARE_VERSION = "6.6.23.V.virtual"
REPORT_PERIOD_S = 0.5
"""Simulated seconds between periodic reports by default (Farmduino v1.4 and later: 500 ms;
the firmware built for the ATmega2560 as FARMDUINO_V10 reports every 5 s)."""
MIN_REPORT_WALL_S = 0.02
"""Least wall seconds between periodic reports, whatever the time scale."""
BOOT_S = 1.0
"""Simulated seconds from a reset to the startup banner (the bootloader's wait)."""
MIN_BOOT_WALL_S = 0.05
"""Least wall seconds from a reset to the banner: pyserial flushes its input as it opens
the port, so a banner sent sooner could be lost."""
STOP_ACK_S = 0.05
"""Simulated seconds from an `E` during a command to the firmware's `R87 Q<n>`; the motors
run on until then (farmbot-arduino-firmware 6.6.23 on an ATmega2560: within about 50 ms)."""
STOP_DONE_S = 0.235
"""... and to its `R03 V1 Q<n>`, the end of the stop (measured: 220-250 ms). Input that
arrives before it is discarded."""
STOP_REPORT_S = 0.1
"""Simulated seconds between the position reports the firmware sends while it stops."""
INPUT_LIMIT = 100
"""The firmware's input buffer: a longer line is cut and processed (INCOMING_CMD_BUF_SIZE)."""

DEFAULT_PARAMETERS: dict[int, float] = {
    **dict.fromkeys(PARAMETERS, 0.0),  # every parameter the firmware knows; unmodelled: 0
    **FIRMWARE_DEFAULTS,
}
"""The firmware's defaults (Config.h) of the parameters modelled here; the others are known
(F21 reads them, F22 writes them) at 0."""
FEEDBACK_PARAMETERS: dict[int, float] = {ENCODERS[a]: 1.0 for a in "xyz"}
"""A board with its encoders on (as FarmBot OS configures a Genesis): it can find home."""
HOMING_MARKER = -1
"""`_Running.error` of a homing stage without endstops or encoders: the axis timeout ends
it, and the firmware tries again, for good."""

SERVO_JOINTS = {6: 3, 5: 4}
"""The servo pins that turn the head, and their joints' places in `joints` (yaw, pitch)."""

_MOVEMENTS = {"G00", "F11", "F12", "F13", "F14", "F15", "F16"}
_WHILE_LOCKED = {"F09", "F20", "F21", "F22", "F81", "F82", "F83"}
_ALIASES = {"G0": "G00", "G01": "G00", "G1": "G00", "F9": "F09"}
_KNOWN = {"G00", "G28", "F09", "F11", "F12", "F13", "F14", "F15", "F16", "F20", "F21", "F22",
          "F31", "F32", "F41", "F42", "F43", "F44", "F61", "F81", "F82", "F83", "F84"}
_NUMBER = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)")
_ERR_EMERGENCY_STOP, _ERR_TIMEOUT, _ERR_ABORTED = 1, 2, 5


def _atof(text: str) -> float:
    """The leading number of `text`, 0 when there is none (C's atof)."""
    match = _NUMBER.match(text)
    return float(match.group()) if match else 0.0


@dataclass
class _Stage:
    """One straight motion of a command: to `end` (physical joints, metres) on `profile`;
    `home_axis` zeroes that axis's counter on arrival (F11-F13)."""

    end: np.ndarray
    profile: MotionProfile
    home_axis: int | None = None
    blind: bool = False
    """Homing without endstops or encoders: nothing tells the firmware it got there."""
    calibrating: bool = False
    """F14-F16: the firmware's calibration loop, which watches no axis timeout."""
    measure_axis: int | None = None
    """F14-F16: on arrival at the far end, report that axis's length in steps (R23)."""


@dataclass
class _Stopping:
    """An emergency stop in progress (simulated seconds)."""

    q: int
    at: float
    """When the `E` arrived."""
    acknowledged: bool = False
    next_report: float = 0.0


@dataclass
class _Running:
    """A movement command in progress. Times are simulated seconds; `stop_at` is when the
    current stage ends, by arrival (`error` 0) or by a fault or timeout (`error` > 0, or
    `reset`: the board restarts there)."""

    q: int
    stages: list[_Stage]
    t0: float = 0.0
    start: np.ndarray = field(default_factory=lambda: np.zeros(3))
    stop_at: float = 0.0
    error: int = 0
    reset: bool = False


class VirtualFarmduino:
    """A Farmduino with FarmBot's firmware on a pseudo-terminal: see the module docstring.

    time_scale: simulated seconds per wall second (> 0).
    params: parameter values {id: value} over `DEFAULT_PARAMETERS`, kept in "EEPROM": they
        come back at every reset; F22 writes last until the next one.
    link_dir: folder of the stable symlink `path` (default: a new temporary folder,
        removed on close).
    start_mm: where the gantry stands at power-on, FarmBot millimetres from the physical
        home (Z <= 0); the counters start at 0 there, as on a real board.
    wall_clock: the seconds simulated time scales (time.monotonic; a simulation's clock).
    report_period_s: simulated seconds between periodic reports.
    on_idle: called with (True, since) when the board is left waiting for the host
        (booted, the port open, no command, stop or boot under way), since the
        `wall_clock` reading its last answer was due at (None: now), and with (False,
        None) when that ends, from the device's thread: a simulation stops its clock
        meanwhile (`PausableClock.host_turn`).
    Use as a context manager, or `start()` then `close()`.
    """

    def __init__(self, *, time_scale: float = 1.0, params: dict[int, float] | None = None,
                 link_dir: str | Path | None = None, start_mm=(0.0, 0.0, 0.0),
                 wall_clock: Callable[[], float] = time.monotonic,
                 report_period_s: float = REPORT_PERIOD_S,
                 on_idle: Callable[[bool, float | None], None] | None = None):
        if not (math.isfinite(time_scale) and time_scale > 0):
            raise InputError("time_scale", f"must be a positive number, got {time_scale!r}")
        self.time_scale = float(time_scale)
        if not (math.isfinite(report_period_s) and report_period_s > 0):
            raise InputError("report_period_s", f"must be positive, got {report_period_s!r}")
        self.report_period_s = float(report_period_s)
        self._eeprom = {**DEFAULT_PARAMETERS, **{int(k): float(v) for k, v in
                                                  (params or {}).items()}}
        self._params = dict(self._eeprom)
        self._own_dir = link_dir is None
        self._dir = Path(tempfile.mkdtemp(prefix="flowerpose-farmduino-") if link_dir is None
                         else link_dir)
        self.path = str(self._dir / "ttyFarmduino")
        """The stable device path: a symlink to the current pty, like /dev/serial/by-id."""
        self._joints = np.zeros(5)  # x, y, z, yaw, pitch as `joints` gives them
        self._set_joints(np.asarray(start_mm, np.float64) / 1000.0)
        self._offset = self._physical()
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self._wall_clock = wall_clock
        self._wall0 = wall_clock()
        self._on_idle = on_idle
        self._idle = False
        self._answered_at: float | None = None  # simulated time the last timed answer was due
        self._master: int | None = None
        self.device: str | None = None
        """The current pty's slave path (changes at a simulated reconnect)."""
        self._relink_at: float | None = None
        self._host_open = False
        self._booted_at: float | None = None  # simulated time the banner is due; None: up
        self._input = bytearray()
        self._running: _Running | None = None
        self._closing: tuple[int, float] | None = None  # (Q, simulated time of its R02)
        self._stopping: _Stopping | None = None
        self._locked = False
        self._servos: dict[int, float] = {}
        self._pins: dict[int, int] = {}
        self._next_report = 0.0
        self._fault: tuple[str, float, float] | None = None
        self._drop_at: tuple[float, float] | None = None  # (simulated time, wall seconds down)
        self._ignored: set[int] = set()
        self.received: list[str] = []
        """Every line the firmware processed, in order (for tests)."""
        self.discarded = 0
        """Bytes discarded because they arrived while a command ran."""
        self.boots = 0
        """Resets so far (each open of the port is one)."""

    # --- life cycle -------------------------------------------------------------------

    def start(self) -> VirtualFarmduino:
        """Open the pty and serve it in a background thread; returns self."""
        self._open_link()
        self._thread = threading.Thread(target=self._serve, name="virtual-farmduino",
                                        daemon=True)
        self._thread.start()
        return self

    def __enter__(self) -> VirtualFarmduino:
        return self.start() if self._thread is None else self

    def __exit__(self, *exc) -> None:
        self.close()

    def wait(self, timeout_s: float | None = None) -> None:
        """Block until the device stops (close() from another thread, or a fault of the
        device itself, which is raised here)."""
        self._stop.wait(timeout_s)
        if self._error is not None:
            raise self._error

    def close(self) -> None:
        """Stop serving, close the pty and remove the symlink; calling it again does nothing.
        A fault of the device itself (a bug) is raised here, once."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(5.0)
        with self._lock:
            self._close_link()
        if self._own_dir:
            shutil.rmtree(self._dir, ignore_errors=True)
        error, self._error = self._error, None
        if error is not None:
            raise error

    # --- state for tests and the command line -----------------------------------------

    def now(self) -> float:
        """Simulated seconds since the device was made."""
        return (self._wall_clock() - self._wall0) * self.time_scale

    def joints(self) -> np.ndarray:
        """(5,) the joints as the MuJoCo model names them: x, y, z metres from the physical
        home (z <= 0), yaw, pitch radians."""
        with self._lock:
            return self._joints.copy()

    def firmware_position_mm(self) -> np.ndarray:
        """(3,) the position the firmware reports (R82), millimetres."""
        with self._lock:
            return (self._physical() - self._offset) * 1000.0

    def servo(self, pin: int) -> float | None:
        """The angle (degrees) servo `pin` is driven to, None while it gets no pulses."""
        with self._lock:
            return self._servos.get(pin)

    def parameter(self, pid: int) -> float | None:
        """Parameter `pid`'s current value, None for one not modelled."""
        with self._lock:
            return self._params.get(pid)

    @property
    def locked(self) -> bool:
        return self._locked

    # --- faults -----------------------------------------------------------------------

    def _schedule(self, kind: str, at_fraction: float, value: float = 0.0) -> None:
        if not 0.0 <= at_fraction <= 1.0:
            raise InputError("at_fraction", f"must be in [0, 1], got {at_fraction!r}")
        with self._lock:
            self._fault = (kind, float(at_fraction), float(value))

    def stall_next_move(self, axis: str, at_fraction: float = 0.5) -> None:
        """The next movement stalls on `axis` ("x", "y" or "z") after `at_fraction` of its
        first stage: the firmware retries (R07, the obstruction still there) and reports
        R03 V31, V32 or V33."""
        if axis not in ("x", "y", "z"):
            raise InputError("axis", f"must be 'x', 'y' or 'z', got {axis!r}")
        self._schedule("stall", at_fraction, "xyz".index(axis))

    def ignore_writes(self, pid: int) -> None:
        """Answer F22 for parameter `pid` with R02 but keep its value, as the firmware does
        for a value it rejects."""
        with self._lock:
            self._ignored.add(int(pid))

    def reset_next_move(self, at_fraction: float = 0.5) -> None:
        """The board restarts after `at_fraction` of the next movement: no final reply, the
        banner again, the position lost."""
        self._schedule("reset", at_fraction)

    def drop_next_move(self, at_fraction: float = 0.5, down_s: float = 0.2) -> None:
        """The link drops after `at_fraction` of the next movement and comes back behind the
        same symlink `down_s` wall seconds later."""
        self._schedule("drop", at_fraction, down_s)

    def drop_connection(self, down_s: float = 0.2) -> None:
        """The link drops now and comes back behind the same symlink `down_s` wall seconds
        later (the board keeps power: a running move goes on)."""
        with self._lock:
            self._drop(down_s)

    def reset(self) -> None:
        """The board restarts now (a brown-out, the reset button)."""
        with self._lock:
            self._boot()

    def inject_garbage(self, data: bytes) -> None:
        """Put raw bytes on the line to the host now (electrical noise)."""
        with self._lock:
            self._write(bytes(data))

    # --- the link ---------------------------------------------------------------------

    def _open_link(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)
        self.device = os.ttyname(slave)
        os.close(slave)  # the host's open and close show as POLLHUP clearing and returning
        os.set_blocking(master, False)
        self._master = master
        self._host_open = False
        link = Path(self.path)
        temporary = link.with_name(link.name + ".new")
        with contextlib.suppress(FileNotFoundError):
            temporary.unlink()
        temporary.symlink_to(self.device)
        temporary.replace(link)

    def _close_link(self) -> None:
        if self._master is not None:
            os.close(self._master)
            self._master = None
        self._host_open = False
        with contextlib.suppress(FileNotFoundError):
            Path(self.path).unlink()

    def _drop(self, down_s: float) -> None:
        """Unplug: the pty and the symlink go; a new pair comes after down_s wall seconds."""
        self._close_link()
        self._relink_at = time.monotonic() + max(0.0, float(down_s))

    def _write(self, data: bytes) -> None:
        """Send to the host; with no host, or a full buffer, the bytes are lost, as on the
        Farmduino's UART."""
        if self._master is None or not self._host_open:
            return
        with contextlib.suppress(BlockingIOError, OSError):
            os.write(self._master, data)

    def _say(self, text: str) -> None:
        if self._booted_at is None:
            self._write(text.encode("ascii") + b"\r\n")

    # --- the board --------------------------------------------------------------------

    def _physical(self) -> np.ndarray:
        return self._joints[:3].copy()

    def _set_joints(self, xyz_m: np.ndarray) -> None:
        self._joints[:3] = xyz_m

    def _profile(self) -> MotionProfile:
        return MotionProfile.from_firmware(self._params)

    def _boot(self) -> None:
        """Restart the board: motion stops, counters restart at 0 where the gantry stands."""
        if self._running is not None:
            running = self._running
            self._set_joints(self._along(running, min(self.now() - running.t0,
                                                      running.stop_at)))
        self._running = None
        self._closing = None
        self._stopping = None
        self._offset = self._physical()
        self._params = dict(self._eeprom)
        self._locked = False
        self._servos.clear()
        self._pins.clear()
        self._input.clear()
        self.boots += 1
        self._booted_at = self.now() + max(BOOT_S, MIN_BOOT_WALL_S * self.time_scale)

    def _position_report(self, q: int) -> str:
        x, y, z = (self._physical() - self._offset) * 1000.0 + 0.0
        return f"R82 X{x:.2f} Y{y:.2f} Z{z:.2f} Q{q}"

    def _report_period(self) -> float:
        return max(self.report_period_s, MIN_REPORT_WALL_S * self.time_scale)

    def _serve(self) -> None:
        try:
            while not self._stop.is_set():
                self._step()
        except BaseException as error:  # noqa: BLE001 - handed to wait(); the thread ends
            self._error = error
            self._stop.set()

    def _step(self) -> None:
        """One turn of the firmware's loop: wait for input or the next event, then act."""
        with self._lock:
            master, wait = self._master, self._wait_s()
        if master is None:  # unplugged: the board runs on, its output lost
            time.sleep(wait)
            with self._lock:
                if self._relink_at is not None and time.monotonic() >= self._relink_at:
                    self._relink_at = None
                    self._open_link()
                self._advance()
                self._say_idle()
            return
        poller = select.poll()
        poller.register(master, select.POLLIN)
        try:
            events = poller.poll(wait * 1000.0)
        except InterruptedError:
            events = []
        data, hung_up = b"", False
        for _, mask in events:
            if mask & select.POLLIN:
                with contextlib.suppress(BlockingIOError, OSError):
                    data = os.read(master, 4096)
            if mask & (select.POLLHUP | select.POLLERR) and not data:
                hung_up = True
        with self._lock:
            if self._master != master:
                return
            if hung_up:
                self._host_open = False
            elif not self._host_open:
                # The host opened the port: DTR resets the board.
                self._host_open = True
                self._boot()
            if data:
                self._feed(data)
            self._advance()
            self._say_idle()
        if hung_up:
            time.sleep(min(wait, 0.005))  # POLLHUP stays set until the host opens again

    def _say_idle(self) -> None:
        """Tell `on_idle` when the board starts or stops waiting for the host (lock held)."""
        idle = (self._host_open and self._booted_at is None and self._running is None
                and self._closing is None and self._stopping is None and self._drop_at is None)
        if self._on_idle is not None and idle != self._idle:
            due = self._answered_at if idle else None
            # The loop wakes a little after an answer is due: the wait starts when it was.
            self._on_idle(idle, None if due is None else self._wall0 + due / self.time_scale)
        self._answered_at = None
        self._idle = idle

    def _wait_s(self) -> float:
        """Wall seconds until the next event (at most 50 ms, so faults set from other
        threads act soon)."""
        now = self.now()
        events = [self._next_report]
        if self._booted_at is not None:
            events.append(self._booted_at)
        if self._running is not None:
            events.append(self._running.t0 + self._running.stop_at)
        if self._stopping is not None:
            events.append(self._stopping.next_report)
        if self._closing is not None:
            events.append(self._closing[1])
        if self._drop_at is not None:
            events.append(self._drop_at[0])
        wait = (min(events) - now) / self.time_scale
        if self._relink_at is not None:
            wait = min(wait, self._relink_at - time.monotonic())
        return min(max(wait, 0.0), 0.05)

    def _feed(self, data: bytes) -> None:
        """Bytes from the host, one at a time as the firmware reads them."""
        discard_rest = False
        for byte in data:
            if self._booted_at is not None:
                continue  # still booting: nothing reads the UART
            if byte in b"Ee":
                self._emergency_stop()
                continue
            if self._stopping is not None or self._closing is not None:
                self.discarded += 1
                continue
            if self._running is not None:
                if byte == ord("@"):
                    self._finish(_ERR_ABORTED)
                else:
                    self.discarded += 1
                continue
            if discard_rest:
                self.discarded += 1
                continue
            if byte == ord("\n") or len(self._input) >= INPUT_LIMIT - 1:
                raw = self._input.decode("ascii", "replace")
                line = raw.strip()
                self._input.clear()
                if line:
                    self._execute(line, echo=raw.lstrip())
                    # The firmware empties its input buffer after every command.
                    discard_rest = True
                continue
            self._input.append(byte)

    def _advance(self) -> None:
        """Move time on: the banner, the running command, the link drop, the reports."""
        now = self.now()
        if self._booted_at is not None and now >= self._booted_at:
            self._booted_at = None
            self._next_report = now + self._report_period()
            self._say(BANNER)
            for pid in sorted(self._params):  # the real firmware lists them all at boot
                self._say(f"R21 P{pid} V{self._params[pid]:g} Q0")
        if self._drop_at is not None and now >= self._drop_at[0]:
            down = self._drop_at[1]
            self._drop_at = None
            self._drop(down)
        if self._stopping is not None:
            self._advance_stop(now)
        if self._closing is not None and now >= self._closing[1]:
            (q, due), self._closing = self._closing, None
            self._say(self._position_report(q))
            self._say(f"R02 Q{q}")
            self._answered_at = due
            self._next_report = now + self._report_period()
        running = self._running
        if running is not None:
            stage = running.stages[0]
            t = now - running.t0
            if t >= running.stop_at:
                self._set_joints(self._along(running, running.stop_at))
                if running.reset:
                    self._boot()
                elif running.error == HOMING_MARKER:
                    self._homing_retry(running, stage)
                elif running.error:
                    self._stalled_or_timed_out(running)
                else:
                    self._arrive(running, stage)
            else:
                self._set_joints(self._along(running, t))
        if self._booted_at is None and self._stopping is None and now >= self._next_report:
            self._next_report = now + self._report_period()
            self._periodic()

    def _periodic(self) -> None:
        busy = self._running.q if self._running is not None else (
            self._closing[0] if self._closing is not None else None)
        if busy is not None:
            self._say(f"R04 Q{busy}")
            self._say(self._position_report(busy))
            return
        self._say("R87 Q0" if self._locked else "R00 Q0")
        self._say(self._position_report(0))
        if self._params.get(2) != 1:
            self._say("R88 Q0")

    # --- commands ---------------------------------------------------------------------

    def _execute(self, line: str, echo: str | None = None) -> None:
        """One command line; `echo` is what the firmware echoes, the sender's carriage
        return included (the real firmware keeps it)."""
        self.received.append(line)
        self._say(f"R08 *{line if echo is None else echo}*")
        tokens = line.split()
        code = _ALIASES.get(tokens[0], tokens[0])
        values: dict[str, float] = {}
        if code[0] in "GF":
            for token in tokens[1:]:
                values.setdefault(token[0], _atof(token[1:]))
        q = int(values.get("Q", 0))
        if self._locked and code not in _WHILE_LOCKED:
            self._say(f"R87 Q{q}")
            return
        if code in _MOVEMENTS and self._params.get(2) != 1:
            self._say(f"R88 Q{q}")
            return
        handler = getattr(self, f"_cmd_{code}", None) if code in _KNOWN else None
        if handler is None:
            self._say(f"R09 Q{q}")
            return
        self._say(f"R01 Q{q}")
        handler(q, values)

    def _done(self, q: int) -> None:
        self._say(f"R02 Q{q}")

    def _to_physical(self, axis: int, mm: float) -> float:
        """The physical joint (metres) of a firmware coordinate on `axis`, in whole steps
        (the firmware truncates to its step counter)."""
        per_mm = self._profile().axis(axis, False).steps_per_mm
        return math.trunc(mm * per_mm) / per_mm / 1000.0 + self._offset[axis]

    def _cmd_G00(self, q: int, values: dict[str, float]) -> None:
        end = np.array([self._to_physical(i, values.get(a, 0.0)) for i, a in enumerate("XYZ")])
        speeds = (values.get("A", 0), values.get("B", 0), values.get("C", 0))
        profile = self._profile().with_override(*(int(s) for s in speeds))
        self._begin(q, [_Stage(end, profile)])

    def _cmd_G28(self, q: int, values: dict[str, float]) -> None:
        profile, stages = self._profile(), []
        end = self._physical()
        for axis in (2, 1, 0):
            end = end.copy()
            end[axis] = self._offset[axis]
            stages.append(_Stage(end, profile))
        self._begin(q, stages)

    def _home(self, q: int, axis: int) -> None:
        name = "xyz"[axis]
        blind = not (self._params.get(ENDSTOPS[name]) or self._params.get(ENCODERS[name]))
        end = self._physical()
        end[axis] = 0.0
        self._begin(q, [_Stage(end, self._profile(), home_axis=axis, blind=blind)])

    def _cmd_F11(self, q: int, values: dict[str, float]) -> None:
        self._home(q, 0)

    def _cmd_F12(self, q: int, values: dict[str, float]) -> None:
        self._home(q, 1)

    def _cmd_F13(self, q: int, values: dict[str, float]) -> None:
        self._home(q, 2)

    def _measure(self, q: int, axis: int) -> None:
        """F14-F16: drive to home, then to the far end at the homing speed (parameters
        65-67, steps/s, no ramp), and report the axis length in steps (R23 P801-803); the
        position counter then reads the length. With neither endstops nor encoders nothing
        tells the firmware it reached home: it drives into the home end until an E (the
        real firmware's calibration loop watches no timeout and no `@`)."""
        name = "xyz"[axis]
        blind = not (self._params.get(ENDSTOPS[name]) or self._params.get(ENCODERS[name]))
        speed = float(self._params.get(65 + axis) or 50)  # 0: unset; the firmware default
        motion = self._profile().axis(axis, False)
        crawl = replace(motion, max_speed=speed, min_speed=speed)
        profile = replace(self._profile(), **{name: crawl}, **({"z_home": crawl} if axis == 2
                                                               else {}))
        home = self._physical()
        home[axis] = 0.0
        stages = [_Stage(home, profile, home_axis=axis, blind=blind, calibrating=True)]
        if not blind:
            far = home.copy()
            # The far end: the travel from home, downward for Z (its joint runs <= 0).
            far[axis] = -PAPER_BOT.travel_m[2] if axis == 2 else PAPER_BOT.travel_m[axis]
            stages.append(_Stage(far, profile, calibrating=True, measure_axis=axis))
        self._begin(q, stages)

    def _cmd_F14(self, q: int, values: dict[str, float]) -> None:
        self._measure(q, 0)

    def _cmd_F15(self, q: int, values: dict[str, float]) -> None:
        self._measure(q, 1)

    def _cmd_F16(self, q: int, values: dict[str, float]) -> None:
        self._measure(q, 2)

    def _cmd_F31(self, q: int, values: dict[str, float]) -> None:
        """Read a status value (the firmware keeps one, "general", at 0)."""
        self._say(f"R31 P{int(values.get('P', 0))} V0 Q{q}")
        self._done(q)

    def _cmd_F32(self, q: int, values: dict[str, float]) -> None:
        """The firmware's F32 reads a status value too (the same handler as F31)."""
        self._cmd_F31(q, values)

    def _cmd_F20(self, q: int, values: dict[str, float]) -> None:
        """Report every parameter."""
        for pid in sorted(self._params):
            self._say(f"R21 P{pid} V{self._params[pid]:g} Q{q}")
        self._done(q)

    def _cmd_F81(self, q: int, values: dict[str, float]) -> None:
        """Report the endstops: none is wired to this board, so none is pressed."""
        self._say(f"R81 XA0 XB0 YA0 YB0 ZA0 ZB0 Q{q}")
        self._done(q)

    def _cmd_F43(self, q: int, values: dict[str, float]) -> None:
        """Set a pin's mode (input / output): nothing here reads it."""
        self._done(q)

    def _cmd_F44(self, q: int, values: dict[str, float]) -> None:
        """Pulse a pin: value V, then W after T milliseconds; it is left at W."""
        self._pins[int(values.get("P", 0))] = int(values.get("W", values.get("V", 0)))
        self._done(q)

    def _cmd_F84(self, q: int, values: dict[str, float]) -> None:
        """Set zero: the named axes' counters become 0 where the gantry stands."""
        here = self._physical()
        for i, name in enumerate("XYZ"):
            if values.get(name, 0) == 1:
                self._offset[i] = here[i]
        self._say(self._position_report(q))
        self._done(q)

    def _cmd_F09(self, q: int, values: dict[str, float]) -> None:
        self._locked = False
        self._done(q)

    def _cmd_F21(self, q: int, values: dict[str, float]) -> None:
        pid = int(values.get("P", 0))
        if pid in self._params:
            self._say(f"R21 P{pid} V{self._params[pid]:g} Q{q}")
        self._done(q)

    def _cmd_F22(self, q: int, values: dict[str, float]) -> None:
        pid = int(values.get("P", 0))
        if pid in self._params and pid not in self._ignored:
            self._params[pid] = float(int(values.get("V", 0)))
        self._done(q)

    def _cmd_F41(self, q: int, values: dict[str, float]) -> None:
        self._pins[int(values.get("P", 0))] = int(values.get("V", 0))
        self._done(q)

    def _cmd_F42(self, q: int, values: dict[str, float]) -> None:
        pin = int(values.get("P", 0))
        self._say(f"R41 P{pin} V{self._pins.get(pin, 0)} Q{q}")
        self._done(q)

    def _cmd_F61(self, q: int, values: dict[str, float]) -> None:
        pin, value = int(values.get("P", 0)), int(values.get("V", 0))
        if pin in SERVO_PINS:
            # Arduino's Servo.write: >= 544 is a pulse in microseconds, less an angle.
            degrees = ((value - 544) / (2400 - 544) * 180.0 if value >= 544
                       else min(max(value, 0), 180))
            self._servos[pin] = float(min(max(degrees, 0.0), 180.0))
            if pin in SERVO_JOINTS:
                offset = (PAPER_BOT.yaw_command_offset_deg if pin == 6
                          else PAPER_BOT.pitch_command_offset_deg)
                self._joints[SERVO_JOINTS[pin]] = float(
                    PAPER_BOT.command_to_angle(self._servos[pin], offset))
        self._done(q)

    def _cmd_F82(self, q: int, values: dict[str, float]) -> None:
        self._say(self._position_report(q))
        self._done(q)

    def _cmd_F83(self, q: int, values: dict[str, float]) -> None:
        self._say(f"R83 {FIRMWARE_VERSION} Q{q}")
        self._done(q)

    # --- movement ---------------------------------------------------------------------

    def _along(self, running: _Running, t: float) -> np.ndarray:
        stage = running.stages[0]
        return move_trajectory([t], running.start, stage.end, stage.profile)[0]

    def _begin(self, q: int, stages: list[_Stage]) -> None:
        self._running = _Running(q, stages)
        self._start_stage(self._running, first=True)

    def _start_stage(self, running: _Running, first: bool = False,
                     at: float | None = None) -> None:
        """Start the running command's next stage at simulated time `at` (now: None); a
        stage that follows another starts when that one ended, however late the loop woke."""
        stage = running.stages[0]
        running.t0, running.start = self.now() if at is None else at, self._physical()
        durations = axis_durations(running.start, stage.end, stage.profile)
        running.stop_at, running.error, running.reset = float(durations.max()), 0, False
        timeouts = [a.timeout_s for a in axis_motions(running.start, stage.end, stage.profile)]
        late = [timeouts[i] for i in range(3) if durations[i] > timeouts[i]]
        if late:
            running.stop_at, running.error = min(late), _ERR_TIMEOUT
        if stage.calibrating:
            running.stop_at, running.error = float(durations.max()), 0
        if stage.blind and stage.calibrating:
            # Calibration watches no timeout: it drives into the home end until an E.
            running.stop_at = math.inf
            return
        if stage.blind:
            # It drives into the home end and on, until the axis times out.
            running.stop_at = float(stage.profile.axis(stage.home_axis, True).timeout_s)
            running.error = HOMING_MARKER
            return
        if not first or self._fault is None:
            return  # a scheduled fault lands on the first stage of the next movement
        (kind, fraction, value), self._fault = self._fault, None
        at = fraction * float(durations.max())
        if at > running.stop_at:
            return
        if kind == "stall":
            running.stop_at, running.error = at, 31 + int(value)
        elif kind == "reset":
            running.stop_at, running.reset = at, True
        else:
            self._drop_at = (running.t0 + at, value)

    def _homing_retry(self, running: _Running, stage: _Stage) -> None:
        """farmbot-arduino-firmware 6.6.23 homing an axis with no endstops or encoders:
        the axis times out (R71-R73), it backs off, reports the home displaced and tries
        again, never ending the command."""
        axis = "XYZ"[stage.home_axis]
        self._say(f"R7{stage.home_axis + 1} Q{running.q}")
        self._say(f"R99 timeout {axis} axis")
        self._say(f"R99 homing displaced {axis} axis")
        self._start_stage(running, at=running.t0 + running.stop_at)

    def _arrive(self, running: _Running, stage: _Stage) -> None:
        if stage.home_axis is not None:
            self._offset[stage.home_axis] = 0.0
        if stage.measure_axis is not None:
            axis = stage.measure_axis
            steps = round(self.firmware_position_mm()[axis]
                          * self._profile().axis(axis, False).steps_per_mm)
            self._say(f"R23 P{21 + axis} V0 Q{running.q}")  # the home end is not inverted
            self._say(f"R23 P{801 + axis} V{float(abs(steps)):.2f} Q{running.q}")
        arrived = running.t0 + running.stop_at
        running.stages.pop(0)
        if running.stages:
            self._start_stage(running, at=arrived)
        else:
            self._end_move(running, arrived)

    def _end_move(self, running: _Running, arrived: float) -> None:
        """The motors stopped at the target at simulated time `arrived`: the end-of-move
        reports, then (END_OF_MOVE_S after it) the position and R02; input meanwhile is
        discarded."""
        q, mm = running.q, self.firmware_position_mm()
        xyz = " ".join(f"{a}{v:.2f}" for a, v in zip("XYZ", mm, strict=True))
        self._running = None
        self._say("R99 stopped")
        for line in (f"R05 X0 Y0 Z0 Q{q}", f"R81 XA0 XB0 YA0 YB0 ZA0 ZB0 Q{q}",
                     f"R84 {xyz} Q{q}", f"R85 {xyz} Q{q}"):
            self._say(line)
        self._closing = (q, arrived + END_OF_MOVE_S)

    def _stalled_or_timed_out(self, running: _Running) -> None:
        if running.error != _ERR_TIMEOUT:
            axis = "XYZ"[running.error - 31]
            self._say(f"R99 deactivate motor {axis} due to missed steps")
            # The obstruction is still there: every retry stalls at once.
            for _ in range(1, int(self._params.get(5, 1))):
                self._say(f"R07 Q{running.q}")
                self._say(f"R99 deactivate motor {axis} due to missed steps")
        else:
            self._say("R99 timeout")
        self._finish(running.error)

    def _finish(self, error: int) -> None:
        """End the running command where the gantry is now: its position, then R02 or
        R03 V<error>."""
        running = self._running
        self._running = None
        if running.stages:  # stopped part way (arrival has set the joints already)
            self._set_joints(self._along(running, min(self.now() - running.t0,
                                                      running.stop_at)))
        self._say(self._position_report(running.q))
        self._say(f"R03 V{error} Q{running.q}" if error else f"R02 Q{running.q}")
        self._answered_at = min(self.now(), running.t0 + running.stop_at)
        self._next_report = self.now() + self._report_period()

    def _emergency_stop(self) -> None:
        """E: the firmware locks and the servos lose their pulses; a running command stops
        as on the real board (`STOP_ACK_S`, `STOP_DONE_S`), an idle board at once."""
        self._locked = True
        self._servos.clear()
        if self._running is not None and self._stopping is None:
            now = self.now()
            running = self._running
            # The motors run on until the firmware acknowledges the stop.
            running.stop_at = min(running.stop_at, now - running.t0 + STOP_ACK_S)
            running.error, running.reset = _ERR_EMERGENCY_STOP, False
            self._stopping = _Stopping(running.q, now, next_report=now + STOP_ACK_S)

    def _advance_stop(self, now: float) -> None:
        """The stop's reports as simulated time passes: R87, positions, then R03 V1."""
        stop = self._stopping
        running = self._running
        if running is not None and now - running.t0 >= running.stop_at:
            self._set_joints(self._along(running, running.stop_at))
            self._running = None
        if now < stop.next_report:
            return
        if not stop.acknowledged:
            stop.acknowledged = True
            self._say(f"R87 Q{stop.q}")
            self._say("R99 emergency stop")
        if now >= stop.at + STOP_DONE_S:
            self._stopping = None
            self._say(self._position_report(stop.q))
            self._say(f"R03 V{_ERR_EMERGENCY_STOP} Q{stop.q}")
            self._answered_at = stop.at + STOP_DONE_S
            self._input.clear()
            self._next_report = now + self._report_period()
            return
        self._say(self._position_report(stop.q))
        stop.next_report = min(now + STOP_REPORT_S, stop.at + STOP_DONE_S)

    def describe(self) -> dict:
        """The device's settings, for scan.json."""
        return {"device": "virtual Farmduino", "firmware": FIRMWARE_VERSION,
                "time_scale": self.time_scale, "path": self.path}
