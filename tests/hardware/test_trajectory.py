"""Poses from a bot's Activities: one activity, a session's timeline, the camera pose as the
servos take it, and trajectory.csv written for a real camera's frames (resumed included)."""

import functools
import math

import numpy as np
import pytest
from cloud_fakes import FakeCapture, FakeDevice, fake_factory, make_token

from flowerpose.hardware.backends.cloud_bot import FarmbotCloudBot
from flowerpose.hardware.backends.cloud_credentials import CloudCredentials
from flowerpose.hardware.backends.usb_camera import FrameChoice, UsbCamera, UsbCameraConfig
from flowerpose.hardware.bot import Activity, Frame, KinematicBot, Recording
from flowerpose.hardware.flights.scan_flight import run_scan
from flowerpose.hardware.flights.scan_plan import ScanConfig, plan_scan
from flowerpose.hardware.kinematics import HeadPose, forward
from flowerpose.hardware.motion import MotionProfile, move_trajectory
from flowerpose.hardware.trajectory import (
    RecordingCamera,
    Timeline,
    TrajectoryRecorder,
    TrajectoryWriter,
    camera_poses,
    last_recorded,
    pose_at,
)
from flowerpose.jsonio import read_json, write_json
from flowerpose.pipeline.frames import FrameSelectConfig, select_frames
from flowerpose.scan_geometry import ScanPathConfig
from flowerpose.scanio import read_trajectory

SMALL = ScanConfig(ScanPathConfig(azimuth_step_deg=90.0, cylinder_bottom_m=0.2,
                                  dome_polar_deg=(50.0,)))
A, B = np.array([1.0, 0.5, 0.5]), np.array([1.3, 0.7, 0.4])


def _move(t0: float, elapsed: float) -> Activity:
    """A move from A to B, cut short after `elapsed` seconds (it takes 8.3 s)."""
    return Activity("move", t0, elapsed, A, B, (0.1, 0.2), (0.1, 0.2), MotionProfile())


def test_pose_at_follows_the_motion_profile_and_turns_the_head_at_servo_speed():
    move = _move(10.0, 3.0)
    t = np.array([5.0, 10.0, 11.5, 13.0, 20.0])
    gantry, yaw, pitch = pose_at(move, t)
    np.testing.assert_allclose(gantry, move_trajectory([0, 0, 1.5, 3.0, 3.0], A, B,
                                                       MotionProfile()))
    np.testing.assert_array_equal(yaw, 0.1)
    turn = Activity("head", 2.0, 1.0, B, B, (0.0, 0.0), (0.6, -0.3))
    _, yaw, pitch = pose_at(turn, [1.0, 2.05, 2.1, 2.5, 9.0], servo_speed_rad_s=6.0)
    np.testing.assert_allclose(yaw, [0.0, 0.3, 0.6, 0.6, 0.6])
    np.testing.assert_allclose(pitch, [0.0, -0.15, -0.3, -0.3, -0.3])
    unknown = Activity("head", 2.0, 0.5, B, B, (math.nan, math.nan), (0.6, -0.3))
    _, yaw, _ = pose_at(unknown, [2.0, 2.4, 2.5, 3.0])
    assert np.isnan(yaw[:2]).all() and np.all(yaw[2:] == 0.6)
    dwell = Activity("dwell", 3.0, 3.0, B, B, (0.6, -0.3), (0.6, -0.3))
    gantry, yaw, _ = pose_at(dwell, [2.0, 4.0])
    np.testing.assert_array_equal(gantry, [B, B])
    np.testing.assert_array_equal(yaw, [0.6, 0.6])


def test_camera_poses_agree_with_mujocos_camera_also_when_the_servos_flip():
    from flowerpose.hardware.backends.sim_bot import MujocoPoser

    rng = np.random.default_rng(3)
    gantry = rng.uniform([0.3, 0.3, 0.3], [2.5, 1.2, 0.6], (12, 3))
    yaw = rng.uniform(0, 2 * np.pi, 12)  # beyond 240 degrees the yaw servo flips
    pitch = rng.uniform(0.0, 1.2, 12)
    positions, rotations = camera_poses(gantry, yaw, pitch)
    poser = MujocoPoser()
    assert np.any(yaw > np.radians(240))
    for k in range(12):
        pose = poser.camera_to_bed(gantry[k], yaw[k], pitch[k])
        np.testing.assert_allclose(positions[k], pose[:3, 3], atol=1e-9)
        np.testing.assert_allclose(rotations[k], pose[:3, :3], atol=1e-9)


def test_the_timeline_holds_each_state_between_activities():
    timeline = Timeline()
    move = _move(10.0, 3.0)
    head = Activity("head", 14.0, 0.5, B, B, (0.1, 0.2), (0.4, 0.2))
    for activity in (move, head):
        timeline.add(activity)
    gantry, yaw, _ = timeline.poses([0.0, 11.0, 13.5, 14.02, 30.0])
    np.testing.assert_allclose(gantry[0], A)  # before the first: its start
    np.testing.assert_allclose(gantry[1], move_trajectory([1.0], A, B, MotionProfile())[0])
    np.testing.assert_allclose(gantry[2], move_trajectory([3.0], A, B, MotionProfile())[0])
    assert yaw[2] == 0.1 and yaw[3] == pytest.approx(0.22) and yaw[4] == 0.4
    assert timeline.end == 14.5


def test_last_recorded_keeps_images_whose_row_was_cut_off(tmp_path):
    assert last_recorded(tmp_path) == (0, None)
    writer = TrajectoryWriter(tmp_path / "trajectory.csv")
    writer.write([0, 1, 2], [0.0, 0.5, 1.0], np.tile(A, (3, 1)), [0.1, np.nan, 0.1],
                 [0.2, 0.2, 0.2])  # frame 1's head was unknown: no row
    writer.close()
    (tmp_path / "frames").mkdir()
    for index in (0, 1, 2, 3):
        (tmp_path / "frames" / f"frame_{index:06d}.jpg").write_bytes(b"")
    with open(tmp_path / "trajectory.csv", "a") as handle:
        handle.write("4,1.5,0.1")  # a row an interruption cut off
    assert last_recorded(tmp_path) == (4, 1.0)
    TrajectoryWriter(tmp_path / "trajectory.csv").close()  # drops the cut-off row
    trajectory = read_trajectory(tmp_path / "trajectory.csv")
    np.testing.assert_array_equal(trajectory.frame, [0, 2])


def test_a_row_cut_mid_value_is_never_trusted_and_a_cut_header_is_written_again(tmp_path,
                                                                               capsys):
    path = tmp_path / "trajectory.csv"
    writer = TrajectoryWriter(path)
    writer.write([0, 1], [0.0, 0.5], np.tile(A, (2, 1)), [0.1, 0.1], [0.2, 0.2])
    writer.close()
    text = path.read_text()
    path.write_text(text[:-6])  # the last value cut short: a number still, but wrong
    trajectory = read_trajectory(path)
    np.testing.assert_array_equal(trajectory.frame, [0])
    assert "cut off by an interruption, is ignored" in capsys.readouterr().err
    path.write_text("frame,t,x")  # killed while the header itself was written
    TrajectoryWriter(path).close()
    assert len(read_trajectory(path)) == 0  # readable: the header is back


class _GridCamera(RecordingCamera):
    """Frames every 1 / fps seconds of a simulated bot's clock, saved as soon as asked."""

    def __init__(self, clock, fps=4.0):
        self._clock, self._fps = clock, fps
        self._next_t = self._index = None

    def intrinsics(self):
        return {"width": 8, "height": 6, "fx": 8.0, "fy": 8.0, "cx": 4.0, "cy": 3.0,
                "fps": self._fps}

    def frame(self):
        return Frame(np.zeros((6, 8, 3), np.uint8), self._clock())

    def start_recording(self, path):
        self._index = last_recorded(path.parent)[0]
        self._next_t = math.ceil(self._clock() * self._fps) / self._fps
        self.start = self._clock()

    def saved_frames(self):
        saved = []
        while self._next_t is not None and self._next_t <= self._clock():
            saved.append((self._index, self._next_t))
            self._index, self._next_t = self._index + 1, self._next_t + 1 / self._fps
        return saved

    def stop_recording(self):
        self._next_t = None
        return Recording(None, self.start, self._clock(), self._fps, self._index)

    def check(self):
        pass


def test_a_recorded_scan_gets_the_pose_of_every_frame_and_a_resumed_one_continues(tmp_path):
    plan = plan_scan(np.array([1.5, 0.75]), 0.25, SMALL)
    recorder = TrajectoryRecorder(_GridCamera)
    activities = []
    bot = KinematicBot(camera=recorder.bind,
                       observer=lambda a: (activities.append(a), recorder.observe(a)))
    run_scan(bot, plan, tmp_path, source={"backend": "kinematic"}, progress=False)
    trajectory = read_trajectory(tmp_path / "trajectory.csv")
    assert len(trajectory) == recorder.rows > 4 * len(plan.waypoints)
    np.testing.assert_array_equal(trajectory.frame, np.arange(len(trajectory)))
    start = activities[0].t0  # the recording starts with the bot's clock at 0
    for activity in activities:
        inside = (trajectory.t > activity.t0 - start) & (
            trajectory.t < activity.t0 + activity.elapsed - start)
        if activity.kind == "move":
            expected = move_trajectory(trajectory.t[inside] + start - activity.t0,
                                       activity.gantry_start, activity.gantry_end,
                                       activity.profile)
            np.testing.assert_allclose(trajectory.gantry[inside], expected, atol=1e-9)
        elif activity.kind == "dwell":
            np.testing.assert_allclose(trajectory.gantry[inside], np.broadcast_to(
                activity.gantry_end, (inside.sum(), 3)), atol=1e-9)
            np.testing.assert_allclose(trajectory.head[inside], np.broadcast_to(
                activity.head_end, (inside.sum(), 2)), atol=1e-9)
    position, rotation = forward(HeadPose(trajectory.gantry, trajectory.head[:, 0],
                                          trajectory.head[:, 1]))
    np.testing.assert_allclose(trajectory.camera_position, position, atol=1e-7)
    np.testing.assert_allclose(trajectory.camera_rotation, rotation, atol=1e-7)

    # A new session (a new bot, its clock from 0) appends after the recorded frames.
    manifest = read_json(tmp_path / "scan.json")
    write_json(tmp_path / "scan.json", {**manifest, "completed": len(plan.waypoints) - 2})
    first = len(trajectory)
    recorder = TrajectoryRecorder(_GridCamera)
    bot = KinematicBot(camera=recorder.bind, observer=recorder.observe)
    run_scan(bot, plan, tmp_path, source={"backend": "kinematic"}, progress=False)
    trajectory = read_trajectory(tmp_path / "trajectory.csv")
    assert len(trajectory) > first and trajectory.frame[first] == first
    assert np.all(np.diff(trajectory.t) > 0)  # the timeline continues


@pytest.mark.slow
def test_a_cloud_scan_with_a_usb_camera_makes_a_scan_folder_the_frame_stage_reads(tmp_path):
    """The whole field chain in real time: the cloud backend (fake client), a USB camera
    (fake capture), the recorder and the executor; then `frames` on the folder."""
    plan = plan_scan(np.array([1.5, 0.75]), 0.25,
                     ScanConfig(SMALL.path, pause_s=0.05))
    config = UsbCameraConfig(width=64, height=48, settle_s=0.0)
    recorder = TrajectoryRecorder(lambda clock: UsbCamera(
        "/dev/v4l/by-id/fake", clock, config, capture=lambda _: FakeCapture(fps=300.0)))
    credentials = CloudCredentials(token=make_token())
    with FarmbotCloudBot(credentials, camera=recorder.bind, observer=recorder.observe,
                         head_settle_s=0.02, reply_latency_s=0.0,
                         client_factory=fake_factory(FakeDevice())) as bot:
        manifest = run_scan(bot, plan, tmp_path, source=bot.describe(), progress=False)
    assert manifest["status"] == "complete"
    trajectory = read_trajectory(tmp_path / "trajectory.csv")
    frames = sorted((tmp_path / "frames").glob("frame_*.jpg"))
    assert manifest["sessions"][0]["frames"] == len(frames) > len(trajectory) > 50
    # Rows are missing only before the first head command (the servos' angles unknown).
    assert trajectory.frame[0] > 0
    np.testing.assert_array_equal(trajectory.frame, np.arange(trajectory.frame[0],
                                                              len(frames)))
    last = plan.waypoints[-1].pose
    np.testing.assert_allclose(trajectory.gantry[-1], last.gantry, atol=1e-9)
    np.testing.assert_allclose(trajectory.head[-1], [last.yaw, last.pitch],
                               atol=math.radians(0.75))  # whole servo degrees
    position, _ = camera_poses(trajectory.gantry[-1:], trajectory.head[-1:, 0],
                               trajectory.head[-1:, 1])
    np.testing.assert_allclose(trajectory.camera_position[-1], position[0])
    chosen = select_frames(tmp_path, tmp_path / "chosen", FrameSelectConfig(count=5),
                           progress=False)
    assert len(chosen["frames"]) == 5


@pytest.mark.slow
def test_scan_json_counts_a_waypoint_done_only_once_its_kept_frames_are_on_disk(tmp_path,
                                                                              monkeypatch):
    """A power cut runs no clean-up, so every scan.json written mid-scan must be safe to
    resume from: the frames the recording keeps from before the waypoints it calls done are
    already on disk with their trajectory rows, none in the writer's queue or the frame
    keeper's open bin."""
    import flowerpose.hardware.flights.flight_journal as journal

    plan = plan_scan(np.array([1.5, 0.75]), 0.25, ScanConfig(SMALL.path, pause_s=0.05))
    config = UsbCameraConfig(width=64, height=48, settle_s=0.0,
                             choose=FrameChoice(duration_s=1.0, bins=4, keep=2))
    snapshots, dwell_ends = [], []

    def write_and_snapshot(path, document):
        write_json(path, document)
        if path.name == "scan.json" and document["status"] == "running":
            rows = tmp_path / "trajectory.csv"
            on_disk = set(read_trajectory(rows).frame) if rows.exists() else set()
            snapshots.append((document["completed"], on_disk))

    monkeypatch.setattr(journal, "write_json", write_and_snapshot)  # scan.json's writer
    recorder = TrajectoryRecorder(lambda clock: UsbCamera(
        "/dev/v4l/by-id/fake", clock, config, capture=lambda _: FakeCapture(fps=300.0)))

    def observe(activity):
        if activity.kind == "dwell":
            dwell_ends.append(activity.t0 + activity.elapsed)
        recorder.observe(activity)

    with FarmbotCloudBot(CloudCredentials(token=make_token()), camera=recorder.bind,
                         observer=observe, head_settle_s=0.02, reply_latency_s=0.0,
                         client_factory=fake_factory(FakeDevice())) as bot:
        manifest = run_scan(bot, plan, tmp_path, source=bot.describe(), progress=False)
    assert manifest["completed"] == len(plan.waypoints) == len(dwell_ends)
    times = np.loadtxt(tmp_path / "frame_times.csv", delimiter=",", skiprows=1, ndmin=2)
    with_rows = set(read_trajectory(tmp_path / "trajectory.csv").frame)
    kept_t = {int(frame): t for frame, t in times if int(frame) in with_rows}
    assert len(snapshots) > len(plan.waypoints) // 2
    assert any(done < k + 1 for k, (done, _) in enumerate(snapshots[1:]))  # a bin lags
    for done, on_disk in snapshots:
        if done:
            needed = {f for f, t in kept_t.items() if t <= dwell_ends[done - 1]}
            assert needed <= on_disk, f"waypoint {done} called done before its frames"


def test_the_recorder_is_usable_only_once_bound():
    recorder = TrajectoryRecorder(functools.partial(_GridCamera, fps=2.0))
    with pytest.raises(RuntimeError, match="bind"):
        recorder.intrinsics()


def test_a_batch_written_twice_is_read_once_and_a_conflicting_row_is_refused(tmp_path, capsys):
    from flowerpose.errors import InputError
    from flowerpose.scanio import TRAJECTORY_COLUMNS, trajectory_row

    rows = [trajectory_row(k, 0.5 * k, np.array([1.0, 0.5, 0.3]), 0.1, 0.2,
                           np.array([1.0, 0.5, 0.2]), np.eye(3)) for k in range(6)]
    path = tmp_path / "trajectory.csv"
    # An interruption before the fix wrote rows 3-4 a second time.
    lines = [TRAJECTORY_COLUMNS, *rows[:5], *rows[3:5], rows[5]]
    path.write_text("".join(",".join(r) + "\n" for r in lines))
    trajectory = read_trajectory(path)
    np.testing.assert_array_equal(trajectory.frame, np.arange(6))
    assert "2 repeated rows" in capsys.readouterr().err
    changed = list(rows[3])
    changed[1] = "9.0"
    path.write_text("".join(",".join(r) + "\n" for r in [TRAJECTORY_COLUMNS, *rows, changed]))
    with pytest.raises(InputError, match="appears twice with different values"):
        read_trajectory(path)


def test_a_zero_quaternion_is_one_line_naming_its_row(tmp_path):
    from flowerpose.errors import InputError
    from flowerpose.scanio import TRAJECTORY_COLUMNS, trajectory_row

    rows = [trajectory_row(k, 0.5 * k, np.array([1.0, 0.5, 0.3]), 0.1, 0.2,
                           np.array([1.0, 0.5, 0.2]), np.eye(3)) for k in range(3)]
    rows[2][-4:] = ["0", "0", "0", "0"]
    path = tmp_path / "trajectory.csv"
    path.write_text("".join(",".join(r) + "\n" for r in [TRAJECTORY_COLUMNS, *rows]))
    with pytest.raises(InputError, match="row 3 \\(frame 2\\).*not a unit quaternion"):
        read_trajectory(path)
