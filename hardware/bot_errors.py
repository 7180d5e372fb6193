"""Typed errors of the bot: hardware faults and refusals, each saying what to do about it.

Hierarchy (everything a bot raises for a fault is a `BotError`):

    BotError                      the operation did not complete
      FirmwareError               the Farmduino firmware reported a failure (.code, .command)
        EmergencyStopError        R03 V1   emergency stop during the command
        MoveTimeoutError          R03 V2   an axis outran its timeout (parameters 11-13)
        StallError                R03 V3, V31-33   missed steps (.axis "x"/"y"/"z" or None)
        CalibrationError          R03 V4   axis length measurement (F14-F16) failed
        AbortedError              R03 V5   the move was aborted (@)
        InvalidCommandError       R03 V14  the firmware rejected the command
        NoConfigError             R03 V15  parameters not accepted
        UnknownCommandError       R09      the firmware does not know the command
        LockedError               R87      refused: locked by an emergency stop
        NotConfiguredError        R88      refused: configuration not approved
      CommandTimeoutError         no final reply (R02, R03, R09, R87, R88) in time
      ConnectionLostError         the serial port or the cloud link dropped
      CameraError                 the camera could not deliver or record frames

`error_for_code(code, command)` turns an R03 code into its class. Requests the bot cannot
carry out because of the request itself (a target outside the travel, a head angle out of
range, a bad speed fraction) are the user's to fix: `OutOfRangeError`, an `InputError`.
"""

from __future__ import annotations

from flowerpose.errors import InputError, PicklableError

_AXIS_CODES = {31: "x", 32: "y", 33: "z"}


class BotError(PicklableError):
    """The bot did not complete an operation. `str(error)` is one line: what happened,
    then what to do."""


class FirmwareError(BotError):
    """The firmware reported a failure of `command` (the line sent, or the operation).

    code: the R03 error code, None for the replies that carry none (R09, R87, R88).
    reply: the firmware's reply that reported it ("R03", "R09", "R87" or "R88").
    """

    reply = "R03"
    what = "unknown firmware error"
    todo = "check the bot and the firmware's R99 messages"

    def __init__(self, command: str, code: int | None = None):
        self.command = command
        self.code = code
        super().__init__(f"{command}: {self._what()} ({self._tag()}); {self.todo}")

    def _tag(self) -> str:
        return f"R03 V{self.code}" if self.code is not None else self.reply

    def _what(self) -> str:
        return self.what


class EmergencyStopError(FirmwareError):
    what = "emergency stop: the motors stopped and the firmware is locked"
    todo = ("check the bot, then unlock (F09); the servos need their angles again "
            "after unlocking")


class _AxisFirmwareError(FirmwareError):
    """A failure on one axis: `.axis` is "x", "y", "z", or None when not known."""

    def __init__(self, command: str, code: int | None = None, axis: str | None = None):
        self.axis = axis or _AXIS_CODES.get(code)
        super().__init__(command, code)

    def _what(self) -> str:
        axis = f"the {self.axis.upper()} axis" if self.axis else "an axis"
        return self.what.format(axis=axis)


class MoveTimeoutError(_AxisFirmwareError):
    what = "{axis} was still moving when its timeout (parameters 11-13) ran out"
    todo = ("look for an obstruction or a slipping belt; raise the timeout for long slow "
            "moves")


class StallError(_AxisFirmwareError):
    what = "stall: {axis} missed steps and stopped"
    todo = "clear the obstruction, then home the axis: its position is no longer certain"


class CalibrationError(FirmwareError):
    what = "the axis length measurement (F14-F16) failed"
    todo = "check the endstops or encoders and measure again"


class AbortedError(FirmwareError):
    what = "the move was aborted"
    todo = "send the move again"


class InvalidCommandError(FirmwareError):
    what = "the firmware rejected the command as invalid"
    todo = "check the command's values (millimetres, fixed-point numbers)"


class NoConfigError(FirmwareError):
    what = "the firmware's parameters are not accepted"
    todo = "send the parameters and approve them (F22 P2 V1)"


class UnknownCommandError(FirmwareError):
    reply = "R09"
    what = "the firmware does not know this command"
    todo = "check the command against the firmware version (F83)"


class LockedError(FirmwareError):
    reply = "R87"
    what = "refused: locked by an emergency stop"
    todo = "unlock (F09) after checking the bot"


class NotConfiguredError(FirmwareError):
    reply = "R88"
    what = "refused: the firmware's configuration is not approved"
    todo = "send the parameters and approve them (F22 P2 V1)"


_R03_CLASSES: dict[int, type[FirmwareError]] = {
    1: EmergencyStopError, 2: MoveTimeoutError, 3: StallError, 4: CalibrationError,
    5: AbortedError, 14: InvalidCommandError, 15: NoConfigError,
    31: StallError, 32: StallError, 33: StallError,
}


def error_for_code(code: int, command: str) -> FirmwareError:
    """The error for the firmware's `R03 V<code>` reply to `command`; a code this module
    does not know still gives a FirmwareError that carries it."""
    return _R03_CLASSES.get(code, FirmwareError)(command, code)


class HomingError(BotError):
    """Home cannot be found, or was not: no endstops or encoders on the axis, or the
    firmware reported the homing timed out or was displaced (it has been stopped)."""


class CommandTimeoutError(BotError):
    """No final reply to `command` within `timeout_s` seconds."""

    def __init__(self, command: str, timeout_s: float):
        self.command = command
        self.timeout_s = timeout_s
        super().__init__(f"{command}: no final reply within {timeout_s:.1f} s; the board may "
                         "have reset or the link stalled: check the connection and read the "
                         "position before moving again")


class ConnectionLostError(BotError):
    """The link to the bot (`link`: a serial port, the cloud) dropped."""

    def __init__(self, link: str, detail: str = ""):
        self.link = link
        super().__init__(f"{link}: connection lost{f' ({detail})' if detail else ''}; "
                         "reconnect, then home before moving: opening the port resets "
                         "the board")


class CameraError(BotError):
    """The camera could not deliver or record frames."""


class OutOfRangeError(InputError):
    """A request the bot cannot carry out as asked: a target outside the travel limits, a
    head angle out of range, a speed fraction outside (0, 1]. The user's to fix."""


class PositionLostError(BotError):
    """The Farmduino's counters do not locate the gantry: the board started (the port was
    opened, or it restarted on its own) and no home() has run since."""

    def __init__(self, command: str, why: str):
        self.command = command
        super().__init__(f"{command}: {why}; the position is unknown: home the bot "
                         "(home(), Z first) before moving")
