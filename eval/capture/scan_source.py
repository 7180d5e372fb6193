"""The photogrammetry source: the simulated bot films the plant along its planned scan, the
sharpest frames are chosen, and pycolmap plus dense stereo turn them into the cloud the
pipeline gets; the cloud is measured against the truth mesh on the way.

Per plant folder:  scan/ (`flowerpose scan --sim`, its plant.json has the scan's
visibility), frames/ (`flowerpose frames`), reconstruction/ (`flowerpose reconstruct`).
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass, field
from pathlib import Path

from flowerpose.cache import StageCache
from flowerpose.cloudio import read_cloud
from flowerpose.config import require, to_dict
from flowerpose.eval.pool import CAPTURE_CPUS, run_jobs, said_steps
from flowerpose.hardware.backends.sim_camera import SimCameraConfig
from flowerpose.jsonio import read_json, write_json
from flowerpose.pipeline.frames import FrameSelectConfig
from flowerpose.pipeline.reconstruct import ReconstructConfig
from flowerpose.scan_geometry import ScanPathConfig
from flowerpose.stopwatch import Stopwatch

#: Frames the eval's simulated camera renders a second of bot time: half the scan
#: command's (`SimCameraConfig.frame_rate_hz`), about 560 frames of a 20-minute scan, plenty
#: to choose 200 from, in half the rendering.
EVAL_FRAME_RATE_HZ = 0.3


@dataclass(frozen=True)
class ScanSourceConfig:
    """The simulated scan and photogrammetry behind `eval --source scan`: the simulated
    camera, the frames chosen and the reconstruction, each the config of the stage that
    reads it (`flowerpose scan --sim`, `frames`, `reconstruct`)."""

    camera: SimCameraConfig = field(
        default_factory=lambda: SimCameraConfig(frame_rate_hz=EVAL_FRAME_RATE_HZ))
    """The simulated camera's recording: the video's size, frame rate (`EVAL_FRAME_RATE_HZ`
    here), render workers, imperfections (`sensor`) and light (`render`); the field preset's
    sensor gain."""
    frames: FrameSelectConfig = field(default_factory=FrameSelectConfig)
    """How frames are chosen for photogrammetry (`flowerpose frames`)."""
    reconstruct: ReconstructConfig = field(default_factory=ReconstructConfig)
    """Photogrammetry (`flowerpose reconstruct`)."""

    def __post_init__(self):
        require(self.frames.count >= 3, "frames", "photogrammetry needs at least 3 frames "
                "(scan.frames.count)")


def scan_plant(plant_dir: Path, out_dir: Path, config: ScanSourceConfig, plan,
               via_farmduino: bool = False, progress: bool = False) -> dict:
    """The simulated scan, as `flowerpose scan --sim` and `eval --source scan` both run it:
    the simulated bot (through the serial backend and a virtual Farmduino when
    `via_farmduino`) flies `plan` (`scan_plan.plan_plant_scan`) round the plant in plant_dir
    with the camera `config` gives, recording the scan folder out_dir; then out_dir/plant.json
    holds the truth with this scan's own visibility. Returns scan.json's content."""
    from flowerpose.hardware.backends.sim_bot import SimBot, SimBotConfig
    from flowerpose.hardware.flights.scan_flight import run_scan

    bot_config = SimBotConfig(camera=config.camera)
    if via_farmduino:
        from flowerpose.hardware.backends.serial_sim_bot import SimulatedSerialBot

        bot = SimulatedSerialBot([plant_dir], bot_config)
    else:
        bot = SimBot([plant_dir], bot_config)
    with bot:
        manifest = run_scan(bot, plan, out_dir, progress=progress,
                            source={**bot.describe(), "plants": [str(Path(plant_dir).resolve())]})
    write_scan_truth(out_dir, plant_dir)
    return manifest


def write_scan_truth(scan_dir: Path, plant_dir: Path, first_instance: int = 0) -> Path:
    """scan_dir/plant.json: the plant's truth with `visible` and `visible_fraction` from this
    scan's own views (visibility.json: rendered instance masks at every settled waypoint)
    instead of the path's geometry alone. Scores of this scan's clouds use it.
    first_instance: the plant's flower ids' offset in the render (`render.instance_offsets`),
    where the scan filmed it among other plants."""
    truth = read_json(Path(plant_dir) / "plant.json")
    seen = read_json(Path(scan_dir) / "visibility.json")
    for flower in truth["flowers"]:
        key = str(flower["id"] + first_instance)
        flower["visible"] = bool(seen["visible"].get(key, False))
        flower["visible_fraction"] = float(seen["fraction"].get(key, 0.0))
    truth["visibility"] = "scan"
    return write_json(Path(scan_dir) / "plant.json", truth)


def film_plant(plant_dir: Path, config: ScanSourceConfig,
               path: ScanPathConfig | None = None) -> dict:
    """The capture's first step: the simulated bot films the plant in plant_dir along its
    planned scan (plant_dir/scan, its truth with the scan's visibility in scan/plant.json).
    Returns the frames recorded and seconds."""
    from flowerpose.hardware.flights.scan_plan import plan_plant_scan
    from flowerpose.sim.export import plant_obstacles, read_plant

    watch = Stopwatch()
    plant = read_plant(plant_dir)
    manifest = scan_plant(plant_dir, plant_dir / "scan", config, plan_plant_scan(
        plant.center[:2], plant.height, plant_obstacles(plant), path))
    watch.lap("scan")
    return {"recorded": sum(s.get("frames", 0) for s in manifest["sessions"]),
            "seconds": watch.report(digits=3, total=None)}


#: What the stage cache keeps of a plant's simulated scan: what later steps read (the truth
#: with the scan's visibility, the trajectory). The recorded frames stay out of it: about
#: 50 MB a plant, needed only to choose frames again, which films the plant again
#: (`photogrammetry.frames_and_cloud`).
SCAN_FILES = ("scan/plant.json", "scan/scan.json", "scan/camera.json", "scan/trajectory.csv")
#: The code a simulated scan runs (the stage cache's code version): this module and what it
#: imports, the simulator and the bot.
CAPTURE_CODE = (__name__,)


def plant_inputs(plant_dir: Path) -> list[Path]:
    """The files of a generated plant that a capture of it depends on (its truth, mesh and
    face labels; not its oracle cloud): the stage cache's inputs."""
    return [plant_dir / name for name in ("plant.json", "plant.ply", "plant_labels.npz")]


def capture_scan_cached(plant_dir: Path, config: ScanSourceConfig,
                        path: ScanPathConfig | None = None,
                        cache_root: Path | None = None) -> dict:
    """Film the plant in plant_dir, choose its frames and reconstruct them
    (`photogrammetry.frames_and_cloud`, the route every filmed plant takes), each step from
    the stage cache at cache_root where it ran before on the same plant files, settings and
    code (None: no cache): the scan keyed by the camera and path, the frames by the scan,
    the reconstruction by the frames, so a sweep over reconstruction settings films each
    plant once. The cloud (plant_dir/reconstruction/cloud.ply) is measured against the
    truth mesh. Returns the frames recorded and chosen, the images registered, the points,
    the quality (with the alignment residual), seconds per step and, in "cached", the
    steps taken from the cache (their seconds 0)."""
    from flowerpose.eval.capture.photogrammetry import frames_and_cloud

    def film() -> dict:
        return film_plant(plant_dir, config, path)

    def film_again() -> None:
        shutil.rmtree(plant_dir / "scan")  # the cached scan's files, without a recording
        film()

    scan_cached, scan_key = False, None
    if cache_root is None:
        scanned = film()
    else:
        camera = {k: v for k, v in to_dict(config).items() if k not in ("frames", "reconstruct")}
        camera["camera"].pop("workers")  # how many render processes changes no frame
        scan_settings = {"scan": camera, "viewpoints": to_dict(path or ScanPathConfig())}
        scanned, scan_cached, scan_key = StageCache(cache_root).run(
            "scan", scan_settings, plant_inputs(plant_dir), plant_dir, SCAN_FILES, film,
            code=CAPTURE_CODE)
    watch = Stopwatch()
    built, cached = frames_and_cloud(plant_dir, config.frames, config.reconstruct, cache_root,
                                     watch, filmed_by=scan_key,
                                     film_again=film_again if scan_cached else None)
    quality = cloud_quality(plant_dir, built)
    cached = ["scan"] * scan_cached + cached
    seconds = {**scanned["seconds"], **watch.report(digits=3, total=None)}
    seconds.update(dict.fromkeys(cached, 0.0))
    return {"recorded": scanned["recorded"], "frames": built["frames"],
            "registered": built["images_registered"], "points": built["points"],
            "quality": quality, "seconds": seconds, "cached": cached}


def cloud_quality(plant_dir: Path, built: dict) -> dict:
    """plant_dir/reconstruction/cloud.ply measured against the plant's truth mesh, with the
    reconstruction's counts `built` (`photogrammetry.RECONSTRUCTION_COUNTS`) beside."""
    from flowerpose.eval.capture.quality import reconstruction_quality
    from flowerpose.sim.export import read_plant

    plant = read_plant(plant_dir)
    cloud = read_cloud(plant_dir / "reconstruction" / "cloud.ply", units="m")
    quality = reconstruction_quality(cloud.points, plant.mesh, plant.face_part,
                                     samples=100_000)
    quality.update(alignment_rms_m=built["alignment_rms_m"],
                   images_registered=built["images_registered"],
                   images_used=built["images_used"], points=built["points"])
    return quality


#: Whether a scan capture's Ray task asks for a GPU, by `scan.reconstruct.dense_method`:
#: PatchMatch runs only on CUDA; "auto" takes it where the cluster has a GPU.
CAPTURE_GPU = {"patch_match": "needed", "auto": "if_any", "sgbm": "none"}


def capture_scan_clouds(config: ScanSourceConfig, viewpoints: ScanPathConfig,
                        folders: dict[int, Path], workers: int | None,
                        cache: Path | None = None
                        ) -> tuple[dict[int, tuple[Path, Path]], dict[str, float], list[dict]]:
    """The scan source for generated plants (seed -> folder), filmed with `config` along
    the scan path `viewpoints` plans: each filmed and reconstructed
    (`capture_scan_cached`), one plant at a time in the pool (rendering, matching and
    stereo each use every core; on Ray one a node, so a cluster's nodes scan in parallel).
    Returns (seed -> (cloud, truth with the scan's visibility)), seconds per stage, and each
    plant's capture report."""
    seeds = list(folders)
    captured = run_jobs(capture_scan_cached, [(folders[s], config, viewpoints, cache)
                                              for s in seeds], 1,
                        lambda k, v: f"seed-{seeds[k]}: scan of {v['recorded']} frames, "
                        f"{v['registered']}/{v['frames']} chosen frames registered, "
                        f"{v['points']} points, petal F-score at 5 mm "
                        f"{v['quality']['petals']['fscore_5mm']:.2f} "
                        + said_steps(v["seconds"], v.get("cached", [])),
                        stage="scan capture", labels=[f"seed-{s}" for s in seeds],
                        cpus=CAPTURE_CPUS, gpu=CAPTURE_GPU[config.reconstruct.dense_method])
    timing = {stage: round(sum(c["seconds"][stage] for c in captured), 4)
              for stage in ("scan", "frames", "reconstruct")}
    clouds = {s: (folders[s] / "reconstruction" / "cloud.ply", folders[s] / "scan" / "plant.json")
              for s in seeds}
    return clouds, timing, captured
