"""The close look: at each flower's pre-approach pose the head's camera looks again, and the
last approach is planned from what it sees.

A pose from a whole-plant scan is a few degrees and millimetres off, and now and then
backwards; a pollinating robot servos on a close view before it touches. At the
pre-approach pose (the swab `standoff_m` out along the flower's axis, the camera about
18 cm from the flower) the executor (`pollination_flight.py`) hands the visit to
`CloseLook.visit`, which:

1. takes `look.views` frames, the camera at the pre-approach pose's optical centre and
   `look.baseline_m` to its right and above (then left and below, for more views), each
   aimed at the flower's centre, resting `look.settle_s` before each (the autofocus); a
   view whose pose or move is out of reach or comes within `clearance_m` of the plant's
   cloud is left out;
2. writes them as a frames folder (`pipeline.frames`' format, the bot's recorded poses)
   and estimates the flower's pose from it (`pipeline.close_look.look_pose`);
3. plans the last approach again from the refined pose (`pollination_plan.plan_visit`,
   from where the head is);
4. else keeps the scan's approach, with the reason; a flower whose sign the scan left
   uncertain is then left alone, as is any whose back the close views see (the swab
   would come in behind it).

It returns the moves to fly from there until the head is back at the top of Z, and the
record of what it saw (flight.json's `look`). The same code runs on every bot: the
simulated one renders its frames with the scan's camera model (`SimCamera`), the physical
one takes them with its USB camera. Metres, radians, the bed frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from flowerpose.atomic import write_image
from flowerpose.hardware.bot import Bot
from flowerpose.hardware.bot_errors import CameraError
from flowerpose.hardware.flights.pollination_plan import (
    Flower,
    Move,
    PlantObstacles,
    PollinateConfig,
    Visit,
    flyable,
    plan_visit,
)
from flowerpose.hardware.geometry import PAPER_BOT, BotGeometry, PollinatorTool
from flowerpose.hardware.kinematics import HeadPose, forward, head_angles, look_at
from flowerpose.hardware.motion import MotionProfile
from flowerpose.jsonio import write_json
from flowerpose.pipeline.close_look import LookedPose, look_pose
from flowerpose.pipeline.colour import ColourConfig
from flowerpose.pipeline.pose import PoseConfig
from flowerpose.stopwatch import Stopwatch

#: What a close look did with a visit (flight.json `look.status`): flew the approach planned
#: from the refined pose, flew the scan's, or touched nothing.
REFINED, KEPT, LEFT = "refined", "kept", "left"


def look_poses(pre: HeadPose, target: np.ndarray, views: int, baseline_m: float,
               geometry: BotGeometry = PAPER_BOT) -> list[HeadPose]:
    """The close look's head poses: the camera at `pre`'s optical centre, then
    `baseline_m` to its right, above, left and below (as many as `views` asks: the first
    three give the stereo pairs two directions), each looking at `target` (3,), metres,
    bed frame."""
    centre, rotation = forward(pre, geometry)
    right, down = rotation[:, 0], rotation[:, 1]
    steps = [np.zeros(3), right, -down, -right, down][:views]
    return [look_at(centre + baseline_m * step, target, geometry) for step in steps]


@dataclass
class CloseLook:
    """What a flight needs to look again at its flowers: the flowers as the scan saw them
    (by id), the plant's cloud, the planner's settings (`look` among them), and the folder
    each flower's frames go to (`folder/flower_<id>/`)."""

    flowers: dict[int, Flower]
    plant: PlantObstacles
    config: PollinateConfig
    folder: Path
    pose: PoseConfig | None = None
    colour: ColourConfig | None = None
    geometry: BotGeometry = PAPER_BOT
    tool: PollinatorTool | None = None
    """The pollinator; None: `config.tool`."""
    profile: MotionProfile | None = None

    def visit(self, bot: Bot, visit: Visit, scan_moves: list[Move]) -> tuple[list[Move], dict]:
        """Look at `visit`'s flower from its pre-approach pose, where `bot` stands, and
        return the moves to fly from there to the visit's end (`scan_moves`: the scan
        plan's, from the approach on; the executor lifts the head before the next visit)
        and flight.json's `look` record."""
        watch = Stopwatch()
        flower = self.flowers[visit.flower]
        t0 = bot.now()
        frames, skipped = self._take(bot, visit, flower)
        looked = (look_pose(self._frames_dir(flower), flower.center, flower.normal,
                            flower.radius, self.config.look, self.pose, self.colour)
                  if len(frames) >= 2 else
                  LookedPose(None, None, f"{len(frames)} close frames could be taken "
                                         f"({'; '.join(skipped) or 'none asked for'})"))
        record = {"frames": len(frames), "bot_s": round(bot.now() - t0, 2),
                  **looked.to_json()}
        moves, status, reason = self._moves(visit, flower, looked, scan_moves)
        record.update(status=status, seconds=round(watch.elapsed(), 2))
        if reason:
            record["why"] = reason
        return moves, record

    def _frames_dir(self, flower: Flower) -> Path:
        return Path(self.folder) / f"flower_{flower.id}"

    def _take(self, bot: Bot, visit: Visit, flower: Flower) -> tuple[list[dict], list[str]]:
        """Fly the look's poses from the pre-approach pose and back, a frame at each, into
        the flower's frames folder; returns frames.json's entries and the views left out,
        why."""
        look = self.config.look
        folder = self._frames_dir(flower)
        (folder / "frames").mkdir(parents=True, exist_ok=True)
        entries, skipped = [], []
        trail: list[HeadPose] = []  # every pose flown since the pre-approach pose
        here = visit.pre
        for index, aimed in enumerate(look_poses(visit.pre, flower.center, look.views,
                                                 look.baseline_m, self.geometry)):
            # Aimed at the flower where that is clear, else as the pre-approach pose looks
            # (the flower lies about 17 degrees below the image's centre there).
            step = forward(aimed, self.geometry)[0] - forward(visit.pre, self.geometry)[0]
            shifted = HeadPose(visit.pre.gantry + step, visit.pre.yaw, visit.pre.pitch)
            for pose in (aimed, shifted):
                way = self._way(here, pose)
                if way is not None:
                    break
            if way is None:
                skipped.append(f"view {index} out of reach or too near the plant")
                continue
            self._fly(bot, way)
            trail.extend(way)
            bot.dwell(look.settle_s)
            try:
                frame = bot.camera.frame()
            except CameraError as error:  # the scan's pose is flown, as without a view
                skipped.append(f"the camera failed: {error}")
                break
            yaw, pitch = bot.head()
            centre, rotation = forward(HeadPose(bot.position(), yaw, pitch), self.geometry)
            name = f"frames/frame_{index:06d}.jpg"
            write_image(folder / name, frame.image, [cv2.IMWRITE_JPEG_QUALITY, 95])
            entries.append({"index": index, "file": name, "t": round(frame.t_s, 4),
                            "pose": {"position": centre.tolist(),
                                     "rotation": rotation.tolist()},
                            "gantry": bot.position().tolist(), "head": [yaw, pitch]})
            here = pose
        # Back the way it came: each move was checked both ways.
        self._fly(bot, [*trail[-2::-1], visit.pre] if trail else [])
        if entries:
            write_json(folder / "camera.json", {"model": "PINHOLE", **bot.camera.intrinsics()})
        write_json(folder / "frames.json", {"poses": "recorded", "flower": flower.id,
                                            "frames": entries})
        return entries, skipped

    def _way(self, a: HeadPose, b: HeadPose) -> list[HeadPose] | None:
        """The moves from a to b, each clear of the plant and within reach (None: none)."""
        if self.plant.tree is None:
            return [b]
        return flyable(a, b, self.plant.tree, self.config, self.geometry,
                       self.tool or self.config.tool,
                       self.profile or MotionProfile())

    def _fly(self, bot: Bot, poses: list[HeadPose]) -> None:
        """Each pose a gantry move, then the head's turn (as the planner checked them)."""
        for pose in poses:
            bot.move_to(pose.gantry)
            angles = head_angles(pose)
            if not np.allclose(angles, bot.head()):
                bot.set_head(*angles)

    def _moves(self, visit: Visit, flower: Flower, looked: LookedPose,
               scan_moves: list[Move]) -> tuple[list[Move], str, str]:
        """The moves after the look, its status and, where the refined pose is not flown,
        why."""
        out = _way_out(scan_moves)
        if looked.back:
            return out, LEFT, looked.reason
        if looked.reason:
            if flower.uncertain:
                return out, LEFT, ("its sign was uncertain and the close look did not settle "
                                   f"it: {looked.reason}")
            return scan_moves, KEPT, looked.reason
        refined = Flower(flower.id, looked.centre, looked.normal, flower.radius)
        again = plan_visit(refined, self.plant, self.config, self.geometry, self.tool,
                           self.profile or MotionProfile(), here=visit.pre)
        if again.status == "planned":
            return _from_here(again, visit, out), REFINED, ""
        why = f"no approach from the refined pose: {again.reason}"
        return (out, LEFT, why) if flower.uncertain else (scan_moves, KEPT, why)


def _way_out(scan_moves: list[Move]) -> list[Move]:
    """From the pre-approach pose back without touching: up the scan plan's path where its
    visit came down one (else the executor's next lift takes the head straight up)."""
    return [m for m in scan_moves if m.kind == "climb"]


def _from_here(again: Visit, visit: Visit, out: list[Move]) -> list[Move]:
    """The refined visit flown from the pre-approach pose: over to its own pre-approach
    pose, in, the rest, out, back and up the way the scan plan's visit came."""
    flower = visit.flower
    return ([Move("descend", flower, p) for p in again.path]
            + [Move("approach", flower, p) for p in again.approach_moves]
            + [Move("dwell", flower, again.touch)]
            + [Move("retreat", flower, p) for p in [*again.approach_moves[-2::-1], again.pre]]
            + [Move("climb", flower, p) for p in [*again.path[-2::-1], visit.pre]]
            + out)
