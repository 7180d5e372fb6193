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
from flowerpose.eval.reports.report import markdown_table
from flowerpose.eval.scoring.stats import interval_text
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


def _deg_interval(stats: dict, key: str = "mean") -> str:
    """A statistic with its 95 % interval, where the report has one."""
    if stats.get(key) is None:
        return "-"
    return f"{stats[key]:.2f}° {interval_text(stats.get(f'{key}_ci95', {}))}".strip()


def _found(summary: dict) -> str:
    """Found of visible, with the recall's 95 % interval where the report has one."""
    interval = interval_text(summary.get("recall_visible_ci95", {}), 2)
    return f"{summary['found_visible']} of {summary['visible']}" + (f" {interval}"
                                                                      if interval else "")


def _auc(summary: dict) -> str:
    curve = summary.get("accuracy", {}).get("plane", {})
    if curve.get("auc") is None:
        return "-"
    return f"{curve['auc']:.3f} {interval_text(curve.get('auc_ci95', {}), 3)}".strip()


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
        if "comparison" in report and "outcomes" in report:
            return "fidelity"
        if "ways" in report and "agreement" in report:
            return "photos"
    raise InputError(path, "not an eval report.json, a stress.json, a bench.json, a "
                     "photo_bench.json or a fidelity.json (made by this version)")


def results_markdown(paths: list[Path], title: str = "Results", paper: bool = True,
                     figure: Path | None = None) -> str:
    """The results page of these runs: a table row per eval report.json (and the paper's
    own numbers as the last row, with `paper`), with their intervals, the plane fit's
    accuracy curves drawn into `figure` (a PNG beside the page) when given, then a section
    per stress.json (robustness), bench.json (speed), photo_bench.json (real photographs to
    a cloud) and fidelity.json (the simulator against a real plant); every run's provenance
    under its table."""
    from flowerpose.eval.studies.bench import bench_markdown
    from flowerpose.eval.studies.stress import stress_markdown

    rows, notes, sections = [], [], []
    pollination, angle_rows, pollination_notes = [], [], []
    curves: dict[str, dict] = {}
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
        if kind == "fidelity":
            sections.append(fidelity_section(report, k))
            continue
        if kind == "photos":
            from flowerpose.eval.studies.photo_bench import photo_bench_markdown

            sections.append(f"## Real photographs to a cloud [{k}]\n\n"
                            f"{photo_bench_markdown(report)}\n{_provenance(k, report['run'])}\n")
            continue
        s = report["summary"]
        if "pollination" in s:
            pollination.append(pollination_row(report, k))
            angle_rows.extend(curve_rows(report, k))
            pollination_notes.append(_provenance(k, report["run"]))
            continue
        plane = s["error_deg"]["plane"]
        rows.append([f"{_what(report)} [{k}]", _found(s), str(s["fp"]),
                     _deg_interval(plane), _deg_interval(plane, "median"),
                     _deg(s["error_deg"]["superellipsoid"]), _deg(s["error_deg"]["paraboloid"]),
                     _auc(s)])
        curves.update(curve_series(report, k))
        notes.append(_provenance(k, report["run"]))
    if paper and rows:
        rows.append(paper_row())
    header = ["run", "found (visible) [95 % CI]", "FP", "plane mean [95 % CI]",
              "plane median [95 % CI]", "superellipsoid", "paraboloid", "plane accuracy AUC"]
    page = (f"# {title}\n\nMade by `flowerpose results` from the runs' own files; each "
            "run's command, code, date and machine are under its table.\n")
    if rows:
        page += (f"\n## Accuracy\n\n{markdown_table(header, rows)}\n\n"
                 "Intervals are 95 %: the recall's Wilson interval, the errors' seeded "
                 "bootstrap over plants, then their flowers. Accuracy AUC: the area under the "
                 "share of visible flowers whose plane normal is within each angle, 0-45°, "
                 "normalised to 0-1, a missed flower failing at every angle "
                 "([reading the numbers](guides/reading-the-numbers.md)).\n\n"
                 + "\n".join(f"- {n}" for n in notes) + "\n")
        if figure is not None and curves:
            write_accuracy_figure(figure, curves)
            page += (f"\n![The plane fit's accuracy curves of the runs above]({figure.name})"
                     "\n\nThe share of visible flowers whose plane normal lies within each "
                     "angle of the truth, per run (and per compared method).\n")
    if pollination:
        page += (f"\n## Pollination\n\n{markdown_table(POLLINATION_HEADER, pollination)}\n\n"
                 "The planner's ceiling plans from the true poses. Flight: the planned bot "
                 "time of the visits from the estimated poses, all plants.\n")
        if angle_rows:
            page += ("\nSuccess against the approach's angle off the true axis (the contact "
                     "replay, the angle rule left out):\n\n"
                     f"{markdown_table(CURVE_HEADER, angle_rows)}\n")
        page += "\n" + "\n".join(f"- {n}" for n in pollination_notes) + "\n"
    return page + "".join(f"\n{section}" for section in sections)


def curve_series(report: dict, k: int) -> dict[str, dict]:
    """An eval report's plane accuracy curves by label: its own, and each compared
    method's."""
    series = {}
    own = report["summary"].get("accuracy", {}).get("plane", {})
    if own.get("share") is not None:
        series[f"[{k}] {_what(report)}"] = own
    for name, compared in report.get("compare", {}).items():
        curve = compared["summary"].get("accuracy", {}).get("plane", {})
        if curve.get("share") is not None:
            series[f"[{k}] {name}"] = curve
    return series


def write_accuracy_figure(path: Path, series: dict[str, dict]) -> Path:
    """The accuracy curves on one plot (PNG): share of flowers within each angle."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from flowerpose.atomic import write_figure

    figure, axis = plt.subplots(figsize=(7.5, 4.2))
    for label, curve in series.items():
        axis.plot([0, *curve["thresholds_deg"]], [0.0, *curve["share"]], "o-", ms=3,
                  label=f"{label[:60]} (AUC {curve['auc']:.3f}, {curve['n']})")
    axis.set_xlabel("plane normal's error within (degrees)")
    axis.set_ylabel("share of visible flowers")
    axis.set_ylim(0, 1.02)
    axis.grid(alpha=0.3)
    axis.legend(fontsize=7, loc="lower right")
    figure.tight_layout()
    written = write_figure(path, figure)
    plt.close(figure)
    return written


def fidelity_section(report: dict, k: int) -> str:
    """A fidelity.json as a section: the statistics' agreement and the predicted scores at
    the real density against the real plant's intervals."""
    from flowerpose.eval.studies.fidelity import outcome_lines, table

    return (f"## Simulator against {report['real_plant']} [{k}]\n\n{table(report)}\n\n"
            f"{report['holds']} of {report['of']} statistics within tolerance "
            f"({report['real']['flowers']} real flowers, {report['synthetic']['flowers']} "
            "synthetic). Predicted at the real density:\n\n"
            + "".join(f"- {line}\n" for line in outcome_lines(report["outcomes"]))
            + f"\n{_provenance(k, report['run'])}\n")


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
    from flowerpose.eval.reports.report import PAPER

    return ["the paper (real scans, hand labels)", "49 of 61", "4",
            f"{PAPER['mean']['plane']}°", f"{PAPER['median']['plane']}°",
            f"{PAPER['mean']['superellipsoid']}°", f"{PAPER['mean']['paraboloid']}°", "-"]

