"""Reports: `report.json` (a contract: DESIGN.md's keys), `report.md`, and the paper's Table I."""

from __future__ import annotations

import datetime
import json
import math
import shlex
import sys
from pathlib import Path
from typing import Any

import numpy as np
from tabulate import tabulate

from flowerpose.atomic import write_text
from flowerpose.eval.scoring.pollinated import SECTIONS, pollination_sections, summarise_pollination
from flowerpose.eval.scoring.stats import (
    NO_INTERVAL,
    accuracy_curve,
    accuracy_scores,
    error_summary,
    interval_text,
    wilson,
)
from flowerpose.eval.scoring.units import flower_groups, share_weight
from flowerpose.jsonio import write_json
from flowerpose.pipeline.methods import METHODS

#: The paper's Table I column order, with its published numbers for comparison.
TABLE_METHODS = ("superellipsoid", "paraboloid", "plane")
PAPER = {"found_pct": 80.3, "mean": {"superellipsoid": 19.3, "paraboloid": 57.9, "plane": 7.7},
         "median": {"superellipsoid": 8.9, "paraboloid": 11.8, "plane": 5.9},
         "std": {"superellipsoid": 33.6, "paraboloid": 73.3, "plane": 5.8}}


def summarise(plants: list[dict], intervals: bool = True) -> dict:
    """The report's summary over plant entries: totals, recalls with their Wilson
    intervals, each fit's error statistics with bootstrap intervals, and each fit's
    accuracy curve (`eval/scoring/stats.py`), the units resampled as `eval/scoring/units.py` says (a
    perturbed plant's repeats nested in its flowers, each flower counted once in a
    share's interval). `intervals=False` leaves the intervals out (None), for a caller that
    only ranks point values many times over."""
    total = {key: sum(p[key] for p in plants)
             for key in ("gt", "visible", "detections", "found", "found_visible", "extra", "fp")}
    recall = total["found_visible"] / total["visible"] if total["visible"] else None
    precision = (1.0 - total["fp"] / total["detections"]) if total["detections"] else None
    f1 = (2 * recall * precision / (recall + precision)
          if recall is not None and precision is not None and recall + precision > 0 else
          0.0 if recall is not None else None)
    weight = share_weight(plants)

    def share(successes: int, trials: int) -> dict:
        return wilson(successes * weight, trials * weight) if intervals else dict(NO_INTERVAL)

    def errors(fit: str) -> list[list[float]]:
        return flower_groups(plants, lambda m: m["error_deg"].get(fit))

    def scores(fit: str) -> list[list[float]]:
        return flower_groups(plants, lambda m: _score(m["error_deg"].get(fit)), missed=0.0)

    return {**total,
            "recall": round(total["found"] / total["gt"], 4) if total["gt"] else None,
            "recall_visible": None if recall is None else round(recall, 4),
            "recall_visible_ci95": share(total["found_visible"], total["visible"]),
            "fp_rate": round(total["fp"] / total["detections"], 4) if total["detections"] else None,
            "precision": None if precision is None else round(precision, 4),
            "precision_ci95": share(total["detections"] - total["fp"], total["detections"]),
            "f1": None if f1 is None else round(f1, 4),
            "error_deg": {m: error_summary(errors(m), intervals, weight) for m in METHODS},
            "accuracy": {m: accuracy_curve([p["error_deg"][m] for p in plants],
                                           [p["visible"] for p in plants], intervals,
                                           scores(m)) for m in METHODS},
            "failed": {m: sum(p["failed"][m] for p in plants) for m in METHODS}}


def run_summary(plants: list[dict], intervals: bool = True) -> dict:
    """The summary of plant entries as report.json holds it: `summarise`'s, with the
    pollination task's sections where every entry was visited
    (`pollinated.pollination_sections`)."""
    return {**summarise(plants, intervals), **pollination_sections(plants)}


def summary_template(task: str = "pose") -> dict:
    """An empty summary of a run of `task` ("pose" or "pollinate"): its keys, the numbers
    a gate or an objective may name."""
    summary = summarise([])
    if task == "pollinate":
        summary.update({key: summarise_pollination([]) for key in SECTIONS})
    return summary


def _score(error: float | None) -> float:
    """A flower's share of the accuracy curve's area (`stats.accuracy_scores`)."""
    return 0.0 if error is None else float(accuracy_scores([error], 1)[0])


def git_commit() -> str | None:
    """The commit of the source flowerpose runs from when it is a git checkout ("+dirty"
    with uncommitted changes), else None (an installed package)."""
    import subprocess

    source = Path(__file__).resolve().parent.parent
    try:
        head = subprocess.run(["git", "-C", str(source), "rev-parse", "HEAD"],
                              capture_output=True, text=True, timeout=5)
        if head.returncode != 0:
            return None
        dirty = subprocess.run(["git", "-C", str(source), "status", "--porcelain",
                                "--untracked-files=no"], capture_output=True, text=True,
                               timeout=5).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return head.stdout.strip() + ("+dirty" if dirty else "")


def run_record() -> dict[str, Any]:
    """flowerpose's version, its git commit when run from a checkout, the time (UTC, ISO
    8601) and the command line of this run."""
    import flowerpose
    from flowerpose import __version__

    arguments = flowerpose.invocation if flowerpose.invocation is not None else sys.argv[1:]
    return {"flowerpose": __version__, "commit": git_commit(),
            "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
            "command": shlex.join(["flowerpose", *arguments]), "machine": machine()}


def assets_record(preset: str | None, profile: str | None) -> dict[str, dict[str, str]]:
    """The shipped settings files a run's settings came from, each {"name", "sha256"} of
    its content: "preset" (assets/presets) and "profile" (assets/configs), where given.
    Two reports of one suite version compare only where these agree."""
    from flowerpose.config import preset_hash, profile_hash

    record = {}
    if preset is not None:
        record["preset"] = {"name": preset, "sha256": preset_hash(preset)}
    if profile is not None:
        record["profile"] = {"name": profile, "sha256": profile_hash(profile)}
    return record


def machine() -> dict[str, Any]:
    """What a run's numbers were measured on: the system, the processor and its cores (a
    time is only worth its machine)."""
    import os
    import platform

    processor = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as info:
            names = [line.split(":", 1)[1].strip() for line in info
                     if line.startswith("model name")]
        processor = names[0] if names else processor
    except OSError:
        pass
    return {"system": platform.platform(terse=True), "processor": processor,
            "cores": os.cpu_count(), "python": platform.python_version()}


def build_report(config: dict, plants: list[dict], timing_s: dict[str, float],
                 extra: dict | None = None) -> dict:
    """The whole report.json document, with what made it (`run`: flowerpose's version, the
    time it was written, in UTC, and the command line)."""
    report = {"run": run_record(), "config": config, "plants": plants,
              "summary": summarise(plants), "timing_s": timing_s}
    report.update(extra or {})
    return report


def _mean(values: list[float]) -> float | None:
    return float(np.mean(values)) if values else None


def _deg(value: float | None) -> str:
    return "-" if value is None or (isinstance(value, float) and math.isnan(value)) \
        else f"{value:.1f}°"


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    """A Markdown table (GitHub's), columns padded, the cells as given (no number
    parsing). Markdown has no rule inside a table's body (one would show as a row of
    dashes), so rows that follow a rule elsewhere (Table I's totals) name themselves."""
    return tabulate(rows, headers=header, tablefmt="github", disable_numparse=True)


def table(report: dict) -> str:
    """The paper's Table I for a report (Markdown): per plant, then all plants' total,
    mean, median and std."""
    header, rows, _ = table_rows(report)
    return markdown_table(header, rows)


def table_rows(report: dict) -> tuple[list[str], list[list[str]], int]:
    """Table I's header, rows and the index of the first summary row (Markdown and HTML
    reports print the same cells)."""
    header = ["Plant", "GT", "Visible", "Found (%)", "Extra", "FP",
              "Superellipsoid", "Paraboloid", "Plane"]
    rows = []
    for p in report["plants"]:
        pct = 100.0 * p["found"] / p["gt"] if p["gt"] else 0.0
        rows.append([p["plant"], str(p["gt"]), str(p["visible"]), f"{p['found']} ({pct:.1f})",
                     str(p["extra"]), str(p["fp"])]
                    + [_deg(_mean(p["error_deg"][m])) for m in TABLE_METHODS])
    s = report["summary"]
    pct = 100.0 * s["found"] / s["gt"] if s["gt"] else 0.0
    rows.append(["Total", str(s["gt"]), str(s["visible"]), f"{s['found']} ({pct:.1f})",
                 str(s["extra"]), str(s["fp"])]
                + [f"{s['error_deg'][m]['n']} normals" for m in TABLE_METHODS])
    for stat, label in (("mean", "Mean"), ("median", "Median"), ("std", "Std Dev")):
        rows.append([label, "-", "-", "-", "-", "-"]
                    + [_deg(s["error_deg"][m][stat]) for m in TABLE_METHODS])
    return header, rows, len(rows) - 4


def comparison_table(report: dict, name: str = "default") -> str:
    """This run's configuration beside each compared one (report["compare"]) on the same
    plants: found, false positives, the error means, and per fit the paired difference on
    the flowers both found (this run minus the compared one, its interval, wins/ties/losses
    and Wilcoxon's p), then each comparison's verdicts in words."""
    header, rows = comparison_rows(report, name)
    lines = [markdown_table(header, rows), COMPARISON_LEGEND.format(name=name)]
    for other, compared in report.get("compare", {}).items():
        if "paired" in compared:
            lines.append(f"{name} against {other}: "
                         + "; ".join(compared["paired"]["verdicts"]))
    return "\n".join(lines)


#: The comparison table's fits, the one pollination uses first.
PAIRED_ORDER = ("plane", "superellipsoid", "paraboloid")
#: What the comparison table's paired columns mean.
COMPARISON_LEGEND = (
    "Δ: {name}'s error minus the compared one's on the flowers both found (negative: "
    "{name} is better), with its 95 % interval and the flowers it is over; wins/ties/losses "
    "count flowers where {name} is better, within 0.5°, or worse.")


def comparison_rows(report: dict, name: str = "default") -> tuple[list[str], list[list[str]]]:
    """`comparison_table`'s header and rows (the verdicts left out)."""
    from flowerpose.eval.scoring.paired import difference_cell, record_cell

    header = ["Profile", "Found", "FP", "Plane mean", "Plane median", "Superellipsoid",
              "Paraboloid", *(f"Δ {m}" for m in PAIRED_ORDER),
              "Plane wins/ties/losses, Wilcoxon"]
    rows = [(name, report["summary"], None)]
    rows += [(other, c["summary"], c.get("paired"))
             for other, c in report.get("compare", {}).items()]
    lines = []
    for label, summary, paired in rows:
        errors = summary["error_deg"]
        fits = (paired or {}).get("fits", {})
        lines.append([label, f"{summary['found']}/{summary['gt']}", str(summary["fp"]),
                      _deg(errors["plane"]["mean"]), _deg(errors["plane"]["median"]),
                      _deg(errors["superellipsoid"]["mean"]), _deg(errors["paraboloid"]["mean"]),
                      *(difference_cell(fits[m]) if m in fits else "-"
                        for m in PAIRED_ORDER),
                      record_cell(fits["plane"]) if "plane" in fits else "-"])
    return header, lines


def summary_lines(report: dict) -> list[str]:
    """Short human summary under the table, with the paper's numbers beside ours: each
    number with its count and 95 % interval."""
    s = report["summary"]
    lines = []
    if s["recall"] is not None:
        lines.append(f"recall {s['recall']:.3f} (paper {PAPER['found_pct'] / 100:.3f}), "
                     f"recall of visible flowers {s['recall_visible'] or 0:.3f} "
                     f"{interval_text(s.get('recall_visible_ci95', {}), 2)} "
                     f"({s['found_visible']} of {s['visible']}), false positives {s['fp']} of "
                     f"{s['detections']} detections")
    for m in METHODS:
        st = s["error_deg"][m]
        if st["n"]:
            lines.append(f"{m}: mean {st['mean']:.2f}° {interval_text(st['mean_ci95'])}, "
                         f"median {st['median']:.2f}° {interval_text(st['median_ci95'])}, "
                         f"p90 {st['p90']:.1f}°, over 20° {_share(st, 'over_20')}, "
                         f"flipped {_share(st, 'over_90')}, accuracy AUC "
                         f"{_auc(s['accuracy'][m])} over {st['n']} flowers, "
                         f"{s['failed'][m]} failed (paper mean {PAPER['mean'][m]}°)")
    timing = report["timing_s"]
    if "wall" in timing:
        lines.append(f"wall time {timing['wall']:.1f} s since the command was launched (its stages "
                     f"{timing.get('total', 0.0):.1f} s)")
    elif "total" in timing:
        lines.append(f"wall time {timing['total']:.1f} s")
    return lines


def note_lines(report: dict) -> list[str]:
    """The warnings the run said of its inputs (the run's own "notes", then each plant's,
    named): what it assumed where an input was odd but usable."""
    lines = list(report.get("notes", []))
    for plant in report["plants"]:
        lines += [f"{plant['plant']}: {note}" for note in plant.get("notes", [])]
    return lines


def _share(stats: dict, key: str) -> str:
    """A share of a fit's errors as a count of its flowers."""
    return f"{round(stats[key] * stats['n'])} of {stats['n']}"


def _auc(curve: dict) -> str:
    if curve.get("auc") is None:
        return "-"
    return f"{curve['auc']:.3f} {interval_text(curve['auc_ci95'], 3)}".strip()


def interval_table(report: dict) -> str:
    """Each fit's errors with their 95 % intervals (Markdown): count, mean, median, 90th
    percentile, gross errors (over 20°), flips (over 90°), the accuracy curve's area."""
    return markdown_table(*interval_rows(report["summary"]))


def interval_rows(summary: dict) -> tuple[list[str], list[list[str]]]:
    """`interval_table`'s header and rows."""
    header = ["Fit", "Flowers", "Mean [95 % CI]", "Median [95 % CI]", "p90", "Over 20°",
              "Flipped (over 90°)", "Accuracy AUC, 0-45°"]
    rows = []
    for m in TABLE_METHODS:
        st = summary["error_deg"][m]
        if not st["n"]:
            rows.append([m, "0", "-", "-", "-", "-", "-", "-"])
            continue
        rows.append([m, str(st["n"]), f"{st['mean']:.1f}° {interval_text(st['mean_ci95'])}",
                     f"{st['median']:.1f}° {interval_text(st['median_ci95'])}",
                     f"{st['p90']:.1f}°", _share(st, "over_20"), _share(st, "over_90"),
                     _auc(summary["accuracy"][m])])
    return header, rows


#: What Table I's columns mean, under the table in report.md.
TABLE_LEGEND = (
    "GT: flowers in the truth. Visible: those a camera of the scan sees (every hand-labelled "
    "flower counts as visible). Found: flowers a detection lies within the match distance "
    "of (percent of GT). Extra: how many of those are hidden or carry no label: matched, "
    "not scored, not false. FP: detections near no flower. Angles: per plant, the mean "
    "error of each fit's normal over its visible found flowers; the rows total, mean, "
    "median and std dev take all plants' flowers together.")


#: What the interval table's columns mean, under it in report.md.
INTERVAL_LEGEND = (
    "Intervals are 95 %, from a seeded bootstrap over the flowers (over plants, then their "
    "flowers, for several plants); shares count flowers. Accuracy AUC: the area under the "
    "share of visible flowers within each angle from 0 to 45°, normalised to 0-1, a missed "
    "flower counting as a failure at every angle. docs/guides/reading-the-numbers.md says "
    "how to read them.")


#: What `write_report` writes into its folder.
REPORT_FILES = ("report.json", "report.md")


def write_report(out_dir: Path, report: dict, title: str) -> tuple[Path, Path]:
    """Write report.json and report.md into out_dir."""
    json_path = write_json(out_dir / "report.json", report)
    md = [f"# {title}", "", table(report), "", TABLE_LEGEND, "",
          *[f"- {line}" for line in summary_lines(report)],
          "", "## Errors with 95 % intervals", "", interval_table(report), "", INTERVAL_LEGEND]
    if report.get("compare"):
        md += ["", "## Compared on the same plants", "", comparison_table(report)]
    if "pollination" in report["summary"]:
        md += ["", "## Pollination", "", *[f"- {line}" for line in pollination_lines(report)],
               "", "![pollination success, and before and after the close look]"
               "(pollination.png)"]
    notes = note_lines(report)
    if notes:
        md += ["", "## What the run assumed", "", *[f"- {line}" for line in notes]]
    md += ["", "## Timing (seconds)", "", markdown_table(
        ["stage", "seconds"], [[k, f"{v:.3f}"] for k, v in report["timing_s"].items()])]
    md += ["", "## Configuration", "", "```json", json.dumps(report["config"], indent=1), "```", ""]
    md_path = write_text(out_dir / "report.md", "\n".join(md))
    return json_path, md_path


def pollination_lines(report: dict) -> list[str]:
    """The printed summary of `eval --task pollinate`: success with the estimated and with
    the true poses, and the failures by cause."""
    lines = []
    looked = "close_look" in report["summary"]
    for key, what in (("pollination", "estimated poses"),
                      ("pollination_scan_pose", "the scan's poses alone"),
                      ("pollination_ceiling", "true poses (the planner's ceiling)")):
        part = report["summary"].get(key)
        if part is None:
            continue
        rate = part["success_rate"]
        failures = ", ".join(f"{cause} {n}" for cause, n in part["failures"].items() if n)
        flowers = part.get("flowers", part["successes"] + sum(part["failures"].values()))
        interval = interval_text(part.get("success_rate_ci95", {}), 2)
        lines.append(f"pollination from {what}: {part['successes']} of {flowers} flowers "
                     f"({'-' if rate is None else f'{rate:.3f} {interval}'.strip()}) in "
                     f"{part['visits']} visits; failures: {failures or 'none'}")
    if looked:
        close = report["summary"]["close_look"]
        times = close["time_per_visit_s"]
        statuses = ", ".join(f"{n} {status}" for status, n in close["looks"].items())
        lines.append(f"close look (in the estimated poses' visits): {close['won']} flowers "
                     f"won and {close['lost']} lost of {close['flowers']} against the scan's "
                     f"poses alone; looks: {statuses or 'none'}")
        if times["visits"]:
            lines.append(f"time per visit: planning {times['planning']:.1f} s, flight "
                         f"{times['flight']:.1f} s and the close look {times['look']:.1f} s "
                         f"(bot clock), its reconstruction {times['look_compute']:.1f} s")
    return lines
