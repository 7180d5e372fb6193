"""Results pages made from runs (`flowerpose results REPORT.json ...`): the numbers a
document shows, with what made them, never typed in by hand. Eval reports become a table's
rows (a pollination run's, a row of the pollination section instead); stress and bench
reports become sections of their own.

Each eval report becomes a row: what ran (the suite and its version, or the source, preset and
plants, or the real folders), the flowers found of the visible, false positives, the plane
error's mean and median and the other fits' means, and under the table, per row, the
command, the code (version and commit), the date and the machine.
"""

from __future__ import annotations

import re
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


def _provenance(k: int, run: dict) -> str:
    """A run's footnote: its command, code version and commit, date and machine."""
    machine = run.get("machine") or {}
    where = (f"{machine.get('processor', '?')}, {machine.get('cores', '?')} cores, "
             f"{machine.get('system', '?')}" if machine else "machine not recorded")
    commit = run.get("commit") or "not a git checkout"
    commit = commit[:12] + ("+dirty" if commit.endswith("+dirty") else "")
    return (f"[{k}] `{run['command']}`; flowerpose {run['flowerpose']} ({commit}), "
            f"{run['date']}, {where}.")


def _check_comparable(path: Path, report: dict, seen: dict[tuple, tuple[Path, dict]]) -> None:
    """Refuse a report of a suite version already on the page whose preset or profile
    files differ (report["run"]["assets"]): the same suite name and version would then
    stand for different settings."""
    suite = report.get("suite")
    if not suite:
        return
    key = (suite["name"], suite["version"], "pollination" in report.get("summary", {}))
    assets = report["run"].get("assets", {})
    if key in seen and seen[key][1] != assets:
        raise InputError(path, f"suite {suite['name']} v{suite['version']} ran with other "
                         f"preset or profile files than {seen[key][0]} (their hashes differ): "
                         "the two do not compare")
    seen.setdefault(key, (path, assets))


def _kind(path: Path, report: object) -> str:
    """Which run wrote this file: an eval's report.json, a stress.json or a bench.json."""
    if isinstance(report, dict) and "run" in report:
        if "summary" in report:
            return "eval"
        if "baseline" in report and "rows" in report:
            return "stress"
        if "results" in report and "simulator_s" in report:
            return "bench"
    raise InputError(path, "not an eval report.json, a stress.json or a bench.json "
                     "(made by this version)")


def results_markdown(paths: list[Path], title: str = "Results", paper: bool = True) -> str:
    """The results page of these runs: a table row per eval report.json (and the paper's
    own numbers as the last row, with `paper`), then a section per stress.json (robustness)
    and per bench.json (speed); every run's provenance under its table."""
    from flowerpose.eval.bench import bench_markdown
    from flowerpose.eval.stress import stress_markdown

    rows, notes, sections = [], [], []
    pollination, curves, pollination_notes = [], [], []
    suites: dict[tuple, tuple[Path, dict]] = {}
    for k, path in enumerate(paths, start=1):
        report = read_json(path)
        kind = _kind(path, report)
        _check_comparable(path, report, suites)
        if kind == "stress":
            # Its own page's title becomes a section of this one.
            body = stress_markdown(report).split("\n", 1)[1].replace("\n## ", "\n### ")
            sections.append(f"## Robustness [{k}]\n{body}\n{_provenance(k, report['run'])}\n")
            continue
        if kind == "bench":
            sections.append(f"## Speed [{k}]\n\n{bench_markdown(report)}\n"
                            f"{_provenance(k, report['run'])}\n")
            continue
        s = report["summary"]
        if "pollination" in s:
            pollination.append(pollination_row(report, k))
            curves.extend(curve_rows(report, k))
            pollination_notes.append(_provenance(k, report["run"]))
            continue
        plane = s["error_deg"]["plane"]
        rows.append([f"{_what(report)} [{k}]", f"{s['found_visible']} of {s['visible']}",
                     str(s["fp"]), _deg(plane),
                     "-" if plane.get("median") is None else f"{plane['median']:.2f}°",
                     _deg(s["error_deg"]["superellipsoid"]), _deg(s["error_deg"]["paraboloid"])])
        notes.append(_provenance(k, report["run"]))
    if paper and rows:
        rows.append(paper_row())
    header = ["run", "found (visible)", "FP", "plane mean", "plane median", "superellipsoid",
              "paraboloid"]
    page = (f"# {title}\n\nMade by `flowerpose results` from the runs' own files; each "
            "run's command, code, date and machine are under its table.\n")
    if rows:
        page += (f"\n## Accuracy\n\n{markdown_table(header, rows)}\n\n"
                 + "\n".join(f"- {n}" for n in notes) + "\n")
    if pollination:
        page += (f"\n## Pollination\n\n{markdown_table(POLLINATION_HEADER, pollination)}\n\n"
                 "The planner's ceiling plans from the true poses. Flight: the planned bot "
                 "time of the visits from the estimated poses, all plants.\n")
        if curves:
            page += ("\nSuccess against the approach's angle off the true axis (the contact "
                     "replay, the angle rule left out):\n\n"
                     f"{markdown_table(CURVE_HEADER, curves)}\n")
        page += "\n" + "\n".join(f"- {n}" for n in pollination_notes) + "\n"
    return page + "".join(f"\n{section}" for section in sections)


POLLINATION_HEADER = ["run", "flowers", "visits", "pollinated", "planner's ceiling",
                      "unreachable", "pose off", "collision", "flight"]
CURVE_HEADER = ["run", "off the axis", "planned", "pollinated", "failures"]


def _rate(part: dict) -> str:
    return f"{part['successes']} ({100 * (part['success_rate'] or 0):.1f} %)"


def pollination_row(report: dict, k: int) -> list[str]:
    """A pollination run's row: flowers, visits, successes from the estimated poses and
    from the true ones, failures by cause and the planned flight time."""
    s = report["summary"]
    ours, ceiling = s["pollination"], s["pollination_ceiling"]
    flowers = sum(len(p["pollination"]["flowers"]) for p in report["plants"])
    minutes = sum(p["pollination"]["planned_s"] for p in report["plants"]) / 60
    failures = ours["failures"]
    # Reports do not record a preset yet; the command that made the run names it.
    preset = re.search(r"--preset[ =](\S+)", report["run"].get("command", ""))
    what = _what(report) + (f", {preset.group(1)} preset" if preset else "")
    return [f"{what} [{k}]",
            str(flowers), str(ours["visits"]), _rate(ours), _rate(ceiling),
            str(failures["unreachable"]), str(failures["pose off"]), str(failures["collision"]),
            f"{minutes:.1f} min"]


def curve_rows(report: dict, k: int) -> list[list[str]]:
    """A pollination run's success against the approach's angle, a row an angle."""
    return [[f"[{k}]", f"{r['angle_deg']:g}°", f"{r['planned']} of {r['flowers']}",
             "-" if r["success_rate"] is None else _rate(r),
             ", ".join(f"{n} {cause}" for cause, n in r["failures"].items()) or "-"]
            for r in report.get("pollination_by_angle", [])]


def paper_row() -> list[str]:
    """The paper's own numbers (Table I over its 7 plants), for a table beside runs."""
    from flowerpose.eval.report import PAPER

    return ["the paper (real scans, hand labels)", "49 of 61", "4",
            f"{PAPER['mean']['plane']}°", f"{PAPER['median']['plane']}°",
            f"{PAPER['mean']['superellipsoid']}°", f"{PAPER['mean']['paraboloid']}°"]

