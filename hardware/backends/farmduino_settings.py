"""The Farmduino's parameters as the serial client reads and writes them at every start of
the board: the bot's own settings written and read back (`write_settings`), the parameters
the client needs (`read_parameters`), and the travel cut to the calibrated axis lengths
(`travel_limits`).

`ask` is the client's way to send one command and get its replies (raising the command's
typed error when it fails).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np

from flowerpose.hardware.bot import BotInfo
from flowerpose.hardware.bot_errors import BotError
from flowerpose.hardware.motion import MotionProfile
from flowerpose.hardware.protocol import (
    AXIS_LENGTHS,
    CONFIG_APPROVED,
    ENCODERS,
    ENDSTOPS,
    MOTION_PARAMETERS,
    MOVEMENT_RETRIES,
    PARAMETER_VALUE,
    Reply,
    describe,
    read_parameter_line,
    write_parameter_line,
)

READ_PARAMETERS = (CONFIG_APPROVED, MOVEMENT_RETRIES,
                   *sorted({pid for ids in MOTION_PARAMETERS.values() for pid in ids}),
                   *AXIS_LENGTHS.values(), *ENDSTOPS.values(), *ENCODERS.values())
"""Parameters read at connect (`protocol`'s tables): the configuration approved, the
movement retries, the motion model's, the axis lengths, and what homing needs (endstops,
encoders)."""
_OPTIONAL_PARAMETERS = {*ENDSTOPS.values(), *ENCODERS.values()}
"""Read when the firmware has them; without them homing is not checked beforehand."""
_Z_HOME_FALLBACK = {44: 43, 64: 63, 74: 73}
"""A firmware without Z's own "toward home" settings moves Z up with its other settings."""

Ask = Callable[[str], list[Reply]]


def _reported(replies: list[Reply], pid: int) -> float | None:
    """The value an F21's replies give parameter `pid` (its R21), None when none does."""
    return next((r.values.get("V") for r in replies
                 if r.code == PARAMETER_VALUE and r.values.get("P") == pid), None)


def write_settings(ask: Ask, settings: dict[int, float], port: str) -> None:
    """Write the bot's settings (F22) and read each back (F21); BotError naming the first
    that did not take."""
    for pid, value in settings.items():
        ask(write_parameter_line(pid, value))
    for pid, value in settings.items():
        held = _reported(ask(read_parameter_line(pid)), pid)
        if held is None or round(held) != round(value):
            raise BotError(f"serial {port}: firmware parameter {describe(pid)} did not take: "
                           f"wrote {round(value)}, the board holds "
                           f"{'nothing' if held is None else f'{held:g}'}; the bot will not "
                           "move on settings it does not hold (check the value, and the "
                           "firmware version against the web app's)")


def read_parameters(ask: Ask, port: str) -> dict[int, float]:
    """`READ_PARAMETERS` as the board holds them (F21); an uncalibrated axis length is 0,
    Z's own homing settings fall back to its others, and a parameter the client cannot do
    without that the firmware does not report is a BotError."""
    params: dict[int, float] = {}
    for pid in READ_PARAMETERS:
        value = _reported(ask(read_parameter_line(pid)), pid)
        if value is not None:
            params[pid] = value
        elif pid in AXIS_LENGTHS.values():
            params[pid] = 0.0  # not calibrated
        elif pid not in _Z_HOME_FALLBACK and pid not in _OPTIONAL_PARAMETERS:
            raise BotError(f"serial {port}: the firmware does not report parameter {pid} "
                           "(F21); is it FarmBot's Farmduino firmware 6.x?")
    for pid, fallback in _Z_HOME_FALLBACK.items():
        params.setdefault(pid, params[fallback])
    return params


def travel_limits(base: BotInfo, params: dict[int, float], profile: MotionProfile,
                  firmware: str | None) -> BotInfo:
    """`base` with the firmware's version and motion, its travel cut to the calibrated axis
    lengths (parameters 141-143, in steps; 0 is not calibrated), metres, bed frame."""
    low, high, home = np.array(base.travel_min), np.array(base.travel_max), base.home
    for i, axis in enumerate((profile.x, profile.y, profile.z)):
        steps = params.get(AXIS_LENGTHS["xyz"[i]], 0.0)
        if steps > 0:
            length = steps / axis.steps_per_m
            if i < 2:
                high[i] = min(high[i], home[i] + length)
            else:
                low[i] = max(low[i], home[i] - length)
    return replace(base, firmware=firmware, motion=profile,
                   travel_min=tuple(map(float, low)), travel_max=tuple(map(float, high)))
