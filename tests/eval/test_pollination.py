"""Pollination scored on synthetic plants: the planner's ceiling on an easy plant, poses
that are off, the report's sections, and a task that cannot run."""

import dataclasses
import json

import numpy as np
import pytest

from flowerpose.eval.jobs.plant_set import PlantSet
from flowerpose.eval.pollination.visits import PollinationScoreConfig, plan_and_score
from flowerpose.eval.pool import Execution
from flowerpose.eval.scoring.pollinated import CAUSES
from flowerpose.hardware.flights.pollination_plan import PollinateConfig


@pytest.fixture(scope="module")
def easy_plant(tmp_path_factory):
    from flowerpose.sim.bundle import make_plant

    folder = tmp_path_factory.mktemp("easy") / "plant"
    bundle = make_plant(2, "easy", out_dir=folder)
    return folder, bundle


def _flowers_json(path, plant, tilt_deg=0.0):
    """The plant's true poses as a flowers.json, each normal tilted by `tilt_deg`."""
    entries = []
    for flower in plant.flowers:
        normal = np.asarray(flower.normal, float)
        side = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
        side /= np.linalg.norm(side)
        tilted = np.cos(np.radians(tilt_deg)) * normal + np.sin(np.radians(tilt_deg)) * side
        entries.append({"id": flower.id, "center": list(map(float, flower.center)),
                        "normals": {"plane": list(map(float, tilted))}})
    path.write_text(json.dumps({"units": "m", "frame": "bed", "flowers": entries}))
    return path


@pytest.mark.slow
def test_the_true_poses_pollinate_every_flower_the_planner_can_reach(easy_plant):
    folder, bundle = easy_plant
    result = plan_and_score(folder, None, bundle.cloud, 0.02, PollinateConfig(),
                            PollinationScoreConfig())
    outcomes = [o["outcome"] for o in result["flowers"]]
    assert len(outcomes) == len(bundle.plant.flowers)
    assert set(outcomes) <= {"success", "unreachable"} and "success" in outcomes
    assert result["successes"] == outcomes.count("success") == result["visits"]
    assert set(result["failures"]) == set(CAUSES)


@pytest.mark.slow
def test_poses_far_off_the_axis_miss_and_the_same_poses_as_a_file_do_not(easy_plant,
                                                                         tmp_path):
    folder, bundle = easy_plant
    # A narrow cone and no paths: the poses are on trial here, and this keeps it quick.
    planner = PollinateConfig(cone_deg=10.0, path_checks=0)
    args = (bundle.cloud, 0.02, planner, PollinationScoreConfig())
    exact = plan_and_score(folder, _flowers_json(tmp_path / "exact.json", bundle.plant),
                           *args)
    ceiling = plan_and_score(folder, None, *args)
    assert exact["successes"] == ceiling["successes"] > 0
    # Beyond the score's angle limit however the planner's cone turns the approach.
    tilt = PollinationScoreConfig().max_angle_deg + planner.cone_deg + 5.0
    off = plan_and_score(folder, _flowers_json(tmp_path / "off.json", bundle.plant, tilt),
                         *args)
    assert off["successes"] == 0
    assert all(o["outcome"] in ("pose off", "unreachable", "collision")
               for o in off["flowers"])
    assert off["failures"]["pose off"] >= 1


@pytest.mark.slow
def test_eval_reports_pollination_and_its_curve(tmp_path):
    from flowerpose.eval.jobs.config import eval_config
    from flowerpose.eval.jobs.eval_run import EvalRun
    from flowerpose.eval.studies.eval_recipe import run_eval

    config = eval_config("easy")
    angles = (30.0,)
    # No path search: the report's sections are on trial here (paths have their own tests).
    config = dataclasses.replace(
        config, pollination=dataclasses.replace(config.pollination, curve_angles_deg=angles),
        pollinate=dataclasses.replace(config.pollinate, path_checks=0))
    report = run_eval(config, EvalRun(PlantSet("oracle", plants=1, seed=2), task="pollinate"),
                      tmp_path / "run", Execution(1))
    summary = report["summary"]
    for key in ("pollination", "pollination_ceiling"):
        assert set(summary[key]) == {"visits", "flowers", "successes", "success_rate",
                                    "success_rate_ci95", "failures", "collision_share",
                                    "collision_share_ci95"}
        collided = summary[key]["failures"]["collision"]
        assert summary[key]["collision_share"] == round(collided / summary[key]["visits"], 4)
    plant = report["plants"][0]
    assert len(plant["pollination"]["flowers"]) == plant["gt"]
    assert sum(r["flowers"] for r in report["pollination_by_error"]) > 0
    curve = report["pollination_by_angle"]
    assert [r["angle_deg"] for r in curve] == list(angles)
    assert all(r["flowers"] == plant["gt"] and 0 <= r["successes"] <= r["planned"]
               <= r["flowers"] for r in curve)
    assert curve[0]["planned"] > 0
    assert (tmp_path / "run" / "pollination.png").stat().st_size > 0
    flight = json.loads((tmp_path / "run" / "plants" / plant["plant"] / "flight.json").read_text())
    assert flight["status"] == "complete"
    assert len(flight["done"]) == plant["pollination"]["visits"]
    # The results page gives the run a row of its pollination section, and its curve.
    from flowerpose.eval.studies.results import results_markdown

    page = results_markdown([tmp_path / "run" / "report.json"])
    assert "## Pollination" in page and "## Accuracy" not in page
    row = next(line for line in page.splitlines() if line.startswith("| 1 plants from seed 2"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[1:3] == [str(plant["gt"]), str(summary["pollination"]["visits"])]
    assert cells[3].startswith(f"{summary['pollination']['successes']} (")
    assert page.count("| [1] ") == len(angles)


def test_pollination_needs_synthetic_plants(tmp_path, capsys):
    from flowerpose.cli import main

    assert main(["eval", "--source", "real", str(tmp_path), "--task", "pollinate",
                 "--out", str(tmp_path / "out")]) == 2
    assert "pollinate needs synthetic plants" in capsys.readouterr().err


@pytest.mark.parametrize("settings, key", [
    ({"curve_angles_deg": (0.0, 95.0)}, "pollination.curve_angles_deg"),
    ({"curve_angles_deg": (-5.0,)}, "pollination.curve_angles_deg"),
    ({"max_angle_deg": 0.0}, "pollination.max_angle_deg"),
])
def test_angles_out_of_range_are_refused_naming_the_setting(settings, key):
    from flowerpose.errors import InputError

    with pytest.raises(InputError, match=key):
        PollinationScoreConfig(**settings)


@pytest.mark.slow
def test_a_flower_under_a_leaf_is_pollinated_down_a_path_that_touches_no_leaf_in_mujoco(
        tmp_path):
    """The planner's path round a leaf, flown by the executor and replayed in the contact
    world: the swab rests on the pistil and neither tool nor head touches the leaf."""
    import sys
    from pathlib import Path

    import trimesh

    pytest.importorskip("ompl")
    sys.path.insert(0, str(Path(__file__).parents[1] / "sim"))
    from simhelpers import box, handmade_plant

    from flowerpose.cloudio import Cloud
    from flowerpose.eval.pollination.contact import ContactWorld
    from flowerpose.eval.pollination.visits import flown_visits, judge
    from flowerpose.hardware.flights.pollination_plan import Flower, plan_pollination
    from flowerpose.hardware.geometry import PollinatorTool
    from flowerpose.hardware.kinematics import head_boxes
    from flowerpose.sim.pieces import Part

    center, up = np.array([1.5, 0.75, 0.15]), np.array([0.0, 0.0, 1.0])
    # The scene is built for a 12 cm shaft (test_approach_path.py's SHORT).
    config = PollinateConfig(tool=PollinatorTool(reach_m=0.12, offset_down_m=0.03),
                             standoff_m=0.065)
    (clear,) = plan_pollination([Flower(0, center, up)], None, config).visits
    centres, rotations, half = head_boxes(clear.pre)
    over_head = max(float((centres[k] + np.abs(rotations[k]) @ half[k])[2]) for k in range(2))
    plant = handmade_plant([(center, up)], [box([*center[:2], over_head + 0.03],
                                                [0.14, 0.14, 0.004])])
    points, faces = trimesh.sample.sample_surface_even(plant.mesh, 20000, seed=0)
    cloud = Cloud(np.asarray(points), np.asarray(plant.mesh.visual.face_colors[faces][:, :3],
                                                 np.uint8))
    plan = plan_pollination([Flower(0, center, up)], cloud.points, config)
    (visit,) = plan.visits
    assert visit.status == "planned" and visit.path
    timeline, flown, _ = flown_visits(plan, tmp_path)
    world = ContactWorld(plant, tool=config.tool)
    outcome = judge(plant.flowers[0], 0, plan, flown, timeline, world,
                    PollinationScoreConfig(), config.tool)
    assert outcome["outcome"] == "success", outcome
    touched = world.fly(timeline, flown[0]["t0"], flown[0]["t1"]).patches
    assert not np.isin(world.patches.part[touched], [int(Part.LEAF)]).any()
