"""The pollination task of `eval --task pollinate`: on each synthetic plant, visits planned
from the pipeline's poses and from the true ones (the planner's ceiling), flown on the
simulated bot and judged in MuJoCo contact (`pollination.py`), and each plant's success
against the approach's angle off the axis (`approach_angle.py`).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from flowerpose.cloudio import read_cloud
from flowerpose.eval.pollination.approach_angle import approach_curve, summarise_curve
from flowerpose.eval.pollination.contact import ContactWorld
from flowerpose.eval.pollination.visits import (
    LookSetup,
    plan_and_score,
    success_by_error,
    write_success_plot,
)
from flowerpose.eval.pool import run_jobs
from flowerpose.eval.scoring.pollinated import pollination_sections
from flowerpose.pipeline.colour import flower_coloured
from flowerpose.sim.export import read_plant

if TYPE_CHECKING:
    from flowerpose.eval.jobs.config import EvalConfig
    from flowerpose.eval.jobs.plants import SyntheticJob


def pollinate_plants(jobs: list[SyntheticJob], entries: list[dict], config: EvalConfig,
                     out_dir: Path, workers: int | None,
                     folders: list[tuple[Path, Path]] | None = None) -> dict:
    """Each synthetic plant's visits from its estimates (with the close look, and where it
    runs without it too) and from its truth, scored, into its entry (`pollination`,
    `pollination_scan_pose`, `pollination_ceiling`); returns the report's sections of the
    success against pose error and against the approach's angle off the axis
    (`approach_angle.py`), which out_dir/pollination.png draws. folders: per job, the
    folder of its plant's files and the one its flowers.json is in and its flights go
    (default: its folder in out_dir, for both; a sweep's settings have their own)."""
    folders = folders or [(job.folder(out_dir), job.folder(out_dir)) for job in jobs]
    results = run_jobs(_pollinate_job, [(job, config, *where)
                                        for job, where in zip(jobs, folders, strict=True)],
                       workers,
                       lambda k, v: f"{jobs[k].name}: pollinated {v[0]['successes']} of "
                       f"{len(v[0]['flowers'])} flowers ("
                       + ("" if v[1] is None else f"{v[1]['successes']} from the scan's "
                                                  "poses alone, ")
                       + f"{v[2]['successes']} from the true poses)",
                       stage="pollinate", labels=[job.name for job in jobs])
    extra: dict = {}
    errors = {}
    for entry, (estimated, scan_pose, ceiling, _) in zip(entries, results, strict=True):
        entry["pollination"], entry["pollination_ceiling"] = estimated, ceiling
        if scan_pose is not None:
            entry["pollination_scan_pose"] = scan_pose
        detected = {m["detection"]: m for m in entry["matches"]}
        for outcome in estimated["flowers"]:
            match = detected.get(outcome["detection"])
            if match is not None and match["error_deg"]["plane"] is not None:
                errors[(entry["plant"], outcome["flower"])] = match["error_deg"]["plane"]
    rows = success_by_error([{"plant": e["plant"], **e["pollination"]} for e in entries],
                            errors)
    extra["pollination_by_error"] = rows
    curve = summarise_curve([result[3] for result in results]) if results else []
    if curve:
        extra["pollination_by_angle"] = curve
    if any(r["flowers"] for r in rows):
        summary = pollination_summary(entries)
        write_success_plot(out_dir / "pollination.png", rows, curve, config.pollinate.cone_deg,
                           config.pollination.max_angle_deg,
                           before_after=(summary.get("pollination_scan_pose"),
                                         summary["pollination"]))
    return extra


def pollination_summary(entries: list[dict]) -> dict:
    """report.json's summary sections of the plants' pollination: from the estimated poses
    (with the close look where it ran), from the scan's poses alone (where a close look
    ran: the same flowers without it, and the pairs' changes) and from the true ones (the
    planner's ceiling)."""
    summary = pollination_sections(entries)
    if "pollination_scan_pose" in summary:
        summary["close_look"] = paired_look(entries)
    return summary


def _pollinate_job(job: SyntheticJob, config: EvalConfig, plant_dir: Path, folder: Path
                   ) -> tuple[dict, dict, list[dict]]:
    """One synthetic plant's (its files in `plant_dir`) pollination from its estimates
    (flowers.json in `folder`, where its flights are written) and from its true poses, and
    its success against the approach's angle (`approach_angle.py`)."""
    cloud = read_cloud(job.cloud)
    world = ContactWorld(read_plant(plant_dir), config.pollination.contact,
                         config.pollinate.tool)
    corolla = flower_coloured(cloud.colors, config.colour)  # once: every plan uses it
    look = LookSetup(config.scan.camera, config.pose, config.colour)

    def score(flowers: Path | None, flight: str, close: LookSetup | None) -> dict:
        return plan_and_score(plant_dir, flowers, cloud, config.score.max_distance_m,
                              config.pollinate, config.pollination, world=world,
                              flight_json=folder / flight, corolla=corolla, look=close)

    estimated = score(folder / "flowers.json", "flight.json", look)
    scan_pose = (score(folder / "flowers.json", "flight_scan_pose.json", None)
                 if config.pollinate.look.views else None)
    ceiling = score(None, "flight_ceiling.json", None)
    curve = approach_curve(world, cloud, config.pollinate, config.pollination,
                           config.pollinate.tool, corolla=corolla)
    return estimated, scan_pose, ceiling, curve


def paired_look(entries: list[dict]) -> dict:
    """The close look against the scan's poses alone, flower by flower on the same plants:
    flowers it won and lost, the flowers both judged, the looks by what they did, and the
    time per visit by part (seconds: planning and the look's reconstruction on the wall
    clock, the flight and the look's own moves on the bot's)."""
    won = lost = paired = 0
    statuses: dict[str, int] = {}
    for entry in entries:
        before = {o["flower"]: o["outcome"] for o in entry["pollination_scan_pose"]["flowers"]}
        for outcome in entry["pollination"]["flowers"]:
            paired += 1
            was = before[outcome["flower"]] == "success"
            now = outcome["outcome"] == "success"
            won, lost = won + (now and not was), lost + (was and not now)
            if "look" in outcome:
                statuses[outcome["look"]] = statuses.get(outcome["look"], 0) + 1
    return {"flowers": paired, "won": won, "lost": lost, "looks": statuses,
            "time_per_visit_s": time_per_visit([e["pollination"]["time_s"] for e in entries]),
            "time_per_visit_scan_pose_s": time_per_visit(
                [e["pollination_scan_pose"]["time_s"] for e in entries])}


def time_per_visit(times: list[dict]) -> dict:
    """Seconds per visit by part, over plants' `time_s` (`visits.visit_times`)."""
    visits = sum(t["visits"] for t in times)
    parts = ("planning", "flight", "look", "look_compute")
    return {"visits": visits, **{part: round(sum(t[part] for t in times) / visits, 2)
                                 if visits else None for part in parts}}
