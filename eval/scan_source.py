"""The photogrammetry source: the simulated bot films the plant along its planned scan, the
sharpest frames are chosen, and pycolmap plus dense stereo turn them into the cloud the
pipeline gets; the cloud is measured against the truth mesh on the way.

Per plant folder:  scan/ (`flowerpose scan --sim`, its plant.json has the scan's
visibility), frames/ (`flowerpose frames`), reconstruction/ (`flowerpose reconstruct`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from flowerpose.cache import StageCache
from flowerpose.config import require, to_dict
from flowerpose.eval.runner import CAPTURE_CPUS, run_jobs, said_steps
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


def capture_scan(plant_dir: Path, config: ScanSourceConfig,
                 path: ScanPathConfig | None = None) -> dict:
    """Scan, choose frames and reconstruct the plant in plant_dir; returns the frame and
    point counts, the cloud's quality against the truth mesh (with the alignment residual)
    and seconds per step. The cloud is plant_dir/reconstruction/cloud.ply, the truth with
    the scan's visibility plant_dir/scan/plant.json."""
    scanned = scan_and_choose(plant_dir, config, path)
    built = reconstruct_capture(plant_dir, config)
    return {**scanned, **built, "seconds": {**scanned["seconds"], **built["seconds"]}}


def scan_and_choose(plant_dir: Path, config: ScanSourceConfig,
                    path: ScanPathConfig | None = None) -> dict:
    """The capture's first steps: film the plant in plant_dir (plant_dir/scan) and choose
    its frames (plant_dir/frames). Returns the frames recorded and chosen, and seconds."""
    from flowerpose.hardware.flights.scan_plan import plan_plant_scan
    from flowerpose.pipeline.frames import select_frames
    from flowerpose.sim.export import plant_obstacles, read_plant

    watch = Stopwatch()
    scan_dir = plant_dir / "scan"
    plant = read_plant(plant_dir)
    manifest = scan_plant(plant_dir, scan_dir, config, plan_plant_scan(
        plant.center[:2], plant.height, plant_obstacles(plant), path))
    watch.lap("scan")
    chosen = select_frames(scan_dir, plant_dir / "frames", config.frames, progress=False)
    watch.lap("frames")
    return {"recorded": sum(s.get("frames", 0) for s in manifest["sessions"]),
            "frames": len(chosen["frames"]), "seconds": watch.report(digits=3, total=None)}


def reconstruct_capture(plant_dir: Path, config: ScanSourceConfig) -> dict:
    """The capture's last step: reconstruct plant_dir/frames into plant_dir/reconstruction
    and measure the cloud against the truth mesh. Returns the registered images, the
    points, the quality and seconds."""
    from flowerpose.eval.quality import reconstruction_quality
    from flowerpose.pipeline.reconstruct import reconstruct
    from flowerpose.sim.export import read_plant

    watch = Stopwatch()
    result = reconstruct(plant_dir / "frames", plant_dir / "reconstruction", config.reconstruct,
                         progress=False)
    watch.lap("reconstruct")
    plant = read_plant(plant_dir)
    quality = reconstruction_quality(result.cloud.points, plant.mesh, plant.face_part,
                                     samples=100_000)
    report = result.report
    quality.update(alignment_rms_m=report["alignment_rms_m"],
                   images_registered=report["images_registered"],
                   images_used=report["images_used"], points=report["points"])
    return {"registered": report["images_registered"], "points": report["points"],
            "quality": quality, "seconds": watch.report(digits=3, total=None)}


#: What the stage cache keeps of a plant's scan and frame choice: the chosen frames as
#: `flowerpose frames` wrote them (a reconstruction can be run again from them) and what
#: later steps read (the truth with the scan's visibility, the trajectory). The scan's
#: other recorded frames stay out of it: about 50 MB a plant, needed only to choose frames
#: again, which a changed frame choice does by scanning again.
SCAN_FILES = ("scan/plant.json", "scan/scan.json", "scan/camera.json", "scan/trajectory.csv",
              "frames")
#: What it keeps of a reconstruction of those frames: the cloud and its report.
RECONSTRUCTION_FILES = ("reconstruction/cloud.ply", "reconstruction/reconstruction.json")


#: The code a capture runs (the stage cache's code version): this module and what it imports,
#: the simulator, the bot, frame choice and photogrammetry, not the detection.
CAPTURE_CODE = (__name__,)


def plant_inputs(plant_dir: Path) -> list[Path]:
    """The files of a generated plant that a capture of it depends on (its truth, mesh and
    face labels; not its oracle cloud): the stage cache's inputs."""
    return [plant_dir / name for name in ("plant.json", "plant.ply", "plant_labels.npz")]


def capture_scan_cached(plant_dir: Path, config: ScanSourceConfig,
                        path: ScanPathConfig | None = None,
                        cache_root: Path | None = None) -> dict:
    """`capture_scan`, each of its two parts taken from the stage cache at cache_root when
    it ran before on the same plant files, settings and code (None: no cache). The scan and
    frame choice are one entry, keyed by the camera, path and frame count; the
    reconstruction another, keyed by the first's key and the reconstruction's settings, so
    a sweep over reconstruction settings films each plant once. "cached" names the steps
    taken from the cache (of "scan", "frames", "reconstruct"); their seconds are this run's
    (none)."""
    if cache_root is None:
        return capture_scan(plant_dir, config, path)
    cache = StageCache(cache_root)
    camera = {k: v for k, v in to_dict(config).items() if k != "reconstruct"}
    camera["camera"].pop("workers")  # how many render processes changes no frame
    scan_settings = {"scan": camera, "viewpoints": to_dict(path or ScanPathConfig())}
    scanned, scan_cached, scan_key = cache.run(
        "scan", scan_settings, plant_inputs(plant_dir), plant_dir, SCAN_FILES,
        lambda: scan_and_choose(plant_dir, config, path), code=CAPTURE_CODE)
    built, built_cached, _ = cache.run(
        "reconstruct", {"reconstruct": to_dict(config.reconstruct)}, [], plant_dir,
        RECONSTRUCTION_FILES, lambda: reconstruct_capture(plant_dir, config),
        parents=[scan_key], code=CAPTURE_CODE)
    seconds = {**scanned["seconds"], **built["seconds"]}
    cached = [step for step, hit in (("scan", scan_cached), ("frames", scan_cached),
                                     ("reconstruct", built_cached)) if hit]
    seconds.update(dict.fromkeys(cached, 0.0))
    return {**scanned, **built, "seconds": seconds, "cached": cached}


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
