"""`flowerpose stress`: a real plant folder under seeded perturbations, reproducibly."""

import json

import pytest
from realplants import write_real_plant

from flowerpose.cli import main
from flowerpose.errors import InputError
from flowerpose.eval.jobs.config import EvalConfig
from flowerpose.eval.jobs.plant_set import PlantSet
from flowerpose.eval.pool import Execution
from flowerpose.eval.studies.stress import plan_from, run_stress


def _levels(**given):
    return {"thin": [], "exposure": [], "cast": [], "noise": [], **given}


@pytest.mark.slow
def test_stress_of_a_real_plant_is_seeded_and_reports_every_perturbation(tmp_path):
    folder = write_real_plant(tmp_path / "plant", "candidates")
    plan = plan_from(_levels(thin=[0.5], cast=[0.15], noise=[0.001]), channels="r",
                     drop_views=2, repeats=2, seed=3)
    first = run_stress(EvalConfig(), plan, PlantSet("real", folders=(folder,)), tmp_path / "a",
                       Execution(1))
    again = run_stress(EvalConfig(), plan, PlantSet("real", folders=(folder,)), tmp_path / "b",
                       Execution(1))
    labels = [row["label"] for row in first["rows"]]
    assert labels == ["thin 0.5", "cast r+0.15", "noise 0.001", "drop_view 0", "drop_view 1"]
    assert [r["repeats"] for r in first["rows"]] == [2, 1, 2, 1, 1]
    assert first["baseline"]["summary"]["found_visible"] == 4
    # The same seed gives the same plants, points and errors.
    strip = lambda report: [(r["plants"], r["points_per_flower"]) for r in report["rows"]]  # noqa: E731
    assert strip(first) == strip(again)
    # A dropped view is one candidates file left out, and the flowers only it saw with it:
    # the first file holds flowers 0-2, the second 2 and 3.
    assert [r["summary"]["found_visible"] for r in first["rows"][3:]] == [2, 3]
    for name in ("stress.json", "stress.md", "stress.png", "report.html"):
        assert (tmp_path / "a" / name).stat().st_size > 0
    assert "drop_view 1" in (tmp_path / "a" / "stress.md").read_text()


@pytest.mark.slow
def test_stress_command_line_and_its_refusals(tmp_path, capsys):
    folder = write_real_plant(tmp_path / "plant", "candidates")
    assert main(["stress", "--source", "real", str(folder), "--thin", "0.5", "--exposure",
                 "0.8", "--cast", "0.1", "--channels", "g", "--noise", "0.0005",
                 "--cut", "0.5", "--drop-views", "0", "--compare", "upstream",
                 "--out", str(tmp_path / "out")]) == 0
    report = json.loads((tmp_path / "out" / "stress.json").read_text())
    assert [r["label"] for r in report["rows"]] == ["thin 0.5", "exposure 0.8", "cast g+0.1",
                                                    "noise 0.0005", "cut 0.5"]
    # The published method on the very same clouds, paired at every level.
    for row in [report["baseline"], *report["rows"]]:
        paired = row["compare"]["upstream"]["paired"]
        assert paired["verdicts"][0].startswith("plane") and "summary" in row["compare"]["upstream"]
    printed = capsys.readouterr().out
    assert "| thin 0.5" in printed and "against upstream" in printed
    assert main(["stress", "--source", "real", str(folder), "--thin", "2",
                 "--out", str(tmp_path / "bad")]) == 2
    assert "thin" in capsys.readouterr().err
    with pytest.raises(InputError):
        run_stress(EvalConfig(), plan_from(_levels(), capture={"frames": ["50"]}),
                   PlantSet("oracle", plants=3), tmp_path / "c")
