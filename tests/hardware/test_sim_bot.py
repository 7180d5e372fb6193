"""The simulated backend end to end on a small, low-resolution scan."""

import csv
import dataclasses

import cv2
import numpy as np
import pytest

from flowerpose.errors import InputError
from flowerpose.eval.capture.scan_source import write_scan_truth
from flowerpose.hardware.backends.sim_bot import SimBot, SimBotConfig
from flowerpose.hardware.backends.sim_camera import SimCameraConfig
from flowerpose.hardware.flights.scan_flight import run_scan
from flowerpose.hardware.flights.scan_plan import ScanConfig, plan_scan
from flowerpose.hardware.kinematics import HeadPose, forward
from flowerpose.jsonio import read_json
from flowerpose.pipeline.frames import FrameSelectConfig, bin_edges, select_frames
from flowerpose.scan_geometry import ScanPathConfig
from flowerpose.scanio import frame_files, read_trajectory
from flowerpose.sim.bundle import make_plant
from flowerpose.sim.render_config import RenderConfig
from flowerpose.sim.sensor import SensorConfig

SMALL = ScanConfig(ScanPathConfig(azimuth_step_deg=60.0, cylinder_bottom_m=0.22,
                                  cylinder_step_m=0.04, dome_polar_deg=(50.0,)))
CONFIG = SimBotConfig(camera=SimCameraConfig(width=160, height=90, frame_rate_hz=1.0,
                                             workers=1, visibility_width=96))


@pytest.fixture(scope="module")
def plant_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("plant")
    make_plant(0, "easy", points=2000, out_dir=out)
    return out


def _plan(plant_dir):
    truth = read_json(plant_dir / "plant.json")
    return plan_scan(np.array(truth["plant_center"][:2]), truth["height"], SMALL)


class _StallsAt(SimBot):
    def __init__(self, plant_dirs, config, count):
        super().__init__(plant_dirs, config)
        self.moves, self.count = 0, count

    def move_to(self, xyz, speed_fraction=1.0):
        self.moves += 1
        if self.moves == self.count:
            self.fail_next_move(31)
        super().move_to(xyz, speed_fraction)


@pytest.mark.slow
def test_scan_records_frames_poses_and_truth_then_resumes(plant_dir, tmp_path):
    plan = _plan(plant_dir)
    scan = tmp_path / "scan"
    with pytest.raises(Exception, match="stall"):
        with _StallsAt([plant_dir], CONFIG, 5) as bot:
            run_scan(bot, plan, scan, source={"backend": "sim"}, progress=False)
    first = read_trajectory(scan / "trajectory.csv")
    assert read_json(scan / "scan.json")["completed"] == 4
    assert len(first) == len(frame_files(scan)) > 0  # the frames recorded so far are kept
    with SimBot([plant_dir], dataclasses.replace(
            CONFIG, camera=dataclasses.replace(CONFIG.camera, width=96, height=54))) as bot:
        with pytest.raises(InputError, match="other camera settings"):
            run_scan(bot, plan, scan, source={"backend": "sim"}, progress=False)
    with SimBot([plant_dir], CONFIG) as bot:
        manifest = run_scan(bot, plan, scan, source={"backend": "sim"}, progress=False)
    assert manifest["status"] == "complete"
    trajectory = read_trajectory(scan / "trajectory.csv")
    assert len(trajectory) == len(frame_files(scan)) > len(first)
    np.testing.assert_array_equal(trajectory.frame, np.arange(len(trajectory)))
    assert np.all(np.diff(trajectory.t) > 0)  # the resumed session continues the timeline
    # MuJoCo's camera agrees with the kinematics: same optical centre and axis (a flipped
    # head turns the image about the axis).
    position, rotation = forward(HeadPose(trajectory.gantry, trajectory.head[:, 0],
                                          trajectory.head[:, 1]))
    np.testing.assert_allclose(trajectory.camera_position, position, atol=1e-6)
    axes = np.einsum("nij,nij->nj", trajectory.camera_rotation, rotation)[:, 2]
    assert np.all(axes > 1 - 1e-9)
    visibility = read_json(scan / "visibility.json")
    truth = read_json(plant_dir / "plant.json")
    assert set(visibility["visible"]) == {str(f["id"]) for f in truth["flowers"]}
    assert sum(visibility["visible"].values()) >= len(truth["flowers"]) - 1
    scan_truth = read_json(write_scan_truth(scan, plant_dir))
    assert scan_truth["visibility"] == "scan"
    assert [f["visible"] for f in scan_truth["flowers"]] == [
        visibility["visible"][str(f["id"])] for f in truth["flowers"]]


@pytest.mark.slow
def test_frame_selection_picks_the_frames_the_simulator_left_sharp(plant_dir, tmp_path):
    scan = tmp_path / "scan"
    with SimBot([plant_dir], CONFIG) as bot:
        run_scan(bot, _plan(plant_dir), scan, source={"backend": "sim"}, progress=False)
    with open(scan / "frames_truth.csv") as handle:
        sharpness = np.array([float(r["sharpness"]) for r in csv.DictReader(handle)])
    assert 0.2 < np.mean(sharpness > 0.9) < 0.9  # some frames sharp, many blurred
    bins = 20
    chosen = select_frames(scan, tmp_path / "frames", FrameSelectConfig(count=bins, crop_px=90),
                           progress=False)["frames"]
    edges = bin_edges(len(sharpness), bins)
    best = np.array([sharpness[edges[b]:edges[b + 1]].max() for b in range(bins)])
    got = sharpness[[f["index"] for f in chosen]]
    # Wherever a bin holds a sharp frame, a sharp one is chosen (two equally ruined frames,
    # as on the first long move from home, have no meaningful order).
    has_sharp = best > 0.9
    assert has_sharp.sum() >= bins - 2
    assert np.all(got[has_sharp] > 0.9), (got, best)


@pytest.mark.slow
def test_the_configured_camera_processing_and_light_reach_the_recorded_frames(plant_dir,
                                                                            tmp_path):
    plan = dataclasses.replace(_plan(plant_dir), waypoints=_plan(plant_dir).waypoints[:2])

    def mean_level(camera):
        scan = tmp_path / f"scan-{len(list(tmp_path.iterdir()))}"
        config = dataclasses.replace(CONFIG, camera=dataclasses.replace(CONFIG.camera, **camera))
        with SimBot([plant_dir], config) as bot:
            run_scan(bot, plan, scan, source={"backend": "sim"}, progress=False)
        return np.mean([cv2.imread(str(f)).mean() for f in frame_files(scan)])

    plain = mean_level({})
    assert mean_level({"sensor": SensorConfig(gain=0.5)}) == pytest.approx(plain / 2, rel=0.05)
    assert mean_level({"render": RenderConfig(sun=0.2, sky=0.1, fill=0.0, bounce=0.0,
                                              background_rgb=(40, 40, 40))}) < 0.7 * plain


def test_the_simulated_bot_flies_the_synthetic_worlds_path(plant_dir):
    """`--set sim.viewpoints.*` moves the cameras that decide visibility and the path the
    bot flies alike."""
    from flowerpose.hardware.flights.scan_plan import plan_plant_scan
    from flowerpose.sim.export import plant_obstacles, read_plant

    plant = read_plant(plant_dir)
    around = (plant.center[:2], plant.height, plant_obstacles(plant))
    coarse = ScanPathConfig(azimuth_step_deg=90.0, cylinder_bottom_m=0.22, dome_polar_deg=(50.0,))
    plan = plan_plant_scan(*around, coarse)
    assert plan.config.path == coarse
    assert len(plan.waypoints) < len(plan_plant_scan(*around).waypoints)
