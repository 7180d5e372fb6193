"""Results pages made from runs (`flowerpose results REPORT.json ...`): the numbers a
document shows, with what made them, never typed in by hand.

Each report becomes a row: what ran (the suite and its version, or the source, preset and
plants, or the real folders), the flowers found of the visible, false positives, the plane
error's mean and median and the other fits' means, and under the table, per row, the
command, the code (version and commit), the date and the machine.
"""

from __future__ import annotations

from pathlib import Path

from flowerpose.errors import InputError
from flowerpose.eval.report import markdown_table
from flowerpose.jsonio import read_json


def _what(report: dict) -> str:
    suite = report.get("suite")
    config = report.get("config", {})
    if suite:
        return f"{suite['name']} (v{suite['version']}): {suite.get('description', '')}"
    if config.get("source") == "real":
        return "real: " + ", ".join(Path(f["folder"]).name for f in config.get("folders", []))
    return (f"{config.get('plants', '?')} plants from seed {config.get('seed', '?')}, "
            f"{config.get('source', '?')} clouds")


def _deg(stats: dict) -> str:
    return "-" if stats.get("mean") is None else f"{stats['mean']:.2f}°"


def results_markdown(paths: list[Path], title: str = "Results", paper: bool = True) -> str:
    """The results page of these report.json files (and the paper's own numbers as the last
    row, with `paper`)."""
    rows, notes = [], []
    for k, path in enumerate(paths, start=1):
        report = read_json(path)
        if not isinstance(report, dict) or "summary" not in report or "run" not in report:
            raise InputError(path, "not an eval report.json (no run or summary)")
        s = report["summary"]
        plane = s["error_deg"]["plane"]
        rows.append([f"{_what(report)} [{k}]", f"{s['found_visible']} of {s['visible']}",
                     str(s["fp"]), _deg(plane),
                     "-" if plane.get("median") is None else f"{plane['median']:.2f}°",
                     _deg(s["error_deg"]["superellipsoid"]), _deg(s["error_deg"]["paraboloid"])])
        run = report["run"]
        machine = run.get("machine") or {}
        where = (f"{machine.get('processor', '?')}, {machine.get('cores', '?')} cores, "
                 f"{machine.get('system', '?')}" if machine else "machine not recorded")
        commit = (run.get("commit") or "not a git checkout")[:12]
        notes.append(f"[{k}] `{run['command']}`; flowerpose {run['flowerpose']} ({commit}), "
                     f"{run['date']}, {where}.")
    if paper:
        rows.append(paper_row())
    header = ["run", "found (visible)", "FP", "plane mean", "plane median", "superellipsoid",
              "paraboloid"]
    return (f"# {title}\n\nMade by `flowerpose results` from the runs' report.json files; "
            "each row's command, code, date and machine are under the table.\n\n"
            f"{markdown_table(header, rows)}\n\n" + "\n".join(f"- {n}" for n in notes) + "\n")


def paper_row() -> list[str]:
    """The paper's own numbers (Table I over its 7 plants), for a table beside runs."""
    from flowerpose.eval.report import PAPER

    return ["the paper (real scans, hand labels)", "49 of 61", "4",
            f"{PAPER['mean']['plane']}°", f"{PAPER['median']['plane']}°",
            f"{PAPER['mean']['superellipsoid']}°", f"{PAPER['mean']['paraboloid']}°"]

