"""The guard (`flowerpose guard`): a change compared with its base on fresh plants, flower by
flower, for non-inferiority within the battery's margins.

The battery (`assets/guard/battery.toml`, versioned) is a list of entries, each a kind of
plant: seeded synthetic plants of a source and preset (the full simulated loop, the oracle,
the field and hard presets, pollination visits), a real plant folder as it is, and the same
folder thinned or with its flowers cut at seeded levels and repeats; its [margins] say how
much worse a change may be on each measure (`guard_verdict.py`).

Every run draws its synthetic plants' seeds, and its perturbations' seeds, from
`fresh_seeds.FRESH_SEEDS`, a range no suite, test, example or document uses, from a run
seed it prints and records (`--seed N` draws the same). Both sides run on those very
plants: the base revision (by default the commit of the entry's newest accepted record,
`accepted.py`; `--base REV` names another) laid out beside the working tree
(`revision.py`), and the working tree with the settings given; each through the same
command (`flowerpose eval`, `flowerpose stress`), sharing the stage cache, so a plant,
scan or reconstruction whose code did not change is made once for both. The battery's
fixed seeds are a trend record (`--trend`): the working tree's values on them, never a
verdict.

`--accept` appends the run's records to the accepted file: refused (exit 2, nothing
written) for a run that failed unless `--accept-loss REASON`, which records the loss as a
decision with its reason, and for a tree with uncommitted changes (the record names the
commit whose code ran).
"""

from __future__ import annotations

import dataclasses
import secrets
from dataclasses import dataclass
from importlib.resources import files
from pathlib import Path
from typing import Any

from flowerpose.atomic import write_text
from flowerpose.config import DEFAULT_PRESET, load_toml
from flowerpose.errors import InputError
from flowerpose.eval.jobs.eval_run import TASKS
from flowerpose.eval.jobs.plant_set import SOURCES, PlantSet
from flowerpose.eval.reports.report import git_commit, run_record, summarise
from flowerpose.eval.studies import accepted as history_file
from flowerpose.eval.studies.fresh_seeds import FRESH_SEEDS, entry_draw
from flowerpose.eval.studies.guard_verdict import Margins, decide, judge_entry, tails
from flowerpose.eval.studies.revision import Revision, dirty, head, materialise, repository, resolve
from flowerpose.jsonio import read_json, write_json
from flowerpose.log import LOG
from flowerpose.stopwatch import Stopwatch

#: The shipped battery and its accepted decisions.
BATTERY = files("flowerpose.assets") / "guard" / "battery.toml"
ACCEPTED = files("flowerpose.assets") / "guard" / "accepted.json"
#: What `flowerpose guard` writes into its --out folder (and each entry's runs).
GUARD_FILES = ("guard.json", "guard.md", "revisions")
#: Each key an entry may have, with its type.
_ENTRY_KEYS: dict[str, type | tuple[type, ...]] = {
    "name": str, "description": str, "source": str, "preset": str, "plants": int,
    "seed": int, "plant": str, "thin": list, "cut": list, "repeats": int, "task": str,
    "quick": bool}
_MARGIN_KEYS = {f.name: f.type for f in dataclasses.fields(Margins)}
_TABLES = {"battery", "margins", "entry"}


@dataclass(frozen=True)
class GuardEntry:
    """One entry of the battery: seeded synthetic plants (`source`, `preset`, `plants`;
    `seed`: the first of the fixed trend seeds), or a real plant folder (`plant`, its
    folder's name) as it is or under seeded perturbations (`thin`: fractions of points
    kept; `cut`: shares of each flower's disc removed; each `repeats` times). `task`:
    "pollinate" flies pollination visits too; `quick`: in the quick guard (CI's)."""

    name: str
    description: str
    source: str
    preset: str = DEFAULT_PRESET
    plants: int = 0
    seed: int = 0
    plant: str = ""
    thin: tuple[float, ...] = ()
    cut: tuple[float, ...] = ()
    repeats: int = 1
    task: str = "pose"
    quick: bool = False

    @property
    def perturbed(self) -> bool:
        return bool(self.thin or self.cut)

    @property
    def real(self) -> bool:
        return self.source == "real"

    def plants_from(self, seed: int) -> PlantSet:
        """A synthetic entry's plants from `seed` (its trend seed, or a run's fresh one)."""
        return PlantSet(self.source, self.preset, self.plants, seed)

    def label(self) -> str:
        if self.real:
            levels = ", ".join([*(f"thin {v:g}" for v in self.thin),
                                *(f"cut {v:g}" for v in self.cut)])
            return self.plant + (f" ({levels}; {self.repeats} repeats)" if levels else "")
        task = ", pollinated" if self.task == "pollinate" else ""
        return f"{self.plants} {self.preset} plants, {self.source} clouds{task}"


@dataclass(frozen=True)
class Battery:
    """The battery's version, what it is for, its margins and entries."""

    version: int
    description: str
    margins: Margins
    entries: tuple[GuardEntry, ...]
    path: str

    def select(self, names: list[str], quick: bool = False) -> tuple[GuardEntry, ...]:
        """The entries named (all, or with `quick` the quick ones, for none); InputError for
        a name it has not."""
        known = [e.name for e in self.entries]
        for name in names:
            if name not in known:
                raise InputError("--only", f"{name!r}: the battery's entries are "
                                 f"{', '.join(known)}")
        return tuple(e for e in self.entries
                     if ((e.name in names) if names else (e.quick or not quick)))


def load_battery(path: Path | None = None) -> Battery:
    """The battery file (the shipped one by default), checked whole before anything runs:
    InputError naming the file for an unknown table or key, a value of the wrong type, a
    margin missing, an entry without a name or source, a synthetic entry without plants
    or a real one without its plant."""
    source = Path(str(path if path is not None else BATTERY))
    data = load_toml(source)
    unknown = sorted(set(data) - _TABLES)
    if unknown:
        raise InputError(source, f"unknown table [{unknown[0]}] (known: [battery], "
                         "[margins], [[entry]])")
    header = data.get("battery", {})
    if not isinstance(header, dict) or not isinstance(header.get("version"), int) \
            or isinstance(header.get("version"), bool) or header["version"] < 1:
        raise InputError(source, "[battery] needs a version, a whole number from 1")
    margins = _margins(source, data.get("margins"))
    raw_entries = data.get("entry", [])
    if not isinstance(raw_entries, list):
        raise InputError(source, "entries are [[entry]] tables")
    entries = [_entry(source, k, raw) for k, raw in enumerate(raw_entries)]
    names = [e.name for e in entries]
    if not entries or len(set(names)) != len(names):
        raise InputError(source, "the battery needs entries, each named once")
    return Battery(header["version"], str(header.get("description", "")), margins,
                   tuple(entries), str(source))


def _margins(source: Path, raw: Any) -> Margins:
    if not isinstance(raw, dict):
        raise InputError(source, "needs a [margins] table: " + ", ".join(_MARGIN_KEYS))
    unknown = sorted(set(raw) - set(_MARGIN_KEYS))
    if unknown:
        raise InputError(source, f"[margins]: unknown key {unknown[0]!r} (known: "
                         f"{', '.join(_MARGIN_KEYS)})")
    values = {}
    for key, kind in _MARGIN_KEYS.items():
        value = raw.get(key)
        whole = kind in (int, "int")
        if value is None or isinstance(value, bool) or not isinstance(
                value, int if whole else (int, float)) or value < 0:
            raise InputError(source, f"[margins] {key}: needs a {'whole ' if whole else ''}"
                             f"number, 0 or more")
        values[key] = value
    return Margins(**values)


def _entry(source: Path, k: int, raw: Any) -> GuardEntry:
    if not isinstance(raw, dict):
        raise InputError(source, f"entry {k}: must be a table")
    unknown = sorted(set(raw) - set(_ENTRY_KEYS))
    if unknown:
        raise InputError(source, f"entry {k}: unknown key {unknown[0]!r} (known: "
                         f"{', '.join(sorted(_ENTRY_KEYS))})")
    for key, value in raw.items():
        kind = _ENTRY_KEYS[key]
        if not isinstance(value, kind) or (isinstance(value, bool) and kind is not bool):
            raise InputError(source, f"entry {raw.get('name', k)}: {key} has the wrong type "
                             f"({type(value).__name__})")
    if "name" not in raw or raw.get("source") not in SOURCES:
        raise InputError(source, f"entry {k}: needs a name and a source ({', '.join(SOURCES)})")
    for key in ("thin", "cut"):
        values = raw.get(key, [])
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and 0 <= v <= 1
                   for v in values):
            raise InputError(source, f"entry {raw['name']}: {key} levels are numbers 0-1")
    entry = GuardEntry(**{**raw, "thin": tuple(raw.get("thin", ())),
                          "cut": tuple(raw.get("cut", ())),
                          "description": raw.get("description", "")})
    if entry.task not in TASKS:
        raise InputError(source, f"entry {entry.name}: task is one of {', '.join(TASKS)}")
    if entry.real and not entry.plant:
        raise InputError(source, f"entry {entry.name}: a real entry names its plant folder")
    if entry.real and entry.task != "pose":
        raise InputError(source, f"entry {entry.name}: pollination needs synthetic plants")
    if not entry.real and (entry.plants < 1 or entry.perturbed):
        raise InputError(source, f"entry {entry.name}: a synthetic entry needs plants "
                         "(1 or more) and no perturbation")
    if not entry.real and entry.seed + entry.plants > FRESH_SEEDS.start:
        raise InputError(source, f"entry {entry.name}: its trend seeds reach the fresh range "
                         f"(from {FRESH_SEEDS.start:,}), which only the guard draws from")
    if entry.repeats < 1:
        raise InputError(source, f"entry {entry.name}: repeats are 1 or more")
    return entry


def real_folder(entry: GuardEntry, folders: list[Path]) -> Path:
    """The folder of a real entry's plant among those given (`--real`), by its name."""
    for folder in folders:
        if Path(folder).resolve().name == entry.plant:
            return Path(folder).resolve()
    raise InputError("--real", f"the battery's entry {entry.name} needs the plant folder "
                     f"{entry.plant}: give it with --real DIR (flowerpose data fetch "
                     f"{entry.plant} --to DIR fetches it)")


@dataclass(frozen=True)
class EntryDraw:
    """The plants an entry runs on in one run: the first synthetic seed and the
    perturbations' seed."""

    seed: int
    stress_seed: int

    def to_json(self, entry: GuardEntry) -> dict:
        if entry.real:
            return {"stress_seed": self.stress_seed} if entry.perturbed else {}
        return {"seeds": [self.seed, self.seed + entry.plants - 1]}


def fresh_plants(entry: GuardEntry, run_seed: int) -> EntryDraw:
    """The entry's fresh plants of a run (`fresh_seeds.entry_draw`)."""
    seed, stress_seed = entry_draw(run_seed, entry.name, max(entry.plants, 1))
    return EntryDraw(seed, stress_seed)


def trend_plants(entry: GuardEntry) -> EntryDraw:
    """The entry's fixed trend plants: its seeds from `seed`, perturbations from 0."""
    return EntryDraw(entry.seed, 0)


def side_arguments(entry: GuardEntry, plants: EntryDraw, out: Path, folders: list[Path],
                   workers: int | None, cache: Path | None) -> list[str]:
    """The command one side runs an entry with (`flowerpose eval` or `stress`)."""
    common = ["--out", str(out), "-q",
              *(["--workers", str(workers)] if workers else []),
              *(["--cache", str(cache)] if cache is not None else ["--no-cache"])]
    if not entry.real:
        drawn = entry.plants_from(plants.seed)
        return ["eval", "--source", drawn.source, "--preset", drawn.preset, "--plants",
                str(drawn.plants), "--seed", str(drawn.seed), "--task", entry.task, *common]
    folder = str(real_folder(entry, folders))
    if not entry.perturbed:
        return ["eval", "--source", "real", folder, *common]
    # Every other perturbation at its identity (left out), so only these levels run.
    return ["stress", "--source", "real", folder,
            "--thin", ",".join(f"{v:g}" for v in entry.thin) or "1",
            "--cut", ",".join(f"{v:g}" for v in entry.cut) or "0",
            "--exposure", "1", "--cast", "0", "--noise", "0", "--drop-views", "0",
            "--repeats", str(entry.repeats), "--stress-seed", str(plants.stress_seed), *common]


def read_side(entry: GuardEntry, out: Path) -> list[dict]:
    """A side's report.json plant entries, each named so that (plant, flower) keys one
    flower; a perturbed entry's: "LEVEL rREPEAT PLANT", naming the plant it repeats."""
    if not entry.perturbed:
        return read_json(out / "report.json")["plants"]
    plants = []
    for row in read_json(out / "stress.json")["rows"]:
        count = len(row["plants"]) // max(1, row["repeats"])
        for k, plant in enumerate(row["plants"]):
            name = plant.get("repeat_of", plant["plant"].split(" r")[0])
            plants.append({**plant, "plant": f"{row['label']} r{k // max(1, count)} {name}",
                           "repeat_of": name})
    return plants


@dataclass(frozen=True)
class GuardRun:
    """What one guard run compares: the entries, their base (None: each entry's newest
    accepted record), the run seed (None: drawn), the settings over the working tree's
    side (their command-line form and their layers, for the record), and where the runs
    go."""

    entries: tuple[GuardEntry, ...]
    folders: tuple[Path, ...]
    accepted: Path
    base: str | None = None
    run_seed: int | None = None
    setting_arguments: tuple[str, ...] = ()
    settings: tuple[dict, ...] = ()
    workers: int | None = None
    cache: Path | None = None
    trend: bool = False
    accept: bool = False
    accept_loss: str | None = None


def plan_bases(battery: Battery, run: GuardRun, history: list[dict]) -> dict[str, str]:
    """Each entry's base commit: `run.base`, else its newest record's; InputError naming
    the fix for an entry without one (none yet, or only of another battery version)."""
    if run.base is not None:
        return {entry.name: run.base for entry in run.entries}
    bases, missing = {}, []
    for entry in run.entries:
        commit = history_file.base_of(history, entry.name, battery.version)
        if commit is None:
            missing.append(entry.name)
        else:
            bases[entry.name] = commit
    if missing:
        others = sorted({r["battery_version"] for r in history if r["entry"] in missing}
                        - {battery.version})
        why = (f"its records are of battery version {', '.join(map(str, others))}, not "
               f"{battery.version}" if others else "it has no accepted record")
        raise InputError(run.accepted, f"{', '.join(missing)}: {why}, so there is no base "
                         "to compare with: give one (--base REV, e.g. the commit before the "
                         "change) and, once it passes, record it with --accept")
    return bases


def check_accept(run: GuardRun, repo: Path) -> None:
    """Refuse, before anything runs, an accept that could not be recorded truly: a tree
    with uncommitted changes (the record names the commit whose code ran), an empty
    reason."""
    if not run.accept:
        return
    if run.accept_loss is not None and not run.accept_loss.strip():
        raise InputError("--accept-loss", "give the reason the loss is accepted")
    changed = dirty(repo, ignore=(run.accepted,))
    if changed:
        raise InputError("--accept", f"the tree has uncommitted changes ({', '.join(changed[:3])}"
                         f"{', ...' if len(changed) > 3 else ''}): commit them first, so the "
                         "record names the code that ran")


def run_guard(battery: Battery, run: GuardRun, out_dir: Path) -> dict:
    """Run each entry on both sides on fresh plants, judge them (`guard_verdict`), write
    guard.json and guard.md into out_dir (each entry's runs under out_dir/NAME/), and with
    `accept` append the records. Returns guard.json's content; "passed" is False where an
    entry failed."""
    from flowerpose.eval.studies.guard_report import guard_markdown

    watch = Stopwatch()
    history = history_file.read_history(run.accepted)
    repo = repository()
    check_accept(run, repo)
    bases = {name: resolve(repo, rev) for name, rev in plan_bases(battery, run, history).items()}
    run_seed = run.run_seed if run.run_seed is not None else secrets.randbits(31)
    LOG.info(f"guard: run seed {run_seed} (--seed {run_seed} draws the same plants)")
    revisions = {commit: materialise(repo, commit, out_dir / "revisions")
                 for commit in sorted(set(bases.values()))}
    # An accept runs on a clean tree (its accepted file aside): the commit is the code.
    working = Revision("working tree", head(repo) if run.accept else git_commit() or head(repo))
    rows: dict[str, dict] = {}
    for entry in run.entries:
        plants = fresh_plants(entry, run_seed)
        sides = {}
        for side, revision, extra in (("base", revisions[bases[entry.name]], []),
                                      ("change", working, list(run.setting_arguments))):
            folder = out_dir / entry.name / side
            LOG.info(f"guard: {entry.name}: {side} ({revision.name}) on {entry.label()}")
            revision.run(side_arguments(entry, plants, folder, list(run.folders), run.workers,
                                        run.cache) + extra, out_dir / entry.name / f"{side}.log")
            sides[side] = read_side(entry, folder)
        rows[entry.name] = {"label": entry.label(), "base": bases[entry.name],
                            "plants": plants.to_json(entry),
                            **judge_entry(sides["change"], sides["base"], battery.margins,
                                          entry.task == "pollinate")}
        if run.trend:
            rows[entry.name]["trend"] = _trend(entry, run, out_dir)
    passed = decide(rows, battery.margins)
    for entry in run.entries:
        row = rows[entry.name]
        row["drift"] = history_file.drift(
            history_file.of_entry(history, entry.name, battery.version), row["measures"])
        passed &= _judge_drift(row, battery.margins)
    report = {"run": run_record(), "run_seed": run_seed,
              "battery": {"version": battery.version, "path": battery.path,
                          "margins": dataclasses.asdict(battery.margins)},
              "change": working.commit, "settings": list(run.settings),
              "accepted": str(run.accepted), "entries": rows, "passed": passed,
              "seconds": round(watch.elapsed(), 1)}
    write_json(out_dir / "guard.json", report)
    write_text(out_dir / "guard.md", guard_markdown(report))
    if run.accept:
        accept(battery, run, report, history)
    return report


def _trend(entry: GuardEntry, run: GuardRun, out_dir: Path) -> dict:
    """The working tree's values on the entry's fixed trend plants (no verdict)."""
    folder = out_dir / entry.name / "trend"
    Revision("working tree").run(
        side_arguments(entry, trend_plants(entry), folder, list(run.folders), run.workers,
                       run.cache) + list(run.setting_arguments),
        out_dir / entry.name / "trend.log")
    plants = read_side(entry, folder)
    summary = summarise(plants)
    plane = summary["error_deg"]["plane"]
    return {"plants": trend_plants(entry).to_json(entry),
            "visible": summary["visible"], "found_visible": summary["found_visible"],
            "recall_visible": summary["recall_visible"], "fp": summary["fp"],
            "plane_mean": plane["mean"], "plane_mean_ci95": plane["mean_ci95"],
            "tails": tails(plants)}


def _judge_drift(row: dict, margins: Margins) -> bool:
    """Fail an entry whose summed accepted losses since the last accepted loss, with this
    run's, pass a margin (the ratchet of small losses each within it)."""
    over = [f"{name}: drift {spans['since_loss']['loss']:+.2f} over "
            f"{spans['since_loss']['records']} records since the last accepted loss, beyond "
            f"the margin {margins.of(name):g}"
            for name, spans in row["drift"].items()
            if "since_loss" in spans and spans["since_loss"]["loss"] > margins.of(name)]
    if over:
        row["reasons"] = [*row["reasons"], *over]
        row["verdict"] = "fail"
    return not over


def accept(battery: Battery, run: GuardRun, report: dict, history: list[dict]) -> None:
    """Append the run's records (module docstring); InputError (nothing written) for a
    failed run without `accept_loss`."""
    failed = [name for name, row in report["entries"].items() if row["verdict"] == "fail"]
    if failed and run.accept_loss is None:
        raise InputError("--accept", f"the run failed on {', '.join(failed)}: nothing "
                         "accepted; accept the loss as a decision with --accept-loss "
                         "\"REASON\", or fix the change")
    records = []
    for name, row in report["entries"].items():
        loss = row["verdict"] == "fail"
        records.append({
            "entry": name, "battery_version": battery.version, "commit": report["change"],
            "base": row["base"], "date": report["run"]["date"],
            "command": report["run"]["command"], "settings": report["settings"],
            "run_seed": report["run_seed"], "plants": row["plants"],
            "decision": "loss" if loss else "pass",
            "reason": run.accept_loss if loss else None, "verdict": row["verdict"],
            "reasons": row["reasons"],
            "measures": {k: {f: m[f] for f in ("loss", "se", "upper", "n", "flowers", "margin",
                                                "verdict")}
                         for k, m in row["measures"].items()},
            "tails": row["tails"], "trend": row.get("trend")})
    history_file.append(run.accepted, history, records)
    LOG.info(f"guard: {len(records)} records appended to {run.accepted}")
