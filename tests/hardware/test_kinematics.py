"""Kinematics of the gantry and camera head: round trips, servo mapping, reachability."""

from __future__ import annotations

import numpy as np
import pytest

from flowerpose.errors import InputError
from flowerpose.hardware.geometry import (
    PAPER_BOT,
    BotGeometry,
    bed_to_farmbot_mm,
    farmbot_mm_to_bed,
)
from flowerpose.hardware.kinematics import (
    HeadPose,
    UnreachableError,
    check_reachable,
    forward,
    from_servo_commands,
    joint_positions,
    look_at,
    servo_commands,
)

PLANT = np.array([1.5, 0.75, 0.0])
"""A plant's crown in the middle of the bed, metres, bed frame."""


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between vectors along the last axis, degrees (atan2: exact near 0)."""
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, -1)))


def _scan_cameras(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """n random cameras on the paper's cylinder (r 0.5 m, aimed at the plant axis) and
    n on its dome (r 0.3 m over a 0.25 m plant, aimed at the dome centre), with targets."""
    azimuth = rng.uniform(0.0, 2.0 * np.pi, n)
    height = rng.uniform(0.16, 0.55, n)
    cylinder = PLANT + np.stack([0.5 * np.cos(azimuth), 0.5 * np.sin(azimuth), height], 1)
    cylinder_target = np.column_stack([np.tile(PLANT[:2], (n, 1)), height])
    polar = np.radians(rng.uniform(5.0, 75.0, n))
    azimuth = rng.uniform(0.0, 2.0 * np.pi, n)
    top = PLANT + [0.0, 0.0, 0.25]
    dome = top + 0.3 * np.stack([np.sin(polar) * np.cos(azimuth),
                                 np.sin(polar) * np.sin(azimuth), np.cos(polar)], 1)
    return (np.concatenate([cylinder, dome]),
            np.concatenate([cylinder_target, np.tile(top, (n, 1))]))


def test_look_at_then_forward_reproduces_camera_and_aim():
    cameras, targets = _scan_cameras(np.random.default_rng(0), 500)
    pose = look_at(cameras, targets)
    position, rotation = forward(pose)
    assert np.abs(position - cameras).max() < 1e-6
    assert _angle_deg(rotation[..., 2], targets - cameras).max() < 0.01
    assert np.abs(rotation @ rotation.transpose(0, 2, 1) - np.eye(3)).max() < 1e-12
    assert np.allclose(np.linalg.det(rotation), 1.0)
    assert np.all((pose.yaw >= 0.0) & (pose.yaw <= np.pi)), "look_at keeps upstream's yaw"
    check_reachable(pose)


def test_single_pose_round_trip_and_known_pose():
    pose = look_at([1.0, 0.5, 0.3], [1.2, 0.5, 0.3])
    assert pose.gantry.shape == (3,) and pose.yaw.shape == ()
    assert pose.yaw == pytest.approx(0.0) and pose.pitch == pytest.approx(0.0)
    position, rotation = forward(pose)
    assert np.allclose(position, [1.0, 0.5, 0.3])
    # Level along +x: image right is -y, image down is -z.
    assert np.allclose(rotation, [[0, 0, 1], [-1, 0, 0], [0, -1, 0]])
    assert np.allclose(pose.gantry, [1.0 - 0.04, 0.5, 0.3 + 0.06])


def test_looking_straight_down():
    pose = look_at([1.0, 0.5, 0.4], [1.0, 0.5, 0.0])
    assert pose.pitch == pytest.approx(np.pi / 2)
    position, rotation = forward(pose)
    assert np.allclose(position, [1.0, 0.5, 0.4])
    assert np.allclose(rotation[:, 2], [0, 0, -1])
    assert np.allclose(pose.gantry, [1.0, 0.5, 0.4 + 0.04 + 0.06])


def test_look_at_flips_yaw_beyond_pi_like_upstream():
    # Looking along -y is yaw 270 degrees: upstream reaches it as yaw 90, pitch 180 - pitch.
    camera = np.array([1.0, 1.0, 0.3])
    pose = look_at(camera, camera + [0.0, -0.2, -0.1])
    down = np.arctan2(0.1, 0.2)
    assert pose.yaw == pytest.approx(np.pi / 2)
    assert pose.pitch == pytest.approx(np.pi - down)
    position, rotation = forward(pose)
    assert np.allclose(position, camera)
    # Upright, image right would be -x and image down would point below the horizon.
    assert np.allclose(rotation[:, 0], [1, 0, 0]) and rotation[2, 1] > 0, "upside down"


def test_look_at_refuses_camera_on_target():
    with pytest.raises(InputError, match="equals"):
        look_at([1.0, 0.5, 0.3], [1.0, 0.5, 0.3])


def test_servo_mapping_matches_upstream():
    gantry = PAPER_BOT.home
    pose = HeadPose(np.tile(gantry, (3, 1)), np.radians([0.0, 90.0, 180.0]),
                    np.radians([0.0, 90.0, 180.0]))
    yaw_cmd, pitch_cmd = servo_commands(pose)
    assert np.allclose(yaw_cmd, [160.0, 100.0, 40.0])
    assert np.allclose(pitch_cmd, [150.0, 90.0, 30.0])
    assert np.allclose(np.degrees(PAPER_BOT.yaw_range_rad), [-30.0, 240.0])
    assert np.allclose(np.degrees(PAPER_BOT.pitch_range_rad), [-45.0, 225.0])


def test_servo_commands_round_trip():
    rng = np.random.default_rng(1)
    yaw_cmd, pitch_cmd = rng.uniform(0.0, 180.0, (2, 200))
    gantry = PAPER_BOT.home + rng.uniform(0.0, 0.3, (200, 3)) * [1, 1, -1]
    pose = from_servo_commands(yaw_cmd, pitch_cmd, gantry)
    back = servo_commands(pose)
    assert np.allclose(back[0], yaw_cmd) and np.allclose(back[1], pitch_cmd)
    again = from_servo_commands(*back, gantry)
    assert np.allclose(again.yaw, pose.yaw) and np.allclose(again.pitch, pose.pitch)
    with pytest.raises(InputError, match="yaw servo command"):
        from_servo_commands(181.0, 90.0, gantry[0])


def test_yaw_out_of_reach_flips_to_same_optical_axis():
    rng = np.random.default_rng(2)
    n = 100
    yaw = rng.uniform(np.radians(241.0), np.radians(329.0), n)
    pitch = rng.uniform(np.radians(-40.0), np.radians(90.0), n)
    pose = HeadPose(np.tile(PAPER_BOT.home - [0, 0, 0.2], (n, 1)), yaw, pitch)
    taken = from_servo_commands(*servo_commands(pose), pose.gantry)
    assert np.allclose(taken.yaw, yaw - np.pi)
    assert np.allclose(taken.pitch, np.pi - pitch)
    (p0, r0), (p1, r1) = forward(pose), forward(taken)
    assert np.abs(p1 - p0).max() < 1e-12
    assert np.allclose(r1[..., 2], r0[..., 2]) and np.allclose(r1[..., :2], -r0[..., :2])
    assert np.allclose(joint_positions(pose)[:, 3:], np.column_stack([taken.yaw, taken.pitch]))
    # A yaw a full turn away is wrapped, not flipped.
    turned = HeadPose(pose.gantry[0], np.radians(370.0), 0.3)
    assert np.allclose(servo_commands(turned), servo_commands(HeadPose(pose.gantry[0],
                                                                       np.radians(10.0), 0.3)))


@pytest.mark.parametrize(("gantry_mm", "limits"), [
    ([-5.0, 100.0, -100.0], ("gantry X",)),
    ([2730.0, 100.0, -100.0], ("gantry X",)),
    ([100.0, 1240.0, -100.0], ("gantry Y",)),
    ([100.0, 100.0, 10.0], ("gantry Z",)),
    ([100.0, -1.0, -440.0], ("gantry Y", "gantry Z")),
])
def test_outside_travel_refused(gantry_mm, limits):
    pose = HeadPose(farmbot_mm_to_bed(gantry_mm), 0.5, 0.3)
    with pytest.raises(UnreachableError) as info:
        check_reachable(pose)
    assert info.value.limits == limits and info.value.waypoint is None
    assert all(f"{limit} travel" in str(info.value) for limit in limits)


def test_soil_clearance_refused():
    low = BotGeometry(home_utm_m=(0.1389, 0.135, 0.45))
    pose = HeadPose(farmbot_mm_to_bed([500.0, 500.0, -400.0], low), 0.0, np.pi / 2)
    with pytest.raises(UnreachableError, match="above the soil") as info:
        check_reachable(pose, low)
    assert info.value.limits == ("soil clearance",)
    below = look_at([1.0, 0.5, -0.05], [1.5, 0.5, 0.0])
    with pytest.raises(UnreachableError, match="camera -0.050 m") as info:
        check_reachable(below)
    assert info.value.limits == ("gantry Z", "soil clearance")


def test_servo_range_refused_and_waypoint_named():
    cameras, targets = _scan_cameras(np.random.default_rng(3), 5)
    pose = look_at(cameras, targets)
    up = HeadPose(pose.gantry, pose.yaw, np.where(np.arange(10) == 7, np.radians(-60.0),
                                                  pose.pitch))
    with pytest.raises(UnreachableError, match="pitch servo command") as info:
        check_reachable(up, name="scan waypoint")
    assert info.value.waypoint == 7 and info.value.limits == ("pitch servo",)
    assert info.value.source == "scan waypoint 7"
    with pytest.raises(UnreachableError, match="pitch servo"):
        servo_commands(up)


def test_whole_batch_checked_and_counted():
    cameras, targets = _scan_cameras(np.random.default_rng(4), 5)
    cameras[[2, 6], 2] = 0.8
    with pytest.raises(UnreachableError, match=r"2 of 10 poses") as info:
        check_reachable(look_at(cameras, targets))
    assert info.value.waypoint == 2 and info.value.limits == ("gantry Z",)


def test_not_finite_refused():
    with pytest.raises(UnreachableError) as info:
        check_reachable(HeadPose(PAPER_BOT.home, np.nan, 0.0))
    assert "finite" in info.value.limits


def test_farmbot_mm_round_trip_and_z_sign():
    home = farmbot_mm_to_bed([0.0, 0.0, 0.0])
    assert np.allclose(home, PAPER_BOT.home)
    lowered = farmbot_mm_to_bed([2722.2, 1230.0, -431.64])
    assert np.allclose(lowered, [0.1389 + 2.7222, 0.135 + 1.23, 0.65 - 0.43164])
    rng = np.random.default_rng(5)
    mm = rng.uniform([0, 0, -431.64], [2722.2, 1230.0, 0.0], (50, 3))
    assert np.allclose(bed_to_farmbot_mm(farmbot_mm_to_bed(mm)), mm, atol=1e-9)
    assert np.all(bed_to_farmbot_mm(PAPER_BOT.home - [0, 0, 0.1])[2] == pytest.approx(-100.0))
