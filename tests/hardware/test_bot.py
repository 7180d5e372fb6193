"""The bot's typed errors and the in-memory KinematicBot behind the Bot interface."""

from __future__ import annotations

import dataclasses
import functools
import math
import threading
import time

import numpy as np
import pytest

from flowerpose.errors import InputError
from flowerpose.hardware.bot import Bot, KinematicBot, SolidCamera
from flowerpose.hardware.bot_errors import (
    AbortedError,
    BotError,
    CalibrationError,
    CommandTimeoutError,
    ConnectionLostError,
    EmergencyStopError,
    FirmwareError,
    InvalidCommandError,
    LockedError,
    MoveTimeoutError,
    NoConfigError,
    NotConfiguredError,
    OutOfRangeError,
    StallError,
    UnknownCommandError,
    error_for_code,
)
from flowerpose.hardware.geometry import PAPER_BOT
from flowerpose.hardware.motion import (
    END_OF_MOVE_S,
    AxisMotion,
    MotionProfile,
    move_duration,
    move_trajectory,
)

COMMAND = "G00 X100.00 Y200.00 Z-50.00 Q7"
HOME = PAPER_BOT.home  # the KinematicBot's default: the paper's bot, starting at home


@pytest.mark.parametrize("code, cls, axis", [
    (1, EmergencyStopError, None), (2, MoveTimeoutError, None), (3, StallError, None),
    (4, CalibrationError, None), (5, AbortedError, None), (14, InvalidCommandError, None),
    (15, NoConfigError, None), (31, StallError, "x"), (32, StallError, "y"),
    (33, StallError, "z"),
])
def test_every_r03_code_maps_to_its_error(code, cls, axis):
    error = error_for_code(code, COMMAND)
    assert type(error) is cls
    assert isinstance(error, FirmwareError) and isinstance(error, BotError)
    assert (error.code, error.command) == (code, COMMAND)
    assert getattr(error, "axis", None) == axis
    message = str(error)
    assert message.startswith(COMMAND) and f"R03 V{code}" in message and "; " in message
    if axis:
        assert f"the {axis.upper()} axis" in message


def test_unknown_code_and_the_replies_without_one():
    error = error_for_code(99, COMMAND)
    assert type(error) is FirmwareError and error.code == 99
    assert "unknown firmware error (R03 V99)" in str(error)
    for cls, reply in ((UnknownCommandError, "R09"), (LockedError, "R87"),
                       (NotConfiguredError, "R88")):
        error = cls("F61 P6 V90")
        assert isinstance(error, FirmwareError) and error.code is None
        assert f"({reply})" in str(error)
    assert "unlock (F09) after checking the bot" in str(LockedError("G00"))
    assert "11-13" in str(MoveTimeoutError("G00", 2, axis="z"))
    assert "12.0 s" in str(CommandTimeoutError("F82", 12.0))
    assert "/dev/ttyACM0: connection lost" in str(ConnectionLostError("/dev/ttyACM0"))
    assert issubclass(OutOfRangeError, InputError)


def test_move_blocks_until_arrival_and_the_clock_advances_by_the_move_and_its_end():
    bot = KinematicBot()
    assert isinstance(bot, Bot)
    start, t0 = bot.position(), bot.now()
    np.testing.assert_array_equal(start, HOME)  # min X, min Y, top of Z
    assert tuple(bot.info.travel_max) == pytest.approx((2.8611, 1.365, 0.65))
    target = HOME + [1.0, 0.4, -0.2]
    bot.move_to(target)
    np.testing.assert_array_equal(bot.position(), target)
    expected = move_duration(start, target, MotionProfile())
    # The motion, then the firmware's end-of-move reports with the gantry at the target.
    assert bot.now() - t0 == pytest.approx(expected + END_OF_MOVE_S, rel=1e-12)
    assert expected == pytest.approx(14.56476, abs=1e-5)  # X's 1 m is the slowest axis here
    t1, further = bot.now(), target + [1.0, 0.0, 0.0]
    bot.move_to(further, speed_fraction=0.5)
    slow = move_duration(target, further, MotionProfile().at_speed(0.5))
    assert bot.now() - t1 == pytest.approx(slow + END_OF_MOVE_S) and slow > expected
    with pytest.raises(OutOfRangeError, match="x = 3.0000 m is outside"):
        bot.move_to([3.0, 0.4, 0.3])
    with pytest.raises(OutOfRangeError, match="speed_fraction"):
        bot.move_to(target, speed_fraction=0.0)
    np.testing.assert_array_equal(bot.position(), further)


def test_injected_stall_names_the_axis_and_leaves_the_gantry_where_it_stopped():
    bot = KinematicBot()
    start, target = bot.position(), HOME + [0.5, 1.0, 0.0]
    total = move_duration(start, target, MotionProfile())
    bot.fail_next_move(32, at_fraction=0.5)
    with pytest.raises(StallError) as caught:
        bot.move_to(target)
    assert caught.value.axis == "y" and caught.value.code == 32
    assert "the Y axis" in str(caught.value) and "move_to(0.6389" in str(caught.value)
    stopped = move_trajectory([0.5 * total], start, target, MotionProfile())[0]
    np.testing.assert_array_equal(bot.position(), stopped)
    assert start[1] < stopped[1] < target[1] and bot.now() == pytest.approx(0.5 * total)
    bot.move_to(target)  # a stall does not lock the bot
    np.testing.assert_array_equal(bot.position(), target)
    bot.fail_next_move(ConnectionLostError("/dev/ttyACM0"), at_fraction=0.0)
    with pytest.raises(ConnectionLostError):
        bot.home("x")
    np.testing.assert_array_equal(bot.position(), target)


def test_moves_longer_than_the_firmware_timeout_stop_at_it():
    profile = MotionProfile(x=AxisMotion(5.0, timeout_s=5.0))
    bot = KinematicBot(dataclasses.replace(KinematicBot().info, motion=profile))
    start, target = bot.position(), HOME + [1.0, 0.0, 0.0]
    with pytest.raises(MoveTimeoutError) as caught:
        bot.move_to(target)
    assert caught.value.axis == "x" and bot.now() == pytest.approx(5.0)
    np.testing.assert_allclose(bot.position(), move_trajectory([5.0], start, target, profile)[0])


def _move_under_way(bot: KinematicBot, target) -> tuple[threading.Thread, list]:
    """`bot.move_to(target)` in a thread of its own, returned once the gantry has left its
    start (so a stop lands mid-move however late this machine runs either thread), with
    the list that gets what the move raised."""
    raised, start = [], bot.position()

    def move():
        try:
            bot.move_to(target)
        except BotError as error:
            raised.append(error)

    mover = threading.Thread(target=move, daemon=True)
    mover.start()
    deadline = time.monotonic() + 30.0
    while np.array_equal(bot.position(), start):
        assert time.monotonic() < deadline, "hung: the move never started"
        time.sleep(0.005)
    return mover, raised


def _ended(mover: threading.Thread, raised: list, how: str) -> BotError:
    """What the move raised, once its thread has ended (30 s at most: a hang guard)."""
    mover.join(30.0)
    assert not mover.is_alive(), f"hung: move_to did not return after {how}"
    assert len(raised) == 1, f"move_to raised nothing after {how}"
    return raised[0]


def test_emergency_stop_from_another_thread_ends_the_move_and_locks():
    # Real time: the 14.6 s move blocks for 14.6 s. Only the stop can end it short of the
    # target with EmergencyStopError (checked below); an ignored one fails on arrival.
    bot = KinematicBot(time_scale=1.0)
    start, target = bot.position(), HOME + [1.0, 0.0, 0.0]
    mover, raised = _move_under_way(bot, target)
    seen = bot.position()
    bot.emergency_stop()
    assert isinstance(_ended(mover, raised, "the emergency stop"), EmergencyStopError)
    stopped = bot.position()
    assert start[0] < seen[0] <= stopped[0] < target[0]
    assert 0 < bot.now() < move_duration(start, target, MotionProfile())
    for command in (lambda: bot.move_to(start), lambda: bot.home(),
                    lambda: bot.set_head(0.1, 0.0)):
        with pytest.raises(LockedError):
            command()
    np.testing.assert_array_equal(bot.position(), stopped)
    bot.unlock()
    bot.move_to(stopped + [0.002, 0.0, 0.0])
    np.testing.assert_allclose(bot.position(), stopped + [0.002, 0.0, 0.0])


def test_one_command_at_a_time():
    bot = KinematicBot(time_scale=0.05)  # the move blocks for 0.73 s
    target = HOME + [1.0, 0.0, 0.0]
    mover, raised = _move_under_way(bot, target)
    with pytest.raises(BotError, match="busy"):
        bot.set_head(0.2, 0.1)
    mover.join(30.0)
    assert not mover.is_alive() and raised == []
    np.testing.assert_array_equal(bot.position(), target)


def test_head_home_and_close():
    with KinematicBot(head_settle_s=0.8) as bot:
        bot.set_head(0.3, -0.2)
        assert bot.head() == (0.3, -0.2) and bot.now() == pytest.approx(0.8)
        with pytest.raises(OutOfRangeError, match="pitch"):
            bot.set_head(0.0, 4.0)  # the pitch servo reaches -45..225 degrees
        bot.move_to([1.0, 0.5, 0.3])
        bot.home("z")
        np.testing.assert_array_equal(bot.position(), [1.0, 0.5, HOME[2]])
        bot.home()
        np.testing.assert_array_equal(bot.position(), bot.info.home)
        with pytest.raises(OutOfRangeError, match="home axes"):
            bot.home("xw")
    bot.emergency_stop()  # does nothing once closed
    with pytest.raises(BotError, match="closed"):
        bot.move_to(HOME)


def test_camera_frames_and_recording(tmp_path):
    import cv2

    bot = KinematicBot(camera=functools.partial(SolidCamera, width=64, height=48, fps=10.0))
    intrinsics = bot.camera.intrinsics()
    # COLMAP's pixel convention, as camera.json everywhere: pixel centres at +0.5.
    assert (intrinsics["width"], intrinsics["height"], intrinsics["cx"]) == (64, 48, 32.0)
    assert intrinsics["fx"] == pytest.approx(32 / math.tan(math.radians(31.1)))
    bot.camera.start_recording(tmp_path / "scan" / "video.mp4")
    bot.move_to(HOME + [0.1, 0.0, 0.0])
    frame = bot.camera.frame()
    assert frame.image.shape == (48, 64, 3) and frame.image.dtype == np.uint8
    assert frame.t_s == bot.now()
    recording = bot.camera.stop_recording()
    assert recording.frames == math.floor(recording.stop_s * 10.0) + 1
    video = cv2.VideoCapture(str(recording.path))
    assert int(video.get(cv2.CAP_PROP_FRAME_COUNT)) == recording.frames
    with pytest.raises(InputError, match="suffix"):
        bot.camera.start_recording(tmp_path / "video.mkv")


def test_close_from_another_thread_ends_a_running_move():
    bot = KinematicBot(time_scale=1.0)  # the 14.6 s move blocks for 14.6 s: see above
    target = HOME + [1.0, 0.0, 0.0]
    mover, raised = _move_under_way(bot, target)
    bot.close()
    assert isinstance(_ended(mover, raised, "close()"), EmergencyStopError)
    assert bot.position()[0] < target[0]  # ended by the close, not by arriving
    with pytest.raises(BotError, match="closed"):
        bot.move_to(HOME)
