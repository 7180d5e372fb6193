"""Fidelity statistics on flowers of known shape, the CLI on a real folder and a seeded
plant, and the field preset's plants and cloud."""

import json

import numpy as np
import pytest
from realplants import write_real_plant

from flowerpose.cli import main
from flowerpose.eval.jobs.config import eval_config
from flowerpose.eval.scoring.real_source import read_real_plant
from flowerpose.eval.studies.fidelity import (
    compare,
    real_sample,
    statistics,
    synthetic_cloud,
    synthetic_folders,
)
from flowerpose.pipeline.colour import petal_mask, pistil_mask, rgb_to_hsv
from flowerpose.pipeline.flowers import PipelineConfig
from flowerpose.sim.bundle import make_plant
from flowerpose.sim.pieces import Part
from flowerpose.sim.world_config import sim_preset


def test_statistics_of_flowers_of_known_size_cupping_and_colour(tmp_path):
    plant = read_real_plant(write_real_plant(tmp_path / "plant", "candidates"))
    stats = statistics([real_sample(plant, PipelineConfig(), 0.02)], PipelineConfig())
    assert stats["flowers"] == 4
    # Corollas of radius 20 mm whose rim rises a tenth of the radius, 0.2 mm of noise.
    assert stats["diameter"]["p50"] == pytest.approx(0.04, rel=0.1)
    assert stats["cupping"]["p50"] == pytest.approx(0.1, abs=0.03)
    assert stats["thickness"]["p50"] < 0.001
    assert stats["petal_colour_fail"]["p50"] < 0.02
    assert stats["leaf_petal_colour"] == 0.0
    # These crops hold nothing behind the petal base, so the stalk cannot be judged.
    assert stats["stalk_pistil_colour"] is None
    rows = compare(stats, stats)
    assert len(rows) == 17
    assert [row["statistic"] for row in rows if not row["holds"]] == [
        "stalk points of pistil colour"]


def test_roughness_tells_a_smooth_surface_from_a_jittered_one():
    from flowerpose.eval.studies.fidelity import local_roughness
    from flowerpose.perturb import smooth_noise

    rng = np.random.default_rng(3)
    disc = np.c_[rng.uniform(-0.02, 0.02, (3000, 2)), np.zeros(3000)]
    smooth = disc + smooth_noise(disc, 0.0005, 0.01, rng)
    jittered = disc + rng.normal(0, 0.0005, disc.shape)
    assert local_roughness(smooth) < 0.2 * local_roughness(jittered)
    assert local_roughness(jittered) == pytest.approx(0.0005, rel=0.6)


@pytest.mark.slow
def test_the_command_compares_a_real_folder_with_a_seeded_plant(tmp_path, plant0, capsys):
    real = write_real_plant(tmp_path / "real", "candidates")
    assert main(["fidelity", str(real), str(plant0[1]), "--out", str(tmp_path / "f")]) == 0
    report = json.loads((tmp_path / "f" / "fidelity.json").read_text())
    assert report["of"] == 17 and report["synthetic"]["plants"] == [plant0[1].name]
    # Generated flowers are 2-3.5 cm across; these test flowers 4 cm.
    sizes = {r["statistic"]: r for r in report["comparison"]}
    assert not sizes["diameter (median)"]["holds"]
    assert (tmp_path / "f" / "fidelity.png").stat().st_size > 0
    out = capsys.readouterr().out
    assert "statistics within tolerance" in out and "predicted at the real density" in out
    # The real plant's scores with their intervals, the synthetic plant's beside them.
    outcome = report["outcomes"]
    assert outcome["real"]["recall_visible"] == 1.0 and outcome["real"]["visible"] == 4
    low, high = (outcome["real"]["plane_mean_ci95"][k] for k in ("low", "high"))
    assert low <= outcome["real"]["plane_mean"] <= high
    assert outcome["predicted"]["visible"] > 0
    assert outcome["recall_inside"] == (outcome["real"]["recall_visible_ci95"]["low"]
                                        <= outcome["predicted"]["recall_visible"])
    # The page of results takes the fidelity run as a section of its own.
    assert main(["results", str(tmp_path / "f" / "fidelity.json"), "--no-paper"]) == 0
    assert "## Simulator against real [1]" in capsys.readouterr().out


def test_crops_cannot_be_described_and_say_so(tmp_path, plant0, capsys):
    real = write_real_plant(tmp_path / "real", "crops")
    assert main(["fidelity", str(real), str(plant0[1]), "--out", str(tmp_path / "f")]) == 2
    assert "fidelity needs cloud.ply or candidates/" in capsys.readouterr().err


@pytest.mark.slow
def test_the_field_preset_makes_large_flowers_and_a_paled_sheened_cloud():
    field = make_plant(1, preset="field")
    realistic = make_plant(1, preset="realistic")
    assert sim_preset("field").plant.name == "field"
    diameters = [2 * f.radius for f in field.plant.flowers]
    assert min(diameters) >= 0.04 and max(diameters) <= 0.06
    # Sampled at 100,000 points, then thinned to the plant's drawn density.
    from flowerpose.sim.degrade import points_per_flower

    assert len(field.cloud) <= 100_000
    assert 90 <= points_per_flower(field.point_flower, field.visible) <= 1100

    def leaves(bundle):
        return rgb_to_hsv(bundle.cloud.colors[bundle.point_part == Part.LEAF])

    assert np.median(leaves(field)[:, 1]) < 0.8 * np.median(leaves(realistic)[:, 1])
    # Sheen gives some leaf points a petal's colour, as on a real photogrammetry cloud.
    assert 0.05 < petal_mask(leaves(field), PipelineConfig().colour).mean() < 0.3
    assert petal_mask(leaves(realistic), PipelineConfig().colour).mean() < 0.01
    # The leaves yellow but the peduncles do not turn a pistil's colour (the real plant's
    # stalks have none).
    stalks = rgb_to_hsv(field.cloud.colors[field.point_part == Part.PEDUNCLE])
    assert pistil_mask(stalks, PipelineConfig().colour).mean() < 0.05


def test_the_field_preset_films_with_the_field_camera_and_keeps_polycams_density():
    field, realistic = eval_config("field"), eval_config("realistic")
    # An auto-exposed camera brightens the render; Polycam's ~800 points a flower is a
    # 2.5 mm voxel (the values the field preset's file gives).
    assert field.scan.camera.sensor.gain == 1.5 > realistic.scan.camera.sensor.gain == 1.0
    assert field.scan.reconstruct.dense.voxel_size_m == 0.0025
    assert realistic.scan.reconstruct.dense.voxel_size_m < 0.0025
    assert field.score.label_error_deg > 0 == realistic.score.label_error_deg


def test_a_scan_run_is_described_by_its_reconstruction_not_the_oracle_cloud(tmp_path):
    plant = tmp_path / "run" / "plants" / "seed-0"
    for name in ("plant.json", "cloud.ply"):
        (plant / name).parent.mkdir(parents=True, exist_ok=True)
        (plant / name).write_text("")
    assert synthetic_cloud(plant) == (plant / "cloud.ply", plant / "plant.json")
    for name in ("reconstruction/cloud.ply", "scan/plant.json"):
        (plant / name).parent.mkdir(parents=True, exist_ok=True)
        (plant / name).write_text("")
    assert synthetic_cloud(plant) == (plant / "reconstruction" / "cloud.ply",
                                      plant / "scan" / "plant.json")
    assert synthetic_folders([tmp_path / "run"]) == [plant]
