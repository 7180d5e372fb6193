"""The speed benchmark measures the pipeline's stages and the simulator's steps and writes
bench.json; it never asserts a speed (this machine is shared)."""

import pytest

from flowerpose.eval.jobs.plant_set import PlantSet
from flowerpose.eval.pool import Execution
from flowerpose.eval.studies.bench import SIMULATOR_BUDGET_S, BenchPlan, run_bench
from flowerpose.jsonio import read_json
from flowerpose.pipeline.flowers import PipelineConfig

#: Realistic seed 3: 18 open flowers.
PLANT = PlantSet("oracle", "realistic", 1, 3)


@pytest.mark.slow
def test_bench_times_every_pipeline_stage_and_simulator_step(tmp_path, capsys):
    report = run_bench(PipelineConfig(), BenchPlan((20000,), repeat=1), PLANT, tmp_path)
    (result,) = report["results"]
    assert result["points"] == 20000 and result["flowers"] > 0
    assert set(result["median_s"]) >= {"total"} and result["median_s"]["total"] > 0
    assert set(report["simulator_s"]) == set(SIMULATOR_BUDGET_S)
    assert all(seconds > 0 for seconds in report["simulator_s"].values())
    assert read_json(tmp_path / "bench.json")["simulator_s"] == report["simulator_s"]
    shown = capsys.readouterr().out
    assert shown.count("simulator step") == 1 and "| plant " in shown


@pytest.mark.slow
def test_bench_and_plant_take_settings_by_their_dotted_keys(tmp_path, capsys):
    import json

    from flowerpose.cli import main

    assert main(["bench", "--points", "20000", "--repeat", "1", "--out", str(tmp_path),
                 "--set", "cluster.eps=0.008"]) == 0
    assert read_json(tmp_path / "bench.json")["config"]["cluster"]["eps"] == 0.008
    assert main(["plant", "--seed", "0", "--points", "5000", "--out", str(tmp_path / "big"),
                 "--set", "sim.plant.flower_diameter_m=[0.04,0.05]"]) == 0
    flowers = json.loads((tmp_path / "big" / "plant.json").read_text())["flowers"]
    assert min(2 * f["radius"] for f in flowers) >= 0.04  # the default is 20-35 mm
    capsys.readouterr()
    assert main(["plant", "--seed", "0", "--out", str(tmp_path / "no"), "--set",
                 "cluster.eps=0.1"]) == 2
    assert "plant reads sim.*, not this" in capsys.readouterr().err
    assert not (tmp_path / "no").exists()


@pytest.mark.slow
def test_bench_takes_its_cloud_from_the_stage_cache_when_made_before(tmp_path, monkeypatch):
    from flowerpose.sim import bundle

    plan = BenchPlan((20000,), repeat=1)
    first = run_bench(PipelineConfig(), plan, PLANT, None, Execution(cache=tmp_path / "cache"))
    made = []
    monkeypatch.setattr(bundle, "make_plant", lambda *a, **k: made.append(a))
    again = run_bench(PipelineConfig(), plan, PLANT, None, Execution(cache=tmp_path / "cache"))
    assert made == [] and len(list((tmp_path / "cache" / "plant").iterdir())) == 1
    assert again["results"][0]["flowers"] == first["results"][0]["flowers"]
