"""Paths round the plant for a pollination visit: a flower under a leaf that no straight
descent reaches is reached down a path whose every flown move keeps its clearance, the same
plan comes out every time, the executor flies the path's waypoints as planned on a virtual
Farmduino, and a flower walled in is refused with its reason."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

pytest.importorskip("ompl")

from flowerpose.cloudio import Cloud, write_cloud  # noqa: E402
from flowerpose.hardware.flights.approach_path import joint_state  # noqa: E402
from flowerpose.hardware.flights.clearance import gap  # noqa: E402
from flowerpose.hardware.flights.pollination_plan import (  # noqa: E402
    Flower,
    PollinateConfig,
    _flown,
    plan_pollination,
)
from flowerpose.hardware.geometry import PAPER_BOT, PollinatorTool  # noqa: E402
from flowerpose.hardware.kinematics import head_boxes  # noqa: E402
from flowerpose.hardware.motion import MotionProfile  # noqa: E402
from flowerpose.jsonio import read_json, write_json  # noqa: E402

CENTER = np.array([1.5, 0.75, 0.15])
UP = np.array([0.0, 0.0, 1.0])
#: The leaf scenes are built for a 12 cm shaft 3 cm under the lens, 6.5 cm out: the default
#: 15 cm one, hanging from the top of Z at the pre-approach pose's angles where every path
#: starts, would already pierce a leaf 3 cm over its pre-approach head.
SHORT = {"tool": PollinatorTool(reach_m=0.12, offset_down_m=0.03), "standoff_m": 0.065}
SHORT_SET = [word for key, value in (("tool.reach_m", SHORT["tool"].reach_m),
                                     ("tool.offset_down_m", SHORT["tool"].offset_down_m),
                                     ("standoff_m", SHORT["standoff_m"]))
             for word in ("--set", f"pollinate.{key}={value}")]


def sheet(center, size, normal_axis: int, spacing: float = 0.004) -> np.ndarray:
    """Points on a flat rectangle (metres, bed frame) across `normal_axis`, `spacing` apart:
    a leaf as a scan samples it."""
    across = [a for a in range(3) if a != normal_axis]
    u, v = (np.arange(-s / 2, s / 2 + 1e-9, spacing) for s in size)
    grid = np.zeros((len(u) * len(v), 3))
    grid[:, across[0]], grid[:, across[1]] = (g.ravel() for g in np.meshgrid(u, v))
    return grid + np.asarray(center)


def head_top_over_pre() -> float:
    """Height of the head's highest corner at the unobstructed visit's pre-approach pose."""
    (visit,) = plan_pollination([Flower(0, CENTER, UP)], None, PollinateConfig(**SHORT)).visits
    centres, rotations, half = head_boxes(visit.pre)
    return max(float((centres[k] + np.abs(rotations[k]) @ half[k])[2]) for k in range(2))


def leaf_over_flower() -> np.ndarray:
    """A 14 cm leaf 3 cm over the head at the flower's pre-approach pose: the straight
    descent from the top of Z passes through it, the approach under it does not."""
    return sheet([*CENTER[:2], head_top_over_pre() + 0.03], (0.14, 0.14), 2)


@pytest.mark.slow
def test_a_flower_under_a_leaf_is_reached_down_a_path_that_keeps_its_clearance():
    leaf, flower = leaf_over_flower(), Flower(0, CENTER, UP)
    (straight,) = plan_pollination([flower], leaf, PollinateConfig(path_checks=0, **SHORT)).visits
    assert straight.status == "unreachable" and "on the descent" in straight.reason
    assert "the way down is blocked (no path searched)" in straight.reason
    plan = plan_pollination([flower], leaf, PollinateConfig(**SHORT))
    (visit,) = plan.visits
    assert visit.status == "planned" and visit.off_axis_deg == 0.0 and visit.path
    assert visit.path[-1] is visit.pre
    kinds = [m.kind for m in plan.moves]
    assert kinds.count("descend") == kinds.count("climb") == len(visit.path)
    tree, config, profile = cKDTree(leaf), PollinateConfig(**SHORT), MotionProfile()
    top = plan.moves[kinds.index("travel")].pose
    assert np.isclose(top.gantry[2], PAPER_BOT.gantry_max[2])
    flown = [top, *visit.path]
    for a, b in zip(flown, flown[1:], strict=False):  # down the path and back up it
        for poses in (_flown(a, b, config, PAPER_BOT, config.tool, profile),
                      _flown(b, a, config, PAPER_BOT, config.tool, profile)):
            assert gap(poses, tree, tree, 0.05, PAPER_BOT, config.tool,
                       config.check_step_m)[0] >= config.clearance_m
    # The path goes round the leaf: some waypoint is beside it, below its height.
    beside = [p for p in visit.path if p.gantry[2] < leaf[0, 2]
              and np.abs(p.gantry[:2] - CENTER[:2]).max() > 0.07]
    assert beside


@pytest.mark.slow
def test_the_same_problem_gives_the_same_plan():
    leaf, flower = leaf_over_flower(), Flower(0, CENTER, UP)
    first, again = (plan_pollination([flower], leaf, PollinateConfig(**SHORT)) for _ in range(2))
    assert len(first.moves) == len(again.moves)
    for a, b in zip(first.moves, again.moves, strict=True):
        assert a.kind == b.kind and np.array_equal(joint_state(a.pose), joint_state(b.pose))


@pytest.mark.slow
def test_a_flower_walled_in_is_refused_saying_no_path_was_found():
    height = head_top_over_pre() + 0.03
    half = 0.2
    walls = [sheet([*CENTER[:2], height], (2 * half, 2 * half), 2)]
    for axis in (0, 1):
        for side in (-1, 1):
            centre = np.array([*CENTER[:2], (height + 0.05) / 2])
            centre[axis] += side * half
            size = (2 * half, height - 0.05)
            walls.append(sheet(centre, size, axis))
    cage = np.vstack(walls)
    (visit,) = plan_pollination([Flower(0, CENTER, UP)], cage,
                                PollinateConfig(path_checks=300, cone_deg=0.0, **SHORT)).visits
    assert visit.status == "unreachable"
    assert "no path round the plant was found in 300 clearance tests" in visit.reason
    assert "the way down is blocked and no path round the plant was found" in visit.reason


@pytest.mark.slow
def test_the_executor_flies_the_paths_waypoints_on_a_virtual_farmduino(tmp_path, capsys):
    virtual = pytest.importorskip("flowerpose.hardware.backends.virtual_farmduino")
    from flowerpose.cli import main

    leaf = leaf_over_flower()
    write_cloud(tmp_path / "plant.ply", Cloud(leaf, np.full((len(leaf), 3), [40, 120, 40],
                                                             np.uint8)))
    write_json(tmp_path / "flowers.json", {"units": "m", "frame": "bed", "flowers": [
        {"id": 0, "center": CENTER.tolist(), "normals": {"plane": UP.tolist()}}]})
    argv = ["pollinate", tmp_path / "flowers.json", "--plant-at", "1.5,0.75",
            "--plant-cloud", tmp_path / "plant.ply", "--out", tmp_path / "visits",
            "--set", "pollinate.look.views=0", *SHORT_SET]  # on the scan's poses
    with virtual.VirtualFarmduino(time_scale=1000.0,
                                  params=virtual.FEEDBACK_PARAMETERS) as device:
        code = main([str(a) for a in [*argv, "--port", device.path]])
        assert code == 0, capsys.readouterr().err
        sent = [line for line in device.received if line.startswith("G00")]
    (visit,) = read_json(tmp_path / "visits" / "pollination.json")["visits"]
    path = np.array(visit["path"])
    assert len(path) >= 2
    targets = np.array([[float(word[1:]) for word in line.split()[1:4]] for line in sent])
    expected = (path[:, :3] - PAPER_BOT.home) * 1000.0
    # Down the path in order, then (after the approach and back) up it in reverse.
    found = [int(np.flatnonzero(np.abs(targets - p).max(axis=1) < 0.01)[0]) for p in expected]
    assert found == sorted(found)
    back = [int(np.flatnonzero(np.abs(targets - p).max(axis=1) < 0.01)[-1])
            for p in expected[:-1]]
    assert back == sorted(back, reverse=True) and min(back) > max(found)

