"""The local pool's failed jobs: the others finish and keep their results, the failures
are named by plant in one error, and bad input stays bad input."""

import shutil

import pytest

from flowerpose.errors import InputError, JobsFailed
from flowerpose.eval.pool import run_jobs
from flowerpose.jsonio import read_json


@pytest.mark.parametrize("workers", [1, 2])
def test_a_failing_job_is_named_after_the_others_have_finished(tmp_path, workers):
    for name in ("seed-0", "seed-2"):
        (tmp_path / name).write_text(name)
    names = ["seed-0", "seed-1", "seed-2"]  # seed-1's file is missing: its copy fails
    with pytest.raises(JobsFailed) as failed:
        run_jobs(shutil.copyfile, [(tmp_path / n, tmp_path / f"{n}.copy") for n in names],
                 workers, stage="scan capture", labels=names)
    assert [label for label, _ in failed.value.failures] == ["seed-1"]
    assert failed.value.failures[0][1].startswith("FileNotFoundError")
    assert "1 scan capture job(s) failed: seed-1" in str(failed.value)
    assert (tmp_path / "seed-0.copy").read_text() == "seed-0"
    assert (tmp_path / "seed-2.copy").read_text() == "seed-2"


def test_jobs_that_fail_on_bad_input_alone_raise_that_input_error(tmp_path):
    (tmp_path / "good.json").write_text('{"a": 1}')
    (tmp_path / "bad.json").write_text("[1]")
    with pytest.raises(InputError, match="expected a JSON object"):
        run_jobs(read_json, [(tmp_path / "bad.json",), (tmp_path / "good.json",)], 2)
