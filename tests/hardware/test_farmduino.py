"""The serial Farmduino backend against the virtual Farmduino over a real pty."""

from __future__ import annotations

import functools
import signal
import threading
import time

import numpy as np
import pytest

from flowerpose.errors import InputError
from flowerpose.hardware.backends.farmduino import FarmduinoBot
from flowerpose.hardware.backends.virtual_farmduino import FEEDBACK_PARAMETERS, VirtualFarmduino
from flowerpose.hardware.bot import KinematicBot, SolidCamera
from flowerpose.hardware.bot_errors import (
    BotError,
    CameraError,
    ConnectionLostError,
    EmergencyStopError,
    HomingError,
    LockedError,
    NotConfiguredError,
    OutOfRangeError,
    PositionLostError,
    StallError,
    UnknownCommandError,
)
from flowerpose.hardware.flights.scan_flight import run_scan
from flowerpose.hardware.flights.scan_plan import ScanConfig, plan_scan
from flowerpose.hardware.geometry import PAPER_BOT, bed_to_farmbot_mm
from flowerpose.hardware.kinematics import HeadPose, servo_commands
from flowerpose.hardware.motion import move_duration
from flowerpose.hardware.protocol import move_line
from flowerpose.jsonio import read_json
from flowerpose.scan_geometry import ScanPathConfig

SCALE = 1000.0  # simulated seconds per wall second
SMALL = ScanConfig(ScanPathConfig(azimuth_step_deg=90.0, cylinder_bottom_m=0.2,
                                  dome_polar_deg=(50.0,)))
CAMERA = functools.partial(SolidCamera, width=32, height=24, fps=2)
PLAN = plan_scan(np.array([1.5, 0.75]), 0.25, SMALL)


#: Every test runs under the 20 s watchdog (conftest.py).
pytestmark = pytest.mark.usefixtures("watchdog")


@pytest.fixture
def device():
    with VirtualFarmduino(time_scale=SCALE, params=FEEDBACK_PARAMETERS) as dev:
        yield dev


def _bot(device, scale=SCALE, **kwargs) -> FarmduinoBot:
    return FarmduinoBot(device.path, camera=CAMERA, clock_scale=scale, **kwargs)


def _moves(device) -> list[str]:
    return [line.rsplit(" Q", 1)[0] for line in device.received if line.startswith("G00")]


# --- lines and replies --------------------------------------------------------------

def test_connect_reads_the_firmware_and_its_own_parameters():
    params = {71: 300, 13: 60, 5: 2, 141: 5000}
    with VirtualFarmduino(time_scale=SCALE, params={**FEEDBACK_PARAMETERS, **params}) as tuned:
        with _bot(tuned) as bot:
            assert bot.info.firmware == "6.6.23.V.virtual"
            assert bot.info.motion.x.max_speed == 300 and bot.info.motion.z.timeout_s == 60
            # 5000 steps at 5 steps/mm: X reaches 1 m from home.
            assert bot.info.travel_max[0] == pytest.approx(PAPER_BOT.home[0] + 1.0)
            assert tuned.parameter(2) == 1  # the configuration was approved
            sent = tuned.received
            assert {f"F21 P{p}" for p in (5, 11, 12, 13, 141, 142, 143)} <= {
                line.rsplit(" Q", 1)[0] for line in sent}
            bot.home()
            with pytest.raises(OutOfRangeError, match="outside the travel"):
                bot.move_to(PAPER_BOT.home + [1.2, 0, 0])


def test_opening_a_missing_port_is_one_clear_input_error(tmp_path):
    with pytest.raises(InputError, match="cannot open the serial port"):
        FarmduinoBot(str(tmp_path / "ttyACM9"))


def test_a_bot_given_no_camera_says_so(device):
    with FarmduinoBot(device.path, clock_scale=SCALE) as bot:
        with pytest.raises(CameraError, match="no camera"):
            bot.camera.intrinsics()


def test_moves_wait_for_homing_after_the_board_starts(device):
    with _bot(device) as bot:
        with pytest.raises(PositionLostError, match="home"):
            bot.move_to(PAPER_BOT.home)
        bot.home()
        assert [line.split()[0] for line in device.received[-3:]] == ["F13", "F12", "F11"]
        bot.move_to([1.0, 0.5, 0.4])
        assert _moves(device)[-1] == "G00 X861.10 Y365.00 Z-250.00"  # all three axes
        np.testing.assert_allclose(bot.position(), [1.0, 0.5, 0.4], atol=2e-4)  # whole steps
        np.testing.assert_allclose(device.joints()[:3], bot.position() - PAPER_BOT.home,
                                   atol=1e-9)


# --- final replies ------------------------------------------------------------------

def test_every_final_reply_ends_the_command_with_its_error(device):
    with _bot(device) as bot:
        bot.home()
        assert bot._command("F82").replies[-1].code == "R02"
        with pytest.raises(UnknownCommandError, match="R09"):
            bot._command("F99")
        bot._command("F22 P2 V0")
        with pytest.raises(NotConfiguredError, match="R88"):
            bot.move_to([1.0, 0.5, 0.4])
        bot._command("F22 P2 V1")
        device.stall_next_move("x", 0.5)
        with pytest.raises(StallError) as stall:
            bot.move_to([1.0, 0.5, 0.4])
        assert stall.value.axis == "x" and stall.value.code == 31
        x_mm = device.firmware_position_mm()[0]
        assert 0 < x_mm < 861
        # position() is where the firmware said the gantry stopped.
        assert bed_to_farmbot_mm(bot.position())[0] == pytest.approx(x_mm, abs=0.01)
        bot.emergency_stop()
        with pytest.raises(LockedError, match="R87"):
            bot._command("F61 P6 V90")
        with pytest.raises(LockedError):
            bot.move_to([1.0, 0.5, 0.4])


def test_q_numbers_cycle_from_999_to_1(device):
    with _bot(device) as bot:
        bot._q = 997
        for _ in range(3):
            bot._command("F82")
    assert [line.rsplit(" ", 1)[1] for line in device.received[-3:]] == ["Q998", "Q999", "Q1"]


# --- head, lock and emergency stop -------------------------------------------------

def test_the_head_takes_whole_servo_degrees_on_pins_6_and_5(device):
    with _bot(device) as bot:
        bot.home()
        bot.set_head(0.5, 1.0)
        yaw, pitch = servo_commands(HeadPose(bot.position(), 0.5, 1.0))
        assert device.servo(6) == round(float(yaw)) and device.servo(5) == round(float(pitch))
        assert bot.head() == pytest.approx((0.5, 1.0), abs=np.radians(0.76))
        np.testing.assert_allclose(device.joints()[3:], bot.head(), atol=1e-9)


def _stop_once_moving(device: VirtualFarmduino, bot: FarmduinoBot) -> None:
    """Emergency-stop `bot` from a thread of its own as soon as `device`'s gantry has left
    where it was homed: mid-move however late this machine runs either thread."""
    def stop():
        deadline = time.monotonic() + 30.0  # bounded; the watchdog fails the test sooner
        while not np.any(device.firmware_position_mm()) and time.monotonic() < deadline:
            time.sleep(0.005)
        bot.emergency_stop()

    threading.Thread(target=stop, daemon=True).start()


@pytest.mark.slow
def test_emergency_stop_from_another_thread_mid_move(device):
    activities = []
    # A 2.66 m X move takes 35 s simulated, 3.5 s of wall time: a stop that lands as it
    # starts ends it short of the target, an ignored one would let it arrive.
    target = np.array([2.8, 0.135, 0.65])
    with VirtualFarmduino(time_scale=10.0, params=FEEDBACK_PARAMETERS) as slow:
        with _bot(slow, scale=10.0, observer=activities.append) as bot:
            bot.home()
            bot.set_head(0.3, 0.8)
            _stop_once_moving(slow, bot)
            with pytest.raises(EmergencyStopError):
                bot.move_to(target)
            assert slow.locked and slow.servo(6) is None  # E cuts the servo pulses
            stopped_at = slow.firmware_position_mm()[0]
            assert 0 < stopped_at < bed_to_farmbot_mm(target)[0]  # stopped, not finished
            move = activities[-1]
            assert move.kind == "move"
            assert move.elapsed < move_duration(move.gantry_start, target, bot.info.motion)
            with pytest.raises(LockedError):
                bot.move_to([1.0, 0.135, 0.65])
            with pytest.raises(LockedError):
                bot.dwell(1.0)
            bot.unlock()
            assert not slow.locked and slow.servo(6) is not None  # angles sent again
            bot.move_to([0.5, 0.135, 0.65])
            assert slow.firmware_position_mm()[0] == pytest.approx(361.1, abs=0.2)
            # An emergency stop during a pause ends it too.
            timer = threading.Timer(0.1, bot.emergency_stop)
            timer.start()
            with pytest.raises(EmergencyStopError):
                bot.dwell(100.0)
            assert activities[-1].kind == "dwell" and activities[-1].elapsed < 50.0


@pytest.mark.slow
@pytest.mark.parametrize("report_period_s", [0.5, 5.0])
def test_unlock_right_after_a_stop_waits_for_the_firmware_to_end_it(monkeypatch,
                                                                    report_period_s):
    """The real firmware answers R87 at once but discards input until its R03 V1 a quarter
    of a second later: an F09 sent on the R87 was lost and unlock() timed out. Also on the
    board that reports only every 5 s."""
    monkeypatch.setattr("flowerpose.hardware.backends.farmduino.REPLY_TIMEOUT_S", 3.0)
    with (VirtualFarmduino(time_scale=2.0, params=FEEDBACK_PARAMETERS,
                           report_period_s=report_period_s) as device,
          _bot(device, scale=2.0) as bot):
        bot.home()
        bot.set_head(0.3, 0.8)
        timer = threading.Timer(0.4, bot.emergency_stop)
        timer.start()
        with pytest.raises(EmergencyStopError):
            bot.move_to([1.2, 0.135, 0.65])
        # The position is where the firmware ended the stop, not its report before R87.
        stopped = device.firmware_position_mm()
        np.testing.assert_allclose(bed_to_farmbot_mm(bot.position()), stopped, atol=0.01)
        bot.unlock()
        assert not device.locked and device.servo(6) is not None
        assert device.received[-3].startswith("F09")


# --- homing and the bot's own settings -----------------------------------------------

@pytest.fixture
def bare():
    """A board on the firmware's defaults: no endstops, no encoders."""
    with VirtualFarmduino(time_scale=SCALE) as dev:
        yield dev


def test_homing_an_axis_without_endstops_or_encoder_is_refused_before_anything_moves(bare):
    with _bot(bare) as bot:
        with pytest.raises(HomingError, match=r"Z: neither its endstops \(parameter 27 "
                           r"\(movement_enable_endpoints_z\)\) nor its encoder \(103 "
                           r"\(encoder_enabled_z\)\).*`home_here`"):
            bot.home()
        assert not any(line.startswith(("F11", "F12", "F13")) for line in bare.received)


def test_a_homing_the_firmware_cannot_finish_fails_at_once_and_is_stopped(bare, monkeypatch):
    """A board whose parameters do not tell: the firmware times out, backs off and tries
    again for good; the client aborts on its first timeout report."""
    monkeypatch.setattr(FarmduinoBot, "_check_homeable", lambda self, name, command: None)
    with _bot(bare) as bot:
        with pytest.raises(HomingError, match="Z axis timeout"):
            bot.home()
        assert bare.received[-1].startswith("F13")
        assert bare.firmware_position_mm() is not None and not bare.locked
        # Not left homing: the board takes the next command.
        assert bot.describe()["firmware"]
        bot.home_here()


def test_home_here_zeroes_the_counters_where_the_gantry_stands(bare):
    with _bot(bare) as bot:
        with pytest.raises(PositionLostError):
            bot.move_to([0.5, 0.135, 0.65])
        bot.home_here()
        np.testing.assert_allclose(bare.firmware_position_mm(), [0, 0, 0])
        bot.move_to([0.5, 0.135, 0.65])
        np.testing.assert_allclose(bare.firmware_position_mm(),
                                   bed_to_farmbot_mm(np.array([0.5, 0.135, 0.65])), atol=0.2)


def test_the_bots_settings_are_written_at_connect_and_read_back(bare):
    settings = {101: 1.0, 102: 1.0, 103: 1.0, 71: 300.0}
    with _bot(bare, settings=settings) as bot:
        assert [bare.parameter(p) for p in settings] == list(settings.values())
        bot.home()  # the encoders make home findable
        bare.reset()  # a restart reloads the defaults: the client writes them again
        with pytest.raises(PositionLostError):
            bot.move_to([0.3, 0.135, 0.65])
        assert bare.parameter(101) == 1.0
        bot.home()
    bare.ignore_writes(72)
    with pytest.raises(BotError, match=r"parameter 72 \(movement_max_spd_y\) did not take: "
                       "wrote 350, the board holds 400"):
        _bot(bare, settings={**settings, 72: 350.0})


def test_close_ends_the_bot(device):
    bot = _bot(device)
    bot.close()
    bot.close()
    bot.emergency_stop()  # does nothing
    with pytest.raises(BotError, match="closed"):
        bot.move_to([1.0, 0.5, 0.4])
    with pytest.raises(BotError, match="closed"):
        bot.unlock()


# --- scans --------------------------------------------------------------------------

def _scan_moves(activities) -> np.ndarray:
    return np.array([a.gantry_end for a in activities if a.kind == "move"])


def test_a_scan_through_the_farmduino_visits_the_kinematic_bots_waypoints(device, tmp_path):
    reference = []
    run_scan(KinematicBot(camera=CAMERA, observer=reference.append), PLAN, tmp_path / "k",
             source={}, progress=False)
    activities = []
    with _bot(device, observer=activities.append) as bot:
        bot.home()
        homing = len(activities)
        manifest = run_scan(bot, PLAN, tmp_path / "f", source=bot.describe(), progress=False)
    assert manifest["status"] == "complete" and manifest["completed"] == len(PLAN.waypoints)
    scanned = activities[homing:]
    assert [a.kind for a in scanned] == [a.kind for a in reference]
    np.testing.assert_allclose(_scan_moves(scanned), _scan_moves(reference), atol=1e-12)
    sent = np.array([[float(v[1:]) for v in line.split()[1:4]] for line in _moves(device)])
    np.testing.assert_allclose(sent, bed_to_farmbot_mm(_scan_moves(reference)), atol=0.005)
    heads = np.array([a.head_end for a in scanned if a.kind == "head"])
    planned = np.array([[w.pose.yaw, w.pose.pitch] for w in PLAN.waypoints])
    np.testing.assert_allclose(heads, planned, atol=np.radians(0.76))  # whole servo degrees
    assert read_json(tmp_path / "f" / "scan.json")["source"]["backend"] == "farmduino"


def _fault_on_move(bot, number: int, fault) -> None:
    """Make `fault()` (a device fault) land on the bot's `number`-th move_to from now."""
    calls, move = [0], bot.move_to

    def move_to(xyz, speed_fraction=1.0):
        calls[0] += 1
        if calls[0] == number:
            fault()
        move(xyz, speed_fraction)

    bot.move_to = move_to


def test_a_stall_mid_scan_raises_with_the_recorded_data_intact(device, tmp_path):
    with _bot(device) as bot:
        bot.home()
        _fault_on_move(bot, 4, lambda: device.stall_next_move("y", 0.5))
        with pytest.raises(StallError) as stall:
            run_scan(bot, PLAN, tmp_path, source={}, progress=False)
    assert stall.value.axis == "y"
    manifest = read_json(tmp_path / "scan.json")
    assert manifest["status"] == "interrupted" and manifest["completed"] == 3
    assert "StallError" in manifest["sessions"][0]["error"]
    assert (tmp_path / "video.mp4").stat().st_size > 0 and (tmp_path / "camera.json").exists()
    with _bot(device) as bot:
        bot.home()
        resumed = run_scan(bot, PLAN, tmp_path, source={}, progress=False)
    assert resumed["status"] == "complete" and resumed["completed"] == len(PLAN.waypoints)
    assert [s["started_waypoint"] for s in resumed["sessions"]] == [0, 3]


def test_a_dropped_link_mid_scan_is_recovered_and_the_scan_completes(device, tmp_path):
    activities = []
    with _bot(device, observer=activities.append) as bot:
        bot.home()
        _fault_on_move(bot, 3, lambda: device.drop_next_move(0.5, down_s=0.15))
        manifest = run_scan(bot, PLAN, tmp_path, source={}, progress=False)
        assert manifest["status"] == "complete"
        assert manifest["completed"] == len(PLAN.waypoints)
        assert device.boots == 2  # reopening the port restarted the board
        np.testing.assert_allclose(bot.position(), PLAN.waypoints[-1].pose.gantry, atol=2e-4)
    starts = [a.t0 for a in activities]
    assert starts == sorted(starts)
    moves = _moves(device)
    third = move_line(bed_to_farmbot_mm(PLAN.waypoints[2].pose.gantry))
    assert moves.count(third) == 2  # the interrupted move, sent again after homing
    resent = [line.split()[0] for line in device.received]
    assert resent.count("F13") == 2 and resent.count("F83") == 2


def test_a_link_dropped_between_commands_is_recovered_before_the_next(device):
    activities = []
    with _bot(device, observer=activities.append) as bot:
        bot.home()
        bot.move_to([1.0, 0.5, 0.4])
        device.drop_connection(down_s=0.1)
        time.sleep(0.05)
        bot.move_to([1.2, 0.6, 0.4])  # reconnects, homes (the board restarted), moves
        assert device.boots == 2
        np.testing.assert_allclose(bot.position(), [1.2, 0.6, 0.4], atol=2e-4)
        np.testing.assert_allclose(device.joints()[:3], bot.position() - PAPER_BOT.home,
                                   atol=1e-9)
    starts = [a.t0 for a in activities]
    assert starts == sorted(starts)  # the observer hears of them in order


def test_a_link_that_does_not_come_back_is_a_connection_lost_error(device):
    with _bot(device, connect_timeout_s=0.5) as bot:
        bot.home()
        # Down for 60 s, three times the watchdog's limit: only giving up after
        # connect_timeout_s ends the move within the test.
        device.drop_next_move(0.2, down_s=60.0)
        with pytest.raises(ConnectionLostError, match="could not reconnect within 0.5 s"):
            bot.move_to([2.0, 1.0, 0.4])


def test_garbage_on_the_line_is_ignored(device):
    with _bot(device) as bot:
        bot.home()
        device.inject_garbage(b"\x00\xff\xfe R9 noise\r\n\x13\x37")  # the next reply follows
        bot.move_to([1.0, 0.5, 0.4])
        device.inject_garbage(bytes(range(256)))
        bot.set_head(0.2, 0.9)
        assert device.servo(6) is not None


def test_a_board_reset_mid_move_stops_with_position_lost_until_homed(device):
    with _bot(device) as bot:
        bot.home()
        device.reset_next_move(0.5)
        with pytest.raises(PositionLostError, match="restarted on its own"):
            bot.move_to([2.0, 1.0, 0.4])
        assert device.parameter(2) == 1  # the firmware was brought up again
        with pytest.raises(PositionLostError, match="not been homed"):
            bot.move_to([1.0, 0.5, 0.4])
        bot.home()
        np.testing.assert_allclose(device.joints()[:3], 0.0)
        bot.move_to([1.0, 0.5, 0.4])
        np.testing.assert_allclose(device.joints()[:3], bot.position() - PAPER_BOT.home,
                                   atol=1e-9)


@pytest.mark.slow
def test_the_simulated_scan_through_the_serial_path(tmp_path):
    """What `flowerpose scan --sim --via-farmduino` runs, on a small plan at 64 x 48."""
    signal.setitimer(signal.ITIMER_REAL, 60.0)  # renders in a process pool: allow more
    from flowerpose.hardware.backends.serial_sim_bot import SimulatedSerialBot
    from flowerpose.hardware.backends.sim_bot import SimBotConfig
    from flowerpose.hardware.backends.sim_camera import SimCameraConfig
    from flowerpose.scanio import frame_files, read_trajectory
    from flowerpose.sim.bundle import make_plant

    plant = tmp_path / "plant"
    make_plant(0, "easy", points=2000, out_dir=plant)
    truth = read_json(plant / "plant.json")
    plan = plan_scan(np.array(truth["plant_center"][:2]), truth["height"], SMALL)
    config = SimBotConfig(camera=SimCameraConfig(width=64, height=48, frame_rate_hz=0.2,
                                                 workers=1, visibility_width=32))
    with SimulatedSerialBot([plant], config, time_scale=20.0) as bot:
        manifest = run_scan(bot, plan, tmp_path / "scan", source=bot.describe(),
                            progress=False)
        assert bot.device.firmware_position_mm() == pytest.approx(
            bed_to_farmbot_mm(plan.waypoints[-1].pose.gantry), abs=0.2)
    assert manifest["status"] == "complete" and manifest["completed"] == len(plan.waypoints)
    trajectory = read_trajectory(tmp_path / "scan" / "trajectory.csv")
    assert len(trajectory) == len(frame_files(tmp_path / "scan")) > len(plan.waypoints)
    assert manifest["source"]["backend"] == "sim via virtual Farmduino"
    # The last frame of each pause sees every waypoint from where the firmware stopped
    # (whole motor steps: within 0.2 mm).
    waypoints = np.array([w.pose.gantry for w in plan.waypoints])
    gap = np.linalg.norm(trajectory.gantry[:, None] - waypoints[None], axis=2).min(0)
    assert gap.max() < 3e-4
    # The simulated world's clock stands still while frames render and while the board
    # waits for the host, a dwell moves it on at once, and the board's late wake-ups are
    # taken back, so the scan takes the direct backend's time whatever the link's latency
    # and the machine's load (which the time scale multiplies), both backends ending every
    # move with the firmware's END_OF_MOVE_S. Measured: 68 and 68 frames, 242.2 and 242.2 s;
    # before the host's turn stood still, 69 against 68 and 246.6 against 236.2 s.
    from flowerpose.hardware.backends.sim_bot import SimBot

    with SimBot([plant], config) as direct:
        run_scan(direct, plan, tmp_path / "direct", source={}, progress=False)
    expected = read_trajectory(tmp_path / "direct" / "trajectory.csv")
    print(f"serial against direct: {len(trajectory)} and {len(expected)} frames, scans of "
          f"{trajectory.t[-1]:.1f} and {expected.t[-1]:.1f} s")
    assert abs(len(trajectory) - len(expected)) <= 1
    assert abs(trajectory.t[-1] - expected.t[-1]) < 0.005 * expected.t[-1]


def test_via_farmduino_needs_the_simulator(capsys):
    from flowerpose.cli import main

    assert main(["scan", "--via-farmduino", "--out", "x"]) == 2
    assert capsys.readouterr().err.count("\n") == 1


def test_the_virtual_board_and_the_serial_bot_need_only_the_core_install():
    """`farmduino --virtual` and a bot on its port run without the simulator's packages."""
    import json
    import subprocess
    import sys

    code = """
import functools, json, sys
for name in ("mujoco", "trimesh", "pyrender"):
    sys.modules[name] = None  # importing one now fails
import numpy as np
from flowerpose.hardware.bot import SolidCamera
from flowerpose.hardware.backends.farmduino import FarmduinoBot
from flowerpose.hardware.backends.virtual_farmduino import FEEDBACK_PARAMETERS, VirtualFarmduino
camera = functools.partial(SolidCamera, width=32, height=24, fps=2)
with VirtualFarmduino(time_scale=1000.0, params=FEEDBACK_PARAMETERS) as device:
    with FarmduinoBot(device.path, camera=camera, clock_scale=1000.0) as bot:
        bot.home()
        bot.move_to([1.0, 0.5, 0.4])
        bot.set_head(np.pi / 2, np.pi)
        print(json.dumps(device.joints().tolist()))
"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 0, done.stderr
    joints = np.array(json.loads(done.stdout))
    np.testing.assert_allclose(joints[:3], np.array([1.0, 0.5, 0.4]) - PAPER_BOT.home,
                               atol=2e-4)  # whole steps
    # The servos take whole command degrees, 1.5 of the head's degrees each.
    np.testing.assert_allclose(joints[3:], [np.pi / 2, np.pi], atol=np.radians(1.5))
