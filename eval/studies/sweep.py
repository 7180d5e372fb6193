"""Sweeps: the benchmark over a grid of settings, to tune grid resolution, DBSCAN and more.

Plants are generated once and shared by every setting (unless a `sim.*` setting varies),
then every (setting, plant) pair is scored in one process pool. Writes `sweep.csv` (a row per
setting), `sweep.png` (each metric per setting, its spread over the plants) and `best.json`
(the best setting, its metrics and whole config; every setting with its plants' metrics).
With the pollination task, each setting's plants are visited as `eval --task pollinate`
visits them (a study of the pollinator's geometry or the planner's settings; a pool for
each setting's visits in turn), and the share of flowers pollinated ranks the settings.
"""

from __future__ import annotations

import csv
import io
import itertools
from collections.abc import Iterable
from pathlib import Path

from flowerpose.atomic import write_figure, write_text
from flowerpose.config import apply_overrides, current_name, to_dict, value_at
from flowerpose.errors import InputError
from flowerpose.eval.jobs.config import WORLD_SECTIONS, EvalConfig, settings_run
from flowerpose.eval.jobs.eval_run import EvalRun
from flowerpose.eval.jobs.plant_set import PlantSet
from flowerpose.eval.jobs.plants import Plants, score_job
from flowerpose.eval.pool import LOCAL, Execution, run_jobs
from flowerpose.eval.reports.report import summarise
from flowerpose.eval.scoring.paired import compare_runs, pollinated_verdict
from flowerpose.eval.scoring.stats import FLIP_DEG, GROSS_DEG, mcnemar, p_text
from flowerpose.jsonio import write_json
from flowerpose.stopwatch import Stopwatch

METRICS = ("recall", "recall_visible", "fp_rate", "plane_mean_deg", "superellipsoid_mean_deg",
           "paraboloid_mean_deg", "seconds_per_plant")
#: sweep.png's metrics for a sweep of the pollination task.
POLLINATION_METRICS = ("pollinated", "pollinated_ceiling", "collision_share", "recall_visible",
                       "plane_mean_deg")


def parse_grid(items: list[str], config: EvalConfig) -> list[tuple[str, list[str]]]:
    """`["cluster.eps=0.008,0.01", ...]` to [(key, values)], each value checked against the
    config so a typo fails before any work starts."""
    grid = []
    for item in items:
        key, sep, values = item.partition("=")
        choices = [v.strip() for v in values.split(",") if v.strip()]
        if not sep or not key.strip() or not choices:
            raise InputError("grid", f"expected key=v1,v2,..., got {item!r}")
        key = current_name(key.strip())
        if key in (k for k, _ in grid):
            raise InputError("grid", f"{key} is given twice; put all its values in one --grid")
        for value in choices:
            apply_overrides(config, {key: value})
        grid.append((key, choices))
    return grid


def _metrics(entries: list[dict], seconds: list[float], intervals: bool = True) -> dict:
    """The sweep's metrics over plant entries (pooled: a recall is found over all the
    plants' flowers; the 95 % bounds of the recall of visible flowers, the precision and
    the plane error's mean, over plants then flowers) and their mean wall seconds per
    plant. `intervals=False` leaves the bounds out (a single plant's row)."""
    s = summarise(entries, intervals)
    metrics = {"recall": s["recall"], "recall_visible": s["recall_visible"],
               "recall_visible_low": s["recall_visible_ci95"]["low"],
               "recall_visible_high": s["recall_visible_ci95"]["high"],
               "fp_rate": s["fp_rate"], "precision_low": s["precision_ci95"]["low"],
               "detections": s["detections"], "fp": s["fp"]}
    for method in ("plane", "superellipsoid", "paraboloid"):
        errors = s["error_deg"][method]
        metrics[f"{method}_mean_deg"] = errors["mean"]
        metrics[f"{method}_median_deg"] = errors["median"]
        metrics[f"{method}_failed"] = s["failed"][method]
    plane = s["error_deg"]["plane"]["mean_ci95"]
    metrics["plane_mean_low_deg"], metrics["plane_mean_high_deg"] = plane["low"], plane["high"]
    metrics.update(tail_metrics(entries, s))
    metrics["seconds_per_plant"] = round(sum(seconds) / len(seconds), 4)
    if entries and all("pollination" in e for e in entries):
        metrics.update(pollination_metrics(entries, intervals))
    return metrics


def pollination_metrics(entries: list[dict], intervals: bool = True) -> dict:
    """A pollination sweep's metrics over plant entries: the share of flowers pollinated
    from the estimated poses and from the true ones (the planner's ceiling), with their
    Wilson 95 % bounds (`pollinated.summarise_pollination`); the visits, the visits that
    collided or pushed a leaf and their share; the flowers no approach reached."""
    from flowerpose.eval.scoring.pollinated import summarise_pollination

    metrics: dict = {}
    for name, key in (("pollinated", "pollination"), ("pollinated_ceiling",
                                                      "pollination_ceiling")):
        summary = summarise_pollination([e[key] for e in entries])
        bounds = summary["success_rate_ci95"] if intervals else {}
        metrics.update({name: summary["success_rate"], f"{name}_low": bounds.get("low"),
                        f"{name}_high": bounds.get("high"),
                        f"{name}_flowers": summary["successes"]})
        if key == "pollination":
            metrics.update(flowers=summary["flowers"], visits=summary["visits"],
                           collisions=summary["failures"]["collision"],
                           collision_share=summary["collision_share"],
                           unreachable=summary["failures"]["unreachable"])
    return metrics


def pollinated_against(ours: list[dict], defaults: list[dict]) -> dict:
    """A setting's pollinated flowers against the defaults' on the same plants: the
    flowers only one of them pollinated, and McNemar's exact test of the difference."""
    def pollinated(entries: list[dict]) -> set:
        return {(e["plant"], o["flower"]) for e in entries
                for o in e["pollination"]["flowers"] if o["outcome"] == "success"}

    flowers = sum(len(e["pollination"]["flowers"]) for e in ours)
    return mcnemar(pollinated(ours), pollinated(defaults), flowers)


def tail_metrics(entries: list[dict], summary: dict) -> dict:
    """The plane error's tails over plant entries: flipped normals and flowers over 20°
    (counts, and their shares' 95 % bounds), the 90th percentile with its bounds, and the
    worst flower."""
    plane = summary["error_deg"]["plane"]
    worst = max(((m["error_deg"]["plane"], f"{p['plant']} flower {m['truth']}")
                 for p in entries for m in p.get("matches", [])
                 if (m.get("error_deg") or {}).get("plane") is not None), default=None)
    errors = [e for p in entries for e in p["error_deg"]["plane"]]
    return {"flipped": sum(e > FLIP_DEG for e in errors),
            "flipped_high": plane["over_90_ci95"]["high"],
            "over_20": sum(e > GROSS_DEG for e in errors),
            "over_20_high": plane["over_20_ci95"]["high"],
            "plane_p90_deg": plane["p90"], "plane_p90_low_deg": plane["p90_ci95"]["low"],
            "plane_p90_high_deg": plane["p90_ci95"]["high"],
            "worst_deg": None if worst is None else worst[0],
            "worst_flower": None if worst is None else worst[1]}


def best_row(rows: list[dict]) -> dict:
    """The best setting: never one that flips a normal the defaults did not
    (`new_flipped`), then ranked by the intervals, not the point values: the highest lower
    bound of the recall of visible flowers, then of the precision, then the lowest upper
    bound of the plane error's mean (a setting that looks better on few flowers does not
    outrank one shown good on many). A pollination sweep's rows rank by the lower bound
    of the share pollinated first, then of the planner's ceiling, then the fewest
    collisions (`POLLINATION_RULE`)."""
    def key(row: dict) -> tuple:
        high = row["plane_mean_high_deg"]
        pollination = (() if "pollinated" not in row else
                       (-(row["pollinated_low"] or 0.0), -(row["pollinated_ceiling_low"] or 0.0),
                        row["collisions"]))
        return (row.get("new_flipped", 0) > 0, *pollination,
                -(row["recall_visible_low"] or 0.0),
                -(row["precision_low"] or 0.0), high if high is not None else 1e9)
    return min(rows, key=key)


#: A setting's comparison with the defaults where the grid changes the plants themselves
#: (`sim.plant.*`): a flower of one side is not the other's, so nothing is paired.
UNPAIRED = {"distinguishable": False, "paired": False,
            "verdicts": ["not compared flower by flower: the grid changes the plants "
                         "(sim.plant.*), so no flower is on both sides"],
            "plane": {"mean_difference": None, "ci95": {"low": None, "high": None}},
            "found": None, "fp": None, "new": {"flipped": [], "over_20": []}}


def _changes_plants(keys: Iterable[str]) -> bool:
    """Whether the grid changes the generated plants' geometry (`sim.plant.*`), not only
    their clouds or captures, so that a seed's flowers differ from setting to setting."""
    return any(key.startswith("sim.plant.") for key in keys)


def against_defaults(ours: list[dict], defaults: list[dict], keys: Iterable[str]) -> dict:
    """A setting's plant entries against the defaults' on the same plants
    (`paired.compare_runs`), and whether any difference is shown: found flowers, false
    positives or a fit's paired error. `keys`: the settings that differ from the defaults;
    where they change the plants themselves, nothing is paired (`UNPAIRED`)."""
    if _changes_plants(keys):
        return {**UNPAIRED}
    paired = compare_runs(ours, defaults)
    shown = (paired["found"]["shown"] or paired["fp"]["shown"]
             or any(fit["shown"] for fit in paired["fits"].values()))
    compared = {"distinguishable": bool(shown), "paired": True,
                "verdicts": paired["verdicts"], "plane": paired["fits"]["plane"],
                "found": paired["found"], "fp": paired["fp"], "new": paired["new"]}
    if ours and all("pollination" in e for e in (*ours, *defaults)):
        pollinated = pollinated_against(ours, defaults)
        compared.update(pollinated=pollinated,
                        distinguishable=compared["distinguishable"] or pollinated["shown"],
                        verdicts=[*compared["verdicts"], pollinated_verdict(pollinated)])
    return compared


#: What each metric's axis in sweep.png says, with its unit.
METRIC_LABELS = {"recall": "recall", "recall_visible": "recall (visible)",
                 "fp_rate": "false positives\n(of detections)",
                 "plane_mean_deg": "plane error (°)",
                 "superellipsoid_mean_deg": "superellipsoid\nerror (°)",
                 "paraboloid_mean_deg": "paraboloid error (°)",
                 "seconds_per_plant": "seconds per plant",
                 "pollinated": "pollinated\n(estimated poses)",
                 "pollinated_ceiling": "pollinated\n(true poses)",
                 "collision_share": "collisions\n(of visits)"}


def setting_label(setting: dict) -> str:
    """A setting as its full dotted keys and values, one a line."""
    return "\n".join(f"{key}={value}" for key, value in setting.items())


def sweep_figure(settings: list[dict], pooled: list[dict], per_plant: list[list[dict]],
                 best: int, metrics: tuple[str, ...] = METRICS):
    """sweep.png's figure: per metric (`METRICS`, or a pollination sweep's
    `POLLINATION_METRICS`), each setting a category on the x axis (nothing joins them), its
    plants' values as a box and points, the value over all its plants as a diamond, and
    the best setting shaded and named.

    settings: the grid's settings (full dotted keys, typed values); pooled: their metrics
    over all plants; per_plant: per setting, each plant's metrics; best: the best
    setting's index."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    rng = np.random.default_rng(0)  # the points' sideways jitter, the same every run
    count = len(settings)
    fig, axes = plt.subplots(len(metrics), 1, sharex=True, squeeze=False,
                             figsize=(max(6.0, 1.3 * count + 3), 1.9 * len(metrics) + 1.2))
    for ax, metric in zip(axes[:, 0], metrics, strict=True):
        ax.axvspan(best - 0.45, best + 0.45, color="gold", alpha=0.25, zorder=0)
        for k, plants in enumerate(per_plant):
            values = np.array([m[metric] for m in plants if m[metric] is not None], float)
            if len(values) > 1:
                ax.boxplot([values], positions=[k], widths=0.5, showfliers=False,
                           medianprops={"color": "tab:blue"}, manage_ticks=False)
            if len(values):
                ax.scatter(k + rng.uniform(-0.12, 0.12, len(values)), values, s=12,
                           color="tab:blue", alpha=0.6, zorder=3,
                           label="a plant" if k == 0 else None)
            if pooled[k][metric] is not None:
                ax.scatter([k], [pooled[k][metric]], marker="D", s=30, color="black",
                           zorder=4, label="all plants" if k == 0 else None)
        ax.set_ylabel(METRIC_LABELS[metric], fontsize=8)
        ax.grid(axis="y", alpha=0.3)
    axes[0, 0].legend(fontsize=7, loc="best")
    labels = [setting_label(s) + ("\n(best)" if k == best else "")
              for k, s in enumerate(settings)]
    axes[-1, 0].set_xticks(range(count), labels, fontsize=7)
    axes[-1, 0].get_xticklabels()[best].set_fontweight("bold")
    axes[-1, 0].set_xlim(-0.6, count - 0.4)
    fig.suptitle(f"flowerpose sweep: {len(per_plant[0])} plants per setting; best: "
                 + ", ".join(f"{key}={value}" for key, value in settings[best].items()),
                 fontsize=9)
    fig.tight_layout()
    return fig


def _separate_plants(keys: list[str], source: str) -> bool:
    """Whether each setting needs plants (and clouds) of its own: the grid varies a
    section the source's clouds depend on (`config.WORLD_SECTIONS`)."""
    return any(key.startswith(f"{section}.") for key in keys
               for section in WORLD_SECTIONS[source])


def sweep_outputs(grid: list[tuple[str, list[str]]], source: str = "oracle",
                  folders: Iterable[Path] = ()) -> tuple[str, ...]:
    """The top-level entries `run_sweep` writes for `grid` (`outputs.OutputFolder`)."""
    count = 1
    for _, values in grid:
        count *= len(values)
    plants = ([] if source == "real" else [f"plants-{k}" for k in range(count)]
              if _separate_plants([k for k, _ in grid], source) else ["plants"])
    return ("sweep.csv", "sweep.png", "best.json", *plants,
            *(f"setting-{k}" for k in range(count)), "setting-defaults",
            *(["plants-defaults"] if plants and plants != ["plants"] else []))


def run_sweep(config: EvalConfig, grid: list[tuple[str, list[str]]], plants: PlantSet | EvalRun,
              out_dir: Path, execution: Execution = LOCAL) -> dict:
    """Evaluate every combination of the grid over `plants` (seeded plants' clouds from a
    source, or real folders; an `EvalRun` for its task too: "pollinate" visits each
    setting's plants as `eval --task pollinate` does); writes sweep.csv, sweep.png and
    best.json, and returns best.json's "best": the best setting (dotted keys, typed values),
    its metrics and its whole resolved config. Plants are generated, and for scan and rgbd
    filmed and reconstructed, once for all settings unless a setting changes them; the
    execution's stage cache is where those captures are taken from and put into."""
    run = plants if isinstance(plants, EvalRun) else EvalRun(plants)
    plant_set, source = run.plants, run.plants.source
    workers, cache = execution.workers, execution.cache
    watch = Stopwatch()
    keys = [key for key, _ in grid]
    settings = [dict(zip(keys, combo, strict=True))
                for combo in itertools.product(*(values for _, values in grid))]
    # The last configuration run is the defaults (the settings without the grid's), which
    # every setting is compared with flower by flower.
    configs = [apply_overrides(config, s) for s in settings] + [config]
    made = Plants(workers, cache)
    separate = _separate_plants(keys, source)
    jobs = []
    for k, cfg in enumerate(configs):
        folder = out_dir / (f"plants-{_name(k, settings)}" if separate else "plants")
        jobs.append(made.jobs(plant_set, cfg, folder).jobs)
    names = [job.name for job in jobs[0]]
    job_args = [(job, cfg, out_dir / f"setting-{_name(k, settings)}" / job.name, cache)
                for k, cfg in enumerate(configs) for job in jobs[k]]
    results = run_jobs(score_job, job_args, workers,
                       lambda j, v: f"setting {_name(j // len(names), settings)} "
                       f"{v[0]['plant']}: {v[0]['found']}/{v[0]['gt']} found, {v[0]['fp']} fp",
                       stage="sweep evaluation",
                       labels=[f"setting {_name(k, settings)} {name}"
                               for k in range(len(configs)) for name in names])
    # The values as the config holds them: 0.008 a number, "mask" a string, 14 an integer.
    typed = [{key: value_at(cfg, key) for key in keys} for cfg in configs[:-1]]
    entries = [[e for e, _ in results[k * len(names):(k + 1) * len(names)]]
               for k in range(len(configs))]
    if run.task == "pollinate":  # each setting's flights and pollination.png in its folder
        from flowerpose.eval.jobs.pollination_task import pollinate_plants

        for k, cfg in enumerate(configs):
            setting = out_dir / f"setting-{_name(k, settings)}"
            pollinate_plants(jobs[k], entries[k], cfg, setting, workers,
                             # A world made before for another setting is that one's.
                             [(job.truth.parent, setting / job.name) for job in jobs[k]])
    pooled, per_plant = [], []
    for k in range(len(configs)):
        chunk = results[k * len(names):(k + 1) * len(names)]
        pooled.append(_metrics(entries[k], [t["total"] for _, t in chunk]))
        per_plant.append([{"plant": e["plant"], **_metrics([e], [t["total"]], False)}
                          for e, t in chunk])
    defaults = {"setting": {key: value_at(config, key) for key in keys},
                "metrics": pooled[-1], "plants": per_plant[-1]}
    pooled, per_plant = pooled[:-1], per_plant[:-1]
    compared = [against_defaults(entries[k], entries[-1], keys) for k in range(len(settings))]
    rows = [{**setting, **metrics, "distinguishable_from_defaults": c["distinguishable"],
             "plane_vs_defaults_deg": c["plane"]["mean_difference"],
             "plane_vs_defaults_low_deg": c["plane"]["ci95"]["low"],
             "plane_vs_defaults_high_deg": c["plane"]["ci95"]["high"],
            "new_flipped": len(c["new"]["flipped"]), "new_over_20": len(c["new"]["over_20"])}
            for setting, metrics, c in zip(typed, pooled, compared, strict=True)]
    if run.task == "pollinate":
        for row, c in zip(rows, compared, strict=True):
            against = c.get("pollinated") or {}
            row.update(pollinated_won=against.get("only_ours"),
                       pollinated_lost=against.get("only_theirs"),
                       pollinated_vs_defaults_p=against.get("p"))
    best_index = rows.index(best_row(rows))
    table = io.StringIO()
    writer = csv.DictWriter(table, fieldnames=list(rows[0]))
    writer.writeheader()
    writer.writerows(rows)
    write_text(out_dir / "sweep.csv", table.getvalue())
    import matplotlib.pyplot as plt

    figure = sweep_figure(typed, pooled, per_plant, best_index,
                          POLLINATION_METRICS if run.task == "pollinate" else METRICS)
    write_figure(out_dir / "sweep.png", figure)
    plt.close(figure)
    best = {"setting": typed[best_index], "metrics": pooled[best_index],
            "vs_defaults": compared[best_index],
            "config": settings_run(configs[best_index], "real" if source == "real"
                                   else "oracle", [job.start for job in jobs[best_index]])}
    if run.task == "pollinate":  # the visits' settings too, as eval's report records them
        best["config"].update(pollinate=to_dict(configs[best_index].pollinate),
                              pollination=to_dict(configs[best_index].pollination))
    write_json(out_dir / "best.json",
               {"best": best, "grid": {key: [value_at(apply_overrides(config, {key: v}), key)
                                             for v in values] for key, values in grid},
                "settings": [{"setting": t, "metrics": m, "plants": p, "vs_defaults": c}
                             for t, m, p, c in zip(typed, pooled, per_plant, compared,
                                                   strict=True)],
                "defaults": defaults, "task": run.task,
                "rule": POLLINATION_RULE if run.task == "pollinate" else RANKING_RULE,
                "plants": len(names), "seed": None if plant_set.real else plant_set.seed,
                "source": source,
                "seconds": round(watch.elapsed(), 2)})
    for row, against in zip(rows, compared, strict=True):
        # The pollinated comparison, last where there is one, has its own line below.
        pose_verdicts = against["verdicts"][:-1 if "pollinated" in against else None]
        print(", ".join(f"{k}={row[k]}" for k in keys) + f": recall_visible "
              f"{row['recall_visible']} {_bounds(row, 'recall_visible', 3)}, fp_rate "
              f"{row['fp_rate']}, plane {row['plane_mean_deg']}° "
              f"{_bounds(row, 'plane_mean', 2, '_deg')}, p90 {row['plane_p90_deg']}° "
              f"{_bounds(row, 'plane_p90', 1, '_deg')}, {row['flipped']} flipped "
              f"({row['new_flipped']} new), {row['over_20']} over 20°, worst "
              f"{row['worst_deg']}° ({row['worst_flower']}), {row['seconds_per_plant']} s/plant; "
              "against the defaults: "
              + "; ".join(pose_verdicts[:1] + pose_verdicts[3:]))
        if run.task == "pollinate":
            share = "-" if row["pollinated"] is None else f"{row['pollinated']:.1%}"
            versus = (f"; against the defaults {row['pollinated_won']} won, "
                      f"{row['pollinated_lost']} lost (McNemar p "
                      f"{p_text(row['pollinated_vs_defaults_p'])})" if against["paired"]
                      else "")
            print(f"  pollinated {row['pollinated_flowers']} of {row['flowers']} "
                  f"({share}) {_bounds(row, 'pollinated', 3)}, from the true "
                  f"poses {row['pollinated_ceiling_flowers']} "
                  f"{_bounds(row, 'pollinated_ceiling', 3)}, {row['unreachable']} unreachable, "
                  f"{row['collisions']} collisions in {row['visits']} visits{versus}")
    print(f"sweep: {out_dir / 'sweep.csv'}, {out_dir / 'sweep.png'}, {out_dir / 'best.json'}")
    return best


#: How the best setting is chosen (best.json's "rule").
RANKING_RULE = ("never a setting that flips a normal the defaults did not; then the highest "
                "95 % lower bound of the recall of visible flowers, then of the precision, "
                "then the lowest upper bound of the plane error's mean")


#: How a pollination sweep's best setting is chosen.
POLLINATION_RULE = ("never a setting that flips a normal the defaults did not; then the highest "
                    "95 % lower bound of the share of flowers pollinated from the estimated "
                    "poses, then from the true poses, then the fewest collisions; then as "
                    "RANKING_RULE")


def _name(k: int, settings: list[dict]) -> str:
    """A configuration's folder name: its index in the grid, or "defaults" for the last."""
    return "defaults" if k == len(settings) else str(k)


def _bounds(row: dict, key: str, digits: int, unit: str = "") -> str:
    low, high = row[f"{key}_low{unit}"], row[f"{key}_high{unit}"]
    return "" if low is None else f"[{low:.{digits}f}, {high:.{digits}f}]"
