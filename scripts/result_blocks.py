"""The result blocks of the docs, made from `make results`' runs (scripts/results.sh).

Every figure the docs give as a result lives between `<!-- results:NAME -->` and
`<!-- /results:NAME -->` in a page of PAGES, and is written there by BLOCKS[NAME] from the
runs under runs/; `tests/test_docs.py` finds result numbers anywhere else. Run after the
runs: `python scripts/result_blocks.py [RUNS [BLOCK ...]]` (every block, or those named).
"""

from __future__ import annotations

import json
import math
import re
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
from scipy import stats as scipy_stats

from flowerpose.atomic import write_text
from flowerpose.eval.scoring.paired import flower_errors
from flowerpose.eval.scoring.stats import interval_text, p_text, wilson

REPO = Path(__file__).resolve().parents[1]
#: The pages that hold result blocks.
PAGES = ("README.md", "DESIGN.md", "docs/guides/reading-the-numbers.md",
         "docs/guides/own-photos.md", "docs/guides/pollination.md")
BLOCK = re.compile(r"(<!-- results:(?P<name>[a-z0-9-]+) -->\n)(?P<body>.*?)"
                   r"(<!-- /results:(?P=name) -->)", re.S)


def _json(path: Path) -> dict:
    """A run's JSON file; one line and exit status 2 where it is missing or unreadable (its
    run has not been made: `make results` makes them all)."""
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as err:
        reason = err.strerror if isinstance(err, OSError) and err.strerror else str(err)
        print(f"result_blocks.py: {path}: {reason}", file=sys.stderr)
        sys.exit(2)


def accuracy_table(runs: Path) -> str:
    """The README's table: the results page's accuracy table, without its footnote marks."""
    page = (REPO / "docs" / "results.md").read_text(encoding="utf-8")
    table = page.split("## Accuracy\n\n", 1)[1].split("\n\n", 1)[0]
    return re.sub(r" \[\d+\]", "", table) + "\n"


def _real3(runs: Path) -> tuple[dict, list[dict], list[dict]]:
    report = _json(runs / "real3" / "report.json")
    return report, report["plants"], report["compare"]["upstream"]["plants"]


def compare_example(runs: Path) -> str:
    """The pipeline against the published method on plant 3, as `eval --compare` says it."""
    report, ours, theirs = _real3(runs)
    compared = report["compare"]["upstream"]
    paired = compared["paired"]
    plane = paired["fits"]["plane"]
    mine = report["summary"]["error_deg"]["plane"]["mean"]
    other = compared["summary"]["error_deg"]["plane"]["mean"]
    found, fp = paired["found"], paired["fp"]
    lines = "; ".join(v for v in paired["verdicts"] if v.startswith(("plane", "found", "false")))
    return (f"```text\ndefault against upstream: {lines}\n```\n\n"
            f"The pipeline's plane mean is {mine:.2f}° and the published method's {other:.2f}°; "
            f"on the {plane['n']} flowers both found the paired difference is "
            f"{plane['mean_difference']:+.1f}° {interval_text(plane['ci95'])}: "
            f"\"{plane['verdict']}\". It finds "
            f"{found['only_ours']} flowers the published method does not and misses "
            f"{found['only_theirs']} it finds (McNemar's test: "
            f"{'shown' if found['shown'] else 'nothing shown'}), and makes {fp['ours']} false "
            f"positives against {fp['theirs']} "
            f"({'a difference shown' if fp['shown'] else 'no difference shown'}).\n")


def flowers_needed(runs: Path) -> str:
    """How wide an interval is at N flowers, from plant 3's spread, and the flowers a
    difference needs."""
    _, ours, theirs = _real3(runs)
    mine = flower_errors(ours, "plane")
    other = flower_errors(theirs, "plane")
    sd = float(np.std(list(mine.values()), ddof=1))
    both = sorted(set(mine) & set(other))
    sd_paired = float(np.std([mine[k] - other[k] for k in both], ddof=1))
    z = scipy_stats.norm.ppf(0.975)
    power = (z + scipy_stats.norm.ppf(0.8)) ** 2
    rows = "\n".join(f"| {n} | {z * sd / math.sqrt(n):.1f}° | {z * sd_paired / math.sqrt(n):.1f}° |"
                     for n in (10, 20, 50, 100))
    return (f"From the authors' plant 3 ({len(mine)} labelled flowers found; the per-flower "
            f"plane error's standard deviation {sd:.1f}°, and {sd_paired:.1f}° for the paired "
            f"difference between the pipeline and the published plane fit on the same "
            f"{len(both)} flowers), the half-width of a 95 % interval is about 1.96 × sd / √n:\n\n"
            "| flowers | the mean's interval, ± | a paired difference's, ± |\n"
            f"|---|---|---|\n{rows}\n\n"
            f"- Two methods compared on **different** flowers need about "
            f"{math.ceil(2 * power * sd ** 2)} flowers each to show a 1° difference of means "
            f"with 80 % power; compared on the **same** flowers, about "
            f"{math.ceil(power * sd_paired ** 2)}. Compare paired.\n"
            f"- A recall measured on 11 flowers is known only roughly: 11 of 11 is "
            f"{_wilson(11, 11)}, 9 of 11 is {_wilson(9, 11)}; 45 of 50 is {_wilson(45, 50)}.\n")


def _wilson(found: int, trials: int) -> str:
    interval = wilson(found, trials)
    return f"{interval['low']:.2f}-{interval['high']:.2f}"


def wilson_example(runs: Path) -> str:
    """A recall of 11 of 11 and its interval."""
    return (f"11 of 11 found is a recall of 1.00 with an interval of {_wilson(11, 11)}, not "
            "\"100 %\".\n")


def uncertain_flag(runs: Path) -> str:
    """What the pose stage's uncertain flag caught on plant 3's stress levels and on the
    synthetic suites."""
    report = _json(runs / "stress-real3" / "stress.json")
    counts = {"scored": 0, "flagged": 0, "flipped": 0, "flipped_flagged": 0, "gross": 0,
              "gross_flagged": 0}
    levels, repeats = [], 0
    for row in report["rows"]:
        kind = row["perturbation"]["kind"]
        if kind not in ("thin", "cut"):
            continue
        levels.append(row["perturbation"])
        repeats = max(repeats, row["repeats"])
        folder = row["label"].replace(" ", "_")
        for entry in row["plants"]:
            plant, _, repeat = entry["plant"].partition(" r")
            name = folder + (f"-r{repeat}" if repeat else "")
            flowers = _json(runs / "stress-real3" / "runs" / name / plant / "flowers.json")
            flags = [f.get("uncertain", False) for f in flowers["flowers"]]
            for match in entry["matches"]:
                error = (match.get("error_deg") or {}).get("plane")
                if error is None:
                    continue
                flagged = bool(flags[match["detection"]])
                counts["scored"] += 1
                counts["flagged"] += flagged
                key = "flipped" if error > 90 else "gross" if error > 30 else None
                if key:
                    counts[key] += 1
                    counts[f"{key}_flagged"] += flagged
    thin = [p["value"] for p in levels if p["kind"] == "thin"]
    shares = []
    for suite in ("oracle-10", "field-10", "scan-3"):
        flags = [f.get("uncertain", False)
                 for path in sorted((runs / suite / "plants").glob("*/flowers.json"))
                 for f in _json(path)["flowers"]]
        shares.append(100 * sum(flags) / max(1, len(flags)))
    return (f"On the authors' plant 3 thinned to {100 * max(thin):g}-{100 * min(thin):g} % and "
            f"cut ({repeats} repeats, {counts['scored']} scored flowers) the flag marked "
            f"{counts['flagged']}, among them {counts['flipped_flagged']} of the "
            f"{counts['flipped']} flipped normals and {counts['gross_flagged']} of the "
            f"{counts['gross']} other errors over 30°; on the oracle, field and full-loop "
            f"suites, {min(shares):.0f}-{max(shares):.0f} % of flowers.\n")


def photos_bench(runs: Path) -> str:
    """The real photos three ways (`flowerpose bench --photos`): its table, as it printed it."""
    from flowerpose.eval.studies.photo_bench import photo_bench_markdown

    return photo_bench_markdown(_json(runs / "photos" / "photo_bench.json"))


def tool_study(runs: Path) -> str:
    """Which pollinator reaches the flowers (`sweep --task pollinate` over the tool's
    reach and offset): a row a tool, the default first."""
    sweep = _json(runs / "sweep-tool" / "best.json")
    rows = [("the default: " if k == 0 else "") + _tool(entry["setting"], sweep)
            for k, entry in enumerate([{"setting": {}}, *sweep["settings"]])]
    metrics = [sweep["defaults"]["metrics"], *(s["metrics"] for s in sweep["settings"])]
    against = [None, *(s["vs_defaults"]["pollinated"] for s in sweep["settings"])]

    def share(m: dict, key: str) -> str:
        return (f"{m[f'{key}_flowers']} ({m[key]:.1%}) "
                f"[{m[f'{key}_low']:.0%}, {m[f'{key}_high']:.0%}]")

    looked = sweep["best"]["config"]["pollinate"]["look"]["views"] > 0
    poses = "the scan's poses, then the close look" if looked else "the scan's poses"
    lines = [f"| pollinator (reach, offset under the lens) | pollinated ({poses}) | "
             "pollinated (true poses) | unreachable | collisions (of visits) | "
             "against the default |", "|---|---|---|---|---|---|"]
    for row, m, c in zip(rows, metrics, against, strict=True):
        versus = "-" if c is None else (f"{c['only_ours']} won, {c['only_theirs']} lost "
                                        f"(McNemar p {p_text(c['p'])})")
        lines.append(f"| {row} | {share(m, 'pollinated')} | {share(m, 'pollinated_ceiling')} "
                     f"| {m['unreachable']} | {m['collisions']} of {m['visits']} | {versus} |")
    best = max(metrics, key=lambda m: m["pollinated_ceiling"])
    reached = [r for r, m in zip(rows, metrics, strict=True) if m["pollinated_ceiling"] >= 0.95]
    answer = (f"The tools that reach 95% of the flowers with the true poses: "
              f"{'; '.join(reached)}." if reached else
              f"No tool swept reaches 95% of the flowers even with the true poses; the most "
              f"is {best['pollinated_ceiling']:.1%}.")
    return (f"{sweep['plants']} plants of the `{sweep['best']['config']['sim']['plant']['name']}`"
            f" preset from seed "
            f"{sweep['seed']}, {metrics[0]['flowers']} flowers:\n\n" + "\n".join(lines)
            + f"\n\n{answer}\n")


def _tool(setting: dict, sweep: dict) -> str:
    """A swept tool as its reach and offset, centimetres: the setting's, else the
    defaults' (best.json's `defaults.setting`), else the best setting's config's."""
    tool = sweep["best"]["config"]["pollinate"]["tool"]
    values = {key: setting.get(f"pollinate.tool.{key}",
                               sweep["defaults"]["setting"].get(f"pollinate.tool.{key}",
                                                                tool[key]))
              for key in ("reach_m", "offset_down_m")}
    return f"{values['reach_m'] * 100:g} cm, {values['offset_down_m'] * 100:g} cm"


def tool_tune(runs: Path) -> str:
    """The same question as a search (`tune --task pollinate` over the tool's reach and
    offset and the standoff): the training front and the defaults on the validation
    plants, the chosen trial, and whether any reaches 95 % with the true poses."""
    tune = _json(runs / "tune-tool" / "tune.json")

    def setting(row: dict) -> str:
        values = row["settings"]
        return (f"{values['pollinate.tool.reach_m'] * 100:.1f} cm, "
                f"{values['pollinate.tool.offset_down_m'] * 100:.1f} cm, "
                f"{values['pollinate.standoff_m'] * 100:.1f} cm")

    def share(value: float | None, digits: int = 1) -> str:
        return "-" if value is None else f"{value:.{digits}%}"

    def scores(scores: dict, train: dict) -> str:
        return (f"{share(train['pollination.success_rate'])} | "
                f"{int(scores['pollination.successes'])} of "
                f"{int(scores['pollination.flowers'])} "
                f"({share(scores['pollination.success_rate'])}) "
                f"[{share(scores['pollination.success_rate_ci95.low'], 0)}, "
                f"{share(scores['pollination.success_rate_ci95.high'], 0)}] | "
                f"{share(scores['pollination_ceiling.success_rate'])} | "
                f"{int(scores['pollination.failures.collision'])} of "
                f"{int(scores['pollination.visits'])}")

    chosen = tune["chosen"]
    rows = [(f"{row['number']}" + (" (chosen)" if chosen and row["number"] == chosen["number"]
                                   else ""), setting(row), scores(row["validate"], row["train"]))
            for row in tune["front"]]
    defaults = tune["defaults"]
    from flowerpose.hardware.flights.pollination_plan import PollinateConfig

    shipped = PollinateConfig()
    rows.append(("defaults", setting({"settings": {
        "pollinate.tool.reach_m": shipped.tool.reach_m,
        "pollinate.tool.offset_down_m": shipped.tool.offset_down_m,
        "pollinate.standoff_m": shipped.standoff_m}}),
        scores(defaults["validate"], defaults["train"])))
    lines = ["| trial | reach, offset under the lens, standoff | pollinated (training) | "
             "pollinated (validation) | pollinated, true poses (validation) | collisions "
             "(validation visits) |", "|---|---|---|---|---|---|"]
    lines += [f"| {name} | {what} | {numbers} |" for name, what, numbers in rows]
    ceiling = max(r["validate"]["pollination_ceiling.success_rate"] or 0.0
                  for r in [*tune["front"], defaults])
    answer = ("A trial reaches 95% of the validation flowers with the true poses."
              if ceiling >= 0.95 else "No trial on the front reaches 95% of the validation "
              f"flowers even with the true poses; the most is {ceiling:.1%}.")
    against = tune.get("chosen_vs_defaults") or {}
    verdict = next((v for v in against.get("verdicts", []) if v.startswith("pollinated")),
                   None)
    counts = tune["counts"]
    return (f"{counts['complete']} trials, training on "
            + "; ".join(s["label"] for s in tune["train"]) + ", validated on "
            + "; ".join(s["label"] for s in tune["validate"])
            + ". The training front and the defaults:\n\n" + "\n".join(lines) + "\n\n"
            + answer + (f" The chosen trial against the defaults on the validation "
                        f"flowers: {verdict}." if verdict else "") + "\n")


#: What makes each block.
BLOCKS: dict[str, Callable[[Path], str]] = {
    "accuracy-table": accuracy_table, "compare-example": compare_example,
    "flowers-needed": flowers_needed, "wilson-example": wilson_example,
    "uncertain-flag": uncertain_flag, "photos-bench": photos_bench,
    "tool-study": tool_study, "tool-tune": tool_tune}


def blocks(text: str) -> list[str]:
    """The names of the result blocks of a page, in order."""
    return [m.group("name") for m in BLOCK.finditer(text)]


def outside_blocks(text: str) -> str:
    """A page with its result blocks' bodies left out."""
    return BLOCK.sub(lambda m: m.group(1) + m.group(4), text)


def fill(text: str, runs: Path, only: set[str] | None = None) -> str:
    """A page with every result block (or those named in `only`) made again from the runs."""
    def made(m: re.Match) -> str:
        if only is not None and m.group("name") not in only:
            return m.group(0)
        return m.group(1) + BLOCKS[m.group("name")](runs) + m.group(4)

    return BLOCK.sub(made, text)


def main(runs: Path, only: set[str] | None = None) -> int:
    unknown = sorted((only or set()) - set(BLOCKS))
    if unknown:
        print(f"result_blocks.py: no such block: {', '.join(unknown)} (the blocks: "
              f"{', '.join(BLOCKS)})", file=sys.stderr)
        return 2
    for page in PAGES:
        path = REPO / page
        text = path.read_text(encoding="utf-8")
        filled = fill(text, runs, only)
        if filled != text:
            write_text(path, filled)
        made = [name for name in blocks(text) if only is None or name in only]
        if made:
            print(f"{page}: {', '.join(made)}")
    return 0


if __name__ == "__main__":
    # python scripts/result_blocks.py [RUNS [BLOCK ...]]: every block, or the ones named.
    sys.exit(main(Path(sys.argv[1]) if len(sys.argv) > 1 else REPO / "runs",
                  set(sys.argv[2:]) or None))
