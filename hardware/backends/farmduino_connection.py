"""The serial Farmduino client's connection: opening the port, bringing the firmware up
after every start of the board (version, the bot's settings, the parameters, approval, the
lock and the servos, the position), and getting the link back after it drops
(`farmduino`'s docstring says how). `Connection` is mixed into `FarmduinoBot`, whose
command exchange (`_transact`, `_raise_for`) and state it uses.
"""

from __future__ import annotations

import os
import queue
import time
from collections.abc import Callable

import serial

from flowerpose.errors import InputError
from flowerpose.hardware.backends.farmduino_settings import (
    read_parameters,
    travel_limits,
    write_settings,
)
from flowerpose.hardware.backends.serial_link import LinkDropped, SerialLink
from flowerpose.hardware.bot_errors import (
    BotError,
    CommandTimeoutError,
    ConnectionLostError,
    PositionLostError,
)
from flowerpose.hardware.geometry import PITCH_PIN, YAW_PIN, farmbot_mm_to_bed
from flowerpose.hardware.motion import MotionProfile
from flowerpose.hardware.protocol import (
    BANNER,
    EMERGENCY_STOP,
    IDLE,
    LOCKED,
    NOT_CONFIGURED,
    POSITION_LINE,
    VERSION,
    VERSION_LINE,
    Reply,
    approve_line,
    servo_line,
)

BAUD = 115200
REPLY_TIMEOUT_S = 15.0
"""Wall seconds a command that does not move may take to its final reply."""
MAX_RECOVERIES = 3
"""Link drops one command recovers from before it gives up."""


class BoardStarted(PositionLostError):
    """The startup banner came while the port stayed open."""


class Connection:
    """The port and the firmware's bring-up, for `FarmduinoBot` (see the module
    docstring)."""

    def _connect(self, first: bool, deadline: float) -> bool:
        """Open the port and bring the firmware up; returns whether the board (re)started."""
        try:
            self._link = SerialLink(self._port, BAUD)
        except (serial.SerialException, OSError, ValueError) as error:
            number = getattr(error, "errno", None)
            reason = os.strerror(number) if number else str(error)
            if first:
                raise InputError(self._port, f"cannot open the serial port ({reason}); check "
                                 "the device path (ls /dev/serial/by-id), that FarmBot OS does "
                                 "not hold it, and that you may open it (the dialout "
                                 "group)") from None
            raise LinkDropped(self._port, reason) from None
        self._lines = self._link.lines
        restarted, approve = self._await_ready(deadline, first)
        if restarted:
            self._stop_sent = None  # a board that starts has no stop under way
        self._initialise(restarted, approve, first)
        return restarted

    def _await_ready(self, deadline: float, first: bool) -> tuple[bool, bool]:
        """Wait for the startup banner or an idle report: (whether the board started, whether
        the firmware asked for its configuration to be approved)."""
        approve = False
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                what = (f"serial {self._port}: no startup banner ({BANNER}) or idle report "
                        f"(R00) within {self._connect_timeout_s:g} s; check that it is a "
                        "Farmduino with FarmBot's firmware at 115200 baud and that FarmBot OS "
                        "does not hold the port")
                if first:
                    raise BotError(what)
                raise LinkDropped(self._port, "no banner after reopening")
            try:
                item = self._lines.get(timeout=min(remaining, 0.05))
            except queue.Empty:
                continue
            try:
                reply = self._reply(item)
            except BoardStarted:
                return True, approve
            if reply is None:
                continue
            approve = approve or reply.code == NOT_CONFIGURED
            if reply.code == LOCKED:
                self._locked.set()
            if reply.code in (IDLE, LOCKED, NOT_CONFIGURED):
                return False, approve

    def _ask(self, body: str) -> list[Reply]:
        """One command's replies while the firmware is brought up (no recovery: a drop
        here restarts the bring-up); raises the command's typed error."""
        exchange = self._transact(body, REPLY_TIMEOUT_S)
        self._raise_for(exchange)
        return exchange.replies

    def _initialise(self, restarted: bool, approve: bool, first: bool) -> None:
        """Version, parameters, approval, lock and servos, position: after every start."""
        self._firmware = next((r.text for r in self._ask(VERSION_LINE) if r.code == VERSION),
                              None)
        write_settings(self._ask, self._settings, self._port)
        self._params = read_parameters(self._ask, self._port)
        if approve or self._params.get(2) != 1:
            self._ask(approve_line())
        self._info = travel_limits(self._base_info, self._params,
                                   MotionProfile.from_firmware(self._params), self._firmware)
        if restarted:
            self._homed.clear()
        if self._locked.is_set():
            # An emergency stop asked for while the link was down, or before a restart.
            self._write(EMERGENCY_STOP)
            self._stop_sent = time.monotonic()
        elif self._servo is not None:
            for pin, value in zip((YAW_PIN, PITCH_PIN), self._servo, strict=True):
                self._ask(servo_line(pin, value))
        where = self._transact(POSITION_LINE, REPLY_TIMEOUT_S)
        self._raise_for(where)
        # After a restart the counters say 0 wherever the gantry is: keep our estimate.
        if (first or not restarted) and where.position_mm() is not None:
            self._xyz = farmbot_mm_to_bed(where.position_mm())

    def _recover(self, command: str, drop: LinkDropped, attempt: int,
                 interrupted: Callable[[], None] | None = None) -> None:
        """Get the link back after it dropped during `command`, and home when reopening
        restarted the board; ConnectionLostError when that cannot be done. `interrupted`
        is called once the port is back (or given up on): the end of a cut-off move."""
        if self._recovering or attempt >= MAX_RECOVERIES or self._closed:
            if interrupted is not None:
                interrupted()
            raise ConnectionLostError(self._port, f"during {command}: {drop.detail}")
        self._recovering = True
        try:
            try:
                restarted = self._reconnect(command, drop)
            finally:
                if interrupted is not None:
                    interrupted()
            if restarted and not self._locked.is_set():
                for name in "zyx":
                    self._home_axis(name)
        finally:
            self._recovering = False

    def _reconnect(self, command: str, drop: LinkDropped) -> bool:
        """Reopen the port with backoff for up to connect_timeout_s; returns whether the
        board restarted."""
        self._disconnect()
        deadline = time.monotonic() + self._connect_timeout_s
        delay, last = 0.05, drop.detail
        while True:
            if self._closed:
                raise BotError(f"{command}: {self._info.name} was closed")
            try:
                return self._connect(first=False, deadline=deadline)
            except LinkDropped as error:
                last = error.detail
            except CommandTimeoutError as error:
                last = str(error)
            self._disconnect()
            if time.monotonic() + delay > deadline:
                raise ConnectionLostError(self._port, f"{command}: could not reconnect within "
                                          f"{self._connect_timeout_s:g} s: {last}")
            time.sleep(delay)
            delay = min(2 * delay, 1.0)

    def _restarted(self, command: str) -> None:
        """The board restarted with the port open: bring the firmware up again, then stop
        the caller with PositionLostError (a restart of its own wants a person's look)."""
        self._initialise(restarted=True, approve=True, first=False)
        raise PositionLostError(command, f"the Farmduino on {self._port} restarted on its "
                                "own (R99 ARDUINO STARTUP COMPLETE): check its power supply "
                                "and the gantry")

    def _disconnect(self) -> None:
        link, self._link = self._link, None
        if link is not None:
            link.close()
