"""`flowerpose field --sim`: a bed of generated plants filmed in one world, each
reconstructed while the next is filmed, scored against its truth, resumable."""

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from beds import BED, SMALL

from flowerpose.cli import main
from flowerpose.cloudio import read_cloud


@pytest.fixture(scope="module")
def bed_run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("bed")
    bed = folder / "bed.toml"
    bed.write_text(BED)
    out = folder / "run"
    # The bed's own stage cache (this fixture runs before the tests' cache is set).
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "FLOWERPOSE_CACHE": str(folder / "cache")}
    done = subprocess.run([sys.executable, "-m", "flowerpose", "field", "--sim", "--bed",
                           str(bed), "--out", str(out), *SMALL, "-q"], capture_output=True,
                          text=True, env=env)
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
    assert all(f'<h2 id="plant-{name}">{name}</h2>' in page for name in ("a", "b"))
    # the bed first: its map, and its table linking each plant to its section
    assert page.index('id="bed-map"') < page.index('id="plant-a"')
    assert all(f'<a href="#plant-{name}">{name}</a>' in page for name in ("a", "b"))


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


def _plane_normals(out, name) -> dict:
    """The plane normal of each truth flower found, by truth id."""
    report = json.loads((out / "report.json").read_text())
    entry = next(p for p in report["plants"] if p["plant"] == name)
    flowers = json.loads((out / "plants" / name / "flowers.json").read_text())["flowers"]
    by_id = {f["id"]: f["normals"]["plane"] for f in flowers}
    return {m["truth"]: np.asarray(by_id[m["detection"]]) for m in entry["matches"]
            if m.get("error_deg", {}).get("plane") is not None}


@pytest.mark.slow
def test_a_bed_killed_while_filming_its_second_plant_resumes_that_scan(bed_run, tmp_path):
    """SIGKILL in the middle of the second plant's scan, then the same command again: the
    first plant is not filmed again, the second's scan goes on from where it was cut, and
    the flowers are those of a run that was never stopped."""
    bed, uninterrupted, _ = bed_run
    out = tmp_path / "killed"
    command = [sys.executable, "-m", "flowerpose", "field", "--sim", "--bed", str(bed),
               "--out", str(out), *SMALL, "-q"]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    run = subprocess.Popen(command, stdout=subprocess.PIPE, text=True, env=env)
    second = next(line.split()[1].rstrip(":") for line in run.stdout
                  if line.startswith("[2/2]"))
    first = ({"a", "b"} - {second}).pop()
    scan = out / "plants" / second / "scan" / "scan.json"
    while not (scan.exists() and json.loads(scan.read_text())["completed"] >= 2):
        assert run.poll() is None, "the run ended before it could be killed"
        time.sleep(0.1)
    run.kill()
    run.wait()
    assert run.returncode == -signal.SIGKILL
    done = subprocess.run(command, capture_output=True, text=True, env=env)
    assert done.returncode == 0, done.stderr
    assert "2 of 2 plants detected" in done.stdout
    first_scan = json.loads((out / "plants" / first / "scan" / "scan.json").read_text())
    assert len(first_scan["sessions"]) == 1  # filmed once
    second_scan = json.loads(scan.read_text())
    cut, resumed = second_scan["sessions"]
    assert "ended without closing" in cut["error"] and resumed["started_waypoint"] >= 2
    assert second_scan["status"] == "complete"
    # The plant filmed before the kill: the same frames, so the same flowers to the bit.
    before, after = _plane_normals(uninterrupted, first), _plane_normals(out, first)
    assert before.keys() == after.keys() and all(
        np.array_equal(before[k], after[k]) for k in before)
    # The resumed plant's frames are other frames of the same stops (each frame has its own
    # sensor noise and moment, as a real camera's would), so a flower on the edge of
    # detection may come or go: the same flowers but at most one, normals within degrees.
    before, after = _plane_normals(uninterrupted, second), _plane_normals(out, second)
    common = before.keys() & after.keys()
    assert len(common) >= max(len(before), len(after)) - 1
    angles = [np.degrees(np.arccos(np.clip(before[k] @ after[k], -1, 1))) for k in common]
    assert max(angles) < 5.0, angles


@pytest.mark.slow
def test_on_ray_the_bed_gives_the_pools_flowers(bed_run, tmp_path, capsys):
    """A bed stopped once its second plant was filmed, resumed with that plant's
    reconstruction as a Ray task: nothing is filmed again, and the same frames give the
    same flowers to the bit."""
    pytest.importorskip("ray", reason="Ray is not installed (pip install 'flowerpose[ray]')")
    bed, pool, _ = bed_run
    out = _filmed_only(pool, tmp_path / "ray", names=("b",))
    scans = {n: (out / "plants" / n / "scan" / "scan.json").read_text() for n in ("a", "b")}
    assert main(["field", "--sim", "--bed", str(bed), "--out", str(out), "--ray", "--no-cache",
                 *SMALL, "-q"]) == 0
    assert "2 of 2 plants detected" in capsys.readouterr().out
    assert scans == {n: (out / "plants" / n / "scan" / "scan.json").read_text()
                     for n in ("a", "b")}
    for name in ("a", "b"):
        before, after = _plane_normals(pool, name), _plane_normals(out, name)
        assert before.keys() == after.keys() and len(before) >= 1
        assert all(np.array_equal(before[k], after[k]) for k in before)


def _filmed_only(done, out, names=("a", "b")):
    """A copy of the finished bed at `out` as if stopped once both plants were filmed and
    the plants not in `names` were detected."""
    import shutil

    out = shutil.copytree(done, out)
    journal = json.loads((out / "bed.json").read_text())
    for name in names:
        plant = journal["plants"][name]
        journal["plants"][name] = {"stage": "scanned", "seconds": plant["seconds"]}
        for made in ("frames", "reconstruction", "flowers.json"):
            path = out / "plants" / name / made
            shutil.rmtree(path) if path.is_dir() else path.unlink()
    (out / "bed.json").write_text(json.dumps(journal))
    return out


@pytest.mark.slow
def test_a_filmed_plants_work_comes_from_the_stage_cache_where_it_ran_before(bed_run,
                                                                            tmp_path,
                                                                            monkeypatch):
    """The same recordings again: each plant's frames, reconstruction and detection are
    taken from the bed's stage cache (0 seconds each) and give the first run's flowers."""
    bed, done, _ = bed_run
    out = _filmed_only(done, tmp_path / "again")
    monkeypatch.setenv("FLOWERPOSE_CACHE", str(bed.parent / "cache"))
    assert main(["field", "--sim", "--bed", str(bed), "--out", str(out), *SMALL, "-q"]) == 0
    journal = json.loads((out / "bed.json").read_text())
    for name in ("a", "b"):
        seconds = journal["plants"][name]["seconds"]
        assert seconds["frames"] == seconds["reconstruct"] == 0.0, seconds
        assert journal["plants"][name]["pipeline_s"]["total"] == 0.0
        assert (out / "plants" / name / "reconstruction" / "plant_cloud.ply").exists()
        before, after = _plane_normals(done, name), _plane_normals(out, name)
        assert before.keys() == after.keys() and len(before) >= 1
        assert all(np.array_equal(before[k], after[k]) for k in before)


@pytest.mark.slow
def test_with_pollinate_each_detected_plant_is_visited_and_scored(bed_run, tmp_path, capsys):
    """The finished bed again with --pollinate: nothing is filmed again; each plant's visits
    are planned from its flowers, flown and judged against its truth, beside the visits
    from its true poses."""
    import shutil

    bed, done, _ = bed_run
    out = shutil.copytree(done, tmp_path / "pollinated")
    scans = {n: (out / "plants" / n / "scan" / "scan.json").read_text() for n in ("a", "b")}
    assert main(["field", "--sim", "--bed", str(bed), "--out", str(out), *SMALL,
                 "--pollinate", "-q"]) == 0
    said = capsys.readouterr().out
    assert "pollination from estimated poses:" in said
    report = json.loads((out / "report.json").read_text())
    for entry in report["plants"]:
        judged = entry["pollination"]["flowers"]
        assert len(judged) == entry["gt"] and entry["pollination_ceiling"]["visits"] > 0
        assert (out / "plants" / entry["plant"] / "flight.json").exists()
    summary = report["summary"]["pollination"]
    assert summary["flowers"] == sum(e["gt"] for e in report["plants"])
    assert summary["successes"] == sum(e["pollination"]["successes"] for e in report["plants"])
    assert summary["success_rate_ci95"]["low"] <= summary["success_rate"]
    rows = {r["plant"]: r for r in report["bed"]["plants"]}
    assert all(rows[n]["pollinated"].endswith(f"of {len(e['pollination']['flowers'])}")
               for n, e in ((e["plant"], e) for e in report["plants"]))
    assert (out / "pollination.png").exists() and "| pollinated" in (out / "report.md").read_text()
    assert scans == {n: (out / "plants" / n / "scan" / "scan.json").read_text()
                     for n in ("a", "b")}


def _small_config():
    """The settings SMALL gives `field --sim` (the bed's cached work is keyed by them)."""
    from flowerpose.eval.jobs.config import eval_config

    sets = dict(item.split("=") for item in SMALL[3::2])
    return eval_config("easy", [{k: float(v) if "." in v else int(v) for k, v in sets.items()}])


@pytest.mark.slow
def test_the_physical_beds_run_finds_the_flowers_without_truth_and_visits_them(bed_run,
                                                                              tmp_path):
    """The simulated bed's recordings as a physical bed's (no truth beside them), processed
    by the physical bed's worker and pollinated by the serial backend on a virtual
    Farmduino: the same flowers as the simulated run (its reconstructions from the stage
    cache), every plant's visits flown, and a report with no score."""
    import contextlib
    import shutil

    from flowerpose.eval.capture import photogrammetry
    from flowerpose.eval.field import bed_loop
    from flowerpose.eval.field import physical_bed as field_bed
    from flowerpose.eval.field.simulated_bed import make_bed_plants, plan_sim_bed
    from flowerpose.eval.pool import Execution
    from flowerpose.hardware.backends.farmduino import FarmduinoBot
    from flowerpose.hardware.flights.bed_plan import read_bed

    virtual = pytest.importorskip("flowerpose.hardware.backends.virtual_farmduino")
    bed_file, done, _ = bed_run
    config = _small_config()
    # The plants' reach as the simulated run cut their clouds to, and its plan (a cylinder
    # of that reach is more than the simulated path keeps clear of).
    sim_bed = make_bed_plants(read_bed(bed_file), config, 0, done)
    bed = sim_bed.bed
    out = tmp_path / "field"
    for spot in bed.plants:
        shutil.copytree(done / "plants" / spot.name / "scan", out / "plants" / spot.name /
                        "scan", ignore=shutil.ignore_patterns(*photogrammetry.TRUTH_FILES))
    journal = bed_loop.open_journal(
        out, bed, bed_loop.fingerprint(bed, field_bed.settings_read(config)), {})
    for spot in bed.plants:  # filmed, as a bed stopped after its last scan would be
        journal.record["plants"][spot.name] = {"stage": "scanned", "seconds": {"scan": 1.0}}
    journal.save()

    @contextlib.contextmanager
    def serial_bot():
        with virtual.VirtualFarmduino(time_scale=100.0, params=virtual.FEEDBACK_PARAMETERS
                                      ) as device, FarmduinoBot(device.path) as bot:
            bot.home()
            yield bot

    said = []
    rig = field_bed.FieldRig(serial_bot, None, None, {"backend": "serial"})
    report = field_bed.run_field_bed(
        config, field_bed.FieldBedRun(bed, plan_sim_bed(sim_bed), rig), out,
        Execution(cache=bed_file.parent / "cache"),
        bed_loop.BedOptions(pollinate=True, say=said.append))
    assert not any("filming" in line for line in said), said
    rows = {row["plant"]: row for row in report["bed"]["plants"]}
    for spot in bed.plants:
        row = rows[spot.name]
        assert row["stage"] == "detected", row
        assert row["seconds"]["frames"] == row["seconds"]["reconstruct"] == 0.0
        found = _flowers(out, spot.name)
        assert found == _flowers(done, spot.name) and row["flowers"] == len(found) >= 1
        visits = row["pollination"]
        assert visits["status"] == "complete" and visits["flown"] == visits["planned"] > 0
        flight = json.loads((out / "plants" / spot.name / "pollination" /
                             "flight.json").read_text())
        assert len(flight["done"]) == visits["flown"] >= visits["done"]
        # This bot has no camera: every close look keeps the scan's pose, saying why (and
        # leaves a flower of uncertain sign alone).
        assert all(entry["look"]["status"] in ("kept", "left") and "camera" in
                   entry["look"]["reason"] for entry in flight["done"])
        assert visits["done"] == sum(entry["look"]["status"] == "kept"
                                     for entry in flight["done"])
        assert flight["source"]["backend"] == "serial"
    summary = report["summary"]
    assert summary["detected"] == 2 and summary["flowers"] == sum(r["flowers"] for r in
                                                                  rows.values())
    assert "visible" not in summary and "pollinated" in (out / "report.md").read_text()
    assert "no truth" in (out / "report.md").read_text() and (out / "report.html").is_file()


def _flowers(out, name) -> list:
    """Each flower's centre and plane normal in a bed plant's flowers.json."""
    flowers = json.loads((out / "plants" / name / "flowers.json").read_text())["flowers"]
    return [(f["center"], f["normals"]["plane"]) for f in flowers]


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


def test_the_bed_map_draws_each_plant_and_its_flowers_normals_from_above():
    from flowerpose.cloudio import Cloud
    from flowerpose.eval.reports.html_report import MAP_NORMAL_M, BedSpot, PlantView, bed_map

    flowers = [{"id": 0, "center": [1.0, 0.8, 0.2], "normals": {"plane": [1.0, 0.0, 0.0]}},
               {"id": 1, "center": [1.05, 0.7, 0.2], "normals": {"plane": None}}]
    empty = Cloud(np.zeros((0, 3)), np.zeros((0, 3), np.uint8))
    figure = bed_map([BedSpot("a", 1.0, 0.75, 0.12), BedSpot("b", 1.6, 0.75, 0.1)],
                     [PlantView("a", empty, flowers)])
    circles = [(s.x0, s.x1, s.y0, s.y1) for s in figure.layout.shapes]
    assert np.allclose(circles, [(0.88, 1.12, 0.63, 0.87), (1.5, 1.7, 0.65, 0.85)])
    names = next(t for t in figure.data if t.mode == "text")
    assert list(names.text) == ["a", "b"]
    normals = next(t for t in figure.data if t.mode == "lines")
    # a horizontal normal along +x is drawn MAP_NORMAL_M long; a flower without one is not
    assert list(normals.x) == [1.0, 1.0 + MAP_NORMAL_M, None]
    assert list(normals.y) == [0.8, 0.8, None]
