"""Fakes for the physical bot's tests: FarmBot OS behind the `farmbot` client, and a V4L2
camera. No network, no device."""

from __future__ import annotations

import base64
import json
import threading
import time
from types import SimpleNamespace

import numpy as np

#: A JWT signature is base64url text; this one is as secret as a real one.
SECRET_JWT_SIGNATURE = "s3cr3t-signature-never-to-be-seen-ok"
PASSWORD = "hunter2-password-never-to-be-seen"
EMAIL = "grower@example.org"


def make_token(bot: str = "device_7") -> dict:
    """A token shaped as FarmBot's /api/tokens returns it; its encoded part is secret."""
    unencoded = {"bot": bot, "mqtt": "mqtt.example.org", "iss": "//my.farm.bot:443",
                 "sub": EMAIL}
    payload = base64.urlsafe_b64encode(json.dumps(unencoded).encode()).decode().rstrip("=")
    return {"token": {"unencoded": unencoded,
                      "encoded": f"eyJhbGciOiJSUzI1NiJ9.{payload}.{SECRET_JWT_SIGNATURE}"}}


class FakeDevice:
    """FarmBot OS and its Farmduino as the fake clients see them (shared between clients)."""

    def __init__(self, position_mm=(100.0, 200.0, -50.0), mcu_params=None, locked=False):
        self.position = list(position_mm)
        self.mcu_params = mcu_params or {}
        self.locked = locked
        self.estopped = threading.Event()
        self.calls: list[tuple] = []
        self.fail_next: str | None = None
        """Explanation of an rpc_error for the next move (the gantry stops half way)."""
        self.silent = False
        """No reply at all (the client times out)."""
        self.block_moves = False
        """Moves run until an emergency stop ends them (a minute at most: longer than any
        test waits for one to end)."""
        self.moving = threading.Event()
        self.logins = {(EMAIL, PASSWORD): make_token()}
        self.points: list[dict] = []
        """The account's garden as the web app's /api/points gives it."""

    def status(self) -> dict:
        return {"location_data": {"position": dict(zip("xyz", self.position, strict=True))},
                "informational_settings": {"locked": self.locked,
                                           "firmware_version": "17.1.0.F"},
                "mcu_params": self.mcu_params}


class FakeFarmbot:
    """farmbot.Farmbot's interface as FarmBotCloudBot uses it; errors go to state.error."""

    def __init__(self, device: FakeDevice):
        self.device = device
        self.state = SimpleNamespace(error=None, last_messages={}, token=None, verbosity=1,
                                     timeout={"api": 15, "listen": 15, "movements": 120})
        self.disconnected = False

    def set_verbosity(self, value):
        self.state.verbosity = value

    def set_timeout(self, duration, key="listen"):
        self.state.timeout[key] = duration

    def set_token(self, token):
        self.state.token = token

    def get_token(self, email, password, server="https://my.farm.bot"):
        self.device.calls.append(("get_token", server))
        token = self.device.logins.get((email, password))
        if token is None:
            self.state.token = None
            self.state.error = "HTTP ERROR: Incorrect email address or password."
            return self.state.error
        self.state.token = token
        return token

    def api_get(self, endpoint, database_id=None, payload=None):
        self.device.calls.append(("api_get", endpoint))
        if self.state.token is None:
            self.state.error = "CLIENT ERROR 401: The user`s token has expired or is invalid."
            return self.state.error
        return [dict(point) for point in self.device.points] if endpoint == "points" else []

    def _reply(self, explanation: str | None = None) -> None:
        if self.device.silent:
            self.state.error = "Timed out waiting for RPC response."
            return
        content = {"kind": "rpc_ok", "args": {"label": "x"}}
        if explanation is not None:
            content = {"kind": "rpc_error", "args": {"label": "x"},
                       "body": [{"kind": "explanation", "args": {"message": explanation}}]}
            self.state.error = "RPC error response received."
        self.state.last_messages.setdefault("from_device", []).append(
            {"topic": "bot/device_7/from_device", "content": content})

    def read_status(self, path=None):
        self.device.calls.append(("read_status",))
        if self.device.silent:
            self.state.error = "Timed out waiting for RPC response."
            return None
        return self.device.status()

    def move(self, x=None, y=None, z=None, safe_z=None, speed=None):
        device = self.device
        device.calls.append(("move", x, y, z, speed))
        if device.locked:
            return self._reply("Device is locked (emergency lock)")
        if device.block_moves:
            device.moving.set()
            device.estopped.wait(60.0)
            return self._reply("Movement aborted: emergency lock")
        if device.fail_next is not None:
            explanation, device.fail_next = device.fail_next, None
            device.position = [(a + b) / 2 for a, b in zip(device.position, (x, y, z),
                                                            strict=True)]
            return self._reply(explanation)
        device.position = [x, y, z]
        self._reply()

    def find_home(self, axis="all", speed=100):
        self.device.calls.append(("find_home", axis, speed))
        self.device.position["xyz".index(axis)] = 0.0
        self._reply()

    def control_servo(self, pin, angle):
        self.device.calls.append(("control_servo", pin, angle))
        if angle < 0 or angle > 180:
            self.state.error = "ERROR: Servo angle constrained to 0-180 degrees."
            return
        self._reply()

    def e_stop(self):
        self.device.calls.append(("e_stop",))
        self.device.locked = True
        self.device.estopped.set()
        self._reply()

    def unlock(self):
        self.device.calls.append(("unlock",))
        self.device.locked = False
        self.device.estopped.clear()
        self._reply()

    def disconnect_broker(self):
        self.disconnected = True


def fake_factory(device: FakeDevice):
    """A client factory for FarmbotCloudBot that records the clients it made."""
    clients: list[FakeFarmbot] = []

    def make() -> FakeFarmbot:
        clients.append(FakeFarmbot(device))
        return clients[-1]

    make.clients = clients
    return make


class FakeCapture:
    """cv2.VideoCapture's interface over synthetic frames: frame k is a solid grey of value
    k mod 256, `fps` of them a second (real time).

    deliver: the (width, height) it delivers whatever is asked; None: what is asked.
    refuse: property ids whose set() the driver refuses. frames: how many it delivers
    before going silent (None: no end). opened: False is a busy device.
    """

    def __init__(self, fps: float = 200.0, deliver=None, refuse=(), frames=None, opened=True):
        import cv2

        self.cv2 = cv2
        self.fps, self.deliver, self.refuse = fps, deliver, set(refuse)
        self.frames, self.opened = frames, opened
        self.props = {cv2.CAP_PROP_EXPOSURE: 156.0, cv2.CAP_PROP_FOCUS: 40.0,
                      cv2.CAP_PROP_AUTO_EXPOSURE: 3.0, cv2.CAP_PROP_AUTOFOCUS: 1.0,
                      cv2.CAP_PROP_FPS: 30.0}
        self.count = 0
        self.released = False

    def isOpened(self):  # noqa: N802 - OpenCV's name
        return self.opened

    def set(self, prop, value):
        if prop in self.refuse:
            return False
        if self.deliver is not None and prop in (self.cv2.CAP_PROP_FRAME_WIDTH,
                                                 self.cv2.CAP_PROP_FRAME_HEIGHT):
            return True
        self.props[prop] = value
        return True

    def get(self, prop):
        if self.deliver is not None and prop == self.cv2.CAP_PROP_FRAME_WIDTH:
            return float(self.deliver[0])
        if self.deliver is not None and prop == self.cv2.CAP_PROP_FRAME_HEIGHT:
            return float(self.deliver[1])
        return float(self.props.get(prop, 0.0))

    def grab(self):
        time.sleep(1.0 / self.fps)
        if self.frames is not None and self.count >= self.frames:
            return False
        self.count += 1
        return True

    def retrieve(self):
        width = int(self.get(self.cv2.CAP_PROP_FRAME_WIDTH))
        height = int(self.get(self.cv2.CAP_PROP_FRAME_HEIGHT))
        return True, np.full((height, width, 3), self.count % 256, np.uint8)

    def release(self):
        self.released = True
