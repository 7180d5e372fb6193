"""The simulated bot flying a pollination visit through a plant, with MuJoCo contact.

The world is the bot's own model (`assets/farmbot/scene.xml`) with the plant's contact
patches added (`sim/contact.py`): leaflets and petioles on sprung ball joints, everything
else fixed. Only the pollinator (shaft and swab) and the head's collision boxes collide,
and only with the plant. The bot's joints follow the pose the executor's bot was at on its
own clock (`Timeline`), one physics step at a time; the leaves answer to the contacts.
Stepping runs only while some part of the bot is within `near_m` of the plant: elsewhere
nothing can touch, and the leaves are back at rest when the bot next comes near.
Metres, seconds, bed frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from flowerpose.hardware.flights.clearance import lever_m, shaft_points
from flowerpose.hardware.flights.scan_plan import head_points
from flowerpose.hardware.geometry import FARMBOT_ASSETS, PAPER_BOT, PAPER_TOOL, PollinatorTool
from flowerpose.hardware.kinematics import JOINT_NAMES, HeadPose, joint_positions
from flowerpose.hardware.trajectory import Timeline
from flowerpose.sim.contact import ContactConfig, PlantPatches, add_plant, plant_patches

#: The bot's geoms that touch: the pollinator's, and the head's collision boxes.
TOOL_GEOMS = ("pollinator_shaft", "pollinator_swab")
HEAD_BODIES = ("head_yaw", "head_pitch")
COLLISION_GROUP = 3  # assets/farmbot/farmbot.xml, class "collision"


@dataclass(frozen=True)
class Touches:
    """What a stretch of a flight touched.

    patches: indices (into the plant's patches) of every patch any bot geom touched.
    swab_patches: of those, the ones the swab itself touched at `at_time`'s step (empty when
        no time was asked about).
    push_m: the farthest any compliant patch (leaflet, petiole) moved from rest, metres.
    steps: physics steps run.
    """

    patches: np.ndarray
    swab_patches: np.ndarray
    push_m: float
    steps: int


def shape_tool(spec, tool: PollinatorTool) -> None:
    """Give the model's pollinator (`farmbot.xml`, body `pollinator`: the shaft, the swab
    and its tip site) the geometry of `tool`, metres in the pitch bracket's frame (x ahead
    along the optical axis, z up in the image: the offset is down)."""
    spec.body("pollinator").pos = [0.0, 0.0, -tool.offset_down_m]
    shaft = spec.geom("pollinator_shaft")
    shaft.fromto = [tool.shaft_start_m, 0.0, 0.0, tool.reach_m - tool.tip_radius_m, 0.0, 0.0]
    shaft.size = [tool.shaft_radius_m, 0.0, 0.0]
    swab = spec.geom("pollinator_swab")
    swab.pos, swab.size = [tool.reach_m, 0.0, 0.0], [tool.tip_radius_m, 0.0, 0.0]
    spec.site("pollinator_tip").pos = [tool.reach_m, 0.0, 0.0]


class ContactWorld:
    """The bot and one plant in MuJoCo, to fly stretches of a flight through."""

    def __init__(self, plant, config: ContactConfig | None = None,
                 tool: PollinatorTool = PAPER_TOOL, near_m: float = 0.01,
                 settle_s: float = 0.1):
        import mujoco

        self._mujoco = mujoco
        config = config or ContactConfig()
        self.config, self.tool, self.near_m, self.settle_s = config, tool, near_m, settle_s
        self.plant = plant
        self.patches: PlantPatches = plant_patches(plant, config)
        spec = mujoco.MjSpec.from_file(str(FARMBOT_ASSETS / "scene.xml"))
        shape_tool(spec, tool)
        spec.option.gravity = [0.0, 0.0, 0.0]  # the generated shape is the leaves' rest shape
        spec.option.timestep = config.timestep_s
        names = add_plant(spec, self.patches, config)
        self.model = model = spec.compile()
        self.data = mujoco.MjData(model)
        self._patch_ids = np.array([model.geom(n).id for n in names])
        self._patch_of = np.full(model.ngeom, -1)
        self._patch_of[self._patch_ids] = np.arange(len(names))
        head = [model.body(b).id for b in HEAD_BODIES]
        bot = [model.geom(n).id for n in TOOL_GEOMS] + [
            g for g in range(model.ngeom)
            if model.geom_bodyid[g] in head and model.geom_group[g] == COLLISION_GROUP]
        model.geom_contype[:] = 0
        model.geom_conaffinity[:] = 0
        model.geom_contype[bot] = 1
        model.geom_conaffinity[self._patch_ids] = 1
        # The broadphase filters by bodies first, on flags compiled from their geoms.
        for flags, body_flags in ((model.geom_contype, model.body_contype),
                                  (model.geom_conaffinity, model.body_conaffinity)):
            body_flags[:] = 0
            np.bitwise_or.at(body_flags, model.geom_bodyid, flags)
        self._swab = model.geom("pollinator_swab").id
        self._qpos = np.array([model.jnt_qposadr[model.joint(j).id] for j in JOINT_NAMES])
        self._qvel = np.array([model.jnt_dofadr[model.joint(j).id] for j in JOINT_NAMES])
        compliant = np.isin(self.patches.piece, list(self.patches.bases))
        self._compliant_ids = self._patch_ids[compliant]
        hulls = self.patches.hulls
        self._leaf_tree = (cKDTree(np.vstack([hulls[k] for k in np.flatnonzero(compliant)]))
                           if compliant.any() else None)
        self._fixed_tree = (cKDTree(np.vstack([hulls[k] for k in np.flatnonzero(~compliant)]))
                            if (~compliant).any() else None)
        mujoco.mj_kinematics(model, self.data)
        self._rest = self.data.geom_xpos[self._compliant_ids].copy()

    def _near(self, pose: HeadPose, tree: cKDTree | None) -> np.ndarray:
        """(N,) whether the pollinator at each pose is within near_m of the points in
        `tree`, or the head's centres (camera, pitch axis) within near_m plus its boxes'
        4 cm (all False for no tree)."""
        near = np.zeros(len(np.atleast_1d(pose.yaw)), bool)
        if tree is None:
            return near
        reach = self.near_m + 0.05  # farther than this is far: the queries stop there
        # Every point of the head and the tool lies within the lever of the UTM's centre:
        # a pose whose UTM is farther than that from the plant is far (most of a flight).
        gantry = np.atleast_2d(pose.gantry)
        close = np.flatnonzero(np.isfinite(tree.query(
            gantry, distance_upper_bound=lever_m(PAPER_BOT, self.tool) + reach)[0]))
        if not len(close):
            return near
        pose = HeadPose(gantry[close], np.atleast_1d(pose.yaw)[close],
                        np.atleast_1d(pose.pitch)[close])
        # Points half near_m apart: one touching the shaft is within near_m of one of them.
        tool = shaft_points(pose, self.tool, PAPER_BOT, self.near_m / 2)
        head = head_points(pose)
        tool_gap = tree.query(tool.reshape(-1, 3), distance_upper_bound=reach)[0]
        head_gap = tree.query(head.reshape(-1, 3), distance_upper_bound=reach)[0]
        tool_gap, head_gap = tool_gap.reshape(tool.shape[:-1]), head_gap.reshape(head.shape[:-1])
        near[close] = (tool_gap.min(axis=-1) < self.near_m) | (head_gap.min(axis=-1) < reach)
        return near

    def fly(self, timeline: Timeline, t0: float, t1: float,
            at_time: float | None = None) -> Touches:
        """Fly the bot's poses between bot-clock t0 and t1 (seconds) through the plant,
        the leaves starting at rest; `at_time`: also say what the swab touches then.

        Near the fixed parts alone, the bot's pose is checked every 10 ms of its clock
        that it moved (under a millimetre at FarmBot's speeds); near a leaflet or
        petiole, the world is stepped at `timestep_s` and the leaves give way."""
        mujoco, model, data = self._mujoco, self.model, self.data
        coarse = np.arange(t0, t1, 0.01)
        if at_time is not None:
            coarse = np.union1d(coarse, [at_time])
        if not len(coarse):
            return Touches(np.zeros(0, int), np.zeros(0, int), 0.0, 0)
        poses = HeadPose(*timeline.poses(coarse))
        q = joint_positions(poses)
        moved = np.r_[True, np.abs(np.diff(q, axis=0)).max(axis=1) > 1e-12]
        asked = coarse == at_time
        touched: set[int] = set()
        swab: set[int] = set()
        mujoco.mj_resetData(model, data)
        checks = np.flatnonzero(self._near(poses, self._fixed_tree) & (moved | asked))
        for k in checks:
            data.qpos[self._qpos] = q[k]
            mujoco.mj_kinematics(model, data)
            mujoco.mj_collision(model, data)
            self._record(touched, swab if asked[k] else None)
        push, steps = 0.0, 0
        for start, end in _windows(coarse, self._near(poses, self._leaf_tree), 0.02):
            times = np.arange(start, end, self.config.timestep_s)
            if at_time is not None and start <= at_time < end:
                times = np.union1d(times, [at_time])
            q = joint_positions(HeadPose(*timeline.poses(times)))
            velocity = np.gradient(q, times, axis=0) if len(times) > 1 else np.zeros_like(q)
            mujoco.mj_resetData(model, data)
            for k in self._steps(times, q, at_time):
                data.qpos[self._qpos] = q[k]
                data.qvel[self._qvel] = velocity[k]
                data.ctrl[:len(JOINT_NAMES)] = q[k]  # the actuators hold what is set
                mujoco.mj_step(model, data)
                steps += 1
                self._record(touched, swab if times[k] == at_time else None)
                moved_by = data.geom_xpos[self._compliant_ids] - self._rest
                push = max(push, float(np.sqrt((moved_by ** 2).sum(1)).max(initial=0.0)))
        return Touches(np.array(sorted(touched), int), np.array(sorted(swab), int), push,
                       steps)

    def _record(self, touched: set[int], swab: set[int] | None) -> None:
        """Add the patches in contact now (penetrating) to `touched`, and those the swab
        touches to `swab` (unless None)."""
        data = self.data
        if not data.ncon:
            return
        pairs = data.contact.geom[:data.ncon]
        deep = data.contact.dist[:data.ncon] < 0
        hits = self._patch_of[pairs].max(axis=1)  # a pair holds one patch
        touched.update(hits[deep & (hits >= 0)].tolist())
        if swab is not None:
            swab.update(hits[deep & (hits >= 0) & (pairs == self._swab).any(axis=1)].tolist())

    def _steps(self, times: np.ndarray, q: np.ndarray, at_time: float | None) -> np.ndarray:
        """Indices of `times` to step at: all while the bot moves, and `settle_s` of each
        stop (the leaves have come to rest by then; nothing changes until it moves on),
        and `at_time`."""
        still = np.r_[False, np.abs(np.diff(q, axis=0)).max(axis=1) < 1e-12]
        # Steps since the bot last moved, counted along each still stretch.
        run = np.arange(len(still)) - np.maximum.accumulate(np.where(~still,
                                                                     np.arange(len(still)), 0))
        keep = run * self.config.timestep_s <= self.settle_s
        if at_time is not None:
            keep |= times == at_time
        return np.flatnonzero(keep)


def _windows(times: np.ndarray, near: np.ndarray, pad_s: float) -> list[tuple[float, float]]:
    """The stretches of `times` where `near` holds, each padded by pad_s, merged."""
    windows: list[list[float]] = []
    step = times[1] - times[0] if len(times) > 1 else 0.0
    for t in times[near]:
        if windows and t - pad_s <= windows[-1][1]:
            windows[-1][1] = t + step + pad_s
        else:
            windows.append([t - pad_s, t + step + pad_s])
    return [(max(a, times[0]), min(b, times[-1] + step)) for a, b in windows]
