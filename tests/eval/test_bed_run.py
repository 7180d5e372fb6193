"""`flowerpose field --sim`: a bed of generated plants filmed in one world, each
reconstructed while the next is filmed, scored against its truth, resumable."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from flowerpose.cli import main
from flowerpose.cloudio import read_cloud

BED = """[scan.path]
cylinder_radius_m = 0.3

[[plant]]
name = "a"
x = 1.0
y = 0.75

[[plant]]
name = "b"
x = 1.6
y = 0.75
"""
SMALL = ["--preset", "easy", "--set", "scan.camera.width=480", "--set",
         "scan.camera.height=270", "--set", "scan.camera.frame_rate_hz=0.04", "--set",
         "scan.frames.count=60"]


@pytest.fixture(scope="module")
def bed_run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("bed")
    bed = folder / "bed.toml"
    bed.write_text(BED)
    out = folder / "run"
    done = subprocess.run([sys.executable, "-m", "flowerpose", "field", "--sim", "--bed",
                           str(bed), "--out", str(out), *SMALL, "-q"], capture_output=True,
                          text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    assert done.returncode == 0, done.stderr
    return bed, out, done.stdout


@pytest.mark.slow
def test_a_bed_is_filmed_reconstructed_and_scored_plant_by_plant(bed_run):
    _, out, said = bed_run
    report = json.loads((out / "report.json").read_text())
    assert [row["stage"] for row in report["bed"]["plants"]] == ["detected", "detected"]
    for entry in report["plants"]:
        assert entry["visible"] > 0 and entry["found_visible"] >= 1 and entry["fp"] <= 1
        folder = out / "plants" / entry["plant"]
        assert (folder / "flowers.json").exists()
        # the cloud cut to the plant reaches less than halfway to its neighbour, 0.6 m off
        centre = json.loads((folder / "plant.json").read_text())["plant_center"]
        points = read_cloud(folder / "reconstruction" / "plant_cloud.ply").points
        assert np.hypot(*(points[:, :2] - centre[:2]).T).max() < 0.3
    assert report["summary"]["visible"] == sum(p["visible"] for p in report["plants"])
    times = report["timing_s"]
    assert times["bed"] >= times["filming"] >= times["computer_idle_while_filming"] >= 0
    assert "2 of 2 plants detected" in said
    assert "## The bed" in (out / "report.md").read_text()
    page = (out / "report.html").read_text()
    assert all(f"<h2>{name}</h2>" in page for name in ("a", "b"))


@pytest.mark.slow
def test_the_scan_of_each_plant_films_its_neighbour_and_scores_only_its_own_flowers(bed_run):
    _, out, _ = bed_run
    for name in ("a", "b"):
        truth = json.loads((out / "plants" / name / "scan" / "plant.json").read_text())
        assert truth["visibility"] == "scan" and any(f["visible"] for f in truth["flowers"])
    journal = json.loads((out / "bed.json").read_text())
    assert sorted(journal["order"]) == ["a", "b"] and journal["status"] == "complete"


@pytest.mark.slow
def test_running_the_bed_again_films_nothing_and_another_seed_is_refused(bed_run, capsys):
    bed, out, _ = bed_run
    scans = {name: (out / "plants" / name / "scan" / "scan.json").read_text()
             for name in ("a", "b")}
    assert main(["field", "--sim", "--bed", str(bed), "--out", str(out), *SMALL, "-q"]) == 0
    assert "2 of 2 plants detected" in capsys.readouterr().out
    assert scans == {name: (out / "plants" / name / "scan" / "scan.json").read_text()
                     for name in ("a", "b")}
    journal = json.loads((out / "bed.json").read_text())
    assert len(journal["sessions"]) == 2
    assert main(["field", "--sim", "--bed", str(bed), "--out", str(out), "--seed", "5",
                 *SMALL]) == 2
    err = capsys.readouterr().err.strip()
    assert "another bed, seed or settings" in err and err.count("\n") == 0
    assert json.loads((out / "bed.json").read_text()) == journal


@pytest.mark.slow
def test_a_dry_run_prints_the_beds_plan_in_row_order_and_writes_nothing(tmp_path, capsys):
    from importlib.resources import files

    example = files("flowerpose.assets") / "beds" / "example-4.toml"
    out = tmp_path / "bed4"
    assert main(["field", "--sim", "--bed", str(example), "--out", str(out), "--dry-run"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert [line.split()[1] for line in lines[1:5]] == ["row-1", "row-2", "row-3", "row-4"]
    assert lines[-1].startswith("4 plants") and not out.exists()


def test_a_bed_needs_the_simulator_and_a_good_bed_file(tmp_path, capsys):
    bed = tmp_path / "bed.toml"
    bed.write_text(BED)
    assert main(["field", "--bed", str(bed), "--out", str(tmp_path / "o")]) == 2
    assert "--sim" in capsys.readouterr().err
    bed.write_text('[[plant]]\nname = "a"\nx = 1.0\n')
    assert main(["field", "--sim", "--bed", str(bed), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert str(bed) in err and "'y' is missing" in err and err.count("\n") == 0
    assert not (tmp_path / "o").exists()
