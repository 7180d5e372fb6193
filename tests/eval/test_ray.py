"""Eval and sweep jobs on Ray (`--ray`): the same report as the process pool, a failing job
retried once and then named by plant and stage with the other jobs' work kept, and one
line without Ray."""

import csv
import sys
from pathlib import Path

import pytest

from flowerpose.cli import main
from flowerpose.errors import JobsFailed
from flowerpose.eval.jobs.config import eval_config
from flowerpose.eval.jobs.plant_set import PlantSet
from flowerpose.eval.pool import TASK_RETRIES, Execution, run_jobs
from flowerpose.eval.studies.sweep import parse_grid, run_sweep

ray = pytest.importorskip("ray", reason="Ray is not installed (pip install 'flowerpose[ray]')")


def _rows(folder: Path) -> list[dict]:
    """sweep.csv's rows without their timings (which differ run to run)."""
    with open(folder / "sweep.csv", newline="") as handle:
        return [{k: v for k, v in row.items() if "seconds" not in k}
                for row in csv.DictReader(handle)]


@pytest.mark.slow
def test_a_sweep_on_ray_gives_the_pools_report(tmp_path):
    config = eval_config("realistic")
    grid = parse_grid(["cluster.min_points=10,20"], config)
    run_sweep(config, grid, PlantSet("oracle", plants=1, seed=0), tmp_path / "pool",
              Execution(2))
    from flowerpose.eval.pool import on_ray

    with on_ray(None) as session:
        run_sweep(config, grid, PlantSet("oracle", plants=1, seed=0), tmp_path / "ray")
    assert _rows(tmp_path / "ray") == _rows(tmp_path / "pool")
    assert len(_rows(tmp_path / "pool")) == 2
    # the plant, then the evaluations of the grid's two settings and of the defaults
    assert sum(session.tasks_by_node.values()) == 1 + 3 * 1


@pytest.mark.slow
def test_a_failing_job_is_tried_again_then_named_and_the_others_are_kept(tmp_path):
    from flowerpose.eval.pool import on_ray

    def job(name: str, folder: Path) -> str:
        with open(folder / f"{name}.tries", "a") as tries:
            tries.write("try\n")
        if name == "seed-1":
            raise RuntimeError("the reconstruction diverged")
        (folder / f"{name}.done").write_text("ok")
        return name

    names = ["seed-0", "seed-1", "seed-2"]
    with on_ray(None), pytest.raises(JobsFailed) as failed:
        run_jobs(job, [(n, tmp_path) for n in names], None, stage="scan capture",
                 labels=names)
    assert failed.value.failures == [("seed-1", "RuntimeError: the reconstruction diverged")]
    assert "1 scan capture job(s) failed" in str(failed.value)
    assert (tmp_path / "seed-1.tries").read_text().count("try") == 1 + TASK_RETRIES
    assert (tmp_path / "seed-0.done").exists() and (tmp_path / "seed-2.done").exists()


def test_ray_without_the_extra_is_one_line(monkeypatch, capsys, tmp_path):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` now fails as if absent
    assert main(["sweep", "--source", "oracle", "--plants", "1", "--grid",
                 "cluster.eps=0.01", "--out", str(tmp_path / "s"), "--ray"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "pip install 'flowerpose[ray]'" in err


def test_a_ray_address_where_nothing_listens_is_one_line_at_once(capsys, tmp_path):
    assert main(["sweep", "--source", "oracle", "--plants", "1", "--grid",
                 "cluster.eps=0.01", "--out", str(tmp_path / "s"), "--ray", "127.0.0.1:1"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "nothing answers at 127.0.0.1:1" in err


@pytest.mark.parametrize("method, gpus_in_cluster, asked", [
    ("patch_match", 1, 1), ("auto", 1, 1), ("auto", 0, 0), ("sgbm", 1, 0)])
def test_a_capture_asks_for_a_gpu_where_patch_match_will_run(monkeypatch, method,
                                                             gpus_in_cluster, asked):
    from flowerpose.eval.capture.scan_source import CAPTURE_GPU
    from flowerpose.eval.pool import _task_gpus

    monkeypatch.setattr(ray, "cluster_resources",
                        lambda: {"CPU": 2.0, **({"GPU": 1.0} if gpus_in_cluster else {})})
    assert _task_gpus(CAPTURE_GPU[method], "scan capture") == asked


def test_patch_match_on_a_cluster_without_a_gpu_is_one_line(monkeypatch):
    from flowerpose.errors import InputError
    from flowerpose.eval.pool import _task_gpus

    monkeypatch.setattr(ray, "cluster_resources", lambda: {"CPU": 2.0})
    with pytest.raises(InputError, match="needs a GPU .* has none"):
        _task_gpus("needed", "scan capture")
