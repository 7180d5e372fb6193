"""FarmBot's motion profile against the firmware's rule (MovementAxis::calculateSpeed)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import quad

from flowerpose.errors import InputError
from flowerpose.hardware.bot_errors import OutOfRangeError
from flowerpose.hardware.motion import (
    AxisMotion,
    MotionProfile,
    axis_duration,
    axis_durations,
    axis_position,
    move_duration,
    move_trajectory,
)

X = MotionProfile().x  # 5 steps/mm, 400 / 50 steps/s, 300-step ramps


def firmware_speed(cur: int, end: int, vmin: int, vmax: int, ramp: int) -> int:
    """Firmware 6.6's calculateSpeed for a move from 0 to `end` steps at step `cur`."""
    halfway = end // 2
    if cur <= halfway:
        if cur > ramp:
            return vmax + 1
        return int(1.0 * cur / ramp * (vmax - vmin)) + vmin
    if cur < end - ramp:
        return vmax + 2
    return int(1.0 * (end - cur) / ramp * (vmax - vmin)) + vmin


def test_long_move_is_ramp_up_cruise_ramp_down_by_hand():
    # 1 m on X = 5000 steps. Each ramp: integral of ds / (50 + 350 s / 300) over 300 steps
    # = 300 / 350 * ln(400 / 50) = 1.78240 s; cruise (5000 - 600) / 400 = 11 s.
    ramp_s = 300 / 350 * math.log(8)
    by_hand = 2 * ramp_s + 11.0
    assert by_hand == pytest.approx(14.56476, abs=1e-5)
    assert axis_duration(1.0, X) == pytest.approx(by_hand, rel=1e-12)
    assert axis_duration(-1.0, X) == pytest.approx(by_hand, rel=1e-12)


@pytest.mark.parametrize("steps", [200, 1000, 5000, 25000])
def test_firmware_stepping_stays_within_half_a_percent(steps):
    # The firmware takes one whole step at a time at the speed of the step's start.
    stepped = sum(1.0 / firmware_speed(k, steps, 50, 400, 300) for k in range(steps))
    assert stepped == pytest.approx(axis_duration(steps / X.steps_per_m, X), rel=5e-3)


#: The firmware's movement interrupt period (MOVEMENT_INTERRUPT_SPEED), microseconds.
TICK_US = 64


@pytest.mark.parametrize("steps", [200, 1000, 2500, 5000, 25000])
def test_the_64_us_movement_interrupt_only_shortens_moves_by_under_3_percent(steps):
    # MovementAxis::setTicks: a step lasts trunc(1e6 / 64 / v) interrupt ticks, never a
    # fraction of one; the cruise speed (max + 1 or + 2 = 401 / 402 steps/s) truncates to
    # 38 ticks, 411 steps/s. So the firmware's own step timing makes a 500 mm X move 1.6 %
    # shorter than the model (8.18 s against 8.31 s), long moves up to 2.6 %: it cannot be
    # what makes the real board's moves 6-7 % longer (motion.py says what remains).
    ticked = sum(math.trunc(1e6 / TICK_US / firmware_speed(k, steps, 50, 400, 300))
                 * TICK_US * 1e-6 for k in range(steps))
    model = axis_duration(steps / X.steps_per_m, X)
    assert 0.97 * model < ticked < 1.005 * model


def test_short_move_peaks_below_max_and_is_symmetric():
    # 40 mm = 200 steps < two ramps: the speed peaks at 100 steps, 50 + 350 / 3 steps/s.
    distance = 0.04
    total = axis_duration(distance, X)
    by_hand = 2 * 300 / 350 * math.log1p(350 / 300 * 100 / 50)
    assert total == pytest.approx(by_hand, rel=1e-12)
    assert total == pytest.approx(2.06395, abs=1e-5)
    tau = np.linspace(0.0, total / 2, 50)
    up = axis_position(tau, 0.0, distance, X)
    down = axis_position(total - tau, 0.0, distance, X)
    np.testing.assert_allclose(up + down, distance, atol=1e-12)
    dt = 1e-6
    mid = axis_position(np.array([total / 2 - dt, total / 2 + dt]), 0.0, distance, X)
    peak = (mid[1] - mid[0]) / (2 * dt) * X.steps_per_m
    assert peak == pytest.approx(50 + 350 / 3, rel=1e-6)
    assert peak < X.max_speed


def test_speed_follows_the_firmware_rule_along_the_whole_move():
    distance, steps = 1.0, 5000.0
    total = axis_duration(distance, X)
    t = np.linspace(0.01, total - 0.01, 2001)
    dt = 1e-6
    s = axis_position(t, 0.0, distance, X) * X.steps_per_m
    speed = (axis_position(t + dt, 0.0, distance, X)
             - axis_position(t - dt, 0.0, distance, X)) / (2 * dt) * X.steps_per_m
    rule = 50 + 350 * np.minimum(np.minimum(s, steps - s), 300) / 300
    np.testing.assert_allclose(speed, rule, rtol=1e-5)
    assert (np.abs(speed - 400) < 1e-3).sum() > 1000  # most of the move cruises


@pytest.mark.parametrize("vmin, vmax, ramp, steps", [
    (50, 400, 300, 5000), (50, 400, 300, 450), (120, 120, 300, 1000),  # k = 0
    (50, 30, 300, 2000),  # an override below the minimum: the speed ramps down to 30
    (10, 2000, 1000, 1500),
])
def test_duration_is_the_integral_of_one_over_speed(vmin, vmax, ramp, steps):
    axis = AxisMotion(steps_per_mm=10.0, max_speed=vmax, min_speed=vmin, ramp_steps=ramp)

    def speed(s):
        return vmin + (vmax - vmin) * min(s, steps - s, ramp) / ramp

    integral, _ = quad(lambda s: 1.0 / speed(s), 0, steps, points=[ramp, steps - ramp],
                       limit=200)
    assert axis_duration(steps / axis.steps_per_m, axis) == pytest.approx(integral, rel=1e-9)


def test_diagonal_move_axes_finish_apart_and_z_is_slow():
    profile = MotionProfile()
    start, end = np.array([0.5, 0.5, 0.5]), np.array([0.7, 0.3, 0.3])  # 0.2 m on each axis
    durations = axis_durations(start, end, profile)
    # X, Y: 1000 steps, 2 ramps + 400 cruise steps; Z: 5000 steps, as 1 m on X.
    xy = 2 * 300 / 350 * math.log(8) + 1.0
    np.testing.assert_allclose(durations, [xy, xy, axis_duration(1.0, X)], rtol=1e-12)
    assert durations[2] == pytest.approx(3.19 * durations[0], rel=1e-2)
    assert move_duration(start, end, profile) == durations[2]
    path = move_trajectory([xy, 0.5 * xy], start, end, profile)
    np.testing.assert_array_equal(path[0, :2], end[:2])  # X, Y done, Z still on its way
    assert 0.3 < path[0, 2] < 0.5
    # Not a straight line: halfway through X's move Z has covered far less of its share.
    assert (0.5 - path[1, 2]) / 0.2 < 0.5 * (path[1, 0] - 0.5) / 0.2


def test_positions_are_monotonic_and_end_exactly_on_target():
    profile = MotionProfile()
    start, end = [2.0, 0.1, 0.2], [0.3337, 1.2001, 0.45]
    total = move_duration(start, end, profile)
    t = np.linspace(-1.0, total + 1.0, 5000)
    path = move_trajectory(t, start, end, profile)
    steps = np.diff(path, axis=0)
    assert np.all(steps[:, 0] <= 0) and np.all(steps[:, 1] >= 0) and np.all(steps[:, 2] >= 0)
    np.testing.assert_array_equal(path[0], start)
    np.testing.assert_array_equal(path[-1], end)
    np.testing.assert_array_equal(move_trajectory([total], start, end, profile)[0], end)
    np.testing.assert_array_equal(move_trajectory([0.0, 5.0], start, start, profile),
                                  [start, start])


def test_profile_from_firmware_parameters():
    params = {55: 10, 71: 800, 61: 100, 41: 500, 11: 60,
              57: 50, 73: 1000, 63: 80, 43: 400, 74: 600, 64: 70, 44: 200, 13: 90}
    profile = MotionProfile.from_firmware(params)
    assert profile.x == AxisMotion(10, 800, 100, 500, 60)
    assert profile.y == AxisMotion(5, 400, 50, 300, 120)  # nothing given: firmware defaults
    assert profile.z == AxisMotion(50, 1000, 80, 400, 90)
    assert profile.z_home == AxisMotion(50, 600, 70, 200, 90)
    # Z going up (toward home) moves with 74, 64, 44; going down with 73, 63, 43.
    assert profile.axis(2, toward_home=True) is profile.z_home
    up = move_duration([0, 0, 0.1], [0, 0, 0.3], profile)
    down = move_duration([0, 0, 0.3], [0, 0, 0.1], profile)
    assert up == pytest.approx(axis_duration(0.2, profile.z_home))
    assert down == pytest.approx(axis_duration(0.2, profile.z))
    assert MotionProfile.from_firmware({}) == MotionProfile(z_home=AxisMotion(25))
    with pytest.raises(InputError, match="firmware parameter 56"):
        MotionProfile.from_firmware({56: 0})


def test_speed_override_only_lowers_and_only_away_from_home():
    profile = MotionProfile()
    over = profile.with_override(200, 800, 0)
    assert over.axis(0, toward_home=False).max_speed == 200
    assert over.axis(1, toward_home=False).max_speed == 400  # 800 > max: ignored
    assert over.axis(2, toward_home=False).max_speed == 400  # 0: none
    assert over.axis(0, toward_home=True).max_speed == 400  # firmware 6.6: not toward home
    away = move_duration([0.1, 0, 0.5], [1.1, 0, 0.5], over)
    assert away == pytest.approx(2 * 300 / 150 * math.log(4) + 4400 / 200)
    assert away > move_duration([0.1, 0, 0.5], [1.1, 0, 0.5], profile)
    assert move_duration([1.1, 0, 0.5], [0.1, 0, 0.5], over) == pytest.approx(
        axis_duration(1.0, X))
    assert profile.override_for(0.5) == (200, 200, 200)
    assert profile.override_for(1.0) == (0, 0, 0)
    assert profile.at_speed(1.0) == profile
    for bad in (0.0, -0.5, 1.5, math.nan):
        with pytest.raises(OutOfRangeError, match="speed_fraction"):
            profile.at_speed(bad)
