"""The sparse stage's features and matches, written into the COLMAP database
(work_dir/database.db) that mapping reads.

Each frame's SIFT features (`extract_features`, sized by `sfm_config.feature_defaults`);
the image pairs to match (`image_pairs`: sequential neighbours, the nearest recorded
cameras looking the same way, or every pair of frames without poses); and their matches,
either guided by the recorded poses (`match_on_poses`: epipolar lines in pixels of the
full image, the matches stored as verified two-view geometries) or by COLMAP's matcher
and RANSAC (`match_with_ransac`). Camera positions are metres in the bed frame, rotations
camera-to-bed.
"""

from __future__ import annotations

# cv2 before pycolmap (sfm.py says why).
import cv2  # noqa: F401  # isort: skip

from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

try:
    import pycolmap
except ImportError:  # the [recon] extra is not installed: the settings still load
    pycolmap = None

from flowerpose.atomic import write_text
from flowerpose.log import Tally
from flowerpose.pipeline.frames import ChosenFrame
from flowerpose.pipeline.sfm_config import SfmConfig, feature_defaults, threads
from flowerpose.processes import reclaim_sigterm
from flowerpose.scanio import Intrinsics

# Importing pycolmap gave SIGTERM to glog, which prints a C stack dump and kills the process.
reclaim_sigterm()

#: Fewest matches for an image pair to count (COLMAP's two_view_geometry min_num_inliers).
MIN_PAIR_MATCHES = 15


def extract_features(database: Path, frames_dir: Path, names: list[str],
                     intrinsics: Intrinsics | None, mode: str, kind: str, longest_side: int,
                     config: SfmConfig) -> None:
    """The frames `names` (in frames_dir) entered into a new `database` in that order, one
    camera for all (camera.json's `intrinsics` fixed where calibrated, else refined from
    its estimate or COLMAP's), and their SIFT features: sized by `feature_defaults` from
    the stage's `mode`, the frames' pose `kind` and their longest side, pixels, where
    `config` leaves them unset."""
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
    options.num_threads = threads(config)
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


def image_pairs(frames: list[ChosenFrame], kind: str, config: SfmConfig
                ) -> list[tuple[int, int]]:
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


def write_pairs(path: Path, names: list[str], pairs: list[tuple[int, int]]) -> Path:
    """The pairs (indices into `names`) as COLMAP's match list: one "NAME1 NAME2" line each."""
    return write_text(path, "".join(f"{names[i]} {names[j]}\n" for i, j in pairs))


def match_with_ransac(database: Path, work_dir: Path, names: list[str],
                      pairs: list[tuple[int, int]], config: SfmConfig) -> None:
    """COLMAP's matcher and RANSAC verification on the pairs (images alone)."""
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = threads(config)
    matching.sift.max_ratio = config.max_ratio
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = config.seed
    chunk = 200
    part = work_dir / "pairs_part.txt"
    with Tally(len(pairs), "matching") as tally:
        for first in range(0, len(pairs), chunk):
            batch = pairs[first:first + chunk]
            write_pairs(part, names, batch)
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


def match_on_poses(database: Path, names: list[str],
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

        with ThreadPoolExecutor(threads(config)) as pool, \
                Tally(len(pairs), "matching") as tally:
            for done, (id1, id2, geometry) in enumerate(pool.map(match, pairs), 1):
                if geometry is not None:
                    db.write_matches(id1, id2, geometry.inlier_matches)
                    db.write_two_view_geometry(id1, id2, geometry)
                tally.advance(1, f"sfm: matched {done}/{len(pairs)} pairs on the recorded poses"
                              if done % 200 == 0 or done == len(pairs) else None)
    finally:
        db.close()
