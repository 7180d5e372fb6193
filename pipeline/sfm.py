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

This module is the stage's driver: the frames it uses, the mapping (triangulation on the
recorded poses with bundle adjustment, or incremental mapping) and the report. Its
settings are `sfm_config.py`'s, the features and matches `sfm_matching.py`'s, where the
model goes in the bed frame `sfm_placement.py`'s.
"""

from __future__ import annotations

# cv2 must be imported before pycolmap: the other order makes a later cv2.imwrite of a PNG
# abort the process (both bundle libpng; double free). tests/pipeline/test_sfm.py keeps it
# caught.
import cv2  # noqa: F401  # isort: skip

import contextlib
import dataclasses
import shutil
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

try:
    import pycolmap
except ImportError:  # the [recon] extra is not installed: the settings still load
    pycolmap = None

from flowerpose.cloudio import Cloud, write_cloud
from flowerpose.errors import InputError, missing_extra
from flowerpose.jsonio import write_json
from flowerpose.log import LOG
from flowerpose.pipeline.frames import ChosenFrame, distinct_views, pose_kind, read_frames
from flowerpose.pipeline.sfm_config import SfmConfig, threads
from flowerpose.pipeline.sfm_matching import (
    extract_features,
    image_pairs,
    match_on_poses,
    match_with_ransac,
    write_pairs,
)
from flowerpose.pipeline.sfm_placement import (
    levelled,
    onto_board,
    onto_recorded_centres,
    sparse_cloud,
)
from flowerpose.processes import reclaim_sigterm
from flowerpose.scanio import image_size, read_intrinsics
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


def _mapper_options(config: SfmConfig, intrinsics_known: bool
                    ) -> pycolmap.IncrementalPipelineOptions:
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = threads(config)
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
    options.ceres.solver_options.num_threads = threads(config)
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
            extract_features(database, frames_dir, names, intrinsics, mode, kind,
                             max(width, height), config)
        with watch.step("matching"):
            pairs = image_pairs(frames, kind, config)
            if mode == "poses":
                positions = np.array([f.position for f in frames])
                # Without a baseline the epipolar geometry checks nothing.
                pairs = [(i, j) for i, j in pairs if np.linalg.norm(
                    positions[i] - positions[j]) >= config.min_baseline_m]
                match_on_poses(database, names, pairs, frames, config)
            else:
                match_with_ransac(database, work_dir, names, pairs, config)
            write_pairs(work_dir / "pairs.txt", names, pairs)

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
            placed = onto_board(reconstruction, frames_dir, config) \
                if config.board != "off" else None
            similarity, alignment = placed or levelled(reconstruction, config)
        else:
            similarity, alignment = onto_recorded_centres(reconstruction, by_name, config,
                                                          frames_dir)
        reconstruction.transform(pycolmap.Sim3d(similarity.scale,
                                                pycolmap.Rotation3d(similarity.rotation),
                                                similarity.translation))
    for stale in sparse_dir.iterdir():
        if stale.is_dir():
            shutil.rmtree(stale)
    reconstruction.write(sparse_dir)
    cloud = sparse_cloud(reconstruction)
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
