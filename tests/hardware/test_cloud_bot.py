"""The FarmBot cloud backend against a fake of the `farmbot` client (and once against the real
client over a fake MQTT broker): units, typed errors, the emergency stop from another
thread, and credentials that never leave memory."""

import functools
import json
import math
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest
from cloud_fakes import (
    EMAIL,
    PASSWORD,
    SECRET_JWT_SIGNATURE,
    FakeDevice,
    fake_factory,
    make_token,
)

from flowerpose.errors import InputError
from flowerpose.hardware.backends.cloud_bot import CloudCommandError, FarmbotCloudBot
from flowerpose.hardware.backends.cloud_credentials import CloudCredentials, parse_token
from flowerpose.hardware.bot import SolidCamera
from flowerpose.hardware.bot_errors import (
    BotError,
    CommandTimeoutError,
    ConnectionLostError,
    EmergencyStopError,
    LockedError,
    MoveTimeoutError,
    StallError,
)
from flowerpose.hardware.flights.scan_flight import run_scan
from flowerpose.hardware.flights.scan_plan import ScanConfig, plan_scan
from flowerpose.hardware.geometry import bed_to_farmbot_mm, farmbot_mm_to_bed
from flowerpose.hardware.kinematics import HeadPose, from_servo_commands, servo_commands
from flowerpose.hardware.motion import move_duration
from flowerpose.scan_geometry import ScanPathConfig

TOKEN_ENV = {"FARMBOT_TOKEN": json.dumps(make_token())}
SECRETS = (SECRET_JWT_SIGNATURE, PASSWORD, EMAIL, make_token()["token"]["encoded"])


def _bot(device=None, environ=TOKEN_ENV, **kwargs):
    device = device or FakeDevice()
    factory = fake_factory(device)
    bot = FarmbotCloudBot(CloudCredentials.from_environment(environ), client_factory=factory,
                          head_settle_s=0.01, **kwargs)
    return bot, device, factory.clients


def test_connecting_reads_position_firmware_and_motion_profile():
    device = FakeDevice(position_mm=(100.0, 200.0, -50.0),
                        mcu_params={"movement_max_spd_x": 800, "movement_timeout_z": 90,
                                    "movement_step_per_mm_y": None})
    bot, _, clients = _bot(device)
    np.testing.assert_allclose(bot.position(), farmbot_mm_to_bed([100.0, 200.0, -50.0]))
    assert bot.info.firmware == "17.1.0.F" and "device_7" in bot.info.name
    assert bot.info.motion.x.max_speed == 800 and bot.info.motion.z.timeout_s == 90
    assert bot.info.motion.y.steps_per_mm == 5.0  # unset: FarmBot's default
    assert all(c.state.verbosity == 0 for c in clients)  # the client prints nothing
    assert all(c.state.token == make_token() for c in clients)
    assert clients[1].state.timeout["listen"] == 5.0  # the emergency stop's own client
    assert all(math.isnan(a) for a in bot.head())  # servos give no feedback
    bot.close()


def test_moves_homing_and_servos_go_out_in_farmbot_units_and_report_activities():
    activities = []
    bot, device, _ = _bot(observer=activities.append)
    target = np.array([1.2, 0.6, 0.4])
    sent = bot.now()
    bot.move_to(target, speed_fraction=0.5)
    mm = bed_to_farmbot_mm(target)
    assert device.calls[-1] == ("move", *np.round(mm, 2).tolist(), 50)
    np.testing.assert_allclose(bot.position(), target)
    move = activities[-1]
    duration = move_duration(move.gantry_start, target, bot.info.motion.at_speed(0.5))
    assert move.kind == "move" and move.t0 >= sent and move.elapsed >= duration
    np.testing.assert_array_equal(move.gantry_end, target)

    bot.set_head(math.radians(100.0), math.radians(30.0))
    commands = [round(float(c)) for c in servo_commands(HeadPose(np.zeros(3), math.radians(100),
                                                                 math.radians(30)))]
    assert device.calls[-2:] == [("control_servo", 6, commands[0]),
                                 ("control_servo", 5, commands[1])]
    assert all(isinstance(c[2], int) for c in device.calls[-2:])
    taken = from_servo_commands(*commands, np.zeros(3))
    assert bot.head() == pytest.approx((float(taken.yaw), float(taken.pitch)))
    assert abs(bot.head()[0] - math.radians(100)) <= math.radians(0.75)  # whole servo degrees
    head = activities[-1]
    assert head.kind == "head" and all(math.isnan(a) for a in head.head_start)
    assert head.elapsed >= 0.01

    bot.home("xz")
    assert [c[1] for c in device.calls if c[0] == "find_home"] == ["z", "x"]
    np.testing.assert_allclose(bot.position(), [bot.info.home[0], 0.6, bot.info.home[2]])
    bot.dwell(0.02)
    assert activities[-1].kind == "dwell" and activities[-1].elapsed >= 0.02
    with pytest.raises(InputError, match="outside the travel"):
        bot.move_to([9.0, 0.5, 0.4])
    bot.close()
    with pytest.raises(BotError, match="closed"):
        bot.move_to(target)


@pytest.mark.parametrize("explanation, error, axis", [
    ("Stall detected on the X axis", StallError, "x"),
    ("Movement timeout on the Y axis", MoveTimeoutError, "y"),
    ("Device is locked by an emergency stop", LockedError, None),
    ("Pin 99 is not a servo pin", CloudCommandError, None),
])
def test_a_failure_in_state_error_raises_its_typed_error(explanation, error, axis):
    activities = []
    bot, device, _ = _bot(observer=activities.append)
    start = bot.position()
    device.fail_next = explanation
    with pytest.raises(error) as raised:
        bot.move_to([1.0, 0.5, 0.4])
    assert getattr(raised.value, "axis", None) == axis
    assert "\n" not in str(raised.value) and "move to X" in str(raised.value)
    # The gantry stopped part way: the position is read back, the activity still reported.
    np.testing.assert_allclose(bot.position(), (start + np.array([1.0, 0.5, 0.4])) / 2,
                               atol=1e-5)
    assert activities[-1].kind == "move"
    bot.close()


def test_no_reply_is_a_command_timeout_and_an_offline_bot_a_lost_connection():
    bot, device, _ = _bot()
    device.silent = True
    with pytest.raises(CommandTimeoutError, match="no final reply within 180"):
        bot.move_to([1.0, 0.5, 0.4])
    assert np.isnan(bot.position()).all()  # not even the position could be read
    bot.close()
    with pytest.raises(ConnectionLostError, match="online"):
        _bot(device)


def _stop_while_blocked(bot: FarmbotCloudBot) -> None:
    """`bot.emergency_stop()` from a thread of its own while a move blocks the owner: it
    returns without waiting for that move, which the fakes end only at the stop (or after
    a minute), so a stop that waited would outlast the 30 s guard here."""
    stopped = []
    stopper = threading.Thread(target=lambda: stopped.append(bot.emergency_stop()),
                               daemon=True)
    stopper.start()
    stopper.join(30.0)
    assert not stopper.is_alive(), "hung: emergency_stop waited for the blocked move"
    assert stopped == [None]  # returned, confirmed (it raises BotError otherwise)


def test_emergency_stop_from_another_thread_ends_the_move_and_locks_until_unlock():
    activities = []
    bot, device, clients = _bot(observer=activities.append)
    bot.set_head(math.radians(90.0), math.radians(20.0))
    angles = bot.head()
    device.block_moves = True
    errors = []

    def scan():
        try:
            bot.move_to([2.0, 1.0, 0.3])
        except BotError as err:
            errors.append(err)

    owner = threading.Thread(target=scan, daemon=True)
    owner.start()
    assert device.moving.wait(30.0), "hung: the move never reached FarmBot OS"
    _stop_while_blocked(bot)
    owner.join(30.0)
    assert not owner.is_alive(), "hung: the move did not end at the emergency stop"
    assert isinstance(errors[0], EmergencyStopError)
    assert clients[1].state.last_messages["from_device"]  # sent by the second client
    assert all(math.isnan(a) for a in bot.head())  # the servos lost their pulses
    device.block_moves = False
    calls = len(device.calls)
    with pytest.raises(LockedError):
        bot.move_to([1.0, 0.5, 0.4])
    with pytest.raises(LockedError):
        bot.dwell(0.01)
    assert len(device.calls) == calls  # refused before anything was sent
    bot.unlock()
    assert device.calls[-3:] == [("unlock",), ("control_servo", 6, device.calls[-2][2]),
                                 ("control_servo", 5, device.calls[-1][2])]
    assert bot.head() == angles and activities[-1].kind == "head"
    bot.move_to([1.0, 0.5, 0.4])
    bot.close()
    bot.emergency_stop()  # does nothing once closed


def test_a_bot_locked_before_connecting_refuses_motion_until_unlocked():
    bot, device, _ = _bot(FakeDevice(locked=True))
    with pytest.raises(LockedError):
        bot.move_to([1.0, 0.5, 0.4])
    bot.unlock()
    bot.move_to([1.0, 0.5, 0.4])
    assert device.calls[-1][0] == "move"
    bot.close()


def test_email_and_password_log_in_and_a_wrong_one_is_one_clear_line():
    environ = {"FARMBOT_EMAIL": EMAIL, "FARMBOT_PASSWORD": PASSWORD,
               "FARMBOT_SERVER": "https://farm.example.org"}
    bot, device, clients = _bot(environ=environ)
    assert device.calls[0] == ("get_token", "https://farm.example.org")
    assert clients[1].state.token == make_token()
    bot.close()
    with pytest.raises(InputError, match="wrong email or password") as raised:
        _bot(environ={**environ, "FARMBOT_PASSWORD": "not-it"})
    assert "not-it" not in str(raised.value)


@pytest.mark.parametrize("environ, names", [
    ({}, "FARMBOT_TOKEN"),
    ({"FARMBOT_EMAIL": EMAIL}, "FARMBOT_PASSWORD"),
    ({"FARMBOT_TOKEN": "not a token"}, "FARMBOT_TOKEN"),
])
def test_missing_or_bad_credentials_are_one_line_naming_the_variable(environ, names):
    with pytest.raises(InputError) as raised:
        CloudCredentials.from_environment(environ)
    message = str(raised.value)
    assert message.startswith(names) and "\n" not in message
    assert EMAIL not in message


def test_token_files_outside_the_repository_only(tmp_path, capsys):
    repo = tmp_path / "repo"
    (repo / ".git").mkdir(parents=True)
    inside = repo / "secrets" / "token.json"
    inside.parent.mkdir()
    inside.write_text(json.dumps(make_token()))
    with pytest.raises(InputError, match="outside the git work tree"):
        CloudCredentials.from_environment({}, token_file=inside)
    outside = tmp_path / "token.jwt"
    outside.write_text(make_token()["token"]["encoded"] + "\n")  # the bare JWT
    outside.chmod(0o644)
    with pytest.raises(InputError, match="other users may read this token file; chmod 600"):
        CloudCredentials.from_environment({}, token_file=outside)
    outside.chmod(0o600)
    credentials = CloudCredentials.from_environment({}, token_file=outside)
    assert credentials._token == make_token()
    with pytest.raises(InputError, match="not found"):
        CloudCredentials.from_environment({}, token_file=tmp_path / "none")
    assert parse_token(json.dumps(make_token()["token"]), "x") == make_token()


@pytest.mark.parametrize("text", ["not-a-jwt", "a.b.c", "eyJhbGciOiJIUzI1NiJ9.bm90IGpzb24.c2ln",
                                  '{"token": {"encoded": "x"}}'])
def test_a_token_that_is_not_one_is_one_line_naming_where_it_came_from(text):
    with pytest.raises(InputError, match="FARMBOT_TOKEN: not a FarmBot token") as raised:
        parse_token(text, "FARMBOT_TOKEN")
    assert text not in str(raised.value)


def test_a_jwt_without_the_bots_claims_is_refused():
    import jwt

    token = jwt.encode({"sub": "someone"}, "a-key-long-enough-for-hs256-signing-0123", "HS256")
    with pytest.raises(InputError, match="it names no bot, mqtt and iss"):
        parse_token(token, "FARMBOT_TOKEN")


def test_credentials_never_appear_in_reprs_errors_output_or_scan_files(tmp_path, capsys,
                                                                       caplog):
    environ = {"FARMBOT_EMAIL": EMAIL, "FARMBOT_PASSWORD": PASSWORD}
    bot, device, clients = _bot(environ=environ, camera=functools.partial(
        SolidCamera, width=32, height=24, fps=2))
    texts = [repr(bot), str(bot.info), repr(CloudCredentials.from_environment(environ)),
             repr(CloudCredentials.from_environment(TOKEN_ENV)), json.dumps(bot.describe())]

    def leaks(*args, **kwargs):
        raise OSError(f"broker refused {make_token()['token']['encoded']} for {EMAIL}")

    clients[0].control_servo = leaks
    with pytest.raises(ConnectionLostError) as raised:
        bot.set_head(0.5, 0.5)
    texts.append(str(raised.value))
    assert "***" in str(raised.value)
    clients[0].control_servo = type(clients[0]).control_servo.__get__(clients[0])
    plan = plan_scan(np.array([1.5, 0.75]), 0.2,
                     ScanConfig(ScanPathConfig(azimuth_step_deg=120.0, cylinder_bottom_m=0.2,
                                               dome_polar_deg=(50.0,)), pause_s=0.01))
    manifest = run_scan(bot, plan, tmp_path, source=bot.describe(), progress=False)
    assert manifest["status"] == "complete"
    bot.close()
    out, err = capsys.readouterr()
    texts += [out, err, caplog.text]
    texts += [p.read_bytes().decode("latin-1") for p in tmp_path.rglob("*") if p.is_file()]
    for secret in SECRETS:
        assert not any(secret in text for text in texts), secret


def test_the_real_client_drives_the_bot_over_a_fake_broker(monkeypatch, capsys):
    """farmbot 2.x itself, its MQTT replaced: the messages it sends and how its state.error
    reports failures are what the backend assumes."""
    farmbot = pytest.importorskip("farmbot")
    from farmbot.functions import api, broker

    device = FakeDevice(position_mm=(10.0, 20.0, -30.0))
    sent, clients, senders = [], [], {}

    class Mqtt:
        def __init__(self, *args, **kwargs):
            self.on_message = self.on_connect = None
            clients.append(self)

        def username_pw_set(self, username, password):
            assert username == "device_7" and password == make_token()["token"]["encoded"]

        def tls_set(self, **kwargs):
            self.tls = True

        def connect(self, host, port=1883, keepalive=60):
            assert host == "mqtt.example.org"
            # The token is the MQTT password: only ever over TLS, on the broker's TLS port.
            assert getattr(self, "tls", False) and port == 8883

        def loop_start(self):
            pass

        def loop_stop(self):
            pass

        def subscribe(self, topic):
            pass

        def disconnect(self):
            self.disconnected = True

        def _deliver(self, channel, content):
            self.on_message(self, None, SimpleNamespace(topic=f"bot/device_7/{channel}",
                                                        payload=json.dumps(content)))

        def publish(self, topic, payload):
            rpc = json.loads(payload)
            body = rpc["body"][0]
            sent.append(body)
            senders.setdefault(body["kind"], set()).add(id(self))
            label = {"label": rpc["args"]["label"]}
            if body["kind"] == "read_status":
                return self._deliver("status", device.status())
            if body["kind"] == "emergency_lock":
                device.estopped.set()
            if body["kind"] == "move" and device.block_moves:
                device.moving.set()

                def later():  # FarmBot OS answers the move once the stop has ended it
                    device.estopped.wait(60.0)
                    self._deliver("from_device", {
                        "kind": "rpc_error", "args": label,
                        "body": [{"kind": "explanation",
                                  "args": {"message": "Movement failed: emergency lock"}}]})
                return threading.Thread(target=later).start()
            self._deliver("from_device", {"kind": "rpc_ok", "args": label})

    def request(**kwargs):
        assert kwargs["url"] == "https://my.farm.bot/api/tokens"
        assert kwargs["json"] == {"user": {"email": EMAIL, "password": PASSWORD}}
        return SimpleNamespace(status_code=200, json=make_token)

    real_sleep = time.sleep
    monkeypatch.setattr(broker.mqtt, "Client", Mqtt)
    monkeypatch.setattr(broker, "time", SimpleNamespace(sleep=lambda s: real_sleep(0.002)))
    monkeypatch.setattr(api.requests, "request", request)
    credentials = CloudCredentials.from_environment({"FARMBOT_EMAIL": EMAIL,
                                                     "FARMBOT_PASSWORD": PASSWORD})
    bot = FarmbotCloudBot(credentials, head_settle_s=0.01, client_factory=farmbot.Farmbot)
    np.testing.assert_allclose(bot.position(), farmbot_mm_to_bed([10.0, 20.0, -30.0]))
    bot.move_to([1.0, 0.5, 0.4], speed_fraction=0.25)
    move = next(b for b in sent if b["kind"] == "move")
    axes = {i["args"]["axis"]: i["args"]["axis_operand"]["args"]["number"]
            for i in move["body"] if i["kind"] == "axis_overwrite"}
    assert axes == dict(zip("xyz", np.round(bed_to_farmbot_mm([1.0, 0.5, 0.4]), 2).tolist(),
                            strict=True))
    assert {i["args"]["speed_setting"]["args"]["number"] for i in move["body"]
            if i["kind"] == "speed_overwrite"} == {25}
    bot.set_head(math.radians(90), math.radians(45))
    servos = [(b["args"]["pin_number"], b["args"]["pin_value"]) for b in sent
              if b["kind"] == "set_servo_angle"]
    assert [pin for pin, _ in servos] == [6, 5] and all(isinstance(v, int) for _, v in servos)
    bot.home("z")
    assert sent[-1] == {"kind": "find_home", "args": {"axis": "z", "speed": 100}}

    device.block_moves = True
    errors = []
    owner = threading.Thread(target=lambda: errors.append(
        pytest.raises(EmergencyStopError, bot.move_to, [1.5, 0.5, 0.4])), daemon=True)
    owner.start()
    assert device.moving.wait(30.0), "hung: the move never reached the broker"
    _stop_while_blocked(bot)
    owner.join(30.0)
    assert not owner.is_alive(), "hung: the move did not end at the emergency stop"
    assert errors  # it raised EmergencyStopError
    assert not senders["emergency_lock"] & senders["move"]  # a connection of its own
    device.block_moves = False
    bot.unlock()
    assert [b["kind"] for b in sent[-3:]] == ["emergency_unlock", "set_servo_angle",
                                              "set_servo_angle"]
    bot.close()
    assert any(getattr(c, "disconnected", False) for c in clients)
    out, err = capsys.readouterr()
    assert out == "" and err == ""  # the client printed nothing, no credential


def test_a_server_that_would_take_the_login_unencrypted_is_refused():
    login = {"FARMBOT_EMAIL": "grower@example.org", "FARMBOT_PASSWORD": "x"}
    with pytest.raises(InputError, match="is http://: the login would cross the network"):
        CloudCredentials.from_environment({**login, "FARMBOT_SERVER": "http://farm.example.org"})
    local = CloudCredentials.from_environment({**login, "FARMBOT_SERVER": "http://localhost:3000"})
    assert local.server == "http://localhost:3000"
    with pytest.raises(InputError, match="expected https://host"):
        CloudCredentials.from_environment({**login, "FARMBOT_SERVER": "farm.example.org"})


def test_a_broker_without_tls_gets_plain_mqtt_and_a_warning(monkeypatch, capsys):
    import paho.mqtt.client as mqtt

    from flowerpose.hardware.backends import cloud_client

    ports = []

    class Mqtt:
        def __init__(self, *args, **kwargs):
            self.tls = False

        def username_pw_set(self, username, password):
            pass

        def tls_set(self, **kwargs):
            self.tls = True

        def connect(self, host, port=1883, keepalive=60):
            ports.append((port, self.tls))
            if port == 8883:
                raise ConnectionRefusedError(111, "Connection refused")

        def loop_start(self):
            pass

    monkeypatch.setattr(mqtt, "Client", Mqtt)
    state = SimpleNamespace(token=make_token(), check_token=lambda: None,
                            print_status=lambda **kw: None, error=None)
    holder = SimpleNamespace(state=state, client=None)
    cloud_client.connect_broker(holder)
    assert ports == [(8883, True), (1883, False)]
    err = capsys.readouterr().err
    assert "no TLS on port 8883" in err and "unencrypted" in err
    assert make_token()["token"]["encoded"] not in err
