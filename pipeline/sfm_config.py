"""The sparse stage's settings (`sfm.reconstruct_sparse`), and the SIFT defaults they leave
to the frames: the image size and first octave by the stage's mode and the frames' pose
kind (`frames.POSE_KINDS`). Sizes in pixels, distances in metres.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Literal

from flowerpose.pipeline.board import BoardSpec


@dataclass(frozen=True)
class SfmConfig:
    """How the sparse reconstruction runs."""

    mode: Literal["poses", "incremental"] = "poses"
    """"poses": match and triangulate with the recorded camera poses, then bundle
    adjustment; "incremental": COLMAP's incremental mapping from the images alone, then a
    similarity onto the recorded camera centres. Without camera.json the intrinsics are
    unknown and incremental mapping runs (it estimates them). On a simulated 200-frame
    1280 x 720 scan "poses" registered 169 of 170 distinct views in about a quarter of the
    CPU time, "incremental" 111."""
    refine_poses: bool = True
    """"poses" mode: bundle adjustment also refines the poses (held near the recorded
    positions by pose_prior_m), then the points are triangulated again with them. A real
    bot's recorded poses are off by millimetres and a fraction of a degree; on the
    simulator, whose poses are exact, it changes nothing measurable."""
    pose_prior_m: float = 0.005
    """Standard deviation per axis of a camera centre about its recorded position in that
    bundle adjustment, metres."""
    max_image_size: int | None = None
    """Longest image side SIFT sees, pixels; larger frames are downscaled for extraction
    (keypoints are scaled back to the full image). None (`feature_defaults`): 640 in
    "poses" mode with a bot's recorded poses, where they guide matching and the features
    only refine them, 960 with calibrated photos' poses, `FULL_IMAGE_SIZE` in
    "incremental" mode, which needs them to find the poses. On the scan-3 suite's 1280 x 720
    scans 640 took the sparse stage from 44 to 20 s a plant on 2 cores (features 23 -> 12 s:
    at 960 it was still 22 s, the resize costing what the smaller image saves), camera
    centres 0.6-0.8 mm RMS from the recorded ones instead of 0.4-0.5, 1-3 fewer of about 176
    views registered, petal F-score at 5 mm 0.999 on each plant, and the same flowers found
    (plane error paired -0.5 degrees [-2.4, 0.2] on 34, no difference shown)."""
    max_features: int = 4096
    """Most SIFT features kept per image (COLMAP: 8192); simulated 1280 x 720 frames give
    about 1,200 with the defaults here."""
    first_octave: int | None = None
    """SIFT's first octave: -1 doubles the image first (COLMAP's default), 0 starts at full
    size (2.7 times faster, about 25 % fewer features). None (`feature_defaults`): 0 in
    "poses" mode, where the recorded poses guide matching; in "incremental" mode -1 for a
    bot's frames (a simulated scan registered 46 instead of 111 of 170 views with 0) and
    for photos smaller than `FULL_IMAGE_SIZE`, 0 for larger photos (rough poses or none: the
    shared real set's 60 photos of 1440 x 1080 registered all 60 either way, the sparse
    stage 21 s with 0 and over 90 s with -1, whose doubled images' features flood the
    matching of every pair; downscaled to 1080 x 810 they registered 31 with 0 and 60
    with -1)."""
    peak_threshold: float = 0.0025
    """SIFT's contrast threshold of a keypoint (COLMAP: 0.0067); lower finds more features
    on faint texture such as leaves and soil."""
    sequential_overlap: int = 5
    """Each frame is matched with this many following frames of the scan."""
    exhaustive_max_images: int = 150
    """Frames without poses are matched every pair with every other up to this many frames
    (photos in any order); more are matched sequentially, `sequential_overlap` times 4
    following frames each (a video or photos taken in order round the plant)."""
    pose_neighbours: int = 6
    """And with this many nearest recorded camera centres (neighbouring rings of the path)."""
    max_view_angle_deg: float = 60.0
    """Pose pairs only between cameras whose optical axes differ by at most this."""
    min_baseline_m: float = 0.01
    """"poses" mode: pairs whose camera centres are closer than this are not matched (their
    epipolar geometry checks nothing)."""
    max_ratio: float = 0.8
    """Lowe's ratio test on SIFT matches (COLMAP's default); in "poses" mode among the
    features near the epipolar line."""
    epipolar_max_px: float = 4.0
    """"poses" mode: a match lies within this of the epipolar line of the recorded poses,
    pixels (full image). Raise it for a bot whose recorded rotations are off by more than
    about 0.2 degree (1 degree is about 18 px at 1280 x 720 with a 60 degree lens)."""
    min_track_length: int = 3
    """Points seen by fewer images are dropped: two-view points are mostly wrong matches
    along the epipolar line (median 10 mm off the truth on a simulated scan, against under
    1 mm for three views and more)."""
    max_reprojection_px: float = 2.0
    """Points whose mean reprojection error exceeds this are dropped, pixels."""
    align_threshold_m: float = 0.02
    """Camera centres farther than this from their recorded position after alignment are
    outliers of the similarity to the bed frame, metres."""
    min_registered: int = 3
    """Fewest registered images accepted."""
    min_registered_fraction: float = 0.5
    """Smallest fraction of the images (at distinct poses) that must register."""
    board: Literal["auto", "required", "off"] = "auto"
    """Frames without poses: look for a printed ChArUco board (`flowerpose marker`) in the
    registered photos, and where it is seen take the scale and up from it ("auto"), or
    fail when it is not ("required"); "off" never looks."""
    board_spec: BoardSpec = field(default_factory=BoardSpec)
    """The board looked for (the one `flowerpose marker` prints by default)."""
    camera_distance_m: float | None = None
    """Frames without poses: the cameras' median distance from the plant's centre, metres,
    as the user measured it; it sets the cloud's scale. None: assumed
    `ASSUMED_CAMERA_DISTANCE_M`, and the report says the cloud is not metric (a marker
    in view, or poses, fix the scale instead)."""
    num_threads: int = 0
    """Threads for extraction, matching and mapping; 0: every core."""
    seed: int = 0
    """Random seed for COLMAP's RANSAC and mapping and for the alignment."""
    colmap_log: bool = False
    """Show COLMAP's own log lines (stderr) besides the progress lines."""


#: The camera distance a pose-less reconstruction assumes where none is stated, metres
#: (a phone held round a potted plant): the dense stage's thresholds are in metres, so the
#: cloud is put near its true size, and called not metric.
ASSUMED_CAMERA_DISTANCE_M = 0.35

#: The longest image side SIFT sees by default, pixels (`feature_defaults`): incremental
#: mapping's, and the frames' own at the paper's 1280 x 720; "poses" mode's with a bot's
#: recorded poses (200 frames close together); with calibrated poses of photos (fewer, wider
#: apart, each registering on its own features: the shared real set's 60 photos of
#: 1440 x 1080 registered 54 at 640, 60 at 960 and at 1280).
FULL_IMAGE_SIZE, POSES_IMAGE_SIZE, CALIBRATED_IMAGE_SIZE = 1280, 640, 960


def threads(config: SfmConfig) -> int:
    """The threads COLMAP's steps get: `num_threads`, or every core for 0."""
    return config.num_threads if config.num_threads > 0 else (os.cpu_count() or 1)


def feature_defaults(mode: str, kind: str, longest_side: int) -> tuple[int, int]:
    """(max_image_size, first_octave) SIFT gets where SfmConfig leaves them None, by the
    sparse stage's mode, the frames' pose kind (`frames.POSE_KINDS`) and their longer side,
    pixels."""
    if mode == "poses":
        return (POSES_IMAGE_SIZE if kind == "recorded" else CALIBRATED_IMAGE_SIZE), 0
    full_size_photos = kind != "recorded" and longest_side >= FULL_IMAGE_SIZE
    return FULL_IMAGE_SIZE, (0 if full_size_photos else -1)
