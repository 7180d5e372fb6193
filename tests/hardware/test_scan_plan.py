import numpy as np
import pytest

from flowerpose.errors import InputError
from flowerpose.hardware.flights.scan_plan import ScanConfig, plan_scan
from flowerpose.hardware.kinematics import UnreachableError, forward
from flowerpose.scan_geometry import ScanPathConfig, path_cameras

MID_BED = np.array([1.5, 0.75])


def test_path_is_the_papers_cylinder_then_dome_and_looks_where_commanded():
    plan = plan_scan(MID_BED, 0.28)
    kinds = [w.kind for w in plan.waypoints]
    assert kinds == sorted(kinds)  # the cylinder first
    rings = np.arange(0.16, 0.28 + 1e-9, 0.02)
    assert kinds.count("cylinder") == 18 * len(rings) and kinds.count("dome") == 4 * 18
    for w in plan.waypoints:
        camera, rotation = forward(w.pose)
        np.testing.assert_allclose(camera, w.camera, atol=1e-9)
        wanted = (w.target - camera) / np.linalg.norm(w.target - camera)
        assert np.degrees(np.arccos(np.clip(rotation[:, 2] @ wanted, -1, 1))) < 1.0
        if w.kind == "cylinder":
            assert np.isclose(np.linalg.norm(w.camera[:2] - MID_BED), 0.5)
        else:
            assert np.isclose(np.linalg.norm(w.camera - w.target), 0.3)
    assert 15 * 60 < plan.duration_s < 25 * 60  # the paper: about 20 minutes


def test_rings_alternate_direction_so_the_path_never_jumps_a_full_turn():
    _, cameras, _ = path_cameras(MID_BED, 0.2, ScanPathConfig())
    steps = np.linalg.norm(np.diff(cameras, axis=0), axis=1)
    assert steps.max() < 0.25


def test_unreachable_paths_are_refused_before_moving():
    with pytest.raises(UnreachableError, match="gantry X"):
        plan_scan(np.array([0.1, 0.75]), 0.25)  # the cylinder leaves the bed's travel
    with pytest.raises(UnreachableError, match="gantry Z"):
        plan_scan(MID_BED, 0.25, ScanConfig(ScanPathConfig(dome_center="top",
                                                           dome_radius_m=0.45)))
    with pytest.raises(InputError, match="plant height"):
        plan_scan(MID_BED, -1.0)


def test_a_path_through_the_plant_is_refused_naming_the_waypoint():
    rng = np.random.default_rng(0)
    # A bushy plant 0.55 m across: the 0.5 m cylinder passes through its leaves.
    angle, radius = rng.uniform(0, 2 * np.pi, 4000), np.sqrt(rng.uniform(0, 0.55**2, 4000))
    bush = np.c_[MID_BED[0] + radius * np.cos(angle), MID_BED[1] + radius * np.sin(angle),
                 rng.uniform(0.05, 0.25, 4000)]
    with pytest.raises(InputError, match="scan waypoint 0.*mm from the plant"):
        plan_scan(MID_BED, 0.25, obstacles=bush)
    small = bush[np.linalg.norm(bush[:, :2] - MID_BED, axis=1) < 0.15]
    assert len(plan_scan(MID_BED, 0.25, obstacles=small).waypoints) > 100


def test_path_geometry_is_the_papers():
    kinds, cameras, targets = path_cameras(np.array([0.4, 0.3]), 0.30)
    rings = len(np.arange(0.16, 0.30 + 1e-9, 0.02))
    assert kinds.count("cylinder") == rings * 18 and kinds.count("dome") == 4 * 18
    cylinder, dome = cameras[:rings * 18], cameras[rings * 18:]
    assert np.linalg.norm(cylinder[:, :2] - [0.4, 0.3], axis=1) == pytest.approx(0.5)
    np.testing.assert_allclose(cylinder[:, 2], targets[:rings * 18, 2])  # level views
    assert np.linalg.norm(dome - [0.4, 0.3, 0.15], axis=1) == pytest.approx(0.3)
    polar = np.degrees(np.arccos((dome[:, 2] - 0.15) / 0.3))
    assert sorted(set(np.round(polar, 6))) == [10.0, 30.0, 50.0, 70.0]


def test_a_plant_off_the_reachable_strip_is_told_where_plants_fit():
    with pytest.raises(UnreachableError, match="gantry Y") as error:
        plan_scan(np.array([1.2, 0.6]), 0.25)
    words = str(error.value).split("this path fits a plant with its stem at ")[1]
    (x_low, x_high), (y_low, y_high) = (
        [float(v) for v in part.split()[1].split("-")] for part in words.split(" and "))
    assert y_low < 0.75 < y_high and x_low < 1.2 < x_high
    # The ends of the strip it names plan, a step beyond them does not.
    plan_scan(np.array([1.2, y_low + 0.005]), 0.25)
    plan_scan(np.array([1.2, y_high - 0.005]), 0.25)
    with pytest.raises(UnreachableError):
        plan_scan(np.array([1.2, y_high + 0.02]), 0.25)
