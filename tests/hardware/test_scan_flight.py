import functools

import numpy as np
import pytest

from flowerpose.errors import InputError
from flowerpose.hardware.bot import KinematicBot, SolidCamera
from flowerpose.hardware.bot_errors import StallError
from flowerpose.hardware.flights.scan_flight import run_scan
from flowerpose.hardware.flights.scan_plan import ScanConfig, plan_scan
from flowerpose.jsonio import read_json, write_json
from flowerpose.scan_geometry import ScanPathConfig

SMALL = ScanConfig(ScanPathConfig(azimuth_step_deg=90.0, cylinder_bottom_m=0.2,
                                  dome_polar_deg=(50.0,)))
SOURCE = {"backend": "kinematic"}


def _bot(**kwargs):
    return KinematicBot(camera=functools.partial(SolidCamera, width=32, height=24, fps=2),
                        **kwargs)


class _StallsAt(KinematicBot):
    """Stalls on Y during its `count`-th move."""

    def __init__(self, count):
        super().__init__(camera=functools.partial(SolidCamera, width=32, height=24, fps=2))
        self.moves, self.count = 0, count

    def move_to(self, xyz, speed_fraction=1.0):
        self.moves += 1
        if self.moves == self.count:
            self.fail_next_move(32)
        super().move_to(xyz, speed_fraction)


def test_scan_visits_every_waypoint_and_takes_the_planned_time(tmp_path):
    plan = plan_scan(np.array([1.5, 0.75]), 0.25, SMALL)
    activities = []
    bot = _bot(observer=activities.append, head_settle_s=0.5)
    manifest = run_scan(bot, plan, tmp_path, source=SOURCE, progress=False)
    assert manifest["status"] == "complete" and manifest["completed"] == len(plan.waypoints)
    np.testing.assert_allclose(bot.position(), plan.waypoints[-1].pose.gantry, atol=1e-12)
    first_move = [a for a in activities if a.kind == "move"][0].elapsed
    expected = plan.duration_s + first_move + 0.5 * len(plan.waypoints)
    assert bot.now() == pytest.approx(expected)
    assert [a.kind for a in activities[:3]] == ["move", "head", "dwell"]
    assert (tmp_path / "camera.json").exists() and (tmp_path / "video.mp4").exists()


def test_an_interrupted_scan_resumes_at_the_next_waypoint(tmp_path):
    plan = plan_scan(np.array([1.5, 0.75]), 0.25, SMALL)
    with pytest.raises(StallError):
        run_scan(_StallsAt(4), plan, tmp_path, source=SOURCE, progress=False)
    stopped = read_json(tmp_path / "scan.json")
    assert stopped["status"] == "interrupted" and stopped["completed"] == 3
    assert "StallError" in stopped["sessions"][0]["error"]
    resumed_bot = _bot()
    manifest = run_scan(resumed_bot, plan, tmp_path, source=SOURCE, progress=False)
    assert manifest["status"] == "complete" and manifest["completed"] == len(plan.waypoints)
    assert [s["started_waypoint"] for s in manifest["sessions"]] == [0, 3]
    other = plan_scan(np.array([1.4, 0.75]), 0.25, SMALL)
    with pytest.raises(InputError, match="different scan"):
        run_scan(_bot(), other, tmp_path, source=SOURCE, progress=False)


def test_a_second_scan_into_a_folder_being_recorded_is_refused(tmp_path):
    from flowerpose.hardware.flights.flight_journal import folder_lock
    from flowerpose.hardware.flights.scan_flight import LOCK_NAME

    plan = plan_scan(np.array([1.5, 0.75]), 0.25, SMALL)
    with folder_lock(tmp_path, LOCK_NAME, "scan"):  # as a scan in another process holds it
        with pytest.raises(InputError, match=r"another scan \(pid \d+\) is under way"):
            run_scan(_bot(), plan, tmp_path, source=SOURCE, progress=False)
    assert not (tmp_path / "scan.json").exists()
    assert run_scan(_bot(), plan, tmp_path, source=SOURCE, progress=False)["status"] == \
        "complete"


def test_a_scan_never_writes_into_a_folder_that_is_not_a_scan(tmp_path):
    plant = tmp_path / "plant"
    plant.mkdir()
    (plant / "plant.json").write_text('{"truth": "kept"}')
    plan = plan_scan(np.array([1.5, 0.75]), 0.25, SMALL)
    with pytest.raises(InputError, match=r"not a flowerpose scan \(plant.json\)"):
        run_scan(_bot(), plan, plant, source=SOURCE, progress=False)
    assert sorted(p.name for p in plant.iterdir()) == ["plant.json"]


def test_a_resume_with_another_camera_is_refused_even_before_the_first_waypoint(tmp_path):
    plan = plan_scan(np.array([1.5, 0.75]), 0.25, SMALL)
    with pytest.raises(StallError):
        run_scan(_StallsAt(1), plan, tmp_path, source=SOURCE, progress=False)
    assert read_json(tmp_path / "scan.json")["completed"] == 0
    wider = KinematicBot(camera=functools.partial(SolidCamera, width=64, height=48, fps=2))
    with pytest.raises(InputError, match="other camera settings"):
        run_scan(wider, plan, tmp_path, source=SOURCE, progress=False)


class _StartFails(SolidCamera):
    """A camera whose recording never starts (Ctrl-C while it opens)."""

    def start_recording(self, path):
        raise KeyboardInterrupt


def test_a_scan_stopped_while_its_camera_starts_is_recorded_as_interrupted(tmp_path):
    plan = plan_scan(np.array([1.5, 0.75]), 0.25, SMALL)
    bot = KinematicBot(camera=functools.partial(_StartFails, width=32, height=24, fps=2))
    with pytest.raises(KeyboardInterrupt):
        run_scan(bot, plan, tmp_path, source=SOURCE, progress=False)
    manifest = read_json(tmp_path / "scan.json")
    assert manifest["status"] == "interrupted" and manifest["completed"] == 0
    assert "KeyboardInterrupt" in manifest["sessions"][0]["error"]


def test_a_session_that_died_without_closing_is_named_on_resume(tmp_path, caplog):
    plan = plan_scan(np.array([1.5, 0.75]), 0.25, SMALL)
    run_scan(_bot(), plan, tmp_path, source=SOURCE, progress=False)
    manifest = read_json(tmp_path / "scan.json")
    session = {k: v for k, v in manifest["sessions"][0].items()
               if k not in ("bot_time_end", "frames", "wall_s")}  # as a power cut leaves it
    write_json(tmp_path / "scan.json", {**manifest, "status": "running", "completed": 2,
                                        "sessions": [session]})
    with caplog.at_level("INFO", logger="flowerpose"):
        resumed = run_scan(_bot(), plan, tmp_path, source=SOURCE, progress=True)
    assert resumed["status"] == "complete"
    assert "power cut" in resumed["sessions"][0]["error"]
    assert "error" not in resumed["sessions"][1]
    assert "the last session ended without closing" in caplog.text
