"""Where the sparse model goes in the bed frame (metres, z up): the similarity from the
model's frame into it.

With the frames' poses, a robust similarity from the reconstructed camera centres onto the
recorded ones (`onto_recorded_centres`). Without: onto a printed ChArUco board where the
photos see it (`onto_board`: metric, z = 0 on the board, z up out of its face), else
levelled by the cameras and the ground plane (`levelled`: `align.level_similarity`),
scaled so the cameras stand `SfmConfig.camera_distance_m` (stated, or
`ASSUMED_CAMERA_DISTANCE_M`) from the scene. Each returns the similarity and the report's
"alignment" section; the stage (`sfm.py`) moves the model by it.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from flowerpose.cloudio import Cloud
from flowerpose.errors import InputError
from flowerpose.log import LOG
from flowerpose.pipeline.align import (
    Similarity,
    level_similarity,
    residuals,
    robust_similarity,
)
from flowerpose.pipeline.board import MIN_VIEWS, board_similarity, find_corners
from flowerpose.pipeline.frames import ChosenFrame
from flowerpose.pipeline.sfm_config import ASSUMED_CAMERA_DISTANCE_M, SfmConfig

if TYPE_CHECKING:
    import pycolmap


def onto_recorded_centres(reconstruction: pycolmap.Reconstruction,
                          frames: dict[str, ChosenFrame], config: SfmConfig,
                          frames_dir: Path) -> tuple[Similarity, dict]:
    """The robust similarity that moves the model's camera centres onto the recorded ones."""
    images = [im for im in reconstruction.images.values() if im.has_pose]
    centres = np.array([im.projection_center() for im in images])
    recorded = np.array([frames[im.name].position for im in images])
    try:
        similarity, inliers = robust_similarity(centres, recorded, config.align_threshold_m,
                                                seed=config.seed)
    except InputError as err:
        raise InputError(frames_dir, f"cannot align the reconstruction to the recorded camera "
                         f"positions: {err.problem}") from None
    return similarity, residuals(similarity, centres, recorded, inliers)


def sparse_cloud(reconstruction: pycolmap.Reconstruction) -> Cloud:
    """The model's triangulated points and their colours, in the model's frame."""
    points = reconstruction.points3D.values()
    xyz = np.array([p.xyz for p in points], dtype=np.float64).reshape(-1, 3)
    rgb = np.array([p.color for p in points], dtype=np.uint8).reshape(-1, 3)
    return Cloud(xyz, rgb)


def board_observations(reconstruction: pycolmap.Reconstruction, frames_dir: Path,
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


def onto_board(reconstruction: pycolmap.Reconstruction, frames_dir: Path,
               config: SfmConfig) -> tuple[Similarity, dict] | None:
    """The similarity that puts the model on the board (metric, z up out of its face,
    z = 0 on it); None where the board is not seen (`config.board` "required":
    InputError)."""
    observations, views = board_observations(reconstruction, frames_dir, config)
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
    LOG.info(f"sfm: the board: {fit['corners']} corners in {views} photos, "
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


def levelled(reconstruction: pycolmap.Reconstruction, config: SfmConfig
             ) -> tuple[Similarity, dict]:
    """The similarity that puts a pose-less model upright (`align.level_similarity`),
    scaled so that the cameras' median distance from the scene's centre (the points'
    median) is `config.camera_distance_m`: stated by the user, or assumed."""
    images = [im for im in reconstruction.images.values() if im.has_pose]
    centres = np.array([im.projection_center() for im in images])
    image_up = np.array([-im.cam_from_world().rotation.matrix()[1] for im in images])
    points = sparse_cloud(reconstruction).points
    scene = np.median(points, axis=0) if len(points) else centres.mean(axis=0)
    distance = float(np.median(np.linalg.norm(centres - scene, axis=1)))
    level, how = level_similarity(centres, image_up, ground_normal(points, distance,
                                                                   config.seed))
    stated = config.camera_distance_m is not None
    scale = (config.camera_distance_m if stated else ASSUMED_CAMERA_DISTANCE_M) / distance
    similarity = Similarity(scale, level.rotation, scale * level.translation)
    return similarity, {"kind": "levelled", "up_from": how, "rms_m": None, "inliers": None,
                        "scale_from": "the camera distance stated" if stated
                        else f"an assumed camera distance of {ASSUMED_CAMERA_DISTANCE_M} m"}
