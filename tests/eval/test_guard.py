"""The guard: a change against its base on fresh plants. The battery is checked whole; the
verdict fails a planted flip, a lost 3 % of flowers and a loss on too few flowers, and passes
an identical run and a shift within the margin; accepting is a decision on record, refused
for a failed run without a reason; another revision's code runs from its own tree."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from realplants import write_real_plant

from flowerpose.cli import main
from flowerpose.errors import InputError
from flowerpose.eval.studies import accepted as history_file
from flowerpose.eval.studies.fresh_seeds import FRESH_SEEDS
from flowerpose.eval.studies.guard import (
    BATTERY,
    GuardRun,
    accept,
    fresh_plants,
    load_battery,
    run_guard,
    side_arguments,
)
from flowerpose.eval.studies.guard_verdict import Margins, decide, judge_entry
from flowerpose.eval.studies.revision import dirty, materialise, repository, resolve

MARGINS = Margins(0.5, 2.0, 1.0, 2.0, 0, 0, 0)
FITS = ("plane", "superellipsoid", "paraboloid")

BATTERY_TEXT = """
[battery]
version = 2

[margins]
plane_mean_deg = 0.5
recall_points = 2.0
fp_per_100_flowers = 1.0
pollinated_points = 2.0
new_flipped = 0
new_over_20 = 0
new_collisions = 0

[[entry]]
name = "plant"
source = "real"
plant = "plant"
quick = true

[[entry]]
name = "plant-thin"
source = "real"
plant = "plant"
thin = [0.5]
repeats = 2
"""


def _plants(errors: dict[str, list[float | None]], fp: int = 0) -> list[dict]:
    """report.json plant entries: one visible flower a value, None where it was missed."""
    plants = []
    for name, values in errors.items():
        found = [e for e in values if e is not None]
        plants.append({
            "plant": name, "gt": len(values), "visible": len(values),
            "detections": len(found) + fp, "found": len(found), "found_visible": len(found),
            "extra": 0, "fp": fp, "error_deg": dict.fromkeys(FITS, found),
            "failed": dict.fromkeys(FITS, 0),
            "matches": [{"detection": k, "truth": k, "distance_m": 0.001,
                         "error_deg": dict.fromkeys(FITS, e)}
                        for k, e in enumerate(values) if e is not None]})
    return plants


def _field(plants: int = 20, flowers: int = 13, seed: int = 0) -> dict[str, list[float]]:
    rng = np.random.default_rng(seed)
    return {f"seed-{k}": list(rng.gamma(3.5, 0.6, flowers)) for k in range(plants)}


def _judged(change: dict, base: dict, **kwargs) -> dict:
    rows = {"e": judge_entry(_plants(change, **kwargs), _plants(base), MARGINS, False)}
    decide(rows, MARGINS)
    return rows["e"]


def test_an_identical_run_is_identical_and_tests_nothing():
    base = _field()
    row = _judged(base, base)
    assert row["verdict"] == "identical" and row["measures"] == {} and not row["reasons"]


def test_a_shift_within_the_margin_passes_and_says_so():
    base = _field()
    change = {name: [e + 0.05 for e in values] for name, values in base.items()}
    row = _judged(change, base)
    assert row["verdict"] == "pass"
    plane = row["measures"]["plane"]
    assert plane["loss"] == pytest.approx(0.05) and plane["upper"] < 0.5
    assert plane["verdict"] == "within the margin" and plane["flowers"] == 260


def test_one_flipped_normal_fails_by_name_whatever_the_mean():
    base = _field()
    change = {name: list(values) for name, values in base.items()}
    change["seed-3"][4] = 171.0  # the mean moves by 0.65 degrees over 260 flowers
    row = _judged(change, base)
    assert row["verdict"] == "fail"
    assert row["new"]["flipped"] == [{"plant": "seed-3", "flower": "4", "error_deg": 171.0,
                                      "base_deg": base["seed-3"][4]}]
    assert any("1 new flipped normals" in r and "seed-3 flower 4" in r for r in row["reasons"])


def test_three_percent_of_flowers_lost_fails_the_recall_margin():
    base = _field()
    change = {name: list(values) for name, values in base.items()}
    lost = 0
    for values in change.values():
        for k in range(0, len(values), 5):
            if lost < 8:  # 8 of 260: 3 %
                values[k], lost = None, lost + 1
    row = _judged(change, base)
    recall = row["measures"]["recall"]
    assert recall["loss"] == pytest.approx(100 * 8 / 260, abs=0.01)
    assert recall["verdict"] == "not shown within the margin" and row["verdict"] == "fail"
    assert any(r.startswith("recall: not shown within the margin") for r in row["reasons"])


def test_a_loss_on_a_few_flowers_is_not_within_and_too_few_is_said():
    base = {"p": [7.0, 5.0, 9.0, 12.0, 3.0, 6.0, 8.0, 4.0, 10.0, 11.0, 7.5]}
    change = {"p": [*base["p"][:-1], base["p"][-1] + 3.0]}  # one flower 3 degrees worse
    assert _judged(change, base)["measures"]["plane"]["verdict"] == "not shown within the margin"
    small = {"p": base["p"][:4]}
    tiny = _judged({"p": [v + 0.1 for v in small["p"]]}, small)
    assert tiny["measures"]["plane"]["verdict"] == "too few flowers to tell"
    assert tiny["verdict"] == "fail"


def test_more_false_positives_beyond_the_margin_fail():
    base = _field()
    row = _judged(base, base, fp=1)  # one more a plant: 7.7 per 100 flowers
    assert row["measures"]["fp"]["loss"] == pytest.approx(100 / 13, abs=0.01)
    assert row["measures"]["fp"]["verdict"] == "not shown within the margin"


def test_holm_spans_every_entry_of_the_run():
    base = _field()
    noise = np.random.default_rng(1)
    change = {name: [e + 0.3 + noise.normal(0, 0.5) for e in values]
              for name, values in base.items()}
    alone = {"a": judge_entry(_plants(change), _plants(base), MARGINS, False)}
    decide(alone, MARGINS)
    many = {name: judge_entry(_plants(change), _plants(base), MARGINS, False)
            for name in "abcdefgh"}
    decide(many, MARGINS)
    assert many["a"]["measures"]["plane"]["p_holm"] > alone["a"]["measures"]["plane"]["p_holm"]


def test_the_shipped_battery_reads_with_its_margins_and_quick_entries():
    battery = load_battery()
    assert battery.path == str(BATTERY) and battery.version >= 2
    assert battery.margins.plane_mean_deg == 0.5 and battery.margins.new_flipped == 0
    quick = {e.name for e in battery.select([], quick=True)}
    assert {"oracle-20", "field-10", "hard-10", "real3", "real3-thin"} == quick
    assert {"scan-6", "pollinate-10", "real3-cut"} <= {e.name for e in battery.select([])}
    assert all(e.seed + e.plants <= FRESH_SEEDS.start for e in battery.entries)


@pytest.mark.parametrize("change,message", [
    ("[[entri]]\nname = 'x'\n", "unknown table"),
    ("[margins]\nplane_mean_deg = 0.5\n", "margins"),
    ("", ""),  # the good one: must load
])
def test_a_battery_is_checked_whole(tmp_path, change, message):
    path = tmp_path / "battery.toml"
    text = BATTERY_TEXT if "[margins]" not in change else BATTERY_TEXT.split("[margins]")[0] \
        + change + BATTERY_TEXT.split("new_collisions = 0\n")[1]
    path.write_text(text if "[margins]" in change else text + change)
    if not message:
        assert len(load_battery(path).entries) == 2
        return
    with pytest.raises(InputError, match=message):
        load_battery(path)


def test_bad_values_in_a_battery_are_one_line(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    for replace, message in ((("repeats = 2", "repeats = '2'"), "wrong type"),
                             (("repeats = 2", "repeats = 2\nx = 1"), "unknown key"),
                             (("new_flipped = 0", "new_flipped = -1"), "new_flipped"),
                             (("new_flipped = 0", "new_flipped = 0.5"), "new_flipped"),
                             (("thin = [0.5]", "thin = [5]"), "0-1"),
                             (("version = 2", "version = true"), "version")):
        bad.write_text(BATTERY_TEXT.replace(*replace))
        with pytest.raises(InputError, match=message):
            load_battery(bad)
    assert main(["guard", "--battery", str(bad), "--out", str(tmp_path / "out")]) == 2
    assert "version" in capsys.readouterr().err
    (tmp_path / "b.toml").write_text(BATTERY_TEXT)
    assert main(["guard", "--battery", str(tmp_path / "b.toml"), "--out",
                 str(tmp_path / "out2")]) == 2
    assert "--real DIR" in capsys.readouterr().err
    assert main(["guard", "--only", "nope", "--out", str(tmp_path / "out3")]) == 2
    assert main(["guard", "--accept-loss", "why", "--out", str(tmp_path / "out4")]) == 2
    assert "--accept too" in capsys.readouterr().err
    assert main(["guard", "--only", "oracle-20", "--accepted", str(tmp_path / "none.json"),
                 "--out", str(tmp_path / "out5")]) == 2
    assert "--base REV" in capsys.readouterr().err


def test_fresh_plants_are_drawn_from_the_run_seed_in_the_fresh_range():
    entry = load_battery().select(["oracle-20"])[0]
    first, again, other = (fresh_plants(entry, s) for s in (5, 5, 6))
    assert first == again != other
    assert first.seed in FRESH_SEEDS and first.seed + entry.plants - 1 in FRESH_SEEDS
    arguments = side_arguments(entry, first, Path("o"), [], 2, None)
    assert arguments[:2] == ["eval", "--source"] and str(first.seed) in arguments
    assert "--no-cache" in arguments


def _record(entry: str, decision: str = "pass", loss: float = 0.1,
            reason: str | None = None) -> dict:
    return {"entry": entry, "battery_version": 2, "commit": f"c-{loss}", "base": "b",
            "date": "2026-12-06", "command": "flowerpose guard", "settings": [],
            "run_seed": 1, "decision": decision, "reason": reason,
            "measures": {"plane": {"loss": loss, "se": 0.1}}}


def test_the_history_reads_the_first_format_and_only_ever_grows(tmp_path):
    legacy = tmp_path / "accepted.json"
    legacy.write_text(json.dumps({"battery_version": 1, "run": {"commit": "abc", "date": "d",
                                                                "command": "c"},
                                  "entries": {"oracle-20": {"visible": 258}}}))
    history = history_file.read_history(legacy)
    assert [(r["entry"], r["decision"], r["battery_version"]) for r in history] == [
        ("oracle-20", "legacy", 1)]
    assert history_file.base_of(history, "oracle-20", 2) is None
    history_file.append(legacy, history, [_record("oracle-20")])
    history_file.append(legacy, history_file.read_history(legacy), [_record("oracle-20", loss=0.2)])
    again = history_file.read_history(legacy)
    assert [r["decision"] for r in again] == ["legacy", "pass", "pass"]
    assert again[0]["values"] == {"visible": 258}
    assert history_file.base_of(again, "oracle-20", 2) == "c-0.2"
    again[2] = {**again[2], "decision": "loss"}
    legacy.write_text(json.dumps({"format": 2, "records": again}))
    with pytest.raises(InputError, match="reason"):
        history_file.read_history(legacy)
    legacy.write_text(json.dumps({"format": 2, "records": [{"entry": 3}]}))
    with pytest.raises(InputError, match="record 0"):
        history_file.read_history(legacy)


def test_drift_sums_the_accepted_losses_and_restarts_at_a_recorded_loss():
    records = [_record("e", loss=0.2), _record("e", loss=0.2),
               _record("e", "loss", 1.0, "a real trade"), _record("e", loss=0.2)]
    drift = history_file.drift(records, {"plane": {"loss": 0.2, "se": 0.1}})
    assert drift["plane"]["total"]["loss"] == pytest.approx(1.8)
    assert drift["plane"]["since_loss"] == {"loss": 0.4, "se": 0.1414, "records": 2}
    assert history_file.drift([], {"plane": {"loss": 0.2, "se": 0.1}}) == {}


def _report(verdict: str) -> dict:
    row = {"verdict": verdict, "base": "b", "plants": {}, "reasons": [], "measures": {
        "plane": {"loss": 0.7, "se": 0.1, "upper": 0.9, "n": 30, "flowers": 30, "margin": 0.5,
                  "verdict": "not shown within the margin"}}, "tails": {}}
    return {"entries": {"oracle-20": row}, "change": "abc", "run_seed": 7, "settings": [],
            "run": {"date": "2026-12-06", "command": "flowerpose guard --accept"}}


def test_a_failed_run_is_accepted_only_as_a_loss_with_its_reason(tmp_path):
    path = tmp_path / "accepted.json"
    history_file.append(path, [], [_record("oracle-20")])
    before = path.read_bytes()
    battery = load_battery()
    run = GuardRun((), (), path, accept=True)
    with pytest.raises(InputError, match="--accept-loss"):
        accept(battery, run, _report("fail"), history_file.read_history(path))
    assert path.read_bytes() == before
    loss = GuardRun((), (), path, accept=True, accept_loss="fits the cupped flowers better")
    accept(battery, loss, _report("fail"), history_file.read_history(path))
    history = history_file.read_history(path)
    assert len(history) == 2 and history[0] == json.loads(before)["records"][0]
    assert (history[1]["decision"], history[1]["reason"], history[1]["run_seed"],
            history[1]["commit"]) == ("loss", "fits the cupped flowers better", 7, "abc")


def _git(folder, *arguments):
    subprocess.run(["git", "-C", str(folder), *arguments], check=True, capture_output=True)


def test_a_revision_runs_its_own_code_from_its_own_layout(tmp_path, monkeypatch):
    repo = tmp_path / "repo"
    (repo / "core").mkdir(parents=True)
    (repo / "stages").mkdir()
    (repo / "pyproject.toml").write_text(
        '[tool.setuptools]\npackage-dir = { "flowerpose" = "core", '
        '"flowerpose.pipeline" = "stages" }\npackages = ["flowerpose", "flowerpose.pipeline"]\n')
    (repo / "core" / "__init__.py").write_text("")
    (repo / "core" / "__main__.py").write_text(
        "import sys, pathlib, flowerpose.pipeline as p\n"
        "print(p.WHO, sys.argv[1:], pathlib.Path(sys.argv[1]).is_file())\n")
    (repo / "stages" / "__init__.py").write_text("WHO = 'the first revision'\n")
    _git(repo, "init", "-q")
    _git(repo, "-c", "user.email=t@t", "-c", "user.name=t", "commit", "-qam", "one",
         "--allow-empty")
    _git(repo, "add", ".")
    _git(repo, "-c", "user.email=t@t", "-c", "user.name=t", "commit", "-qm", "two")
    (repo / "stages" / "__init__.py").write_text("WHO = 'the working tree'\n")
    assert dirty(repo) == ["stages/__init__.py"]
    commit = resolve(repo, "HEAD")
    revision = materialise(repo, commit, tmp_path / "revisions")
    # Relative paths mean what they mean to the caller (CI passes `--out runs/...`).
    monkeypatch.chdir(tmp_path)
    Path("hello.txt").write_text("")
    revision.run(["hello.txt"], Path("run.log"))
    assert (tmp_path / "run.log").read_text().strip() == "the first revision ['hello.txt'] True"
    assert materialise(repo, commit, tmp_path / "revisions").tree == revision.tree  # reused
    with pytest.raises(InputError, match="names no commit"):
        resolve(repo, "no-such-revision")


@pytest.mark.slow
def test_a_guard_run_compares_both_sides_on_the_same_plants(tmp_path):
    try:
        head = resolve(repository(), "HEAD")
    except InputError:
        pytest.skip("flowerpose runs from an installed copy, not a git checkout")
    folder = write_real_plant(tmp_path / "plant", "candidates")
    path = tmp_path / "battery.toml"
    path.write_text(BATTERY_TEXT)
    battery = load_battery(path)
    run = GuardRun(battery.entries, (folder,), tmp_path / "accepted.json", base=head,
                   run_seed=3, workers=1)
    same = run_guard(battery, run, tmp_path / "a")
    assert same["passed"] and same["run_seed"] == 3
    assert all(row["verdict"] == "identical" for row in same["entries"].values())
    assert (tmp_path / "a" / "guard.md").is_file()
    assert json.loads((tmp_path / "a" / "guard.json").read_text())["entries"]["plant-thin"][
        "plants"]["stress_seed"] in FRESH_SEEDS
    # A corolla test far too strict loses flowers: the change fails, naming the measure.
    worse = run_guard(battery, GuardRun(
        battery.entries[:1], (folder,), tmp_path / "accepted.json", base=head, run_seed=3,
        workers=1, setting_arguments=("--set", "cluster.min_coverage=3.0")), tmp_path / "b")
    row = worse["entries"]["plant"]
    assert not worse["passed"] and row["verdict"] == "fail"
    assert row["measures"]["recall"]["loss"] > 0
    assert any(reason.startswith("recall:") for reason in row["reasons"])
    assert not (tmp_path / "accepted.json").exists()


def test_the_guard_is_on_the_command_line_with_its_decisions(capsys):
    with pytest.raises(SystemExit):
        main(["guard", "--help"])
    text = capsys.readouterr().out
    for flag in ("--base", "--seed", "--quick", "--accept-loss", "--trend"):
        assert flag in text


def test_the_same_code_laid_out_as_another_revision_has_the_same_code_version(tmp_path):
    """The guard's two sides share the stage cache: a revision laid out as one tree names its
    files as the installed packages do."""
    from flowerpose.cache import _module_file, code_version, module_closure

    try:
        repo = repository()
    except InputError:
        pytest.skip("flowerpose runs from an installed copy, not a git checkout")
    roots = ("flowerpose.eval.capture.scan_source",)
    files = [str(_module_file(m).relative_to(repo)) for m in module_closure(roots)
             if _module_file(m).is_relative_to(repo)]
    if subprocess.run(["git", "-C", str(repo), "diff", "--quiet", "HEAD", "--", *files]
                      ).returncode != 0:
        pytest.skip("the capture's code has uncommitted changes")
    revision = materialise(repo, resolve(repo, "HEAD"), tmp_path)
    probe = ("from flowerpose.cache import code_version; "
             f"print(code_version({roots!r}))")
    laid_out = subprocess.run([sys.executable, "-P", "-c", probe], cwd=revision.tree,
                              env={**os.environ, "PYTHONPATH": str(revision.tree)},
                              capture_output=True, text=True, check=True).stdout.strip()
    assert laid_out == code_version(roots)
