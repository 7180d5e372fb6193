"""Pollination visits planned from flower poses and checked before the bot moves.

A visit brings the pollinator's swab (`geometry.PollinatorTool`, `kinematics.tool_at`) to a
flower's centre along the flower's axis: from the top of Z it descends to a pre-approach
pose `standoff_m` out along the axis, moves straight in until the swab touches the centre,
rests, and retreats the same way. Where the straight descent is blocked (a leaf over the
flower), the head comes down a path round the foliage instead (`approach_path`, OMPL), and
climbs back up it after the visit. Every pose is checked against the gantry's travel, the
servos' range and the soil clearance (naming the limit that fails), and every move against
the plant's cloud: the head's housings and the shaft keep `clearance_m` from it, except
that the shaft may pass through the target flower's own corolla (its points of a flower's
colour within `touch_radius_m` of the centre). A flower whose axis cannot be taken is
approached along the nearest direction within `cone_deg` of it that can, or reported
unreachable with the reason. The visits are ordered to keep travel short (nearest
neighbour, then 2-opt), on FarmBot's motion profile; a visit whose travel at the top of Z
would pass the plant (a tall plant, a long tool) is left out with that reason.

Frames, units: bed frame, metres, radians; normals point out of the corolla's open face.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from scipy.spatial import cKDTree

from flowerpose.config import require
from flowerpose.hardware.flights.approach_path import joint_state, plan_path
from flowerpose.hardware.flights.clearance import checked_poses, gap
from flowerpose.hardware.geometry import PAPER_BOT, BotGeometry, PollinatorTool
from flowerpose.hardware.kinematics import (
    HeadPose,
    UnreachableError,
    check_reachable,
    tool_at,
    tool_points,
)
from flowerpose.hardware.motion import (
    END_OF_MOVE_S,
    MotionProfile,
    move_duration,
    move_trajectory,
)
from flowerpose.pipeline.close_look import CloseLookConfig
from flowerpose.pipeline.colour import ColourConfig
from flowerpose.pipeline.pose import PoseConfig


@dataclass(frozen=True)
class PollinateConfig:
    """How a flower is visited, metres and degrees."""

    standoff_m: float = 0.061
    """The pre-approach pose: the swab this far out along the flower's axis. Farther out,
    the head reaches it (and leaves it) clear of the foliage round the flower, which the
    cloud holds only where the scan saw it. Chosen with the pollinator's geometry by `tune
    --task pollinate` (the 12 cm tool's was 0.065). With that tool it mattered little: on
    the planner's ceiling (true poses, 10 field plants, seeds 0-9) 0.045 and 0.085
    pollinated 106 of 134 as 0.065 did (3 and 2 flowers won, as many lost); on estimated
    poses 0.05 pushed leaves over 1 cm in 2 visits (seeds 0-9) and 3 (seeds 100-109) where
    0.065 pushed none."""
    press_m: float = 0.002
    """How far past the flower's centre the swab goes, to touch it with a little force."""
    dwell_s: float = 1.0
    """Seconds the swab rests on the flower."""
    cone_deg: float = 55.0
    """Largest angle between an approach and the flower's axis, for a flower whose axis
    cannot be taken (out of reach, or blocked): 5 degrees inside the angle a pollinated
    flower may be approached at (`pollination.max_angle_deg`, 60), for the pose's own
    error. The nearest direction that is clear is taken, so a wide cone costs only the
    flowers it makes reachable (10 realistic plants, seeds 0-9, the corolla not yet bounded
    by the flower's radius: 98 of 134 pollinated with a 40-degree cone, 106 with 55)."""
    cone_step_deg: float = 5.0
    """Angle between the rings of directions tried inside that cone."""
    cone_azimuths: int = 16
    """Directions tried on each ring. Measured on the planner's ceiling (true poses, 10
    field plants, seeds 0-9, flown and judged in contact): 8 directions pollinated 106 of
    134, 16 109 (3 won, none lost; a flower's plan costs up to twice the checks where its
    axis is blocked), 16 with rings every 2.5 degrees 109 as well."""
    clearance_m: float = 0.01
    """Least distance between the plant's points and the head's housings (its two servo
    boxes, `kinematics.head_boxes`) or the shaft anywhere along a visit. Less does not
    reach more: with 0.005 (the planner's ceiling, 10 field plants, seeds 0-9) 5 more
    flowers were planned and 5 others lost, 4 of them to leaves pushed 15-65 mm aside
    (a field cloud has holes where a leaf is). Below `calyx_radius_m`, or the target's own
    sepals block every visit (a field plant, seed 1: 9 of 11 planned at 10 mm, none at 15)."""
    touch_radius_m: float = 0.02
    """The target flower's own points (of a flower's colour, when the cloud's colours are
    given) within this distance of its centre may touch the shaft and swab (its corolla);
    for a flower of known radius, within its radius and `rim_margin_m`, where that is less,
    so a neighbour's petals that reach inside this distance stay obstacles (on 10 realistic
    plants, 5 of 8 failed visits touched such a neighbour)."""
    rim_margin_m: float = 0.003
    """How far beyond a flower's known radius its own corolla may reach (a petal's curl and
    the radius's error)."""
    visit_uncertain: bool = False
    """Visit a flower whose normal's sign the pose stage could not settle (flowers.json
    `uncertain`: a near tie of its votes, a pistil of a few points, or none). Left alone by
    default: a turned normal sends the swab at the back of the flower."""
    calyx_radius_m: float = 0.012
    """The target's points within this distance of its centre, whatever their colour, are
    its own too: the green sepals and stalk right behind the receptacle, where the swab
    presses."""
    straight_within_m: float = 0.002
    """The approach keeps within this distance of the straight line to the centre. FarmBot
    runs each axis on its own profile, so a diagonal move bends: it is cut into shorter
    moves until it does not bend more."""
    soil_margin_m: float = 0.005
    """Least height of the swab above the soil."""
    samples_per_move: int = 12
    """Fewest poses checked along each move (more where `check_step_m` asks)."""
    check_step_m: float = 0.005
    """Largest distance any point of the head or the pollinator moves between two poses
    checked along a move, and between two points checked along the shaft
    (`flights/clearance.py`): at most `clearance_m`, so that a point touching them lies
    within about half of it from a checked place and fails the check. Twelve poses a move
    whatever its length missed a neighbour's petal or a leaf between two of them (the
    planner's ceiling, 10 field plants, seeds 0-9, a 15 cm tool: 3 of its 7 collisions)."""
    path_checks: int = 4000
    """Most clearance tests the search for a path round the plant may make for one approach
    direction, where the straight descent to it is blocked (0: straight descents only). A
    count, not a time, so a plan is the same on any machine (a resumed flight re-plans it)."""
    path_tries: int = 3
    """Approach directions (the axis first, then the cone's) a path is searched for, per
    flower: a flower whose pre-approach pose is walled in costs each try's whole search."""
    path_box_m: float = 0.15
    """The path's search box: this far beyond the pre-approach pose across the bed and below
    it, up to the top of Z, within the gantry's travel."""
    path_bend_m: float = 0.01
    """The path's search keeps this much more than `clearance_m` from the plant: room for
    the bend of a FarmBot move (each axis on its own profile), so most of the path's
    segments fly as one move (with 2 mm, a path round a leaf took 23 moves, with 10 mm 7)."""
    path_step_m: float = 0.005
    """Spacing of the clearance tests along the path's segments while searching (an angle
    counts as `approach_path.ANGLE_LEVER_M` metres a radian); each segment is then checked
    as flown (`check_step_m`)."""

    tool: PollinatorTool = field(default_factory=PollinatorTool)
    """The pollinator on the head (`geometry.PollinatorTool`): where its swab is, how long
    and how far under the camera its shaft runs. The plans, the flights and the contact
    replay all take its geometry from here. A longer shaft reaches lower flowers (the
    gantry's Z travel ends 0.218 m above the soil); a tip less than 18.75 degrees under the
    lens's axis (its offset against its reach past the lens, 8 cm) shows in the frames."""
    look: CloseLookConfig = field(default_factory=CloseLookConfig)
    """The close look before each touch (`flights/close_look.py`): a few frames from near
    the pre-approach pose refine the flower's centre and axis, and the last approach is
    planned again from them."""

    def __post_init__(self):
        for name in ("standoff_m", "clearance_m", "touch_radius_m", "straight_within_m",
                     "cone_step_deg", "path_box_m", "path_step_m", "path_tries", "path_bend_m",
                     "rim_margin_m", "cone_azimuths", "check_step_m"):
            require(getattr(self, name) > 0, f"pollinate.{name}",
                    f"must be positive, got {getattr(self, name)}")
        require(self.path_checks >= 0, "pollinate.path_checks", "must be 0 or more, got "
                f"{self.path_checks}")
        require(self.check_step_m <= self.clearance_m, "pollinate.check_step_m",
                f"must be at most pollinate.clearance_m ({self.clearance_m:g}), got "
                f"{self.check_step_m:g}: a point between two checked places could touch")
        require(self.clearance_m < self.calyx_radius_m, "pollinate.clearance_m",
                f"must be below pollinate.calyx_radius_m ({self.calyx_radius_m:g}), got "
                f"{self.clearance_m:g}: the target's own sepals would block every visit")
        require(0 <= self.cone_deg < 90, "pollinate.cone_deg",
                f"must be 0 or more, below 90, got {self.cone_deg}")

    @property
    def plans_uncertain(self) -> bool:
        """Whether flowers whose sign is uncertain are planned: when asked, or when a close
        look settles it first (`look.visit_uncertain`)."""
        return self.visit_uncertain or bool(self.look.views and self.look.visit_uncertain)


@dataclass(frozen=True)
class PollinateSettings:
    """What `flowerpose pollinate` reads: the planner's settings and the colour model that
    tells a target's own corolla from the rest of the plant, the pipeline's (so a profile's
    or `--set colour.*` reaches the planner as it reaches the detector)."""

    pollinate: PollinateConfig = field(default_factory=PollinateConfig)
    """The planner (`plan_pollination`)."""
    colour: ColourConfig = field(default_factory=ColourConfig)
    """The colour model (`pipeline.colour`)."""
    pose: PoseConfig = field(default_factory=PoseConfig)
    """The pose stage (`pipeline.pose`), which estimates a flower's pose again from the
    close look's frames."""


@dataclass(frozen=True)
class Flower:
    """A flower to visit: its id (flowers.json's), centre (3,) and unit normal (3,),
    metres, bed frame, and its radius where known (metres)."""

    id: int
    center: np.ndarray
    normal: np.ndarray
    radius: float | None = None
    uncertain: bool = False
    """The pose stage could not settle the normal's sign (flowers.json `uncertain`): only a
    close look that settles it lets the swab touch."""


@dataclass(frozen=True)
class Visit:
    """One flower's visit, or why there is none."""

    flower: int
    status: Literal["planned", "unreachable"]
    reason: str = ""
    """Unreachable: the limit that fails along the flower's axis (and that no direction in
    the cone does better)."""
    approach: np.ndarray | None = None
    """(3,) unit direction the swab moves in to touch, bed frame."""
    off_axis_deg: float | None = None
    """Angle between the approach and the flower's axis (0: along it)."""
    pre: HeadPose | None = None
    """The pre-approach pose, `standoff_m` out along the approach."""
    touch: HeadPose | None = None
    """The pose that touches the centre."""
    approach_moves: list[HeadPose] = field(default_factory=list)
    """The gantry positions (one pose each) the approach is cut into, the last `touch`."""
    path: list[HeadPose] = field(default_factory=list)
    """The way down from the top of Z above `pre` to it, where the straight descent is
    blocked: waypoints, each flown as a gantry move with the head still and then the head's
    turn, the last `pre` (empty: the straight descent)."""

    def to_json(self) -> dict:
        entry = {"flower": self.flower, "status": self.status}
        if self.status != "planned":
            return {**entry, "reason": self.reason}
        return {**entry, "off_axis_deg": round(float(self.off_axis_deg), 2),
                "approach": [round(float(v), 6) for v in self.approach],
                "pre_gantry_m": self.pre.gantry.round(6).tolist(),
                "touch_gantry_m": self.touch.gantry.round(6).tolist(),
                "yaw_rad": round(float(self.pre.yaw), 6),
                "pitch_rad": round(float(self.pre.pitch), 6),
                "approach_moves": len(self.approach_moves),
                "path": [[round(float(v), 6) for v in joint_state(p)] for p in self.path]}


@dataclass(frozen=True)
class Move:
    """One gantry move of the plan, or a rest: what it is and the pose it ends at."""

    kind: Literal["lift", "travel", "descend", "approach", "dwell", "retreat", "climb"]
    flower: int
    pose: HeadPose


@dataclass(frozen=True)
class PollinationPlan:
    """Visits in the order flown (the planned ones; then the unreachable), and the moves."""

    visits: list[Visit]
    moves: list[Move]
    duration_s: float
    """Moves, their ends and the rests on the motion profile, seconds."""
    config: PollinateConfig

    @property
    def planned(self) -> list[Visit]:
        return [v for v in self.visits if v.status == "planned"]

    def to_json(self) -> dict:
        from dataclasses import asdict

        return {"visits": [v.to_json() for v in self.visits],
                "planned": len(self.planned), "unreachable": len(self.visits)
                - len(self.planned), "moves": len(self.moves),
                "duration_s": round(self.duration_s, 2), "config": asdict(self.config)}


def plan_pollination(flowers: list[Flower], obstacles: np.ndarray | None,
                     config: PollinateConfig = PollinateConfig(),
                     geometry: BotGeometry = PAPER_BOT, tool: PollinatorTool | None = None,
                     profile: MotionProfile | None = None,
                     start: np.ndarray | None = None,
                     corolla: np.ndarray | None = None) -> PollinationPlan:
    """Plan a visit to each flower, in a short order, from the gantry at `start` ((3,) UTM,
    metres, bed frame; default home). obstacles: (M, 3) points of the plant (its cloud),
    metres, bed frame, or None to check reach alone. corolla: (M,) bool, the obstacles of a
    flower's colour (`pipeline.colour.flower_coloured`): only they may be a target's own
    corolla, so a leaf beside the flower stays an obstacle; None: any point near it.
    tool: the pollinator; None: `config.tool`."""
    profile = profile or MotionProfile()
    tool = tool or config.tool
    start = geometry.home if start is None else np.asarray(start, np.float64)
    plant = PlantObstacles.of(obstacles, corolla)
    visits = [plan_visit(f, plant, config, geometry, tool, profile) for f in flowers]
    while True:
        planned = [v for v in visits if v.status == "planned"]
        ordered = [planned[k] for k in _short_order(planned, start, geometry, profile)]
        moves = plan_moves(ordered, start, geometry)
        blocked = _blocked_travel(moves, plant.tree, config, geometry, tool, profile)
        if blocked is None:
            break
        flower, distance = blocked  # left out, and the rest planned again without it
        visits = [Visit(v.flower, "unreachable", f"the travel to it at the top of Z passes "
                        f"{distance * 1000:.0f} mm from the plant: the head, turned for "
                        "this visit, hangs lower than the gantry can clear the plant")
                  if v.flower == flower else v for v in visits]
    duration = sum(move_duration(a.pose.gantry, b.pose.gantry, profile) + END_OF_MOVE_S
                   for a, b in zip(moves, moves[1:], strict=False) if b.kind != "dwell")
    duration += config.dwell_s * len(ordered)
    unreachable = [v for v in visits if v.status != "planned"]
    return PollinationPlan(ordered + unreachable, moves, float(duration), config)


@dataclass(frozen=True)
class PlantObstacles:
    """The plant's cloud as the planner checks a visit against it: points (M, 3), metres,
    bed frame; `corolla` (M,) bool, those of a flower's colour (a target's own corolla may
    be only these); their tree (None without points: reach alone)."""

    points: np.ndarray
    corolla: np.ndarray
    tree: cKDTree | None

    @classmethod
    def of(cls, obstacles: np.ndarray | None, corolla: np.ndarray | None = None
           ) -> PlantObstacles:
        """`plan_pollination`'s obstacles and corolla (None: no cloud; every point)."""
        points = np.empty((0, 3)) if obstacles is None else np.asarray(obstacles, np.float64)
        flowery = (np.ones(len(points), bool) if corolla is None
                   else np.asarray(corolla, bool).reshape(len(points)))
        return cls(points, flowery, cKDTree(points) if len(points) else None)


def plan_visit(flower: Flower, plant: PlantObstacles, config: PollinateConfig,
               geometry: BotGeometry = PAPER_BOT, tool: PollinatorTool | None = None,
               profile: MotionProfile | None = None, here: HeadPose | None = None) -> Visit:
    """One flower's visit (`plan_pollination`'s, without the order): down from the top of
    Z, or with `here` from the head's pose near the flower (after a close look, `Visit.path`
    the move from it)."""
    return _plan_visit(flower, plant.points, plant.corolla, plant.tree, config, geometry,
                       tool or config.tool, profile or MotionProfile(), here)


def tilted(normal: np.ndarray, angle_deg, azimuth_rad) -> np.ndarray:
    """Unit directions `angle_deg` off the unit `normal` (3,), turned `azimuth_rad` about it
    from a fixed reference across it: (3,) for scalars, (K, 3) for (K,) arrays."""
    normal = np.asarray(normal, np.float64) / np.linalg.norm(normal)
    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(normal, helper)
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    theta = np.radians(np.asarray(angle_deg, np.float64))[..., None]
    phi = np.asarray(azimuth_rad, np.float64)[..., None]
    return np.cos(theta) * normal + np.sin(theta) * (np.cos(phi) * u + np.sin(phi) * v)


def _directions(normal: np.ndarray, config: PollinateConfig) -> tuple[np.ndarray, np.ndarray]:
    """(K, 3) unit axes to approach along (the flower's own first, then rings further off
    it) and (K,) their angles off it, degrees."""
    rings = np.arange(config.cone_step_deg, config.cone_deg + 1e-9, config.cone_step_deg)
    azimuths = 2 * np.pi * np.arange(config.cone_azimuths) / config.cone_azimuths
    theta = np.repeat(rings, len(azimuths))
    off = tilted(normal, theta, np.tile(azimuths, len(rings))).reshape(-1, 3)
    return (np.vstack([normal / np.linalg.norm(normal), off]),
            np.concatenate([[0.0], theta]))


def _plan_visit(flower: Flower, points: np.ndarray, corolla: np.ndarray,
                tree: cKDTree | None, config: PollinateConfig, geometry: BotGeometry,
                tool: PollinatorTool, profile: MotionProfile,
                here: HeadPose | None = None) -> Visit:
    """The visit along the flower's axis, else along the nearest direction in the cone
    that is reachable and clear: down the straight descent, or where that is blocked a path
    round the plant (`path_tries` directions at most); else why not. With `here` (the head
    near the flower already, after a close look) the way to the pre-approach pose is the
    move from `here` instead (`Visit.path`: its pieces, the last the pre-approach pose)."""
    axes, angles = _directions(flower.normal, config)
    distance = np.linalg.norm(points - flower.center, axis=1)
    own = (config.touch_radius_m if flower.radius is None
           else min(config.touch_radius_m, flower.radius + config.rim_margin_m))
    near_flower = ((corolla & (distance <= own))
                   | (distance <= config.calyx_radius_m))
    others = cKDTree(points[~near_flower]) if (~near_flower).any() else None
    first_reason, tries = "", 0
    blocked: Counter[str] = Counter()
    for axis, angle, flip in _candidates(axes, angles):
        approach, out = -axis, flower.center + config.standoff_m * axis
        pre = tool_at(out, approach, tool, geometry, flip)
        if flip and _same_solution(pre, tool_at(out, approach, tool, geometry)):
            continue
        touch = tool_at(flower.center - config.press_m * axis, approach, tool, geometry, flip)
        reason, kind = _unreachable(pre, touch, config, geometry, tool), "out of reach"
        if not reason:
            steps = _straight(pre, touch, config, profile)
            reason = _approach_blocked(pre, steps, tree, others, config, geometry, tool,
                                       profile)
            kind = ("the camera head meets the plant on the way in"
                    if reason.startswith("the camera head")
                    else "the pollinator meets the plant on the way in")
        if not reason and here is not None:
            path = ([pre] if tree is None
                    else flyable(here, pre, tree, config, geometry, tool, profile))
            kind = "the move from the close look's pose is blocked"
            if path is not None:
                return Visit(flower.id, "planned", "", approach, float(angle), pre, touch,
                             steps, path)
            reason = "no clear move to it from the close look's pose"
        elif not reason:
            reason = _descent_blocked(pre, tree, config, geometry, tool, profile)
            kind = "the way down is blocked (no path searched)"
            path: list[HeadPose] = []
            if reason and tries < config.path_tries and config.path_checks:
                tries += 1
                path = _route(pre, tree, config, geometry, tool, profile, seed=flower.id)
                kind = "the way down is blocked and no path round the plant was found"
                reason = "" if path else (f"{reason}, and no path round the plant was found "
                                          f"in {config.path_checks} clearance tests")
            if not reason:
                return Visit(flower.id, "planned", "", approach, float(angle), pre, touch,
                             steps, path)
        first_reason = first_reason or reason
        blocked[kind] += 1
    tally = ", ".join(f"{count} {kind}" for kind, count in blocked.most_common())
    return Visit(flower.id, "unreachable",
                 f"along its axis: {first_reason}; of the {sum(blocked.values())} approaches "
                 f"within {config.cone_deg:g} degrees of it (the head either way up): {tally}")


def _candidates(axes: np.ndarray, angles: np.ndarray):
    """(axis, angle, flip) in the order tried: each direction with the head's usual
    solution, then upside down (`kinematics.tool_at`'s flip)."""
    for axis, angle in zip(axes, angles, strict=True):
        yield axis, angle, False
        yield axis, angle, True


def _same_solution(a: HeadPose, b: HeadPose) -> bool:
    """Whether two poses put the servos at the same angles."""
    return bool(np.allclose(joint_state(a)[3:], joint_state(b)[3:]))


def _unreachable(pre: HeadPose, touch: HeadPose, config: PollinateConfig,
                 geometry: BotGeometry, tool: PollinatorTool) -> str:
    """The limits the visit's poses break ("" when none)."""
    for name, pose in (("pre-approach", pre), ("touch", touch)):
        try:
            check_reachable(pose, geometry, name=name)
        except UnreachableError as error:
            return f"the {name} pose is {error.problem}"
        swab = tool_points(pose, tool, geometry)[..., 2].min()
        if swab < config.soil_margin_m:
            return f"the {name} pose puts the pollinator {swab * 1000:.0f} mm above the soil"
    return ""


def _straight(pre: HeadPose, touch: HeadPose, config: PollinateConfig,
              profile: MotionProfile) -> list[HeadPose]:
    """The approach from `pre` to `touch` as moves short enough that each keeps within
    `straight_within_m` of the line: the gantry positions they end at."""
    start, end = pre.gantry, touch.gantry
    line = end - start
    for count in (1, 2, 4, 8, 16, 32, 64):
        ends = start + np.outer(np.arange(1, count + 1) / count, line)
        bend = max(_bend(a, b, start, line, profile)
                   for a, b in zip(np.vstack([start, ends[:-1]]), ends, strict=True))
        if bend <= config.straight_within_m:
            break
    return [HeadPose(g, pre.yaw, pre.pitch) for g in ends]


def _bend(a: np.ndarray, b: np.ndarray, origin: np.ndarray, line: np.ndarray,
          profile: MotionProfile) -> float:
    """Farthest the gantry gets from the line through origin along `line`, moving a to b."""
    duration = max(move_duration(a, b, profile), 1e-9)
    path = move_trajectory(np.linspace(0.0, duration, 16), a, b, profile) - origin
    unit = line / max(np.linalg.norm(line), 1e-12)
    return float(np.linalg.norm(path - np.outer(path @ unit, unit), axis=1).max())


def _top_over(pose: HeadPose, geometry: BotGeometry) -> HeadPose:
    """The pose with the gantry at the top of Z above where `pose` is."""
    gantry = pose.gantry.copy()
    gantry[2] = geometry.gantry_max[2]
    return HeadPose(gantry, pose.yaw, pose.pitch)


def _too_close(poses: HeadPose, tree: cKDTree, shaft_tree: cKDTree | None, name: str,
               config: PollinateConfig, geometry: BotGeometry, tool: PollinatorTool) -> str:
    """Where `poses` (the move called `name`) come within `clearance_m` of the plant ("" if
    nowhere)."""
    least, part = gap(poses, tree, shaft_tree, config.clearance_m, geometry, tool,
                      config.check_step_m)
    if least >= config.clearance_m:
        return ""
    return (f"the {part} passes {least * 1000:.0f} mm from the plant on the {name} (least "
            f"{config.clearance_m * 1000:.0f} mm)")


def _descent_blocked(pre: HeadPose, tree: cKDTree | None, config: PollinateConfig,
                     geometry: BotGeometry, tool: PollinatorTool,
                     profile: MotionProfile) -> str:
    """Where the straight descent from the top of Z to `pre` comes too close to the plant
    (the head and the shaft to any point; "" if never)."""
    if tree is None:
        return ""
    poses = _along(_top_over(pre, geometry), pre, config, geometry, tool, profile)
    return _too_close(poses, tree, tree, "descent", config, geometry, tool)


def _approach_blocked(pre: HeadPose, steps: list[HeadPose], tree: cKDTree | None,
                      others: cKDTree | None, config: PollinateConfig, geometry: BotGeometry,
                      tool: PollinatorTool, profile: MotionProfile) -> str:
    """Where the approach from `pre` in to the centre comes too close to the plant ("" if
    never): the head's housings to any point, the shaft to any but the target flower's own."""
    if tree is None:
        return ""
    for a, b in zip([pre, *steps[:-1]], steps, strict=True):
        poses = _along(a, b, config, geometry, tool, profile)
        reason = _too_close(poses, tree, others, "approach", config, geometry, tool)
        if reason:
            return reason
    return ""


def _route(pre: HeadPose, tree: cKDTree | None, config: PollinateConfig,
           geometry: BotGeometry, tool: PollinatorTool, profile: MotionProfile,
           seed: int) -> list[HeadPose]:
    """A way down from the top of Z above `pre` to it round the plant (`approach_path`), as
    flown: each segment cut into moves whose flight, either way, keeps `clearance_m` from
    the plant. The search keeps `path_bend_m` more, for the moves' bends. Empty when none
    is found."""
    if tree is None:
        return []
    start = _top_over(pre, geometry)

    def clear(pose: HeadPose) -> bool:
        # The room for bends tapers to none at the pre-approach pose, which itself may keep
        # only `clearance_m`: the moves near it are short, and all are checked as flown.
        taper = min(1.0, float(np.linalg.norm(pose.gantry - pre.gantry)) / BEND_TAPER_M)
        margin = config.clearance_m + config.path_bend_m * taper
        return (not _unreachable(pose, pose, config, geometry, tool)
                and gap(pose, tree, tree, margin, geometry, tool, config.check_step_m)[0]
                >= margin)

    box = np.array([config.path_box_m, config.path_box_m])
    lower = np.concatenate([np.maximum(pre.gantry[:2] - box, geometry.gantry_min[:2]),
                            [max(pre.gantry[2] - config.path_box_m, geometry.gantry_min[2])],
                            [geometry.yaw_range_rad[0], geometry.pitch_range_rad[0]]])
    upper = np.concatenate([np.minimum(pre.gantry[:2] + box, geometry.gantry_max[:2]),
                            [geometry.gantry_max[2]],
                            [geometry.yaw_range_rad[1], geometry.pitch_range_rad[1]]])
    path = plan_path(start, pre, clear, lower, upper, config.path_checks, config.path_step_m,
                     seed)
    if path is None:
        return []
    flown: list[HeadPose] = []
    for a, b in zip([start, *path[:-1]], path, strict=True):
        pieces = flyable(a, b, tree, config, geometry, tool, profile)
        if pieces is None:
            return []
        flown.extend(pieces)
    flown[-1] = pre
    return flown


#: Distance from the pre-approach pose over which a path's room for bends
#: (`PollinateConfig.path_bend_m`) grows from none to all of it, metres.
BEND_TAPER_M = 0.05


def _along(a: HeadPose, b: HeadPose, config: PollinateConfig, geometry: BotGeometry,
           tool: PollinatorTool, profile: MotionProfile) -> HeadPose:
    """The poses checked along the move from a to b (`clearance.checked_poses`)."""
    return checked_poses(a, b, profile, config.check_step_m, geometry, tool,
                         config.samples_per_move)


def _flown(a: HeadPose, b: HeadPose, config: PollinateConfig, geometry: BotGeometry,
           tool: PollinatorTool, profile: MotionProfile) -> HeadPose:
    """The poses the executor takes from a to b, as checked: the gantry on its motion
    profile with the head still, then the head's turn."""
    move = _along(a, HeadPose(b.gantry, a.yaw, a.pitch), config, geometry, tool, profile)
    turn = _along(HeadPose(b.gantry, a.yaw, a.pitch), b, config, geometry, tool, profile)
    return HeadPose(np.vstack([move.gantry, turn.gantry]),
                    np.concatenate([move.yaw, turn.yaw]),
                    np.concatenate([move.pitch, turn.pitch]))


def flyable(a: HeadPose, b: HeadPose, tree: cKDTree, config: PollinateConfig,
             geometry: BotGeometry, tool: PollinatorTool,
             profile: MotionProfile) -> list[HeadPose] | None:
    """The segment from a to b (joint space) cut into the fewest equal moves (up to 64)
    whose flight down and back up keeps `clearance_m` from the plant and within the bot's
    limits: the poses they end at, the last b; None where no cut does."""
    ends = np.array([joint_state(a), joint_state(b)])
    for count in (1, 2, 4, 8, 16, 32, 64):
        share = np.arange(count + 1)[:, None] / count
        poses = [HeadPose(s[:3], s[3], s[4]) for s in ends[0] + share * (ends[1] - ends[0])]
        fine = True
        for u, v in zip(poses, poses[1:], strict=False):
            both = [_flown(u, v, config, geometry, tool, profile),
                    _flown(v, u, config, geometry, tool, profile)]
            if any(_unreachable(p, p, config, geometry, tool)
                   or gap(p, tree, tree, config.clearance_m, geometry, tool,
                          config.check_step_m)[0] < config.clearance_m for p in both):
                fine = False
                break
        if fine:
            return poses[1:]
    return None


def _transfer_cost(a: np.ndarray, b: np.ndarray, profile: MotionProfile) -> float:
    """Seconds from the top of Z over a to the top of Z over b, down to b's height (the
    part of a transfer that depends on the order)."""
    top = max(a[2], b[2])
    return (move_duration(a, [a[0], a[1], top], profile)
            + move_duration([a[0], a[1], top], [b[0], b[1], top], profile)
            + move_duration([b[0], b[1], top], b, profile))


def _short_order(visits: list[Visit], start: np.ndarray, geometry: BotGeometry,
                 profile: MotionProfile) -> list[int]:
    """An order of the visits that keeps transfers short: nearest neighbour from `start`,
    then 2-opt. A plant has tens of flowers, so the O(n^3) 2-opt takes milliseconds."""
    if not visits:
        return []
    places = [start] + [v.pre.gantry for v in visits]
    n = len(places)
    cost = np.array([[_transfer_cost(places[i], places[j], profile) for j in range(n)]
                     for i in range(n)])
    order, left = [0], set(range(1, n))
    while left:
        nearest = min(left, key=lambda j: cost[order[-1], j])
        order.append(nearest)
        left.remove(nearest)
    improved = True
    while improved:
        improved = False
        for i in range(1, n - 1):
            for j in range(i + 1, n):
                after = order[j + 1] if j + 1 < n else None
                old = cost[order[i - 1], order[i]] + (cost[order[j], after] if after else 0)
                new = cost[order[i - 1], order[j]] + (cost[order[i], after] if after else 0)
                if new < old - 1e-9:
                    order[i:j + 1] = order[i:j + 1][::-1]
                    improved = True
    return [k - 1 for k in order[1:]]


def plan_moves(visits: list[Visit], start: np.ndarray, geometry: BotGeometry = PAPER_BOT
               ) -> list[Move]:
    """The moves of the visits in order: up to the top of Z, across, down to the
    pre-approach pose (straight, or along the visit's path), in to the centre, a rest, back
    out (and up the path). The head turns at the top, and at a path's waypoints."""
    moves = [Move("lift", -1, _top_over(HeadPose(start, 0.0, 0.0), geometry))]
    for visit in visits:
        here = moves[-1].pose
        if moves[-1].kind != "lift":
            moves.append(Move("lift", visit.flower, _top_over(here, geometry)))
        top = _top_over(visit.pre, geometry)
        moves.append(Move("travel", visit.flower, top))
        moves.extend(Move("descend", visit.flower, p) for p in visit.path or [visit.pre])
        moves.extend(Move("approach", visit.flower, step) for step in visit.approach_moves)
        moves.append(Move("dwell", visit.flower, visit.touch))
        # Out the way it went in, move for move: one long diagonal move would bend.
        moves.extend(Move("retreat", visit.flower, step)
                     for step in [*visit.approach_moves[-2::-1], visit.pre])
        if visit.path:  # back up the way it came
            moves.extend(Move("climb", visit.flower, p) for p in [*visit.path[-2::-1], top])
    if visits:
        moves.append(Move("lift", -1, _top_over(visits[-1].pre, geometry)))
    return moves


def _blocked_travel(moves: list[Move], tree: cKDTree | None, config: PollinateConfig,
                    geometry: BotGeometry, tool: PollinatorTool, profile: MotionProfile
                    ) -> tuple[int, float] | None:
    """The first travel at the top of Z within `clearance_m` of the plant (the head turned
    for the visit it travels to): that visit's flower and the distance, metres; or None."""
    if tree is None:
        return None
    for a, b in zip(moves, moves[1:], strict=False):
        if b.kind != "travel":
            continue
        poses = _along(a.pose, b.pose, config, geometry, tool, profile)
        distance = gap(poses, tree, tree, config.clearance_m, geometry, tool,
                       config.check_step_m)[0]
        if distance < config.clearance_m:
            return b.flower, float(distance)
    return None
