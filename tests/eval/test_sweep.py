"""Sweeps: best.json's typed setting and whole config, and sweep.png's figure."""

import csv
import json

import numpy as np
import pytest

from flowerpose.config import apply_overrides
from flowerpose.eval.jobs.config import eval_config
from flowerpose.eval.jobs.plant_set import PlantSet
from flowerpose.eval.pool import Execution
from flowerpose.eval.studies.sweep import METRICS, parse_grid, run_sweep, sweep_figure


@pytest.mark.slow
def test_a_tiny_sweep_names_the_best_setting_with_its_whole_typed_config(tmp_path):
    # The base asks 2000 points of a cluster (no flower has them); the grid tries it and 20.
    base = apply_overrides(eval_config("realistic"), {"cluster.min_points": "2000"})
    grid = parse_grid(["cluster.min_points=2000,20", "detect.backproject=mask"], base)
    best = run_sweep(base, grid, PlantSet("oracle", plants=2, seed=0), tmp_path, Execution(1))
    saved = json.loads((tmp_path / "best.json").read_text())
    assert saved["best"] == best
    assert best["setting"] == {"cluster.min_points": 20, "detect.backproject": "mask"}
    assert type(best["setting"]["cluster.min_points"]) is int  # as the config holds it
    # The winner's own config, not the base the grid started from.
    assert best["config"]["cluster"]["min_points"] == 20
    assert saved["grid"] == {"cluster.min_points": [2000, 20], "detect.backproject": ["mask"]}
    assert [s["setting"]["cluster.min_points"] for s in saved["settings"]] == [2000, 20]
    assert [p["plant"] for p in saved["settings"][1]["plants"]] == ["seed-0", "seed-1"]
    assert best["metrics"]["recall_visible"] == 1.0
    assert saved["settings"][0]["metrics"]["recall_visible"] == 0.0
    rows = list(csv.DictReader((tmp_path / "sweep.csv").open()))
    assert [r["cluster.min_points"] for r in rows] == ["2000", "20"]
    assert (tmp_path / "sweep.png").read_bytes()[:4] == b"\x89PNG"


@pytest.mark.slow
def test_a_sweep_that_changes_the_plants_compares_no_flower_with_the_defaults(tmp_path):
    # Another petal jitter makes other flowers under the same seed's names: pairing them
    # by name would compare one flower with another.
    base = eval_config("easy")
    grid = parse_grid(["sim.plant.petal_cup_jitter=0.0"], base)
    run_sweep(base, grid, PlantSet("oracle", plants=1, seed=0), tmp_path, Execution(1))
    against = json.loads((tmp_path / "best.json").read_text())["settings"][0]["vs_defaults"]
    assert against["paired"] is False and against["found"] is None
    assert "not compared flower by flower" in against["verdicts"][0]
    assert (tmp_path / "plants-0").is_dir() and (tmp_path / "plants-defaults").is_dir()


def _plant_metrics(rng, plants):
    return [{metric: float(v) for metric, v in zip(METRICS, rng.random(len(METRICS)),
                                                   strict=True)} for _ in range(plants)]


def test_the_sweep_figure_shows_each_settings_spread_as_a_category_and_marks_the_best():
    import matplotlib.collections
    import matplotlib.pyplot as plt

    rng = np.random.default_rng(0)
    settings = [{"detect.backproject": b, "cluster.eps": e}
                for b in ("box", "mask") for e in (0.008, 0.01)]
    per_plant = [_plant_metrics(rng, 3) for _ in settings]
    pooled = [{m: float(np.mean([p[m] for p in plants])) for m in METRICS}
              for plants in per_plant]
    pooled[0]["plane_mean_deg"] = None  # a metric nobody could measure is left out
    figure = sweep_figure(settings, pooled, per_plant, best=2)
    try:
        axes = figure.axes
        assert len(axes) == len(METRICS)
        labels = [t.get_text() for t in axes[-1].get_xticklabels()]
        assert labels[0] == "detect.backproject=box\ncluster.eps=0.008"  # full names
        assert labels[2].endswith("(best)") and "(best)" not in "".join(labels[:2] + labels[3:])
        assert axes[-1].get_xticklabels()[2].get_fontweight() == "bold"
        for ax in axes:
            # Categories: no line runs from one setting to another.
            for line in ax.get_lines():
                x = np.asarray(line.get_xdata(), float)
                assert np.ptp(x) < 1.0, ax.get_ylabel()
            points = [c for c in ax.collections
                      if isinstance(c, matplotlib.collections.PathCollection)]
            plants = sum(len(c.get_offsets()) for c in points if c.get_sizes()[0] == 12)
            assert plants == 3 * len(settings)  # every plant's value is there
            shaded = [p for p in ax.patches if p.get_facecolor()[:3] != (1.0, 1.0, 1.0)]
            assert any(abs(p.get_x() + p.get_width() / 2 - 2) < 1e-9 for p in shaded
                       if hasattr(p, "get_x"))
    finally:
        plt.close(figure)


@pytest.mark.slow
def test_a_sweep_over_real_plant_folders(tmp_path):
    from realplants import write_real_plant

    from flowerpose.cli import main

    folder = write_real_plant(tmp_path / "plant", "candidates")
    assert main(["sweep", "--source", "real", str(folder), "--grid",
                 "cluster.eps=0.008,0.01", "--out", str(tmp_path / "out")]) == 0
    best = json.loads((tmp_path / "out" / "best.json").read_text())
    assert [s["setting"]["cluster.eps"] for s in best["settings"]] == [0.008, 0.01]
    assert all(s["plants"][0]["plant"] == "plant" for s in best["settings"])
    assert best["source"] == "real" and "sim" not in best["best"]["config"]


def test_the_best_setting_never_adds_a_flipped_normal():
    from flowerpose.eval.studies.sweep import best_row

    row = {"recall_visible_low": 0.9, "precision_low": 0.9, "plane_mean_high_deg": 3.0,
           "new_flipped": 0}
    better_but_flips = {**row, "recall_visible_low": 0.99, "plane_mean_high_deg": 2.0,
                        "new_flipped": 1}
    assert best_row([better_but_flips, row]) is row
    assert best_row([better_but_flips, {**row, "recall_visible_low": 0.95}])[
        "recall_visible_low"] == 0.95


def test_a_pollination_sweep_ranks_by_the_share_pollinated_then_the_ceiling_then_collisions():
    from flowerpose.eval.studies.sweep import best_row

    row = {"recall_visible_low": 0.9, "precision_low": 0.9, "plane_mean_high_deg": 3.0,
           "new_flipped": 0, "pollinated": 0.8, "pollinated_low": 0.7,
           "pollinated_ceiling_low": 0.8, "collisions": 2}
    # The share pollinated from the estimated poses outranks a higher ceiling and the poses.
    higher_ceiling = {**row, "pollinated_low": 0.69, "pollinated_ceiling_low": 0.95,
                      "recall_visible_low": 0.99}
    assert best_row([higher_ceiling, row]) is row
    # Tied on it, the ceiling decides; tied on both, the fewer collisions.
    assert best_row([row, {**row, "pollinated_ceiling_low": 0.85}])[
        "pollinated_ceiling_low"] == 0.85
    assert best_row([row, {**row, "collisions": 1}])["collisions"] == 1
    # Never a setting that flips a normal the defaults did not, however many it pollinates.
    assert best_row([{**row, "pollinated_low": 0.99, "new_flipped": 1}, row]) is row


@pytest.mark.slow
def test_a_pollination_sweep_ranks_the_settings_by_the_flowers_pollinated(tmp_path):
    from flowerpose.eval.jobs.eval_run import EvalRun

    # No path search and no close look: the sweep's pollination is on trial here.
    base = apply_overrides(eval_config("easy"), {"pollinate.path_checks": "0",
                                                 "pollinate.look.views": "0",
                                                 "pollinate.tool.offset_down_m": "0.03"})
    # A shaft too short to reach past the head's own housing pollinates nothing.
    grid = parse_grid(["pollinate.tool.reach_m=0.05"], base)
    run = EvalRun(PlantSet("oracle", plants=1, seed=2), task="pollinate")
    best = run_sweep(base, grid, run, tmp_path, Execution(1))
    saved = json.loads((tmp_path / "best.json").read_text())
    assert saved["task"] == "pollinate" and "pollinated" in saved["rule"]
    short = saved["settings"][0]["metrics"]
    defaults = saved["defaults"]["metrics"]
    assert short["pollinated"] == 0.0 and defaults["pollinated"] > 0.0
    assert defaults["pollinated_ceiling_flowers"] >= defaults["pollinated_flowers"]
    assert (0.0 <= defaults["pollinated_low"] <= defaults["pollinated"]
            <= defaults["pollinated_high"])
    rows = list(csv.DictReader((tmp_path / "sweep.csv").open()))
    assert int(rows[0]["pollinated_lost"]) == defaults["pollinated_flowers"]
    assert int(rows[0]["pollinated_won"]) == 0
    # The poses are the same on both sides, so any difference shown is the pollination's.
    against = saved["settings"][0]["vs_defaults"]
    assert against["distinguishable"] == against["pollinated"]["shown"]
    assert best["setting"] == {"pollinate.tool.reach_m": 0.05}  # the only setting swept
    assert saved["defaults"]["setting"] == {"pollinate.tool.reach_m": 0.15}
    assert best["config"]["pollinate"]["tool"]["reach_m"] == 0.05
    # Each setting's flights beside its flowers; the plant's files shared.
    assert (tmp_path / "setting-0" / "seed-2" / "flight.json").exists()
    assert (tmp_path / "setting-defaults" / "seed-2" / "flight_ceiling.json").exists()
    assert not (tmp_path / "plants" / "seed-2" / "flight.json").exists()
    assert (tmp_path / "setting-defaults" / "pollination.png").exists()
    assert (tmp_path / "sweep.png").read_bytes()[:4] == b"\x89PNG"
