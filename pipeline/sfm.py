"""Sparse reconstruction of a frames folder with pycolmap, in the bed frame.

    frames_dir/frames.json, frames/*.jpg, camera.json (optional)   (`flowerpose frames`)
      -> work_dir/database.db      SIFT features and verified matches
      -> work_dir/pairs.txt        the image pairs matched: sequential + nearby poses
      -> work_dir/sparse/          the COLMAP model, already in the bed frame (metres)
      -> work_dir/sparse.ply       its points, coloured
      -> work_dir/sparse.json      the report (counts, errors, alignment, seconds, config)

Two ways to get camera poses (SfmConfig.mode):
- "poses": the bot's recorded poses are the cameras; points are triangulated with them and
  refined by bundle adjustment (optionally the poses too). Needs camera.json.
- "incremental": COLMAP's full incremental mapping from the images alone.
Either way a robust similarity from the reconstructed camera centres to the recorded ones
puts the model in the bed frame, and its residual is reported.
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
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import pycolmap

from flowerpose.cloudio import Cloud, write_cloud
from flowerpose.errors import InputError
from flowerpose.pipeline.align import Similarity, residuals, robust_similarity
from flowerpose.jsonio import read_json, write_json
from flowerpose.scanio import Intrinsics, read_intrinsics

#: An image that sees fewer triangulated points than this counts as not registered (the
#: inliers COLMAP's mapper asks of a new image's pose, abs_pose_min_num_inliers).
MIN_IMAGE_POINTS = 30


@dataclass(frozen=True)
class SfmConfig:
    """How the sparse reconstruction runs."""

    max_image_size: int = 1024
    """Longest image side SIFT sees, pixels; larger frames are downscaled for extraction
    (keypoints are scaled back to the full image)."""
    max_features: int = 4096
    """Most SIFT features kept per image (COLMAP: 8192; half costs a quarter of the
    brute-force matching at equal accuracy on scans)."""
    first_octave: int = -1
    """SIFT's first octave: -1 doubles the image first (COLMAP's default, most features),
    0 starts at full size (much faster, fewer small-scale features)."""
    sequential_overlap: int = 5
    """Each frame is matched with this many following frames of the scan."""
    pose_neighbours: int = 6
    """And with this many nearest recorded camera centres (neighbouring rings of the path)."""
    max_view_angle_deg: float = 60.0
    """Pose pairs only between cameras whose optical axes differ by at most this."""
    mode: Literal["poses", "incremental"] = "poses"
    """"poses": triangulate with the recorded poses, then bundle adjustment; "incremental":
    COLMAP's incremental mapping from the images alone. Without camera.json the
    intrinsics are unknown and incremental mapping runs (it estimates them)."""
    refine_poses: bool = True
    """In "poses" mode, let bundle adjustment also refine the camera poses (a real bot's
    recorded poses are off by millimetres and a degree or so)."""
    align_threshold_m: float = 0.02
    """Camera centres farther than this from their recorded position after alignment are
    outliers of the similarity to the bed frame, metres."""
    min_registered: int = 3
    """Fewest registered images accepted."""
    min_registered_fraction: float = 0.5
    """Smallest fraction of the images given that must register."""
    num_threads: int = 0
    """Threads for extraction, matching and mapping; 0: every core."""
    seed: int = 0
    """Random seed for COLMAP's RANSAC and mapping and for the alignment."""
    colmap_log: bool = False
    """Show COLMAP's own log lines (stderr) besides the progress lines."""


@dataclass
class SparseResult:
    """A sparse reconstruction in the bed frame."""

    reconstruction: pycolmap.Reconstruction
    """Cameras, images and points, metres, bed frame (cam_from_world maps bed to camera)."""
    cloud: Cloud
    """The triangulated points, metres, bed frame, with their colours."""
    report: dict
    """Counts, errors, the alignment residual, seconds per step and the config."""


@dataclass(frozen=True)
class FrameRecord:
    """One frame of frames.json."""

    name: str
    """Image path relative to the frames folder (COLMAP's image name)."""
    position: np.ndarray
    """(3,) recorded camera centre, metres, bed frame."""
    rotation: np.ndarray
    """(3, 3) camera-to-bed rotation, OpenCV camera axes."""


def _progress(message: str) -> None:
    print(f"sfm: {message}", file=sys.stderr, flush=True)


@contextlib.contextmanager
def _colmap_logging(show: bool) -> Iterator[None]:
    """COLMAP's INFO lines hidden unless asked for (they are hundreds per step)."""
    before = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 0 if show else 2
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = before


def read_frames(frames_dir: Path) -> list[FrameRecord]:
    """frames.json's frames with their recorded poses, checked (images present, poses
    finite and rotations proper)."""
    path = Path(frames_dir) / "frames.json"
    data = read_json(path)
    entries = data.get("frames")
    if not isinstance(entries, list):
        raise InputError(path, "expected a \"frames\" list")
    frames = []
    for k, entry in enumerate(entries):
        try:
            name = str(entry["file"])
            position = np.asarray(entry["pose"]["position"], dtype=np.float64)
            rotation = np.asarray(entry["pose"]["rotation"], dtype=np.float64)
        except (KeyError, TypeError, ValueError):
            raise InputError(path, f"frame {k} needs \"file\" and \"pose\" with \"position\" "
                             "(3) and \"rotation\" (3 x 3)") from None
        if position.shape != (3,) or rotation.shape != (3, 3) or not (
                np.isfinite(position).all() and np.isfinite(rotation).all()):
            raise InputError(path, f"frame {k}: pose needs a finite position (3) and "
                             "rotation (3 x 3)")
        if np.abs(rotation.T @ rotation - np.eye(3)).max() > 1e-4 or np.linalg.det(rotation) < 0:
            raise InputError(path, f"frame {k}: pose rotation is not a proper rotation")
        if not (Path(frames_dir) / name).is_file():
            raise InputError(Path(frames_dir) / name, "image listed in frames.json not found")
        frames.append(FrameRecord(name, position, rotation))
    return frames


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


def _image_size(path: Path) -> tuple[int, int]:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InputError(path, "unreadable image")
    return image.shape[1], image.shape[0]


def _threads(config: SfmConfig) -> int:
    return config.num_threads if config.num_threads > 0 else (os.cpu_count() or 1)


def _extract(database: Path, frames_dir: Path, names: list[str],
             intrinsics: Intrinsics | None, config: SfmConfig) -> None:
    reader = pycolmap.ImageReaderOptions()
    if intrinsics is not None:
        reader.camera_model = "PINHOLE"
        reader.camera_params = ",".join(repr(float(v)) for v in (
            intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy))
    else:
        reader.camera_model = "SIMPLE_RADIAL"
    options = pycolmap.FeatureExtractionOptions()
    options.max_image_size = config.max_image_size
    options.num_threads = _threads(config)
    options.sift.max_num_features = config.max_features
    options.sift.first_octave = config.first_octave
    chunk = 25
    start = time.perf_counter()
    for first in range(0, len(names), chunk):
        pycolmap.extract_features(database, frames_dir, image_names=names[first:first + chunk],
                                  camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, extraction_options=options,
                                  device=pycolmap.Device.cpu)
        done = min(len(names), first + chunk)
        _progress(f"features {done}/{len(names)} images ({time.perf_counter() - start:.1f} s)")


def _match(database: Path, pairs_path: Path, names: list[str], pairs: list[tuple[int, int]],
           config: SfmConfig) -> None:
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = _threads(config)
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = config.seed
    chunk = 200
    start = time.perf_counter()
    for first in range(0, len(pairs), chunk):
        part = pairs[first:first + chunk]
        pairs_path.write_text("".join(f"{names[i]} {names[j]}\n" for i, j in part))
        pycolmap.match_image_pairs(
            database, matching_options=matching,
            pairing_options=pycolmap.ImportedPairingOptions(match_list_path=pairs_path),
            verification_options=verification, device=pycolmap.Device.cpu)
        done = min(len(pairs), first + chunk)
        _progress(f"matched {done}/{len(pairs)} pairs ({time.perf_counter() - start:.1f} s)")
    pairs_path.write_text("".join(f"{names[i]} {names[j]}\n" for i, j in pairs))


def _mapper_options(config: SfmConfig, intrinsics_known: bool) -> pycolmap.IncrementalPipelineOptions:
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


def _cam_from_world(frame: FrameRecord) -> pycolmap.Rigid3d:
    rotation = frame.rotation.T
    return pycolmap.Rigid3d(pycolmap.Rotation3d(rotation), -rotation @ frame.position)


def _posed_reconstruction(database: Path, frames: dict[str, FrameRecord]
                          ) -> pycolmap.Reconstruction:
    """The database's cameras and images, each at its recorded pose (no points yet)."""
    db = pycolmap.Database.open(database)
    try:
        reconstruction = pycolmap.Reconstruction()
        for camera in db.read_all_cameras():
            reconstruction.add_camera_with_trivial_rig(camera)
        for image in db.read_all_images():
            posed = pycolmap.Image(name=image.name, camera_id=image.camera_id,
                                   image_id=image.image_id)
            reconstruction.add_image_with_trivial_frame(posed,
                                                        _cam_from_world(frames[image.name]))
    finally:
        db.close()
    return reconstruction


def _triangulate(database: Path, frames_dir: Path, output: Path,
                 frames: dict[str, FrameRecord], config: SfmConfig) -> pycolmap.Reconstruction:
    reconstruction = _posed_reconstruction(database, frames)
    return pycolmap.triangulate_points(reconstruction, database, frames_dir, output,
                                       clear_points=True,
                                       options=_mapper_options(config, True),
                                       refine_intrinsics=False)


def _bundle_adjust(reconstruction: pycolmap.Reconstruction, config: SfmConfig) -> None:
    """Refine points and poses (intrinsics fixed), then drop points that no longer fit."""
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_focal_length = False
    options.refine_principal_point = False
    options.refine_extra_params = False
    options.print_summary = False
    options.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    options.ceres.solver_options.num_threads = _threads(config)
    pycolmap.bundle_adjustment(reconstruction, options)
    pipeline = pycolmap.IncrementalPipelineOptions()
    pycolmap.ObservationManager(reconstruction).filter_all_points3D(
        pipeline.mapper.filter_max_reproj_error, pipeline.mapper.filter_min_tri_angle)


def _map_incremental(database: Path, frames_dir: Path, output: Path, total: int,
                     config: SfmConfig, intrinsics_known: bool) -> pycolmap.Reconstruction:
    start = time.perf_counter()
    registered = [0]

    def next_image() -> None:
        registered[0] += 1
        if registered[0] % 10 == 0:
            _progress(f"mapping: {registered[0]} images registered of {total} "
                      f"({time.perf_counter() - start:.1f} s)")

    options = _mapper_options(config, intrinsics_known)
    models = pycolmap.incremental_mapping(database, frames_dir, output, options,
                                          next_image_callback=next_image)
    if not models:
        raise InputError(frames_dir, f"no reconstruction: COLMAP found no initial image pair "
                         f"among the {total} images (too little overlap or texture)")
    best = max(models.values(), key=lambda m: m.num_reg_images())
    return best


def _to_bed_frame(reconstruction: pycolmap.Reconstruction, frames: dict[str, FrameRecord],
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


def reconstruct_sparse(frames_dir: Path, work_dir: Path, config: SfmConfig | None = None
                       ) -> SparseResult:
    """Sparse reconstruction of a frames folder, in the bed frame (metres, z up).

    Reads frames_dir/frames.json (images and recorded camera-to-bed poses) and camera.json
    when present; writes the database, the pairs, work_dir/sparse/ (COLMAP model, bed
    frame), sparse.ply and sparse.json. Raises InputError naming the frames folder when
    fewer than config.min_registered images, or fewer than config.min_registered_fraction
    of them, register.
    """
    config = config or SfmConfig()
    frames_dir, work_dir = Path(frames_dir), Path(work_dir)
    if not frames_dir.is_dir():
        raise InputError(frames_dir, "frames folder not found")
    started = time.perf_counter()
    frames = read_frames(frames_dir)
    need = max(3, config.min_registered)
    if len(frames) < need:
        raise InputError(frames_dir, f"{len(frames)} images: structure from motion needs at "
                         f"least {need}")
    names = [f.name for f in frames]
    if len(set(names)) != len(names):
        raise InputError(frames_dir / "frames.json", "an image is listed twice")
    by_name = dict(zip(names, frames, strict=True))
    camera_path = frames_dir / "camera.json"
    intrinsics = None
    if camera_path.exists():
        width, height = _image_size(frames_dir / names[0])
        intrinsics = read_intrinsics(camera_path).scaled(width, height)
    mode = config.mode
    if mode == "poses" and intrinsics is None:
        _progress("no camera.json: intrinsics unknown, running incremental mapping")
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
    seconds: dict[str, float] = {}
    pycolmap.set_random_seed(config.seed)
    with _colmap_logging(config.colmap_log):
        tick = time.perf_counter()
        _extract(database, frames_dir, names, intrinsics, config)
        seconds["features"] = time.perf_counter() - tick

        tick = time.perf_counter()
        positions = np.array([f.position for f in frames])
        rotations = np.array([f.rotation for f in frames])
        pairs = sorted(sequential_pairs(len(frames), config.sequential_overlap)
                       | pairs_from_poses(positions, rotations, config.pose_neighbours,
                                          config.max_view_angle_deg))
        _match(database, work_dir / "pairs.txt", names, pairs, config)
        seconds["matching"] = time.perf_counter() - tick

        tick = time.perf_counter()
        if mode == "poses":
            _progress(f"triangulating with the {len(frames)} recorded poses")
            reconstruction = _triangulate(database, frames_dir, sparse_dir, by_name, config)
            seconds["triangulation"] = time.perf_counter() - tick
            if config.refine_poses:
                tick = time.perf_counter()
                _progress(f"bundle adjustment of {reconstruction.num_points3D()} points and "
                          f"{reconstruction.num_reg_images()} poses")
                _bundle_adjust(reconstruction, config)
                seconds["bundle_adjustment"] = time.perf_counter() - tick
        else:
            _progress(f"incremental mapping of {len(frames)} images")
            reconstruction = _map_incremental(database, frames_dir, sparse_dir, len(frames),
                                              config, intrinsics is not None)
            seconds["mapping"] = time.perf_counter() - tick

    seen = [im for im in reconstruction.images.values()
            if im.has_pose and im.num_points3D >= MIN_IMAGE_POINTS]
    wanted = max(config.min_registered, int(np.ceil(config.min_registered_fraction
                                                    * len(frames))))
    if len(seen) < wanted:
        raise InputError(frames_dir, f"only {len(seen)} of {len(frames)} images registered "
                         f"(need {wanted}): too blurry, too little texture or too little "
                         "overlap between frames")

    tick = time.perf_counter()
    similarity, alignment = _to_bed_frame(reconstruction, by_name, config, frames_dir)
    seconds["alignment"] = time.perf_counter() - tick
    for stale in sparse_dir.iterdir():
        if stale.is_dir():
            shutil.rmtree(stale)
    reconstruction.write(sparse_dir)
    cloud = _cloud(reconstruction)
    write_cloud(work_dir / "sparse.ply", cloud)
    seconds["total"] = time.perf_counter() - started
    camera = next(iter(reconstruction.cameras.values()))
    report = {
        "frames": str(frames_dir), "mode": mode,
        "intrinsics": "camera.json" if intrinsics is not None else "estimated",
        "camera": {"model": camera.model.name, "width": camera.width,
                   "height": camera.height, "params": [float(v) for v in camera.params]},
        "images_given": len(frames), "images_registered": len(seen),
        "images_posed": reconstruction.num_reg_images(), "pairs": len(pairs),
        "points": reconstruction.num_points3D(),
        "mean_track_length": float(reconstruction.compute_mean_track_length()),
        "mean_reprojection_error_px": float(reconstruction.compute_mean_reprojection_error()),
        "alignment": {**alignment, "scale": similarity.scale,
                      "threshold_m": config.align_threshold_m},
        "alignment_rms_m": alignment["rms_m"],
        "seconds": {k: round(v, 3) for k, v in seconds.items()},
        "config": dataclasses.asdict(config),
    }
    write_json(work_dir / "sparse.json", report)
    _progress(f"{len(seen)}/{len(frames)} images, {report['points']} points, reprojection "
              f"{report['mean_reprojection_error_px']:.2f} px, camera centres "
              f"{1000 * alignment['rms_m']:.1f} mm RMS from the recorded ones "
              f"({seconds['total']:.1f} s)")
    return SparseResult(reconstruction, cloud, report)
