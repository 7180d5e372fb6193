"""Speed benchmark: a cloud to flower poses, per stage, at the paper's phone-scan density
(125,000 points) and beyond (imports, plant generation and file reading excluded); and the
simulator's own steps for one realistic plant, against their budgets. Speed is measured
here, not asserted in unit tests, since this machine is shared."""

from __future__ import annotations

import dataclasses
import os
import statistics
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from flowerpose.cloudio import Cloud, read_cloud
from flowerpose.config import DEFAULT_PRESET, to_dict
from flowerpose.errors import InputError
from flowerpose.eval.jobs.plant_set import PlantSet
from flowerpose.eval.pool import LOCAL, Execution
from flowerpose.eval.reports.report import markdown_table, run_record
from flowerpose.jsonio import write_json
from flowerpose.log import LOG
from flowerpose.pipeline.flowers import PipelineConfig, find_flowers
from flowerpose.sim.world_config import sim_preset
from flowerpose.stopwatch import Stopwatch

#: The published code's time per plant (docs/deviations.md), for the printed comparison.
UPSTREAM_SECONDS = (78, 105)

#: Seconds each simulator step may take for one realistic plant on this 2-core machine: a
#: 10-plant oracle benchmark then generates its plants in well under a minute.
SIMULATOR_BUDGET_S = {"plant": 2.0, "visibility": 3.0, "oracle_cloud": 5.0}


def simulator_seconds(seed: int = 0, repeat: int = 3, name: str = DEFAULT_PRESET
                      ) -> dict[str, float]:
    """Median wall seconds of the simulator's steps for plant `seed` of preset `name`:
    generating
    the plant, its flowers' visibility from the scan path, and its oracle cloud."""
    from flowerpose.scan_geometry import path_cameras
    from flowerpose.sim.oracle import sample_oracle_cloud
    from flowerpose.sim.plant import generate_plant
    from flowerpose.sim.visibility import flower_visibility
    from flowerpose.sim.world_config import OracleCloudConfig, preset

    runs: dict[str, list[float]] = {name: [] for name in SIMULATOR_BUDGET_S}
    for _ in range(repeat):
        watch = Stopwatch()
        with watch.step("plant"):
            plant = generate_plant(seed, preset(name))
        views = path_cameras(plant.center[:2], plant.height)[1]
        with watch.step("visibility"):
            flower_visibility(plant, views)
        with watch.step("oracle_cloud"):
            sample_oracle_cloud(plant, OracleCloudConfig(), views, np.random.default_rng(seed))
        for name, seconds in watch.seconds.items():
            runs[name].append(seconds)
    return {name: round(statistics.median(values), 4) for name, values in runs.items()}


def _oracle_cloud(plant: PlantSet, points: int, cache: Path | None) -> Cloud:
    """The plant's oracle cloud of `points` points, as `eval` makes it."""
    from flowerpose.eval.jobs.plants import generate_plant_files

    seed, sim = plant.seed, sim_preset(plant.preset)
    sim = dataclasses.replace(sim, oracle=dataclasses.replace(sim.oracle, points=points))
    with tempfile.TemporaryDirectory() as folder:
        generate_plant_files(seed, sim, Path(folder), cache)
        return read_cloud(Path(folder) / "cloud.ply")


@dataclass(frozen=True)
class BenchPlan:
    """What `flowerpose bench` times: the plant's oracle cloud at each of `point_counts`
    points, each detection `repeat` times (the median kept)."""

    point_counts: tuple[int, ...]
    repeat: int = 3


def run_bench(config: PipelineConfig, plan: BenchPlan, plant: PlantSet, out: Path | None = None,
              execution: Execution = LOCAL) -> dict:
    """Median wall seconds per stage over the plan's repeats for each cloud size of the one
    seeded `plant` (its preset's oracle cloud, and the simulator's steps for it); prints a
    table and writes bench.json to `out` when given. The clouds are the plant stage's
    (from the execution's stage cache when made before); the timed runs never are."""
    if plant.real or plant.plants != 1:
        raise InputError("seed", "bench times one seeded synthetic plant")
    repeat, seed, cache = plan.repeat, plant.seed, execution.cache
    results = []
    for points in plan.point_counts:
        LOG.info(f"a {points:,}-point cloud (seed {seed}, {plant.preset})...")
        cloud = _oracle_cloud(plant, points, cache)
        find_flowers(cloud, config)  # warm-up: first-call costs of Open3D and SciPy
        runs = [find_flowers(cloud, config) for _ in range(repeat)]
        stages = list(runs[0].timing_s)
        median = {s: round(statistics.median(r.timing_s[s] for r in runs), 4) for s in stages}
        results.append({"points": len(cloud), "flowers": len(runs[0].flowers),
                        "median_s": median,
                        "runs_total_s": [round(r.timing_s["total"], 4) for r in runs]})
    simulator = simulator_seconds(seed, repeat, plant.preset)
    report = {"run": run_record(), "results": results, "simulator_s": simulator,
              "simulator_budget_s": SIMULATOR_BUDGET_S, "repeat": repeat, "seed": seed,
              "cpu_count": os.cpu_count(), "config": to_dict(config)}
    print(bench_markdown(report), end="")
    if out is not None:
        write_json(out / "bench.json", report)
        print(f"bench: {out / 'bench.json'}")
    return report


def bench_markdown(report: dict) -> str:
    """bench.json as Markdown: seconds per pipeline stage at each size, then the simulator's
    steps against their budgets."""
    results = report["results"]
    stages = list(results[0]["median_s"])
    pipeline = markdown_table(["points", "flowers", *stages],
                              [[f"{r['points']:,}", str(r["flowers"]),
                                *(f"{r['median_s'][s]:.3f}" for s in stages)] for r in results])
    simulator = markdown_table(
        ["simulator step", "seconds", "budget"],
        [[name, f"{seconds:.3f}", f"{report['simulator_budget_s'][name]:g}"
          + ("" if seconds <= report["simulator_budget_s"][name] else " (over)")]
         for name, seconds in report["simulator_s"].items()])
    return (f"{pipeline}\n\nseconds, median of {report['repeat']} runs on "
            f"{report['cpu_count']} cores; the published code: {UPSTREAM_SECONDS[0]}-"
            f"{UPSTREAM_SECONDS[1]} s a plant\n\n{simulator}\n")
