"""Sweeps: the benchmark over a grid of settings, to tune grid resolution, DBSCAN and more.

Plants are generated once and shared by every setting (unless a `sim.*` setting varies),
then every (setting, plant) pair runs in one process pool. Writes `sweep.csv`, `sweep.png`
(the metrics per setting) and `best.json`.
"""

from __future__ import annotations

import csv
import io
import itertools
import time
from pathlib import Path

from flowerpose.atomic import write_figure, write_text
from flowerpose.config import apply_overrides, to_dict
from flowerpose.errors import InputError
from flowerpose.eval.harness import EvalConfig, evaluate_cloud, generate_plants, run_jobs
from flowerpose.eval.report import summarise
from flowerpose.jsonio import write_json

METRICS = ("recall", "recall_visible", "fp_rate", "plane_mean_deg", "superellipsoid_mean_deg",
           "paraboloid_mean_deg", "seconds_per_plant")


def parse_grid(items: list[str], config: EvalConfig) -> list[tuple[str, list[str]]]:
    """`["cluster.eps=0.008,0.01", ...]` to [(key, values)], each value checked against the
    config so a typo fails before any work starts."""
    grid = []
    for item in items:
        key, sep, values = item.partition("=")
        choices = [v.strip() for v in values.split(",") if v.strip()]
        if not sep or not key.strip() or not choices:
            raise InputError("--grid", f"expected key=v1,v2,..., got {item!r}")
        if key.strip() in (k for k, _ in grid):
            raise InputError("--grid", f"{key.strip()} is given twice; put all its values in "
                             "one --grid")
        for value in choices:
            apply_overrides(config, {key.strip(): value})
        grid.append((key.strip(), choices))
    return grid


def _row(setting: dict[str, str], entries: list[dict], seconds: list[float]) -> dict:
    s = summarise(entries)
    row: dict = dict(setting)
    row.update({"recall": s["recall"], "recall_visible": s["recall_visible"],
                "fp_rate": s["fp_rate"], "detections": s["detections"], "fp": s["fp"]})
    for method in ("plane", "superellipsoid", "paraboloid"):
        row[f"{method}_mean_deg"] = s["error_deg"][method]["mean"]
        row[f"{method}_median_deg"] = s["error_deg"][method]["median"]
        row[f"{method}_failed"] = s["failed"][method]
    row["seconds_per_plant"] = round(sum(seconds) / len(seconds), 4)
    return row


def best_row(rows: list[dict]) -> dict:
    """The best setting: most visible flowers found, then fewest false positives, then the
    smallest plane error."""
    def key(row: dict) -> tuple:
        return (-(row["recall_visible"] or 0.0), row["fp_rate"] or 0.0,
                row["plane_mean_deg"] if row["plane_mean_deg"] is not None else 1e9)
    return min(rows, key=key)


def _plot(path: Path, rows: list[dict], keys: list[str]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = [", ".join(f"{k.split('.')[-1]}={r[k]}" for k in keys) for r in rows]
    fig, axes = plt.subplots(len(METRICS), 1, figsize=(max(6, 0.6 * len(rows) + 3),
                                                       2.0 * len(METRICS)), sharex=True)
    for ax, metric in zip(axes, METRICS, strict=True):
        values = [r[metric] if r[metric] is not None else float("nan") for r in rows]
        ax.plot(range(len(rows)), values, "o-")
        ax.set_ylabel(metric.replace("_", " "), fontsize=8)
        ax.grid(alpha=0.3)
    axes[-1].set_xticks(range(len(rows)), labels, rotation=45, ha="right", fontsize=8)
    fig.suptitle("flowerpose sweep")
    fig.tight_layout()
    write_figure(path, fig)
    plt.close(fig)


def sweep_outputs(grid: list[tuple[str, list[str]]]) -> tuple[str, ...]:
    """The top-level entries `run_sweep` writes for `grid` (`outputs.OutputFolder`)."""
    count = 1
    for _, values in grid:
        count *= len(values)
    plants = ([f"plants-{k}" for k in range(count)] if any(k.startswith("sim.") for k, _ in grid)
              else ["plants"])
    return ("sweep.csv", "sweep.png", "best.json", *plants,
            *(f"setting-{k}" for k in range(count)))


def run_sweep(config: EvalConfig, grid: list[tuple[str, list[str]]], plants: int, seed: int,
              out_dir: Path, workers: int | None = None) -> dict:
    """Evaluate every combination of the grid over `plants` seeded plants; returns the best
    row (its settings and metrics)."""
    if plants < 1:
        raise InputError("--plants", f"must be at least 1, got {plants}")
    start = time.perf_counter()
    keys = [key for key, _ in grid]
    settings = [dict(zip(keys, combo, strict=True))
                for combo in itertools.product(*(values for _, values in grid))]
    configs = [apply_overrides(config, s) for s in settings]
    seeds = list(range(seed, seed + plants))
    sim_varies = any(k.startswith("sim.") for k in keys)
    plant_dirs = []
    for k, cfg in enumerate(configs):
        if k == 0 or sim_varies:
            base = out_dir / (f"plants-{k}" if sim_varies else "plants")
            generate_plants(seeds, cfg.sim, base, workers)
        plant_dirs.append(base)
    jobs = [(plant_dirs[k] / f"seed-{s}" / "cloud.ply", plant_dirs[k] / f"seed-{s}" / "plant.json",
             cfg, out_dir / f"setting-{k}" / f"seed-{s}", f"seed-{s}")
            for k, cfg in enumerate(configs) for s in seeds]
    results = run_jobs(evaluate_cloud, jobs, workers,
                       lambda j, v: f"setting {j // len(seeds)} {v[0]['plant']}: "
                       f"{v[0]['found']}/{v[0]['gt']} found, {v[0]['fp']} fp")
    rows = []
    for k, setting in enumerate(settings):
        chunk = results[k * len(seeds):(k + 1) * len(seeds)]
        rows.append(_row(setting, [e for e, _ in chunk], [t["total"] for _, t in chunk]))
    table = io.StringIO()
    writer = csv.DictWriter(table, fieldnames=list(rows[0]))
    writer.writeheader()
    writer.writerows(rows)
    write_text(out_dir / "sweep.csv", table.getvalue())
    _plot(out_dir / "sweep.png", rows, keys)
    best = best_row(rows)
    write_json(out_dir / "best.json",
               {"best": best, "rows": rows, "plants": plants, "seed": seed,
                "config": to_dict(config), "seconds": round(time.perf_counter() - start, 2)})
    for row in rows:
        print(", ".join(f"{k}={row[k]}" for k in keys) + f": recall_visible "
              f"{row['recall_visible']}, fp_rate {row['fp_rate']}, plane "
              f"{row['plane_mean_deg']}°, {row['seconds_per_plant']} s/plant")
    print(f"sweep: {out_dir / 'sweep.csv'}, {out_dir / 'sweep.png'}, {out_dir / 'best.json'}")
    return best
