"""The RGB-D source: a depth camera on the same head films the plant from every settled
waypoint of the planned scan, and the frames are fused into the cloud the pipeline gets.

The simulator renders colour and depth aligned, at the pose MuJoCo gives the head, adds the
colour sensor's noise and compression (the camera is at rest) and the depth sensor's error
model (`sim.depth`), and writes an RGB-D scan folder (`pipeline.rgbd`). Visibility truth
comes from the same views' rendered instance masks.
"""

from __future__ import annotations

import csv
import dataclasses
import io
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from flowerpose.atomic import write_image, write_text
from flowerpose.config import require, to_dict
from flowerpose.eval.capture.scan_source import plant_inputs
from flowerpose.eval.pool import CAPTURE_CPUS, run_jobs, said_steps
from flowerpose.jsonio import read_json, write_json
from flowerpose.pipeline.rgbd import FusionConfig, fuse_rgbd_scan
from flowerpose.scan_geometry import ScanPathConfig
from flowerpose.scanio import FRAME_PATTERN, TRAJECTORY_COLUMNS, trajectory_row
from flowerpose.sim.depth import DepthSensorConfig
from flowerpose.stopwatch import Stopwatch


@dataclass(frozen=True)
class RgbdConfig:
    """The simulated RGB-D scan."""

    width: int = 640
    """Image width of the aligned colour and depth, pixels (an RGB-D camera's depth
    stream; the head's 62.2 degree field of view)."""
    height: int = 360
    """Image height, pixels."""
    depth: DepthSensorConfig = field(default_factory=DepthSensorConfig)
    seed: int = 0
    """Seed of the sensor noise."""

    def __post_init__(self):
        require(self.width >= 16 and self.height >= 16, "rgbd.width",
                "width and height must be at least 16 pixels")


def record_rgbd_scan(plant_dir: Path, out_dir: Path, config: RgbdConfig,
                     viewpoints: ScanPathConfig | None = None) -> dict:
    """Film the plant in plant_dir at every waypoint of its planned scan (`viewpoints`, the
    synthetic world's path, or the default); write an RGB-D scan folder to out_dir (frames/,
    depth/, trajectory.csv, camera.json, plant.json with the views' visibility). Returns a
    small report."""
    from flowerpose.hardware.backends.sim_bot import MujocoPoser
    from flowerpose.hardware.flights.scan_plan import plan_plant_scan
    from flowerpose.pipeline.rgbd import DEPTH_PATTERN
    from flowerpose.sim.camera import CameraConfig, intrinsics_from_config
    from flowerpose.sim.depth import apply_depth_sensor
    from flowerpose.sim.export import plant_obstacles, read_plant
    from flowerpose.sim.render import Output, PlantRenderer
    from flowerpose.sim.sensor import SensorConfig, apply_sensor
    from flowerpose.sim.visibility import VISIBLE_SHARE, petal_samples, seen_in_render

    plant = read_plant(plant_dir)
    plan = plan_plant_scan(plant.center[:2], plant.height, plant_obstacles(plant), viewpoints)
    poser = MujocoPoser()
    intrinsics = intrinsics_from_config(CameraConfig(width=config.width, height=config.height))
    renderer = PlantRenderer([plant])
    petals = petal_samples([plant], renderer.instance_id, seed=config.seed)
    (out_dir / "frames").mkdir(parents=True, exist_ok=True)
    (out_dir / "depth").mkdir(parents=True, exist_ok=True)
    best = {flower: 0.0 for flower, _ in petals}
    rows = []
    unit = config.depth.unit_m
    for k, waypoint in enumerate(plan.waypoints):
        pose = poser.camera_to_bed(waypoint.pose.gantry, float(waypoint.pose.yaw),
                                   float(waypoint.pose.pitch))
        out = renderer.render(pose, intrinsics, Output.ALL)
        rng = np.random.default_rng([config.seed, k])
        colour, _ = apply_sensor(out.rgb, np.zeros(2), 3.0, SensorConfig(), rng)
        depth = apply_depth_sensor(out.depth, config.depth, rng)
        write_image(out_dir / "frames" / FRAME_PATTERN.format(k), colour,
                    [cv2.IMWRITE_JPEG_QUALITY, 95])
        write_image(out_dir / "depth" / DEPTH_PATTERN.format(k),
                    np.round(depth / unit).astype(np.uint16))
        for flower, share in seen_in_render(out.instance, out.depth, pose, intrinsics,
                                            petals).items():
            best[flower] = max(best[flower], share)
        rows.append(trajectory_row(k, k * plan.config.pause_s, waypoint.pose.gantry,
                                   float(waypoint.pose.yaw), float(waypoint.pose.pitch),
                                   pose[:3, 3], pose[:3, :3]))
    renderer.close()
    table = io.StringIO()
    csv.writer(table).writerows([TRAJECTORY_COLUMNS, *rows])
    write_text(out_dir / "trajectory.csv", table.getvalue())
    write_json(out_dir / "camera.json", {**intrinsics.to_json(), "depth_unit_m": unit})
    truth = read_json(plant_dir / "plant.json")
    for flower in truth["flowers"]:
        share = best.get(renderer.instance_id(0, flower["id"]), 0.0)
        flower["visible"], flower["visible_fraction"] = bool(share >= VISIBLE_SHARE), share
    truth["visibility"] = "rgbd scan"
    write_json(out_dir / "plant.json", truth)
    write_json(out_dir / "scan.json", {"version": 1, "source": {
        "backend": "sim rgbd", **dataclasses.asdict(config)}, "plan": plan.to_json(),
        "waypoints": len(rows), "completed": len(rows), "status": "complete"})
    return {"frames": len(rows)}


def capture_rgbd_cached(plant_dir: Path, config: RgbdConfig, fusion: FusionConfig,
                        viewpoints: ScanPathConfig, cache_root: Path | None) -> dict:
    """`capture_rgbd`, or its earlier result for the same plant files, settings and code from
    the stage cache at cache_root (None: no cache), its cloud and truth copied back."""
    if cache_root is None:
        return capture_rgbd(plant_dir, config, fusion, viewpoints)
    from flowerpose.cache import StageCache

    settings = {"rgbd": to_dict(config), "fusion": to_dict(fusion),
                "viewpoints": to_dict(viewpoints)}
    result, cached, _ = StageCache(cache_root).run(
        "rgbd", settings, plant_inputs(plant_dir), plant_dir, ("rgbd/cloud.ply", "rgbd/plant.json"),
        lambda: capture_rgbd(plant_dir, config, fusion, viewpoints), code=(__name__,))
    return {**result, "cached": ["rgbd"], "seconds": 0.0} if cached else result


def capture_rgbd(plant_dir: Path, config: RgbdConfig, fusion: FusionConfig,
                 viewpoints: ScanPathConfig) -> dict:
    """The RGB-D source for one plant: record plant_dir/rgbd/ (`record_rgbd_scan`), fuse it
    into plant_dir/rgbd/cloud.ply, and measure the cloud against the truth mesh."""
    from flowerpose.cloudio import write_cloud
    from flowerpose.eval.capture.quality import reconstruction_quality
    from flowerpose.sim.export import read_plant

    watch = Stopwatch()
    scan_dir = plant_dir / "rgbd"
    recorded = record_rgbd_scan(plant_dir, scan_dir, config, viewpoints)
    cloud, fused = fuse_rgbd_scan(scan_dir, fusion)
    write_cloud(scan_dir / "cloud.ply", cloud)
    plant = read_plant(plant_dir)
    quality = reconstruction_quality(cloud.points, plant.mesh, plant.face_part, samples=100_000)
    return {"frames": recorded["frames"], "points": fused["points"], "quality": quality,
            "seconds": watch.elapsed()}


def capture_rgbd_clouds(config: RgbdConfig, fusion: FusionConfig, viewpoints: ScanPathConfig,
                        folders: dict[int, Path], workers: int | None,
                        cache: Path | None = None
                        ) -> tuple[dict[int, tuple[Path, Path]], dict[str, float], list[dict]]:
    """The RGB-D source for generated plants (seed -> folder), filmed with `config` at the
    waypoints `viewpoints` plans and fused by `fusion` (`capture_rgbd_cached`). Returns
    (seed -> (cloud, truth)), seconds per stage, and each plant's capture report."""
    seeds = list(folders)
    captured = run_jobs(capture_rgbd_cached, [(folders[s], config, fusion, viewpoints, cache)
                                              for s in seeds],
                        workers,
                        lambda k, v: f"seed-{seeds[k]}: RGB-D scan of {v['frames']} views "
                        f"fused into {v['points']} points "
                        + said_steps({"rgbd": v["seconds"]}, v.get("cached", [])),
                        stage="RGB-D capture", labels=[f"seed-{s}" for s in seeds],
                        cpus=CAPTURE_CPUS)
    clouds = {s: (folders[s] / "rgbd" / "cloud.ply", folders[s] / "rgbd" / "plant.json")
              for s in seeds}
    return clouds, {"rgbd": round(sum(c["seconds"] for c in captured), 4)}, captured
