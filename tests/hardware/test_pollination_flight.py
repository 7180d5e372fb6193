"""Flying a pollination plan on a bot: the visits flown touch where the plan says, a flight
cut short resumes at the next visit, the bot's own limits and position are checked before
anything moves, and `flowerpose pollinate --port` flies on a virtual Farmduino."""

import json
from dataclasses import replace

import numpy as np
import pytest
from cli_run import run_cli

from flowerpose.cloudio import Cloud, write_cloud
from flowerpose.errors import InputError
from flowerpose.hardware.bot import BotInfo, KinematicBot
from flowerpose.hardware.bot_errors import StallError
from flowerpose.hardware.flights.pollination_flight import FLIGHT_NAME, fly_pollination
from flowerpose.hardware.flights.pollination_plan import Flower, plan_pollination
from flowerpose.hardware.kinematics import HeadPose, tool_forward
from flowerpose.hardware.trajectory import Timeline
from flowerpose.jsonio import read_json

CENTER = np.array([1.5, 0.75, 0.2])
#: These flights test the executor on the scan's poses: the close look needs a camera
#: (tests/hardware/test_close_look.py flies it).
NO_LOOK = ("--set", "pollinate.look.views=0")


def _flowers() -> list[Flower]:
    tilts = [np.array([0.0, 0.0, 1.0]), np.array([0.4, 0.0, 1.0]), np.array([0.0, -0.3, 1.0])]
    offsets = [np.zeros(3), np.array([0.06, 0.02, -0.02]), np.array([-0.05, 0.04, 0.01])]
    return [Flower(k, CENTER + offset, tilt / np.linalg.norm(tilt))
            for k, (offset, tilt) in enumerate(zip(offsets, tilts, strict=True))]


def test_the_flown_visits_rest_the_swab_where_the_plan_touches(tmp_path):
    plan = plan_pollination(_flowers(), None)
    assert len(plan.planned) == 3
    timeline = Timeline()
    bot = KinematicBot(observer=timeline.add)
    flight = fly_pollination(bot, plan, tmp_path, source={"backend": "kinematic"})
    assert flight["status"] == "complete"
    assert [d["flower"] for d in flight["done"]] == [v.flower for v in plan.planned]
    assert read_json(tmp_path / FLIGHT_NAME) == flight
    dwells = [a for a in timeline.activities() if a.kind == "dwell"]
    assert len(dwells) == 3
    for visit, dwell in zip(plan.planned, dwells, strict=True):
        gantry, yaw, pitch = timeline.poses([dwell.t0 + dwell.elapsed / 2])
        tip, ahead = tool_forward(HeadPose(gantry[0], yaw[0], pitch[0]))
        planned_tip, planned_ahead = tool_forward(visit.touch)
        assert np.abs(tip - planned_tip).max() < 1e-9
        assert np.abs(ahead - planned_ahead).max() < 1e-9
    # Every visit starts and ends at the top of Z, clear of the plant.
    top = bot.info.travel_max[2]
    for entry in flight["done"]:
        lift = next(a for a in timeline.activities() if a.t0 >= entry["t0"] - 1e-3)
        assert lift.kind == "move" and np.isclose(lift.gantry_end[2], top)
    assert np.isclose(bot.position()[2], top)


class _CutBot(KinematicBot):
    """Stalls on its `cut_at`-th move, as a motor would."""

    def __init__(self, cut_at: int, **kwargs):
        super().__init__(**kwargs)
        self.moves, self.cut_at = 0, cut_at

    def move_to(self, xyz, speed_fraction: float = 1.0) -> None:
        self.moves += 1
        if self.moves == self.cut_at:
            self.fail_next_move(31)
        super().move_to(xyz, speed_fraction)


def test_a_flight_cut_short_resumes_at_the_next_visit(tmp_path):
    plan = plan_pollination(_flowers(), None)
    per_visit = 1 + sum(m.flower == plan.planned[0].flower and m.kind not in ("lift", "dwell")
                        for m in plan.moves)
    bot = _CutBot(cut_at=per_visit + 3)  # part way into the second visit
    with pytest.raises(StallError):
        fly_pollination(bot, plan, tmp_path, source={})
    cut = read_json(tmp_path / FLIGHT_NAME)
    assert cut["status"] == "interrupted" and "StallError" in cut["sessions"][0]["error"]
    assert [d["flower"] for d in cut["done"]] == [plan.planned[0].flower]
    timeline = Timeline()
    again = KinematicBot(observer=timeline.add)
    flight = fly_pollination(again, plan, tmp_path, source={})
    assert flight["status"] == "complete" and len(flight["sessions"]) == 2
    assert [d["flower"] for d in flight["done"]] == [v.flower for v in plan.planned]
    assert sum(a.kind == "dwell" for a in timeline.activities()) == 2  # the first not again
    before = again.now()
    assert fly_pollination(again, plan, tmp_path, source={})["status"] == "complete"
    assert again.now() == before  # complete: nothing flown


def test_another_plans_flight_and_a_bot_that_cannot_fly_it_are_refused_before_moving(
        tmp_path):
    plan = plan_pollination(_flowers(), None)
    fly_pollination(KinematicBot(), plan, tmp_path, source={})
    other = plan_pollination(_flowers()[:2], None)
    bot = KinematicBot()
    with pytest.raises(InputError, match="another plan"):
        fly_pollination(bot, other, tmp_path, source={})
    info = BotInfo.from_geometry("short")
    short = KinematicBot(info=replace(info, travel_max=np.array([1.4, *info.travel_max[1:]])))
    with pytest.raises(InputError, match=r"short cannot fly the plan: .*x = 1\.\d+ m"):
        fly_pollination(short, plan, tmp_path / "short", source={})
    assert short.now() == 0.0 and not (tmp_path / "short" / FLIGHT_NAME).exists()


def _flowers_file(tmp_path):
    tmp_path.mkdir(parents=True, exist_ok=True)
    path = tmp_path / "flowers.json"
    path.write_text(json.dumps({"frame": "bed", "flowers": [
        {"id": 3, "center": CENTER.tolist(), "normals": {"plane": [0.0, 0.0, 1.0]}}]}))
    angle = np.linspace(0, 2 * np.pi, 200)
    ring = np.c_[CENTER[0] + 0.1 * np.cos(angle), CENTER[1] + 0.1 * np.sin(angle),
                 np.full(200, 0.05)]
    write_cloud(tmp_path / "plant.ply", Cloud(ring, np.full((200, 3), 90, np.uint8)))
    return path



@pytest.mark.slow
def test_pollinate_flies_on_a_virtual_farmduino_after_homing(tmp_path, capsys):
    virtual = pytest.importorskip("flowerpose.hardware.backends.virtual_farmduino")
    flowers = _flowers_file(tmp_path)
    argv = ["pollinate", flowers, "--plant-at", "1.5,0.75", "--plant-cloud",
            tmp_path / "plant.ply", "--out", tmp_path / "visits", *NO_LOOK]
    code, out, err = run_cli(capsys, *argv, "--port", "/dev/no-such-port", "--dry-run")
    assert code == 0 and " dwell " in out and not (tmp_path / "visits" / FLIGHT_NAME).exists()
    with virtual.VirtualFarmduino(time_scale=100.0,
                                  params=virtual.FEEDBACK_PARAMETERS) as device:
        code, out, err = run_cli(capsys, *argv, "--port", device.path)
        assert code == 0, err
        assert "homing" in err and "flight complete: 1/1 flowers pollinated" in out
        assert any(line.startswith("F11") for line in device.received)
    flight = read_json(tmp_path / "visits" / FLIGHT_NAME)
    assert flight["source"]["backend"] == "serial" and flight["done"][0]["flower"] == 3


@pytest.mark.parametrize("extra, words", [
    (["--port", "/dev/ttyACM0", "--cloud"], "choose one bot"),
    (["--cloud", "--home-here"], "is for --port"),
    (["--port", "/dev/ttyACM0", "--token-file", "t.json"], "is for --cloud"),
])
def test_pollinate_with_bad_bot_options_is_one_line_and_exit_2(tmp_path, capsys, extra, words):
    flowers = _flowers_file(tmp_path)
    code, _, err = run_cli(capsys, "pollinate", flowers, "--plant-at", "1.5,0.75", "--out",
                        tmp_path / "visits", *extra)
    assert code == 2 and err.count("\n") == 1 and words in err
    assert not (tmp_path / "visits").exists()


def test_flying_without_the_plants_cloud_is_refused_before_connecting(tmp_path, capsys):
    flowers = _flowers_file(tmp_path)
    code, _, err = run_cli(capsys, "pollinate", flowers, "--plant-at", "1.5,0.75", "--out",
                        tmp_path / "visits", "--port", "/dev/no-such-port")
    assert code == 2 and "--plant-cloud: needed to fly" in err.splitlines()[-1]
    assert not (tmp_path / "visits").exists()


@pytest.mark.slow
def test_a_cloud_flight_interrupted_resumes_at_the_next_visit(tmp_path, capsys, monkeypatch):
    from cloud_fakes import FakeDevice, fake_factory, make_token

    from flowerpose.hardware.backends import cloud_bot

    for name in ("FARMBOT_EMAIL", "FARMBOT_PASSWORD", "FARMBOT_SERVER"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("FARMBOT_TOKEN", json.dumps(make_token()))
    path = tmp_path / "flowers.json"
    path.write_text(json.dumps({"frame": "bed", "flowers": [
        {"id": k, "center": f.center.tolist(), "normals": {"plane": f.normal.tolist()}}
        for k, f in enumerate(_flowers())]}))
    _flowers_file(tmp_path / "cloud")  # its ring of plant points
    device = FakeDevice(position_mm=(500.0, 300.0, -200.0))
    moves = []

    def factory():
        client = fake_factory(device)()

        def move(**kwargs):
            moves.append(kwargs)
            record = tmp_path / "visits" / FLIGHT_NAME
            if len(moves) > 3 and len(read_json(record)["done"]) == 1:  # into the second
                raise KeyboardInterrupt
            return type(client).move(client, **kwargs)
        client.move = move
        return client

    argv = ["pollinate", path, "--plant-at", "1.5,0.75", "--plant-cloud",
            tmp_path / "cloud" / "plant.ply", "--out", tmp_path / "visits", "--cloud",
            *NO_LOOK]
    monkeypatch.setattr(cloud_bot, "farmbot_client", factory)
    code, _, err = run_cli(capsys, *argv)
    assert code == 130 and "interrupted" in err
    cut = read_json(tmp_path / "visits" / FLIGHT_NAME)
    assert cut["status"] == "interrupted" and len(cut["done"]) == 1
    monkeypatch.setattr(cloud_bot, "farmbot_client", lambda: fake_factory(device)())
    code, out, err = run_cli(capsys, *argv)
    assert code == 0, err
    assert "resuming at visit 2 of 3" in err and "flight complete: 3/3" in out
    flight = read_json(tmp_path / "visits" / FLIGHT_NAME)
    assert flight["source"]["backend"] == "farmbot-cloud" and len(flight["sessions"]) == 2
    assert make_token()["token"]["encoded"] not in (tmp_path / "visits" / FLIGHT_NAME).read_text()


def test_flying_without_credentials_is_refused_before_the_plan_is_written(tmp_path, capsys,
                                                                          monkeypatch):
    for name in ("FARMBOT_TOKEN", "FARMBOT_EMAIL", "FARMBOT_PASSWORD", "FARMBOT_SERVER"):
        monkeypatch.delenv(name, raising=False)
    flowers = _flowers_file(tmp_path)
    code, _, err = run_cli(capsys, "pollinate", flowers, "--plant-at", "1.5,0.75",
                        "--plant-cloud", tmp_path / "plant.ply", "--out", tmp_path / "visits",
                        "--cloud", *NO_LOOK)
    assert code == 2 and "FARMBOT_TOKEN" in err.splitlines()[-1]
    assert not (tmp_path / "visits").exists()


def test_a_flight_into_a_folder_another_is_flying_from_is_refused_and_a_dead_one_is_marked(
        tmp_path):
    from flowerpose.hardware.flights.flight_journal import folder_lock
    from flowerpose.hardware.flights.pollination_flight import LOCK_NAME

    plan = plan_pollination(_flowers(), None)
    with folder_lock(tmp_path, LOCK_NAME, "pollination flight"):  # another process's
        with pytest.raises(InputError, match=r"another pollination flight \(pid \d+\)"):
            fly_pollination(KinematicBot(), plan, tmp_path, source={})
    assert not (tmp_path / FLIGHT_NAME).exists()
    # A session that never wrote its end died (a power cut): the resume says so in it, as a
    # scan's does, and flies on.
    bot = _CutBot(cut_at=3)
    with pytest.raises(StallError):
        fly_pollination(bot, plan, tmp_path, source={})
    record = read_json(tmp_path / FLIGHT_NAME)
    record["status"] = "running"
    del record["sessions"][0]["bot_time_end"], record["sessions"][0]["error"]
    (tmp_path / FLIGHT_NAME).write_text(json.dumps(record))
    flight = fly_pollination(KinematicBot(), plan, tmp_path, source={})
    assert flight["status"] == "complete"
    assert flight["sessions"][0]["error"].startswith("ended without closing")
