"""The cloud backend as it runs in the field: the real `farmbot` client and paho over a real
MQTT broker (mosquitto on a loopback port, plain and with TLS), FarmBot OS played by a
stand-in on the broker's other side; a scan, and a scan whose broker drops mid-move and
that resumes once it is back."""

import functools
import json
import threading

import numpy as np
import pytest
from cloud_fakes import make_token
from farmbot_os import Broker, FarmbotOS, free_port, make_certificate, mosquitto_binary

from flowerpose.hardware.backends import cloud_client
from flowerpose.hardware.backends.cloud_bot import CloudLinkError, FarmbotCloudBot
from flowerpose.hardware.backends.cloud_credentials import CloudCredentials
from flowerpose.hardware.bot import SolidCamera
from flowerpose.hardware.bot_errors import ConnectionLostError
from flowerpose.hardware.flights.scan_flight import run_scan
from flowerpose.hardware.flights.scan_plan import ScanConfig, plan_scan
from flowerpose.hardware.geometry import bed_to_farmbot_mm
from flowerpose.jsonio import read_json
from flowerpose.scan_geometry import ScanPathConfig

farmbot = pytest.importorskip("farmbot")
pytestmark = pytest.mark.skipif(mosquitto_binary() is None,
                                reason="mosquitto is not installed (scripts/setup-system.sh)")

PLAN = plan_scan(np.array([1.5, 0.75]), 0.2,
                 ScanConfig(ScanPathConfig(azimuth_step_deg=180.0, cylinder_bottom_m=0.2,
                                           dome_polar_deg=(50.0,)), pause_s=0.01))


def _credentials() -> CloudCredentials:
    token = make_token()
    token["token"]["unencoded"]["mqtt"] = "localhost"
    return CloudCredentials.from_environment({"FARMBOT_TOKEN": json.dumps(token)})


def _bot(**kwargs) -> FarmbotCloudBot:
    return FarmbotCloudBot(_credentials(), client_factory=farmbot.Farmbot, head_settle_s=0.01,
                           camera=functools.partial(SolidCamera, width=32, height=24, fps=2),
                           **kwargs)


@pytest.fixture(autouse=True)
def _warnings_anew(monkeypatch):
    monkeypatch.setattr(cloud_client, "_PLAIN_BROKERS", set())


@pytest.fixture
def plain(tmp_path, monkeypatch):
    """A plain broker; the backend's TLS port leads nowhere, so it falls back to plain."""
    broker = Broker(tmp_path, free_port()).start()
    monkeypatch.setattr(cloud_client, "MQTT_PLAIN_PORT", broker.port)
    monkeypatch.setattr(cloud_client, "MQTT_TLS_PORT", free_port())
    device = FarmbotOS(broker.port)
    yield broker, device
    device.close()
    broker.stop()


@pytest.fixture
def tls(tmp_path, monkeypatch):
    """A TLS-only broker with a test certificate; no plain listener at all."""
    cert, key = make_certificate(tmp_path)
    broker = Broker(tmp_path, free_port(), tls=(cert, key)).start()
    monkeypatch.setattr(cloud_client, "MQTT_TLS_PORT", broker.port)
    monkeypatch.setattr(cloud_client, "MQTT_PLAIN_PORT", free_port())
    device = FarmbotOS(broker.port, ca_file=cert)
    yield broker, device, cert
    device.close()
    broker.stop()


def _assert_scanned(device: FarmbotOS, manifest: dict) -> None:
    assert manifest["status"] == "complete" and manifest["completed"] == len(PLAN.waypoints)
    kinds = device.kinds()
    assert kinds.count("move") == len(PLAN.waypoints)
    assert kinds.count("set_servo_angle") == 2 * len(PLAN.waypoints)
    np.testing.assert_allclose(device.position, bed_to_farmbot_mm(PLAN.waypoints[-1].pose.gantry),
                               atol=0.01)


@pytest.mark.slow
def test_a_scan_over_a_plain_broker_warns_that_the_token_crosses_unencrypted(plain, tmp_path,
                                                                              capsys):
    _, device = plain
    bot = _bot()
    manifest = run_scan(bot, PLAN, tmp_path / "scan", source=bot.describe(), progress=False)
    bot.close()
    _assert_scanned(device, manifest)
    assert device.kinds()[0] == "read_status"
    assert "unencrypted" in capsys.readouterr().err


@pytest.mark.slow
def test_a_scan_over_tls_checks_the_broker_certificate(tls, tmp_path, monkeypatch, capsys):
    _, device, cert = tls
    # Not trusted: an error naming the certificate, never a fall back to plain MQTT.
    monkeypatch.setenv("SSL_CERT_FILE", str(tmp_path / "no-such-authority.pem"))
    with pytest.raises(CloudLinkError, match="TLS certificate did not verify"):
        _bot()
    assert "unencrypted" not in capsys.readouterr().err
    monkeypatch.setenv("SSL_CERT_FILE", str(cert))
    bot = _bot()
    manifest = run_scan(bot, PLAN, tmp_path / "scan", source=bot.describe(), progress=False)
    bot.close()
    _assert_scanned(device, manifest)
    assert "unencrypted" not in capsys.readouterr().err


@pytest.mark.slow
def test_a_broker_dropped_mid_move_interrupts_the_scan_which_resumes_when_it_is_back(
        plain, tmp_path):
    broker, device = plain
    out = tmp_path / "scan"
    bot = _bot(move_timeout_s=3.0, command_timeout_s=3.0)
    device.hold_after = 2

    def drop_during_third_move():
        assert device.held.wait(30.0)
        broker.stop()

    dropper = threading.Thread(target=drop_during_third_move)
    dropper.start()
    with pytest.raises(ConnectionLostError, match="broker connection dropped"):
        run_scan(bot, PLAN, out, source=bot.describe(), progress=False)
    dropper.join(5.0)
    bot.close()
    stopped = read_json(out / "scan.json")
    assert stopped["status"] == "interrupted" and stopped["completed"] == 2
    assert "broker connection dropped" in stopped["sessions"][0]["error"]

    broker.start()
    device.hold_after = None
    device.release()
    device.wait_connected()
    bot = _bot()
    manifest = run_scan(bot, PLAN, out, source=bot.describe(), progress=False)
    bot.close()
    assert manifest["status"] == "complete" and manifest["completed"] == len(PLAN.waypoints)
    assert [s["started_waypoint"] for s in manifest["sessions"]] == [0, 2]
