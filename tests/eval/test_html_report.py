"""report.html in a real headless browser (Chromium): the tables are there and the 3D
view renders the cloud with the estimated and true normals."""

import re
import shutil
import subprocess

import cv2
import numpy as np
import pytest

from flowerpose.cli import main

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
pytestmark = pytest.mark.skipif(CHROMIUM is None,
                                reason="Chromium is not installed (scripts/setup-system.sh)")
FLAGS = ["--headless=new", "--no-sandbox", "--enable-unsafe-swiftshader",
         "--use-angle=swiftshader", "--hide-scrollbars", "--virtual-time-budget=8000"]


def _browser(*args, timeout=120):
    return subprocess.run([CHROMIUM, *FLAGS, *args], capture_output=True, text=True,
                          timeout=timeout)


def _near(image_rgb, colour, tolerance=40):
    return int((np.abs(image_rgb.astype(int) - colour).max(axis=2) <= tolerance).sum())


@pytest.mark.slow
def test_an_eval_report_opens_from_disk_with_its_tables_and_3d_view(tmp_path, capsys):
    out = tmp_path / "eval"
    assert main(["eval", "-q", "--source", "oracle", "--plants", "1", "--seed", "1",
                 "--workers", "1", "--out", str(out)]) == 0
    capsys.readouterr()
    page = out / "report.html"
    text = page.read_text()
    assert "http://" not in text.split("<script", 1)[0] and "src=\"http" not in text
    dom = _browser("--dump-dom", page.as_uri()).stdout
    assert 'id="table-1"' in dom and ">Total<" in dom and 'id="flowers-seed-1"' in dom
    # The errors with their intervals and the accuracy curves.
    assert 'id="intervals"' in dom and 'id="accuracy"' in dom and "95 % CI" in dom
    assert dom.count("<canvas") >= 1  # plotly built the WebGL view
    shot = tmp_path / "shot.png"
    _browser("--window-size=1200,2600", f"--screenshot={shot}", page.as_uri())
    image = cv2.cvtColor(cv2.imread(str(shot)), cv2.COLOR_BGR2RGB)
    assert image.shape[:2] == (2600, 1200)
    # The 3D view drew the normals: red estimated and green true segments and ids.
    assert _near(image, (220, 30, 30)) > 200 and _near(image, (20, 160, 60)) > 200
    assert len(np.unique(image.reshape(-1, 3), axis=0)) > 1000  # not a blank page


def test_a_results_page_is_made_from_reports_with_what_made_them(tmp_path, capsys):
    from realplants import write_real_plant

    from flowerpose.cli import main

    folder = write_real_plant(tmp_path / "plant", "candidates")
    assert main(["eval", "--source", "real", str(folder), "--out", str(tmp_path / "r")]) == 0
    capsys.readouterr()
    assert main(["results", str(tmp_path / "r" / "report.json"), "--figure",
                 str(tmp_path / "accuracy.png")]) == 0
    page = capsys.readouterr().out
    assert "| real: plant [1]" in page and "4 of 4 [0.51, 1.00]" in page and "the paper" in page
    assert "](accuracy.png)" in page and (tmp_path / "accuracy.png").read_bytes()[:4] == b"\x89PNG"
    assert "flowerpose eval --source real" in page and "cores" in page
    assert main(["results", str(folder / "labels.json")]) == 2


@pytest.mark.slow
def test_a_results_page_has_a_section_per_stress_and_bench_run(tmp_path, capsys):
    from realplants import write_real_plant

    from flowerpose.cli import main
    from flowerpose.eval.reports.report import run_record
    from flowerpose.jsonio import write_json

    folder = write_real_plant(tmp_path / "plant", "candidates")
    assert main(["stress", "--source", "real", str(folder), "--thin", "0.5", "--exposure",
                 "0.8", "--cast", "0.1", "--noise", "0.0005", "--drop-views", "0",
                 "--out", str(tmp_path / "s")]) == 0
    bench = {"run": run_record(), "repeat": 3, "seed": 3, "cpu_count": 2,
             "results": [{"points": 125000, "flowers": 18,
                          "median_s": {"grid": 0.125, "total": 0.5}}],
             "simulator_s": {"plant": 1.5, "visibility": 4.0},
             "simulator_budget_s": {"plant": 2.0, "visibility": 3.0}}
    write_json(tmp_path / "bench.json", bench)
    capsys.readouterr()
    assert main(["results", str(tmp_path / "s" / "stress.json"), str(tmp_path / "bench.json"),
                 "--no-paper"]) == 0
    page = capsys.readouterr().out
    assert "## Accuracy" not in page and "the paper" not in page
    assert "## Robustness [1]" in page and "| thin 0.5 " in page
    assert "[1] `flowerpose stress --source real" in page
    assert "## Speed [2]" in page and "| 125,000 " in page and "0.125" in page
    assert re.search(r"\| visibility +\| 4\.000 +\| 3 \(over\)", page)


@pytest.mark.slow
def test_a_real_report_marks_its_false_positives_and_extra_detections(tmp_path, capsys):
    from realplants import CENTRES, SCALE, write_real_plant

    # Three flowers labelled, the fourth listed as unlabelled: its detection is extra.
    folder = write_real_plant(tmp_path / "plant", "candidates", labelled=3,
                              source={"unlabelled": [list(CENTRES[3] * SCALE)]})
    out = tmp_path / "eval"
    assert main(["eval", "-q", "--source", "real", str(folder), "--compare", "upstream",
                 "--out", str(out)]) == 0
    capsys.readouterr()
    dom = _browser("--dump-dom", (out / "report.html").as_uri()).stdout
    assert ">extra<" in dom and "extra (1)" in dom and ">scored<" in dom
    assert 'id="compare"' in dom and "no difference shown" in dom
