"""The virtual Farmduino speaks FarmBot's firmware protocol on a real pty (raw pyserial)."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import serial

from flowerpose.errors import InputError
from flowerpose.hardware.backends.serial_sim_bot import PausableClock
from flowerpose.hardware.backends.virtual_farmduino import (
    DEFAULT_PARAMETERS,
    FEEDBACK_PARAMETERS,
    VirtualFarmduino,
)
from flowerpose.hardware.backends.virtual_firmware import FIRMWARE_VERSION
from flowerpose.hardware.motion import END_OF_MOVE_S, MotionProfile, move_duration
from flowerpose.hardware.protocol import BANNER

SCALE = 100.0  # simulated seconds per wall second: a 1 m X move takes 0.15 s
SLOW = 20.0  # for tests that act during a move: 0.7 s of wall time for 1 m, so a busy
# machine that stalls a thread for a while still finds the move running


#: Every test runs under the 20 s watchdog (conftest.py).
pytestmark = pytest.mark.usefixtures("watchdog")


class Link:
    """The host end: raw lines over pyserial."""

    def __init__(self, path: str):
        self.port = serial.Serial(path, 115200, timeout=0.05)
        self.seen: list[str] = []

    def send(self, text: str) -> None:
        self.port.write(text.encode("ascii") + b"\r\n")

    def until(self, predicate, timeout_s: float = 10.0) -> list[str]:
        """Lines read up to and including the first that satisfies `predicate` (within
        `timeout_s`: a hang guard)."""
        lines, deadline = [], time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            raw = self.port.readline()
            if raw.endswith(b"\n"):
                line = raw.decode("ascii", "replace").strip()
                lines.append(line)
                self.seen.append(line)
                if predicate(line):
                    return lines
        raise AssertionError(f"nothing matched within {timeout_s} s; got {lines[-12:]}")

    def command(self, text: str) -> list[str]:
        """Send `text` (with its Q) and read to its final reply."""
        q = text.split("Q")[-1]
        self.send(text)
        return self.until(lambda line: line.split()[0] in ("R02", "R03", "R09", "R87", "R88")
                          and line.endswith(f"Q{q}"))

    def close(self) -> None:
        self.port.close()


@pytest.fixture
def device(request):
    with VirtualFarmduino(time_scale=getattr(request, "param", SCALE),
                          params=FEEDBACK_PARAMETERS) as dev:
        yield dev


@pytest.fixture
def link(device):
    host = Link(device.path)
    host.until(lambda line: line == BANNER)
    yield host
    host.close()


def _approve(link):
    assert link.command("F22 P2 V1 Q90")[-1] == "R02 Q90"


@contextlib.contextmanager
def _approved_board(time_scale: float, params=None, **options):
    """A board of its own (`options` for VirtualFarmduino), booted, with its configuration
    approved: (device, link)."""
    with VirtualFarmduino(time_scale=time_scale, params=params or {}, **options) as device:
        link = Link(device.path)
        try:
            link.until(lambda line: line == BANNER)
            _approve(link)
            yield device, link
        finally:
            link.close()


def _wait_for(condition, what: str) -> None:
    """Poll until `condition()` holds (10 s at most: a hang guard)."""
    deadline = time.monotonic() + 10.0
    while not condition():
        assert time.monotonic() < deadline, f"hung: {what}"
        time.sleep(0.005)


def _after_turn(device: VirtualFarmduino) -> None:
    """Wait for the turn the board's loop is in to end (a turn holds the device's lock):
    everything it said is then on the line."""
    with device._lock:
        pass


def test_opening_the_port_boots_and_every_command_is_echoed_with_its_q(device, link):
    assert device.boots == 1 and os.path.islink(device.path)
    lines = link.command("F83 Q5")
    # The echo keeps the sender's carriage return, as the real firmware's does.
    assert lines[-4:] == ["R08 *F83 Q5\r*", "R01 Q5", f"R83 {FIRMWARE_VERSION} Q5", "R02 Q5"]
    lines = link.command("F82 Q6")
    assert lines[-2:] == ["R82 X0.00 Y0.00 Z0.00 Q6", "R02 Q6"]


@pytest.mark.parametrize("device", [SLOW], indirect=True)
def test_idle_reports_and_r88_until_the_configuration_is_approved(device, link):
    link.until(lambda line: line == "R00 Q0")
    report = link.until(lambda line: line == "R88 Q0")
    assert "R82 X0.00 Y0.00 Z0.00 Q0" in report
    # A movement before approval is refused with R88 alone: no R01, no R03.
    lines = link.command("G00 X10.00 Y0.00 Z0.00 Q7")
    assert lines[-2:] == ["R08 *G00 X10.00 Y0.00 Z0.00 Q7\r*", "R88 Q7"]
    assert device.firmware_position_mm()[0] == 0.0
    _approve(link)
    assert device.parameter(2) == 1
    lines = link.command("G00 X1000.00 Y0.00 Z0.00 Q8")
    assert lines[-1] == "R02 Q8" and "R01 Q8" in lines
    assert "R04 Q8" in lines  # busy, with the command's Q, while it moves
    positions = [float(line.split()[1][1:]) for line in lines if line.startswith("R82")]
    # Reported on the way, in order (the first may come before the axis has started, on a
    # busy machine).
    assert positions[-1] == 1000.0 and any(0 < p < 1000.0 for p in positions)
    assert positions == sorted(positions)
    np.testing.assert_allclose(device.joints()[:3], [1.0, 0.0, 0.0])  # MuJoCo's joints


def test_parameters_read_written_and_unknown_ids_answer_r02_only(device, link):
    assert link.command("F21 P71 Q3")[-2:] == ["R21 P71 V400 Q3", "R02 Q3"]
    assert link.command("F22 P71 V300 Q4")[-1] == "R02 Q4"
    assert link.command("F21 P71 Q5")[-2:] == ["R21 P71 V300 Q5", "R02 Q5"]
    lines = link.command("F21 P9999 Q6")
    assert lines[-1] == "R02 Q6" and not any(line.startswith("R21") for line in lines)
    # Written parameters live until the next reset; the "EEPROM" ones come back.
    device.reset()
    link.until(lambda line: line == BANNER)
    assert link.command("F21 P71 Q7")[-2] == "R21 P71 V400 Q7"


def test_unknown_commands_answer_r09(link):
    assert link.command("F99 Q3")[-1] == "R09 Q3"
    # Not a G or F code: the firmware stops parsing before the Q.
    link.send("X12 Q4")
    assert link.until(lambda line: line.startswith("R09"))[-1] == "R09 Q0"


def test_emergency_stop_locks_until_f09(device, link):
    _approve(link)
    assert link.command("F61 P6 V90 Q2")[-1] == "R02 Q2" and device.servo(6) == 90.0
    link.port.write(b"E")
    link.until(lambda line: line == "R87 Q0")  # the idle report says locked
    assert device.locked and device.servo(6) is None  # the servos lost their pulses
    assert link.command("G00 X10.00 Y0.00 Z0.00 Q3")[-2:] == [
        "R08 *G00 X10.00 Y0.00 Z0.00 Q3\r*", "R87 Q3"]
    assert link.command("F61 P6 V90 Q4")[-1] == "R87 Q4"
    assert link.command("F82 Q5")[-1] == "R02 Q5"  # reading is allowed while locked
    assert link.command("F09 Q6")[-1] == "R02 Q6" and not device.locked
    assert link.command("G00 X10.00 Y0.00 Z0.00 Q7")[-1] == "R02 Q7"


def test_an_e_anywhere_in_a_line_is_an_emergency_stop(device, link):
    _approve(link)
    link.send("F22 P71 V1e3 Q3")
    link.until(lambda line: line.startswith("R87"))
    assert device.locked


@pytest.mark.parametrize("device", [SLOW], indirect=True)
def test_input_while_busy_is_discarded_except_e_and_abort(device, link):
    _approve(link)
    link.send("G00 X1000.00 Y0.00 Z0.00 Q3")
    link.until(lambda line: line == "R01 Q3")
    link.send("F82 Q4")  # no queue: dropped
    assert link.until(lambda line: line.startswith("R02") or line.startswith("R03"))[-1] == \
        "R02 Q3"
    assert device.discarded >= len("F82 Q4\r\n") and "R08 *F82 Q4\r*" not in link.seen
    assert link.command("F82 Q5")[-1] == "R02 Q5"
    # @ aborts the running move (once it is well under way), E stops it.
    link.send("G00 X0.00 Y0.00 Z0.00 Q6")
    link.until(lambda line: line.startswith("R82 X") and line.endswith("Q6")
               and float(line.split()[1][1:]) < 700)
    link.port.write(b"@")
    lines = link.until(lambda line: line.startswith("R03"))
    assert lines[-1] == "R03 V5 Q6" and 0 < device.firmware_position_mm()[0] < 700
    assert not device.locked
    link.send("G00 X1000.00 Y0.00 Z0.00 Q7")
    link.until(lambda line: line == "R04 Q7")
    link.port.write(b"E")
    lines = link.until(lambda line: line.startswith("R03"))
    assert "R87 Q7" in lines and lines[-1] == "R03 V1 Q7" and device.locked


@pytest.mark.slow
def test_a_stop_takes_as_long_as_the_real_firmwares_and_discards_what_comes_meanwhile():
    """farmbot-arduino-firmware 6.6.23: R87 within about 50 ms of the E, position reports
    while it stops, R03 V1 220-250 ms after the E; input before that R03 is dropped. From
    the E on, the board's clock moves only when the test moves it, so every reply is
    checked at its simulated time, however late this machine runs either end of the link."""
    clock = PausableClock()
    with _approved_board(1.0, FEEDBACK_PARAMETERS, wall_clock=clock) as (device, link):
        link.send("G00 X1000.00 Y0.00 Z0.00 Q3")
        link.until(lambda line: line == "R01 Q3")
        time.sleep(0.3)
        with clock.paused():
            link.port.write(b"E")
            _wait_for(lambda: device.locked, "the board never took the E")
            _after_turn(device)
            sent = device.now()

            def at(seconds: float) -> None:
                """Move the board's clock on to `seconds` after the E."""
                clock.skip(sent + seconds - device.now() + 1e-6)

            at(0.05)
            lines = link.until(lambda line: line == "R87 Q3")
            discarded = device.discarded
            link.send("F09 Q4")  # inside the stop window: lost
            _wait_for(lambda: device.discarded >= discarded + len("F09 Q4\r\n"),
                      "the F09 never reached the board")
            at(0.22)
            lines += link.until(lambda line: line.startswith("R82") and line.endswith("Q3"))
            lines += link.until(lambda line: line.startswith("R82") and line.endswith("Q3"))
            _after_turn(device)  # the report of the board's turn at 0.22 s
            assert not any(line.startswith("R03") for line in lines)
            assert link.port.in_waiting == 0  # nor is one on its way
            at(0.25)
            lines += link.until(lambda line: line.startswith("R03"))
        assert lines[-1] == "R03 V1 Q3"
        after = lines[lines.index("R87 Q3"):]
        assert sum(line.startswith("R82") and line.endswith("Q3") for line in after) >= 2
        assert "R08 *F09 Q4\r*" not in link.seen and device.locked
        # The last report is where the motors stopped.
        assert float(lines[-2].split()[1][1:]) == pytest.approx(
            device.firmware_position_mm()[0], abs=0.01)
        assert link.command("F09 Q5")[-1] == "R02 Q5" and not device.locked


def test_homing_without_endstops_or_encoders_times_out_and_tries_again_for_good():
    with _approved_board(1000.0) as (_, link):  # the firmware's defaults
        link.send("F13 Q3")
        lines = link.until(lambda line: line.startswith("R99 homing displaced"))
        assert "R73 Q3" in lines and "R99 timeout Z axis" in lines
        lines = link.until(lambda line: line.startswith("R99 homing displaced"))
        assert "R73 Q3" in lines and not any(line.startswith(("R02", "R03")) for line in lines)
        link.port.write(b"@")
        assert link.until(lambda line: line.startswith("R03"))[-1] == "R03 V5 Q3"


def test_the_commands_the_real_firmware_knows_beyond_motion(device, link):
    _approve(link)
    dump = link.command("F20 Q3")
    assert dump[-1] == "R02 Q3" and "R21 P101 V1 Q3" in dump and "R21 P27 V0 Q3" in dump
    assert link.command("F81 Q4")[-2:] == ["R81 XA0 XB0 YA0 YB0 ZA0 ZB0 Q4", "R02 Q4"]
    assert link.command("F43 P13 M1 Q5")[-1] == "R02 Q5"
    assert link.command("F44 P13 V1 W0 T100 M0 Q6")[-1] == "R02 Q6"
    assert link.command("G00 X100.00 Y0.00 Z0.00 Q7")[-1] == "R02 Q7"
    zeroed = link.command("F84 X1 Y0 Z0 Q8")
    assert zeroed[-2:] == ["R82 X0.00 Y0.00 Z0.00 Q8", "R02 Q8"]
    assert link.command("F31 P1 Q9")[-2:] == ["R31 P1 V0 Q9", "R02 Q9"]
    assert link.command("F32 P1 Q10")[-2:] == ["R31 P1 V0 Q10", "R02 Q10"]


@pytest.mark.parametrize("code, axis, steps", [("F14", 0, 13611), ("F15", 1, 6150),
                                               ("F16", 2, 10791)])
def test_measuring_an_axis_reports_its_length_in_steps(code, axis, steps):
    with _approved_board(2000.0, FEEDBACK_PARAMETERS) as (device, link):
        lines = link.command(f"{code} Q3")
        assert lines[-1] == "R02 Q3" and f"R23 P{21 + axis} V0 Q3" in lines
        assert f"R23 P{801 + axis} V{steps:.2f} Q3" in lines
        # The travel of the MuJoCo gantry (assets/farmbot), in the firmware's steps.
        length_mm = steps / (5.0, 5.0, 25.0)[axis]
        assert abs(device.firmware_position_mm()[axis]) == pytest.approx(length_mm, abs=0.2)


def test_measuring_an_axis_without_endstops_or_encoders_drives_on_until_e():
    with _approved_board(1000.0) as (bare, link):  # the firmware's defaults
        link.send("F14 Q3")
        # Far beyond the axis timeout (120 s simulated), still busy, never an R23.
        lines = link.until(lambda line: line == "R04 Q3")
        time.sleep(0.3)
        lines = link.until(lambda line: line == "R04 Q3")
        assert bare.now() > 150.0
        assert not any(line.startswith(("R02", "R03", "R23", "R71")) for line in lines)
        link.port.write(b"E")
        assert link.until(lambda line: line.startswith("R03"))[-1] == "R03 V1 Q3"


def test_the_boot_lists_every_parameter_and_a_move_ends_with_the_firmwares_reports():
    with VirtualFarmduino(time_scale=SCALE, params=FEEDBACK_PARAMETERS) as device:
        link = Link(device.path)
        try:
            link.until(lambda line: line == BANNER)
            dump = link.until(lambda line: line == "R21 P223 V0 Q0")
            assert sum(line.startswith("R21 ") for line in dump) == len(DEFAULT_PARAMETERS)
            assert "R21 P101 V1 Q0" in dump
            _approve(link)
            lines = link.command("G00 X50.00 Y0.00 Z0.00 Q4")
            tail = [line for line in lines[lines.index("R99 stopped"):]
                    if not line.startswith("R04")]  # busy reports may come meanwhile
            assert [line.split()[0] for line in tail[:5]] == ["R99", "R05", "R81", "R84", "R85"]
            assert tail[-2:] == ["R82 X50.00 Y0.00 Z0.00 Q4", "R02 Q4"]
            assert tail[3] == "R84 X50.00 Y0.00 Z0.00 Q4"
        finally:
            link.close()


def test_lines_are_processed_one_at_a_time(device, link):
    link.port.write(b"F21 P11 Q3\r\nF21 P12 Q4\r\n")
    link.until(lambda line: line == "R02 Q3")
    time.sleep(0.05)
    link.send("F83 Q5")
    link.until(lambda line: line == "R02 Q5")
    assert "F21 P12 Q4" not in device.received and "R02 Q4" not in link.seen


def test_servo_commands_drive_only_servo_pins(device, link):
    before = device.joints()
    assert link.command("F61 P7 V90 Q3")[-2:] == ["R01 Q3", "R02 Q3"]
    assert device.servo(7) is None
    np.testing.assert_array_equal(device.joints(), before)
    assert link.command("F61 P6 V40 Q4")[-1] == "R02 Q4"
    assert device.servo(6) == 40.0
    assert device.joints()[3] == pytest.approx(np.pi)  # command 40 is geometric yaw 180
    link.command("F61 P5 V1472 Q5")  # >= 544: microseconds (1472 us is the middle)
    assert device.servo(5) == pytest.approx(90.0)
    link.command("F41 P13 V1 M0 Q6")
    assert link.command("F42 P13 M0 Q7")[-2:] == ["R41 P13 V1 Q7", "R02 Q7"]


def test_missing_axes_go_to_zero_and_g28_and_homing(device, link):
    _approve(link)
    link.command("G00 X50.00 Y40.00 Z-30.00 Q2")
    link.command("G00 X20.00 Q3")
    np.testing.assert_allclose(device.firmware_position_mm(), [20.0, 0.0, 0.0])
    link.command("G00 X50.00 Y40.00 Z-30.00 Q4")
    assert link.command("G28 Q5")[-1] == "R02 Q5"
    np.testing.assert_allclose(device.firmware_position_mm(), [0.0, 0.0, 0.0], atol=1e-9)
    # Homing drives to the physical home and zeroes the counter there.
    link.command("G00 X100.00 Y0.00 Z0.00 Q6")
    device.reset()  # the counters restart at 0 where the gantry stands
    link.until(lambda line: line == BANNER)
    _approve(link)
    assert device.firmware_position_mm()[0] == 0.0 and device.joints()[0] == pytest.approx(0.1)
    assert link.command("F11 Q7")[-1] == "R02 Q7"
    assert device.joints()[0] == 0.0 and device.firmware_position_mm()[0] == 0.0


def test_positions_are_whole_steps_and_speed_overrides_slow_moves_away_from_home():
    # The board's clock stands still while it waits for the host: a move takes its
    # profile's time and END_OF_MOVE_S exactly, however late either end of the link runs.
    clock = PausableClock()
    with _approved_board(SCALE, FEEDBACK_PARAMETERS, wall_clock=clock,
                         on_idle=clock.host_turn) as (device, link):
        link.command("G00 X100.13 Y0.00 Z-10.01 Q2")
        np.testing.assert_allclose(device.firmware_position_mm(), [100.0, 0.0, -10.0],
                                   atol=1e-9)
        for q, extra in ((3, ""), (5, " A100")):
            link.command("G00 X0.00 Y0.00 Z0.00 Q9" + str(q))
            _after_turn(device)  # the clock has stopped for the host's turn
            t0 = device.now()
            link.command(f"G00 X500.00 Y0.00 Z0.00{extra} Q{q}")
            _after_turn(device)
            expected = move_duration([0, 0, 0], [0.5, 0, 0], MotionProfile().with_override(
                100.0 if extra else 0.0))
            assert device.now() - t0 == pytest.approx(expected + END_OF_MOVE_S, abs=1e-3)


def test_a_move_past_its_axis_timeout_stops_with_r03_v2(device, link):
    _approve(link)
    link.command("F22 P11 V5 Q2")  # X may move for 5 s
    lines = link.command("G00 X1000.00 Y0.00 Z0.00 Q3")
    assert lines[-1] == "R03 V2 Q3"
    x = device.firmware_position_mm()[0]
    assert 300 < x < 400  # 5 s of a 14.5 s move


def test_injected_faults_on_the_line(device, link):
    _approve(link)
    device.stall_next_move("y", 0.5)
    lines = link.command("G00 X0.00 Y500.00 Z0.00 Q3")
    assert lines[-1] == "R03 V32 Q3" and lines.count("R07 Q3") == 2  # 3 attempts
    assert 200 < device.firmware_position_mm()[1] < 300
    device.inject_garbage(b"\x00\xff#!noise")
    assert link.command("F83 Q4")[-1] == "R02 Q4"
    device.reset_next_move(0.5)
    link.send("G00 X0.00 Y0.00 Z0.00 Q5")
    link.until(lambda line: line == BANNER)  # no final reply: the board restarted
    assert link.command("G00 X0.00 Y0.00 Z0.00 Q6")[-1] == "R88 Q6"
    assert device.firmware_position_mm()[1] == 0.0 and device.joints()[1] > 0.1


@pytest.mark.slow
def test_a_dropped_link_comes_back_behind_the_same_symlink(device, link):
    _approve(link)
    device.drop_next_move(0.3, down_s=1.0)
    link.send("G00 X1000.00 Y0.00 Z0.00 Q3")
    with pytest.raises(serial.SerialException):
        link.until(lambda line: False)
    link.close()
    assert not os.path.exists(device.path)
    _wait_for(lambda: os.path.exists(device.path), "the symlink never came back")
    again = Link(device.path)
    again.until(lambda line: line == BANNER)
    assert device.boots == 2 and os.path.realpath(device.path) == device.device
    assert device.joints()[0] == pytest.approx(1.0)  # the move ended while unplugged
    assert device.firmware_position_mm()[0] == 0.0  # and opening the port reset the board
    again.close()


def test_time_scale_is_checked():
    with pytest.raises(InputError, match="time_scale"):
        VirtualFarmduino(time_scale=0)


@pytest.mark.slow
def test_command_line_serves_until_ctrl_c():
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    process = subprocess.Popen([sys.executable, "-m", "flowerpose", "farmduino", "--virtual",
                                "--time-scale", "50"], stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True, env=env,
                               # as from a terminal, even where this runs as a background job
                               preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        path = process.stdout.readline().strip()
        host = Link(path)
        host.until(lambda line: line == BANNER)
        assert host.command("F83 Q1")[-1] == "R02 Q1"
        host.close()
        process.send_signal(signal.SIGINT)
        out, err = process.communicate(timeout=10)
    finally:
        process.kill()
    assert process.returncode == 0 and "Traceback" not in err and "stopped" in err
    assert not os.path.exists(path)
    bad = subprocess.run([sys.executable, "-m", "flowerpose", "farmduino"],
                         capture_output=True, text=True)
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "--virtual" in bad.stderr


def test_a_simulated_worlds_clock_stands_still_while_the_board_waits_for_the_host():
    """With a PausableClock, the board's time passes only for its own work: a move takes
    its motion and END_OF_MOVE_S exactly, however late the host or the board's loop, and
    a host's wait moves the clock on at once by what it asks."""
    clock = PausableClock()
    with VirtualFarmduino(time_scale=SCALE, params=FEEDBACK_PARAMETERS, wall_clock=clock,
                          on_idle=clock.host_turn) as device:
        link = Link(device.path)
        try:
            link.until(lambda line: line == BANNER)
            _approve(link)
            start = device.now()
            time.sleep(0.05)  # 5 s of simulated time, were the clock running
            assert device.now() == start
            assert link.command("G00 X100.00 Y0.00 Z0.00 Q5")[-1] == "R02 Q5"
            motion = move_duration([0.0, 0.0, 0.0], [0.1, 0.0, 0.0],
                                   MotionProfile.from_firmware(device_parameters(device)))
            assert device.now() - start == pytest.approx(motion + END_OF_MOVE_S, abs=1e-3)
            answered = device.now()
            time.sleep(0.05)
            assert device.now() == answered
            clock.skip(2.0 / SCALE)
            assert device.now() - answered == pytest.approx(2.0, abs=1e-9)
        finally:
            link.close()


def device_parameters(device: VirtualFarmduino) -> dict[int, float]:
    """The board's current parameter values."""
    return {pid: device.parameter(pid) for pid in DEFAULT_PARAMETERS}
