"""The Farmduino firmware's protocol facts, one owner for them: the startup banner, the
replies that end a command, the servo pins, the grammar of the lines a client sends and
reads (`parse_reply`, `move_line`, `servo_line`, `checked_line`), and the parameters (ids,
the names FarmBot OS and the web app give them, the firmware's defaults, and the bot's own
settings as the web app exports them).

The table is farmbot-arduino-firmware 6.x's (its README, "Arduino parameter numbers"), with
FarmBot OS's names (`FarmbotFirmware.Param`), which are the keys of the web app's firmware
settings. FarmBot OS writes a bot's settings to the board every time it connects; with the
Farmduino on our own serial port nobody does, and after a reset the firmware runs on its
defaults unless parameter 3 (use EEPROM) was stored as 1. `read_settings` reads the settings a
user exports, for `FarmduinoBot(settings=...)` to write and check.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from flowerpose.errors import InputError
from flowerpose.hardware.bot_errors import BotError, OutOfRangeError
from flowerpose.jsonio import read_json

# The reply codes the client reads (farmbot-arduino-firmware 6.x, "Codes received").
IDLE = "R00"
"""Idle: reported every few seconds while nothing runs (Q0)."""
STARTED = "R01"
DONE = "R02"
"""The command finished."""
ERROR = "R03"
"""The command failed (`V<code>`: `bot_errors.error_for_code`)."""
BUSY = "R04"
MOTOR_STATE = "R05"
"""Which motors run (reported after a stop)."""
RETRY = "R07"
"""A movement retried after missed steps."""
ECHO = "R08"
"""The command as the firmware read it, between asterisks."""
UNKNOWN = "R09"
"""The command is not one the firmware knows."""
PARAMETER_VALUE = "R21"
"""A parameter's value, `P<id> V<value>`, the reply to `read_parameter_line`."""
AXIS_LENGTH = "R23"
"""A calibration's measured axis length, steps (`P801`-`P803`)."""
STATUS_VALUE = "R31"
PIN_VALUE = "R41"
HOMING_TIMEOUTS = {"R71": "x", "R72": "y", "R73": "z"}
"""A homing that timed out on this axis."""
ENDSTOP_STATES = "R81"
POSITION = "R82"
"""The position, `X Y Z` in millimetres, the reply to `POSITION_LINE` and reported while
moving."""
VERSION = "R83"
"""The firmware's version, the reply to `VERSION_LINE`."""
ENCODER_SCALED = "R84"
ENCODER_RAW = "R85"
LOCKED = "R87"
"""Locked after an emergency stop: nothing but `UNLOCK_LINE` runs."""
NOT_CONFIGURED = "R88"
"""The parameters were never approved (`approve_line`)."""
TEXT = "R99"
"""Free text; at a (re)start `R99 ARDUINO TEXT COMPLETE`, during a homing its reasons."""

STARTUP_TEXT = "ARDUINO TEXT COMPLETE"
"""What the firmware's `R99` says when the board has (re)started."""
BANNER = f"{TEXT} {STARTUP_TEXT}"
FINAL_REPLIES = frozenset({DONE, ERROR, UNKNOWN, LOCKED, NOT_CONFIGURED})
"""Replies that end a command: done, error, unknown, locked, not configured (the last
three come without an R03)."""

# The lines the client sends that take no value (the others are built below).
EMERGENCY_STOP = b"E"
"""Read by the firmware as an emergency stop wherever it is, at once (not a line)."""
ABORT = b"@"
"""Read as an abort of the running command, at once (not a line)."""
UNLOCK_LINE = "F09"
"""Unlock after an emergency stop."""
POSITION_LINE = "F82"
VERSION_LINE = "F83"
ZERO_LINE = "F84 X1 Y1 Z1"
"""Make the current position the origin of all three axes."""
HOME_LINES = {"x": "F11", "y": "F12", "z": "F13"}
"""Find one axis's home, which the firmware's counter then calls 0."""
CALIBRATE_LINES = {"x": "F14", "y": "F15", "z": "F16"}
"""Measure one axis's length: to home, then to the far end (`AXIS_LENGTH`)."""
COMMANDS = frozenset({"G00", "G28", "F09", "F11", "F12", "F13", "F14", "F15", "F16", "F20",
                      "F21", "F22", "F31", "F32", "F41", "F42", "F43", "F44", "F61", "F81",
                      "F82", "F83", "F84"})
"""The commands firmware 6.6 knows; another answers `UNKNOWN`."""
COMMAND_ALIASES = {"G0": "G00", "G01": "G00", "G1": "G00", "F9": "F09"}
"""Spellings the firmware reads as another command."""
MOVEMENT_COMMANDS = frozenset({"G00", *HOME_LINES.values(), *CALIBRATE_LINES.values()})
"""The commands that move an axis, refused (`NOT_CONFIGURED`) until the configuration is
approved."""
COMMANDS_WHILE_LOCKED = frozenset({"F09", "F20", "F21", "F22", "F81", "F82", "F83"})
"""The commands still served after an emergency stop; another answers `LOCKED`."""
ERROR_EMERGENCY_STOP, ERROR_TIMEOUT, ERROR_ABORTED = 1, 2, 5
"""The `ERROR` reply's codes (`R03 V<code>`) the client acts on; the errors module names
them all."""
CONFIG_APPROVED = 2
"""The parameter that says the configuration is approved (`param_config_ok`)."""
SERVO_PINS = (4, 5, 6, 11)
"""The only Farmduino pins that drive servos (F61 on another answers R02 and does nothing)."""

PARAMETERS: dict[int, str] = {
    2: "param_config_ok", 3: "param_use_eeprom", 4: "param_e_stop_on_mov_err",
    5: "param_mov_nr_retry",
    11: "movement_timeout_x", 12: "movement_timeout_y", 13: "movement_timeout_z",
    15: "movement_keep_active_x", 16: "movement_keep_active_y", 17: "movement_keep_active_z",
    18: "movement_home_at_boot_x", 19: "movement_home_at_boot_y", 20: "movement_home_at_boot_z",
    21: "movement_invert_endpoints_x", 22: "movement_invert_endpoints_y",
    23: "movement_invert_endpoints_z",
    25: "movement_enable_endpoints_x", 26: "movement_enable_endpoints_y",
    27: "movement_enable_endpoints_z",
    31: "movement_invert_motor_x", 32: "movement_invert_motor_y", 33: "movement_invert_motor_z",
    36: "movement_secondary_motor_x", 37: "movement_secondary_motor_invert_x",
    41: "movement_steps_acc_dec_x", 42: "movement_steps_acc_dec_y",
    43: "movement_steps_acc_dec_z", 44: "movement_steps_acc_dec_z2",
    45: "movement_stop_at_home_x", 46: "movement_stop_at_home_y", 47: "movement_stop_at_home_z",
    51: "movement_home_up_x", 52: "movement_home_up_y", 53: "movement_home_up_z",
    55: "movement_step_per_mm_x", 56: "movement_step_per_mm_y", 57: "movement_step_per_mm_z",
    61: "movement_min_spd_x", 62: "movement_min_spd_y", 63: "movement_min_spd_z",
    64: "movement_min_spd_z2",
    65: "movement_home_spd_x", 66: "movement_home_spd_y", 67: "movement_home_spd_z",
    71: "movement_max_spd_x", 72: "movement_max_spd_y", 73: "movement_max_spd_z",
    74: "movement_max_spd_z2",
    75: "movement_invert_2_endpoints_x", 76: "movement_invert_2_endpoints_y",
    77: "movement_invert_2_endpoints_z",
    81: "movement_motor_current_x", 82: "movement_motor_current_y",
    83: "movement_motor_current_z",
    85: "movement_stall_sensitivity_x", 86: "movement_stall_sensitivity_y",
    87: "movement_stall_sensitivity_z",
    91: "movement_microsteps_x", 92: "movement_microsteps_y", 93: "movement_microsteps_z",
    101: "encoder_enabled_x", 102: "encoder_enabled_y", 103: "encoder_enabled_z",
    105: "encoder_type_x", 106: "encoder_type_y", 107: "encoder_type_z",
    111: "encoder_missed_steps_max_x", 112: "encoder_missed_steps_max_y",
    113: "encoder_missed_steps_max_z",
    115: "encoder_scaling_x", 116: "encoder_scaling_y", 117: "encoder_scaling_z",
    121: "encoder_missed_steps_decay_x", 122: "encoder_missed_steps_decay_y",
    123: "encoder_missed_steps_decay_z",
    125: "encoder_use_for_pos_x", 126: "encoder_use_for_pos_y", 127: "encoder_use_for_pos_z",
    131: "encoder_invert_x", 132: "encoder_invert_y", 133: "encoder_invert_z",
    141: "movement_axis_nr_steps_x", 142: "movement_axis_nr_steps_y",
    143: "movement_axis_nr_steps_z",
    145: "movement_stop_at_max_x", 146: "movement_stop_at_max_y", 147: "movement_stop_at_max_z",
    161: "movement_calibration_retry_x", 162: "movement_calibration_retry_y",
    163: "movement_calibration_retry_z",
    165: "movement_axis_stealth_x", 166: "movement_axis_stealth_y",
    167: "movement_axis_stealth_z",
    171: "movement_calibration_deadzone_x", 172: "movement_calibration_deadzone_y",
    173: "movement_calibration_deadzone_z",
    175: "movement_calibration_retry_total_x", 176: "movement_calibration_retry_total_y",
    177: "movement_calibration_retry_total_z",
    198: "pin_report_1_pin_nr", 199: "pin_report_2_pin_nr",
    201: "pin_guard_1_pin_nr", 202: "pin_guard_1_time_out", 203: "pin_guard_1_active_state",
    205: "pin_guard_2_pin_nr", 206: "pin_guard_2_time_out", 207: "pin_guard_2_active_state",
    211: "pin_guard_3_pin_nr", 212: "pin_guard_3_time_out", 213: "pin_guard_3_active_state",
    215: "pin_guard_4_pin_nr", 216: "pin_guard_4_time_out", 217: "pin_guard_4_active_state",
    221: "pin_guard_5_pin_nr", 222: "pin_guard_5_time_out", 223: "pin_guard_5_active_state",
}
"""Firmware parameter id -> FarmBot OS / web app name."""
IDS: dict[str, int] = {name: pid for pid, name in PARAMETERS.items()}

FIRMWARE_DEFAULTS: dict[int, float] = {
    2: 0, 3: 0, 5: 3,                # configuration approved, use EEPROM, movement retries
    11: 120, 12: 120, 13: 120,       # move timeouts, seconds
    41: 300, 42: 300, 43: 300, 44: 300,  # ramp length, steps (44: Z toward home)
    55: 5, 56: 5, 57: 25,            # steps per millimetre: X and Y belts, the Z lead screw
    61: 50, 62: 50, 63: 50, 64: 50,  # minimum speed, steps/s
    71: 400, 72: 400, 73: 400, 74: 400,  # maximum speed, steps/s
    141: 0, 142: 0, 143: 0,          # axis lengths, steps (0: not measured)
    25: 0, 26: 0, 27: 0,             # endstops off
    101: 0, 102: 0, 103: 0,          # encoders off: such a board cannot find home
}
"""The firmware's defaults (its Config.h) of the parameters flowerpose reads or models: what
a board runs on after a reset unless its EEPROM holds others."""

MOTION_PARAMETERS = {
    "x": (55, 71, 61, 41, 11),
    "y": (56, 72, 62, 42, 12),
    "z": (57, 73, 63, 43, 13),
    "z_home": (57, 74, 64, 44, 13),
}
"""Per settings set of the motion model (`motion.AxisMotion`), its parameters: steps/mm,
maximum speed, minimum speed, ramp and timeout. "z_home" is Z moving toward home (up): its
own speeds and ramp, Z's steps/mm and timeout."""
AXIS_LENGTHS = {"x": 141, "y": 142, "z": 143}
"""Per axis, the parameter holding its measured length, steps (0: not measured)."""
MOVEMENT_RETRIES = 5
"""The parameter holding how many times the firmware retries a failed movement."""
ENDSTOPS = {"x": 25, "y": 26, "z": 27}
"""Per axis, the parameter that enables its endstops (1: on)."""
ENCODERS = {"x": 101, "y": 102, "z": 103}
"""Per axis, the parameter that enables its rotary encoder (1: on)."""

NOT_WRITTEN = frozenset({"param_config_ok", "param_version", "param_test"})
"""Settings FarmBot OS never writes as they are: the configuration is approved last, by the
client (`F22 P2 V1`), once the others are written."""
_RECORD_KEYS = frozenset({"id", "created_at", "updated_at", "device_id", "api_migrated",
                          "param_version", "param_test"})
"""Keys of the web app's record that are not firmware settings."""


def describe(pid: int) -> str:
    """`25 (movement_enable_endpoints_x)`: a parameter as error messages name it."""
    return f"{pid} ({PARAMETERS[pid]})" if pid in PARAMETERS else str(pid)


def read_settings(path: str | Path) -> dict[int, float]:
    """The firmware settings of a web app export: a JSON object of parameter name -> value
    (the web app's firmware settings, or a whole account export holding them under
    "firmware_config"), as parameter id -> value, in the order the firmware numbers them.
    The record's own fields (id, dates) and null values are skipped; an unknown name or a
    value that is not a finite number names the file and the key (InputError)."""
    data = read_json(path)
    if isinstance(data.get("firmware_config"), dict):
        data = data["firmware_config"]
    settings: dict[int, float] = {}
    for name, value in data.items():
        if name in _RECORD_KEYS or value is None:
            continue
        if name not in IDS:
            raise InputError(path, f"unknown firmware parameter {name!r} (known: the names "
                             "of FarmBot OS, e.g. encoder_enabled_x)")
        if (isinstance(value, bool) or not isinstance(value, int | float)
                or not math.isfinite(value)):
            raise InputError(path, f"{name}: the value must be a number, got {value!r}")
        if name not in NOT_WRITTEN:
            settings[IDS[name]] = float(value)
    if not settings:
        raise InputError(path, "holds no firmware parameter to write")
    return dict(sorted(settings.items()))


#: What the firmware reads as an emergency stop, an abort or a line end, wherever it is.
_FORBIDDEN = re.compile(r"[eE@\r\n]")


@dataclass(frozen=True)
class Reply:
    """One line from the firmware: `code` ("R02", ...), its letter fields as numbers, its Q
    (None when it has none) and its text after the code."""

    code: str
    values: dict[str, float]
    q: int | None
    text: str


_CODE = re.compile(r"R\d\d")
_FIELD = re.compile(r"(?<![A-Za-z])([A-Z])(-?\d+(?:\.\d+)?)(?![\w.])")


def parse_reply(line: str) -> Reply | None:
    """The reply in one received line, None for a line without one (noise). Noise before
    the code is dropped; an echo's (R08) Q is the echoed command's, not its own."""
    match = _CODE.search(line)
    if match is None:
        return None
    code, text = match.group(), line[match.end():].strip()
    if code == "R08":
        return Reply(code, {}, None, text)
    values = {letter: float(number) for letter, number in _FIELD.findall(text)}
    q = values.pop("Q", None)
    return Reply(code, values, None if q is None else int(q),
                 re.sub(r"\s*Q\d+$", "", text))


def checked_line(line: str) -> str:
    """`line` if the firmware reads it as one command; BotError for an `e` or `E` (an
    emergency stop to the firmware), an `@` (abort) or a line end inside it."""
    bad = _FORBIDDEN.search(line)
    if bad is not None:
        raise BotError(f"{line!r}: refusing to send {bad.group()!r}, which the Farmduino reads "
                       "as an emergency stop, an abort or a line end; this is a bug")
    return line


def fixed(value: float) -> str:
    """`value` in fixed point with two decimals, never "-0.00": scientific notation's `e`
    would be an emergency stop."""
    return f"{round(float(value), 2) + 0.0:.2f}"


def move_line(xyz_mm, speeds=(0, 0, 0)) -> str:
    """The G00 line to FarmBot coordinates `xyz_mm` ((3,) millimetres, Z <= 0), all three
    axes always; `speeds`: G00's A, B, C in whole steps/s, all 0 for none."""
    xyz = np.asarray(xyz_mm, np.float64)
    if xyz.shape != (3,) or not np.all(np.isfinite(xyz)):
        raise OutOfRangeError("G00", f"needs 3 finite coordinates (mm), got {xyz_mm!r}")
    line = "G00 " + " ".join(f"{axis}{fixed(v)}" for axis, v in zip("XYZ", xyz, strict=True))
    if any(speeds):
        line += " " + " ".join(f"{c}{int(s)}" for c, s in zip("ABC", speeds, strict=True))
    return checked_line(line)


def servo_line(pin: int, degrees: float) -> str:
    """The F61 line turning servo `pin` to `degrees` (0-180), rounded to whole degrees as
    the firmware reads them; OutOfRangeError for a pin that drives no servo or an angle
    outside 0-180 (the firmware would answer R02 and do something else)."""
    if pin not in SERVO_PINS:
        raise OutOfRangeError(f"servo pin {pin}", "only pins 4, 5, 6 and 11 drive servos; "
                              "the firmware answers R02 for any other and does nothing")
    if not (math.isfinite(degrees) and -0.5 < degrees < 180.5):
        raise OutOfRangeError(f"servo pin {pin}", f"{degrees!r} degrees is outside 0-180")
    return checked_line(f"F61 P{pin} V{round(degrees)}")


def read_parameter_line(pid: int) -> str:
    """The F21 line asking parameter `pid`'s value (answered by `PARAMETER_VALUE`)."""
    return checked_line(f"F21 P{int(pid)}")


def write_parameter_line(pid: int, value: float) -> str:
    """The F22 line writing parameter `pid` (the firmware keeps whole numbers)."""
    return checked_line(f"F22 P{int(pid)} V{round(value)}")


def approve_line() -> str:
    """The line approving the configuration once the parameters are written."""
    return write_parameter_line(CONFIG_APPROVED, 1)
