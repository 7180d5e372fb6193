"""Output folders: a command deletes only what it wrote, refuses other folders unless told,
and a rerun that fails or is killed leaves the earlier finished output."""

import json
from pathlib import Path

import numpy as np
import pytest

from flowerpose.cli import main
from flowerpose.cloudio import Cloud, write_cloud
from flowerpose.errors import InputError
from flowerpose.outputs import MARKER, OutputFolder, check_output


def test_a_stage_replaces_its_own_output_and_refuses_anything_else(tmp_path):
    out = tmp_path / "out"
    first = OutputFolder(out, "detect")
    (out / "crops").mkdir()
    for name in ("crops/flower_00.ply", "crops/flower_01.ply", "flowers.json"):
        (out / name).write_text("old")
        first.record(out / name)
    first.finish()
    second = OutputFolder(out, "detect")  # the earlier output is stale: removed first
    assert not any((out / name).exists() for name in (
        "crops/flower_00.ply", "crops/flower_01.ply", "flowers.json"))
    second.finish()
    with pytest.raises(InputError, match="holds the output of flowerpose detect"):
        check_output(out, "frames")
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("keep me")
    with pytest.raises(InputError, match=r"did not write \(notes.txt\).*--overwrite"):
        OutputFolder(foreign, "detect")
    OutputFolder(foreign, "detect", overwrite=True).finish()
    assert (foreign / "notes.txt").read_text() == "keep me"


def test_detect_removes_its_earlier_crops_and_keeps_foreign_files(tmp_path, capsys):
    rng = np.random.default_rng(0)
    cloud = tmp_path / "cloud.ply"
    write_cloud(cloud, Cloud(rng.uniform(-0.1, 0.1, (2000, 3)) + [1.5, 0.75, 0.2],
                             np.tile(np.array([60, 120, 40], np.uint8), (2000, 1))))
    out = tmp_path / "detect"
    assert main(["detect", str(cloud), "--out", str(out)]) == 0
    stale = out / "crops" / "flower_07.ply"  # as an earlier, bigger detection left it
    stale.parent.mkdir(exist_ok=True)
    stale.write_text("stale")
    marker = json.loads((out / MARKER).read_text())
    marker["files"].append("crops/flower_07.ply")
    (out / MARKER).write_text(json.dumps(marker))
    assert main(["detect", str(cloud), "--out", str(out)]) == 0
    assert not stale.exists() and json.loads((out / "flowers.json").read_text())["flowers"] == []
    scan = tmp_path / "scan"
    scan.mkdir()
    (scan / "scan.json").write_text("{}")
    assert main(["detect", str(cloud), "--out", str(scan)]) == 2
    assert "did not write (scan.json)" in capsys.readouterr().err
    assert (scan / "scan.json").read_text() == "{}"


def test_frames_refuses_another_scan_folder(tmp_path, capsys):
    other = tmp_path / "other_scan"
    (other / "frames").mkdir(parents=True)
    (other / "frames" / "frame_000000.jpg").write_bytes(b"a recorded frame")
    (other / "camera.json").write_text("{}")
    scan = tmp_path / "scan"
    scan.mkdir()
    assert main(["frames", str(scan), "--count", "2", "--out", str(other)]) == 2
    assert (other / "frames" / "frame_000000.jpg").read_bytes() == b"a recorded frame"
    assert (other / "camera.json").read_text() == "{}"


def test_a_failed_reconstruction_keeps_the_earlier_one(tmp_path, monkeypatch):
    from flowerpose.pipeline import reconstruct as stage

    frames = tmp_path / "frames"
    frames.mkdir()
    (frames / "camera.json").write_text("{}")
    out = tmp_path / "recon"
    earlier = OutputFolder(out, "reconstruct")
    (out / "cloud.ply").write_text("the earlier cloud")
    earlier.record(out / "cloud.ply")
    earlier.finish()

    def fails(*args, **kwargs):
        raise InputError(frames, "only 3 of 200 images registered")

    monkeypatch.setattr(stage, "_reconstruct", fails)
    with pytest.raises(InputError, match="registered"):
        stage.reconstruct(frames, out)
    assert (out / "cloud.ply").read_text() == "the earlier cloud"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frames", "recon"]


def test_overwrite_never_claims_or_writes_over_what_the_stage_did_not_write(tmp_path):
    # A scan's own frames/ and camera.json in the folder a frame selection is told to use
    # (the audit's case: claimed once with --overwrite, they were deleted by the next run).
    folder = tmp_path / "scan_copy"
    (folder / "frames").mkdir(parents=True)
    (folder / "frames" / "frame_000000.jpg").write_bytes(b"recorded")
    (folder / "notes.txt").write_text("keep me")
    with pytest.raises(InputError, match="frames: was not written by flowerpose frames"):
        OutputFolder(folder, "frames", overwrite=True, writes=("frames", "camera.json"))
    output = OutputFolder(folder, "detect", overwrite=True, writes=("flowers.json",))
    with pytest.raises(InputError, match="not claimed"):
        output.record(folder / "frames")
    output.record(folder / "flowers.json")
    output.finish()
    OutputFolder(folder, "detect", overwrite=True, writes=("flowers.json",)).finish()
    assert (folder / "frames" / "frame_000000.jpg").read_bytes() == b"recorded"
    assert (folder / "notes.txt").read_text() == "keep me"


def test_a_reconstruction_over_a_folder_of_other_files_deletes_none(tmp_path):
    from flowerpose.pipeline.reconstruct import reconstruct

    frames = tmp_path / "frames"
    frames.mkdir()
    (frames / "camera.json").write_text("{}")
    plant = tmp_path / "plant"
    (plant / "sparse").mkdir(parents=True)
    (plant / "sparse" / "my_model.txt").write_text("mine")
    (plant / "cloud.ply").write_text("the oracle cloud")
    with pytest.raises(InputError, match="was not written by flowerpose reconstruct"):
        reconstruct(frames, plant, overwrite=True)
    assert (plant / "sparse" / "my_model.txt").read_text() == "mine"
    assert (plant / "cloud.ply").read_text() == "the oracle cloud"


def test_overwrite_never_writes_a_report_or_plant_over_a_file_it_did_not_write(plant0,
                                                                                 tmp_path,
                                                                                 capsys):
    """The commands without their own staging (score, plant, eval, sweep, fidelity) name
    what they write, so --overwrite refuses a same-named file that is not theirs."""
    _, plant_dir = plant0
    flowers = tmp_path / "flowers.json"
    flowers.write_text(json.dumps({"flowers": []}))
    score = ["score", str(flowers), str(plant_dir / "plant.json")]
    out = tmp_path / "mine"
    out.mkdir()
    (out / "report.md").write_text("my notes")
    assert main([*score, "--out", str(out), "--overwrite"]) == 2
    assert (out / "report.md").read_text() == "my notes" and not (out / "report.json").exists()
    assert main([*score, "--out", str(tmp_path / "own")]) == 0
    assert main([*score, "--out", str(tmp_path / "own")]) == 0  # its own: written again
    assert main(["plant", "--seed", "0", "--out", str(plant_dir), "--overwrite"]) == 2
    capsys.readouterr()
    assert main(["eval", "--source", "real", str(tmp_path / "nowhere"), "--out", str(out),
                 "--overwrite"]) == 2
    assert "report.md: was not written by flowerpose eval" in capsys.readouterr().err
    assert (out / "report.md").read_text() == "my notes"


def test_a_folder_in_use_is_refused_and_a_refused_command_leaves_nothing(tmp_path, capsys):
    from flowerpose.cli import main
    from flowerpose.outputs import OutputFolder

    busy = OutputFolder(tmp_path / "busy", "eval", writes=("report.json",))
    assert main(["eval", "--source", "oracle", "--plants", "1", "--out",
                 str(tmp_path / "busy")]) == 2
    assert "in use by another running flowerpose command" in capsys.readouterr().err
    busy.finish()
    # A real plant folder that is no plant: refused inside the run, no folder left.
    (tmp_path / "empty").mkdir()
    assert main(["eval", "--source", "real", str(tmp_path / "empty"), "--out",
                 str(tmp_path / "never")]) == 2
    assert not (tmp_path / "never").exists()


def test_an_unwritable_junit_path_is_refused_before_the_run(tmp_path, capsys):
    from flowerpose.cli import main

    assert main(["eval", "--source", "oracle", "--plants", "1", "--require", "recall>=0.5",
                 "--junit", str(tmp_path / "missing" / "gates.xml"),
                 "--out", str(tmp_path / "out")]) == 2
    assert "does not exist" in capsys.readouterr().err and not (tmp_path / "out").exists()


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux's /proc")
def test_a_junit_folder_that_refuses_files_is_found_before_the_run(tmp_path, capsys):
    # /proc passes a permission check as root, yet takes no new file.
    from flowerpose.cli import main

    assert main(["eval", "--source", "oracle", "--plants", "1", "--require", "recall>=0.5",
                 "--junit", "/proc/gates.xml", "--out", str(tmp_path / "out")]) == 2
    assert "cannot be written here" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_an_eval_rerun_into_its_folder_replaces_all_of_its_earlier_output(tmp_path, capsys):
    from flowerpose.cli import main

    out = tmp_path / "run"
    assert main(["eval", "-q", "--source", "oracle", "--plants", "2", "--out", str(out),
                 "--cache", str(tmp_path / "cache")]) == 0
    assert sorted(p.name for p in (out / "plants").iterdir()) == ["seed-0", "seed-1"]
    (out / "notes.txt").write_text("mine")  # the user's own file stays
    assert main(["eval", "-q", "--source", "oracle", "--plants", "1", "--out", str(out),
                 "--cache", str(tmp_path / "cache"), "--overwrite"]) == 0
    capsys.readouterr()
    assert sorted(p.name for p in (out / "plants").iterdir()) == ["seed-0"]
    assert (out / "notes.txt").read_text() == "mine"


def _report(out: Path, text: str) -> OutputFolder:
    run = OutputFolder(out, "eval")
    (out / "report.json").write_text(text)
    run.record(out / "report.json")
    return run


def test_an_unfinished_rerun_never_costs_the_finished_output(tmp_path):
    out = tmp_path / "out"
    _report(out, "finished").finish()
    killed = _report(out, "half")  # killed before it finished: neither finish nor abandon
    killed.release()
    assert (out / ".flowerpose-previous" / "files" / "report.json").read_text() == "finished"
    failed = OutputFolder(out, "eval")  # the next run puts the finished one back first
    (out / "report.json").write_text("broken")
    failed.record(out / "report.json")
    failed.abandon()  # a run that fails puts it back too
    assert (out / "report.json").read_text() == "finished"
    assert not (out / ".flowerpose-previous").exists()
    assert json.loads((out / MARKER).read_text())["complete"] is True
    _report(out, "new").finish()
    assert (out / "report.json").read_text() == "new"
    assert not (out / ".flowerpose-previous").exists()


def test_an_eval_rerun_that_is_interrupted_keeps_the_finished_report(tmp_path, monkeypatch):
    import sys

    sys.path.insert(0, str(Path(__file__).parent / "eval"))
    from realplants import write_real_plant

    from flowerpose.eval.studies import eval_recipe as harness

    folder = write_real_plant(tmp_path / "plant", "candidates")
    out = tmp_path / "out"
    assert main(["eval", "--source", "real", str(folder), "--out", str(out), "-q"]) == 0
    finished = (out / "report.json").read_bytes()

    def interrupted(*args, **kwargs):
        (out / "report.json").write_text("{}")  # the new run got this far
        raise KeyboardInterrupt

    monkeypatch.setattr(harness, "run_eval", interrupted)
    assert main(["eval", "--source", "real", str(folder), "--out", str(out), "-q"]) == 130
    assert (out / "report.json").read_bytes() == finished
