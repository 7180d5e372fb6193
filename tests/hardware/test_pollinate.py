"""The pollinator on the head and the visits planned for it: its kinematics against the
MuJoCo model, reach and collisions on constructed flowers, short orders, and bad input."""

import json

import numpy as np
import pytest
from scipy.spatial import cKDTree

from flowerpose.hardware.flights.clearance import head_gap
from flowerpose.hardware.flights.pollination_plan import (
    Flower,
    PollinateConfig,
    _short_order,
    _transfer_cost,
    plan_pollination,
)
from flowerpose.hardware.geometry import PAPER_BOT, PAPER_TOOL
from flowerpose.hardware.kinematics import HeadPose, joint_positions, tool_at, tool_forward
from flowerpose.hardware.motion import MotionProfile, move_trajectory

CENTER = np.array([1.5, 0.75, 0.2])


def test_the_tools_tip_in_the_model_is_where_the_kinematics_put_it():
    mujoco = pytest.importorskip("mujoco")
    from flowerpose.hardware.geometry import FARMBOT_ASSETS

    model = mujoco.MjModel.from_xml_path(str(FARMBOT_ASSETS / "scene.xml"))
    data = mujoco.MjData(model)
    rng = np.random.default_rng(2)
    n = 200  # yaws over the whole servo reach: the flipped solutions too
    poses = HeadPose(rng.uniform(PAPER_BOT.gantry_min, PAPER_BOT.gantry_max, (n, 3)),
                     rng.uniform(0.0, 2 * np.pi, n), rng.uniform(-0.5, 2.0, n))
    tips, _ = tool_forward(poses)
    site = model.site("pollinator_tip").id
    for qpos, tip in zip(joint_positions(poses), tips, strict=True):
        data.qpos[:] = qpos
        mujoco.mj_kinematics(model, data)
        assert np.abs(data.site_xpos[site] - tip).max() < 1e-9


def test_another_tool_is_shaped_in_the_contact_model_where_its_kinematics_put_it():
    mujoco = pytest.importorskip("mujoco")
    from flowerpose.eval.pollination.contact import shape_tool
    from flowerpose.hardware.geometry import FARMBOT_ASSETS, PollinatorTool

    tool = PollinatorTool(reach_m=0.2, offset_down_m=0.045, tip_radius_m=0.005)
    spec = mujoco.MjSpec.from_file(str(FARMBOT_ASSETS / "scene.xml"))
    shape_tool(spec, tool)
    model = spec.compile()
    data = mujoco.MjData(model)
    rng = np.random.default_rng(4)
    poses = HeadPose(rng.uniform(PAPER_BOT.gantry_min, PAPER_BOT.gantry_max, (50, 3)),
                     rng.uniform(0.0, 2 * np.pi, 50), rng.uniform(-0.5, 2.0, 50))
    tips, _ = tool_forward(poses, tool)
    for qpos, tip in zip(joint_positions(poses), tips, strict=True):
        data.qpos[:] = qpos
        mujoco.mj_kinematics(model, data)
        assert np.abs(data.site_xpos[model.site("pollinator_tip").id] - tip).max() < 1e-9
        assert np.abs(data.geom_xpos[model.geom("pollinator_swab").id] - tip).max() < 1e-9
    assert model.geom("pollinator_swab").size[0] == pytest.approx(0.005)


def test_a_longer_shaft_reaches_a_low_flower_a_shorter_cannot():
    from flowerpose.hardware.geometry import PollinatorTool

    low = Flower(0, np.array([1.5, 0.75, 0.04]), np.array([1.0, 0.0, 0.0]))
    (short,) = _plan([low], tool=PollinatorTool(reach_m=0.12, offset_down_m=0.03)).visits
    assert short.status == "unreachable" and "Z travel" in short.reason
    (longer,) = _plan([low], tool=PollinatorTool(reach_m=0.22)).visits
    assert longer.status == "planned"
    tip, _ = tool_forward(longer.touch, PollinatorTool(reach_m=0.22))
    assert np.linalg.norm(tip - (low.center + 0.002 * longer.approach)) < 1e-9


@pytest.mark.parametrize("settings, words", [
    ({"reach_m": 0.0}, "reach_m: must be positive"),
    ({"offset_down_m": -0.01}, "offset_down_m: must be 0 or more"),
    ({"shaft_start_m": 0.2}, "the shaft must start"),
])
def test_a_bad_tool_is_refused_naming_its_setting(settings, words):
    from flowerpose.errors import InputError
    from flowerpose.hardware.geometry import PollinatorTool

    with pytest.raises(InputError, match=words):
        PollinatorTool(**settings)


def test_a_clearance_the_targets_own_sepals_would_break_is_refused_before_any_work(
        tmp_path, capsys):
    from flowerpose.cli import main
    from flowerpose.errors import InputError

    with pytest.raises(InputError, match="calyx_radius_m"):
        PollinateConfig(clearance_m=0.015)
    assert PollinateConfig(clearance_m=0.015, calyx_radius_m=0.02).clearance_m == 0.015
    assert main(["sweep", "--task", "pollinate", "--grid", "pollinate.clearance_m=0.01,0.015",
                 "--out", str(tmp_path / "never")]) == 2
    assert "own sepals would block every visit" in capsys.readouterr().err
    assert not (tmp_path / "never").exists()


def test_a_check_step_wider_than_the_clearance_is_refused():
    from flowerpose.errors import InputError

    with pytest.raises(InputError, match="check_step_m: must be at most"):
        PollinateConfig(check_step_m=0.02)


def test_no_point_of_the_head_or_shaft_moves_more_than_a_step_between_checked_poses():
    from flowerpose.hardware.flights.clearance import checked_poses, shaft_points
    from flowerpose.hardware.geometry import PollinatorTool
    from flowerpose.hardware.kinematics import head_boxes

    tool = PollinatorTool(reach_m=0.24, offset_down_m=0.07)
    a = HeadPose(np.array([0.8, 0.4, -0.02]), 0.0, 0.3)
    b = HeadPose(np.array([1.6, 0.9, -0.30]), 2.5, 1.9)  # a long move with a big turn
    poses = checked_poses(a, b, MotionProfile(), 0.005, PAPER_BOT, tool)
    shaft = shaft_points(poses, tool, PAPER_BOT, 0.005)
    corners = head_boxes(poses)[0]
    for points in (shaft, corners):
        steps = np.linalg.norm(np.diff(points, axis=0), axis=-1)
        assert steps.max() <= 0.005 + 1e-12
    assert np.linalg.norm(np.diff(shaft, axis=1), axis=-1).max() <= 0.005 + 1e-12
    assert len(poses.yaw) > PollinateConfig().samples_per_move


def test_a_petal_between_two_poses_the_old_fixed_count_checked_blocks_the_descent():
    from flowerpose.hardware.flights.clearance import checked_poses, gap
    from flowerpose.hardware.flights.pollination_plan import _top_over
    from flowerpose.hardware.flights.scan_plan import poses_along
    from flowerpose.hardware.kinematics import tool_points

    config, profile, tool = PollinateConfig(path_checks=0), MotionProfile(), PAPER_TOOL
    flower = Flower(0, CENTER, np.array([0.6, 0.0, 0.8]))  # the shaft sweeps a slanted strip
    (clear,) = _plan([flower], path_checks=0).visits
    top = _top_over(clear.pre, PAPER_BOT)
    # Of the places the shaft's outer half passes going down, the one farthest from every
    # place the old check looked at (twelve poses, six points along the shaft).
    swept = tool_points(poses_along(top, clear.pre, profile, 111), tool, PAPER_BOT, 51)
    swept = swept[:, 25:].reshape(-1, 3)
    coarse = tool_points(poses_along(top, clear.pre, profile, 12), tool, PAPER_BOT, 6)
    unseen = cKDTree(coarse.reshape(-1, 3)).query(swept)[0]
    petal = swept[np.argmax(unseen)]
    assert unseen.max() > config.clearance_m  # the old check passed it
    (visit,) = plan_pollination([flower], petal[None, :], config).visits
    assert visit.status == "unreachable" or visit.off_axis_deg > 0 or not np.allclose(
        joint_positions(visit.pre)[3:], joint_positions(clear.pre)[3:])
    if visit.status == "planned":  # the descent it takes keeps clear of the petal, finely
        fine = checked_poses(_top_over(visit.pre, PAPER_BOT), visit.pre, profile, 0.001,
                             PAPER_BOT, tool)
        petal_tree = cKDTree(petal[None, :])
        least = gap(fine, petal_tree, petal_tree, 0.05, PAPER_BOT, tool, 0.001)[0]
        assert least >= config.clearance_m - config.check_step_m


def test_tool_at_puts_the_tip_where_asked_along_the_direction_asked():
    rng = np.random.default_rng(3)
    tips = rng.uniform([0.5, 0.3, 0.05], [2.5, 1.2, 0.3], (100, 3))
    directions = rng.normal(size=(100, 3))
    reached, ahead = tool_forward(tool_at(tips, directions))
    assert np.abs(reached - tips).max() < 1e-12
    unit = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    assert np.abs(ahead - unit).max() < 1e-12


def _plan(flowers, obstacles=None, **settings):
    return plan_pollination(flowers, obstacles, PollinateConfig(**settings))


def test_an_open_flower_facing_up_is_touched_along_its_axis_on_a_straight_path():
    plan = _plan([Flower(0, CENTER, np.array([0.3, 0.0, 1.0]) / np.hypot(0.3, 1.0))])
    (visit,) = plan.visits
    assert visit.status == "planned" and visit.off_axis_deg == 0.0
    normal = np.array([0.3, 0.0, 1.0]) / np.hypot(0.3, 1.0)
    tip, ahead = tool_forward(visit.touch)
    assert np.allclose(tip, CENTER - PollinateConfig().press_m * normal)
    assert np.allclose(ahead, -normal)
    pre_tip, _ = tool_forward(visit.pre)
    assert np.allclose(pre_tip, CENTER + PollinateConfig().standoff_m * normal)
    # FarmBot runs each axis on its own profile: the approach is cut until it keeps to
    # the straight line through the centre.
    line = visit.touch.gantry - visit.pre.gantry
    unit = line / np.linalg.norm(line)
    ends = [visit.pre.gantry] + [step.gantry for step in visit.approach_moves]
    for a, b in zip(ends, ends[1:], strict=False):
        path = move_trajectory(np.linspace(0, 60, 400), a, b, MotionProfile()) - visit.pre.gantry
        bend = np.linalg.norm(path - np.outer(path @ unit, unit), axis=1).max()
        assert bend <= PollinateConfig().straight_within_m + 1e-9
    assert [m.kind for m in plan.moves][:3] == ["lift", "travel", "descend"]
    assert plan.moves[-2].kind == "retreat" and plan.duration_s > 0
    # It goes back out the same way, move for move, so it bends no more than going in.
    retreat = [m.pose.gantry for m in plan.moves if m.kind == "retreat"]
    assert len(visit.approach_moves) > 1
    assert np.allclose(retreat, ends[-2::-1])


def test_a_flower_facing_the_bed_is_unreachable_naming_the_servo():
    plan = _plan([Flower(0, CENTER, np.array([0.0, 0.0, -1.0]))])
    (visit,) = plan.visits
    assert visit.status == "unreachable" and "pitch servo" in visit.reason


def test_a_flower_outside_the_travel_is_unreachable_naming_the_axis():
    plan = _plan([Flower(0, np.array([2.99, 0.75, 0.2]), np.array([1.0, 0.0, 0.0]))])
    (visit,) = plan.visits
    assert visit.status == "unreachable" and "gantry X travel" in visit.reason


def _leaf(radius: float, height: float) -> np.ndarray:
    """A leaf: points on a level disc of `radius` over the flower's centre, `height` above it."""
    r, a = np.meshgrid(np.linspace(0, radius, 12), np.linspace(0, 2 * np.pi, 48))
    return np.stack([CENTER[0] + r.ravel() * np.cos(a.ravel()),
                     CENTER[1] + r.ravel() * np.sin(a.ravel()),
                     np.full(r.size, CENTER[2] + height)], 1)


def test_a_flower_behind_a_leaf_is_approached_round_it_or_not_at_all():
    flower = Flower(0, CENTER, np.array([0.0, 0.0, 1.0]))
    # A 1 cm leaf 4.5 cm over the centre blocks the axis; 30 degrees off it, the swab
    # comes down 2.5 cm to its side and slants in under it.
    wide = {"cone_deg": 30.0, "cone_step_deg": 10.0}
    (visit,) = _plan([flower], _leaf(0.01, 0.045), **wide).visits
    assert visit.status == "planned" and visit.off_axis_deg == pytest.approx(30.0)
    (clear,) = _plan([flower], _leaf(0.01, 0.045) + [0.1, 0.0, 0.0], **wide).visits  # aside
    assert clear.status == "planned" and clear.off_axis_deg == 0.0
    (blocked,) = _plan([flower], _leaf(0.1, 0.045), **wide).visits  # over the whole flower
    assert blocked.status == "unreachable" and "from the plant" in blocked.reason


def test_a_visit_whose_travel_at_the_top_of_z_meets_the_plant_is_left_out_with_why():
    from flowerpose.hardware.flights.scan_plan import poses_along
    from flowerpose.hardware.kinematics import tool_points

    flower = Flower(0, CENTER, np.array([0.0, 0.0, 1.0]))
    clear = _plan([flower])
    lift, travel = clear.moves[:2]
    assert travel.kind == "travel"
    # Something as tall as the swab hangs at the top of Z, halfway along the travel: far
    # from the flower, its descent and its approach.
    poses = poses_along(lift.pose, travel.pose, MotionProfile(),
                        PollinateConfig().samples_per_move)
    shaft = tool_points(poses, PollinateConfig().tool, PAPER_BOT)
    middle = shaft[len(shaft) // 2]
    tip = middle[np.argmin(middle[:, 2])]  # the swab's lowest point there
    assert np.linalg.norm(tip[:2] - CENTER[:2]) > 0.3
    post = tip + np.stack([np.zeros(20), np.zeros(20), np.linspace(-0.3, 0.0, 20)], 1)
    plan = _plan([flower], post)
    (visit,) = plan.visits
    assert visit.status == "unreachable" and "travel to it at the top of Z" in visit.reason
    assert not plan.planned and "travel" not in [m.kind for m in plan.moves]


def test_the_order_is_no_longer_than_the_flowers_order():
    rng = np.random.default_rng(4)
    centres = CENTER + rng.uniform([-0.12, -0.12, -0.02], [0.12, 0.12, 0.05], (9, 3))
    flowers = [Flower(k, c, np.array([0.0, 0.0, 1.0])) for k, c in enumerate(centres)]
    plan = _plan(flowers)
    assert sorted(v.flower for v in plan.visits) == list(range(9))
    profile = MotionProfile()

    def length(visits):
        places = [PAPER_BOT.home] + [v.pre.gantry for v in visits]
        return sum(_transfer_cost(a, b, profile) for a, b in zip(places, places[1:],
                                                                 strict=False))

    given = sorted(plan.visits, key=lambda v: v.flower)
    assert length(plan.visits) <= length(given) + 1e-9
    assert _short_order(given, PAPER_BOT.home, PAPER_BOT, profile) == [
        given.index(v) for v in plan.visits]


@pytest.mark.parametrize("flowers, words", [
    ({"frame": "bed", "flowers": [{"center": [1.5, 0.75, 0.2],
                                   "normals": {"plane": None}}]}, "no flower has a plane"),
    ({"frame": "cloud", "flowers": [{"center": [1.5, 0.75, 0.2],
                                     "normals": {"plane": [0, 0, 1]}}]}, "bed frame"),
    ({"frame": "bed", "flowers": [{"center": [0.5, 0.75, 0.2],
                                   "normals": {"plane": [0, 0, 1]}}]}, "not on the plant"),
])
def test_bad_flowers_are_one_line_and_exit_2(tmp_path, capsys, flowers, words):
    from flowerpose.cli import main

    path = tmp_path / "flowers.json"
    path.write_text(json.dumps(flowers))
    assert main(["pollinate", str(path), "--plant-at", "1.5,0.75", "--out",
                 str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and words in err and "flowers.json" in err
    assert not (tmp_path / "out").exists()


def test_a_plant_outside_the_bed_is_one_line_and_exit_2(tmp_path, capsys):
    from flowerpose.cli import main

    path = tmp_path / "flowers.json"
    path.write_text(json.dumps({"frame": "bed", "flowers": [
        {"center": [1.5, 0.75, 0.2], "normals": {"plane": [0, 0, 1]}}]}))
    assert main(["pollinate", str(path), "--plant-at", "3.5,0.75", "--out",
                 str(tmp_path / "out")]) == 2
    assert "--plant-at: (3.5, 0.75) m is outside the bed" in capsys.readouterr().err


def test_pollinate_writes_the_plan_and_prints_the_moves(tmp_path, capsys):
    from flowerpose.cli import main

    path = tmp_path / "flowers.json"
    path.write_text(json.dumps({"frame": "bed", "flowers": [
        {"id": 4, "center": [1.5, 0.75, 0.2], "normals": {"plane": [0, 0, 1]}},
        {"id": 5, "center": [1.5, 0.75, 0.15], "normals": {"plane": [0, 0, -1]}}]}))
    assert main(["pollinate", str(path), "--plant-at", "1.5,0.75", "--out",
                 str(tmp_path / "out"), "--dry-run", "--set", "standoff_m=0.04"]) == 0
    shown = capsys.readouterr().out
    assert "1 of 2 flowers visited" in shown and "flower 5: unreachable" in shown
    assert " approach " in shown and " dwell " in shown
    written = json.loads((tmp_path / "out" / "pollination.json").read_text())
    assert written["planned"] == 1 and written["config"]["standoff_m"] == 0.04
    assert [v["flower"] for v in written["visits"]] == [4, 5]


def test_the_head_boxes_are_the_models_collision_geoms():
    mujoco = pytest.importorskip("mujoco")
    from flowerpose.hardware.geometry import FARMBOT_ASSETS
    from flowerpose.hardware.kinematics import head_boxes

    model = mujoco.MjModel.from_xml_path(str(FARMBOT_ASSETS / "scene.xml"))
    data = mujoco.MjData(model)
    head = [model.body(name).id for name in ("head_yaw", "head_pitch")]
    geoms = [g for g in range(model.ngeom)
             if model.geom_bodyid[g] in head and model.geom_group[g] == 3]
    rng = np.random.default_rng(5)
    n = 50
    poses = HeadPose(rng.uniform(PAPER_BOT.gantry_min, PAPER_BOT.gantry_max, (n, 3)),
                     rng.uniform(0.0, 2 * np.pi, n), rng.uniform(-0.5, 2.0, n))
    centres, rotations, half = head_boxes(poses)
    assert np.allclose(half, model.geom_size[geoms])
    for k, qpos in enumerate(joint_positions(poses)):
        data.qpos[:] = qpos
        mujoco.mj_kinematics(model, data)
        assert np.abs(data.geom_xpos[geoms] - centres[k]).max() < 1e-12
        assert np.abs(data.geom_xmat[geoms].reshape(-1, 3, 3) - rotations[k]).max() < 1e-12


def test_a_leaf_inside_the_heads_housing_blocks_the_axis_though_far_from_its_centres():
    from flowerpose.hardware.flights.scan_plan import head_points
    from flowerpose.hardware.kinematics import head_boxes

    flower = Flower(0, CENTER, np.array([0.0, 0.0, 1.0]))
    (clear,) = _plan([flower]).visits
    centres, rotations, _ = head_boxes(clear.pre)
    leaf = centres[1] + rotations[1] @ np.array([0.0, 0.02, 0.0])  # in the pitch box
    assert np.linalg.norm(head_points(clear.pre)[0] - leaf, axis=1).min() > 0.02
    (visit,) = _plan([flower], leaf[None, :]).visits
    # The usual head blocked, the visit turns the head upside down or leaves the axis.
    assert visit.status == "planned"
    assert visit.off_axis_deg > 0 or not np.allclose(joint_positions(visit.pre)[3:],
                                                     joint_positions(clear.pre)[3:])
    gap = head_gap(visit.pre, cKDTree(leaf[None, :]), 0.05, PAPER_BOT)
    assert gap >= PollinateConfig().clearance_m


def test_the_upside_down_head_puts_the_tip_where_the_usual_one_does():
    tip, direction = CENTER + [0.0, 0.0, 0.05], np.array([0.3, 0.1, -1.0])
    usual, flipped = (tool_at(tip, direction, flip=flip) for flip in (False, True))
    assert not np.allclose(joint_positions(usual)[3:], joint_positions(flipped)[3:])
    for pose in (usual, flipped):
        at, ahead = tool_forward(pose)
        np.testing.assert_allclose(at, tip, atol=1e-9)
        np.testing.assert_allclose(ahead, direction / np.linalg.norm(direction), atol=1e-9)


def test_a_leaf_over_the_flower_blocks_the_shaft_unless_it_has_a_flowers_colour():
    flower = Flower(0, CENTER, np.array([0.0, 0.0, 1.0]))
    grid = np.linspace(-0.003, 0.003, 4)
    disc = np.array([[x, y, 0.016] for x in grid for y in grid]) + CENTER
    for corolla, blocked in ((None, False), (np.ones(len(disc), bool), False),
                             (np.zeros(len(disc), bool), True)):
        (visit,) = plan_pollination([flower], disc, PollinateConfig(), corolla=corolla).visits
        axis_taken = visit.status == "planned" and visit.off_axis_deg == 0.0
        assert axis_taken != blocked, (corolla, visit)


def test_flower_coloured_points_are_petals_and_pistils():
    from flowerpose.pipeline.colour import flower_coloured

    rgb = np.array([[245, 245, 240], [230, 200, 40], [60, 140, 50], [120, 90, 60]], np.uint8)
    assert flower_coloured(rgb).tolist() == [True, True, False, False]


def test_a_neighbours_petals_inside_the_touch_radius_stay_obstacles_once_the_radius_is_known():
    # A neighbour's petals 16 mm over a flower's centre: within the 2 cm its own corolla
    # may reach, beyond the rim of a flower 10 mm in radius (and 3 mm), within one of 14.
    grid = np.linspace(-0.003, 0.003, 4)
    disc = np.array([[x, y, 0.016] for x in grid for y in grid]) + CENTER
    petals = np.ones(len(disc), bool)
    for radius, blocked in ((None, False), (0.010, True), (0.014, False)):
        flower = Flower(0, CENTER, np.array([0.0, 0.0, 1.0]), radius)
        (visit,) = plan_pollination([flower], disc, PollinateConfig(cone_deg=0.0,
                                                                    path_checks=0),
                                    corolla=petals).visits
        assert (visit.status == "unreachable") == blocked, (radius, visit)


def test_a_flowers_radius_is_read_from_its_box_in_its_files_unit(tmp_path):
    from flowerpose.hardware.flights.visit_flowers import read_visit_flowers
    from flowerpose.pipeline.flowers import read_flowers

    path = tmp_path / "flowers.json"
    path.write_text(json.dumps({"units": "mm", "flowers": [
        {"id": 0, "center": [1500, 750, 200], "normals": {"plane": [0, 0, 1]},
         "box": {"extent": [30.0, 5.0, 24.0]}},
        {"id": 1, "center": [1500, 750, 200], "normals": {"plane": [0, 0, 1]}}]}))
    flowers, _ = read_visit_flowers(read_flowers(path))
    assert flowers[0].radius == pytest.approx(0.012) and flowers[1].radius is None


def test_an_uncertain_flower_is_left_alone_unless_asked(tmp_path):
    from flowerpose.hardware.flights.visit_flowers import (
        NO_NORMAL,
        UNCERTAIN,
        read_visit_flowers,
    )
    from flowerpose.pipeline.flowers import read_flowers

    path = tmp_path / "flowers.json"
    path.write_text(json.dumps({"flowers": [
        {"id": 0, "center": [1.5, 0.75, 0.2], "normals": {"plane": [0, 0, 1]}},
        {"id": 1, "center": [1.5, 0.75, 0.2], "normals": {"plane": [0, 0, 1]},
         "uncertain": True},
        {"id": 2, "center": [1.5, 0.75, 0.2], "normals": {"plane": None}}]}))
    flowers, skipped = read_visit_flowers(read_flowers(path))
    assert [f.id for f in flowers] == [0] and skipped == {1: UNCERTAIN, 2: NO_NORMAL}
    flowers, skipped = read_visit_flowers(read_flowers(path), visit_uncertain=True)
    assert [f.id for f in flowers] == [0, 1] and skipped == {2: NO_NORMAL}


def test_the_planners_flower_colours_are_the_runs_colour_model():
    from flowerpose.pipeline.colour import ColourConfig, flower_coloured

    petal = np.array([[245, 245, 240]] * 60, np.uint8)
    assert flower_coloured(petal).all()
    assert not flower_coloured(petal, ColourConfig(petal_min_value=0.99)).any()
