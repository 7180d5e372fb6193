"""A real MQTT broker (Debian's mosquitto, on a loopback port, plain or TLS) and a small
FarmBot OS stand-in that answers the `farmbot` client's RPCs on FarmBot's topics, for the
cloud backend's tests over a real network link.

FarmBot OS listens on `bot/<device>/from_clients` for CeleryScript `rpc_request`s, answers
each on `bot/<device>/from_device` with `rpc_ok` or `rpc_error` (carrying the request's
label), and publishes its status tree on `bot/<device>/status`.
"""

from __future__ import annotations

import getpass
import json
import shutil
import socket
import ssl
import subprocess
import threading
import time
from pathlib import Path

import paho.mqtt.client as mqtt

DEVICE = "device_7"


def mosquitto_binary() -> str | None:
    """The mosquitto executable (Debian installs it in /usr/sbin), or None."""
    return shutil.which("mosquitto") or shutil.which("mosquitto", path="/usr/sbin:/usr/bin")


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def make_certificate(folder: Path) -> tuple[Path, Path]:
    """A self-signed certificate for localhost and 127.0.0.1 (its own authority), and its
    key; returns (certificate, key)."""
    cert, key = folder / "broker.crt", folder / "broker.key"
    subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "1",
                    "-keyout", str(key), "-out", str(cert), "-subj", "/CN=localhost",
                    "-addext", "subjectAltName=DNS:localhost,IP:127.0.0.1"],
                   check=True, capture_output=True)
    key.chmod(0o644)  # mosquitto started as root reads it as its own user
    return cert, key


class Broker:
    """mosquitto on 127.0.0.1:`port`, with TLS when given a certificate and key; `stop()`
    kills it (a dropped broker), `start()` brings it back on the same port."""

    def __init__(self, folder: Path, port: int, tls: tuple[Path, Path] | None = None):
        self.port = port
        self.config = folder / f"mosquitto-{port}.conf"
        lines = [f"listener {port} 127.0.0.1", "allow_anonymous true", "persistence false",
                 f"user {getpass.getuser()}", "log_dest stderr"]
        if tls is not None:
            lines += [f"certfile {tls[0]}", f"keyfile {tls[1]}"]
        self.config.write_text("\n".join(lines) + "\n")
        self.log = folder / f"mosquitto-{port}.log"
        self.process: subprocess.Popen | None = None

    def start(self) -> Broker:
        binary = mosquitto_binary()
        assert binary is not None, "mosquitto is not installed (scripts/setup-system.sh)"
        with open(self.log, "ab") as log:
            self.process = subprocess.Popen([binary, "-c", str(self.config)], stdout=log,
                                            stderr=log)
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"mosquitto exited: {self.log.read_text()[-500:]}")
            try:
                socket.create_connection(("127.0.0.1", self.port), timeout=0.2).close()
                return self
            except OSError:
                time.sleep(0.05)
        raise RuntimeError(f"mosquitto did not listen on {self.port}")

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.kill()
            self.process.wait(5.0)


class FarmbotOS:
    """FarmBot OS as the broker's other client: moves take `move_s` seconds (moves after
    the first `hold_after`, when set, until an emergency lock or `release()`; `held` is set
    while one waits), positions are FarmBot millimetres, `calls` records every request's
    kind and args in order."""

    def __init__(self, port: int, *, ca_file: Path | None = None,
                 position_mm=(100.0, 200.0, -50.0), move_s: float = 0.02):
        self.position = [float(v) for v in position_mm]
        self.locked = False
        self.move_s = move_s
        self.hold_after: int | None = None
        self.calls: list[tuple[str, dict]] = []
        self.held = threading.Event()
        self._moves = 0
        self._stop = threading.Event()
        self._release = threading.Event()
        self._client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2,
                                   client_id=f"farmbot-os-{port}")
        if ca_file is not None:
            self._client.tls_set(ca_certs=str(ca_file), cert_reqs=ssl.CERT_REQUIRED)
        self._client.reconnect_delay_set(min_delay=1, max_delay=1)
        self._client.on_connect = self._subscribe
        self._client.on_message = self._on_message
        self._client.connect("localhost", port, keepalive=5)
        self._client.loop_start()

    def status(self) -> dict:
        return {"location_data": {"position": dict(zip("xyz", self.position, strict=True))},
                "informational_settings": {"locked": self.locked,
                                           "firmware_version": "17.1.0.F"},
                "mcu_params": {}}

    def kinds(self) -> list[str]:
        return [kind for kind, _ in self.calls]

    def wait_connected(self, timeout_s: float = 15.0) -> None:
        """Until the stand-in is back on the broker (paho reconnects once a second)."""
        deadline = time.monotonic() + timeout_s
        while not self._client.is_connected():
            assert time.monotonic() < deadline, "FarmBot OS did not reconnect to the broker"
            time.sleep(0.05)

    def release(self) -> None:
        """End a held move normally."""
        self._release.set()

    def close(self) -> None:
        self._client.loop_stop()
        self._client.disconnect()

    def _subscribe(self, client, _userdata, _flags, reason, _properties=None):
        client.subscribe(f"bot/{DEVICE}/from_clients")

    def _publish(self, channel: str, content: dict) -> None:
        self._client.publish(f"bot/{DEVICE}/{channel}", json.dumps(content))

    def _on_message(self, _client, _userdata, message):
        rpc = json.loads(message.payload)
        # Every request on its own thread: an emergency lock must get through a long move.
        threading.Thread(target=self._answer, args=(rpc,), daemon=True).start()

    def _answer(self, rpc: dict) -> None:
        label = rpc["args"]["label"]
        body = rpc["body"][0]
        kind, args = body["kind"], body.get("args", {})
        self.calls.append((kind, {"body": body.get("body", []), **args}))
        error = getattr(self, f"_do_{kind}", self._unknown)(body)
        if error is None:
            self._publish("from_device", {"kind": "rpc_ok", "args": {"label": label}})
        else:
            self._publish("from_device", {
                "kind": "rpc_error", "args": {"label": label},
                "body": [{"kind": "explanation", "args": {"message": error}}]})

    def _unknown(self, body: dict) -> str:
        return f"unknown command {body['kind']}"

    def _do_read_status(self, body: dict) -> None:
        self._publish("status", self.status())

    def _do_move(self, body: dict) -> str | None:
        if self.locked:
            return "Device is locked (emergency lock)"
        target = list(self.position)
        for item in body.get("body", []):
            if item["kind"] == "axis_overwrite":
                target["xyz".index(item["args"]["axis"])] = float(
                    item["args"]["axis_operand"]["args"]["number"])
        self._moves += 1
        if self.hold_after is not None and self._moves > self.hold_after:
            self.held.set()
            while not (self._stop.is_set() or self._release.is_set()):
                time.sleep(0.01)
            self._release.clear()
            self.held.clear()
        else:
            self._stop.wait(self.move_s)
        if self._stop.is_set() or self.locked:
            return "Movement failed: emergency lock"
        self.position = target
        return None

    def _do_find_home(self, body: dict) -> None:
        axes = "xyz" if body["args"]["axis"] == "all" else body["args"]["axis"]
        for axis in axes:
            self.position["xyz".index(axis)] = 0.0

    def _do_set_servo_angle(self, body: dict) -> str | None:
        angle = body["args"]["pin_value"]
        return None if 0 <= angle <= 180 else "servo angle out of range"

    def _do_emergency_lock(self, body: dict) -> None:
        self.locked = True
        self._stop.set()

    def _do_emergency_unlock(self, body: dict) -> None:
        self.locked = False
        self._stop.clear()
