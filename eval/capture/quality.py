"""Reconstruction quality against the truth mesh (issue 4's `reconstruction` report section).

accuracy: median distance from the cloud to the truth surface. completeness at d: share of
the truth surface (area-weighted samples) within d of the cloud. F-score at d: the harmonic
mean of precision (share of cloud points within d of the truth) and completeness at d.
Computed for the whole plant (the soil left out on both sides) and for the petals alone (the
petal surface, and the cloud points whose nearest truth surface is a petal).
"""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from flowerpose.log import open3d
from flowerpose.sim.pieces import Part

THRESHOLDS_M = (0.002, 0.005)


def _closest(mesh: trimesh.Trimesh, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(distance (N,), face index (N,)) of points to the mesh's nearest surface, metres."""
    o3d = open3d()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
                        o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))
    query = o3d.core.Tensor(np.asarray(points, np.float32))
    result = scene.compute_closest_points(query)
    nearest = result["points"].numpy().astype(np.float64)
    return np.linalg.norm(nearest - points, axis=1), result["primitive_ids"].numpy()


def _scores(distance_cloud: np.ndarray, distance_truth: np.ndarray) -> dict:
    out: dict = {"accuracy_m": float(np.median(distance_cloud)) if len(distance_cloud) else None,
                 "points": int(len(distance_cloud))}
    for d in THRESHOLDS_M:
        precision = float(np.mean(distance_cloud <= d)) if len(distance_cloud) else 0.0
        recall = float(np.mean(distance_truth <= d)) if len(distance_truth) else 0.0
        f = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
        mm = f"{d * 1000:g}mm"
        out[f"precision_{mm}"] = round(precision, 4)
        out[f"completeness_{mm}"] = round(recall, 4)
        out[f"fscore_{mm}"] = round(f, 4)
    return out


def cloud_agreement(a: np.ndarray, b: np.ndarray, threshold_m: float) -> dict:
    """How well two clouds of one scene agree (both metres, one frame): precision (share
    of a's points within threshold_m of b), completeness (b's within it of a) and their
    harmonic mean, the F-score."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if len(a) == 0 or len(b) == 0:
        return {"precision": 0.0, "completeness": 0.0, "fscore": 0.0}
    precision = float(np.mean(cKDTree(b).query(a)[0] <= threshold_m))
    completeness = float(np.mean(cKDTree(a).query(b)[0] <= threshold_m))
    total = precision + completeness
    return {"precision": precision, "completeness": completeness,
            "fscore": 2 * precision * completeness / total if total else 0.0}


def rigid_icp(source: np.ndarray, target: np.ndarray, max_distance_m: float = 0.005
              ) -> np.ndarray:
    """(N, 3) `source` moved onto `target` by rigid point-to-point ICP (Open3D; no scale:
    what the cameras' alignment made metric stays so), starting where it is: the last
    millimetre of an alignment two clouds' camera centres leave."""
    o3d = open3d()
    registration = o3d.pipelines.registration
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(source, np.float64)))
    onto = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(target, np.float64)))
    result = registration.registration_icp(
        cloud, onto, max_distance_m, np.eye(4),
        registration.TransformationEstimationPointToPoint(with_scaling=False))
    transform = result.transformation
    return np.asarray(source, np.float64) @ transform[:3, :3].T + transform[:3, 3]


def reconstruction_quality(points: np.ndarray, mesh: trimesh.Trimesh, face_part: np.ndarray,
                           samples: int = 200_000, seed: int = 0) -> dict:
    """Quality of a reconstructed cloud against the plant's truth mesh.

    points: (N, 3) cloud, metres, bed frame. mesh: the truth (bed frame, metres) with
    face_part (F,) its `Part` per face. Returns {"plant": {...}, "petals": {...}} with
    accuracy_m, precision, completeness and F-score at 2 mm and 5 mm.
    """
    points = np.asarray(points, np.float64)
    plant_faces = np.flatnonzero(face_part != Part.SOIL)
    plant = trimesh.Trimesh(mesh.vertices, mesh.faces[plant_faces], process=False)
    # Cloud points of the plant: in the plant's box (grown by 1 cm) and nearer to a plant
    # surface than to the soil; their distance to that surface is their error.
    low, high = plant.bounds[0] - 0.01, plant.bounds[1] + 0.01
    region = np.flatnonzero(np.all((points >= low) & (points <= high), axis=1))
    distance, face = (_closest(mesh, points[region]) if len(region)
                      else (np.zeros(0), np.zeros(0, int)))
    on_plant = face_part[face] != Part.SOIL
    part = face_part[face]
    truth, truth_face = trimesh.sample.sample_surface(plant, samples, seed=seed)
    tree = cKDTree(points) if len(points) else None
    to_cloud = tree.query(truth)[0] if tree is not None else np.full(len(truth), np.inf)
    petal_truth = face_part[plant_faces][truth_face] == Part.PETAL
    petal_cloud = on_plant & (part == Part.PETAL)
    return {"plant": _scores(distance[on_plant], to_cloud),
            "petals": _scores(distance[petal_cloud], to_cloud[petal_truth])}
