"""Sparse reconstruction of a frames folder with pycolmap, in the bed frame.

    frames_dir/frames.json, frames/*.jpg, camera.json (optional)   (`flowerpose frames`)
      -> work_dir/database.db      SIFT features and verified matches
      -> work_dir/pairs.txt        the image pairs matched: sequential + nearby poses
      -> work_dir/sparse/          the COLMAP model, already in the bed frame (metres)
      -> work_dir/sparse.ply       its points, coloured
      -> work_dir/sparse.json      the report (counts, errors, alignment, seconds, config)

Two ways to get camera poses (SfmConfig.mode):
- "poses": the recorded poses are the cameras; points are triangulated with them and
  refined by bundle adjustment (optionally the poses too). Needs a calibrated camera.json
  and poses good to a fraction of a degree (frames.json's "poses": "recorded" by the bot,
  or "calibrated").
- "incremental": COLMAP's full incremental mapping from the images alone. Always so for
  "rough" poses (a gantry's log: degrees off), for none, and for an estimated camera.
With poses, a robust similarity from the reconstructed camera centres to the given ones
puts the model in their frame (metres), and its residual is reported. Without, the model
is levelled (`align.level_similarity`: z up, origin at the cameras' mean) and its scale
is the reconstruction's own: the report says "metric": false.
"""

from __future__ import annotations

# cv2 must be imported before pycolmap: the other order makes a later cv2.imwrite of a PNG
# abort the process (both bundle libpng; double free). tests/pipeline/test_sfm.py keeps it
# caught.
import cv2  # isort: skip

import contextlib
import dataclasses
import os
import shutil
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

try:
    import pycolmap
except ImportError:  # the [recon] extra is not installed: the settings still load
    pycolmap = None

from flowerpose.atomic import write_text
from flowerpose.cloudio import Cloud, write_cloud
from flowerpose.errors import InputError, missing_extra
from flowerpose.jsonio import write_json
from flowerpose.log import LOG, Tally
from flowerpose.pipeline.align import (
    Similarity,
    level_similarity,
    residuals,
    robust_similarity,
)
from flowerpose.pipeline.board import MIN_VIEWS, BoardSpec, board_similarity, find_corners
from flowerpose.pipeline.frames import ChosenFrame, distinct_views, pose_kind, read_frames
from flowerpose.processes import reclaim_sigterm
from flowerpose.scanio import Intrinsics, image_size, read_intrinsics
from flowerpose.stopwatch import Stopwatch

# Importing pycolmap gave SIGTERM to glog, which prints a C stack dump and kills the process.
reclaim_sigterm()

#: An image that sees fewer triangulated points than this counts as not registered (the
#: inliers COLMAP's mapper asks of a new image's pose, abs_pose_min_num_inliers).
MIN_IMAGE_POINTS = 30
#: Frames closer than this in position (metres) and viewing direction (degrees) were taken
#: at one stop of the scan; only the first is used. Tighter than the dense stage's
#: duplicates (`DenseConfig.duplicate_distance_m`): a pair a few millimetres apart still
#: helps a frame register, but adds no depth to stereo.
SAME_POSE_M = 0.001
SAME_POSE_DEG = 0.5
#: Fewest matches for an image pair to count (COLMAP's two_view_geometry min_num_inliers).
MIN_PAIR_MATCHES = 15


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


@dataclass
class SparseResult:
    """A sparse reconstruction in the bed frame."""

    reconstruction: pycolmap.Reconstruction
    """Cameras, images and points, metres, bed frame (cam_from_world maps bed to camera)."""
    cloud: Cloud
    """The triangulated points, metres, bed frame, with their colours."""
    report: dict
    """Counts, errors, the alignment residual, seconds per step and the config."""


def _progress(message: str) -> None:
    LOG.info(f"sfm: {message}")


@contextlib.contextmanager
def _colmap_logging(show: bool) -> Iterator[None]:
    """COLMAP's INFO lines hidden unless asked for (they are hundreds per step)."""
    before = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 0 if show else 2
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = before


def distinct_poses(positions: np.ndarray, rotations: np.ndarray) -> np.ndarray:
    """(N,) bool: False for a frame recorded at the pose of an earlier kept one
    (`frames.distinct_views` within SAME_POSE_M and SAME_POSE_DEG).

    A stop-and-go scan often gives two chosen frames at one stop. Such a pair has no
    baseline: its matches confirm any feature, and a track through both counts one view
    twice (on a simulated scan those tracks held most points more than 5 mm off).
    positions: (N, 3) metres, bed frame; rotations: (N, 3, 3) camera-to-bed.
    """
    return distinct_views(positions, rotations[:, :, 2], -np.arange(len(positions)),
                          SAME_POSE_M, SAME_POSE_DEG)


def sequential_pairs(count: int, overlap: int) -> set[tuple[int, int]]:
    """(i, j), i < j: each frame with the `overlap` frames after it."""
    return {(i, j) for i in range(count) for j in range(i + 1, min(count, i + overlap + 1))}


def pairs_from_poses(positions: np.ndarray, rotations: np.ndarray, neighbours: int,
                     max_angle_deg: float) -> set[tuple[int, int]]:
    """(i, j), i < j: each camera with its nearest cameras that look the same way.

    positions: (N, 3) camera centres, metres, bed frame; rotations: (N, 3, 3) camera-to-bed
    (the third column is the optical axis).
    """
    n = len(positions)
    if n < 2 or neighbours < 1:
        return set()
    axes = rotations[:, :, 2]
    distance = np.linalg.norm(positions[:, None] - positions[None], axis=2)
    usable = axes @ axes.T >= np.cos(np.radians(max_angle_deg))
    np.fill_diagonal(usable, False)
    distance = np.where(usable, distance, np.inf)
    order = np.argsort(distance, axis=1, kind="stable")[:, :neighbours]
    rows = np.repeat(np.arange(n), order.shape[1])
    cols = order.ravel()
    keep = np.isfinite(distance[rows, cols])
    return {(int(min(i, j)), int(max(i, j))) for i, j in zip(rows[keep], cols[keep],
                                                             strict=True)}


def _threads(config: SfmConfig) -> int:
    return config.num_threads if config.num_threads > 0 else (os.cpu_count() or 1)


def feature_defaults(mode: str, kind: str, longest_side: int) -> tuple[int, int]:
    """(max_image_size, first_octave) SIFT gets where SfmConfig leaves them None, by the
    sparse stage's mode, the frames' pose kind (`frames.POSE_KINDS`) and their longer side,
    pixels."""
    if mode == "poses":
        return (POSES_IMAGE_SIZE if kind == "recorded" else CALIBRATED_IMAGE_SIZE), 0
    full_size_photos = kind != "recorded" and longest_side >= FULL_IMAGE_SIZE
    return FULL_IMAGE_SIZE, (0 if full_size_photos else -1)


def _extract(database: Path, frames_dir: Path, names: list[str],
             intrinsics: Intrinsics | None, mode: str, kind: str, longest_side: int,
             config: SfmConfig) -> None:
    reader = pycolmap.ImageReaderOptions()
    if intrinsics is not None and not intrinsics.estimated:
        reader.camera_model = "PINHOLE"
        reader.camera_params = ",".join(repr(float(v)) for v in (
            intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy))
    else:
        # Not calibrated: COLMAP refines a focal length and one radial distortion term from
        # camera.json's estimate (EXIF or its own default).
        reader.camera_model = "SIMPLE_RADIAL"
        if intrinsics is not None:
            reader.camera_params = ",".join(repr(float(v)) for v in (
                (intrinsics.fx + intrinsics.fy) / 2, intrinsics.cx, intrinsics.cy, 0.0))
    options = pycolmap.FeatureExtractionOptions()
    size, octave = feature_defaults(mode, kind, longest_side)
    options.max_image_size = config.max_image_size or size
    options.num_threads = _threads(config)
    options.sift.max_num_features = config.max_features
    options.sift.first_octave = config.first_octave if config.first_octave is not None \
        else octave
    options.sift.peak_threshold = config.peak_threshold
    # Images enter the database first, one after another in `names`' order: extraction
    # would number them as its threads finish, and matching and triangulation follow the
    # numbers, so the same frames would give another model each run.
    pycolmap.Database.open(database).close()  # made empty
    pycolmap.import_images(database, frames_dir, camera_mode=pycolmap.CameraMode.SINGLE,
                           image_names=names, options=reader)
    chunk = 25
    with Tally(len(names), "features") as tally:
        for first in range(0, len(names), chunk):
            batch = names[first:first + chunk]
            pycolmap.extract_features(database, frames_dir, image_names=batch,
                                      camera_mode=pycolmap.CameraMode.SINGLE,
                                      reader_options=reader, extraction_options=options,
                                      device=pycolmap.Device.cpu)
            tally.advance(len(batch), f"sfm: features {tally.done + len(batch)}/{len(names)} "
                          "images")


def _write_pairs(path: Path, names: list[str], pairs: list[tuple[int, int]]) -> Path:
    return write_text(path, "".join(f"{names[i]} {names[j]}\n" for i, j in pairs))


def _match_ransac(database: Path, work_dir: Path, names: list[str],
                  pairs: list[tuple[int, int]], config: SfmConfig) -> None:
    """COLMAP's matcher and RANSAC verification on the pairs (images alone)."""
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = _threads(config)
    matching.sift.max_ratio = config.max_ratio
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = config.seed
    chunk = 200
    part = work_dir / "pairs_part.txt"
    with Tally(len(pairs), "matching") as tally:
        for first in range(0, len(pairs), chunk):
            batch = pairs[first:first + chunk]
            _write_pairs(part, names, batch)
            pycolmap.match_image_pairs(
                database, matching_options=matching,
                pairing_options=pycolmap.ImportedPairingOptions(match_list_path=part),
                verification_options=verification, device=pycolmap.Device.cpu)
            tally.advance(len(batch), f"sfm: matched {tally.done + len(batch)}/{len(pairs)} "
                          "pairs")
    part.unlink()


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def unit_descriptors(descriptors: np.ndarray) -> np.ndarray:
    """(N, D) descriptors as float32 rows of unit length."""
    unit = descriptors.astype(np.float32)
    unit /= np.maximum(np.linalg.norm(unit, axis=1, keepdims=True), 1e-9)
    return unit


def epipolar_matches(points1: np.ndarray, points2: np.ndarray, descriptors1: np.ndarray,
                     descriptors2: np.ndarray, fundamental: np.ndarray, max_px: float,
                     max_ratio: float = 0.8, max_angle: float = 0.7) -> np.ndarray:
    """(K, 2) indices of features that match across two images of known relative pose.

    Each feature's candidates are the other image's features within max_px of its epipolar
    line; among them the nearest descriptor must be mutual, closer than
    max_angle (radians between unit descriptors) and than max_ratio times the second
    nearest (Lowe's test with COLMAP's defaults, here among the candidates), so the
    repeated texture of a leaf along the line is refused while true matches that a global
    ratio test would lose are kept.
    points1 (N, 2), points2 (M, 2): pixels; descriptors1 (N, D), descriptors2 (M, D): SIFT;
    fundamental: (3, 3), x2^T F x1 = 0 for pixel coordinates.
    """
    empty = np.zeros((0, 2), dtype=np.int64)
    if len(points1) == 0 or len(points2) == 0:
        return empty
    x1 = np.c_[points1, np.ones(len(points1))]
    x2 = np.c_[points2, np.ones(len(points2))]
    lines2 = x1 @ fundamental.T
    lines2 /= np.maximum(np.linalg.norm(lines2[:, :2], axis=1, keepdims=True), 1e-12)
    # A band round each epipolar line holds a few percent of the other image's features:
    # one dense pass finds them, everything after works on that short list.
    distance = lines2.astype(np.float32) @ x2.T.astype(np.float32)
    np.abs(distance, out=distance)
    # flatnonzero then divmod: several times faster than a 2-D np.nonzero.
    rows, cols = np.divmod(np.flatnonzero(distance < max_px), len(points2))
    del distance
    if len(rows) == 0:
        return empty
    d1, d2 = unit_descriptors(descriptors1), unit_descriptors(descriptors2)
    angle = np.arccos(np.clip((d1 @ d2.T)[rows, cols], -1.0, 1.0))
    # rows come sorted, so each feature's candidates are contiguous.
    starts = np.flatnonzero(np.r_[True, rows[1:] != rows[:-1]])
    counts = np.diff(np.r_[starts, len(rows)])
    nearest = np.minimum.reduceat(angle, starts)
    is_nearest = angle == np.repeat(nearest, counts)
    best = np.flatnonzero(is_nearest)
    best = best[np.r_[True, rows[best][1:] != rows[best][:-1]]]
    others = angle.copy()
    others[best] = np.inf
    second = np.minimum.reduceat(others, starts)
    good = (nearest < max_angle) & (nearest < max_ratio * second)
    chosen = best[good]
    # Mutual: no other feature of image 1 is nearer this one's match in image 2.
    by_col = np.argsort(cols, kind="stable")  # a radix sort: integers
    col_starts = np.flatnonzero(np.r_[True, cols[by_col][1:] != cols[by_col][:-1]])
    nearest_of_col = np.full(len(points2), np.inf)
    nearest_of_col[cols[by_col[col_starts]]] = np.minimum.reduceat(angle[by_col], col_starts)
    chosen = chosen[angle[chosen] <= nearest_of_col[cols[chosen]]]
    chosen = chosen[np.unique(cols[chosen], return_index=True)[1]]
    return np.c_[rows[chosen], cols[chosen]]


def _in_front(rays1: np.ndarray, rays2: np.ndarray, baseline: np.ndarray) -> np.ndarray:
    """(K,) whether the closest points of paired rays lie in front of both cameras.

    rays1, rays2: (K, 3) directions in the bed frame from centres c1 and c2 (camera z > 0
    along them); baseline: c1 - c2.
    """
    a = (rays1 * rays1).sum(1)
    b = (rays1 * rays2).sum(1)
    c = (rays2 * rays2).sum(1)
    d = rays1 @ baseline
    e = rays2 @ baseline
    denominator = a * c - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (b * e - c * d) / denominator
        t = (a * e - b * d) / denominator
    return (s > 0) & (t > 0)


def _match_with_poses(database: Path, names: list[str],
                      pairs: list[tuple[int, int]], frames: list[ChosenFrame],
                      config: SfmConfig) -> None:
    """Epipolar-guided matching on the recorded poses; the matches are written as verified
    (calibrated) two-view geometries, so no RANSAC runs."""
    db = pycolmap.Database.open(database)
    try:
        ids = {image.name: image.image_id for image in db.read_all_images()}
        camera = db.read_all_cameras()[0]
        inverse_k = np.linalg.inv(camera.calibration_matrix())
        keypoints = {i: db.read_keypoints(i)[:, :2].astype(np.float64) for i in ids.values()}
        descriptors = {i: db.read_descriptors(i).data for i in ids.values()}

        def match(pair: tuple[int, int]) -> tuple[int, int, pycolmap.TwoViewGeometry | None]:
            k1, k2 = pair
            id1, id2 = ids[names[k1]], ids[names[k2]]
            if id1 > id2:
                k1, k2, id1, id2 = k2, k1, id2, id1
            f1, f2 = frames[k1], frames[k2]
            rotation = f2.rotation.T @ f1.rotation
            translation = f2.rotation.T @ (f1.position - f2.position)
            essential = _skew(translation) @ rotation
            fundamental = inverse_k.T @ essential @ inverse_k
            found = epipolar_matches(keypoints[id1], keypoints[id2], descriptors[id1],
                                     descriptors[id2], fundamental, config.epipolar_max_px,
                                     config.max_ratio)
            if len(found):
                rays1 = np.c_[keypoints[id1][found[:, 0]], np.ones(len(found))] @ \
                    (f1.rotation @ inverse_k).T
                rays2 = np.c_[keypoints[id2][found[:, 1]], np.ones(len(found))] @ \
                    (f2.rotation @ inverse_k).T
                found = found[_in_front(rays1, rays2, f1.position - f2.position)]
            if len(found) < MIN_PAIR_MATCHES:
                return id1, id2, None
            geometry = pycolmap.TwoViewGeometry()
            geometry.config = pycolmap.TwoViewGeometryConfiguration.CALIBRATED
            geometry.E = essential
            geometry.F = fundamental
            geometry.cam2_from_cam1 = pycolmap.Rigid3d(pycolmap.Rotation3d(rotation),
                                                       translation)
            geometry.inlier_matches = found.astype(np.uint32)
            return id1, id2, geometry

        with ThreadPoolExecutor(_threads(config)) as pool, \
                Tally(len(pairs), "matching") as tally:
            for done, (id1, id2, geometry) in enumerate(pool.map(match, pairs), 1):
                if geometry is not None:
                    db.write_matches(id1, id2, geometry.inlier_matches)
                    db.write_two_view_geometry(id1, id2, geometry)
                tally.advance(1, f"sfm: matched {done}/{len(pairs)} pairs on the recorded poses"
                              if done % 200 == 0 or done == len(pairs) else None)
    finally:
        db.close()


def _mapper_options(config: SfmConfig, intrinsics_known: bool
                    ) -> pycolmap.IncrementalPipelineOptions:
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = _threads(config)
    options.random_seed = config.seed
    options.mapper.random_seed = config.seed
    options.triangulation.random_seed = config.seed
    if intrinsics_known:
        options.ba_refine_focal_length = False
        options.ba_refine_extra_params = False
        options.mapper.abs_pose_refine_focal_length = False
        options.mapper.abs_pose_refine_extra_params = False
    return options


def _cam_from_world(frame: ChosenFrame) -> pycolmap.Rigid3d:
    rotation = frame.rotation.T
    return pycolmap.Rigid3d(pycolmap.Rotation3d(rotation), -rotation @ frame.position)


def _posed_reconstruction(database: Path, frames: dict[str, ChosenFrame]
                          ) -> pycolmap.Reconstruction:
    """The database's cameras and images, each at its recorded pose (no points yet)."""
    db = pycolmap.Database.open(database)
    try:
        reconstruction = pycolmap.Reconstruction()
        for camera in db.read_all_cameras():
            reconstruction.add_camera_with_trivial_rig(camera)
        for image in db.read_all_images():
            if image.name not in frames:
                continue
            posed = pycolmap.Image(name=image.name, camera_id=image.camera_id,
                                   image_id=image.image_id)
            reconstruction.add_image_with_trivial_frame(posed,
                                                        _cam_from_world(frames[image.name]))
    finally:
        db.close()
    return reconstruction


def _triangulate(posed: pycolmap.Reconstruction, database: Path, frames_dir: Path,
                 output: Path, config: SfmConfig) -> pycolmap.Reconstruction:
    """Points from the database's verified matches, triangulated with `posed`'s cameras
    held fixed (COLMAP's point_triangulator; its own filters at 4 px)."""
    return pycolmap.triangulate_points(posed, database, frames_dir, output,
                                       clear_points=True,
                                       options=_mapper_options(config, True),
                                       refine_intrinsics=False)


def _filter_points(reconstruction: pycolmap.Reconstruction, config: SfmConfig) -> None:
    """Drop points seen by too few images, or that reproject too far, or that lie at
    too small a triangulation angle (COLMAP's filter_min_tri_angle) or behind a camera."""
    manager = pycolmap.ObservationManager(reconstruction)
    manager.filter_all_points3D(config.max_reprojection_px,
                                pycolmap.IncrementalMapperOptions().filter_min_tri_angle)
    manager.filter_points3D_with_short_tracks(config.min_track_length)


def _bundle_adjust(reconstruction: pycolmap.Reconstruction, frames: dict[str, ChosenFrame],
                   config: SfmConfig) -> None:
    """Refine points and poses (intrinsics fixed), the camera centres held near their
    recorded positions (a prior of config.pose_prior_m per axis)."""
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_focal_length = False
    options.refine_principal_point = False
    options.refine_extra_params = False
    options.print_summary = False
    options.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    options.ceres.solver_options.num_threads = _threads(config)
    setup = pycolmap.BundleAdjustmentConfig()
    priors = []
    for image_id in reconstruction.reg_image_ids():
        image = reconstruction.image(image_id)
        setup.add_image(image_id)
        priors.append(pycolmap.PosePrior(
            corr_data_id=image.data_id, position=frames[image.name].position,
            position_covariance=np.eye(3) * config.pose_prior_m ** 2,
            coordinate_system=pycolmap.PosePriorCoordinateSystem.CARTESIAN))
    for camera_id in reconstruction.cameras:
        setup.set_constant_cam_intrinsics(camera_id)
    adjuster = pycolmap.create_pose_prior_bundle_adjuster(
        options, pycolmap.PosePriorBundleAdjustmentOptions(), setup, priors, reconstruction)
    adjuster.solve()


def _map_incremental(database: Path, frames_dir: Path, output: Path, total: int,
                     config: SfmConfig, intrinsics_known: bool) -> pycolmap.Reconstruction:
    watch = Stopwatch()
    registered = [0]

    def next_image() -> None:
        registered[0] += 1
        if registered[0] % 20 == 0:
            _progress(f"mapping: {registered[0]} registrations, {total} images "
                      f"({watch.elapsed():.1f} s)")

    options = _mapper_options(config, intrinsics_known)
    models = pycolmap.incremental_mapping(database, frames_dir, output, options,
                                          next_image_callback=next_image)
    if not models:
        return pycolmap.Reconstruction()
    return max(models.values(), key=lambda m: m.num_reg_images())


def _to_bed_frame(reconstruction: pycolmap.Reconstruction, frames: dict[str, ChosenFrame],
                  config: SfmConfig, frames_dir: Path) -> tuple[Similarity, dict]:
    """Move the model onto the recorded camera centres (robust similarity, in place)."""
    images = [im for im in reconstruction.images.values() if im.has_pose]
    centres = np.array([im.projection_center() for im in images])
    recorded = np.array([frames[im.name].position for im in images])
    try:
        similarity, inliers = robust_similarity(centres, recorded, config.align_threshold_m,
                                                seed=config.seed)
    except InputError as err:
        raise InputError(frames_dir, f"cannot align the reconstruction to the recorded camera "
                         f"positions: {err.problem}") from None
    reconstruction.transform(pycolmap.Sim3d(similarity.scale,
                                            pycolmap.Rotation3d(similarity.rotation),
                                            similarity.translation))
    return similarity, residuals(similarity, centres, recorded, inliers)


def _cloud(reconstruction: pycolmap.Reconstruction) -> Cloud:
    points = reconstruction.points3D.values()
    xyz = np.array([p.xyz for p in points], dtype=np.float64).reshape(-1, 3)
    rgb = np.array([p.color for p in points], dtype=np.uint8).reshape(-1, 3)
    return Cloud(xyz, rgb)


def _model(mode: str, database: Path, frames_dir: Path, sparse_dir: Path,
           frames: dict[str, ChosenFrame], config: SfmConfig, intrinsics_known: bool,
           watch: Stopwatch) -> pycolmap.Reconstruction:
    """Poses and filtered points from the matched database, by `mode`; times each step
    on `watch`."""
    if mode == "incremental":
        _progress(f"incremental mapping of {len(frames)} images")
        with watch.step("mapping"):
            reconstruction = _map_incremental(database, frames_dir, sparse_dir, len(frames),
                                              config, intrinsics_known)
            _filter_points(reconstruction, config)
        return reconstruction
    _progress(f"triangulating with the {len(frames)} recorded poses")
    with watch.step("triangulation"):
        reconstruction = _triangulate(_posed_reconstruction(database, frames), database,
                                      frames_dir, sparse_dir, config)
    if config.refine_poses:
        with watch.step("bundle_adjustment"):
            # Two-view points are mostly wrong matches: keep them out of the adjustment.
            pycolmap.ObservationManager(reconstruction).filter_points3D_with_short_tracks(
                config.min_track_length)
            _progress(f"bundle adjustment of {reconstruction.num_points3D()} points and "
                      f"{reconstruction.num_reg_images()} poses")
            _bundle_adjust(reconstruction, frames, config)
        with watch.step("triangulation"):
            # Matches the recorded poses were too far off to triangulate fit the refined
            # ones.
            reconstruction = _triangulate(reconstruction, database, frames_dir, sparse_dir,
                                          config)
    _filter_points(reconstruction, config)
    return reconstruction


def _pose_kind(frames_dir: Path, given: list[ChosenFrame]) -> str:
    """frames.json's pose kind (`frames.POSE_KINDS`), checked against its frames: all
    posed, or none and "poses": "none"."""
    kind = pose_kind(frames_dir)
    posed = sum(f.pose is not None for f in given)
    if posed and posed < len(given):
        raise InputError(frames_dir / "frames.json", f"{posed} of {len(given)} frames have a "
                         "pose: give every frame's or none")
    if not posed and kind != "none":
        raise InputError(frames_dir / "frames.json", 'no frame has a "pose": mark such a '
                         'folder "poses": "none" (flowerpose frames --images does)')
    if posed and kind == "none":
        raise InputError(frames_dir / "frames.json", '"poses": "none", yet the frames have '
                         "poses")
    return kind


def _pairs(frames: list[ChosenFrame], kind: str, config: SfmConfig) -> list[tuple[int, int]]:
    """The image pairs to match: sequential neighbours and, with poses, the nearest
    cameras looking the same way; without, every pair (`exhaustive_max_images`)."""
    count = len(frames)
    if kind == "none":
        if count <= config.exhaustive_max_images:
            return [(i, j) for i in range(count) for j in range(i + 1, count)]
        return sorted(sequential_pairs(count, 4 * config.sequential_overlap))
    positions = np.array([f.position for f in frames])
    rotations = np.array([f.rotation for f in frames])
    return sorted(sequential_pairs(count, config.sequential_overlap)
                  | pairs_from_poses(positions, rotations, config.pose_neighbours,
                                     config.max_view_angle_deg))


def _board_observations(reconstruction: pycolmap.Reconstruction, frames_dir: Path,
                        config: SfmConfig) -> tuple[dict, int]:
    """The board's corners in the registered photos: per corner id, (normalised image
    point, cam_from_world (3, 4)) per view that saw it; and how many views saw it."""
    observations: dict[int, list] = {}
    views = 0
    for image in reconstruction.images.values():
        if not image.has_pose:
            continue
        grey = cv2.imread(str(frames_dir / image.name), cv2.IMREAD_GRAYSCALE)
        ids, pixels = find_corners(grey, config.board_spec)
        if len(ids) == 0:
            continue
        views += 1
        camera = reconstruction.cameras[image.camera_id]
        # OpenCV puts the first pixel's centre at 0, COLMAP at 0.5.
        rays = camera.cam_from_img(pixels + 0.5)
        projection = image.cam_from_world().matrix()
        for corner, ray in zip(ids, rays, strict=True):
            observations.setdefault(int(corner), []).append((ray, projection))
    return observations, views


def _place_on_board(reconstruction: pycolmap.Reconstruction, frames_dir: Path,
                    config: SfmConfig) -> tuple[Similarity, dict] | None:
    """The model put on the board (metric, z up out of its face, z = 0 on it), in place;
    None where the board is not seen (`config.board` "required": InputError)."""
    observations, views = _board_observations(reconstruction, frames_dir, config)
    centres = np.array([im.projection_center() for im in reconstruction.images.values()
                        if im.has_pose])
    try:
        if views < MIN_VIEWS:
            raise InputError(frames_dir, f"the board is seen in {views} photos (need "
                             f"{MIN_VIEWS})")
        similarity, fit = board_similarity(observations, centres, config.board_spec)
    except InputError as err:
        if config.board == "required":
            spec = config.board_spec
            raise InputError(frames_dir, f"no {spec.squares_x} x {spec.squares_y} ChArUco "
                             f"board ({spec.dictionary}) found: {err.problem}; print one "
                             "with flowerpose marker and put it flat beside the plant") from None
        return None
    reconstruction.transform(pycolmap.Sim3d(similarity.scale,
                                            pycolmap.Rotation3d(similarity.rotation),
                                            similarity.translation))
    _progress(f"the board: {fit['corners']} corners in {views} photos, "
              f"{1000 * fit['rms_m']:.2f} mm RMS from the printed ones")
    return similarity, {"kind": "board", "up_from": "the board's face", "rms_m": None,
                        "inliers": None, "scale_from": "the board", "board": {
                            **fit, "views": views}}


#: A pose-less model's ground: a plane within this fraction of the cameras' distance from
#: the scene holding at least GROUND_MIN_FRACTION of the sparse points (the table or the
#: soil round the pot, as the board would be).
GROUND_DISTANCE_FRACTION, GROUND_MIN_FRACTION = 0.01, 0.25


def ground_normal(points: np.ndarray, camera_distance: float, seed: int) -> np.ndarray | None:
    """The unit normal (either sign) of the dominant plane of a model's sparse points where
    one holds GROUND_MIN_FRACTION of them, else None (RANSAC, Open3D); model units."""
    if len(points) < 50 or camera_distance <= 0:
        return None
    from flowerpose.log import open3d

    o3d = open3d()
    o3d.utility.random.seed(seed)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    plane, inliers = cloud.segment_plane(GROUND_DISTANCE_FRACTION * camera_distance, 3, 500)
    if len(inliers) < GROUND_MIN_FRACTION * len(points):
        return None
    return np.asarray(plane[:3], np.float64)


def _level(reconstruction: pycolmap.Reconstruction, config: SfmConfig
           ) -> tuple[Similarity, dict]:
    """Put a pose-less model upright in place (`align.level_similarity`), scaled so that
    the cameras' median distance from the scene's centre (the points' median) is
    `config.camera_distance_m`: stated by the user, or assumed."""
    images = [im for im in reconstruction.images.values() if im.has_pose]
    centres = np.array([im.projection_center() for im in images])
    image_up = np.array([-im.cam_from_world().rotation.matrix()[1] for im in images])
    points = _cloud(reconstruction).points
    scene = np.median(points, axis=0) if len(points) else centres.mean(axis=0)
    distance = float(np.median(np.linalg.norm(centres - scene, axis=1)))
    level, how = level_similarity(centres, image_up, ground_normal(points, distance,
                                                                   config.seed))
    stated = config.camera_distance_m is not None
    scale = (config.camera_distance_m if stated else ASSUMED_CAMERA_DISTANCE_M) / distance
    similarity = Similarity(scale, level.rotation, scale * level.translation)
    reconstruction.transform(pycolmap.Sim3d(similarity.scale,
                                            pycolmap.Rotation3d(similarity.rotation),
                                            similarity.translation))
    return similarity, {"kind": "levelled", "up_from": how, "rms_m": None, "inliers": None,
                        "scale_from": "the camera distance stated" if stated
                        else f"an assumed camera distance of {ASSUMED_CAMERA_DISTANCE_M} m"}


def _distinct_frames(frames_dir: Path, given: list[ChosenFrame], config: SfmConfig
                     ) -> list[ChosenFrame]:
    """The frames at distinct poses (all of them without poses); InputError when too few
    are left."""
    if len({f.file for f in given}) != len(given):
        raise InputError(frames_dir / "frames.json", "an image is listed twice")
    if given and given[0].pose is None:
        if len(given) < max(3, config.min_registered):
            raise InputError(frames_dir, f"{len(given)} images: structure from motion needs at "
                             f"least {max(3, config.min_registered)}")
        return list(given)
    distinct = distinct_poses(np.array([f.position for f in given]).reshape(-1, 3),
                              np.array([f.rotation for f in given]).reshape(-1, 3, 3))
    frames = [f for f, keep in zip(given, distinct, strict=True) if keep]
    repeated = f" at distinct poses ({len(given)} given)" if len(frames) < len(given) else ""
    need = max(3, config.min_registered)
    if len(frames) < need:
        raise InputError(frames_dir, f"{len(frames)} images{repeated}: structure from motion "
                         f"needs at least {need}")
    if repeated:
        _progress(f"{len(given) - len(frames)} of {len(given)} frames repeat an earlier "
                  "frame's pose: left out")
    return frames


def reconstruct_sparse(frames_dir: Path, work_dir: Path, config: SfmConfig | None = None
                       ) -> SparseResult:
    """Sparse reconstruction of a frames folder, in the bed frame (metres, z up).

    Reads frames_dir/frames.json (images and recorded camera-to-bed poses) and camera.json
    when present; writes the database, the pairs, work_dir/sparse/ (COLMAP model, bed
    frame), sparse.ply and sparse.json. Raises InputError naming the frames folder when
    fewer than config.min_registered images, or fewer than config.min_registered_fraction
    of them, register.
    """
    if pycolmap is None:
        raise missing_extra("pycolmap", "flowerpose reconstruct")
    config = config or SfmConfig()
    frames_dir, work_dir = Path(frames_dir), Path(work_dir)
    if not frames_dir.is_dir():
        raise InputError(frames_dir, "frames folder not found")
    watch = Stopwatch()
    given = read_frames(frames_dir, need_poses=False)
    kind = _pose_kind(frames_dir, given)
    frames = _distinct_frames(frames_dir, given, config)
    names = [f.file for f in frames]
    by_name = dict(zip(names, frames, strict=True))
    camera_path = frames_dir / "camera.json"
    width, height = image_size(frames_dir / names[0])
    intrinsics = None
    if camera_path.exists():
        intrinsics = read_intrinsics(camera_path).scaled(width, height)
    mode = config.mode
    if mode == "poses" and (intrinsics is None or intrinsics.estimated):
        _progress("the camera is not calibrated: running incremental mapping, which "
                  "estimates it")
        mode = "incremental"
    elif mode == "poses" and kind in ("rough", "none"):
        _progress(f"poses {'rough' if kind == 'rough' else 'unknown'}: running incremental "
                  "mapping")
        mode = "incremental"

    work_dir.mkdir(parents=True, exist_ok=True)
    database = work_dir / "database.db"
    sparse_dir = work_dir / "sparse"
    for stale in (database, sparse_dir):
        if stale.is_dir():
            shutil.rmtree(stale)
        elif stale.exists():
            stale.unlink()
    sparse_dir.mkdir()
    pycolmap.set_random_seed(config.seed)
    with _colmap_logging(config.colmap_log):
        with watch.step("features"):
            _extract(database, frames_dir, names, intrinsics, mode, kind, max(width, height),
                     config)
        with watch.step("matching"):
            pairs = _pairs(frames, kind, config)
            if mode == "poses":
                positions = np.array([f.position for f in frames])
                # Without a baseline the epipolar geometry checks nothing.
                pairs = [(i, j) for i, j in pairs if np.linalg.norm(
                    positions[i] - positions[j]) >= config.min_baseline_m]
                _match_with_poses(database, names, pairs, frames, config)
            else:
                _match_ransac(database, work_dir, names, pairs, config)
            _write_pairs(work_dir / "pairs.txt", names, pairs)

        reconstruction = _model(mode, database, frames_dir, sparse_dir, by_name, config,
                                intrinsics is not None and not intrinsics.estimated, watch)

    registered = [im for im in reconstruction.images.values()
                  if im.has_pose and im.num_points3D >= MIN_IMAGE_POINTS]
    wanted = max(config.min_registered, int(np.ceil(config.min_registered_fraction
                                                    * len(frames))))
    if len(registered) < wanted:
        raise InputError(frames_dir, f"only {len(registered)} of {len(frames)} images registered "
                         f"(need {wanted}): too blurry, too little texture or too little "
                         "overlap between frames")

    with watch.step("alignment"):
        if kind == "none":
            placed = _place_on_board(reconstruction, frames_dir, config) \
                if config.board != "off" else None
            similarity, alignment = placed or _level(reconstruction, config)
        else:
            similarity, alignment = _to_bed_frame(reconstruction, by_name, config, frames_dir)
    for stale in sparse_dir.iterdir():
        if stale.is_dir():
            shutil.rmtree(stale)
    reconstruction.write(sparse_dir)
    cloud = _cloud(reconstruction)
    write_cloud(work_dir / "sparse.ply", cloud)
    seconds = watch.report(digits=3)
    camera = next(iter(reconstruction.cameras.values()))
    report = {
        "frames": str(frames_dir), "mode": mode, "poses": kind,
        "intrinsics": "camera.json" if intrinsics is not None and not intrinsics.estimated
        else "estimated",
        "camera": {"model": camera.model.name, "width": camera.width,
                   "height": camera.height, "params": [float(v) for v in camera.params]},
        "images_given": len(given), "images_used": len(frames),
        "images_registered": len(registered),
        "images_posed": reconstruction.num_reg_images(), "pairs": len(pairs),
        "points": reconstruction.num_points3D(),
        "mean_track_length": float(reconstruction.compute_mean_track_length()),
        "mean_reprojection_error_px": float(reconstruction.compute_mean_reprojection_error()),
        "alignment": {**alignment, "scale": similarity.scale,
                      "threshold_m": config.align_threshold_m},
        "alignment_rms_m": alignment["rms_m"],
        "metric": kind != "none" or alignment["kind"] == "board"
        or config.camera_distance_m is not None,
        "seconds": seconds,
        "config": dataclasses.asdict(config),
    }
    write_json(work_dir / "sparse.json", report)
    placed = (f"camera centres {1000 * alignment['rms_m']:.1f} mm RMS from the given ones"
              if kind != "none" else f"levelled by {alignment['up_from']}, scale from "
              f"{alignment['scale_from']}")
    _progress(f"{len(registered)}/{len(frames)} images, {report['points']} points, reprojection "
              f"{report['mean_reprojection_error_px']:.2f} px, {placed} "
              f"({seconds['total']:.1f} s)")
    return SparseResult(reconstruction, cloud, report)
