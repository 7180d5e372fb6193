"""Pollination as the harness scores it (`eval --task pollinate`): each synthetic plant's
visits planned from the pipeline's poses (and, for the planner's own ceiling, from the true
poses), flown by the same executor that drives the physical bot (`hardware/
pollination_flight.py`) on a simulated bot, and that flight replayed through the plant in
MuJoCo with contact (`eval/pollination/contact.py`): leaflets and petioles give way on
sprung joints, flowers and stalks stand.

A visit succeeds when, at the rest, the swab's centre is within `touch_radius_m` of the
true flower's centre and touches its receptacle or stamens, its approach lies within
`max_angle_deg` of the true axis, and on the way in and out the pollinator and head touch
no other flower's petals, anthers or receptacle and push no leaflet or petiole more than
`max_push_m` from where it grew. Every true flower gets one outcome: success, or the cause
of failure: "missed" (no detection), "no pose" (a detection without a normal),
"uncertain" (a detection whose normal's sign the pose stage could not settle, left alone:
`pollinate.visit_uncertain`), "unreachable" (the planner found no approach), "pose off"
(the swab misses the centre, stops short of it or comes in too far off the axis),
"collision" (another flower, or a leaf pushed too far). Metres and degrees, bed frame.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from flowerpose.cloudio import Cloud
from flowerpose.errors import InputError
from flowerpose.eval.pollination.contact import ContactWorld, Touches
from flowerpose.eval.scoring.pollinated import CAUSES, tally
from flowerpose.hardware.backends.sim_camera import SimCameraConfig
from flowerpose.hardware.bot import KinematicBot
from flowerpose.hardware.flights.close_look import CloseLook
from flowerpose.hardware.flights.pollination_flight import fly_pollination
from flowerpose.hardware.flights.pollination_plan import (
    Flower,
    PlantObstacles,
    PollinateConfig,
    plan_pollination,
)
from flowerpose.hardware.flights.visit_flowers import UNCERTAIN, read_visit_flowers
from flowerpose.hardware.geometry import PollinatorTool
from flowerpose.hardware.kinematics import HeadPose, tool_forward
from flowerpose.hardware.trajectory import Timeline
from flowerpose.jsonio import write_json
from flowerpose.pipeline.colour import ColourConfig, flower_coloured
from flowerpose.pipeline.pose import PoseConfig
from flowerpose.sim.contact import ContactConfig
from flowerpose.sim.pieces import FLOWER_PARTS, Part
from flowerpose.stopwatch import Stopwatch


@dataclass(frozen=True)
class PollinationScoreConfig:
    """What counts as a pollinated flower."""

    touch_radius_m: float = 0.004
    """The swab's centre within this of the true centre: the receptacle is 6-8 mm wide, and
    an 8 mm swab there covers the anthers round it."""
    max_angle_deg: float = 60.0
    """The approach within this of the true axis. The contact replay (`curve_angles_deg`,
    `approach_angle.py`; 10 realistic plants, seeds 0-9, at 0-75 degrees: docs/results.md)
    found the swab's touch independent of the angle to 75 degrees: no visit missed its
    pistil, and the few lost (97-100 % pollinated at every angle, 0 included) touched a leaf
    or a neighbour on the way in. 60 keeps the shaft 9 mm over the rim of a flat corolla
    30 mm wide (4 mm at 75, about a cupped corolla's depth)."""
    curve_angles_deg: tuple[float, ...] = ()
    """Angles off the true axis at which every flower's visit is replayed for the
    success-against-angle curve (`approach_angle.py`; report.json's `pollination_by_angle`,
    pollination.png), e.g. [0, 10, 20, 30, 40, 45, 50]; each costs about one more planning
    and flight of every flower. Empty: not measured."""
    max_push_m: float = 0.01
    """How far the tool may push any point of a leaflet or petiole from where it grew."""
    contact: ContactConfig = field(default_factory=ContactConfig)
    """The plant in MuJoCo: its contact patches and how its leaves give way."""

    def __post_init__(self):
        if not 0 < self.max_angle_deg <= 180:
            raise InputError("pollination.max_angle_deg", f"must be above 0 and at most 180, "
                             f"got {self.max_angle_deg}")
        bad = [a for a in self.curve_angles_deg if not 0 <= a < 90]
        if bad:
            raise InputError("pollination.curve_angles_deg", f"angles off the axis must be 0 "
                             f"or more and below 90 degrees, got {bad}")


#: Parts of another flower that a visit must not touch (its sepals sit behind the petals,
#: where the tool brushes them without harm).
OTHER_FLOWER_PARTS = [int(p) for p in FLOWER_PARTS if p != Part.SEPAL]
#: Parts whose touch by the swab at the rest pollinates.
PISTIL_PARTS = [int(Part.RECEPTACLE), int(Part.STAMEN)]


@dataclass(frozen=True)
class LookSetup:
    """What a close look needs in the simulator (`pollinate.look`): the scan's camera, its
    model and imperfections, and the pipeline's pose and colour settings, which estimate
    the flower's pose again from the close frames."""

    camera: SimCameraConfig
    pose: PoseConfig
    colour: ColourConfig


def plan_and_score(plant_dir: Path, flowers_json: Path | None, cloud: Cloud | None,
                   match_distance_m: float, plan_config: PollinateConfig,
                   config: PollinationScoreConfig, tool: PollinatorTool | None = None,
                   flight_json: Path | None = None, world: ContactWorld | None = None,
                   corolla: np.ndarray | None = None, look: LookSetup | None = None) -> dict:
    """One plant's pollination: plan from flowers.json's poses (None: the true poses) with
    the plant's cloud (bed frame, metres; None: reach alone) as obstacles, fly
    the plan on a simulated bot, replay the flight through the plant in MuJoCo and judge
    every open flower of the plant in plant_dir (`flowerpose plant`'s folder). The flight's
    record goes to flight_json when given; `world`: the plant's contact world (and the plant
    read once), when the caller has one; `corolla`: the cloud's points of a flower's colour
    by the run's colour model (`flower_coloured`), which may be a target's own corolla,
    when the caller has them (else by the default model); `look`: each visit looks again
    before it touches (`hardware/flights/close_look.py`) where `pollinate.look.views` asks,
    the frames rendered by the simulated camera; `tool`: the pollinator (None:
    `plan_config.tool`). Returns the per-plant report section."""
    from flowerpose.pipeline.flowers import read_flowers
    from flowerpose.sim.export import read_plant

    plant = world.plant if world is not None else read_plant(plant_dir)
    truth = plant.flowers
    tool = tool or plan_config.tool
    looking = look is not None and plan_config.look.views > 0
    if flowers_json is None:
        estimates = [Flower(f.id, np.asarray(f.center, float), np.asarray(f.normal, float),
                            float(f.radius))
                     for f in truth]
        nearest, skipped = {f.id: f.id for f in truth}, {}
    else:
        entries = read_flowers(flowers_json)
        estimates, skipped = read_visit_flowers(
            entries, visit_uncertain=plan_config.plans_uncertain if looking
            else plan_config.visit_uncertain)
        nearest = _match(truth, entries, match_distance_m)
    watch = Stopwatch()
    obstacles = PlantObstacles.of(None if cloud is None else cloud.points,
                                  None if cloud is None else corolla if corolla is not None
                                  else flower_coloured(cloud.colors))
    plan = plan_pollination(estimates, None if cloud is None else obstacles.points,
                            plan_config, tool=tool, corolla=obstacles.corolla)
    planning_s = watch.elapsed()
    with tempfile.TemporaryDirectory() as scratch:  # a fresh flight, never a resumed one
        close = (CloseLook({f.id: f for f in estimates}, obstacles, plan_config,
                           Path(scratch) / "look", look.pose, look.colour, tool=tool)
                 if looking else None)
        timeline, flown, flight = flown_visits(plan, Path(scratch) / "flight", close,
                                               (plant_dir, look.camera) if looking else None)
    if flight_json is not None:
        write_json(flight_json, flight)
    world = world or ContactWorld(plant, config.contact, tool)
    outcomes = [judge(f, nearest.get(f.id), plan, flown, timeline, world, config, tool,
                      skipped, {e.id for e in estimates if e.uncertain})
                for f in truth]
    return {"visits": len(plan.planned), "planned_s": round(plan.duration_s, 1),
            "flown_s": round(flight["sessions"][-1]["bot_time_end"], 1)
            if flight["sessions"] else 0.0,
            "time_s": visit_times(flight, planning_s),
            "flowers": outcomes, **tally(outcomes)}


def visit_times(flight: dict, planning_s: float) -> dict:
    """A flight's time by part, summed over its visits, seconds: planning (wall clock), the
    flights (bot clock, from each lift to the way out's end, the close look's own moves
    and rests apart), the close look's moves and rests (bot clock) and its reconstruction
    and pose (wall clock); and the visits they add up over."""
    done = flight["done"]
    looks = [d["look"] for d in done if "look" in d]
    look_s = sum(look["bot_s"] for look in looks)
    return {"visits": len(done), "planning": round(planning_s, 2),
            "flight": round(sum(d["t1"] - d["t0"] for d in done) - look_s, 2),
            "look": round(look_s, 2),
            "look_compute": round(sum(look["seconds"] for look in looks), 2)}


def flown_visits(plan, scratch: Path, look: CloseLook | None = None,
                 camera: tuple[Path, SimCameraConfig] | None = None
                 ) -> tuple[Timeline, dict[int, dict], dict]:
    """`plan` flown by the executor on a simulated bot (its record in the empty folder
    `scratch`): the bot's timeline, each flower's visit (flight.json's `done` entry) and the
    flight's record. With `look`, each visit looks again first, the frames rendered of the
    plant in `camera`'s folder by its camera."""
    timeline = Timeline()
    if camera is None:
        bot = KinematicBot(observer=timeline.add)
    else:
        from flowerpose.hardware.backends.sim_bot import SimBot, SimBotConfig

        bot = SimBot([camera[0]], SimBotConfig(camera=camera[1]), observer=timeline.add)
    flight = fly_pollination(bot, plan, scratch, source={"backend": "simulated"},
                             progress=False, look=look)
    return timeline, {int(d["flower"]): d for d in flight["done"]}, flight


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


def judge(flower, detection: int | None, plan, flown: dict[int, dict],
          timeline: Timeline, world: ContactWorld, config: PollinationScoreConfig,
          tool: PollinatorTool, skipped: dict[int, str] | None = None,
          uncertain: set[int] = frozenset()) -> dict:
    """One true flower's outcome: success or the first cause of failure. `flown`: each
    visit's flight.json `done` entry; `skipped`: the detections left alone before planning
    and why (`read_visit_flowers`); `uncertain`: the planned detections whose sign was
    uncertain (a close look had to settle it)."""
    entry = {"flower": int(flower.id), "detection": detection}
    if detection is None:
        return {**entry, "outcome": "missed"}
    visit = next((v for v in plan.visits if v.flower == detection), None)
    if visit is None:
        left = (skipped or {}).get(detection) == UNCERTAIN
        return {**entry, "outcome": "uncertain" if left else "no pose"}
    if visit.status != "planned":
        return {**entry, "outcome": "unreachable", "reason": visit.reason}
    done = flown[detection]
    if "look" in done:
        entry["look"] = done["look"]["status"]
    if done["rest"] is None:  # the close look left it alone
        return {**entry, "outcome": "uncertain" if detection in uncertain else "unreachable",
                "reason": done["look"].get("why", "")}
    t0, t1 = done["t0"], done["t1"]
    rest = (done["rest"][0] + done["rest"][1]) / 2
    tip, ahead = tool_forward(HeadPose(*(v[0] for v in timeline.poses([rest]))), tool)
    miss = float(np.linalg.norm(tip - np.asarray(flower.center)))
    angle = float(np.degrees(np.arccos(np.clip(-ahead @ np.asarray(flower.normal), -1, 1))))
    touches = world.fly(timeline, t0, t1, at_time=rest)
    entry.update(miss_m=round(miss, 4), angle_deg=round(angle, 2),
                 push_m=round(touches.push_m, 4), contact_steps=touches.steps)
    pistil = _of(world, touches.swab_patches, PISTIL_PARTS, flower.id)
    if miss > config.touch_radius_m:
        return {**entry, "outcome": "pose off",
                "reason": f"the swab rests {miss * 1000:.0f} mm from the centre"}
    if angle > config.max_angle_deg:
        return {**entry, "outcome": "pose off",
                "reason": f"the approach is {angle:.0f} degrees off the axis"}
    if not pistil:
        return {**entry, "outcome": "pose off", "reason": "the swab does not touch the pistil"}
    others = sorted({int(f) for f in world.patches.flower[_others(world, touches, flower.id)]})
    if others:
        return {**entry, "outcome": "collision", "reason": f"touches flower {others[0]}"}
    if touches.push_m > config.max_push_m:
        return {**entry, "outcome": "collision",
                "reason": f"pushes a leaf {touches.push_m * 1000:.0f} mm aside"}
    return {**entry, "outcome": "success"}


def _of(world: ContactWorld, patches: np.ndarray, parts: list[int], flower: int) -> bool:
    """Whether any of `patches` is one of `parts` of `flower`."""
    return bool(np.any(np.isin(world.patches.part[patches], parts)
                       & (world.patches.flower[patches] == flower)))


def _others(world: ContactWorld, touches: Touches, flower: int) -> np.ndarray:
    """The touched patches that are petals, anthers or receptacle of another flower."""
    patches = touches.patches
    part, owner = world.patches.part[patches], world.patches.flower[patches]
    return patches[np.isin(part, OTHER_FLOWER_PARTS) & (owner >= 0) & (owner != flower)]


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


def write_success_plot(path: Path, rows: list[dict], curve: list[dict] = (),
                       cone_deg: float | None = None, max_angle_deg: float | None = None,
                       before_after: tuple[dict | None, dict] | None = None) -> Path:
    """pollination.png: success rate against the pose's plane error; with `curve`
    (`approach_angle.summarise_curve`), beside it success against the approach's angle off
    the true axis, the planner's cone and the score's angle limit marked; with
    `before_after` (the summaries from the scan's poses alone and with the close look),
    the flowers by outcome before and after the close look."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from flowerpose.atomic import write_file

    used = [r for r in rows if r["flowers"]]
    if not used:
        raise InputError(path, "no detected flower to plot")
    curve = [r for r in curve if r["planned"]]
    compared = before_after if before_after is not None and before_after[0] else None
    ratios = [3] + ([2] if curve else []) + ([2] if compared else [])
    figure, axes = plt.subplots(1, len(ratios), figsize=(4 + 3.5 * len(ratios), 3.5),
                                squeeze=False, gridspec_kw={"width_ratios": ratios})
    axis = axes[0][0]
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
    if curve:
        _plot_curve(axes[0][1], curve, cone_deg, max_angle_deg)
    if compared:
        _plot_before_after(axes[0][-1], *compared)
    figure.tight_layout()
    write_file(path, lambda tmp: figure.savefig(tmp, format="png", dpi=120))
    plt.close(figure)
    return path


def _plot_curve(axis, curve: list[dict], cone_deg: float | None,
                max_angle_deg: float | None) -> None:
    """Success against the approach's angle off the true axis, with the planned count at
    each point."""
    angles = [r["angle_deg"] for r in curve]
    rates = [r["success_rate"] for r in curve]
    axis.plot(angles, rates, "o-", color="#3f7f1f", label="of the approaches planned")
    for angle, rate, r in zip(angles, rates, curve, strict=True):
        axis.annotate(str(r["planned"]), (angle, rate), textcoords="offset points",
                      xytext=(0, 5), ha="center", fontsize=7)
    for value, style, name in ((cone_deg, "--", "the planner's cone"),
                               (max_angle_deg, ":", "the score's limit")):
        if value is not None:
            axis.axvline(value, linestyle=style, color="grey", label=name)
    axis.set_xlabel("approach off the true axis, degrees (the count above each point)")
    axis.set_ylabel("touch success (contact replay)")
    axis.set_ylim(0, 1.15)
    axis.legend(loc="lower left", fontsize=8)


def _plot_before_after(axis, before: dict, after: dict) -> None:
    """The flowers by outcome from the scan's poses alone and with the close look."""
    outcomes = ["success", *CAUSES]
    x = np.arange(len(outcomes))
    for offset, summary, colour, name in ((-0.2, before, "#c9c9c9", "the scan's poses alone"),
                                          (0.2, after, "#3f7f1f", "with the close look")):
        counts = [summary["successes"], *(summary["failures"][c] for c in CAUSES)]
        axis.bar(x + offset, counts, width=0.4, color=colour, label=name)
        for k, count in enumerate(counts):
            axis.annotate(str(count), (x[k] + offset, count), ha="center", va="bottom",
                          fontsize=7)
    axis.set_xticks(x, outcomes, rotation=30, ha="right", fontsize=8)
    axis.set_ylabel("flowers")
    axis.set_title("before and after the close look", fontsize=9)
    axis.legend(loc="upper right", fontsize=8)
