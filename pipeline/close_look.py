"""The close look: one flower's pose again, from a few frames taken near it.

Before the pollinator touches a flower, the head's camera takes a few frames of it from
the pre-approach pose and a few centimetres round it (`hardware/flights/close_look.py`).
Their poses are the bot's own (recorded, as a scan's are), so the frames are a small scan
of one flower at about 18 cm, more than twice as near as the whole-plant scan: this stage
reconstructs them by the dense stage (`dense.reconstruct_dense`, with close-range
settings), crops the points round the scan's estimate and estimates the flower's pose by
the pose stage (`pose.estimate_pose`), as the pipeline does on a plant's cloud; its
centre is the circle of the pistil's points (`ring_centre`), which a one-sided view does
not pull off as it does their centroid. The
result is kept only where it is the same flower (its centre near the scan's, its axis
near the scan's) and its sign is settled and agrees; else the caller keeps the scan's
pose, with the reason, or, where the close views see the flower's back, touches nothing.

Measured on simulated close views (a realistic plant, seed 2, 14 flowers seen, the scan's
normal 12 degrees off and its centre 1-5 mm off): the plane's error 0.8-4.0 degrees
(mean 2.4) and the centre's 1.0-1.4 mm; a fit of one plane through the triangulated
pistil to the views' colours (a plane-induced homography) did worse, 2-23 degrees (mean
9), so it is not used.

Frames, units: the bed frame, metres, degrees.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from flowerpose.cloudio import Cloud
from flowerpose.config import require
from flowerpose.errors import InputError
from flowerpose.pipeline.cluster_config import ClusterConfig
from flowerpose.pipeline.colour import ColourConfig
from flowerpose.pipeline.dense import reconstruct_dense
from flowerpose.pipeline.dense_config import DenseConfig
from flowerpose.pipeline.frames import read_frames
from flowerpose.pipeline.pose import PoseConfig, estimate_pose, split_petals_pistil
from flowerpose.stopwatch import Stopwatch


def close_range_dense() -> DenseConfig:
    """The dense stage at a close look's range: depths from 5 to 40 cm, pairs whose camera
    centres are 1-10 cm apart, and frames 2 mm apart kept (a look's steps are 2 cm)."""
    return DenseConfig(depth_range_m=(0.05, 0.4), baseline_m=(0.01, 0.1),
                       duplicate_distance_m=0.002)


@dataclass(frozen=True)
class CloseLookConfig:
    """How a flower is looked at again before the swab touches it (`pollinate.look`)."""

    views: int = 3
    """Frames taken: the first from the pre-approach pose's camera, the others
    `baseline_m` to its right, above, left and below, each aimed at the flower's centre (0:
    no close look; the visits fly on the scan's poses). On simulated close views of 14
    flowers (a realistic plant, seed 2) the plane's error was 2.4 degrees on the mean with
    four views, 2.4 with three (right and above) and 2.9 with three in a row (right and
    left); each view costs about 5 s of the bot's time."""
    baseline_m: float = 0.02
    """How far the camera steps between the frames, metres: at the look's 18 cm, 2 cm is
    6.3 degrees of parallax, enough to measure depth to a millimetre and little enough
    that the views look alike."""
    settle_s: float = 2.0
    """Seconds the head rests before each frame: the camera's autofocus settles in 2 s
    (`scan.camera.sensor.autofocus_settle_s`)."""
    crop_margin_m: float = 0.01
    """The points within the flower's radius and this of the scan's centre are its own."""
    default_radius_m: float = 0.02
    """A flower's radius where the scan gives none (its box), metres."""
    max_shift_m: float = 0.01
    """The refined centre within this of the scan's, metres: farther, the close views
    found another flower (a neighbour's pistil) and the scan's pose is kept."""
    max_turn_deg: float = 45.0
    """The refined axis within this of the scan's (either sign), degrees: farther, the
    close views saw something else (a leaf's edge, a bud) and the scan's pose is kept."""
    min_points: int = 50
    """Fewest points of the crop that make a pose."""
    visit_uncertain: bool = True
    """Plan the flowers whose sign the scan left uncertain (`pose.uncertain`) too: the
    close look settles it, and a flower it cannot settle is left alone."""
    dense: DenseConfig = field(default_factory=close_range_dense)
    """The dense stage on the close frames."""

    def __post_init__(self):
        require(self.views == 0 or self.views >= 2, "pollinate.look.views",
                "must be 0 (no close look) or at least 2")
        for name in ("baseline_m", "crop_margin_m", "default_radius_m", "max_shift_m"):
            require(getattr(self, name) > 0, f"pollinate.look.{name}", "must be positive")
        require(self.settle_s >= 0, "pollinate.look.settle_s", "must be 0 or more")
        require(0 < self.max_turn_deg <= 90, "pollinate.look.max_turn_deg",
                "must be above 0 and at most 90")
        require(self.min_points >= 3, "pollinate.look.min_points", "must be at least 3")


@dataclass(frozen=True)
class LookedPose:
    """What a close look made of a flower: its refined pose, or why there is none.

    centre (3,) and normal (3,), metres and unit, bed frame, where `reason` is empty.
    back: the refined normal points against the scan's: the scan's side of the flower, the
    one the camera looks from, is its back (the swab must not touch it).
    """

    centre: np.ndarray | None
    normal: np.ndarray | None
    reason: str = ""
    back: bool = False
    points: int = 0
    """Points of the close cloud round the flower."""
    seconds: float = 0.0
    """Reconstruction and pose, wall-clock seconds."""

    def to_json(self) -> dict:
        entry = {"points": self.points, "seconds": round(self.seconds, 2)}
        if self.reason:
            return {**entry, "reason": self.reason, "back": self.back}
        return {**entry, "centre": [round(float(v), 6) for v in self.centre],
                "normal": [round(float(v), 6) for v in self.normal]}


def look_pose(frames_dir: Path, prior_centre: np.ndarray, normal: np.ndarray,
              radius: float | None, config: CloseLookConfig = CloseLookConfig(),
              pose: PoseConfig | None = None, colour: ColourConfig | None = None,
              method: str = "plane") -> LookedPose:
    """The pose of the flower the scan put at `prior_centre` (3,) with `normal` (3,) and `radius`
    (metres, or None), from a close look's frames folder (frames.json with the recorded
    poses, camera.json, the frames: `pipeline.frames`' format)."""
    watch = Stopwatch()
    radius = radius or config.default_radius_m
    prior_centre = np.asarray(prior_centre, np.float64)
    normal = np.asarray(normal, np.float64)

    def refused(reason: str, points: int = 0) -> LookedPose:
        return LookedPose(None, None, reason, points=points, seconds=watch.elapsed())

    dense = config.dense
    frames = read_frames(frames_dir)
    if len(frames) == 2:  # a pixel's depth can be checked by one view only
        dense = replace(dense, min_consistent_views=min(1, dense.min_consistent_views))
    try:
        cloud, _ = reconstruct_dense(frames_dir, config=dense)
    except InputError as error:
        return refused(f"the close frames gave no cloud ({error.problem})")
    near = np.linalg.norm(cloud.points - prior_centre, axis=1) <= radius + config.crop_margin_m
    points = int(near.sum())
    if points < config.min_points:
        return refused(f"{points} points of the close cloud near the flower (fewest "
                       f"{config.min_points}): the view is blocked", points)
    crop = Cloud(cloud.points[near], cloud.colors[near])
    found = estimate_pose(crop, pose, colour)
    refined = found.normals.get(method)
    if refined is None or not found.pistil_found:
        return refused("the close views do not settle the flower's axis ("
                       + ("no pistil seen" if not found.pistil_found else "no plane") + ")",
                       points)
    # The cameras saw the pistil, which only the flower's face shows: its normal points
    # their way. On a whole plant the pose stage signs it by votes; here the views say it.
    cameras = np.mean([frame.position for frame in frames], axis=0)
    refined = refined if refined @ (cameras - found.center) >= 0 else -refined
    pistil = split_petals_pistil(crop, colour or ColourConfig(), ClusterConfig())[1]
    centre = ring_centre(crop.points[pistil], found.center, refined)
    shift = float(np.linalg.norm(centre - prior_centre))
    if shift > config.max_shift_m:
        return refused(f"the close views' flower is {shift * 1000:.0f} mm from the scan's "
                       f"(most {config.max_shift_m * 1000:.0f} mm)", points)
    cosine = float(np.clip(refined @ normal / np.linalg.norm(normal), -1.0, 1.0))
    turn = float(np.degrees(np.arccos(abs(cosine))))
    if turn > config.max_turn_deg:
        return refused(f"the close views' axis is {turn:.0f} degrees from the scan's (most "
                       f"{config.max_turn_deg:g})", points)
    if cosine < 0:  # the scan's normal points away from where the cameras saw the face
        return LookedPose(None, None, "the close views see the flower's face on the other "
                          "side of the scan's", back=True, points=points,
                          seconds=watch.elapsed())
    return LookedPose(centre, np.asarray(refined, np.float64), points=points,
                      seconds=watch.elapsed())


#: A ring fit is kept where its radius lies in this range, metres (a strawberry flower's
#: stamens ring its 6-8 mm receptacle), and its points lie within this share of its radius
#: of the circle (median).
RING_RADIUS_M, RING_SPREAD = (0.002, 0.012), 0.35


def ring_centre(pistil: np.ndarray, centre: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """The flower's centre from its pistil-coloured points (K, 3), seen from one side:
    the centre of the circle they lie on in the corolla's plane (an algebraic fit), at the
    height along `normal` of `centre` (the pistil's centroid). The stamens ring the
    receptacle, and from a close, oblique view the ring's far side hides behind it, which
    pulls a centroid towards the cameras (on simulated field flowers, 2-3 mm); the circle
    does not move. Where the points do not lie on a circle, `centre`."""
    if len(pistil) < 8:
        return np.asarray(centre, np.float64)
    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(normal, helper)
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    offset = pistil - centre
    x, y = offset @ u, offset @ v
    solution = np.linalg.lstsq(np.column_stack([2 * x, 2 * y, np.ones_like(x)]),
                               x * x + y * y, rcond=None)[0]
    a, b = solution[0], solution[1]
    radius = float(np.sqrt(max(solution[2] + a * a + b * b, 0.0)))
    spread = float(np.median(np.abs(np.hypot(x - a, y - b) - radius)))
    if not (RING_RADIUS_M[0] <= radius <= RING_RADIUS_M[1] and spread <= RING_SPREAD * radius):
        return np.asarray(centre, np.float64)
    return centre + a * u + b * v
