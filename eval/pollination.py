"""Pollination as the harness scores it (`eval --task pollinate`): each synthetic plant's
visits planned from the pipeline's poses (and, for the planner's own ceiling, from the true
poses), flown along the motion profile, and judged against the plant's exact geometry.

A visit succeeds when the swab's centre ends within `touch_radius_m` of the true flower's
centre, its approach lies within `max_angle_deg` of the true axis, and on the way in and
out the pollinator touches no other flower's petals, anthers or receptacle and pushes no
leaf or stem aside by more than `max_push_m`. Every true flower gets one outcome: success,
or the cause of failure: "missed" (no detection), "no pose" (a detection without a normal),
"unreachable" (the planner found no approach), "pose off" (the swab misses the centre or
comes in too far off the axis), "collision" (another flower, or a leaf pushed too far).

This is kinematic, not MuJoCo contact: the tool is rigid and the plant's surfaces stand
still, so a touch is the tool coming nearer a surface sample than its radius, and a push
how much nearer (the depth a leaf would have to move aside). Metres and degrees, bed frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from flowerpose.errors import InputError
from flowerpose.hardware.geometry import PAPER_TOOL, PollinatorTool
from flowerpose.hardware.kinematics import HeadPose, tool_forward, tool_points
from flowerpose.hardware.motion import MotionProfile
from flowerpose.hardware.pollinate import (
    Flower,
    PollinateConfig,
    PollinationPlan,
    plan_pollination,
    read_visit_flowers,
)
from flowerpose.hardware.scan_plan import poses_along

#: The causes a visit fails for, in the order they are looked at.
CAUSES = ("missed", "no pose", "unreachable", "pose off", "collision")


@dataclass(frozen=True)
class PollinationScoreConfig:
    """What counts as a pollinated flower."""

    touch_radius_m: float = 0.004
    """The swab's centre within this of the true centre: the receptacle is 6-8 mm wide, and
    an 8 mm swab there covers the anthers round it."""
    max_angle_deg: float = 20.0
    """The approach within this of the true axis: further off, the swab meets the petals'
    inner side before the centre (a 30 mm corolla cupped 3-4 mm)."""
    max_push_m: float = 0.01
    """How far a leaf or stem may be pushed aside by the tool."""
    surface_samples: int = 200_000
    """Points sampled on the plant's surfaces to test contact."""
    samples_per_move: int = 12
    """Poses checked along each move of the plan."""


def plan_and_score(plant_dir: Path, flowers_json: Path | None, obstacles: np.ndarray | None,
                   match_distance_m: float, plan_config: PollinateConfig,
                   config: PollinationScoreConfig, tool: PollinatorTool = PAPER_TOOL) -> dict:
    """One plant's pollination: plan from flowers.json's poses (None: the true poses), fly
    the plan, and judge every open flower of the plant in plant_dir (`flowerpose plant`'s
    folder). Returns the per-plant report section."""
    from flowerpose.pipeline.flowers import read_flowers
    from flowerpose.sim.export import read_plant

    plant = read_plant(plant_dir)
    truth = plant.flowers
    if flowers_json is None:
        estimates = [Flower(f.id, np.asarray(f.center, float), np.asarray(f.normal, float))
                     for f in truth]
        nearest = {f.id: f.id for f in truth}
    else:
        entries = read_flowers(flowers_json)
        estimates, _ = read_visit_flowers(entries)
        nearest = _match(truth, entries, match_distance_m)
    plan = plan_pollination(estimates, obstacles, plan_config, tool=tool)
    surfaces = _Surfaces(plant, config.surface_samples)
    outcomes = []
    for flower in truth:
        outcomes.append(_judge(flower, nearest.get(flower.id), plan, surfaces, config, tool))
    return {"visits": len(plan.planned), "planned_s": round(plan.duration_s, 1),
            "flowers": outcomes, **tally(outcomes)}


def _match(truth: list, entries: list[dict], distance_m: float) -> dict[int, int | None]:
    """Each true flower's detection id among flowers.json `entries`: the nearest within
    `distance_m`, one each (greedy on distance); a detection without a normal counts too,
    as "no pose"."""
    centres = {int(e.get("id", k)): np.asarray(e["center"], float) for k, e in enumerate(entries)}
    pairs = sorted((float(np.linalg.norm(np.asarray(t.center) - c)), t.id, d)
                   for t in truth for d, c in centres.items())
    found: dict[int, int | None] = {t.id: None for t in truth}
    used: set[int] = set()
    for distance, true_id, detection in pairs:
        if distance <= distance_m and found[true_id] is None and detection not in used:
            found[true_id] = detection
            used.add(detection)
    return found


class _Surfaces:
    """Samples of the plant's surfaces with what each belongs to, for contact tests."""

    def __init__(self, plant, samples: int):
        import trimesh

        from flowerpose.sim.pieces import FLOWER_PARTS, Part

        points, faces = trimesh.sample.sample_surface(plant.mesh, samples, seed=0)
        part, flower = plant.face_part[faces], plant.face_flower[faces]
        self.flower_parts = np.isin(part, [int(p) for p in FLOWER_PARTS if p != Part.SEPAL])
        self.pushable = np.isin(part, [int(Part.LEAF), int(Part.PETIOLE), int(Part.PEDUNCLE),
                                       int(Part.SEPAL), int(Part.BUD), int(Part.FRUIT)])
        self.points, self.flower = points, flower
        self.tree = cKDTree(points)


def _judge(flower, detection: int | None, plan: PollinationPlan, surfaces: _Surfaces,
           config: PollinationScoreConfig, tool: PollinatorTool) -> dict:
    """One true flower's outcome: success or the first cause of failure."""
    entry = {"flower": int(flower.id), "detection": detection}
    if detection is None:
        return {**entry, "outcome": "missed"}
    visit = next((v for v in plan.visits if v.flower == detection), None)
    if visit is None:
        return {**entry, "outcome": "no pose"}
    if visit.status != "planned":
        return {**entry, "outcome": "unreachable", "reason": visit.reason}
    tip, ahead = tool_forward(visit.touch, tool)
    miss = float(np.linalg.norm(tip - np.asarray(flower.center)))
    angle = float(np.degrees(np.arccos(np.clip(-ahead @ np.asarray(flower.normal), -1, 1))))
    entry.update(miss_m=round(miss, 4), angle_deg=round(angle, 2))
    if miss > config.touch_radius_m or angle > config.max_angle_deg:
        return {**entry, "outcome": "pose off"}
    touched, push = _contacts(_visit_path(plan, detection, config), flower.id, surfaces, tool)
    entry.update(push_m=round(push, 4))
    if touched:
        return {**entry, "outcome": "collision", "reason": f"touches flower {touched[0]}"}
    if push > config.max_push_m:
        return {**entry, "outcome": "collision",
                "reason": f"pushes a leaf {push * 1000:.0f} mm aside"}
    return {**entry, "outcome": "success"}


def _visit_path(plan: PollinationPlan, detection: int,
                config: PollinationScoreConfig) -> HeadPose:
    """Poses along the moves of one visit (travel in, descent, approach, retreat) on the
    motion profile."""
    profile = MotionProfile()
    moves = plan.moves
    indices = [k for k, m in enumerate(moves) if m.flower == detection]
    first, last = max(indices[0] - 1, 0), indices[-1]
    poses = [poses_along(moves[k].pose, moves[k + 1].pose, profile, config.samples_per_move)
             for k in range(first, last)]
    return HeadPose(np.concatenate([p.gantry for p in poses]),
                    np.concatenate([p.yaw for p in poses]),
                    np.concatenate([p.pitch for p in poses]))


def _contacts(path: HeadPose, target: int, surfaces: _Surfaces,
              tool: PollinatorTool) -> tuple[list[int], float]:
    """The other flowers the tool touches along `path`, and the deepest it goes into a
    leaf or stem (metres; 0 when it touches none)."""
    shaft = tool_points(path, tool, samples=24).reshape(-1, 3)
    radius = max(tool.tip_radius_m, tool.shaft_radius_m)
    near = surfaces.tree.query_ball_point(shaft, radius)
    hit = np.unique(np.concatenate([np.asarray(n, int) for n in near] or [np.zeros(0, int)]))
    others = hit[surfaces.flower_parts[hit] & (surfaces.flower[hit] != target)]
    touched = sorted({int(f) for f in surfaces.flower[others]})
    pushed = hit[surfaces.pushable[hit]]
    if not len(pushed):
        return touched, 0.0
    depth = radius - cKDTree(shaft).query(surfaces.points[pushed])[0]
    return touched, float(max(depth.max(), 0.0))


def tally(outcomes: list[dict]) -> dict:
    """Successes, their rate and the failures by cause of a list of flower outcomes."""
    successes = sum(o["outcome"] == "success" for o in outcomes)
    return {"successes": successes, "success_rate": round(successes / len(outcomes), 4)
            if outcomes else None,
            "failures": {cause: sum(o["outcome"] == cause for o in outcomes)
                         for cause in CAUSES}}


def summarise_pollination(plants: list[dict]) -> dict:
    """report.json's `summary.pollination` from the plants' sections."""
    outcomes = [o for p in plants for o in p["flowers"]]
    return {"visits": sum(p["visits"] for p in plants), **tally(outcomes)}


def success_by_error(plants: list[dict], truth_errors: dict[tuple[str, int], float],
                     edges_deg=(0, 2, 4, 6, 8, 10, 15, 20, 30, 45, 90, 180)) -> list[dict]:
    """Success rate per bin of the pose's plane error (degrees) over the flowers detected
    with a normal, and over those whose visit was planned (reach is the pose's error's
    business only through the approach it asks for): how much angle error is enough,
    measured."""
    rows = []
    flowers = [(truth_errors[(p["plant"], o["flower"])], o["outcome"])
               for p in plants for o in p["flowers"] if (p["plant"], o["flower"]) in truth_errors]
    for low, high in zip(edges_deg, edges_deg[1:], strict=False):
        inside = [outcome for error, outcome in flowers if low <= error < high]
        planned = [outcome for outcome in inside if outcome != "unreachable"]
        rows.append({"from_deg": low, "to_deg": high, "flowers": len(inside),
                     "success_rate": _rate(inside), "planned": len(planned),
                     "success_rate_planned": _rate(planned)})
    return rows


def _rate(outcomes: list[str]) -> float | None:
    return round(outcomes.count("success") / len(outcomes), 4) if outcomes else None


def write_success_plot(path: Path, rows: list[dict]) -> Path:
    """pollination.png: success rate against the pose's plane error."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from flowerpose.atomic import write_file

    used = [r for r in rows if r["flowers"]]
    if not used:
        raise InputError(path, "no detected flower to plot")
    figure, axis = plt.subplots(figsize=(7, 3.5))
    labels = [f"{r['from_deg']}-{r['to_deg']}" for r in used]
    x = np.arange(len(used))
    for offset, key, count, colour, name in (
            (-0.2, "success_rate", "flowers", "#9bbf85", "of the flowers detected"),
            (0.2, "success_rate_planned", "planned", "#3f7f1f", "of the visits planned")):
        heights = [r[key] or 0.0 for r in used]
        axis.bar(x + offset, heights, width=0.4, color=colour, label=name)
        for k, r in enumerate(used):
            axis.annotate(str(r[count]), (x[k] + offset, heights[k]), ha="center",
                          va="bottom", fontsize=7)
    axis.set_xticks(x, labels)
    axis.set_xlabel("plane normal error, degrees (the count above each bar)")
    axis.set_ylabel("pollination success")
    axis.set_ylim(0, 1.15)
    axis.legend(loc="upper right", fontsize=8)
    figure.tight_layout()
    write_file(path, lambda tmp: figure.savefig(tmp, format="png", dpi=120))
    plt.close(figure)
    return path
