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
    plan_and_score,
    success_by_error,
    summarise_pollination,
    write_success_plot,
)
from flowerpose.eval.pool import run_jobs
from flowerpose.pipeline.colour import flower_coloured
from flowerpose.sim.export import read_plant

if TYPE_CHECKING:
    from flowerpose.eval.jobs.config import EvalConfig
    from flowerpose.eval.jobs.plants import SyntheticJob


def pollinate_plants(jobs: list[SyntheticJob], entries: list[dict], config: EvalConfig,
                     out_dir: Path, workers: int | None) -> dict:
    """Each synthetic plant's visits from its estimates and from its truth, scored, into
    its entry (`pollination`, `pollination_ceiling`); returns the report's sections of the
    success against pose error and against the approach's angle off the axis
    (`approach_angle.py`), which out_dir/pollination.png draws."""
    results = run_jobs(_pollinate_job, [(job, config, out_dir) for job in jobs], workers,
                       lambda k, v: f"{jobs[k].name}: pollinated {v[0]['successes']} of "
                       f"{len(v[0]['flowers'])} flowers ({v[1]['successes']} from the true "
                       "poses)", stage="pollinate", labels=[job.name for job in jobs])
    extra: dict = {}
    errors = {}
    for entry, (estimated, ceiling, _) in zip(entries, results, strict=True):
        entry["pollination"], entry["pollination_ceiling"] = estimated, ceiling
        detected = {m["detection"]: m for m in entry["matches"]}
        for outcome in estimated["flowers"]:
            match = detected.get(outcome["detection"])
            if match is not None and match["error_deg"]["plane"] is not None:
                errors[(entry["plant"], outcome["flower"])] = match["error_deg"]["plane"]
    rows = success_by_error([{"plant": e["plant"], **e["pollination"]} for e in entries],
                            errors)
    extra["pollination_by_error"] = rows
    curve = summarise_curve([result[2] for result in results]) if results else []
    if curve:
        extra["pollination_by_angle"] = curve
    if any(r["flowers"] for r in rows):
        write_success_plot(out_dir / "pollination.png", rows, curve, config.pollinate.cone_deg,
                           config.pollination.max_angle_deg)
    return extra


def pollination_summary(entries: list[dict]) -> dict:
    """report.json's summary sections of the plants' pollination: from the estimated poses
    and from the true ones (the planner's ceiling)."""
    return {"pollination": summarise_pollination([e["pollination"] for e in entries]),
            "pollination_ceiling": summarise_pollination([e["pollination_ceiling"]
                                                          for e in entries])}


def _pollinate_job(job: SyntheticJob, config: EvalConfig, out_dir: Path
                   ) -> tuple[dict, dict, list[dict]]:
    """One synthetic plant's pollination from its estimates and from its true poses, and
    its success against the approach's angle (`approach_angle.py`)."""
    plant_dir = job.folder(out_dir)
    cloud = read_cloud(job.cloud)
    world = ContactWorld(read_plant(plant_dir), config.pollination.contact)
    corolla = flower_coloured(cloud.colors, config.colour)  # once: three plans use it
    estimated, ceiling = (plan_and_score(plant_dir, flowers, cloud, config.score.max_distance_m,
                                         config.pollinate, config.pollination,
                                         flight_json=plant_dir / flight, world=world,
                                         corolla=corolla)
                          for flowers, flight in ((plant_dir / "flowers.json", "flight.json"),
                                                  (None, "flight_ceiling.json")))
    curve = approach_curve(world, cloud, config.pollinate, config.pollination,
                           corolla=corolla)
    return estimated, ceiling, curve
