"""The MuJoCo FarmBot model: every scene steps cleanly and agrees with geometry.py."""

from __future__ import annotations

import os

import mujoco
import numpy as np
import pytest

from flowerpose.hardware.geometry import FARMBOT_ASSETS, PAPER_BOT, PAPER_TOOL
from flowerpose.hardware.kinematics import JOINT_NAMES, HeadPose, forward, joint_positions

MODELS = sorted(FARMBOT_ASSETS.glob("*.xml"))
OPENCV_FROM_MUJOCO = np.diag([1.0, -1.0, -1.0])
"""MuJoCo cameras look along -z with +y up; OpenCV along +z with +y down."""


@pytest.fixture(scope="module")
def scene() -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(FARMBOT_ASSETS / "scene.xml"))


@pytest.mark.parametrize("path", MODELS, ids=[p.name for p in MODELS])
def test_steps_under_control_noise_without_warnings(path):
    model = mujoco.MjModel.from_xml_path(str(path))
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, model.key("home").id)
    rng = np.random.default_rng(0)
    low, high = model.actuator_ctrlrange.T
    for _ in range(int(2.0 / model.opt.timestep)):
        step = rng.normal(0.0, 0.02, model.nu) * (high - low)
        data.ctrl[:] = np.clip(data.ctrl + step, low, high)
        mujoco.mj_step(model, data)
    warnings = {mujoco.mjtWarning(i).name: w.number for i, w in enumerate(data.warning)
                if w.number > 0}
    assert not warnings, f"{path.name}: MuJoCo warnings {warnings}"
    assert np.isfinite(data.qpos).all() and np.isfinite(data.qvel).all()
    assert data.time == pytest.approx(2.0)


def test_joint_and_control_ranges_match_geometry(scene):
    travel = PAPER_BOT.travel_m
    expected = {"x": (0.0, travel[0]), "y": (0.0, travel[1]), "z": (-travel[2], 0.0),
                "yaw": PAPER_BOT.yaw_range_rad, "pitch": PAPER_BOT.pitch_range_rad}
    assert tuple(scene.joint(i).name for i in range(scene.njnt)) == JOINT_NAMES
    for name in JOINT_NAMES:
        assert np.allclose(scene.joint(name).range, expected[name], atol=1e-9), name
        assert np.allclose(scene.actuator(name).ctrlrange, expected[name], atol=1e-9), name
    soil = scene.geom("soil")
    assert np.allclose(2.0 * soil.size[:2], PAPER_BOT.bed_size_m)
    assert np.allclose(soil.pos + [0, 0, soil.size[2]], [*np.multiply(PAPER_BOT.bed_size_m,
                                                                       0.5), 0.0])
    assert np.allclose(2.0 * soil.size[2], PAPER_BOT.bed_depth_m)
    assert scene.geom("floor").pos[2] == pytest.approx(-PAPER_BOT.bed_depth_m)
    assert scene.vis.global_.offwidth >= 1280 and scene.vis.global_.offheight >= 720


def test_camera_pose_matches_forward(scene):
    data = mujoco.MjData(scene)
    rng = np.random.default_rng(1)
    n = 200
    gantry = rng.uniform(PAPER_BOT.gantry_min, PAPER_BOT.gantry_max, (n, 3))
    yaw = rng.uniform(*PAPER_BOT.yaw_range_rad, n)
    pitch = rng.uniform(*PAPER_BOT.pitch_range_rad, n)
    poses = HeadPose(gantry, yaw, pitch)
    positions, rotations = forward(poses)
    camera = scene.camera("camera").id
    for qpos, position, rotation in zip(joint_positions(poses), positions, rotations,
                                        strict=True):
        data.qpos[:] = qpos
        mujoco.mj_kinematics(scene, data)
        mujoco.mj_camlight(scene, data)
        assert np.abs(data.cam_xpos[camera] - position).max() < 1e-6
        mujoco_rotation = data.cam_xmat[camera].reshape(3, 3) @ OPENCV_FROM_MUJOCO
        assert np.abs(mujoco_rotation - rotation).max() < 1e-6


def test_the_drawn_pollinator_is_the_one_planned_for(scene):
    # In the pitch bracket's frame: x along the optical axis, z up (the image's top).
    body = scene.body("pollinator")
    assert np.allclose(body.pos, [0.0, 0.0, -PAPER_TOOL.offset_down_m])
    assert np.allclose(scene.site("pollinator_tip").pos, [PAPER_TOOL.reach_m, 0.0, 0.0])
    swab, shaft = scene.geom("pollinator_swab"), scene.geom("pollinator_shaft")
    assert np.allclose(swab.pos, [PAPER_TOOL.reach_m, 0.0, 0.0])
    assert swab.size[0] == pytest.approx(PAPER_TOOL.tip_radius_m)
    assert shaft.size[0] == pytest.approx(PAPER_TOOL.shaft_radius_m)
    # A capsule's half length, from the shaft's start to the swab's back.
    assert shaft.size[1] == pytest.approx(
        (PAPER_TOOL.reach_m - PAPER_TOOL.tip_radius_m - PAPER_TOOL.shaft_start_m) / 2)


def test_home_keyframe_is_farmbot_home(scene):
    data = mujoco.MjData(scene)
    mujoco.mj_resetDataKeyframe(scene, data, scene.key("home").id)
    mujoco.mj_kinematics(scene, data)
    mujoco.mj_camlight(scene, data)
    position, _ = forward(HeadPose(PAPER_BOT.home, 0.0, 0.0))
    assert np.allclose(data.cam_xpos[scene.camera("camera").id], position)
    assert np.allclose(data.ctrl, data.qpos)
    beam, utm = scene.geom("beam"), scene.geom("utm")
    assert data.geom_xpos[beam.id][2] - beam.size[2] == pytest.approx(PAPER_BOT.beam_bottom_m)
    assert data.geom_xpos[utm.id][2] - utm.size[1] == pytest.approx(PAPER_BOT.home[2])
    assert utm.size[0] == pytest.approx(PAPER_BOT.utm_radius_m)


def test_renders_camera_at_1280x720(scene):
    if not os.environ.get("MUJOCO_GL") and not os.environ.get("DISPLAY"):
        pytest.skip("headless: set MUJOCO_GL=egl (make test does)")
    try:
        renderer = mujoco.Renderer(scene, 720, 1280)
    except Exception as error:  # no OpenGL context on this machine (set MUJOCO_GL=egl)
        pytest.skip(f"no MuJoCo rendering here: {error}")
    data = mujoco.MjData(scene)
    data.qpos[:] = joint_positions(HeadPose(PAPER_BOT.home + [1.0, 0.6, 0.0], 0.0, np.pi / 2))
    mujoco.mj_forward(scene, data)
    with renderer:
        renderer.update_scene(data, camera="camera")
        image = renderer.render()
    assert image.shape == (720, 1280, 3)
    red, green, blue = np.median(image.reshape(-1, 3), axis=0)
    assert red > green > blue, "looking down, the camera sees brown soil (and shadows)"
