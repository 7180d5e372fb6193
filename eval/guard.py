"""The guard battery (`flowerpose guard`): every pipeline change checked on plants nobody
tuned it on before it lands, against the values last accepted.

The battery (`assets/guard/battery.toml`, versioned like the suites) is a list of entries:
seeded synthetic plants of a source and preset (the full simulated loop, the oracle, the
field and hard presets, on seeds outside the 0-9 the settings were chosen on), a real
plant folder as it is, and the same folder thinned or with its flowers cut at seeded
levels and repeats (`flowerpose stress`). Each entry's flowers are keyed (plant, flower;
for a perturbed entry, its level and repeat too), so a run compares with the accepted one
flower by flower (`eval/paired.py`).

An entry fails where the run is worse beyond the uncertainty: its recall of visible flowers
below the accepted value's 95 % interval or fewer flowers found by McNemar's test; its
plane error's mean above the accepted interval or worse by the paired difference's
interval; more false positives by the counts' exact test. The accepted values
(`assets/guard/accepted.json`) are written by `flowerpose guard --accept`, which a change
that is meant to move them commits with the change.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib.resources import files
from pathlib import Path

from flowerpose.atomic import write_text
from flowerpose.config import DEFAULT_PRESET, load_toml
from flowerpose.errors import InputError
from flowerpose.eval.config import EvalConfig, eval_config
from flowerpose.eval.paired import compare_runs, difference_cell
from flowerpose.eval.report import markdown_table, run_record, summarise
from flowerpose.eval.stats import interval_text
from flowerpose.jsonio import read_json, write_json
from flowerpose.log import LOG

#: The shipped battery and its accepted values.
BATTERY = files("flowerpose.assets") / "guard" / "battery.toml"
ACCEPTED = files("flowerpose.assets") / "guard" / "accepted.json"
#: What `flowerpose guard` writes into its --out folder (and each entry's run folder).
GUARD_FILES = ("guard.json", "guard.md")
_ENTRY_KEYS = {"name", "description", "source", "preset", "plants", "seed", "plant", "thin",
               "cut", "repeats"}


@dataclass(frozen=True)
class GuardEntry:
    """One entry of the battery: seeded synthetic plants (`source`, `preset`, `plants` from
    `seed`), or a real plant folder (`plant`, its folder's name) as it is or under seeded
    perturbations (`thin`: fractions of points kept; `cut`: shares of each flower's disc
    removed; each `repeats` times)."""

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

    @property
    def perturbed(self) -> bool:
        return bool(self.thin or self.cut)

    def label(self) -> str:
        if self.source == "real":
            levels = ", ".join([*(f"thin {v:g}" for v in self.thin),
                                *(f"cut {v:g}" for v in self.cut)])
            return self.plant + (f" ({levels}; {self.repeats} repeats)" if levels else "")
        return (f"{self.plants} {self.preset} plants, {self.source} clouds, seeds "
                f"{self.seed}-{self.seed + self.plants - 1}")


@dataclass(frozen=True)
class Battery:
    """The battery's version, what it is for, and its entries."""

    version: int
    description: str
    entries: tuple[GuardEntry, ...]
    path: str

    def select(self, names: list[str]) -> tuple[GuardEntry, ...]:
        """The entries named (all for none); InputError for a name it has not."""
        known = [e.name for e in self.entries]
        for name in names:
            if name not in known:
                raise InputError("only", f"{name!r}: the battery's entries are {', '.join(known)}")
        return tuple(e for e in self.entries if not names or e.name in names)


def load_battery(path: Path | None = None) -> Battery:
    """The battery file (the shipped one by default), checked: InputError naming the file
    for an entry without a name or source, an unknown key, a synthetic entry without
    plants, or a real one without its plant."""
    source = Path(str(path if path is not None else BATTERY))
    data = load_toml(source)
    header = data.get("battery", {})
    if not isinstance(header.get("version"), int) or header["version"] < 1:
        raise InputError(source, "[battery] needs a version, a whole number from 1")
    entries = []
    for k, raw in enumerate(data.get("entry", [])):
        unknown = sorted(set(raw) - _ENTRY_KEYS)
        if unknown:
            raise InputError(source, f"entry {k}: unknown key {unknown[0]!r} (known: "
                             f"{', '.join(sorted(_ENTRY_KEYS))})")
        if "name" not in raw or raw.get("source") not in ("oracle", "scan", "rgbd", "real"):
            raise InputError(source, f"entry {k}: needs a name and a source (oracle, scan, "
                             "rgbd or real)")
        entry = GuardEntry(**{**raw, "thin": tuple(raw.get("thin", ())),
                              "cut": tuple(raw.get("cut", ())),
                              "description": raw.get("description", "")})
        if entry.source == "real" and not entry.plant:
            raise InputError(source, f"entry {entry.name}: a real entry names its plant folder")
        if entry.source != "real" and (entry.plants < 1 or entry.perturbed):
            raise InputError(source, f"entry {entry.name}: a synthetic entry needs plants "
                             "(1 or more) and no perturbation")
        entries.append(entry)
    names = [e.name for e in entries]
    if not entries or len(set(names)) != len(names):
        raise InputError(source, "the battery needs entries, each named once")
    return Battery(header["version"], header.get("description", ""), tuple(entries),
                   str(source))


def real_folder(entry: GuardEntry, folders: list[Path]) -> Path:
    """The folder of a real entry's plant among those given (`--real`), by its name."""
    for folder in folders:
        if Path(folder).resolve().name == entry.plant:
            return Path(folder)
    raise InputError("real", f"the battery's entry {entry.name} needs the plant folder "
                     f"{entry.plant}: give it with --real DIR (flowerpose data fetch "
                     f"{entry.plant} --to DIR fetches it)")


def entry_config(entry: GuardEntry, overrides: tuple[dict, ...] = ()) -> EvalConfig:
    """An entry's settings: its preset's (a real plant: the defaults), with the user's
    `overrides` (dotted keys) over them in order."""
    return eval_config(DEFAULT_PRESET if entry.source == "real" else entry.preset, overrides)


def run_entry(entry: GuardEntry, config: EvalConfig, out_dir: Path, folders: list[Path],
              workers: int | None, cache: Path | None) -> list[dict]:
    """One entry run with `config` (`entry_config`) into out_dir: its report.json plant
    entries, each plant named so that (plant, flower) keys one flower (a perturbed entry's:
    "LEVEL rREPEAT PLANT")."""
    from flowerpose.eval.harness import run_eval
    from flowerpose.eval.run import EvalRun

    if entry.source != "real":
        run = EvalRun(source=entry.source, plants=entry.plants, seed=entry.seed)
        return run_eval(config, run, out_dir, workers, cache)["plants"]
    folder = real_folder(entry, folders)
    if not entry.perturbed:
        return run_eval(config, EvalRun(source="real", folders=(folder,)), out_dir,
                        workers, cache)["plants"]
    from flowerpose.eval.stress import plan_from, run_stress

    plan = plan_from({"thin": list(entry.thin), "cut": list(entry.cut)}, repeats=entry.repeats)
    report = run_stress(config, plan, out_dir, "real", [folder], workers=workers)
    return [{**plant, "plant": f"{row['label']} r{k} {plant['plant']}"}
            for row in report["rows"] for k, plant in enumerate(row["plants"])]


def entry_record(entry: GuardEntry, plants: list[dict]) -> dict:
    """What the guard keeps of an entry's run: its summary's numbers and its plant entries
    (the flowers found and their errors, for the next run's paired comparison)."""
    summary = summarise(plants)
    plane = summary["error_deg"]["plane"]
    return {"label": entry.label(), "found_visible": summary["found_visible"],
            "visible": summary["visible"], "recall_visible": summary["recall_visible"],
            "recall_visible_ci95": summary["recall_visible_ci95"], "fp": summary["fp"],
            "detections": summary["detections"], "plane": {
                key: plane[key] for key in ("mean", "mean_ci95", "median", "p90", "n",
                                            "over_90")},
            "plants": [{key: p[key] for key in ("plant", "visible", "found_visible", "fp",
                                                "detections", "gt", "found", "extra",
                                                "error_deg", "failed", "matches")}
                       for p in plants]}


def judge(record: dict, accepted: dict | None) -> dict:
    """An entry's verdict against its accepted record (None: none yet): "worse" where the
    recall, the plane error or the false positives are worse beyond the uncertainty
    (module docstring), "better" where one is better beyond it and none worse, else
    "pass"; with the reasons, and the paired comparison with the accepted flowers."""
    if accepted is None:
        return {"verdict": "new", "reasons": ["no accepted value yet"], "paired": None}
    paired = compare_runs(record["plants"], accepted["plants"])
    reasons = []
    low = accepted["recall_visible_ci95"]["low"]
    if record["recall_visible"] is not None and low is not None and record["recall_visible"] < low:
        reasons.append(f"recall {record['recall_visible']:.3f} below the accepted interval "
                       f"{interval_text(accepted['recall_visible_ci95'], 3)}")
    found = paired["found"]
    if found["shown"] and found["only_theirs"] > found["only_ours"]:
        reasons.append(f"{found['only_theirs']} flowers lost, {found['only_ours']} gained "
                       f"(McNemar p = {found['p']:.3g})")
    high = accepted["plane"]["mean_ci95"]["high"]
    mean = record["plane"]["mean"]
    if mean is not None and high is not None and mean > high:
        reasons.append(f"plane mean {mean:.2f}° above the accepted interval "
                       f"{interval_text(accepted['plane']['mean_ci95'])}")
    plane = paired["fits"]["plane"]
    if plane["shown"] and plane["direction"] == "worse":
        reasons.append(f"plane error worse by {difference_cell(plane)} flowers (paired)")
    false = paired["fp"]
    if false["shown"] and false["ours"] > false["theirs"]:
        reasons.append(f"false positives {false['ours']} against {false['theirs']} "
                       f"(p = {false['p']:.3g})")
    if reasons:
        return {"verdict": "worse", "reasons": reasons, "paired": paired}
    gains = [text for shown, text in (
        (found["shown"] and found["only_ours"] > found["only_theirs"],
         f"{found['only_ours']} flowers gained, {found['only_theirs']} lost"),
        (plane["shown"] and plane["direction"] == "better", "plane error lower (paired)"),
        (false["shown"] and false["ours"] < false["theirs"], "fewer false positives"))
        if shown]
    return {"verdict": "better" if gains else "pass", "reasons": gains, "paired": paired}


def read_accepted(path: Path, battery: Battery) -> dict[str, dict]:
    """The accepted records of this battery version by entry (none for another version or
    no file)."""
    if not Path(path).is_file():
        return {}
    document = read_json(path)
    if document.get("battery_version") != battery.version:
        LOG.warning(f"guard: {path} holds values of battery version "
                    f"{document.get('battery_version')}, not {battery.version}: nothing to "
                    "compare with")
        return {}
    return document.get("entries", {})


def run_guard(battery: Battery, entries: tuple[GuardEntry, ...], out_dir: Path,
              folders: list[Path], accepted_path: Path, workers: int | None = None,
              cache: Path | None = None, accept: bool = False,
              overrides: tuple[dict, ...] = ()) -> dict:
    """Run the entries (with the user's `overrides` over each one's preset), judge each
    against its accepted record, write guard.json and guard.md into out_dir (each entry's
    run under out_dir/NAME), and with `accept` write the run's records as the accepted ones
    (the entries not run keep theirs). Returns guard.json's content; its "passed" is False
    where an entry is worse."""
    accepted = read_accepted(accepted_path, battery)
    configs = {entry.name: entry_config(entry, overrides) for entry in entries}
    rows = {}
    for entry in entries:
        LOG.info(f"guard: {entry.name}: {entry.label()}")
        record = entry_record(entry, run_entry(entry, configs[entry.name], out_dir / entry.name,
                                               folders, workers, cache))
        rows[entry.name] = {"record": record, **judge(record, accepted.get(entry.name))}
    report = {"run": run_record(), "battery": {"version": battery.version,
                                               "path": battery.path},
              "settings": list(overrides),
              "accepted": str(accepted_path), "entries": rows,
              "passed": all(r["verdict"] != "worse" for r in rows.values())}
    write_json(out_dir / "guard.json", report)
    write_text(out_dir / "guard.md", guard_markdown(report, accepted))
    if accept:
        kept = {name: value for name, value in accepted.items() if name not in rows}
        write_json(accepted_path, {
            "battery_version": battery.version, "run": report["run"],
            "entries": {**kept, **{name: r["record"] for name, r in rows.items()}}})
    return report


def guard_rows(report: dict, accepted: dict[str, dict]) -> tuple[list[str], list[list[str]]]:
    """The guard table's header and a row per entry: flowers, recall and plane error with
    their intervals beside the accepted values, the paired difference, the verdict."""
    header = ["entry", "visible flowers", "recall [95 % CI]", "accepted", "FP (accepted)",
              "plane mean [95 % CI]", "accepted", "Δ plane, paired", "verdict"]
    rows = []
    for name, row in report["entries"].items():
        record, old = row["record"], accepted.get(name)
        plane = record["plane"]
        paired = row["paired"]
        rows.append([
            name, str(record["visible"]),
            _recall(record), "-" if old is None else _recall(old),
            f"{record['fp']}" + ("" if old is None else f" ({old['fp']})"),
            _plane(plane), "-" if old is None else _plane(old["plane"]),
            "-" if paired is None else difference_cell(paired["fits"]["plane"]),
            row["verdict"] + (f": {'; '.join(row['reasons'])}"
                              if row["verdict"] in ("worse", "better") else "")])
    return header, rows


def _recall(record: dict) -> str:
    if record["recall_visible"] is None:
        return "-"
    return (f"{record['found_visible']}/{record['visible']} = {record['recall_visible']:.3f} "
            f"{interval_text(record['recall_visible_ci95'], 2)}")


def _plane(plane: dict) -> str:
    if plane["mean"] is None:
        return "-"
    return f"{plane['mean']:.2f}° {interval_text(plane['mean_ci95'])} on {plane['n']}"


def guard_markdown(report: dict, accepted: dict[str, dict]) -> str:
    """guard.md: the verdict, then the table."""
    failed = [n for n, r in report["entries"].items() if r["verdict"] == "worse"]
    verdict = (f"**worse on {', '.join(failed)}**" if failed
               else "no entry is worse than its accepted values")
    return (f"# flowerpose guard\n\n`{report['run']['command']}` ({report['run']['date']}), "
            f"battery v{report['battery']['version']}: {verdict}.\n\n"
            f"{markdown_table(*guard_rows(report, accepted))}\n\n"
            "Intervals are 95 %. Δ plane: this run's plane error minus the accepted run's "
            "on the flowers both found, with its interval and count. An entry is worse where "
            "its recall falls below the accepted interval or McNemar shows flowers lost, its "
            "plane mean rises above the accepted interval or the paired difference shows it "
            "worse, or it has more false positives by the counts' exact test.\n")
