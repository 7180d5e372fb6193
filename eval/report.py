"""Reports: `report.json` (a contract: DESIGN.md's keys), `report.md`, and the paper's Table I."""

from __future__ import annotations

import datetime
import json
import math
import shlex
import sys
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
from tabulate import SEPARATING_LINE, tabulate

from flowerpose.atomic import write_text
from flowerpose.jsonio import write_json
from flowerpose.pipeline.methods import METHODS

#: The paper's Table I column order, with its published numbers for comparison.
TABLE_METHODS = ("superellipsoid", "paraboloid", "plane")
PAPER = {"found_pct": 80.3, "mean": {"superellipsoid": 19.3, "paraboloid": 57.9, "plane": 7.7},
         "median": {"superellipsoid": 8.9, "paraboloid": 11.8, "plane": 5.9},
         "std": {"superellipsoid": 33.6, "paraboloid": 73.3, "plane": 5.8}}


def error_stats(errors: list[float]) -> dict[str, float | int | None]:
    """Mean, median, population std (degrees) and count; None where there is no error."""
    if not errors:
        return {"mean": None, "median": None, "std": None, "n": 0}
    values = np.asarray(errors, float)
    return {"mean": round(float(values.mean()), 4), "median": round(float(np.median(values)), 4),
            "std": round(float(values.std()), 4), "n": int(len(values))}


def plant_entry(name: str, score: Any) -> dict:
    """One plant's row of report.json from a PlantScore; "matches" names the truth flower
    and the detection behind each error."""
    matches = [{**m, "error_deg": {k: None if e is None else round(e, 4)
                                   for k, e in m["error_deg"].items()}}
               if "error_deg" in m else m for m in score.matches]
    return {"plant": name, "gt": score.gt, "visible": score.visible,
            "detections": score.detections, "found": score.found,
            "found_visible": score.found_visible, "extra": score.extra, "fp": score.fp,
            "error_deg": {m: [round(e, 4) for e in score.error_deg[m]] for m in METHODS},
            "failed": {m: score.failed[m] for m in METHODS}, "matches": matches}


def summarise(plants: list[dict]) -> dict:
    """The report's summary over plant entries: totals, recalls and error statistics."""
    total = {key: sum(p[key] for p in plants)
             for key in ("gt", "visible", "detections", "found", "found_visible", "extra", "fp")}
    recall = total["found_visible"] / total["visible"] if total["visible"] else None
    precision = (1.0 - total["fp"] / total["detections"]) if total["detections"] else None
    f1 = (2 * recall * precision / (recall + precision)
          if recall is not None and precision is not None and recall + precision > 0 else
          0.0 if recall is not None else None)
    return {**total,
            "recall": round(total["found"] / total["gt"], 4) if total["gt"] else None,
            "recall_visible": None if recall is None else round(recall, 4),
            "fp_rate": round(total["fp"] / total["detections"], 4) if total["detections"] else None,
            "precision": None if precision is None else round(precision, 4),
            "f1": None if f1 is None else round(f1, 4),
            "error_deg": {m: error_stats([e for p in plants for e in p["error_deg"][m]])
                          for m in METHODS},
            "failed": {m: sum(p["failed"][m] for p in plants) for m in METHODS}}


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


def _deg(value: float | None) -> str:
    return "-" if value is None or (isinstance(value, float) and math.isnan(value)) \
        else f"{value:.1f}°"


def markdown_table(header: list[str], rows: list[list[str]],
                   rules_before: Iterable[int] = ()) -> str:
    """A Markdown table (GitHub's), columns padded, the cells as given (no number
    parsing); a rule before each row index in `rules_before` (the paper's Table I separates
    its totals)."""
    rules = set(rules_before)
    body: list = []
    for k, row in enumerate(rows):
        if k in rules:
            body.append(SEPARATING_LINE)
        body.append(row)
    return tabulate(body, headers=header, tablefmt="github", disable_numparse=True)


def table(report: dict) -> str:
    """The paper's Table I for a report (Markdown): per plant, then total, mean, median,
    std."""
    header, rows, rule = table_rows(report)
    return markdown_table(header, rows, rules_before=[rule])


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
                    + [_deg(error_stats(p["error_deg"][m])["mean"]) for m in TABLE_METHODS])
    s = report["summary"]
    pct = 100.0 * s["found"] / s["gt"] if s["gt"] else 0.0
    rows.append(["Total", str(s["gt"]), str(s["visible"]), f"{s['found']} ({pct:.1f})",
                 str(s["extra"]), str(s["fp"])]
                + [f"{s['error_deg'][m]['n']} normals" for m in TABLE_METHODS])
    for stat, label in (("mean", "Mean"), ("median", "Median"), ("std", "Std Dev")):
        rows.append([label, "-", "-", "-", "-", "-"]
                    + [_deg(s["error_deg"][m][stat]) for m in TABLE_METHODS])
    return header, rows, len(rows) - 4


def _plane_errors(plants: list[dict]) -> dict[tuple[str, Any], float]:
    """Plane errors keyed by (plant, truth flower id)."""
    return {(p["plant"], str(m["truth"])): m["error_deg"]["plane"]
            for p in plants for m in p.get("matches", [])
            if m.get("error_deg", {}).get("plane") is not None}


def comparison_table(report: dict, name: str = "default") -> str:
    """This run's configuration beside each compared one (report["compare"]) on the same
    plants: found, false positives, the error means, and the plane error over the flowers
    every row found (paired, so a profile that finds fewer, easier flowers gains nothing)."""
    return markdown_table(*comparison_rows(report, name))


def comparison_rows(report: dict, name: str = "default") -> tuple[list[str], list[list[str]]]:
    """`comparison_table`'s header and rows."""
    rows = [(name, report["summary"], report["plants"])]
    rows += [(other, c["summary"], c["plants"]) for other, c in report.get("compare", {}).items()]
    errors_by_row = [_plane_errors(plants) for _, _, plants in rows]
    # Over the rows that scored any flower: a method that found none has nothing to pair.
    scored = [set(e) for e in errors_by_row if e]
    common = sorted(set.intersection(*scored)) if scored else []
    header = ["Profile", "Found", "FP", "Plane mean", "Plane median", "Superellipsoid",
              "Paraboloid", "Plane, flowers all found"]
    lines = []
    for (label, summary, _), theirs in zip(rows, errors_by_row, strict=True):
        paired = (f"{np.mean([theirs[k] for k in common]):.1f}° over {len(common)}"
                  if common and theirs else "-")
        errors = summary["error_deg"]
        lines.append([label, f"{summary['found']}/{summary['gt']}", str(summary["fp"]),
                      _deg(errors["plane"]["mean"]), _deg(errors["plane"]["median"]),
                      _deg(errors["superellipsoid"]["mean"]), _deg(errors["paraboloid"]["mean"]),
                      paired])
    return header, lines


def summary_lines(report: dict) -> list[str]:
    """Short human summary under the table, with the paper's numbers beside ours."""
    s = report["summary"]
    lines = []
    if s["recall"] is not None:
        lines.append(f"recall {s['recall']:.3f} (paper {PAPER['found_pct'] / 100:.3f}), "
                     f"recall of visible flowers {s['recall_visible'] or 0:.3f}, "
                     f"false positives {s['fp']} of {s['detections']} detections")
    for m in METHODS:
        st = s["error_deg"][m]
        if st["n"]:
            lines.append(f"{m}: mean {st['mean']:.2f}°, median {st['median']:.2f}°, "
                         f"std {st['std']:.2f}° over {st['n']} flowers, {s['failed'][m]} failed "
                         f"(paper mean {PAPER['mean'][m]}°)")
    timing = report["timing_s"]
    if "wall" in timing:
        lines.append(f"wall time {timing['wall']:.1f} s since the command was launched (its stages "
                     f"{timing.get('total', 0.0):.1f} s)")
    elif "total" in timing:
        lines.append(f"wall time {timing['total']:.1f} s")
    return lines


#: What Table I's columns mean, under the table in report.md.
TABLE_LEGEND = (
    "GT: flowers in the truth. Visible: those a camera of the scan sees (every hand-labelled "
    "flower counts as visible). Found: flowers a detection lies within the match distance "
    "of (percent of GT). Extra: how many of those are hidden or carry no label: matched, "
    "not scored, not false. FP: detections near no flower. Angles: per plant, the mean "
    "error of each fit's normal over its visible found flowers; the rows below the rule "
    "take all plants' flowers together.")


#: What `write_report` writes into its folder.
REPORT_FILES = ("report.json", "report.md")


def write_report(out_dir: Path, report: dict, title: str) -> tuple[Path, Path]:
    """Write report.json and report.md into out_dir."""
    json_path = write_json(out_dir / "report.json", report)
    md = [f"# {title}", "", table(report), "", TABLE_LEGEND, "",
          *[f"- {line}" for line in summary_lines(report)]]
    if report.get("compare"):
        md += ["", "## Compared on the same plants", "", comparison_table(report)]
    md += ["", "## Timing (seconds)", "", markdown_table(
        ["stage", "seconds"], [[k, f"{v:.3f}"] for k, v in report["timing_s"].items()])]
    md += ["", "## Configuration", "", "```json", json.dumps(report["config"], indent=1), "```", ""]
    md_path = write_text(out_dir / "report.md", "\n".join(md))
    return json_path, md_path


def pollination_lines(report: dict) -> list[str]:
    """The printed summary of `eval --task pollinate`: success with the estimated and with
    the true poses, and the failures by cause."""
    lines = []
    for key, what in (("pollination", "estimated poses"),
                      ("pollination_ceiling", "true poses (the planner's ceiling)")):
        part = report["summary"].get(key)
        if part is None:
            continue
        rate = part["success_rate"]
        failures = ", ".join(f"{cause} {n}" for cause, n in part["failures"].items() if n)
        lines.append(f"pollination from {what}: {part['successes']} flowers "
                     f"({'-' if rate is None else f'{100 * rate:.1f}%'}) in "
                     f"{part['visits']} visits; failures: {failures or 'none'}")
    return lines
