"""FarmBot's motion profile in closed form: when each gantry axis is where during a move.

The Farmduino firmware (6.6, `MovementAxis::calculateSpeed`) steps every axis on its own.
At `s` steps into a move of `L` steps, with ramp length `R`, minimum speed `v_min` and
maximum speed `v_max` (steps/s), the axis runs at

    v(s) = v_min + (v_max - v_min) * min(s, L - s, R) / R

so the speed ramps linearly with the DISTANCE travelled (not with time) over the first and
the last `R` steps, cruises at `v_max` in between, and on a move shorter than two ramps
(`L < 2R`) peaks below `v_max` at the halfway point, symmetric about it. Time follows from
dt = ds / v(s): on a ramp with slope k = (v_max - v_min) / R,

    t(s) = ln(1 + k s / v_min) / k        (s / v_min when k = 0)
    s(t) = v_min (exp(k t) - 1) / k       (its inverse)

and a whole move takes 2 t(r) + (L - 2r) / v_max with r = min(R, L / 2). All three axes
start together and finish at their own times: the path is not a straight line, and Z
(25 steps/mm against 5 on X and Y) is five times slower in millimetres per second.

Direction matters. A move toward home (X or Y decreasing, Z going up in the bed frame:
home is min X, min Y and the top of Z) uses the firmware's "toward home" settings, which
differ only on Z (parameters 44, 64, 74 instead of 43, 63, 73). G00's speed override
(A, B, C in steps/s) replaces the configured maximum only when it is lower, and firmware
6.6 applies it only to moves AWAY from home (`setMaxSpeed` sets `motorSpeedMax`; a move
toward home reads `motorSpeedMaxHome`). This module reproduces that.

The model is the firmware's rule with continuous steps. The firmware evaluates v(s) once
per whole step, truncated to whole steps/s, and cruises at max + 1 and max + 2 steps/s;
summed step by step its durations stay within 0.5 % of the ones here (a 1 m X move:
14.536 s against 14.565 s). It times each step in whole ticks of its 64 us movement
interrupt, trunc(15625 / v) of them, which cruises at 411 steps/s instead of 400: by its
own step timing the firmware would be up to 2.6 % faster than this model (a 500 mm X move
8.18 s against 8.31 s). The real firmware, run in an AVR simulator, is slower instead:
8.8-8.9 s for that move. About 0.3 s of it is the end-of-move reports before the final
R02 (END_OF_MOVE_S below); the other 0.2-0.3 s (3-4 %) is time the step
timing does not explain (interrupt ticks lost to the board's other work, its main loop
updating v(s) late) and is not modelled. A client that waits for the reply is not
misled by it; a prediction of when the gantry passes a point can be off by that much.

Units: positions in metres in the bed frame, times in seconds; the firmware's own units
(steps, steps/s, steps/mm) appear only in `AxisMotion`, whose fields are the firmware's
parameters.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace

import numpy as np

from flowerpose.errors import InputError
from flowerpose.hardware.bot_errors import OutOfRangeError
from flowerpose.hardware.protocol import FIRMWARE_DEFAULTS, MOTION_PARAMETERS

# The firmware's defaults (`protocol.FIRMWARE_DEFAULTS`); X and Y belts at 5 steps/mm, the
# Z lead screw at 25.
DEFAULT_STEPS_PER_MM = {name: float(FIRMWARE_DEFAULTS[ids[0]])
                        for name, ids in MOTION_PARAMETERS.items()}
_FIELDS = ("steps_per_mm", "max_speed", "min_speed", "ramp_steps", "timeout_s")


def _check_positive(source: str, name: str, value: float) -> None:
    if not (np.isfinite(value) and value > 0):
        raise InputError(source, f"{name} must be a positive number, got {value!r}")


@dataclass(frozen=True)
class AxisMotion:
    """How the firmware drives one axis in one direction, in the firmware's own units.

    steps_per_mm: motor steps per millimetre of travel (parameters 55-57).
    max_speed: cruise speed, steps/s (parameters 71-73; 74 for Z toward home).
    min_speed: speed at the start and the end of every move, steps/s (61-63; 64).
    ramp_steps: steps over which the speed ramps between min and max, at each end of a
        move (41-43; 44).
    timeout_s: the firmware stops the move with a timeout error (R03 V2) when this axis is
        still moving this long after the move began, seconds (parameters 11-13).
    Defaults are the firmware's: 400 steps/s (80 mm/s on X and Y, 16 mm/s on Z), 50 steps/s,
    300 steps (60 mm on X and Y, 12 mm on Z), 120 s.
    """

    steps_per_mm: float
    max_speed: float = float(FIRMWARE_DEFAULTS[71])
    min_speed: float = float(FIRMWARE_DEFAULTS[61])
    ramp_steps: float = float(FIRMWARE_DEFAULTS[41])
    timeout_s: float = float(FIRMWARE_DEFAULTS[11])

    def __post_init__(self):
        for name in _FIELDS:
            _check_positive("motion profile", name, getattr(self, name))

    @classmethod
    def from_firmware(cls, params: Mapping[int, float], settings: str) -> AxisMotion:
        """The settings set `settings` ("x", "y", "z" or "z_home", `protocol.MOTION_PARAMETERS`)
        from firmware parameters {id: value} as F21 reads them; ids left out take the
        firmware's defaults."""
        default = cls(DEFAULT_STEPS_PER_MM[settings])
        values = {}
        for name, pid in zip(_FIELDS, MOTION_PARAMETERS[settings], strict=True):
            values[name] = float(params.get(pid, getattr(default, name)))
            _check_positive(f"firmware parameter {pid}", name, values[name])
        return cls(**values)

    @property
    def steps_per_m(self) -> float:
        return 1000.0 * self.steps_per_mm

    def overridden(self, speed: float) -> AxisMotion:
        """These settings under a G00 speed override of `speed` steps/s: it replaces
        max_speed only when 0 < speed < max_speed, as the firmware does."""
        return replace(self, max_speed=float(speed)) if 0 < speed < self.max_speed else self


@dataclass(frozen=True)
class MotionProfile:
    """The motion settings of the three gantry axes.

    x, y, z: the settings of each axis (z: moving away from home, i.e. down).
    z_home: Z moving toward home (up), parameters 44, 64, 74; None means the same as z.
    override: G00's A, B, C speed override in steps/s for X, Y, Z; 0 is none. Applied only
        to moves away from home and only where lower than the maximum, as firmware 6.6
        does. Set it with `with_override` or `at_speed`.
    """

    x: AxisMotion = field(default_factory=lambda: AxisMotion(DEFAULT_STEPS_PER_MM["x"]))
    y: AxisMotion = field(default_factory=lambda: AxisMotion(DEFAULT_STEPS_PER_MM["y"]))
    z: AxisMotion = field(default_factory=lambda: AxisMotion(DEFAULT_STEPS_PER_MM["z"]))
    z_home: AxisMotion | None = None
    override: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @classmethod
    def from_firmware(cls, params: Mapping[int, float]) -> MotionProfile:
        """All axes from firmware parameters {id: value} (41-44, 55-57, 61-64, 71-74 and the
        timeouts 11-13); ids left out take the firmware's defaults."""
        return cls(*(AxisMotion.from_firmware(params, name)
                     for name in ("x", "y", "z", "z_home")))

    def axis(self, index: int, toward_home: bool) -> AxisMotion:
        """The settings axis `index` (0 X, 1 Y, 2 Z) moves with in the given direction, the
        speed override applied where the firmware applies it."""
        if toward_home:
            return (self.x, self.y, self.z_home or self.z)[index]
        return (self.x, self.y, self.z)[index].overridden(self.override[index])

    def with_override(self, a: float = 0.0, b: float = 0.0, c: float = 0.0) -> MotionProfile:
        """This profile with G00's speed override A, B, C (steps/s; 0 is none)."""
        return replace(self, override=(float(a), float(b), float(c)))

    def override_for(self, fraction: float) -> tuple[int, int, int]:
        """G00's A, B, C (whole steps/s, at least 1) that run each axis at `fraction` of its
        maximum speed away from home; (0, 0, 0), no override, for a fraction of 1."""
        if not 0.0 < fraction <= 1.0:
            raise OutOfRangeError("speed_fraction", f"must be in (0, 1], got {fraction!r}")
        if fraction == 1.0:
            return (0, 0, 0)
        a, b, c = (max(1, round(fraction * axis.max_speed)) for axis in (self.x, self.y, self.z))
        return (a, b, c)

    def at_speed(self, fraction: float) -> MotionProfile:
        """This profile with the override `override_for(fraction)`."""
        return self.with_override(*self.override_for(fraction))


def _ramp_time(steps: np.ndarray | float, axis: AxisMotion) -> np.ndarray:
    """Seconds to cover `steps` from the start of a ramp (v = min_speed + k * steps)."""
    k = (axis.max_speed - axis.min_speed) / axis.ramp_steps
    if k == 0.0:
        return np.asarray(steps) / axis.min_speed
    return np.log1p(k * np.asarray(steps) / axis.min_speed) / k


def _ramp_steps(t: np.ndarray, axis: AxisMotion) -> np.ndarray:
    """Steps covered `t` seconds after the start of a ramp (the inverse of _ramp_time)."""
    k = (axis.max_speed - axis.min_speed) / axis.ramp_steps
    if k == 0.0:
        return axis.min_speed * t
    return axis.min_speed * np.expm1(k * t) / k


def _phases(steps: float, axis: AxisMotion) -> tuple[float, float, float]:
    """(ramp steps r actually used, seconds of one ramp, total seconds) of a move of `steps`."""
    ramp = min(axis.ramp_steps, 0.5 * steps)
    ramp_s = float(_ramp_time(ramp, axis))
    return ramp, ramp_s, 2.0 * ramp_s + (steps - 2.0 * ramp) / axis.max_speed


def axis_duration(distance_m: float, axis: AxisMotion) -> float:
    """Seconds one axis takes to travel `distance_m` metres (either sign) from rest to rest."""
    return _phases(abs(distance_m) * axis.steps_per_m, axis)[2]


def axis_position(t: np.ndarray | float, start_m: float, end_m: float,
                  axis: AxisMotion) -> np.ndarray:
    """Position (metres) of one axis moving from `start_m` to `end_m` at times `t` (seconds
    from the start of the move; any shape). Before 0 it is at the start; from the move's
    duration on, exactly at the end."""
    t = np.asarray(t, dtype=np.float64)
    steps = abs(end_m - start_m) * axis.steps_per_m
    ramp, ramp_s, total = _phases(steps, axis)
    tc = np.clip(t, 0.0, total)
    rising = _ramp_steps(np.minimum(tc, ramp_s), axis)
    falling = steps - _ramp_steps(np.minimum(total - tc, ramp_s), axis)
    done = np.where(tc <= ramp_s, rising,
                    np.where(tc <= total - ramp_s, ramp + axis.max_speed * (tc - ramp_s),
                             falling))
    position = start_m + np.sign(end_m - start_m) * np.clip(done, 0.0, steps) / axis.steps_per_m
    return np.where(t >= total, end_m, position)


def _toward_home(start: np.ndarray, end: np.ndarray) -> tuple[bool, bool, bool]:
    """Per axis, whether the move heads toward home (X, Y decreasing; Z up, bed frame)."""
    return (bool(end[0] < start[0]), bool(end[1] < start[1]), bool(end[2] > start[2]))


def _endpoints(start_xyz, end_xyz) -> tuple[np.ndarray, np.ndarray]:
    start = np.asarray(start_xyz, dtype=np.float64).reshape(3)
    end = np.asarray(end_xyz, dtype=np.float64).reshape(3)
    return start, end


def axis_motions(start_xyz, end_xyz, profile: MotionProfile) -> tuple[AxisMotion, ...]:
    """The settings each axis (X, Y, Z) uses for the move from `start_xyz` to `end_xyz`
    (bed frame, metres): by direction, with the profile's override where it applies."""
    start, end = _endpoints(start_xyz, end_xyz)
    return tuple(profile.axis(i, home) for i, home in enumerate(_toward_home(start, end)))



END_OF_MOVE_S = 0.3
"""Seconds a move's end takes after the motors stop, before the firmware's final R02: it
reports `R99 stopped`, motors, endstops and encoders (R05, R81, R84, R85), then R82 (about
0.3 s on farmbot-arduino-firmware 6.6.23 in an AVR simulator). The gantry stands at its
target meanwhile. The virtual Farmduino takes it, and so does `KinematicBot`, so the direct
and the serial backends' scans keep the same time."""

def axis_durations(start_xyz, end_xyz, profile: MotionProfile) -> np.ndarray:
    """(3,) seconds each axis (X, Y, Z) takes for the move from `start_xyz` to `end_xyz`."""
    start, end = _endpoints(start_xyz, end_xyz)
    axes = axis_motions(start, end, profile)
    return np.array([axis_duration(end[i] - start[i], axes[i]) for i in range(3)])


def move_duration(start_xyz, end_xyz, profile: MotionProfile) -> float:
    """Seconds the gantry takes from `start_xyz` to `end_xyz` (bed frame, metres): the
    slowest axis's time."""
    return float(axis_durations(start_xyz, end_xyz, profile).max())


def move_trajectory(t: np.ndarray, start_xyz, end_xyz, profile: MotionProfile) -> np.ndarray:
    """(len(t), 3) gantry positions (bed frame, metres) at times `t` (seconds from the start
    of the move, shape (T,)) on the move from `start_xyz` to `end_xyz`, each axis on its
    own profile; rows at or after an axis's own duration sit exactly on its target."""
    start, end = _endpoints(start_xyz, end_xyz)
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    axes = axis_motions(start, end, profile)
    return np.stack([axis_position(t, start[i], end[i], axes[i]) for i in range(3)], axis=1)
