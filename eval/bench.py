"""Speed benchmark: a cloud to flower poses, per stage, at the paper's phone-scan density
(125,000 points) and beyond. Imports, plant generation and file reading are excluded."""

from __future__ import annotations

import os
import statistics
from pathlib import Path

from flowerpose.config import to_dict
from flowerpose.eval.report import markdown_table
from flowerpose.jsonio import write_json
from flowerpose.log import LOG
from flowerpose.pipeline.flowers import PipelineConfig, find_flowers
from flowerpose.sim.bundle import make_plant

#: The published code's time per plant (upstream.md), for the printed comparison.
UPSTREAM_SECONDS = (78, 105)


def run_bench(point_counts: list[int], repeat: int = 3, seed: int = 3,
              out: Path | None = None, config: PipelineConfig | None = None) -> dict:
    """Median wall seconds per stage over `repeat` runs for each cloud size; prints a table
    and writes bench.json to `out` when given."""
    config = config or PipelineConfig()
    results = []
    for points in point_counts:
        LOG.info(f"generating a {points:,}-point cloud (seed {seed}, realistic)...")
        cloud = make_plant(seed, points=points).cloud
        find_flowers(cloud, config)  # warm-up: first-call costs of Open3D and SciPy
        runs = [find_flowers(cloud, config) for _ in range(repeat)]
        stages = list(runs[0].timing_s)
        median = {s: round(statistics.median(r.timing_s[s] for r in runs), 4) for s in stages}
        results.append({"points": len(cloud), "flowers": len(runs[0].flowers),
                        "median_s": median,
                        "runs_total_s": [round(r.timing_s["total"], 4) for r in runs]})
    stages = list(results[0]["median_s"])
    print(markdown_table(["points", "flowers", *stages],
                         [[f"{r['points']:,}", str(r["flowers"]),
                           *(f"{r['median_s'][s]:.3f}" for s in stages)] for r in results]))
    print(f"seconds, median of {repeat} runs on {os.cpu_count()} cores; the published code: "
          f"{UPSTREAM_SECONDS[0]}-{UPSTREAM_SECONDS[1]} s a plant")
    report = {"results": results, "repeat": repeat, "seed": seed, "cpu_count": os.cpu_count(),
              "config": to_dict(config)}
    if out is not None:
        write_json(out / "bench.json", report)
        print(f"bench: {out / 'bench.json'}")
    return report
