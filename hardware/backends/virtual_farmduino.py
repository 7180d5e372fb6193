"""A virtual Farmduino: FarmBot's firmware protocol on a pseudo-terminal, over a simulated gantry.

`VirtualFarmduino` answers on a real device path that pyserial opens (`os.openpty`), and
keeps a stable symlink to it (`path`, like /dev/serial/by-id) that survives a simulated
reconnect. It behaves as farmbot-arduino-firmware 6.6 does (docs/guides/physical-bot.md,
"The wire protocol"):

- Opening the port resets the board (as DTR does on a real one): `R99 ARDUINO TEXT
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
import select
import shutil
import tempfile
import threading
import time
import tty
from collections.abc import Callable
from pathlib import Path

import numpy as np

from flowerpose.errors import InputError
from flowerpose.hardware.backends.virtual_firmware import (
    FIRMWARE_VERSION,
    HOMING_MARKER,
    FirmwareBehaviour,
    Running,
    Stopping,
)
from flowerpose.hardware.motion import (
    MotionProfile,
)
from flowerpose.hardware.protocol import (
    BANNER,
    BUSY,
    DONE,
    ENCODERS,
    ERROR_ABORTED,
    FIRMWARE_DEFAULTS,
    IDLE,
    LOCKED,
    NOT_CONFIGURED,
    PARAMETER_VALUE,
    PARAMETERS,
    POSITION,
)

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


class VirtualFarmduino(FirmwareBehaviour):
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
        self._running: Running | None = None
        self._closing: tuple[int, float] | None = None  # (Q, simulated time of its R02)
        self._stopping: Stopping | None = None
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
        return f"{POSITION} X{x:.2f} Y{y:.2f} Z{z:.2f} Q{q}"

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
                    self._finish(ERROR_ABORTED)
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
                self._say(f"{PARAMETER_VALUE} P{pid} V{self._params[pid]:g} Q0")
        if self._drop_at is not None and now >= self._drop_at[0]:
            down = self._drop_at[1]
            self._drop_at = None
            self._drop(down)
        if self._stopping is not None:
            self._advance_stop(now)
        if self._closing is not None and now >= self._closing[1]:
            (q, due), self._closing = self._closing, None
            self._say(self._position_report(q))
            self._say(f"{DONE} Q{q}")
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
            self._say(f"{BUSY} Q{busy}")
            self._say(self._position_report(busy))
            return
        self._say(f"{LOCKED} Q0" if self._locked else f"{IDLE} Q0")
        self._say(self._position_report(0))
        if self._params.get(2) != 1:
            self._say(f"{NOT_CONFIGURED} Q0")

    def describe(self) -> dict:
        """The device's settings, for scan.json."""
        return {"device": "virtual Farmduino", "firmware": FIRMWARE_VERSION,
                "time_scale": self.time_scale, "path": self.path}
