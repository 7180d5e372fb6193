"""The speed benchmark measures the pipeline's stages and the simulator's steps and writes
bench.json; it never asserts a speed (this machine is shared)."""

from flowerpose.eval.bench import SIMULATOR_BUDGET_S, run_bench
from flowerpose.jsonio import read_json


def test_bench_times_every_pipeline_stage_and_simulator_step(tmp_path, capsys):
    report = run_bench([20000], repeat=1, seed=3, out=tmp_path)
    (result,) = report["results"]
    assert result["points"] == 20000 and result["flowers"] > 0
    assert set(result["median_s"]) >= {"total"} and result["median_s"]["total"] > 0
    assert set(report["simulator_s"]) == set(SIMULATOR_BUDGET_S)
    assert all(seconds > 0 for seconds in report["simulator_s"].values())
    assert read_json(tmp_path / "bench.json")["simulator_s"] == report["simulator_s"]
    assert "| simulator step | seconds | budget |" in capsys.readouterr().out
