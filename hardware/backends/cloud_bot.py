"""The FarmBot through FarmBot's web app: the `farmbot` client (PyPI, 2.x) over MQTT.

FarmBot OS runs the commands on the bot; this backend sends them from anywhere the web app
is reachable. Everything at the interface is the bed frame in SI units (bot.py); FarmBot's
millimetres and servo degrees appear only here, converted by hardware/geometry.py and
hardware/kinematics.py.

The client (farmbot 2.x, read from its source): `Farmbot()`, `set_token(token)` or
`get_token(email, password, server)`; `move(x, y, z, speed=percent)` (absolute mm),
`find_home(axis, speed)`, `control_servo(pin, angle)` (whole degrees 0-180),
`read_status()` (the status tree: position, lock, firmware parameters), `e_stop()`,
`unlock()`. Each call publishes one RPC and blocks until FarmBot OS replies or a timeout
runs out (`state.timeout`: "movements" for moves and homing, "listen" otherwise); none
raises for a failure: each leaves a message in `state.error` (None on success), so every
call here is followed by a check that turns it into a typed BotError. The client keeps
one MQTT connection per command group and shares its `state` between them, so the
emergency stop goes through a second client of its own: it can be sent from any thread
while a move blocks in the first.

Timing: the bot's clock is time.monotonic(), which the USB camera stamps frames with. A
command's reply reaches us `reply_latency_s` (an estimate: the broker's relay plus the
client's 0.25 s polling) after the bot finished, so a move's Activity is put to end then,
on the motion profile of the bot's own firmware parameters (read from the status tree;
FarmBot's defaults where missing), and no earlier than it was sent.

Credentials come from the environment or a token file outside the repository
(`cloud_credentials`), the client from `cloud_client`. They are kept in memory only: never
in a repr, a message, a log, a file or scan.json; error messages are scrubbed of them, and
the client prints nothing.
"""

from __future__ import annotations

import json
import math
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from typing import Any

import numpy as np

from flowerpose.errors import InputError
from flowerpose.hardware.backends.cloud_client import (
    broker_lost,
    disconnect,
    farmbot_client,
    secure_broker,
)
from flowerpose.hardware.backends.cloud_credentials import (
    ENV_EMAIL,
    ENV_PASSWORD,
    CloudCredentials,
    parse_token,
)
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
    LockedError,
    MoveTimeoutError,
    StallError,
)
from flowerpose.hardware.geometry import (
    PAPER_BOT,
    PITCH_PIN,
    YAW_PIN,
    BotGeometry,
    bed_to_farmbot_mm,
    farmbot_mm_to_bed,
)
from flowerpose.hardware.kinematics import HeadPose, from_servo_commands, servo_commands
from flowerpose.hardware.motion import (
    MotionProfile,
    move_duration,
    move_trajectory,
)
from flowerpose.hardware.protocol import MOTION_PARAMETERS, PARAMETERS

# The firmware parameters the motion model reads (motion.py), by their names in FarmBot OS's
# status tree, mcu_params.
_MCU_PARAMETERS = {pid: PARAMETERS[pid]
                   for ids in MOTION_PARAMETERS.values() for pid in ids}


class CloudCommandError(BotError):
    """FarmBot OS reported that a command failed, for a reason with no class of its own."""

    def __init__(self, command: str, detail: str):
        self.command = command
        super().__init__(f"{command}: FarmBot OS reported a failure ({detail}); see the "
                         "bot's logs in the web app")


class CloudLinkError(ConnectionLostError):
    """The link to FarmBot's web app, its MQTT broker or the bot itself failed."""

    def __init__(self, link: str, detail: str):
        self.link = link
        BotError.__init__(self, f"{link}: {detail}; check the network, and that the web app "
                          "shows the bot online")


def motion_from_status(mcu_params: Mapping[str, Any] | None) -> MotionProfile:
    """The motion profile of the firmware parameters in a status tree's mcu_params
    (FarmBot's defaults for those missing or unset)."""
    mcu = mcu_params or {}
    values = {pid: float(mcu[name]) for pid, name in _MCU_PARAMETERS.items()
              if isinstance(mcu.get(name), int | float) and not isinstance(mcu.get(name), bool)}
    return MotionProfile.from_firmware(values)


def account_token(client: Any, credentials: CloudCredentials, link: str,
                  secrets: list[str]) -> dict:
    """The FarmBot token to use: the credentials' own, else the one FarmBot's server gives
    `client` for their email and password (its encoded part then joins `secrets`, the
    strings every message is scrubbed of). A refused password is an InputError; a server
    that cannot be reached, a CloudLinkError naming `link`."""
    token = credentials._token
    if token is not None:
        return token
    client.state.error = None
    try:
        client.get_token(credentials._email, credentials._password, credentials.server)
    except Exception as err:  # noqa: BLE001 - the client's own failures, scrubbed
        raise CloudLinkError(link, _scrubbed(f"log in: {err}", secrets)) from None
    token = getattr(client.state, "token", None)
    if not token or client.state.error:
        error = _scrubbed(str(client.state.error or "no token"), secrets)
        if "password" in error.lower() or "422" in error:
            raise InputError(f"{ENV_EMAIL} and {ENV_PASSWORD}", "FarmBot's server "
                             "refused the login: wrong email or password") from None
        raise CloudLinkError(link, f"log in: {error}")
    token = parse_token(json.dumps(token), "FarmBot's login reply")
    secrets.append(token["token"]["encoded"])
    return token


def _scrubbed(text: str, secrets: list[str]) -> str:
    """`text` with every secret replaced by ***."""
    for secret in secrets:
        if secret:
            text = text.replace(secret, "***")
    return text


def account_plants(credentials: CloudCredentials | None = None,
                   client_factory: Callable[[], Any] | None = None) -> list[dict]:
    """The plants of the FarmBot account's garden, as its web app's REST API gives them
    (`/api/points` of pointer_type "Plant": name, x, y, z and radius in FarmBot's
    millimetres): what `flowerpose field --cloud` makes a bed of. Logs in as
    `FarmbotCloudBot` does; the bot need not be online. CloudLinkError (naming the server,
    never a secret) where the server cannot be reached or answers with an error."""
    credentials = credentials or CloudCredentials.from_environment()
    link = f"FarmBot web app ({credentials.server})"
    secrets = credentials.secrets()
    client = (client_factory or farmbot_client)()
    client.set_verbosity(0)  # the client would print every reply
    client.set_token(account_token(client, credentials, link, secrets))
    client.state.error = None
    try:
        points = client.api_get("points")
    except Exception as err:  # noqa: BLE001 - the client's own failures, scrubbed
        raise CloudLinkError(link, _scrubbed(f"reading the garden's points: {err}",
                                             secrets)) from None
    if client.state.error or not isinstance(points, list):
        problem = client.state.error or f"an answer that is not a list of points: {points!r}"
        raise CloudLinkError(link, _scrubbed(f"reading the garden's points: {problem}",
                                             secrets)[:300])
    return [p for p in points if isinstance(p, dict) and p.get("pointer_type") == "Plant"]


class FarmbotCloudBot(Bot):
    """A FarmBot run through FarmBot's web app: see the module docstring.

    credentials: default `CloudCredentials.from_environment()`.
    camera: makes the head's camera from the bot's clock (e.g. a `TrajectoryRecorder`'s
        bind); None: the bot has none, and `camera` raises CameraError.
    observer: called with an `Activity` after every move, homing, head turn and dwell, from
        the thread that commanded it (a TrajectoryRecorder's observe).
    info: limits and motion profile; default the paper's bot with the motion profile of the
        bot's own firmware parameters.
    geometry: converts the bed frame to FarmBot's millimetres and servo degrees.
    head_settle_s: seconds to wait after the servo commands (no position feedback).
    reply_latency_s: estimated seconds between the bot finishing and its reply arriving.
    move_timeout_s, command_timeout_s: how long to wait for FarmBot OS's reply to a move or
        homing, and to anything else; estop_timeout_s: to an emergency stop.
    client_factory: makes a farmbot client (tests pass a fake); default farmbot.Farmbot.

    The head's angles are unknown (NaN) until the first `set_head`, and again after an
    emergency stop until `unlock()` re-sends them. `head()` gives the angles the servos were
    sent: whole command degrees (FarmBot OS takes integers), 1.5 geometric degrees apart.
    Connecting reads the status tree: an unreachable bot raises CloudLinkError, a bot
    locked by an emergency stop refuses motion (LockedError) until `unlock()`.
    """

    def __init__(self, credentials: CloudCredentials | None = None, *,
                 camera: Callable[[Callable[[], float]], Camera] | None = None,
                 observer: Callable[[Activity], None] | None = None,
                 info: BotInfo | None = None, geometry: BotGeometry = PAPER_BOT,
                 head_settle_s: float = 0.5, reply_latency_s: float = 0.2,
                 move_timeout_s: float = 180.0, command_timeout_s: float = 15.0,
                 estop_timeout_s: float = 5.0,
                 client_factory: Callable[[], Any] | None = None):
        self._credentials = credentials or CloudCredentials.from_environment()
        self._observer = observer
        self._geometry = geometry
        self._settle_s = float(head_settle_s)
        self._latency = float(reply_latency_s)
        self._timeouts = {"movements": float(move_timeout_s),
                          "listen": float(command_timeout_s), "api": float(command_timeout_s)}
        self._estop_timeout = float(estop_timeout_s)
        self._secrets = self._credentials.secrets()
        self._lock = threading.Lock()
        self._estop_lock = threading.Lock()
        self._stop = threading.Event()
        self._busy = self._closed = self._locked = False
        self._moving: tuple[float, np.ndarray, np.ndarray, MotionProfile] | None = None
        self._angles: tuple[float, float] | None = None
        self._head_known = False
        self._camera: Camera | None = None
        self._link = f"FarmBot cloud ({self._credentials.server})"
        factory = client_factory or farmbot_client
        secure_broker()
        self._client = self._estop_client = None
        try:
            self._client, self._estop_client = factory(), factory()
            for client in (self._client, self._estop_client):
                client.set_verbosity(0)  # the client would print every message it sends
                for key, seconds in self._timeouts.items():
                    client.set_timeout(seconds, key)
            self._estop_client.set_timeout(self._estop_timeout, "listen")
            self._log_in()
            status = self._read_status("connect")
            self._info = info or BotInfo.from_geometry(
                self._name(), geometry, firmware=status["firmware"],
                motion=motion_from_status(status["mcu_params"]))
            self._xyz, self._locked = status["xyz"], status["locked"]
            self._camera = camera(self.now) if camera is not None else None
        except BaseException:
            self.close()
            raise

    # --- connection -------------------------------------------------------------------

    def _log_in(self) -> None:
        token = account_token(self._client, self._credentials, self._link, self._secrets)
        self._client.set_token(token)
        self._estop_client.set_token(token)
        self._token_claims = token["token"]["unencoded"]

    def _name(self) -> str:
        host = str(self._token_claims.get("iss", "")).lstrip("/").split(":")[0]
        return f"FarmBot cloud {self._token_claims.get('bot', '')} ({host})".replace("  ", " ")

    def _read_status(self, command: str) -> dict:
        """Position (metres, bed frame), lock, firmware version and parameters from the
        status tree."""
        try:
            tree = self._call(command, self._client.read_status, expect_reply=False)
        except CommandTimeoutError:
            raise CloudLinkError(self._link, "no status from FarmBot OS within "
                                 f"{self._timeouts['listen']:.0f} s") from None
        if not isinstance(tree, dict):
            raise CloudLinkError(self._link, "FarmBot OS sent no status tree")
        position = (tree.get("location_data") or {}).get("position") or {}
        mm = [position.get(axis) for axis in "xyz"]
        mm = [float(v) if isinstance(v, int | float) else math.nan for v in mm]
        settings = tree.get("informational_settings") or {}
        return {"xyz": farmbot_mm_to_bed(mm, self._geometry),
                "locked": bool(settings.get("locked", False)),
                "firmware": settings.get("firmware_version"),
                "mcu_params": tree.get("mcu_params")}

    def _scrub(self, text: str) -> str:
        return _scrubbed(text, self._secrets)

    # --- one command at a time ----------------------------------------------------------

    def _call(self, command: str, method: Callable[..., Any], *args: Any,
              expect_reply: bool = True, **kwargs: Any) -> Any:
        """Run one client call and check `state.error`: a typed BotError for a failure."""
        state = self._client.state
        state.error = None
        state.last_messages.clear()  # the client judges replies by the newest message
        try:
            result = method(*args, **kwargs)
        except Exception as err:  # noqa: BLE001 - the client raises for a lost link
            detail = self._scrub(f"{command}: {type(err).__name__}: {err}")
            raise CloudLinkError(self._link, detail) from None
        error = state.error
        if error:
            raise self._error_for(command, str(error))
        if expect_reply and not state.last_messages.get("from_device"):
            # The client swallows Ctrl-C while it waits: no reply and no error means that.
            raise KeyboardInterrupt
        return result

    def _error_for(self, command: str, error: str) -> BotError:
        """The typed error of a failed command from the client's `state.error` and FarmBot
        OS's explanation."""
        if self._stop.is_set():
            return EmergencyStopError(command, 1)
        if "timed out waiting" in error.lower():
            if broker_lost(self._client):
                return CloudLinkError(self._link, f"{command}: the MQTT broker connection "
                                      "dropped and no reply came")
            key = "movements" if command.startswith(("move", "find home")) else "listen"
            return CommandTimeoutError(command, self._timeouts[key])
        detail = self._scrub(self._explanation() or error)
        text = detail.lower()
        axis = next((a for a in "xyz" if f"{a} axis" in text or f"axis {a}" in text), None)
        if "emergency" in text or "locked" in text:
            self._locked = True
            return LockedError(command)
        if "stall" in text:
            return StallError(command, axis=axis)
        if "timeout" in text or "timed out" in text:
            return MoveTimeoutError(command, 2, axis=axis)
        return CloudCommandError(command, detail)

    def _explanation(self) -> str:
        """FarmBot OS's explanation in the newest rpc_error reply, "" when there is none."""
        for message in reversed(self._client.state.last_messages.get("from_device") or []):
            content = message.get("content") or {} if isinstance(message, dict) else {}
            if content.get("kind") == "rpc_error":
                return "; ".join(str((item.get("args") or {}).get("message", ""))
                                 for item in content.get("body") or [] if isinstance(item, dict))
        return ""

    @contextmanager
    def _command(self, command: str, *, when_locked: bool = False) -> Iterator[None]:
        """Hold the bot for one command: open, idle and (unless `when_locked`) unlocked."""
        with self._lock:
            if self._closed:
                raise BotError(f"{command}: {self._link} is closed; connect a new bot")
            if self._busy:
                raise BotError(f"{command}: the bot is busy with another command; send one "
                               "command at a time")
            if self._locked and not when_locked:
                raise LockedError(command)
            self._busy = True
        try:
            yield
        finally:
            with self._lock:
                self._busy = False

    def _notify(self, activity: Activity, error: BaseException | None) -> None:
        """Report the activity, then raise the command's error (which wins over the
        observer's)."""
        try:
            if self._observer is not None:
                self._observer(activity)
        finally:
            if error is not None:
                raise error

    # --- the Bot interface ----------------------------------------------------------------

    @property
    def info(self) -> BotInfo:
        return self._info

    @property
    def camera(self) -> Camera:
        if self._camera is None:
            raise CameraError(f"{self._link}: no camera; pass one (e.g. a UsbCamera)")
        return self._camera

    def now(self) -> float:
        return time.monotonic()

    def position(self) -> np.ndarray:
        with self._lock:
            moving, xyz = self._moving, self._xyz.copy()
        if moving is None:
            return xyz
        sent, start, target, profile = moving
        return move_trajectory([self.now() - sent], start, target, profile)[0]

    def head(self) -> tuple[float, float]:
        if self._head_known and self._angles is not None:
            return self._angles
        return (math.nan, math.nan)

    def move_to(self, xyz, speed_fraction: float = 1.0) -> None:
        target = check_target(self._info, xyz)
        profile = self._info.motion.at_speed(speed_fraction)
        x, y, z = np.round(bed_to_farmbot_mm(target, self._geometry), 2)
        speed = None if speed_fraction == 1.0 else max(1, round(100 * speed_fraction))
        self._gantry(f"move to X {x:.2f} Y {y:.2f} Z {z:.2f} mm", target, profile,
                     self._client.move, x=float(x), y=float(y), z=float(z), speed=speed)

    def home(self, axes: str = "xyz") -> None:
        for name in check_axes(axes):
            target = self.position()
            i = "xyz".index(name)
            target[i] = self._info.home[i]
            self._gantry(f"find home {name.upper()}", target, self._info.motion,
                         self._client.find_home, axis=name, speed=100)

    def _gantry(self, command: str, target: np.ndarray, profile: MotionProfile,
                method: Callable[..., Any], **kwargs: Any) -> None:
        """One gantry command to `target` (metres), reported as a move Activity."""
        error: BaseException | None = None
        with self._command(command):
            start = self._xyz.copy()
            sent = self.now()
            with self._lock:
                self._moving = (sent, start, target, profile)
            try:
                self._call(command, method, **kwargs)
                end = target
            except BaseException as err:  # noqa: BLE001 - re-raised after the Activity
                error = err
                end = self._stopped_at()
            finally:
                with self._lock:
                    self._moving = None
            returned = self.now()
            self._xyz = end
            activity = self._move_activity(sent, returned, start, end, profile)
        self._notify(activity, error)

    def _stopped_at(self) -> np.ndarray:
        """Where the gantry stopped after a failed command; NaN when it cannot be read."""
        try:
            return self._read_status("read position")["xyz"]
        except (BotError, KeyboardInterrupt):
            return np.full(3, math.nan)

    def _move_activity(self, sent: float, returned: float, start: np.ndarray,
                       end: np.ndarray, profile: MotionProfile) -> Activity:
        """The move as it most likely happened: on the profile, ending `reply_latency_s`
        before the reply came, starting no earlier than it was sent."""
        if np.all(np.isfinite(start)) and np.all(np.isfinite(end)):
            duration = move_duration(start, end, profile)
            t0 = max(sent, returned - self._latency - duration)
            elapsed = max(returned - t0, duration)
        else:
            t0, elapsed = sent, returned - sent
        head = self.head()
        return Activity("move", t0, elapsed, start, end, head, head, profile)

    def _servo_commands(self, angles: tuple[float, float]) -> tuple[int, int]:
        """Whole-degree yaw and pitch servo commands of geometric angles, radians."""
        yaw, pitch = servo_commands(HeadPose(np.zeros(3), *angles), self._geometry)
        return int(round(float(yaw))), int(round(float(pitch)))

    def set_head(self, yaw_rad: float, pitch_rad: float) -> None:
        yaw_cmd, pitch_cmd = self._servo_commands(check_head(self._info, yaw_rad, pitch_rad))
        taken = from_servo_commands(yaw_cmd, pitch_cmd, np.zeros(3), self._geometry)
        command = f"set head: yaw servo {yaw_cmd}, pitch servo {pitch_cmd} degrees"
        with self._command(command):
            activity, error = self._send_head(command, (float(taken.yaw), float(taken.pitch)))
        self._notify(activity, error)

    def _send_head(self, command: str, angles: tuple[float, float]
                   ) -> tuple[Activity, BaseException | None]:
        """Send both servo angles (radians, as whole servo degrees take them) and wait for
        the head to settle; (its Activity, the error that cut it short or None)."""
        start, error = self.head(), None
        sent = self.now()
        self._head_known = False  # until both servos have their new angle
        try:
            yaw_cmd, pitch_cmd = self._servo_commands(angles)
            self._call(command, self._client.control_servo, YAW_PIN, yaw_cmd)
            self._call(command, self._client.control_servo, PITCH_PIN, pitch_cmd)
            self._angles, self._head_known = angles, True
            if self._stop.wait(self._settle_s):
                raise EmergencyStopError(command, 1)
        except BaseException as err:  # noqa: BLE001 - re-raised after the Activity
            error = err
        returned = self.now()
        xyz = self._xyz.copy()
        return Activity("head", sent, returned - sent, xyz, xyz, start, self.head()), error

    def dwell(self, seconds: float) -> None:
        seconds = max(0.0, float(seconds))
        with self._command(f"dwell {seconds:.3f} s"):
            sent = self.now()
            stopped = self._stop.wait(seconds)
            xyz, head = self._xyz.copy(), self.head()
            activity = Activity("dwell", sent, self.now() - sent, xyz, xyz, head, head)
        self._notify(activity, EmergencyStopError(f"dwell {seconds:.3f} s", 1) if stopped
                     else None)

    def emergency_stop(self) -> None:
        """Lock the bot now through a client of its own (safe from any thread while a command
        blocks in another); BotError when FarmBot OS does not confirm it."""
        with self._lock:
            if self._closed:
                return
            self._locked = True
            self._head_known = False  # the servos lose their pulses
            self._stop.set()
        with self._estop_lock:
            state = self._estop_client.state
            state.error = None
            state.last_messages.clear()
            try:
                self._estop_client.e_stop()
                failure = state.error or ("" if state.last_messages.get("from_device")
                                          else "no reply")
            except Exception as err:  # noqa: BLE001 - reported below, scrubbed
                failure = f"{type(err).__name__}: {err}"
        if failure:
            raise BotError(f"emergency stop: FarmBot OS did not confirm it within "
                           f"{self._estop_timeout:.0f} s ({self._scrub(str(failure))}); press "
                           "the bot's emergency stop button")

    def unlock(self) -> None:
        """Unlock (FarmBot OS's emergency_unlock), then re-send the head's last angles and
        let it settle."""
        activity = error = None
        with self._command("unlock", when_locked=True):
            self._stop.clear()  # a failure of the unlock itself is no emergency stop
            self._call("unlock", self._client.unlock)
            with self._lock:
                self._locked = False
            if self._angles is not None:
                activity, error = self._send_head("unlock: re-send the head's angles",
                                                  self._angles)
        if activity is not None:
            self._notify(activity, error)

    def describe(self) -> dict:
        """The backend for scan.json: no credential."""
        return {"backend": "farmbot-cloud", "bot": self._info.name,
                "firmware": self._info.firmware, "server": self._credentials.server}

    def __repr__(self) -> str:
        return f"FarmbotCloudBot({self._link!r})"

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._stop.set()  # a dwell or settle still waiting ends now
        try:
            close = getattr(self._camera, "close", None)
            if close is not None:
                close()
        finally:
            for client in (self._client, self._estop_client):
                if client is not None:
                    disconnect(client)
