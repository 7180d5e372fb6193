"""The simulated backend: the bot on MuJoCo, filming generated plants with an imperfect camera.

`SimBot` is the in-memory `KinematicBot` (FarmBot's motion profile on a simulated clock)
whose camera is `SimCamera`. The camera's pose comes from the MuJoCo model
(`assets/farmbot/scene.xml`) at the joint positions the bot takes. While recording, the
camera takes frames on a fixed grid of the bot's clock, `frame_rate_hz` of the real 30 fps
video. Each frame's state is known exactly: the gantry on its motion profile, the head
turning at servo speed, the image's speed (motion blur) and the time since the camera
stopped (defocus while the autofocus settles). At the end of every pause the frames so far
are rendered in a process pool with pyrender, given the sensor model's imperfections and
appended to `frames/`, `trajectory.csv` and `frames_truth.csv` (the blur and noise each
frame got), before the executor records the waypoint as done: an interrupted scan keeps
every frame written and resumes at the next waypoint. What each settled waypoint's camera
sees of every flower (its rendered instance mask) is merged into `visibility.json`.

This is the one module of `hardware` that imports `sim`.
"""

from __future__ import annotations

import os

# Headless rendering (MuJoCo's preview, pyrender's frames) unless the user chose otherwise.
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import contextlib  # noqa: E402
import functools  # noqa: E402
import math
import multiprocessing
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from flowerpose.atomic import write_bytes, write_file
from flowerpose.errors import InputError
from flowerpose.hardware.backends.sim_camera import SimCameraConfig
from flowerpose.hardware.bot import Activity, BotInfo, Camera, Frame, KinematicBot, Recording
from flowerpose.hardware.bot_errors import CameraError
from flowerpose.hardware.geometry import FARMBOT_ASSETS
from flowerpose.hardware.kinematics import HeadPose, joint_positions
from flowerpose.hardware.motion import move_duration
from flowerpose.hardware.trajectory import (
    head_turn_time,
    last_recorded,
    pose_at,
)
from flowerpose.jsonio import read_json, write_json
from flowerpose.log import LOG
from flowerpose.processes import quiet_worker
from flowerpose.scanio import (
    FRAME_PATTERN,
    TRAJECTORY_COLUMNS,
    Intrinsics,
    open_rows,
    trajectory_row,
)
from flowerpose.sim.render_config import RenderConfig
from flowerpose.sim.sensor import SensorConfig
from flowerpose.sim.visibility import VISIBLE_SHARE, petal_samples, seen_in_render
from flowerpose.stopwatch import Stopwatch

TRUTH_COLUMNS = ("frame", "t", "speed_px_s", "since_stop_s", "motion_blur_px", "defocus_px",
                 "noise_sigma", "sharpness")
"""frames_truth.csv: what the simulator did to each frame (pixels, seconds; sharpness: the
share of fine detail the blur kept, `sim.sensor.SensorRecord.sharpness`)."""


class MujocoPoser:
    """Camera poses from the MuJoCo model of the bot."""

    def __init__(self, scene: Path = FARMBOT_ASSETS / "scene.xml"):
        import mujoco

        self._mujoco = mujoco
        self.model = mujoco.MjModel.from_xml_path(str(scene))
        self.data = mujoco.MjData(self.model)
        self._camera = self.model.camera("camera").id

    def camera_to_bed(self, gantry: np.ndarray, yaw: float, pitch: float) -> np.ndarray:
        """(4, 4) camera-to-bed, OpenCV axes, of the head at (gantry, yaw, pitch), bed frame,
        metres and radians (the servos' flip applied as the real head takes it)."""
        self.data.qpos[:] = joint_positions(HeadPose(gantry, yaw, pitch))
        self._mujoco.mj_kinematics(self.model, self.data)
        self._mujoco.mj_camlight(self.model, self.data)
        pose = np.eye(4)
        pose[:3, 3] = self.data.cam_xpos[self._camera]
        # MuJoCo's camera looks along its -z with +y up; OpenCV's looks along +z, y down.
        pose[:3, :3] = self.data.cam_xmat[self._camera].reshape(3, 3) @ np.diag([1, -1, -1])
        return pose


@dataclass(frozen=True)
class FrameTask:
    """One frame to render: its index, time and pose, and its sensor state."""

    index: int
    t: float
    gantry: np.ndarray
    yaw: float
    pitch: float
    camera_to_bed: np.ndarray
    speed_px_s: np.ndarray
    """(2,) image-plane velocity, pixels per second."""
    since_stop_s: float
    """Seconds since the image stopped moving (0 while moving)."""


# Render workers: one renderer per process, built once from the plant folders.
_worker: dict = {}


def _init_worker(plant_dirs: list[str], intrinsics: dict, visibility_width: int,
                 samples: int, seed: int, render: RenderConfig) -> None:
    from flowerpose.sim.export import read_plant
    from flowerpose.sim.render import PlantRenderer

    # Ctrl-C reaches the whole process group: the scan's own process stops the scan, and
    # the renderers finish the frames it still asks for instead of dying mid-batch.
    quiet_worker()
    plants = [read_plant(d) for d in plant_dirs]
    _worker["renderer"] = PlantRenderer(plants, render)
    _worker["intrinsics"] = Intrinsics(**{k: intrinsics[k] for k in
                                          ("width", "height", "fx", "fy", "cx", "cy", "fps")})
    width = visibility_width
    height = round(width * intrinsics["height"] / intrinsics["width"])
    _worker["small"] = _worker["intrinsics"].scaled(width, height)
    _worker["petals"] = petal_samples(plants, _worker["renderer"].instance_id, samples, seed)


def _render_frame(task: FrameTask, frames_dir: str, sensor_seed: int,
                  sensor: SensorConfig) -> dict:
    import cv2

    from flowerpose.sim.render import Output
    from flowerpose.sim.sensor import apply_sensor

    rgb = _worker["renderer"].render(task.camera_to_bed, _worker["intrinsics"], Output.RGB).rgb
    rng = np.random.default_rng([sensor_seed, task.index])
    # The stored JPEG is the camera's compression: apply_sensor stops before it.
    image, record = apply_sensor(rgb, task.speed_px_s, task.since_stop_s,
                                 replace(sensor, jpeg_quality=None), rng)
    ok, jpeg = cv2.imencode(".jpg", cv2.cvtColor(image, cv2.COLOR_RGB2BGR),
                            [cv2.IMWRITE_JPEG_QUALITY, int(sensor.jpeg_quality or 95)])
    if not ok:
        raise CameraError(f"frame {task.index}: JPEG encoding failed")
    write_bytes(Path(frames_dir) / FRAME_PATTERN.format(task.index), jpeg.tobytes())
    return {"motion_blur_px": record.motion_blur_px, "defocus_px": record.defocus_px,
            "noise_sigma": record.noise_sigma_dn, "sharpness": record.sharpness}


def _visible_fractions(camera_to_bed: np.ndarray) -> dict[int, float]:
    """Per flower instance, the share of its petal samples this camera sees."""
    from flowerpose.sim.render import Output

    small = _worker["small"]
    out = _worker["renderer"].render(camera_to_bed, small, Output.INSTANCE | Output.DEPTH)
    return seen_in_render(out.instance, out.depth, camera_to_bed, small, _worker["petals"])


#: The noise stream of the stills (`SimCamera.frame`), apart from each video frame's own.
STILL_STREAM = 1


class SimCamera(Camera):
    """The simulated IMX219 on the head: see the module docstring."""

    def __init__(self, clock, plant_dirs: list[Path], intrinsics: Intrinsics,
                 poser: MujocoPoser, config: SimCameraConfig, state,
                 pause: Callable[[], contextlib.AbstractContextManager] = contextlib.nullcontext):
        self._clock = clock
        self._pause = pause
        self._plant_dirs = [str(p) for p in plant_dirs]
        self._intrinsics = intrinsics
        self._poser = poser
        self.config = config
        self._state = state  # () -> (gantry, yaw, pitch) now
        self._scan_dir: Path | None = None
        self._writer: _FrameWriter | None = None
        self._tasks: list[FrameTask] = []
        self._written = 0
        self._still_since = 0.0
        self._next_index = 0
        self._start = 0.0
        self._renderer = None  # the stills' renderer, made at the first still
        self._stills = 0

    def intrinsics(self) -> dict[str, float]:
        return self._intrinsics.to_json()

    def frame(self) -> Frame:
        """A still from the video stream: rendered where the head is, with the sensor's
        imperfections for the time since the camera stopped (its defocus), noise and the
        stream's JPEG compression, as a recorded frame gets them."""
        from flowerpose.sim.export import read_plant
        from flowerpose.sim.render import Output, PlantRenderer
        from flowerpose.sim.sensor import apply_sensor

        if self._renderer is None:
            self._renderer = PlantRenderer([read_plant(d) for d in self._plant_dirs],
                                           self.config.render)
        gantry, yaw, pitch = self._state()
        pose = self._poser.camera_to_bed(gantry, yaw, pitch)
        with self._pause():  # rendering takes none of the bot's time
            rgb = self._renderer.render(pose, self._intrinsics, Output.RGB).rgb
            # Stills draw their noise from a stream of their own, apart from the video's.
            rng = np.random.default_rng([self.config.seed, STILL_STREAM, self._stills])
            image, _ = apply_sensor(rgb, np.zeros(2), self._clock() - self._still_since,
                                    self.config.sensor, rng)
        self._stills += 1
        return Frame(image, self._clock())

    def start_recording(self, path: str | Path) -> None:
        if self._scan_dir is not None:
            raise CameraError(f"{path}: already recording; stop that recording first")
        scan_dir = Path(path).parent
        (scan_dir / "frames").mkdir(parents=True, exist_ok=True)
        self._next_index, last_t = last_recorded(scan_dir)
        self._tasks, self._written, self._start = [], 0, self._clock()
        self._still_since = self._clock()
        # Times count from the scan's start, and a resumed scan's continue the recorded ones
        # (the new bot's clock restarts), whatever the bot did before it recorded (a serial
        # bot homes first).
        self._time_offset = (0.0 if last_t is None else last_t + 1.0 / 30.0) - self._start
        self._writer = _FrameWriter(scan_dir, self._plant_dirs, self._intrinsics, self.config)
        self._scan_dir = scan_dir

    def _pose_state(self, activity: Activity, t: float) -> tuple[np.ndarray, float, float]:
        """(gantry, yaw, pitch) at bot time t within `activity`."""
        gantry, yaw, pitch = pose_at(activity, [t], self.config.servo_speed_rad_s)
        return gantry[0], float(yaw[0]), float(pitch[0])

    def _image_speed(self, activity: Activity, t: float, pose: np.ndarray) -> np.ndarray:
        """(2,) pixels per second the image moves at time t (finite difference)."""
        from flowerpose.sim.sensor import image_velocity

        dt = self.config.velocity_dt_s
        later = self._poser.camera_to_bed(*self._pose_state(activity, t + dt))
        return image_velocity(pose, later, dt, self._intrinsics, self.config.image_depth_m)

    def observe(self, activity: Activity) -> None:
        """Schedule the frames the camera takes during `activity` (bot clock seconds); not
        recording, only note when the camera last stopped (a still's defocus)."""
        end = activity.t0 + activity.elapsed
        moving_until = activity.t0
        if activity.kind == "move" and np.any(activity.gantry_start != activity.gantry_end):
            # The motors stop before the move's end (END_OF_MOVE_S at the target).
            moving_until = end if activity.profile is None else min(end, activity.t0 + (
                move_duration(activity.gantry_start, activity.gantry_end, activity.profile)))
        elif activity.kind == "head":
            moving_until = activity.t0 + head_turn_time(activity,
                                                        self.config.servo_speed_rad_s)
        if self._scan_dir is None:
            self._still_since = max(self._still_since, moving_until)
            return
        rate = self.config.frame_rate_hz
        # Frames on a grid from the recording's start, the same for every backend.
        first = math.ceil((activity.t0 - self._start) * rate - 1e-9)
        times = [self._start + k / rate
                 for k in range(first, math.ceil((end - self._start) * rate - 1e-9))]
        video_frame = 1.0 / 30.0
        if activity.kind == "dwell" and activity.elapsed > video_frame and (
                not times or times[-1] < end - 2 * video_frame):
            # The last video frame of each pause: the settled view the pause exists for.
            times.append(end - video_frame)
        for t in times:
            gantry, yaw, pitch = self._pose_state(activity, t)
            pose = self._poser.camera_to_bed(gantry, yaw, pitch)
            moving = t < moving_until
            speed = self._image_speed(activity, t, pose) if moving else np.zeros(2)
            since = 0.0 if moving else t - max(self._still_since, moving_until)
            self._tasks.append(FrameTask(self._next_index + len(self._tasks),
                                         t + self._time_offset, gantry, yaw, pitch, pose, speed,
                                         since))
        if moving_until > activity.t0:
            self._still_since = moving_until
        if activity.kind == "dwell" and activity.elapsed > 0:
            # Render this waypoint's frames before the executor records it as done, so what
            # scan.json calls complete is on disk.
            settled = self._poser.camera_to_bed(*self._pose_state(activity, end))
            with self._pause():  # rendering takes none of the bot's time
                self._written += self._writer.write(self._tasks, settled)
            self._next_index += len(self._tasks)
            self._tasks = []

    def stop_recording(self) -> Recording:
        if self._scan_dir is None:
            raise CameraError("stop_recording: not recording; start a recording first")
        scan_dir, writer, tasks = self._scan_dir, self._writer, self._tasks
        self._scan_dir, self._tasks = None, []
        try:
            self._written += writer.write(tasks, None) if tasks else 0
        finally:
            writer.close()
        return Recording(scan_dir / "frames", self._start, self._clock(),
                         self.config.frame_rate_hz, self._written)


class _FrameWriter:
    """Renders frames in a process pool and appends them, in order, to the scan folder:
    each image is written before its trajectory.csv row, so an interruption leaves rows only
    for frames on disk."""

    def __init__(self, scan_dir: Path, plant_dirs: list[str], intrinsics: Intrinsics,
                 config: SimCameraConfig):
        self.scan_dir = scan_dir
        init = (plant_dirs, intrinsics.to_json(), config.visibility_width,
                config.visibility_samples, config.seed, config.render)
        self._pool = ProcessPoolExecutor(config.workers or os.cpu_count() or 1,
                                         mp_context=multiprocessing.get_context("spawn"),
                                         initializer=_init_worker, initargs=init)
        self._trajectory_file, self._trajectory = open_rows(scan_dir / "trajectory.csv",
                                                            TRAJECTORY_COLUMNS)
        self._truth_file, self._truth = open_rows(scan_dir / "frames_truth.csv", TRUTH_COLUMNS)
        # Frames below this index have their rows: a batch an interruption cut short is
        # offered again when the recording stops, and its written part is skipped.
        self._next_row = last_recorded(scan_dir)[0]
        self._render = functools.partial(_render_frame, frames_dir=str(scan_dir / "frames"),
                                         sensor_seed=config.seed, sensor=config.sensor)
        self._watch, self._count = Stopwatch(), 0

    def write(self, tasks: list[FrameTask], settled: np.ndarray | None) -> int:
        """Render and append `tasks`; with a settled camera pose, also merge what it sees
        into visibility.json. Returns the number of frames written."""
        visibility = self._pool.submit(_visible_fractions, settled) if settled is not None \
            else None
        tasks = [task for task in tasks if task.index >= self._next_row]
        for task, record in zip(tasks, self._pool.map(self._render, tasks), strict=True):
            self._trajectory.writerow(trajectory_row(task.index, task.t, task.gantry, task.yaw,
                                                     task.pitch, task.camera_to_bed[:3, 3],
                                                     task.camera_to_bed[:3, :3]))
            self._truth.writerow([task.index, f"{task.t:.6f}",
                                  f"{float(np.linalg.norm(task.speed_px_s)):.3f}",
                                  f"{task.since_stop_s:.6f}", f"{record['motion_blur_px']:.4f}",
                                  f"{record['defocus_px']:.4f}", f"{record['noise_sigma']:.4f}",
                                  f"{record['sharpness']:.6f}"])
            self._trajectory_file.flush()
            self._truth_file.flush()
            self._next_row = task.index + 1
            self._count += 1
            if self._count % 100 == 0:
                LOG.info(f"scan: rendered {self._count} frames "
                         f"({self._watch.elapsed():.0f} s)")
        if visibility is not None:
            _merge_visibility(self.scan_dir / "visibility.json", [visibility.result()])
        return len(tasks)

    def close(self) -> None:
        self._pool.shutdown(cancel_futures=True)
        self._trajectory_file.close()
        self._truth_file.close()


def _merge_visibility(path: Path, fractions: list[dict[int, float]]) -> None:
    """Keep, per flower, the largest share of its petals seen from any settled waypoint,
    merged with an earlier session's (a resumed scan)."""

    best: dict[str, float] = {}
    if path.exists():
        best = {str(k): float(v) for k, v in read_json(path).get("fraction", {}).items()}
    for per_pose in fractions:
        for instance, value in per_pose.items():
            best[str(instance)] = max(best.get(str(instance), 0.0), value)
    write_json(path, {"rule": "visible: at least half of the petal samples seen (own instance "
                      "mask, rendered depth) from one settled waypoint",
                      "fraction": best,
                      "visible": {k: v >= VISIBLE_SHARE for k, v in best.items()}})


@dataclass(frozen=True)
class SimBotConfig:
    """The simulated bot: its camera and head."""

    camera: SimCameraConfig = field(default_factory=SimCameraConfig)
    head_settle_s: float = 0.5
    """Seconds `set_head` takes (the servos turn, then settle)."""


def sim_camera(plant_dirs: list[Path], config: SimBotConfig,
               state: Callable[[], tuple[np.ndarray, float, float]],
               pause: Callable[[], contextlib.AbstractContextManager] = contextlib.nullcontext,
               ) -> Callable[[Callable[[], float]], SimCamera]:
    """A bot's camera factory (it takes the bot's clock) making `SimCamera`s that film the
    plants in `plant_dirs` (checked now) as `config` says. state: () -> (gantry (3,)
    metres bed frame, yaw, pitch radians) now. The bot's observer must hand every
    Activity to `camera.observe`."""
    from flowerpose.sim.camera import CameraConfig, intrinsics_from_config

    for folder in plant_dirs:
        if not (Path(folder) / "plant.json").exists():
            raise InputError(folder, "not a plant folder (no plant.json): make one with "
                             "flowerpose plant")
    intrinsics = intrinsics_from_config(CameraConfig(width=config.camera.width,
                                                     height=config.camera.height))
    poser = MujocoPoser()
    return lambda clock: SimCamera(clock, plant_dirs, intrinsics, poser, config.camera, state,
                                   pause)


class SimBot(KinematicBot):
    """The simulated FarmBot: `KinematicBot` timing, MuJoCo's camera pose, rendered frames."""

    def __init__(self, plant_dirs: list[Path], config: SimBotConfig = SimBotConfig(),
                 observer: Callable[[Activity], None] | None = None):
        """observer: also told of every Activity, after the camera (a flight's timeline)."""
        self.sim_config = config

        def observe(activity: Activity) -> None:
            self.camera.observe(activity)
            if observer is not None:
                observer(activity)

        super().__init__(BotInfo.from_geometry("simulated (MuJoCo)"),
                         head_settle_s=config.head_settle_s,
                         camera=sim_camera(plant_dirs, config, self._current),
                         observer=observe)

    def _current(self) -> tuple[np.ndarray, float, float]:
        yaw, pitch = self.head()
        return self.position(), yaw, pitch

    def describe(self) -> dict:
        """The backend's settings, for scan.json."""
        return {"backend": "sim", **asdict(self.sim_config)}


def write_preview(scan_dir: Path, plant_centers: list[np.ndarray], plant_heights: list[float],
                  width: int = 640, height: int = 360, fps: float = 15.0,
                  max_frames: int = 300) -> Path:
    """preview.mp4: MuJoCo's view of the gantry scanning, from outside the bed, at most
    `max_frames` frames spread over trajectory.csv; each plant stands in as a green
    ellipsoid. Shadows and reflections are off: on a CPU they triple the time."""
    import cv2
    import mujoco

    from flowerpose.scanio import read_trajectory

    trajectory = read_trajectory(scan_dir / "trajectory.csv")
    spec = mujoco.MjSpec.from_file(str(FARMBOT_ASSETS / "scene.xml"))
    for center, plant_height in zip(plant_centers, plant_heights, strict=True):
        geom = spec.worldbody.add_geom()
        geom.type = mujoco.mjtGeom.mjGEOM_ELLIPSOID
        geom.size = [0.19, 0.19, plant_height / 2]
        geom.pos = [center[0], center[1], plant_height / 2]
        geom.rgba = [0.25, 0.6, 0.2, 1.0]
        geom.contype = geom.conaffinity = 0
    model = spec.compile()
    data = mujoco.MjData(model)
    renderer = mujoco.Renderer(model, height, width)
    options = mujoco.MjvOption()
    view = mujoco.MjvCamera()
    view.lookat[:] = [*plant_centers[0][:2], 0.3]
    view.distance, view.azimuth, view.elevation = 1.8, 235.0, -22.0
    qpos = joint_positions(HeadPose(trajectory.gantry, trajectory.head[:, 0],
                                    trajectory.head[:, 1]))

    def film(path: Path) -> bool:
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps,
                                 (width, height))
        if not writer.isOpened():
            return False
        try:
            for k in np.unique(np.linspace(0, len(trajectory) - 1,
                                           max_frames).round().astype(int)):
                data.qpos[:] = qpos[k]
                mujoco.mj_kinematics(model, data)
                renderer.update_scene(data, camera=view, scene_option=options)
                renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
                renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = False
                writer.write(np.ascontiguousarray(renderer.render()[:, :, ::-1]))
        finally:
            writer.release()
        return True

    try:
        return write_file(scan_dir / "preview.mp4", film)
    finally:
        renderer.close()
