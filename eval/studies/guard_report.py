"""guard.md and the guard's table: each entry's change against its base, with the losses'
bounds beside their margins, the tails of both sides, the verdict and the drift."""

from __future__ import annotations

from flowerpose.eval.reports.report import markdown_table
from flowerpose.eval.scoring.stats import interval_text, p_text
from flowerpose.eval.studies.guard_verdict import MEASURES, UNITS


def _loss(m: dict | None) -> str:
    """"+0.12 [≤ 0.31] / 0.5": a measure's loss, its one-sided 95 % upper bound and its
    margin."""
    if m is None:
        return "-"
    if m["loss"] is None:
        return "no flowers"
    upper = "" if m["upper"] is None else f" [≤ {m['upper']:+.2f}]"
    return f"{m['loss']:+.2f}{upper} / {m['margin']:g}"


def _count(tails: dict, key: str) -> str:
    return f"{tails[key]} of {tails['n']}"


def _worst(tails: dict) -> str:
    worst = tails["worst"]
    if worst is None:
        return "-"
    return f"{worst['error_deg']:.1f}° ({worst['plant']} flower {worst['flower']})"


def guard_rows(report: dict) -> tuple[list[str], list[list[str]]]:
    """The guard table's header and a row per entry."""
    header = ["entry", "base", "plane Δ° [95 % upper] / margin", "recall Δ points",
              "FP Δ per 100", "pollinated Δ points", "flipped: base → change",
              "over 20°: base → change", "p90 change [95 % CI]", "worst flower (change)",
              "verdict"]
    rows = []
    for name, row in report["entries"].items():
        measures = row["measures"]
        base, change = row["tails"]["base"], row["tails"]["change"]
        identical = row["verdict"] == "identical"
        rows.append([
            name, row["base"][:9],
            *(("identical" if key in row["applies"] else "-") if identical
              else _loss(measures.get(key)) for key in MEASURES),
            f"{_count(base, 'flipped')} → {change['flipped']}",
            f"{_count(base, 'over_20')} → {change['over_20']}",
            "-" if change["p90"] is None else
            f"{change['p90']:.1f}° {interval_text(change['p90_ci95'])}",
            _worst(change), row["verdict"]])
    return header, rows


def guard_markdown(report: dict) -> str:
    """guard.md: the verdict, the table, each entry's measures with their Holm-adjusted
    p-values, the reasons of every failure and the drift since the accepted records."""
    failed = [n for n, r in report["entries"].items() if r["verdict"] == "fail"]
    verdict = (f"**failed on {', '.join(failed)}**" if failed
               else "every entry passed or is identical to its base")
    margins = report["battery"]["margins"]
    lines = [
        "# flowerpose guard", "",
        f"`{report['run']['command']}` ({report['run']['date']}, {report['seconds']} s), "
        f"battery v{report['battery']['version']}, run seed {report['run_seed']} (`--seed "
        f"{report['run_seed']}` draws the same plants): {verdict}.", "",
        markdown_table(*guard_rows(report)), "",
        "Δ is the change's loss against its base on the same fresh plants (positive: "
        "worse), with its one-sided 95 % upper bound; a measure is within its margin where "
        "Holm's correction over every measure of the run still shows its loss below the "
        f"margin. Margins: plane mean {margins['plane_mean_deg']:g}°, recall "
        f"{margins['recall_points']:g} points, false positives "
        f"{margins['fp_per_100_flowers']:g} per 100 flowers, pollinated "
        f"{margins['pollinated_points']:g} points; new flipped normals "
        f"{margins['new_flipped']}, new flowers over 20° {margins['new_over_20']}, new "
        f"collisions {margins['new_collisions']}.", ""]
    for name, row in report["entries"].items():
        lines += [f"## {name}", "", f"{row['label']}; base {row['base'][:12]}; plants "
                  f"{_plants(row['plants'])}; {row['verdict']}.", ""]
        for key in MEASURES:
            m = row["measures"].get(key)
            if m is not None:
                lines.append(f"- {key}: loss {_value(m['loss'])}{UNITS[key]} "
                             f"{interval_text(m['ci95'], 2)}, upper bound "
                             f"{_value(m['upper'])} against {m['margin']:g} on {m['n']} "
                             f"values of {m['flowers']} flowers; Holm p {p_text(m['p_holm'])}: "
                             f"{m['verdict']}")
        lines += [f"- {reason}" for reason in row["reasons"]]
        drift = row.get("drift", {})
        if drift:
            lines.append("- drift (summed accepted losses, with this run's): " + "; ".join(
                f"{key} {spans['total']['loss']:+.2f} ± {spans['total']['se']:.2f} over "
                f"{spans['total']['records']} since the first record, "
                f"{spans['since_loss']['loss']:+.2f} since the last accepted loss"
                for key, spans in drift.items() if "total" in spans))
        trend = row.get("trend")
        if trend:
            lines.append(f"- trend (working tree on the fixed plants {_plants(trend['plants'])}): "
                         f"{trend['found_visible']}/{trend['visible']} found, {trend['fp']} "
                         f"false positives, plane mean {_value(trend['plane_mean'])}° "
                         f"{interval_text(trend['plane_mean_ci95'])}, "
                         f"{trend['tails']['flipped']} flipped")
        lines.append("")
    return "\n".join(lines)


def _value(value: float | None) -> str:
    return "-" if value is None else f"{value:+.2f}"


def _plants(plants: dict) -> str:
    if "seeds" in plants:
        return f"seeds {plants['seeds'][0]}-{plants['seeds'][1]}"
    if "stress_seed" in plants:
        return f"stress seed {plants['stress_seed']}"
    return "the folder as it is"
