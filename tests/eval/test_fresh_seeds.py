"""The guard's fresh seeds are nobody else's: no file of the project, no suite, battery trend
or command default uses a seed of the range, and sweep and tune refuse one."""

import re
import subprocess
from pathlib import Path

import pytest

from flowerpose.cli import main
from flowerpose.config import load_suite, suite_names
from flowerpose.eval.studies.fresh_seeds import FRESH_SEEDS, entry_draw
from flowerpose.eval.studies.guard import load_battery

REPO = Path(__file__).resolve().parents[2]
#: The files allowed to hold seeds of the range: where it is written down, and the guard's
#: own records of the plants it drew.
OWNERS = {"eval/studies/fresh_seeds.py", "assets/guard/accepted.json"}
#: A whole number (not part of a word, a hex digest or a decimal fraction).
NUMBER = re.compile(r"(?<![0-9A-Za-z_.])(\d[\d_]*)(?![0-9A-Za-z_]|\.\d)")


def _project_files() -> list[Path]:
    try:
        listed = subprocess.run(["git", "-C", str(REPO), "ls-files"], capture_output=True,
                                text=True, check=True).stdout.split()
        return [REPO / name for name in listed]
    except (OSError, subprocess.CalledProcessError):
        return [p for p in REPO.rglob("*") if p.is_file() and not {".git", ".venv", "runs"}
                & set(p.relative_to(REPO).parts)]


def test_no_file_of_the_project_uses_a_seed_of_the_fresh_range():
    bounds = {FRESH_SEEDS.start, FRESH_SEEDS.stop - 1}
    used = []
    for path in _project_files():
        name = path.relative_to(REPO).as_posix()
        if name in OWNERS or not path.is_file():
            continue
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            continue  # a picture, a model
        for match in NUMBER.finditer(text):
            value = int(match.group(1).replace("_", ""))
            if value in FRESH_SEEDS and value not in bounds:
                used.append(f"{name}: {value}")
    assert not used


def test_suites_battery_trends_and_defaults_stay_below_the_range():
    for name in suite_names():
        fixed = load_suite(name)["eval"]
        if fixed["source"] != "real":
            assert fixed["seed"] + fixed["plants"] <= FRESH_SEEDS.start, name
    for entry in load_battery().entries:
        assert entry.seed + entry.plants <= FRESH_SEEDS.start, entry.name


def test_an_entry_draw_is_reproducible_and_inside_the_range():
    first, stress = entry_draw(12, "oracle-20", 20)
    assert (first, stress) == entry_draw(12, "oracle-20", 20)
    assert entry_draw(12, "field-10", 20) != (first, stress)
    assert first in FRESH_SEEDS and first + 19 in FRESH_SEEDS and stress in FRESH_SEEDS


@pytest.mark.parametrize("command", [
    ["sweep", "--grid", "cluster.eps=0.01", "--plants", "2", "--seed",
     str(FRESH_SEEDS.start + len(FRESH_SEEDS) // 2)],
    ["tune", "--space", "SPACE", "--trials", "1", "--seed", str(FRESH_SEEDS.stop - 1)],
    ["tune", "--space", "SPACE", "--trials", "1", "--seed", str(FRESH_SEEDS.start - 2)],
])
def test_sweep_and_tune_refuse_the_guards_seeds(tmp_path, capsys, command):
    space = tmp_path / "space.toml"
    space.write_text('"cluster.eps" = { low = 0.006, high = 0.012 }\n')
    arguments = [str(space) if a == "SPACE" else a for a in command]
    assert main([*arguments, "--out", str(tmp_path / "out")]) == 2
    assert "guard's fresh plants" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
