"""Plants as scored jobs: the one way a set of plants (seeded synthetic plants of a source and
preset, or labelled real folders) becomes typed jobs that `eval`, `sweep`, `stress`,
`tune` and `guard` score, each through the job's own methods.

A synthetic set's plants are generated (`sim.bundle`) and, for the scan and RGB-D sources,
filmed and reconstructed or fused (`scan_source.py`, `rgbd_source.py`), once for each
setting of the sections their clouds depend on (`config.WORLD_SECTIONS`); the stage cache
keeps every capture, so a setting that changes only the pipeline's settings reuses them.
A real folder is read and checked (`real_source.py`). Either job scores the pipeline on its
cloud as it is, or under a seeded perturbation (`Perturbed`: `flowerpose stress`).
"""

from __future__ import annotations

import hashlib
import json
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from flowerpose.cloudio import Cloud, read_cloud
from flowerpose.config import to_dict
from flowerpose.errors import InputError
from flowerpose.eval.capture.detection import detect_cloud
from flowerpose.eval.capture.rgbd_source import capture_rgbd_clouds
from flowerpose.eval.capture.scan_source import capture_scan_clouds
from flowerpose.eval.jobs.config import WORLD_SECTIONS, EvalConfig, pipeline_part
from flowerpose.eval.jobs.plant_set import PlantSet
from flowerpose.eval.pool import run_jobs
from flowerpose.eval.reports.html_report import PlantView
from flowerpose.eval.scoring.match import MAX_MATCH_DISTANCE, plant_entry, score_plant
from flowerpose.eval.scoring.real_source import (
    RealPlant,
    evaluate_real_plant,
    plant_cloud,
    read_plant_clouds,
    real_truth,
)
from flowerpose.eval.scoring.truth import as_labelled, read_plant_truth
from flowerpose.log import noted
from flowerpose.perturb import Perturbation, draw_cuts, perturb
from flowerpose.pipeline.flowers import (
    PipelineConfig,
    Start,
    find_flowers,
    read_flowers,
    write_flowers,
)
from flowerpose.sim.world_config import SimConfig
from flowerpose.stopwatch import Stopwatch


def world_digest(config: EvalConfig, source: str) -> str:
    """A digest of the settings `source`'s plants and clouds depend on (`WORLD_SECTIONS`):
    two configs of one digest share their captures."""
    sections = {name: to_dict(getattr(config, name)) for name in WORLD_SECTIONS[source]}
    return hashlib.sha256(json.dumps(sections, sort_keys=True).encode()).hexdigest()[:12]


@dataclass(frozen=True)
class Perturbed:
    """A perturbation a job's cloud is scored under (`flowerpose stress`): each plant and
    repeat draws its own generator from `seed`, the same on every run."""

    perturbation: Perturbation
    repeat: int = 0
    seed: int = 0

    def rng(self, plant: str) -> np.random.Generator:
        return np.random.default_rng([self.seed, self.repeat, zlib.crc32(plant.encode()),
                                      zlib.crc32(self.perturbation.label.encode())])

    def to_json(self) -> dict:
        return {"perturbation": self.perturbation.to_json(), "repeat": self.repeat,
                "seed": self.seed}


def cut_flowers(truth: list) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """(centre, normal, radius) of the truth flowers a cut acts on: those with a pose (a
    real plant's unlabelled flowers have none); a flower without a radius takes the median
    of the others' (the match distance when none has one)."""
    posed = [t for t in truth if not str(t.id).startswith("unlabelled")]
    radii = [t.radius for t in posed if t.radius]
    fallback = float(np.median(radii)) if radii else MAX_MATCH_DISTANCE
    return [(t.center, t.normal, t.radius or fallback) for t in posed]


def perturbed_real(clouds: list[Cloud], stage: str, perturbation: Perturbation,
                   rng: np.random.Generator, truth: list | None = None
                   ) -> tuple[list[Cloud], tuple[int, ...]]:
    """A real plant's clouds (as `read_plant_clouds` gives them) under a perturbation, and
    the grid views to leave out: candidates thinned file by file, a dropped view one file
    left out (a whole cloud: that grid view's detections), colour and noise on the merged
    points; crops each on its own; a cut of the `truth` flowers the same in every file."""
    p = perturbation
    if p.kind == "cut":
        cuts = draw_cuts(cut_flowers(truth or []), p.value, rng)
        return [perturb(c, p, rng, cuts) for c in clouds], ()
    if p.kind == "drop_view":
        if stage == "cloud":
            return clouds, (int(p.value),)
        if stage == "crops" or int(p.value) >= len(clouds):
            raise InputError("drop_view", f"view {int(p.value)}: the plant has "
                             f"{len(clouds)} {stage} files" if stage == "candidates" else
                             "crops hold one flower each: no view to drop")
        return [c for k, c in enumerate(clouds) if k != int(p.value)], ()
    if p.kind == "thin" or stage != "candidates":
        return [perturb(c, p, rng) for c in clouds], ()
    merged = Cloud(np.concatenate([c.points for c in clouds]),
                   np.concatenate([c.colors for c in clouds]))
    return [perturb(merged.subset(merged.first_copies()), p, rng)], ()


def scored_truth(truth_path: Path, config: EvalConfig, name: str) -> list:
    """A synthetic plant's truth as it is scored: tilted by the hand labels' error where
    `score.label_error_deg` says so (seeded by the plant's name)."""
    truth = read_plant_truth(truth_path)
    if config.score.label_error_deg > 0:
        truth = as_labelled(truth, config.score.label_error_deg, name)
    return truth


@dataclass(frozen=True)
class SyntheticJob:
    """A generated plant to score: its cloud (from the set's source) and its truth."""

    name: str
    cloud: Path
    truth: Path
    source: str = "oracle"
    start: Start = "cloud"
    """Where the pipeline starts on it: the whole cloud."""

    def folder(self, out_dir: Path) -> Path:
        """Where the plant's files and its flowers go in a run's folder."""
        return out_dir / "plants" / self.name

    def scored_truth(self, config: EvalConfig) -> list:
        """The truth as it is scored (`scored_truth`)."""
        return scored_truth(self.truth, config, self.name)

    def score(self, config: EvalConfig, folder: Path, cache: Path | None = None,
              perturbed: Perturbed | None = None) -> tuple[dict, dict[str, float]]:
        """The pipeline on the cloud (as it is, or `perturbed`), its flowers written into
        `folder` and scored: the report's plant entry and stage timings. With `cache` (the
        stage cache's folder), a detection and a score made before from the same files,
        settings and code are taken from it (their seconds 0 here)."""
        pipeline = pipeline_part(config)
        if perturbed is not None:
            return self._score_perturbed(config, pipeline, folder, cache, perturbed)

        def score() -> dict:
            watch = Stopwatch()
            entry = plant_entry(self.name, score_plant(
                read_flowers(folder / "flowers.json"), self.scored_truth(config),
                config.score.max_distance_m))
            return {"entry": entry, "seconds": watch.elapsed()}

        timing, detect_key = detect_cloud(self.cloud, pipeline, folder, cache)
        if detect_key is None:
            scored = score()
            return scored["entry"], {**timing, "score": scored["seconds"]}
        from flowerpose.cache import StageCache

        scored, score_cached, _ = StageCache(cache).run(
            "score", {"score": to_dict(config.score), "plant": self.name}, [self.truth],
            folder, (), score, parents=[detect_key])
        return scored["entry"], {**timing, "score": 0.0 if score_cached else scored["seconds"]}

    def _score_perturbed(self, config: EvalConfig, pipeline: PipelineConfig, folder: Path,
                         cache: Path | None, perturbed: Perturbed
                         ) -> tuple[dict, dict[str, float]]:
        """`score` under a perturbation of the cloud (a dropped view: of the grid's
        detections), from the stage cache where the same cloud, truth, perturbation and
        settings ran before."""

        def compute() -> dict:
            cloud = read_cloud(self.cloud)
            truth = read_plant_truth(self.truth)
            p = perturbed.perturbation
            drop: tuple[int, ...] = ()
            if p.kind == "drop_view":
                drop = (int(p.value),)
            else:
                rng = perturbed.rng(self.name)
                cuts = draw_cuts(cut_flowers(truth), p.value, rng) if p.kind == "cut" else None
                cloud = perturb(cloud, p, rng, cuts)
            result = find_flowers(cloud, pipeline, drop_views=drop)
            write_flowers(folder / "flowers.json", result, self.cloud)
            entry = plant_entry(self.name, score_plant(
                [f.pose for f in result.flowers], self.scored_truth(config),
                config.score.max_distance_m))
            return {"entry": entry, "timing_s": result.timing_s}

        if cache is None:
            result = compute()
        else:
            from flowerpose.cache import StageCache

            settings = {"pipeline": to_dict(pipeline), **perturbed.to_json(),
                        "plant": self.name, "score": to_dict(config.score)}
            result, _, _ = StageCache(cache).run("stress", settings, [self.cloud, self.truth],
                                                 folder, ("flowers.json",), compute)
        return result["entry"], result["timing_s"]

    def method_input(self, folder: Path) -> Path:
        """The cloud an external method gets."""
        return self.cloud

    def view(self, config: EvalConfig, out_dir: Path) -> PlantView:
        """report.html's view: the cloud, the flowers, the truth as scored and the camera
        path the cloud was made from."""
        return PlantView(self.name, read_cloud(self.cloud),
                         read_flowers(self.folder(out_dir) / "flowers.json"),
                         self.scored_truth(config),
                         cameras=camera_path(self.folder(out_dir), self.source))


@dataclass(frozen=True)
class RealJob:
    """A labelled real plant folder to score (`real_source.RealPlant`)."""

    name: str
    plant: RealPlant

    @property
    def start(self) -> Start:
        """Where the pipeline starts on it: what the folder holds (cloud, candidates,
        crops)."""
        return self.plant.stage

    def folder(self, out_dir: Path) -> Path:
        return out_dir / self.name

    def scored_truth(self, config: EvalConfig) -> list:
        return real_truth(self.plant, config.score.max_distance_m)

    def score(self, config: EvalConfig, folder: Path, cache: Path | None = None,
              perturbed: Perturbed | None = None) -> tuple[dict, dict[str, float]]:
        """The pipeline from where the folder's data starts (its clouds as they are, or
        `perturbed`: `perturbed_real`), its flowers written into `folder` and scored
        against the labels."""
        clouds, drop = None, ()
        if perturbed is not None:
            clouds, drop = perturbed_real(read_plant_clouds(self.plant), self.plant.stage,
                                          perturbed.perturbation, perturbed.rng(self.name),
                                          self.scored_truth(config))
        return evaluate_real_plant(self.plant, pipeline_part(config), folder,
                                   config.score.max_distance_m, clouds, drop)

    def method_input(self, folder: Path) -> Path:
        """The plant's cloud, or its candidates or crops merged into one in `folder`."""
        from flowerpose.cloudio import write_cloud

        if self.plant.stage == "cloud":
            return Path(self.plant.clouds[0])
        return write_cloud(folder / "input.ply", plant_cloud(self.plant))

    def view(self, config: EvalConfig, out_dir: Path) -> PlantView:
        return PlantView(self.name, plant_cloud(self.plant),
                         read_flowers(self.folder(out_dir) / "flowers.json"),
                         self.scored_truth(config))


PlantJob = SyntheticJob | RealJob


def score_job(job: PlantJob, config: EvalConfig, folder: Path,
              cache: Path | None = None) -> tuple[dict, dict[str, float]]:
    """`job.score` as a worker calls it (a module-level function, so a process pool takes
    it): the plant entry, with the warnings said on the way (its "notes": what the run
    assumed of the plant's files), and stage timings."""
    with noted() as notes:
        entry, timing = job.score(config, folder, cache)
    return {**entry, "notes": notes}, timing


def camera_path(plant_dir: Path, source: str) -> np.ndarray | None:
    """(K, 4, 4) camera-to-bed poses (metres) of the frames a plant's cloud was made from,
    in the order they were taken: the scan source's chosen frames (frames/frames.json,
    the frames photogrammetry got), the RGB-D source's views (rgbd/trajectory.csv); None
    for a source without a camera."""
    if source == "scan":
        from flowerpose.pipeline.frames import read_frames

        frames = read_frames(plant_dir / "frames")
        return np.array([f.pose for f in frames]).reshape(-1, 4, 4)
    if source == "rgbd":
        from flowerpose.scanio import read_trajectory

        trajectory = read_trajectory(plant_dir / "rgbd" / "trajectory.csv")
        poses = np.tile(np.eye(4), (len(trajectory), 1, 1))
        poses[:, :3, :3], poses[:, :3, 3] = trajectory.camera_rotation, trajectory.camera_position
        return poses
    return None


@dataclass
class Captured:
    """A set's jobs, and what making them said: seconds per stage (plant generation and
    the capture's steps) and the capture's report sections ("reconstruction", "cache")."""

    jobs: list[PlantJob]
    timing: dict[str, float]
    report: dict


class Plants:
    """Makes plant sets into jobs (`jobs`): synthetic plants generated and captured once
    per world (the settings their clouds depend on), in a folder the caller names, over
    `workers` processes (or Ray), their stages from the stage cache at `cache` (None: none)."""

    def __init__(self, workers: int | None = None, cache: Path | None = None):
        self.workers, self.cache = workers, cache
        self._made: dict[tuple, Captured] = {}

    def jobs(self, plant_set: PlantSet, config: EvalConfig, folder: Path) -> Captured:
        """The set's jobs for `config`'s world. A synthetic set's plants go into
        folder/seed-S (unless this world's were made before, into another folder); a real
        set's folders are read and checked, each named uniquely."""
        if plant_set.real:
            plants = plant_set.real_plants()
            return Captured([RealJob(plant.name, plant) for plant in plants], {}, {})
        key = (plant_set.source, world_digest(config, plant_set.source), plant_set.seed,
               plant_set.plants)
        if key not in self._made:
            self._made[key] = self._synthetic(plant_set, config, folder)
        return self._made[key]

    def _synthetic(self, plant_set: PlantSet, config: EvalConfig, folder: Path) -> Captured:
        seeds = plant_set.seeds
        generation = generate_plants(seeds, config.sim, folder, self.workers, self.cache)
        folders = {s: folder / f"seed-{s}" for s in seeds}
        clouds, timing, report = capture_clouds(config, plant_set.source, folders,
                                                self.workers, self.cache)
        jobs: list[PlantJob] = [SyntheticJob(f"seed-{s}", *clouds[s], plant_set.source)
                                for s in seeds]
        return Captured(jobs, {"plant": round(sum(generation), 4), **timing}, report)


def generate_plant_files(seed: int, sim: SimConfig, plant_dir: Path,
                         cache: Path | None = None) -> float:
    """Write plant `seed`'s truth, mesh and oracle cloud into plant_dir, or copy them from
    the stage cache at `cache` (None: none); wall seconds spent generating (0 when cached)."""
    from flowerpose.sim.bundle import make_plant
    from flowerpose.sim.export import PLANT_FILES

    def generate() -> dict:
        watch = Stopwatch()
        make_plant(seed, out_dir=plant_dir, config=sim)
        return {"seconds": watch.elapsed()}

    if cache is None:
        return generate()["seconds"]
    from flowerpose.cache import StageCache

    result, cached, _ = StageCache(cache).run("plant", {"seed": seed, "sim": to_dict(sim)}, [],
                                              plant_dir, PLANT_FILES, generate,
                                              code=("flowerpose.sim.bundle",))
    return 0.0 if cached else result["seconds"]


def generate_plants(seeds: list[int], sim: SimConfig, plants_dir: Path,
                    workers: int | None, cache: Path | None = None) -> list[float]:
    """Every plant's files under plants_dir/seed-<s>/ (from the stage cache at `cache` when
    there); seconds generating per plant."""
    return run_jobs(generate_plant_files,
                    [(s, sim, plants_dir / f"seed-{s}", cache) for s in seeds], workers,
                    lambda k, sec: f"plant seed-{seeds[k]} generated ({sec:.1f} s)",
                    stage="plant", labels=[f"seed-{s}" for s in seeds])


def _capture_scan(config: EvalConfig, folders: dict[int, Path], workers: int | None,
                  cache: Path | None) -> tuple[dict, dict, list[dict]]:
    return capture_scan_clouds(config.scan, config.sim.viewpoints, folders, workers, cache)


def _capture_rgbd(config: EvalConfig, folders: dict[int, Path], workers: int | None,
                  cache: Path | None) -> tuple[dict, dict, list[dict]]:
    return capture_rgbd_clouds(config.rgbd, config.fusion, config.sim.viewpoints, folders,
                               workers, cache)


#: How each filmed source captures its plants' clouds (`scan_source`, `rgbd_source`): each
#: takes (config, seed -> plant folder, workers, cache) and gives (seed -> (cloud, truth)),
#: seconds per stage, and each plant's capture report (its "quality", and the steps it took
#: from the stage cache, "cached").
CAPTURES = {"scan": _capture_scan, "rgbd": _capture_rgbd}


def capture_clouds(config: EvalConfig, source: str, folders: dict[int, Path],
                   workers: int | None, cache: Path | None = None
                   ) -> tuple[dict[int, tuple[Path, Path]], dict, dict]:
    """The cloud and truth each generated plant (seed -> folder) has from `source`: its
    oracle cloud as generated, or one filmed and reconstructed now or taken from the stage
    cache at `cache` (`CAPTURES`). Returns (seed -> (cloud, truth)), seconds per stage, and
    the reconstruction report ("reconstruction", "cache")."""
    seeds = list(folders)
    if source == "oracle":
        return {s: (folders[s] / "cloud.ply", folders[s] / "plant.json") for s in seeds}, {}, {}
    clouds, timing, captured = CAPTURES[source](config, folders, workers, cache)
    report: dict = {"reconstruction": {f"seed-{s}": c["quality"]
                                       for s, c in zip(seeds, captured, strict=True)}}
    if cache is not None:
        steps = {f"seed-{s}": c.get("cached", []) for s, c in zip(seeds, captured, strict=True)}
        whole = len(timing)  # the capture's steps: a plant reused whole skipped them all
        report["cache"] = {"dir": str(cache), "steps_reused": steps,
                           "reused": [plant for plant, c in steps.items() if len(c) == whole]}
    return clouds, timing, report


def points_per_flower(flowers_json: Path) -> float | None:
    """The median points of the flowers a run found (its density as the pipeline saw it),
    from its flowers.json; None where it found none."""
    from flowerpose.jsonio import read_json

    points = [f.get("points") for f in read_json(flowers_json).get("flowers", [])]
    points = [p for p in points if isinstance(p, int)]
    return float(np.median(points)) if points else None
