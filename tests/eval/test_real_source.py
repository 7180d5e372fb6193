"""Real labelled plant folders: the reader, the SageMaker labels' convention and scale, each
stage the folder allows, unlabelled flowers, and bad folders as one line and exit 2."""

import json
from dataclasses import replace

import numpy as np
import pytest
from realplants import CENTRES, NORMALS, SCALE, cuboids, flower, write_real_plant

from flowerpose.cli import main
from flowerpose.cloudio import Cloud
from flowerpose.errors import InputError
from flowerpose.eval.jobs.config import EvalConfig
from flowerpose.eval.jobs.eval_run import EvalRun
from flowerpose.eval.jobs.plant_set import PlantSet
from flowerpose.eval.pool import Execution
from flowerpose.eval.scoring.real_source import read_real_plant, real_truth
from flowerpose.eval.scoring.truth import read_sagemaker_truth
from flowerpose.eval.studies.eval_recipe import run_eval
from flowerpose.pipeline.flowers import PipelineConfig, pose_crops
from flowerpose.pipeline.segment import cluster_flowers


def test_labels_come_back_in_the_cloud_units_with_the_authors_euler_convention(tmp_path):
    folder = write_real_plant(tmp_path / "plant", "crops")
    plant = read_real_plant(folder)
    assert (plant.stage, plant.label_format, plant.truth_scale) == ("crops", "sagemaker", 25.0)
    truth = real_truth(plant)
    np.testing.assert_allclose([t.center for t in truth], CENTRES, atol=1e-12)
    np.testing.assert_allclose([t.normal for t in truth], NORMALS, atol=1e-9)
    assert all(t.visible for t in truth)
    # The cuboids use all three angles, so the other convention reads other normals.
    other = read_sagemaker_truth(folder / "labels.json", SCALE, convention="sagemaker")
    assert max(np.degrees(np.arccos(np.clip(t.normal @ n, -1, 1)))
               for t, n in zip(other, NORMALS, strict=True)) > 20


@pytest.mark.parametrize("stage", ["crops", "candidates", "cloud"])
def test_each_stage_finds_every_labelled_flower_and_its_normal(tmp_path, stage):
    folder = write_real_plant(tmp_path / stage, stage)
    report = run_eval(EvalConfig(), EvalRun(PlantSet("real", folders=(folder,))), tmp_path / "out",
                      Execution(1))
    plant = report["plants"][0]
    assert (plant["stage"], plant["gt"], plant["found"], plant["fp"]) == (stage, 4, 4, 0)
    assert max(plant["error_deg"]["plane"]) < 2.0
    assert sorted(m["truth"] for m in plant["matches"]) == [f"Flower:{k}" for k in range(1, 5)]
    assert (tmp_path / "out" / stage / "flowers.json").exists()
    config = json.loads((tmp_path / "out" / "report.json").read_text())["config"]
    assert config["source"] == "real"
    # The settings of the stages that ran from where the folder's data starts, no others.
    assert set(config) == {"source", "folders", "score", *{
        "crops": ("colour", "cluster", "pose"),
        "candidates": ("colour", "outliers", "cluster", "pose"),
        "cloud": ("colour", "ground", "grid", "detect", "outliers", "cluster", "pose")}[stage]}


@pytest.mark.slow
def test_a_flower_without_a_label_counts_as_extra_when_the_folder_lists_it(tmp_path):
    unlisted = write_real_plant(tmp_path / "unlisted", "candidates", labelled=3)
    listed = write_real_plant(tmp_path / "listed", "candidates", labelled=3,
                              source={"unlabelled": [list(CENTRES[3] * SCALE)]})
    report = run_eval(EvalConfig(), EvalRun(PlantSet("real", folders=(unlisted, listed))),
                      tmp_path / "out", Execution(1))
    first, second = report["plants"]
    assert (first["found"], first["extra"], first["fp"]) == (3, 0, 1)
    assert (second["found"], second["visible"], second["extra"], second["fp"]) == (4, 3, 1, 0)


def test_a_labelled_flower_the_cloud_does_not_hold_is_not_visible(tmp_path):
    folder = write_real_plant(tmp_path / "plant", "candidates")
    labels = json.loads((folder / "labels.json").read_text())
    # A fifth label 40 cm from every point: the reconstruction lost that flower.
    lost = cuboids(CENTRES[:1] + [0.4, 0.0, 0.0], NORMALS[:1])["answers"][0]["answerContent"]
    cuboid = {**lost["boundingCuboids"]["boundingCuboids"][0], "objectName": "Flower:lost"}
    labels["answers"][0]["answerContent"]["boundingCuboids"]["boundingCuboids"].append(cuboid)
    (folder / "labels.json").write_text(json.dumps(labels))
    truth = real_truth(read_real_plant(folder))
    assert [t.visible for t in truth] == [True, True, True, True, False]
    report = run_eval(EvalConfig(), EvalRun(PlantSet("real", folders=(folder,))), tmp_path / "out",
                      Execution(1))
    plant = report["plants"][0]
    assert (plant["gt"], plant["visible"], plant["found_visible"]) == (5, 4, 4)
    assert report["summary"]["recall_visible"] == 1.0
    assert report["summary"]["accuracy"]["plane"]["n"] == 4


def test_the_upstream_profile_runs_beside_the_default(tmp_path):
    folder = write_real_plant(tmp_path / "plant", "crops")
    run = EvalRun(PlantSet("real", folders=(folder,)), compare={"upstream": EvalConfig()})
    report = run_eval(EvalConfig(), run, tmp_path / "out", Execution(1))
    assert report["compare"]["upstream"]["summary"]["found"] == 4
    assert set(report["compare"]["upstream"]["config"]) == {"colour", "cluster", "pose"}
    assert (tmp_path / "out" / "upstream" / "plant" / "flowers.json").exists()


def test_a_scale_that_puts_no_label_near_any_point_is_refused(tmp_path):
    folder = write_real_plant(tmp_path / "plant", "candidates")
    with pytest.raises(InputError, match="is the scale right"):
        run_eval(EvalConfig(), EvalRun(PlantSet("real", folders=(folder,), truth_scale=1.0)),
                 tmp_path / "out", Execution(1))


def test_a_wrong_truth_scale_is_said_as_the_flag_that_set_it(tmp_path, capsys):
    folder = write_real_plant(tmp_path / "plant", "candidates")
    assert main(["eval", "--source", "real", str(folder), "--truth-scale", "1", "--out",
                 str(tmp_path / "out")]) == 2
    # The scale is judged on the plant's points, once the run has started: its start
    # line, then the error, alone.
    err = capsys.readouterr().err.strip().splitlines()
    assert [line.startswith("flowerpose: error:") for line in err] == [False, True]
    assert "is the scale right? (--truth-scale, or truth_scale in source.json)" in err[1]

def _bad(tmp_path, make):
    folder = tmp_path / "bad"
    make(folder)
    return folder


@pytest.mark.parametrize("make, message", [
    (lambda f: None, "no such folder"),
    (lambda f: f.mkdir(), "no labels.json"),
    (lambda f: (f.mkdir(), (f / "labels.json").write_text('{"answers": []}')),
     "SageMaker Ground Truth cuboid labels"),
    (lambda f: (f.mkdir(), (f / "labels.json").write_text(json.dumps(cuboids(CENTRES, NORMALS)))),
     "no cloud.ply, candidates"),
    (lambda f: (write_real_plant(f, "crops"), (f / "source.json").write_text('{"scale": 2}')),
     "unknown key 'scale'"),
    (lambda f: (write_real_plant(f, "crops"),
                (f / "source.json").write_text('{"truth_scale": -1}')), "positive number"),
    (lambda f: (write_real_plant(f, "crops"), (f / "source.json").write_text('{"units": "ft"}')),
     '"units" must be'),
])
def test_bad_folders_are_one_line_and_exit_2(tmp_path, capsys, make, message):
    folder = _bad(tmp_path, make)
    assert main(["eval", "--source", "real", str(folder), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("flowerpose: error:") and message in err[0]


def test_folders_need_the_real_source_and_the_real_source_needs_folders(tmp_path, capsys):
    assert main(["eval", "--source", "oracle", str(tmp_path)]) == 2
    assert main(["eval", "--source", "real", "--out", str(tmp_path / "o")]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert "plant folders are for --source real" in lines[0]
    assert "needs at least one labelled plant folder" in lines[1]


def test_detect_takes_a_detectors_candidates_and_counts_a_point_once(tmp_path, capsys):
    from flowerpose.cloudio import Cloud, read_cloud, write_cloud

    folder = write_real_plant(tmp_path / "plant", "candidates")
    views = [read_cloud(p) for p in sorted((folder / "candidates").glob("*.ply"))]
    merged = tmp_path / "merged.ply"
    write_cloud(merged, Cloud(np.vstack([v.points for v in views]),
                              np.vstack([v.colors for v in views])))
    assert main(["detect", str(merged), "--candidates", "--out", str(tmp_path / "d")]) == 0
    flowers = json.loads((tmp_path / "d" / "flowers.json").read_text())["flowers"]
    assert len(flowers) == 4 and not (tmp_path / "d" / "views").exists()
    assert "4 flowers (4 with a normal)" in capsys.readouterr().out


def _disc_flowers(scale: float) -> Cloud:
    rng = np.random.default_rng(0)
    flowers = [flower(c, n, rng) for c, n in zip(CENTRES, NORMALS, strict=True)]
    return Cloud(np.vstack([f.points for f in flowers]) * scale,
                 np.vstack([f.colors for f in flowers]))


def test_limits_are_sized_to_flowers_outside_the_size_band():
    """A cloud whose flowers measure outside `cluster.size_band_m` is grouped as the cloud
    shrunk to the band would be at the limits as stated; inside the band nothing changes."""
    config = PipelineConfig()
    inside = _disc_flowers(1.0)
    kept = cluster_flowers(inside, np.arange(len(inside)), config.outliers, config.cluster,
                           config.colour)
    assert kept.scale == 1.0 and kept.config == config.cluster and len(kept.clusters) == 4
    big = _disc_flowers(3.0)
    grouping = cluster_flowers(big, np.arange(len(big)), config.outliers, config.cluster,
                               config.colour)
    low, high = config.cluster.size_band_m
    assert grouping.size > high
    assert grouping.scale == pytest.approx(grouping.size / high)
    assert grouping.config.eps == pytest.approx(config.cluster.eps * grouping.scale)
    shrunk = Cloud(big.points / grouping.scale, big.colors)
    stated = cluster_flowers(shrunk, np.arange(len(shrunk)), config.outliers,
                             replace(config.cluster, size_band_m=None), config.colour)
    assert stated.scale == 1.0
    assert [c.tolist() for c in grouping.clusters] == [c.tolist() for c in stated.clusters]
    unsized = cluster_flowers(big, np.arange(len(big)), config.outliers,
                              replace(config.cluster, size_band_m=None), config.colour)
    assert unsized.scale == 1.0 and unsized.config.eps == config.cluster.eps


def test_the_pose_of_crops_holds_whatever_the_unit_of_the_cloud():
    for scale in (0.3, 1.0, 4.0):
        rng = np.random.default_rng(1)
        crops = [flower(c, n, rng) for c, n in zip(CENTRES, NORMALS, strict=True)]
        poses, _ = pose_crops([Cloud(c.points * scale, c.colors) for c in crops],
                              PipelineConfig())
        for pose, normal in zip(poses, NORMALS, strict=True):
            assert np.degrees(np.arccos(min(1.0, abs(pose.normals["plane"] @ normal)))) < 3.0
