"""Photogrammetry of a frames folder: sparse structure from motion, then dense stereo.

    frames_dir (`flowerpose frames`: frames/*.jpg, frames.json with the bot's poses,
    camera.json)
      -> out_dir/database.db, pairs.txt, sparse/, sparse.ply, sparse.json   (`sfm.py`)
      -> out_dir/cloud.ply            the dense coloured cloud, metres, bed frame, z up
      -> out_dir/reconstruction.json  images registered, the alignment residual, point
                                      counts, seconds per stage, the config

The sparse stage refines the camera poses and moves them into the bed frame (a robust
similarity onto the bot's recorded camera centres); the dense stage then runs on those
refined poses, so a real bot's pose errors (millimetres, fractions of a degree) do not
smear the cloud. Dense stereo is semi-global matching on the CPU (`dense.py`), or COLMAP's
PatchMatch where pycolmap has CUDA (`patch_match.py`, out_dir/mvs/).
"""

from __future__ import annotations

# cv2 before pycolmap (sfm.py says why).
import cv2  # isort: skip

import dataclasses
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from flowerpose.atomic import write_image
from flowerpose.cloudio import Cloud, write_cloud
from flowerpose.errors import InputError
from flowerpose.jsonio import write_json
from flowerpose.outputs import check_output, publish, staging_folder
from flowerpose.pipeline.dense import DenseConfig, reconstruct_dense
from flowerpose.pipeline.patch_match import cuda_available, reconstruct_patch_match
from flowerpose.pipeline.sfm import MIN_IMAGE_POINTS, SparseResult, reconstruct_sparse
from flowerpose.pipeline.sfm_config import FULL_IMAGE_SIZE, SfmConfig
from flowerpose.scanio import Intrinsics
from flowerpose.stopwatch import Stopwatch


@dataclass(frozen=True)
class ReconstructConfig:
    """Sparse then dense reconstruction of a frames folder."""

    sfm: SfmConfig = field(default_factory=SfmConfig)
    """The sparse stage (features, matching, poses, alignment to the bed frame)."""
    dense: DenseConfig = field(default_factory=DenseConfig)
    """The CPU dense stage (pairwise semi-global matching and multi-view fusion)."""
    dense_method: Literal["auto", "sgbm", "patch_match"] = "auto"
    """Dense stereo: "sgbm" (pairwise semi-global matching on the CPU, `dense.py`),
    "patch_match" (COLMAP's PatchMatch stereo and fusion, which needs pycolmap built with
    CUDA, `patch_match.py`), or "auto": patch_match where pycolmap has CUDA, else sgbm."""
    dense_poses: Literal["refined", "recorded"] = "refined"
    """Camera poses sgbm uses: "refined" (the sparse stage's, in the bed frame;
    frames that did not register are left out) or "recorded" (frames.json's, as the bot
    logged them; every frame)."""


@dataclass
class Reconstruction:
    """A reconstructed frames folder."""

    cloud: Cloud
    """The dense cloud: points (N, 3) metres, bed frame, colours (N, 3) uint8."""
    sparse: SparseResult
    """The sparse model, points and its report."""
    report: dict
    """reconstruction.json's content."""


def refined_poses(sparse: SparseResult) -> dict[str, np.ndarray]:
    """Camera-to-bed (4, 4) poses, metres, OpenCV camera axes, of the registered images
    (posed, and seeing at least `MIN_IMAGE_POINTS` points), keyed by image name (the
    frame's file as frames.json names it)."""
    poses = {}
    for image in sparse.reconstruction.images.values():
        if not image.has_pose or image.num_points3D < MIN_IMAGE_POINTS:
            continue
        cam_from_bed = np.eye(4)
        cam_from_bed[:3] = image.cam_from_world().matrix()
        poses[image.name] = np.linalg.inv(cam_from_bed)
    return poses


def sparse_intrinsics(sparse: SparseResult) -> Intrinsics:
    """The pinhole camera the sparse model used (camera.json's, at the frames' size)."""
    camera = next(iter(sparse.reconstruction.cameras.values()))
    fx, fy, cx, cy = (float(v) for v in camera.params)
    return Intrinsics(camera.width, camera.height, fx, fy, cx, cy)


def undistorted_frames(sparse: SparseResult, frames_dir: Path, out_dir: Path
                       ) -> tuple[Path, Intrinsics]:
    """The registered frames of a sparse model whose camera the mapping estimated (with a
    distortion), undistorted to a pinhole for dense stereo: out_dir/frames/ with
    frames.json (the same "file" names) and camera.json. Returns out_dir and the pinhole."""
    from flowerpose.pipeline.undistort import Undistorter

    undistort = Undistorter(next(iter(sparse.reconstruction.cameras.values())))
    poses = refined_poses(sparse)
    entries = []
    for k, name in enumerate(sorted(poses)):
        rgb = cv2.cvtColor(cv2.imread(str(frames_dir / name), cv2.IMREAD_COLOR),
                           cv2.COLOR_BGR2RGB)
        write_image(out_dir / name, undistort(rgb), [cv2.IMWRITE_JPEG_QUALITY, 95])
        entries.append({"index": k, "file": name})
    intrinsics = undistort.intrinsics
    write_json(out_dir / "camera.json", intrinsics.to_json())
    write_json(out_dir / "frames.json", {"poses": "none", "frames": entries})
    return out_dir, intrinsics


#: What a reconstruction writes in its folder (`outputs.check_output` refuses a folder where
#: one of them is there and not an earlier reconstruction's, before minutes of work).
RECONSTRUCT_OUTPUTS = ("cloud.ply", "database.db", "pairs.txt", "reconstruction.json",
                       "sparse", "sparse.json", "sparse.ply", "mvs", "undistorted")


def reconstruct(frames_dir: str | Path, out_dir: str | Path,
                config: ReconstructConfig = ReconstructConfig(),
                progress: bool = True, overwrite: bool = False) -> Reconstruction:
    """Dense cloud of a frames folder in the bed frame; writes out_dir (see the module).

    Raises InputError naming the frames folder when too few images register
    (`SfmConfig.min_registered`, `min_registered_fraction`) or no stereo pair is usable.
    """
    frames_dir, out_dir = Path(frames_dir), Path(out_dir)
    if not frames_dir.is_dir():
        raise InputError(frames_dir, "frames folder not found (make one with flowerpose frames)")
    if not (frames_dir / "camera.json").is_file():
        # Checked first: the sparse stage alone could estimate a distorted camera, but
        # dense stereo needs a calibrated pinhole, and would fail only minutes later.
        raise InputError(frames_dir / "camera.json", "not found: dense reconstruction needs "
                         "the camera's intrinsics (flowerpose frames copies the scan's)")
    # The work happens beside out_dir and moves in only when whole: a run that fails
    # leaves an earlier reconstruction in out_dir as it was (`outputs.publish`).
    check_output(out_dir, "reconstruct", overwrite, RECONSTRUCT_OUTPUTS)
    staging = staging_folder(out_dir)
    try:
        result = _reconstruct(frames_dir, staging, out_dir, config, progress)
        publish(staging, out_dir, "reconstruct", overwrite)
    finally:
        if staging.exists():
            shutil.rmtree(staging)
    return result


def _reconstruct(frames_dir: Path, work_dir: Path, out_dir: Path, config: ReconstructConfig,
                 progress: bool) -> Reconstruction:
    """`reconstruct`'s work in work_dir, its report naming where the files will be."""
    watch = Stopwatch()
    sparse = reconstruct_sparse(frames_dir, work_dir, config.sfm)
    watch.lap("sparse")
    method = config.dense_method
    if method == "auto":
        method = "patch_match" if cuda_available() else "sgbm"
    if method == "patch_match":
        cloud, dense_report = reconstruct_patch_match(frames_dir, work_dir / "sparse",
                                                      work_dir / "mvs",
                                                      config.sfm.max_image_size
                                                      or FULL_IMAGE_SIZE)
    else:
        poses = refined_poses(sparse) if config.dense_poses == "refined" else None
        stereo_frames, intrinsics = frames_dir, None
        if sparse.report["intrinsics"] == "estimated":
            # The mapping estimated a distortion: stereo needs a pinhole, and frames.json's
            # poses (if any) are not the images' refined ones.
            stereo_frames, intrinsics = undistorted_frames(sparse, frames_dir,
                                                           work_dir / "undistorted")
            poses = refined_poses(sparse)
        cloud, dense_report = reconstruct_dense(stereo_frames, poses=poses,
                                                intrinsics=intrinsics
                                                or sparse_intrinsics(sparse),
                                                config=config.dense, progress=progress,
                                                scene_points=sparse.cloud.points)
    write_cloud(work_dir / "cloud.ply", cloud)
    watch.lap("dense")
    sparse_report = {k: v for k, v in sparse.report.items() if k != "config"}
    report = {
        "frames": str(frames_dir),
        "cloud": str(out_dir / "cloud.ply"),
        "points": len(cloud),
        "images_used": sparse_report["images_used"],
        "images_registered": sparse_report["images_registered"],
        "alignment_rms_m": sparse_report["alignment_rms_m"],
        "alignment": sparse_report["alignment"],
        "metric": sparse_report["metric"],
        "dense_method": method,
        "dense_poses": config.dense_poses if method == "sgbm" else "refined",
        "seconds": watch.report(digits=3),
        "sparse": sparse_report,
        "dense": {k: v for k, v in dense_report.items() if k != "config"},
        "config": dataclasses.asdict(config),
    }
    write_json(work_dir / "reconstruction.json", report)
    return Reconstruction(cloud, sparse, report)
