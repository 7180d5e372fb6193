"""The plant in MuJoCo with the bot: contact patches cut from a generated plant, and a
leaflet that a tool drives into giving way by about as far as it is driven."""

import numpy as np
import pytest

pytest.importorskip("mujoco")

from flowerpose.eval.pollination.contact import ContactWorld  # noqa: E402
from flowerpose.hardware.bot import KinematicBot  # noqa: E402
from flowerpose.hardware.kinematics import (
    head_angles,  # noqa: E402
    tool_at,  # noqa: E402
)
from flowerpose.hardware.trajectory import Timeline  # noqa: E402
from flowerpose.sim.pieces import Part  # noqa: E402


@pytest.fixture(scope="module")
def world():
    from flowerpose.sim.bundle import make_plant

    return ContactWorld(make_plant(2, "easy").plant)


@pytest.mark.slow
def test_the_patches_cover_the_plant_but_its_soil(world):
    patches = world.patches
    assert len(patches.hulls) == len(patches.part) == len(patches.flower) > 100
    assert Part.SOIL not in patches.part and Part.LEAF in patches.part
    flowers = set(patches.flower[patches.flower >= 0].tolist())
    assert flowers  # every patch of an open flower carries its id
    assert all(len(h) >= 6 and np.ptp(h, axis=0).max() < 0.03 for h in patches.hulls)
    leaves = np.unique(patches.piece[patches.part == Part.LEAF])
    assert set(leaves.tolist()) <= set(patches.bases)  # each leaflet is sprung


def _open_leaf(world) -> np.ndarray:
    """The centre of a leaflet patch with nothing of the plant above it within 3 cm."""
    patches = world.patches
    centres = np.array([h.mean(0) for h in patches.hulls])
    for k in np.flatnonzero(patches.part == Part.LEAF):
        side = np.hypot(*(centres[:, :2] - centres[k, :2]).T)
        if not np.any((side < 0.03) & (centres[:, 2] > centres[k, 2] + 0.003)):
            return centres[k]
    raise AssertionError("no leaflet open from above")


def _drive(world, leaf: np.ndarray, past_m: float):
    """Bring the swab straight down from 4 cm above `leaf` to `past_m` below it (negative:
    above it), on a simulated bot; what it touched."""
    timeline = Timeline()
    bot = KinematicBot(observer=timeline.add)
    down = np.array([0.0, 0.0, -1.0])
    above = tool_at(leaf + 0.04 * np.array([0.0, 0.0, 1.0]), down)
    into = tool_at(leaf + past_m * down, down)
    top = bot.info.travel_max[2]
    bot.move_to([*above.gantry[:2], top])
    bot.set_head(*head_angles(above))
    bot.move_to(above.gantry)
    start = bot.now()
    bot.move_to(into.gantry)
    bot.dwell(0.5)
    return world.fly(timeline, start, bot.now())


def test_a_leaflet_gives_way_by_about_as_far_as_the_tool_drives_into_it(world):
    leaf = _open_leaf(world)
    short = _drive(world, leaf, -0.02)
    assert short.push_m == 0.0 and not len(short.patches)
    pushed = _drive(world, leaf, 0.015)
    assert len(pushed.patches) and pushed.steps > 0
    # Driven 15 mm past where it grew, the leaflet moves that far plus the swab's radius
    # (4 mm) and half its thickness, give or take where on it the swab landed.
    assert 0.015 < pushed.push_m < 0.03


def test_a_point_touching_a_long_shaft_midway_between_twelve_points_is_near():
    from types import SimpleNamespace

    from scipy.spatial import cKDTree

    from flowerpose.hardware.geometry import PollinatorTool
    from flowerpose.hardware.kinematics import HeadPose, tool_points

    tool = PollinatorTool(reach_m=0.24, offset_down_m=0.07)
    pose = tool_at(np.array([1.5, 0.75, 0.2]), np.array([0.0, 0.0, -1.0]), tool)
    pose = HeadPose(pose.gantry[None], np.array([pose.yaw]), np.array([pose.pitch]))
    # On the shaft's surface (2 mm from its axis), halfway between two of twelve points.
    point = tool_points(pose, tool, samples=23)[0, 11] + np.array([0.002, 0.0, 0.0])
    twelve = tool_points(pose, tool, samples=12)[0]
    assert np.linalg.norm(twelve - point, axis=1).min() > 0.01  # twelve would miss it
    world = SimpleNamespace(tool=tool, near_m=0.01)  # all `_near` reads of the world
    assert ContactWorld._near(world, pose, cKDTree(point[None, :])).all()
