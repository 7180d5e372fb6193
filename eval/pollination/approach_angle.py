"""How far off a flower's axis a pollination visit may come, measured in the contact world.

For each angle of `PollinationScoreConfig.curve_angles_deg`, every true flower of a plant is
visited along a direction that many degrees off its true axis (at a seeded azimuth): the
planner plans that one direction (no cone), the executor flies the plan on a simulated bot,
and the flight is replayed through the plant in MuJoCo and judged as `eval --task pollinate`
judges a visit, with the angle rule left out: the swab must rest on the pistil and the way
in and out must touch no other flower and push no leaf too far. The curve, success against
the angle over the approaches the planner could plan, is what the planner's cone
(`PollinateConfig.cone_deg`) and the score's angle limit (`max_angle_deg`) rest on.
Degrees, bed frame.
"""

from __future__ import annotations

import dataclasses
import tempfile
from pathlib import Path

import numpy as np

from flowerpose.cloudio import Cloud
from flowerpose.eval.pollination.contact import ContactWorld
from flowerpose.eval.pollination.visits import PollinationScoreConfig, flown_visits, judge
from flowerpose.eval.scoring.pollinated import CAUSES
from flowerpose.hardware.flights.pollination_plan import (
    Flower,
    PollinateConfig,
    plan_pollination,
    tilted,
)
from flowerpose.hardware.geometry import PAPER_TOOL, PollinatorTool
from flowerpose.pipeline.colour import flower_coloured


def approach_curve(world: ContactWorld, cloud: Cloud, plan_config: PollinateConfig,
                   config: PollinationScoreConfig, tool: PollinatorTool = PAPER_TOOL,
                   corolla: np.ndarray | None = None) -> list[dict]:
    """One plant's visits at each of `config.curve_angles_deg` off its flowers' true axes:
    per angle, the approaches planned and each one's outcome (`judge` without the angle
    rule). world: the plant's contact world (its plant read; the plant's seed seeds the
    azimuths); cloud: its cloud (metres, bed frame), the planner's obstacles; corolla: its
    points of a flower's colour by the run's colour model (`flower_coloured`; None: by the
    default model), which may be a target's own corolla."""
    if not config.curve_angles_deg:
        return []
    plant = world.plant
    unjudged = dataclasses.replace(config, max_angle_deg=180.0)
    along = dataclasses.replace(plan_config, cone_deg=0.0)
    corolla = flower_coloured(cloud.colors) if corolla is None else corolla
    rows = []
    for k, angle in enumerate(config.curve_angles_deg):
        flowers = []
        for flower in plant.flowers:
            azimuth = np.random.default_rng([plant.seed, flower.id, k]).uniform(0.0, 2.0 * np.pi)
            flowers.append(Flower(flower.id, np.asarray(flower.center, np.float64),
                                  tilted(flower.normal, angle, azimuth), float(flower.radius)))
        plan = plan_pollination(flowers, cloud.points, along, tool=tool, corolla=corolla)
        with tempfile.TemporaryDirectory() as scratch:
            timeline, flown, _ = flown_visits(plan, Path(scratch))
        planned = {v.flower for v in plan.planned}
        outcomes = [judge(f, f.id, plan, flown, timeline, world, unjudged, tool)
                    for f in plant.flowers if f.id in planned]
        rows.append({"angle_deg": float(angle), "flowers": len(plant.flowers),
                     "planned": len(outcomes),
                     "outcomes": [o["outcome"] for o in outcomes]})
    return rows


def summarise_curve(plants: list[list[dict]]) -> list[dict]:
    """report.json's `pollination_by_angle`: per angle over all plants, the flowers, the
    approaches planned, their successes and rate, and the failures by cause."""
    rows = []
    for per_angle in zip(*plants, strict=True):
        outcomes = [o for row in per_angle for o in row["outcomes"]]
        successes = outcomes.count("success")
        rows.append({"angle_deg": per_angle[0]["angle_deg"],
                     "flowers": sum(row["flowers"] for row in per_angle),
                     "planned": len(outcomes), "successes": successes,
                     "success_rate": round(successes / len(outcomes), 4) if outcomes else None,
                     "failures": {cause: outcomes.count(cause) for cause in CAUSES
                                  if outcomes.count(cause)}})
    return rows
