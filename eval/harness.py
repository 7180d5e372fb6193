"""The end-to-end harness: seeded plants -> clouds -> the pipeline -> scores -> report.

Generate every plant (truth, mesh, oracle cloud) into `plants/seed-<s>/` over a process
pool; for the scan and RGB-D sources, film each plant and reconstruct its cloud
(`scan_source.py`, `rgbd_source.py`); then run the pipeline on each cloud and score it
against its truth. The pipeline reads only the cloud, exactly as it would a real scan.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from flowerpose.atomic import write_text
from flowerpose.cloudio import read_cloud
from flowerpose.config import apply_overrides, load_preset, require, settings_toml, to_dict
from flowerpose.errors import InputError
from flowerpose.eval.html_report import PlantView, write_html_report
from flowerpose.eval.kinds import EvalRun
from flowerpose.eval.match import MAX_MATCH_DISTANCE, score_plant
from flowerpose.eval.methods import ExternalMethod, run_method
from flowerpose.eval.paired import compare_runs
from flowerpose.eval.pollination import PollinationScoreConfig
from flowerpose.eval.report import (
    REPORT_FILES,
    build_report,
    plant_entry,
    summarise,
    write_report,
)
from flowerpose.eval.rgbd_source import RgbdConfig, capture_rgbd_clouds
from flowerpose.eval.runner import run_jobs
from flowerpose.eval.scan_source import ScanSourceConfig, capture_scan_clouds
from flowerpose.eval.truth import as_labelled, read_plant_truth, read_sagemaker_truth
from flowerpose.hardware.flights.pollinate import PollinateConfig
from flowerpose.pipeline.detect import ONNX_PREFIX
from flowerpose.pipeline.flowers import (
    PipelineConfig,
    Start,
    find_flowers,
    read_flowers,
    sections_run,
    write_flowers,
    write_normals_ply,
)
from flowerpose.pipeline.rgbd import FusionConfig
from flowerpose.sim.world_config import PresetName, SimConfig
from flowerpose.stopwatch import Stopwatch

if TYPE_CHECKING:
    from flowerpose.eval.real_source import RealPlant


@dataclass(frozen=True)
class ScoreConfig:
    """How estimates are matched to the truth."""

    max_distance_m: float = MAX_MATCH_DISTANCE
    """Largest centre distance of a match, metres (the paper: 2 cm)."""
    label_error_deg: float = 0.0
    """Synthetic plants: score against truth normals tilted as hand labels are, by a
    seeded random tilt of this mean angle in degrees (0: the exact truth). The field
    preset sets the paper's estimate, 5 degrees, so its numbers predict scores against
    hand labels; the README gives them both ways."""

    def __post_init__(self):
        require(0 <= self.label_error_deg < 90, "score.label_error_deg",
                "must be 0 or more degrees, below 90")


@dataclass(frozen=True)
class EvalConfig(PipelineConfig):
    """The pipeline's settings plus the synthetic world and the scoring."""

    sim: SimConfig = field(default_factory=SimConfig)
    score: ScoreConfig = field(default_factory=ScoreConfig)
    rgbd: RgbdConfig = field(default_factory=RgbdConfig)
    fusion: FusionConfig = field(default_factory=FusionConfig)
    scan: ScanSourceConfig = field(default_factory=ScanSourceConfig)
    pollinate: PollinateConfig = field(default_factory=PollinateConfig)
    """`eval --task pollinate`: how each flower is visited (`hardware/flights/pollinate.py`)."""
    pollination: PollinationScoreConfig = field(default_factory=PollinationScoreConfig)
    """`eval --task pollinate`: what counts as a pollinated flower (`eval/pollination.py`)."""


def eval_config(preset: PresetName, configure: Callable[[Any], Any] = lambda c: c) -> EvalConfig:
    """The harness config for a preset (assets/presets/NAME.toml over the defaults: "field"
    also scores against truth tilted by the hand labels' error and films with the field
    camera and photogrammetry) with the user's overrides applied."""
    settings, _ = load_preset(preset)
    return configure(apply_overrides(EvalConfig(), settings))


def pipeline_part(config: PipelineConfig) -> PipelineConfig:
    """Just the pipeline's sections of a config."""
    return PipelineConfig(**{f.name: getattr(config, f.name)
                             for f in dataclasses.fields(PipelineConfig)})


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


#: What the detect stage writes of a synthetic plant, and the stage cache keeps.
DETECT_FILES = ("flowers.json", "flowers.ply", "normals.ply")


def evaluate_cloud(cloud_path: Path, truth_path: Path, config: EvalConfig, out_dir: Path,
                   name: str, cache: Path | None = None) -> tuple[dict, dict[str, float]]:
    """Run the pipeline on a cloud, write flowers.json to out_dir, score it against the
    truth; returns the report's plant entry and stage timings. With `cache` (the stage
    cache's folder), a detection and a score made before from the same files, settings and
    code are taken from it (their seconds 0 here)."""
    pipeline = pipeline_part(config)

    def detect() -> dict:
        result = find_flowers(read_cloud(cloud_path), pipeline)
        write_flowers(out_dir / "flowers.json", result, cloud_path)
        write_normals_ply(out_dir, result.flowers)
        return {"timing_s": result.timing_s}

    def score() -> dict:
        watch = Stopwatch()
        truth = scored_truth(truth_path, config.score, name)
        entry = plant_entry(name, score_plant(read_flowers(out_dir / "flowers.json"), truth,
                                              config.score.max_distance_m))
        return {"entry": entry, "seconds": watch.elapsed()}

    if cache is None or not _cacheable(pipeline):
        detected, scored = detect(), score()
        return scored["entry"], {**detected["timing_s"], "score": scored["seconds"]}
    from flowerpose.cache import StageCache

    stages = StageCache(cache)
    detected, detect_cached, detect_key = stages.run(
        "detect", to_dict(pipeline), [cloud_path, *_detector_files(pipeline)], out_dir,
        DETECT_FILES, detect)
    scored, score_cached, _ = stages.run(
        "score", {"score": to_dict(config.score), "plant": name}, [truth_path], out_dir, (),
        score, parents=[detect_key])
    timing = {stage: 0.0 if detect_cached else t for stage, t in detected["timing_s"].items()}
    return scored["entry"], {**timing, "score": 0.0 if score_cached else scored["seconds"]}


def scored_truth(truth_path: Path, score: ScoreConfig, name: str) -> list:
    """A synthetic plant's truth as it is scored: tilted by the hand labels' error where
    `score.label_error_deg` says so (seeded by the plant's name)."""
    truth = read_plant_truth(truth_path)
    if score.label_error_deg > 0:
        truth = as_labelled(truth, score.label_error_deg, name)
    return truth


def _cacheable(pipeline: PipelineConfig) -> bool:
    """Whether a detection with these settings may come from the stage cache: the built-in
    detectors' code is in the cache's code version (an ONNX model's file in the key); a
    plug-in class's code is not, so its detections are always run."""
    detector = pipeline.detect.detector
    return detector == "colour" or detector.startswith(ONNX_PREFIX)


def _detector_files(pipeline: PipelineConfig) -> list[Path]:
    """The files a detection reads besides the cloud: an ONNX model."""
    detector = pipeline.detect.detector
    return [Path(detector.removeprefix(ONNX_PREFIX))] if detector.startswith(ONNX_PREFIX) else []


def sum_timings(timings: Iterable[dict[str, float]]) -> dict[str, float]:
    """Per-stage sums of several timing dicts (seconds)."""
    total: dict[str, float] = {}
    for timing in timings:
        for stage, seconds in timing.items():
            total[stage] = total.get(stage, 0.0) + seconds
    return {k: round(v, 4) for k, v in total.items()}


def generate_plants(seeds: list[int], sim: SimConfig, plants_dir: Path,
                    workers: int | None, cache: Path | None = None) -> list[float]:
    """Every plant's files under plants_dir/seed-<s>/ (from the stage cache at `cache` when
    there); seconds generating per plant."""
    return run_jobs(generate_plant_files,
                    [(s, sim, plants_dir / f"seed-{s}", cache) for s in seeds], workers,
                    lambda k, sec: f"plant seed-{seeds[k]} generated ({sec:.1f} s)",
                    stage="plant", labels=[f"seed-{s}" for s in seeds])


def _describe_entry(k: int, value: tuple[dict, dict]) -> str:
    entry, timing = value
    plane = entry["error_deg"]["plane"]
    plane_text = f", plane {np.mean(plane):.1f}°" if plane else ""
    return (f"{entry['plant']} scored: {entry['gt']} flowers, {entry['visible']} visible, "
            f"{entry['found']} found, {entry['fp']} fp{plane_text} (detection "
            f"{timing['total']:.2f} s)")


#: The sections of an EvalConfig each source reads besides the pipeline's: the synthetic
#: world and the scoring, and the simulated camera and its reconstruction or fusion.
SOURCE_SECTIONS: dict[str, tuple[str, ...]] = {
    "oracle": ("sim", "score"), "rgbd": ("sim", "score", "rgbd", "fusion"),
    "scan": ("sim", "score", "scan"), "real": ("score",)}


def settings_run(config: EvalConfig, source: str, starts: Iterable[Start] = ("cloud",)) -> dict:
    """The settings of the stages a run ran, as report.json's `config` records them: the
    pipeline's from where it started (`flowers.sections_run`), then the source's own
    (`SOURCE_SECTIONS`); an oracle run carries no scan, RGB-D or fusion settings, a run
    from candidates no ground, grid or detection settings."""
    return {**sections_run(config, starts),
            **{name: to_dict(getattr(config, name)) for name in SOURCE_SECTIONS[source]}}


@dataclass(frozen=True)
class SyntheticJob:
    """A generated plant to score: its cloud (from the run's source) and its truth."""

    name: str
    cloud: Path
    truth: Path

    def folder(self, out_dir: Path) -> Path:
        """Where the plant's files and its flowers go in a run's folder."""
        return out_dir / "plants" / self.name

    start: Start = "cloud"
    """Where the pipeline starts on it: the whole cloud."""

    def scored_truth(self, config: EvalConfig) -> list:
        """The truth as it is scored (`scored_truth`)."""
        return scored_truth(self.truth, config.score, self.name)

    def score(self, config: EvalConfig, out_dir: Path,
              cache: Path | None = None) -> tuple[dict, dict[str, float]]:
        """The pipeline on the cloud, scored: the report's plant entry and stage timings."""
        return evaluate_cloud(self.cloud, self.truth, config, self.folder(out_dir), self.name,
                              cache)

    def method_input(self, folder: Path) -> Path:
        """The cloud an external method gets."""
        return self.cloud

    def view(self, config: EvalConfig, out_dir: Path, source: str) -> PlantView:
        """report.html's view: the cloud, the flowers, the truth as scored and the camera
        path the cloud was made from."""
        return PlantView(self.name, read_cloud(self.cloud),
                         read_flowers(self.folder(out_dir) / "flowers.json"),
                         self.scored_truth(config),
                         cameras=camera_path(self.folder(out_dir), source))


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
        from flowerpose.eval.real_source import real_truth

        return real_truth(self.plant, config.score.max_distance_m)

    def score(self, config: EvalConfig, out_dir: Path,
              cache: Path | None = None) -> tuple[dict, dict[str, float]]:
        from flowerpose.eval.real_source import evaluate_real_plant

        return evaluate_real_plant(self.plant, pipeline_part(config), self.folder(out_dir),
                                   config.score.max_distance_m)

    def method_input(self, folder: Path) -> Path:
        """The plant's cloud, or its candidates or crops merged into one in `folder`."""
        from flowerpose.cloudio import write_cloud
        from flowerpose.eval.real_source import plant_cloud

        if self.plant.stage == "cloud":
            return Path(self.plant.clouds[0])
        return write_cloud(folder / "input.ply", plant_cloud(self.plant))

    def view(self, config: EvalConfig, out_dir: Path, source: str) -> PlantView:
        from flowerpose.eval.real_source import plant_cloud

        return PlantView(self.name, plant_cloud(self.plant),
                         read_flowers(self.folder(out_dir) / "flowers.json"),
                         self.scored_truth(config))


PlantJob = SyntheticJob | RealJob


def run_eval(config: EvalConfig, run: EvalRun, out_dir: Path = Path("runs/eval"),
             workers: int | None = None, cache: Path | None = None) -> dict:
    """The benchmark: generate (or read) the plants, capture their clouds, detect and score,
    and report. Returns report.json's content and writes report.json, report.md,
    report.html, config.toml and, per plant, its flowers (and for synthetic plants its truth
    and cloud) under out_dir; compared settings and methods under out_dir/NAME/.
    `cache`: the stage cache's folder (`flowerpose.cache`) the captures, detections and
    scores are taken from and put into; None runs every stage."""
    watch = Stopwatch()
    jobs, timing, extra, run_config, title = _plant_jobs(config, run, out_dir, workers, cache)
    entries, stage_timing = _score_jobs(jobs, config, out_dir, workers, cache)
    timing.update(stage_timing)
    _compare(jobs, entries, run, config, out_dir, workers, cache, extra)
    if run.task == "pollinate":
        from flowerpose.eval.pollination_task import pollinate_plants

        with watch.step("pollinate"):
            extra.update(pollinate_plants(jobs, entries, config, out_dir, workers))
        timing["pollinate"] = round(watch.seconds["pollinate"], 4)
    timing["total"] = round(watch.elapsed(), 4)
    report = build_report(run_config, entries, timing,
                          {**extra, **({"suite": run.suite} if run.suite is not None else {})})
    if run.assets:
        report["run"]["assets"] = run.assets
    if run.task == "pollinate":
        from flowerpose.eval.pollination_task import pollination_summary

        report["summary"].update(pollination_summary(entries))
    write_report(out_dir, report, title)
    write_text(out_dir / RUN_CONFIG, settings_toml(run_config, RUN_CONFIG_HEADER))
    write_html_report(out_dir / "report.html", title, report,
                      [job.view(config, out_dir, run.source) for job in jobs])
    return report


def _plant_jobs(config: EvalConfig, run: EvalRun, out_dir: Path, workers: int | None,
                cache: Path | None) -> tuple[list[PlantJob], dict, dict, dict, str]:
    """The run's plants as scoring jobs, generated and their clouds captured (synthetic) or
    read and checked (real): the jobs, stage timings, the capture's report sections, the
    run's config (report.json's `config`) and the report's title."""
    from flowerpose.log import LOG

    # The start line comes after the inputs are checked: bad input is one line, the error.
    if run.source == "real":
        plants = real_plants(list(run.folders), run.truth_scale)
        LOG.info(f"eval: {len(plants)} real plants -> {out_dir}")
        jobs: list[PlantJob] = [RealJob(plant.name, plant) for plant in plants]
        run_config = {"source": run.source, "folders": [p.describe() for p in plants],
                      **settings_run(config, run.source, [job.start for job in jobs])}
        timing, extra = {}, {}
        title = f"flowerpose eval: {len(jobs)} real plants"
    else:
        LOG.info(f"eval: {run.plants} {config.sim.plant.name} plants from seed {run.seed}, "
                 f"{run.source} clouds -> {out_dir}")
        jobs, timing, extra = _synthetic_jobs(config, run.source, run.plants, run.seed,
                                              out_dir, workers, cache)
        run_config = {"source": run.source, "plants": run.plants, "seed": run.seed,
                      **settings_run(config, run.source)}
        title = (f"flowerpose eval: {run.plants} {config.sim.plant.name} plants, "
                 f"{run.source} clouds")
    if run.task == "pollinate":
        run_config.update(task=run.task, pollinate=to_dict(config.pollinate),
                          pollination=to_dict(config.pollination))
    return jobs, timing, extra, run_config, title


def _compare(jobs: list[PlantJob], entries: list[dict], run: EvalRun, config: EvalConfig,
             out_dir: Path, workers: int | None, cache: Path | None, extra: dict) -> None:
    """The compared settings and external methods on the same clouds, into
    extra["compare"] by name, each paired flower by flower with this run's `entries`."""
    starts = [job.start for job in jobs]
    for name, other in run.compare.items():
        others, _ = _score_jobs(jobs, other, out_dir / name, workers, cache)
        extra.setdefault("compare", {})[name] = {
            "summary": summarise(others), "plants": others,
            "config": sections_run(other, starts), "paired": compare_runs(entries, others)}
    for method in run.methods:
        results = run_jobs(_method_job, [(job, method, config, out_dir) for job in jobs],
                           workers, lambda k, v, name=method.name: f"{name}: "
                           + _describe_entry(k, v), stage=f"method {method.name}",
                           labels=[job.name for job in jobs])
        others = [entry for entry, _ in results]
        extra.setdefault("compare", {})[method.name] = {
            "summary": summarise(others), "plants": others,
            "config": {"method": method.command, "timeout_s": method.timeout_s},
            "paired": compare_runs(entries, others)}


def _method_job(job: PlantJob, method: ExternalMethod, config: EvalConfig,
                out_dir: Path) -> tuple[dict, dict[str, float]]:
    """An external method on one job's cloud, scored against the job's truth."""
    folder = out_dir / method.name / job.name
    return run_method(method, job.method_input(folder), job.scored_truth(config), folder,
                      job.name, config.score.max_distance_m)


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


def _score_jobs(jobs: list[PlantJob], config: EvalConfig, out_dir: Path,
                workers: int | None, cache: Path | None = None
                ) -> tuple[list[dict], dict[str, float]]:
    """Every job scored with `config` (`PlantJob.score`); the plant entries and summed stage
    timings. `cache`: the stage cache's folder, which a synthetic plant's detection and
    score are taken from and put into."""
    results = run_jobs(_score_job, [(job, config, out_dir, cache) for job in jobs], workers,
                       _describe_entry, stage="score", labels=[job.name for job in jobs])
    return [entry for entry, _ in results], sum_timings(t for _, t in results)


def _score_job(job: PlantJob, config: EvalConfig, out_dir: Path,
               cache: Path | None = None) -> tuple[dict, dict[str, float]]:
    """A worker's call: `job.score` (a module-level function, so a process pool takes it)."""
    return job.score(config, out_dir, cache)


def real_plants(folders: list[Path], truth_scale: float | None) -> list:
    """The real plant folders, checked (`read_real_plant`), each named uniquely."""
    from flowerpose.eval.real_source import read_real_plant

    if not folders:
        raise InputError("source", "real needs at least one labelled plant folder: "
                         "--source real DIR [DIR ...]")
    plants = [read_real_plant(folder, truth_scale) for folder in folders]
    return [dataclasses.replace(plant, name=name)
            for name, plant in zip(real_names(folders), plants, strict=True)]


def real_names(folders: Iterable[Path]) -> list[str]:
    """Each real plant folder's name in a report: its own, or, where two folders share
    it, with its parent's before it (PARENT-NAME); a folder given twice is refused."""
    given = [Path(f) for f in folders]
    resolved = [f.resolve() for f in given]
    for k, folder in enumerate(resolved):
        if folder in resolved[:k]:
            raise InputError(given[k], "is given twice: each plant counts once")
    names = [f.name for f in resolved]
    return _unique([f"{f.parent.name}-{f.name}" if names.count(f.name) > 1 else f.name
                    for f in resolved])



def _unique(names: list[str]) -> list[str]:
    """Folder names made unique by a count: a, a-2, a-3."""
    seen: dict[str, int] = {}
    unique = []
    for name in names:
        seen[name] = seen.get(name, 0) + 1
        unique.append(name if seen[name] == 1 else f"{name}-{seen[name]}")
    return unique


#: The run's settings as a --config file, beside its report.
RUN_CONFIG = "config.toml"
RUN_CONFIG_HEADER = ("flowerpose eval: the settings of the run beside this file (report.json's "
                     "config).\nflowerpose eval --config config.toml --out DIR runs it again.")


def eval_outputs(source: str, folders: Iterable[Path] = (), compared: Iterable[str] = ()
                 ) -> tuple[str, ...]:
    """The top-level entries `run_eval` writes (`outputs.OutputFolder`): the reports, the
    plants (a real plant under its folder's name) and a folder per compared profile or
    method."""
    plants = real_names(folders) if source == "real" else ["plants"]
    return (*REPORT_FILES, RUN_CONFIG, "report.html", "pollination.png", *plants, *compared)


def _synthetic_jobs(config: EvalConfig, source: str, plants: int, seed: int, out_dir: Path,
                    workers: int | None, cache: Path | None = None
                    ) -> tuple[list[PlantJob], dict, dict]:
    """Generate the seeded plants (and, for the scan and RGB-D sources, film and
    reconstruct them, or take that from the stage cache at `cache`); the scoring jobs,
    timings and reconstruction reports."""
    seeds = list(range(seed, seed + plants))
    plants_dir = out_dir / "plants"
    generation = generate_plants(seeds, config.sim, plants_dir, workers, cache)
    folders = {s: plants_dir / f"seed-{s}" for s in seeds}
    clouds, timing, extra = capture_clouds(config, source, folders, workers, cache)
    timing = {"plant": round(sum(generation), 4), **timing}
    return [SyntheticJob(f"seed-{s}", *clouds[s]) for s in seeds], timing, extra


#: How each filmed source captures its plants' clouds (`scan_source`, `rgbd_source`): each
#: takes (config, seed -> plant folder, workers, cache) and gives (seed -> (cloud, truth)),
#: seconds per stage, and each plant's capture report (its "quality", and the steps it took
#: from the stage cache, "cached").
CAPTURES = {"scan": capture_scan_clouds, "rgbd": capture_rgbd_clouds}


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
    extra: dict = {"reconstruction": {f"seed-{s}": c["quality"]
                                      for s, c in zip(seeds, captured, strict=True)}}
    if cache is not None:
        steps = {f"seed-{s}": c.get("cached", []) for s, c in zip(seeds, captured, strict=True)}
        whole = len(timing)  # the capture's steps: a plant reused whole skipped them all
        extra["cache"] = {"dir": str(cache), "steps_reused": steps,
                          "reused": [plant for plant, c in steps.items() if len(c) == whole]}
    return clouds, timing, extra


def score_files(flowers_path: Path, truth_path: Path, truth_format: str = "plant",
                truth_scale: float = 25.0, max_distance: float = MAX_MATCH_DISTANCE) -> dict:
    """A one-plant report for a flowers.json against plant.json or SageMaker labels."""
    if not (truth_scale > 0 and math.isfinite(truth_scale)):
        raise InputError("truth_scale", f"must be positive, got {truth_scale}")
    if not (max_distance > 0 and math.isfinite(max_distance)):
        raise InputError("score.max_distance_m", f"must be positive, got {max_distance}")
    estimates = read_flowers(flowers_path)
    if truth_format == "plant":
        from flowerpose.eval.truth import is_sagemaker
        from flowerpose.jsonio import read_json

        document = read_json(truth_path)
        if isinstance(document, dict) and "flowers" not in document and is_sagemaker(document):
            raise InputError(truth_path, "holds SageMaker Ground Truth cuboids, not a "
                             "plant.json: add `truth_format` sagemaker")
    truth = (read_plant_truth(truth_path) if truth_format == "plant"
             else read_sagemaker_truth(truth_path, truth_scale))
    watch = Stopwatch()
    score = score_plant(estimates, truth, max_distance)
    config = {"truth_format": truth_format, "truth_scale": truth_scale,
              "max_distance_m": max_distance}
    seconds = round(watch.elapsed(), 6)
    return build_report(config, [plant_entry(flowers_path.parent.name or "plant", score)],
                        {"score": seconds, "total": seconds})
