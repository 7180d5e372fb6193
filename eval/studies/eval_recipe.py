"""The end-to-end harness, a recipe: a run's plants as scored jobs (`plants.py`) -> their
scores -> the compared settings and methods on the same clouds -> pollination -> the report.

The plants are generated (and, for the scan and RGB-D sources, filmed and reconstructed)
into `plants/seed-<s>/`, or read from real folders; the pipeline reads only each cloud,
exactly as it would a real scan, and each plant is scored against its truth.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from flowerpose.atomic import write_text
from flowerpose.config import settings_toml, to_dict
from flowerpose.eval.jobs.config import EvalConfig, settings_run
from flowerpose.eval.jobs.eval_run import EvalRun
from flowerpose.eval.jobs.plant_set import real_names
from flowerpose.eval.jobs.plants import PlantJob, Plants, score_job
from flowerpose.eval.pool import LOCAL, Execution, run_jobs
from flowerpose.eval.reports.html_report import write_html_report
from flowerpose.eval.reports.report import REPORT_FILES, build_report, summarise, write_report
from flowerpose.eval.scoring.methods import ExternalMethod, run_method
from flowerpose.eval.scoring.paired import compare_runs
from flowerpose.log import LOG
from flowerpose.pipeline.flowers import sections_run
from flowerpose.stopwatch import Stopwatch


@dataclass
class RunRecord:
    """What a run was, as its report says it: report.json's `config` (the run and the
    settings of the stages it ran) and the report's title."""

    config: dict
    title: str
    said: str
    """The run as the start line says it."""


@dataclass
class Sections:
    """The report's sections beside its plants and summary, each by its report.json key."""

    reconstruction: dict | None = None
    cache: dict | None = None
    compare: dict = field(default_factory=dict)
    pollination_by_error: list | None = None
    pollination_by_angle: list | None = None
    suite: dict | None = None

    def to_report(self) -> dict:
        return {key: value for key, value in vars(self).items()
                if value is not None and value != {}}


def run_eval(config: EvalConfig, run: EvalRun, out_dir: Path = Path("runs/eval"),
             execution: Execution = LOCAL) -> dict:
    """The benchmark: the run's plants as jobs, scored, compared, pollinated and reported.
    Returns report.json's content and writes report.json, report.md, report.html,
    config.toml and, per plant, its flowers (and for synthetic plants its truth and cloud)
    under out_dir; compared settings and methods under out_dir/NAME/. `execution`: the
    workers, and the stage cache the captures, detections and scores are taken from and
    put into."""
    workers, cache = execution.workers, execution.cache
    watch = Stopwatch()
    record = describe_run(config, run)
    LOG.info(f"eval: {record.said} -> {out_dir}")
    captured = Plants(workers, cache).jobs(run.plants, config, out_dir / "plants")
    jobs, timing = captured.jobs, dict(captured.timing)
    record.config = {**record.config,
                     **settings_run(config, run.plants.source,
                                    [job.start for job in jobs])}
    entries, stage_timing = _score_jobs(jobs, config, out_dir, workers, cache)
    timing.update(stage_timing)
    sections = Sections(reconstruction=captured.report.get("reconstruction"),
                        cache=captured.report.get("cache"), suite=run.suite,
                        compare=_compare(jobs, entries, run, config, out_dir, workers, cache))
    pollination_summary = {}
    if run.task == "pollinate":
        with watch.step("pollinate"):
            pollination_summary = _pollinate(jobs, entries, config, out_dir, workers, sections)
        timing["pollinate"] = round(watch.seconds["pollinate"], 4)
    timing["total"] = round(watch.elapsed(), 4)
    report = build_report(record.config, entries, timing, sections.to_report())
    report["summary"].update(pollination_summary)
    if run.assets:
        report["run"]["assets"] = run.assets
    write_report(out_dir, report, record.title)
    write_text(out_dir / RUN_CONFIG, settings_toml(record.config, RUN_CONFIG_HEADER))
    write_html_report(out_dir / "report.html", record.title, report,
                      [job.view(config, out_dir) for job in jobs])
    return report


def describe_run(config: EvalConfig, run: EvalRun) -> RunRecord:
    """The run's part of report.json's `config` (its plants, `PlantSet.describe`; the
    settings of the stages are added once the jobs say where the pipeline starts), and the
    title. Bad input (a folder given twice or unreadable) is refused here, before any
    work."""
    plants = run.plants
    config_run = plants.describe()
    if plants.real:
        said = f"{len(config_run['folders'])} real plants"
        title = f"flowerpose eval: {said}"
    else:
        said = (f"{plants.plants} {config.sim.plant.name} plants from seed {plants.seed}, "
                f"{plants.source} clouds")
        title = (f"flowerpose eval: {plants.plants} {config.sim.plant.name} plants, "
                 f"{plants.source} clouds")
    if run.task == "pollinate":
        config_run.update(task=run.task, pollinate=to_dict(config.pollinate),
                          pollination=to_dict(config.pollination))
    return RunRecord(config_run, title, said)


def _pollinate(jobs: list[PlantJob], entries: list[dict], config: EvalConfig, out_dir: Path,
               workers: int | None, sections: Sections) -> dict:
    """The pollination task's step: each plant's visits flown and scored into its entry,
    the success curves into `sections`; returns the summary's pollination sections."""
    from flowerpose.eval.jobs.pollination_task import pollinate_plants, pollination_summary

    curves = pollinate_plants(jobs, entries, config, out_dir, workers)
    sections.pollination_by_error = curves.get("pollination_by_error")
    sections.pollination_by_angle = curves.get("pollination_by_angle")
    return pollination_summary(entries)


def _describe_entry(k: int, value: tuple[dict, dict]) -> str:
    entry, timing = value
    plane = entry["error_deg"]["plane"]
    plane_text = f", plane {np.mean(plane):.1f}°" if plane else ""
    return (f"{entry['plant']} scored: {entry['gt']} flowers, {entry['visible']} visible, "
            f"{entry['found']} found, {entry['fp']} fp{plane_text} (detection "
            f"{timing['total']:.2f} s)")


def sum_timings(timings: Iterable[dict[str, float]]) -> dict[str, float]:
    """Per-stage sums of several timing dicts (seconds)."""
    total: dict[str, float] = {}
    for timing in timings:
        for stage, seconds in timing.items():
            total[stage] = total.get(stage, 0.0) + seconds
    return {k: round(v, 4) for k, v in total.items()}


def _compare(jobs: list[PlantJob], entries: list[dict], run: EvalRun, config: EvalConfig,
             out_dir: Path, workers: int | None, cache: Path | None) -> dict:
    """The compared settings and external methods on the same clouds, by name, each paired
    flower by flower with this run's `entries` (report.json's `compare`)."""
    starts = [job.start for job in jobs]
    compared: dict = {}
    for name, other in run.compare.items():
        others, _ = _score_jobs(jobs, other, out_dir / name, workers, cache)
        compared[name] = {"summary": summarise(others), "plants": others,
                          "config": sections_run(other, starts),
                          "paired": compare_runs(entries, others)}
    for method in run.methods:
        results = run_jobs(_method_job, [(job, method, config, out_dir) for job in jobs],
                           workers, lambda k, v, name=method.name: f"{name}: "
                           + _describe_entry(k, v), stage=f"method {method.name}",
                           labels=[job.name for job in jobs])
        others = [entry for entry, _ in results]
        compared[method.name] = {
            "summary": summarise(others), "plants": others,
            "config": {"method": method.command, "timeout_s": method.timeout_s},
            "paired": compare_runs(entries, others)}
    return compared


def _method_job(job: PlantJob, method: ExternalMethod, config: EvalConfig,
                out_dir: Path) -> tuple[dict, dict[str, float]]:
    """An external method on one job's cloud, scored against the job's truth."""
    folder = out_dir / method.name / job.name
    return run_method(method, job.method_input(folder), job.scored_truth(config), folder,
                      job.name, config.score.max_distance_m)


def _score_jobs(jobs: list[PlantJob], config: EvalConfig, out_dir: Path,
                workers: int | None, cache: Path | None = None
                ) -> tuple[list[dict], dict[str, float]]:
    """Every job scored with `config` (`PlantJob.score`); the plant entries and summed stage
    timings. `cache`: the stage cache's folder, which a synthetic plant's detection and
    score are taken from and put into."""
    results = run_jobs(score_job, [(job, config, job.folder(out_dir), cache) for job in jobs],
                       workers, _describe_entry, stage="score", labels=[job.name for job in jobs])
    return [entry for entry, _ in results], sum_timings(t for _, t in results)


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


