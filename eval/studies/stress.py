"""The robustness report (`flowerpose stress`): the pipeline over seeded perturbations of its
clouds, scored against the same truth, against the perturbation's strength.

Each plant (a real plant folder, or a synthetic plant's cloud from any `eval` source) runs
once as it is (the baseline) and once per perturbation and repeat (`flowerpose/perturb.py`
says what each does and in what unit). For a real plant's candidates each file is thinned
on its own (a seeded uniform subsample of each, as a coarser scan would give every view),
a dropped view is one candidates file left out, and colour and noise act on the merged
points; for a whole cloud a dropped view is one grid view's detections left out. For the
scan source the capture's own knobs are perturbations too: fewer frames chosen
(`scan.frames.count`) and a lower image resolution (`scan.camera.width` x
`scan.camera.height`), each filmed and reconstructed once (stage cache).

Writes stress.json (every row: the perturbation, its repeats, the summary as report.json's,
flipped normals and the median points per flower found), stress.md, stress.png (a panel
per perturbation kind: recall of visible flowers and plane error against the strength,
the unperturbed values marked) and report.html (the same, interactive).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from flowerpose.atomic import write_figure, write_text
from flowerpose.config import to_dict
from flowerpose.errors import InputError
from flowerpose.eval.jobs.plant_set import PlantSet
from flowerpose.eval.pool import LOCAL, Execution, run_jobs
from flowerpose.eval.reports.report import markdown_table, run_record, summarise
from flowerpose.eval.scoring.paired import compare_runs, difference_cell, record_cell
from flowerpose.eval.scoring.stats import GROSS_DEG as STATS_GROSS_DEG
from flowerpose.eval.scoring.stats import interval_text
from flowerpose.jsonio import write_json
from flowerpose.perturb import KINDS, UNITS, Perturbation
from flowerpose.stopwatch import Stopwatch

if TYPE_CHECKING:  # the harness's plants import the simulator: the command line does not
    from flowerpose.eval.jobs.plants import Perturbed, PlantJob

#: The default strengths of each perturbation: thinning through the envelope's lower
#: bound (50 points a flower) and beyond, exposure and a cast of one channel at the
#: envelope's bounds and inside, position noise up to its bound (metres).
DEFAULT_LEVELS: dict[str, tuple[float, ...]] = {
    "thin": (0.5, 0.2, 0.1, 0.05), "exposure": (0.6, 0.8, 1.3), "cast": (-0.15, 0.15),
    "noise": (0.0005, 0.001, 0.0015), "cut": (0.25, 0.5)}
#: The operating envelope's bound of each perturbation (DESIGN.md, "The operating
#: envelope"): stress.md marks the rows at it.
ENVELOPE_BOUNDS: dict[str, tuple[float, ...]] = {
    "exposure": (0.6, 1.3), "cast": (-0.15, 0.15), "noise": (0.0015,)}
#: Capture knobs of the scan source (`scan.frames.count`, `scan.camera.width` x
#: `scan.camera.height`).
CAPTURE_KINDS = ("frames", "resolution")
#: The strength at which each perturbation leaves a cloud as it is: the unperturbed run's
#: place on its kind's curve.
IDENTITY = {"thin": 1.0, "exposure": 1.0, "cast": 0.0, "noise": 0.0, "cut": 0.0}
#: A plane error beyond this is a flipped normal, degrees.
FLIPPED_DEG = 90.0
#: What stress writes into its --out folder.
STRESS_FILES = ("stress.json", "stress.md", "stress.png", "report.html", "plants", "runs")


@dataclass(frozen=True)
class Variant:
    """One thing a plant is run under: a cloud perturbation, a scan capture's knob, or
    neither (the baseline)."""

    perturbation: Perturbation | None = None
    capture: tuple[str, str] | None = None
    """("frames", "100") or ("resolution", "640x360"): a scan capture setting."""

    @property
    def label(self) -> str:
        if self.perturbation is not None:
            return self.perturbation.label
        if self.capture is not None:
            return f"{self.capture[0]} {self.capture[1]}"
        return "none"

    @property
    def kind(self) -> str:
        if self.perturbation is not None:
            return self.perturbation.kind
        return self.capture[0] if self.capture is not None else "none"

    @property
    def value(self) -> float:
        if self.perturbation is not None:
            return self.perturbation.value
        if self.capture is None:
            return math.nan
        kind, text = self.capture
        return float(text) if kind == "frames" else float(text.split("x")[0])

    def to_json(self) -> dict:
        if self.perturbation is not None:
            return self.perturbation.to_json()
        if self.capture is not None:
            unit = "frames chosen" if self.capture[0] == "frames" else "width x height, pixels"
            return {"kind": self.capture[0], "value": self.capture[1], "unit": unit}
        return {"kind": "none"}


@dataclass(frozen=True)
class StressPlan:
    """What `flowerpose stress` runs."""

    variants: tuple[Variant, ...]
    """Every perturbation or capture knob, the baseline left out (it always runs)."""
    repeats: int = 1
    """Seeded repeats of each random perturbation (thinning, noise, cut)."""
    seed: int = 0
    """Seed of the perturbations (each plant, perturbation and repeat draws its own)."""
    compare: dict[str, Any] = field(default_factory=dict)
    """Other settings by name (EvalConfigs, e.g. the published method's profile), run on
    the very same perturbed clouds and compared flower by flower at every level."""

    def __post_init__(self):
        if self.repeats < 1:
            raise InputError("repeats", f"must be at least 1, got {self.repeats}")


def plan_from(levels: dict[str, list[float]], channels: str = "rgb", drop_views: int = 0,
              capture: dict[str, list[str]] | None = None, repeats: int = 1,
              seed: int = 0, compare: dict[str, Any] | None = None) -> StressPlan:
    """A plan from the strengths of each kind (`DEFAULT_LEVELS`' keys), the channels a cast
    acts on, how many views are dropped one at a time (the first `drop_views`), and the
    scan capture's knobs (frames, resolution)."""
    variants: list[Variant] = []
    for kind in KINDS:
        if kind == "drop_view":
            variants += [Variant(Perturbation("drop_view", k)) for k in range(drop_views)]
            continue
        for value in levels.get(kind, ()):
            if kind == "cast":
                variants += [Variant(Perturbation("cast", value, c)) for c in channels]
            else:
                variants.append(Variant(Perturbation(kind, value)))  # type: ignore[arg-type]
    for kind, values in (capture or {}).items():
        if kind not in CAPTURE_KINDS:
            raise InputError(kind, f"not a capture knob ({', '.join(CAPTURE_KINDS)})")
        variants += [Variant(capture=(kind, v)) for v in values]
    variants = [v for v in variants if v.perturbation is None or not v.perturbation.is_identity()]
    return StressPlan(tuple(variants), repeats, seed, dict(compare or {}))


def _random(variant: Variant) -> bool:
    return variant.kind in ("thin", "noise", "cut")


def _perturbed(variant: Variant, repeat: int, seed: int) -> Perturbed | None:
    """What a job is scored under for a variant: its cloud perturbation, drawn per plant and
    repeat from `seed` (a capture knob or the baseline: the cloud as captured)."""
    from flowerpose.eval.jobs.plants import Perturbed

    if variant.perturbation is None:
        return None
    return Perturbed(variant.perturbation, repeat, seed)


def _stress_job(job: PlantJob, perturbed: Perturbed | None, config: Any, folder: Path,
                cache: Path | None) -> dict:
    """One plant's cloud under a perturbation (or as captured), detected and scored through
    the job's own `score`, and the median points of the flowers it found."""
    entry, _ = job.score(config, folder, cache, perturbed)
    from flowerpose.eval.jobs.plants import points_per_flower

    return {"entry": entry, "points": points_per_flower(folder / "flowers.json")}


def run_stress(config: Any, plan: StressPlan, plants: PlantSet, out_dir: Path,
               execution: Execution = LOCAL) -> dict:
    """The robustness report of `plants` (real folders, or seeded synthetic plants of a
    source): writes stress.json, stress.md, stress.png and report.html to out_dir and
    returns stress.json's content. `config`: an EvalConfig; the plan's `compare` settings
    run on the very same perturbed clouds."""
    from flowerpose.eval.jobs.config import pipeline_part
    from flowerpose.eval.jobs.plants import Plants

    workers, cache, compare = execution.workers, execution.cache, plan.compare

    watch = Stopwatch()
    variants = (Variant(),) + plan.variants
    capture = [v for v in variants if v.capture is not None]
    if capture and plants.source != "scan":
        raise InputError(capture[0].kind, "a capture knob needs --source scan")
    keyed = [(v, r) for v in variants for r in range(plan.repeats if _random(v) else 1)]
    runs = out_dir / "runs"
    made = Plants(workers, cache)
    if plants.real:
        jobs = {None: made.jobs(plants, config, out_dir / "plants").jobs}
    else:
        jobs = {v.capture: made.jobs(plants, _captured_with(config, v),
                                     out_dir / "plants" / (_folder(v, 0) if v.capture
                                                           else "as-captured")).jobs
                for v in [Variant(), *capture]}
    names = [job.name for job in jobs[None]]

    def scored(settings: Any, folder: Path) -> list[dict]:
        """Every (variant, repeat, plant) job under `settings`, its runs under `folder`."""
        job_args = [(job, _perturbed(v, r, plan.seed), settings,
                     folder / _folder(v, r) / job.name, cache)
                    for v, r in keyed for job in jobs[v.capture]]
        return run_jobs(_stress_job, job_args, workers, _describe(keyed, names),
                        stage="stress", labels=[a[0].name for a in job_args])

    rows = _rows(keyed, names, scored(config, runs),
                 {name: scored(other, runs / name) for name, other in compare.items()})
    report = {"run": run_record(), "config": {**plants.describe(), "repeats": plan.repeats,
                                              "stress_seed": plan.seed,
                                              "pipeline": to_dict(pipeline_part(config)),
                                              "compare": {name: to_dict(pipeline_part(other))
                                                          for name, other in
                                                          compare.items()}},
              "baseline": rows[0], "rows": rows[1:], "seconds": round(watch.elapsed(), 2)}
    write_json(out_dir / "stress.json", report)
    write_text(out_dir / "stress.md", stress_markdown(report))
    _write_figure(out_dir / "stress.png", report)
    _write_html(out_dir / "report.html", report)
    return report


def _folder(variant: Variant, repeat: int) -> str:
    return variant.label.replace(" ", "_") + (f"-r{repeat}" if repeat else "")


def _describe(keyed: list[tuple[Variant, int]], names: list[str]):
    def describe(k: int, value: dict) -> str:
        variant, _ = keyed[k // len(names)]
        entry = value["entry"]
        return (f"{variant.label}: {names[k % len(names)]}: {entry['found_visible']}/"
                f"{entry['visible']} found, {entry['fp']} fp")
    return describe


def _captured_with(config: Any, variant: Variant) -> Any:
    """The config a variant's plants are captured with: a capture knob's, or the run's."""
    if variant.capture is None:
        return config
    kind, text = variant.capture
    if kind == "frames":
        return dataclasses.replace(config, scan=dataclasses.replace(
            config.scan, frames=dataclasses.replace(config.scan.frames, count=int(text))))
    width, height = (int(v) for v in text.split("x"))
    camera = dataclasses.replace(config.scan.camera, width=width, height=height)
    return dataclasses.replace(config, scan=dataclasses.replace(config.scan, camera=camera))


def _rows(keyed: list[tuple[Variant, int]], names: list[str], results: list[dict],
          compared: dict[str, list[dict]]) -> list[dict]:
    """A row per variant (the baseline first): its repeats' plants summarised together, and
    each compared setting's on the same clouds, paired flower by flower (a flower is its
    plant's in one repeat)."""
    rows: list[dict] = []
    groups: dict[str, dict] = {}
    for k, (variant, repeat) in enumerate(keyed):
        at = slice(k * len(names), (k + 1) * len(names))
        group = groups.setdefault(variant.label, {"variant": variant, "ours": [],
                                                  "theirs": {n: [] for n in compared}})
        group["ours"] += [_in_repeat(c, repeat) for c in results[at]]
        for name, theirs in compared.items():
            group["theirs"][name] += [_in_repeat(c, repeat) for c in theirs[at]]
    for label, group in groups.items():
        ours = group["ours"]
        entries = [c["entry"] for c in ours]
        points = [c["points"] for c in ours if c["points"] is not None]
        rows.append({"label": label, "perturbation": group["variant"].to_json(),
                     "repeats": len(entries) // len(names), **_scores(entries),
                     "points_per_flower": (round(float(np.median(points)), 1)
                                           if points else None),
                     "plants": [{**e, "plane": e["error_deg"]["plane"]} for e in entries],
                     "compare": {name: {**_scores([c["entry"] for c in theirs]),
                                        "paired": compare_runs(
                                            entries, [c["entry"] for c in theirs])}
                                 for name, theirs in group["theirs"].items()}})
    return rows


def _in_repeat(result: dict, repeat: int) -> dict:
    """A job's result with its plant named by its repeat too ("seed-3 r2") and naming the
    plant it repeats (`repeat_of`): the same flower in two repeats is one flower seen twice
    (`eval/scoring/units.py`)."""
    entry = result["entry"]
    name = entry["plant"] if repeat == 0 else f"{entry['plant']} r{repeat}"
    return {**result, "entry": {**entry, "plant": name, "repeat_of": entry["plant"]}}


#: A plane error beyond this is a gross error (`stress` counts them per repeat).
GROSS_DEG = 30.0


def _scores(entries: list[dict]) -> dict:
    """A row's summary (report.json's), its flipped normals, the most plane errors over
    GROSS_DEG in one plant's repeat, and its worst flower (which, how far)."""
    plane = [e for p in entries for e in p["error_deg"]["plane"]]
    worst = max(((m["error_deg"]["plane"], p["plant"], str(m["truth"])) for p in entries
                 for m in p.get("matches", []) if (m.get("error_deg") or {}).get("plane")
                 is not None), default=None)
    return {"summary": summarise(entries), "flipped": sum(e > FLIPPED_DEG for e in plane),
            "worst_gross": max((sum(e > GROSS_DEG for e in p["error_deg"]["plane"])
                                for p in entries), default=0),
            "worst": None if worst is None else {"error_deg": worst[0], "plant": worst[1],
                                                 "flower": worst[2]}}


def _share(count: int, n: int, interval: dict) -> str:
    """"1 of 55 [0.00, 0.26]": a count of flowers with its share's interval."""
    return f"{count} of {n} {interval_text(interval, 2)}".rstrip()


def _cells(row: dict, baseline: dict) -> list[str]:
    summary = row["summary"]
    plane = summary["error_deg"]["plane"]
    recall = summary["recall_visible"]
    base = baseline["summary"]["recall_visible"]
    relative = "-" if not base or recall is None else f"{recall / base:.2f}"
    over_20 = round((plane.get("over_20") or 0) * plane["n"])
    worst = row.get("worst")
    return [row["label"], str(row["repeats"]), f"{summary['found_visible']}/{summary['visible']}",
            "-" if recall is None else
            f"{recall:.3f} {interval_text(summary.get('recall_visible_ci95', {}), 2)}",
            relative, str(summary["fp"]),
            "-" if plane["mean"] is None else
            f"{plane['mean']:.2f}° {interval_text(plane.get('mean_ci95', {}))}",
            "-" if plane["median"] is None else f"{plane['median']:.2f}°",
            "-" if plane.get("p90") is None else
            f"{plane['p90']:.1f}° {interval_text(plane.get('p90_ci95', {}))}",
            _share(row["flipped"], plane["n"], plane.get("over_90_ci95", {})),
            _share(over_20, plane["n"], plane.get("over_20_ci95", {})),
            "-" if worst is None else f"{worst['error_deg']:.1f}° ({worst['plant']} "
            f"{worst['flower']})",
            str(row.get("worst_gross", "-")),
            "-" if row["points_per_flower"] is None else f"{row['points_per_flower']:g}"]


def stress_table(report: dict) -> str:
    """The table of every perturbation against the baseline (Markdown)."""
    header = ["perturbation", "repeats", "found (visible)", "recall [95 % CI]", "of baseline",
              "FP", "plane mean [95 % CI]", "plane median", "plane p90 [95 % CI]",
              "flipped [share's 95 % CI]", f"over {STATS_GROSS_DEG:g}° [share's 95 % CI]",
              "worst flower", f"most over {GROSS_DEG:g}° in a repeat", "points a flower"]
    rows = [_cells(report["baseline"], report["baseline"])]
    rows += [_cells(row, report["baseline"]) for row in report["rows"]]
    return markdown_table(header, rows)


def compare_tables(report: dict) -> list[tuple[str, str]]:
    """Per compared setting, (its name, a Markdown table of it against this run at every
    perturbation on the same clouds): found and false positives of each, the plane
    error's paired difference on the flowers both found, wins/ties/losses, flips."""
    tables = []
    rows_all = [report["baseline"], *report["rows"]]
    for name in report["baseline"].get("compare", {}):
        header = ["perturbation", "found: this / it", "FP: this / it",
                  "Δ plane, this minus it [95 % CI]", "wins/ties/losses, Wilcoxon",
                  "flipped: this / it", "verdict"]
        rows = []
        for row in rows_all:
            other = row["compare"][name]
            ours, theirs = row["summary"], other["summary"]
            paired = other["paired"]
            rows.append([row["label"],
                         f"{ours['found_visible']} / {theirs['found_visible']} of "
                         f"{ours['visible']}", f"{ours['fp']} / {theirs['fp']}",
                         difference_cell(paired["fits"]["plane"]),
                         record_cell(paired["fits"]["plane"]),
                         f"{row['flipped']} / {other['flipped']}",
                         "; ".join(v for v in paired["verdicts"]
                                   if v.startswith(("plane", "found", "false", "tails")))])
        tables.append((name, markdown_table(header, rows)))
    return tables


def stress_markdown(report: dict) -> str:
    """stress.md: the table of every perturbation against the baseline, then each
    compared setting against this run."""
    config = report["config"]
    what = (", ".join(f["folder"] for f in config["folders"]) if config["source"] == "real"
            else f"{config['plants']} {config['preset']} plants from seed {config['seed']}, "
            f"{config['source']} clouds")
    units = "; ".join(f"{k}: {v}" for k, v in UNITS.items())
    bounds = ", ".join(f"{k} {'/'.join(f'{v:g}' for v in vs)}"
                       for k, vs in ENVELOPE_BOUNDS.items())
    page = (f"# flowerpose stress\n\n{what}; `{report['run']['command']}` "
            f"({report['run']['date']}, {report['seconds']} s).\n\n"
            f"{stress_table(report)}\n\nValues: {units}. The operating "
            f"envelope's bounds: {bounds}; its density bound is 50 points a flower. A plane "
            f"error over {FLIPPED_DEG:g}° is a flipped normal. \"of baseline\" is the "
            "recall over the unperturbed recall. Intervals are 95 %, over what is independent "
            "(several plants: the plants, then their flowers; one plant: its flowers, each "
            "carrying its repeats), a flower counted once in a share however many repeats "
            "saw it.\n")
    for name, table in compare_tables(report):
        page += (f"\n## Against {name}, on the same perturbed clouds\n\n{table}\n\n"
                 "Δ: this run's plane error minus the compared one's on the flowers both "
                 "found, a flower's repeats nested in it, negative where this run is better; "
                 "a difference is shown where its interval leaves out 0 and is within the "
                 "margin where it lies within ±0.5°; under 10 flowers there are too few to "
                 "tell. McNemar counts a flower once: found where most repeats found it.\n")
    return page


def _series(report: dict) -> dict[str, list[dict]]:
    """The rows by kind, each kind's rows in order of strength."""
    kinds: dict[str, list[dict]] = {}
    for row in report["rows"]:
        kinds.setdefault(row["perturbation"]["kind"], []).append(row)
    return kinds


def _x(row: dict) -> float:
    p = row["perturbation"]
    value = p["value"]
    if isinstance(value, str):
        return float(value.split("x")[0])
    return float(value)


def _write_figure(path: Path, report: dict) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    kinds = _series(report)
    base = report["baseline"]["summary"]
    figure, axes = plt.subplots(1, max(1, len(kinds)), figsize=(4.2 * max(1, len(kinds)), 3.6),
                                squeeze=False)
    for axis, (kind, rows) in zip(axes[0], kinds.items(), strict=False):
        groups: dict[str, list[dict]] = {}
        for row in rows:
            groups.setdefault(row["perturbation"].get("channel", ""), []).append(row)
        error_axis = axis.twinx()
        for channel, members in groups.items():
            if kind in IDENTITY:
                members = [*members, {**report["baseline"], "perturbation": {
                    "kind": kind, "value": IDENTITY[kind]}}]
            members = sorted(members, key=_x)
            xs = [_x(r) for r in members]
            name = f" {channel}" if channel else ""
            axis.plot(xs, [r["summary"]["recall_visible"] or 0 for r in members], "o-",
                      color="tab:blue", label=f"recall{name}")
            error_axis.plot(xs, [r["summary"]["error_deg"]["plane"]["mean"] or np.nan
                                 for r in members], "s--", color="tab:red",
                            label=f"plane{name}")
        axis.axhline(base["recall_visible"] or 0, color="tab:blue", lw=0.8, ls=":")
        if base["error_deg"]["plane"]["mean"] is not None:
            error_axis.axhline(base["error_deg"]["plane"]["mean"], color="tab:red", lw=0.8,
                               ls=":")
        axis.set_ylim(0, 1.05)
        error_axis.set_ylim(bottom=0)
        axis.set_xlabel(f"{kind} ({_unit(rows[0])})")
        axis.set_ylabel("recall of visible flowers", color="tab:blue")
        error_axis.set_ylabel("plane error mean, degrees", color="tab:red")
        axis.set_title(f"{kind} (dotted: unperturbed)")
    figure.tight_layout()
    written = write_figure(path, figure)
    plt.close(figure)
    return written


def _unit(row: dict) -> str:
    return row["perturbation"].get("unit", "")


def _write_html(path: Path, report: dict) -> Path:
    """report.html of a stress run: its table and a plotly figure per perturbation kind."""
    import html

    import plotly.graph_objects as go
    from plotly.offline import get_plotlyjs
    from plotly.subplots import make_subplots

    kinds = _series(report)
    base = report["baseline"]["summary"]
    figure = make_subplots(rows=1, cols=max(1, len(kinds)),
                           subplot_titles=[f"{k} ({_unit(r[0])})" for k, r in kinds.items()],
                           specs=[[{"secondary_y": True}] * max(1, len(kinds))])
    for col, (kind, rows) in enumerate(kinds.items(), start=1):
        rows = sorted(rows, key=_x)
        labels = [r["label"] for r in rows]
        figure.add_trace(go.Scatter(x=[_x(r) for r in rows], text=labels, mode="markers+lines",
                                    y=[r["summary"]["recall_visible"] for r in rows],
                                    name=f"{kind}: recall", marker_color="royalblue"),
                         row=1, col=col, secondary_y=False)
        figure.add_trace(go.Scatter(x=[_x(r) for r in rows], text=labels, mode="markers",
                                    y=[r["summary"]["error_deg"]["plane"]["mean"] for r in rows],
                                    name=f"{kind}: plane error", marker_color="crimson"),
                         row=1, col=col, secondary_y=True)
        figure.add_hline(y=base["recall_visible"] or 0, line_dash="dot", line_color="royalblue",
                         row=1, col=col)
    figure.update_layout(height=420, showlegend=False,
                         title="recall (blue, left) and plane error in degrees (red, right); "
                         "dotted: unperturbed")
    body = (f"<h1>flowerpose stress</h1><h2>Robustness</h2>"
            f"{figure.to_html(full_html=False, include_plotlyjs=False)}"
            f"<pre>{html.escape(stress_table(report))}</pre>"
            + "".join(f"<h2>Against {html.escape(name)}</h2><pre>{html.escape(table)}</pre>"
                      for name, table in compare_tables(report)))
    page = ("<!doctype html><html><head><meta charset='utf-8'><title>flowerpose stress</title>"
            f"<script>{get_plotlyjs()}</script></head><body>{body}</body></html>")
    return write_text(path, page)
