"""The virtual Farmduino's firmware: what each command does, and how the gantry moves,
times out, homes and stops, as farmbot-arduino-firmware 6.6 does (`virtual_farmduino`'s
docstring says it all). `FirmwareBehaviour` is mixed into `VirtualFarmduino`, whose state
it reads and changes (the parameters, the joints, the command running, the stop) and whose
line it answers on (`_say`, `_done`). Units as there.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field, replace

import numpy as np

from flowerpose.hardware.geometry import PAPER_BOT
from flowerpose.hardware.motion import (
    END_OF_MOVE_S,
    MotionProfile,
    axis_durations,
    axis_motions,
    move_trajectory,
)
from flowerpose.hardware.protocol import (
    AXIS_LENGTH,
    COMMAND_ALIASES,
    COMMANDS,
    COMMANDS_WHILE_LOCKED,
    DONE,
    ECHO,
    ENCODER_RAW,
    ENCODER_SCALED,
    ENCODERS,
    ENDSTOP_STATES,
    ENDSTOPS,
    ERROR,
    ERROR_EMERGENCY_STOP,
    ERROR_TIMEOUT,
    LOCKED,
    MOTOR_STATE,
    MOVEMENT_COMMANDS,
    NOT_CONFIGURED,
    PARAMETER_VALUE,
    PIN_VALUE,
    RETRY,
    SERVO_PINS,
    STARTED,
    STATUS_VALUE,
    TEXT,
    UNKNOWN,
    VERSION,
)

FIRMWARE_VERSION = "6.6.23.V.virtual"
STOP_ACK_S = 0.05
"""Simulated seconds from an `E` during a command to the firmware's `R87 Q<n>`; the motors
run on until then (farmbot-arduino-firmware 6.6.23 on an ATmega2560: within about 50 ms)."""
STOP_DONE_S = 0.235
"""... and to its `R03 V1 Q<n>`, the end of the stop (measured: 220-250 ms). Input that
arrives before it is discarded."""
STOP_REPORT_S = 0.1
"""Simulated seconds between the position reports the firmware sends while it stops."""
HOMING_MARKER = -1
"""`Running.error` of a homing stage without endstops or encoders: the axis timeout ends
it, and the firmware tries again, for good."""

SERVO_JOINTS = {6: 3, 5: 4}
"""The servo pins that turn the head, and their joints' places in `joints` (yaw, pitch)."""

_NUMBER = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)")


def _atof(text: str) -> float:
    """The leading number of `text`, 0 when there is none (C's atof)."""
    match = _NUMBER.match(text)
    return float(match.group()) if match else 0.0


@dataclass
class Stage:
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
class Stopping:
    """An emergency stop in progress (simulated seconds)."""

    q: int
    at: float
    """When the `E` arrived."""
    acknowledged: bool = False
    next_report: float = 0.0


@dataclass
class Running:
    """A movement command in progress. Times are simulated seconds; `stop_at` is when the
    current stage ends, by arrival (`error` 0) or by a fault or timeout (`error` > 0, or
    `reset`: the board restarts there)."""

    q: int
    stages: list[Stage]
    t0: float = 0.0
    start: np.ndarray = field(default_factory=lambda: np.zeros(3))
    stop_at: float = 0.0
    error: int = 0
    reset: bool = False


class FirmwareBehaviour:
    """The firmware's commands and motion, for `VirtualFarmduino` (see the module
    docstring)."""

    # --- commands ---------------------------------------------------------------------

    def _execute(self, line: str, echo: str | None = None) -> None:
        """One command line; `echo` is what the firmware echoes, the sender's carriage
        return included (the real firmware keeps it)."""
        self.received.append(line)
        self._say(f"{ECHO} *{line if echo is None else echo}*")
        tokens = line.split()
        code = COMMAND_ALIASES.get(tokens[0], tokens[0])
        values: dict[str, float] = {}
        if code[0] in "GF":
            for token in tokens[1:]:
                values.setdefault(token[0], _atof(token[1:]))
        q = int(values.get("Q", 0))
        if self._locked and code not in COMMANDS_WHILE_LOCKED:
            self._say(f"{LOCKED} Q{q}")
            return
        if code in MOVEMENT_COMMANDS and self._params.get(2) != 1:
            self._say(f"{NOT_CONFIGURED} Q{q}")
            return
        handler = getattr(self, f"_cmd_{code}", None) if code in COMMANDS else None
        if handler is None:
            self._say(f"{UNKNOWN} Q{q}")
            return
        self._say(f"{STARTED} Q{q}")
        handler(q, values)

    def _done(self, q: int) -> None:
        self._say(f"{DONE} Q{q}")

    def _to_physical(self, axis: int, mm: float) -> float:
        """The physical joint (metres) of a firmware coordinate on `axis`, in whole steps
        (the firmware truncates to its step counter)."""
        per_mm = self._profile().axis(axis, False).steps_per_mm
        return math.trunc(mm * per_mm) / per_mm / 1000.0 + self._offset[axis]

    def _cmd_G00(self, q: int, values: dict[str, float]) -> None:
        end = np.array([self._to_physical(i, values.get(a, 0.0)) for i, a in enumerate("XYZ")])
        speeds = (values.get("A", 0), values.get("B", 0), values.get("C", 0))
        profile = self._profile().with_override(*(int(s) for s in speeds))
        self._begin(q, [Stage(end, profile)])

    def _cmd_G28(self, q: int, values: dict[str, float]) -> None:
        profile, stages = self._profile(), []
        end = self._physical()
        for axis in (2, 1, 0):
            end = end.copy()
            end[axis] = self._offset[axis]
            stages.append(Stage(end, profile))
        self._begin(q, stages)

    def _home(self, q: int, axis: int) -> None:
        name = "xyz"[axis]
        blind = not (self._params.get(ENDSTOPS[name]) or self._params.get(ENCODERS[name]))
        end = self._physical()
        end[axis] = 0.0
        self._begin(q, [Stage(end, self._profile(), home_axis=axis, blind=blind)])

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
        stages = [Stage(home, profile, home_axis=axis, blind=blind, calibrating=True)]
        if not blind:
            far = home.copy()
            # The far end: the travel from home, downward for Z (its joint runs <= 0).
            far[axis] = -PAPER_BOT.travel_m[2] if axis == 2 else PAPER_BOT.travel_m[axis]
            stages.append(Stage(far, profile, calibrating=True, measure_axis=axis))
        self._begin(q, stages)

    def _cmd_F14(self, q: int, values: dict[str, float]) -> None:
        self._measure(q, 0)

    def _cmd_F15(self, q: int, values: dict[str, float]) -> None:
        self._measure(q, 1)

    def _cmd_F16(self, q: int, values: dict[str, float]) -> None:
        self._measure(q, 2)

    def _cmd_F31(self, q: int, values: dict[str, float]) -> None:
        """Read a status value (the firmware keeps one, "general", at 0)."""
        self._say(f"{STATUS_VALUE} P{int(values.get('P', 0))} V0 Q{q}")
        self._done(q)

    def _cmd_F32(self, q: int, values: dict[str, float]) -> None:
        """The firmware's F32 reads a status value too (the same handler as F31)."""
        self._cmd_F31(q, values)

    def _cmd_F20(self, q: int, values: dict[str, float]) -> None:
        """Report every parameter."""
        for pid in sorted(self._params):
            self._say(f"{PARAMETER_VALUE} P{pid} V{self._params[pid]:g} Q{q}")
        self._done(q)

    def _cmd_F81(self, q: int, values: dict[str, float]) -> None:
        """Report the endstops: none is wired to this board, so none is pressed."""
        self._say(f"{ENDSTOP_STATES} XA0 XB0 YA0 YB0 ZA0 ZB0 Q{q}")
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
            self._say(f"{PARAMETER_VALUE} P{pid} V{self._params[pid]:g} Q{q}")
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
        self._say(f"{PIN_VALUE} P{pin} V{self._pins.get(pin, 0)} Q{q}")
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
        self._say(f"{VERSION} {FIRMWARE_VERSION} Q{q}")
        self._done(q)

    # --- movement ---------------------------------------------------------------------

    def _along(self, running: Running, t: float) -> np.ndarray:
        stage = running.stages[0]
        return move_trajectory([t], running.start, stage.end, stage.profile)[0]

    def _begin(self, q: int, stages: list[Stage]) -> None:
        self._running = Running(q, stages)
        self._start_stage(self._running, first=True)

    def _start_stage(self, running: Running, first: bool = False,
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
            running.stop_at, running.error = min(late), ERROR_TIMEOUT
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

    def _homing_retry(self, running: Running, stage: Stage) -> None:
        """farmbot-arduino-firmware 6.6.23 homing an axis with no endstops or encoders:
        the axis times out (R71-R73), it backs off, reports the home displaced and tries
        again, never ending the command."""
        axis = "XYZ"[stage.home_axis]
        self._say(f"R7{stage.home_axis + 1} Q{running.q}")
        self._say(f"{TEXT} timeout {axis} axis")
        self._say(f"{TEXT} homing displaced {axis} axis")
        self._start_stage(running, at=running.t0 + running.stop_at)

    def _arrive(self, running: Running, stage: Stage) -> None:
        if stage.home_axis is not None:
            self._offset[stage.home_axis] = 0.0
        if stage.measure_axis is not None:
            axis = stage.measure_axis
            steps = round(self.firmware_position_mm()[axis]
                          * self._profile().axis(axis, False).steps_per_mm)
            self._say(f"{AXIS_LENGTH} P{21 + axis} V0 Q{running.q}")  # the home end is not inverted
            self._say(f"{AXIS_LENGTH} P{801 + axis} V{float(abs(steps)):.2f} Q{running.q}")
        arrived = running.t0 + running.stop_at
        running.stages.pop(0)
        if running.stages:
            self._start_stage(running, at=arrived)
        else:
            self._end_move(running, arrived)

    def _end_move(self, running: Running, arrived: float) -> None:
        """The motors stopped at the target at simulated time `arrived`: the end-of-move
        reports, then (END_OF_MOVE_S after it) the position and R02; input meanwhile is
        discarded."""
        q, mm = running.q, self.firmware_position_mm()
        xyz = " ".join(f"{a}{v:.2f}" for a, v in zip("XYZ", mm, strict=True))
        self._running = None
        self._say(f"{TEXT} stopped")
        for line in (f"{MOTOR_STATE} X0 Y0 Z0 Q{q}",
                     f"{ENDSTOP_STATES} XA0 XB0 YA0 YB0 ZA0 ZB0 Q{q}",
                     f"{ENCODER_SCALED} {xyz} Q{q}", f"{ENCODER_RAW} {xyz} Q{q}"):
            self._say(line)
        self._closing = (q, arrived + END_OF_MOVE_S)

    def _stalled_or_timed_out(self, running: Running) -> None:
        if running.error != ERROR_TIMEOUT:
            axis = "XYZ"[running.error - 31]
            self._say(f"{TEXT} deactivate motor {axis} due to missed steps")
            # The obstruction is still there: every retry stalls at once.
            for _ in range(1, int(self._params.get(5, 1))):
                self._say(f"{RETRY} Q{running.q}")
                self._say(f"{TEXT} deactivate motor {axis} due to missed steps")
        else:
            self._say(f"{TEXT} timeout")
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
        self._say(f"{ERROR} V{error} Q{running.q}" if error else f"{DONE} Q{running.q}")
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
            running.error, running.reset = ERROR_EMERGENCY_STOP, False
            self._stopping = Stopping(running.q, now, next_report=now + STOP_ACK_S)

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
            self._say(f"{LOCKED} Q{stop.q}")
            self._say(f"{TEXT} emergency stop")
        if now >= stop.at + STOP_DONE_S:
            self._stopping = None
            self._say(self._position_report(stop.q))
            self._say(f"{ERROR} V{ERROR_EMERGENCY_STOP} Q{stop.q}")
            self._answered_at = stop.at + STOP_DONE_S
            self._input.clear()
            self._next_report = now + self._report_period()
            return
        self._say(self._position_report(stop.q))
        stop.next_report = min(now + STOP_REPORT_S, stop.at + STOP_DONE_S)
