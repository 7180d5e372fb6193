"""Line-of-sight tests from camera positions to surface points (Open3D ray casting)."""

from __future__ import annotations

import numpy as np

from flowerpose.log import open3d

o3d = open3d()

#: Rays per Open3D call: bounds the memory of one batch (6 float32 per ray).
RAY_BATCH = 2_000_000


def make_scene(vertices: np.ndarray, faces: np.ndarray) -> o3d.t.geometry.RaycastingScene:
    """A ray-casting scene of a triangle mesh (vertices (V, 3) metres, faces (F, 3))."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(vertices, np.float32)),
                        o3d.core.Tensor(np.asarray(faces, np.uint32)))
    return scene


def _seen(scene: o3d.t.geometry.RaycastingScene, origins: np.ndarray, targets: np.ndarray,
          tolerance: float) -> np.ndarray:
    """(R,) bool: nothing lies on the segment from each origin to `tolerance` before its
    target ((R, 3) each, metres); both faces of every triangle block."""
    offset = targets - origins
    length = np.linalg.norm(offset, axis=1, keepdims=True)
    # Direction scaled so that t = 1 is `tolerance` short of the target: one any-hit
    # query over [0, 1] then asks "is anything in front of the point?".
    direction = offset * (np.maximum(length - tolerance, 0.0) / np.maximum(length, 1e-12))
    rays = np.concatenate([origins, direction], 1).astype(np.float32)
    occluded = scene.test_occlusions(o3d.core.Tensor(rays), tnear=0.0, tfar=1.0).numpy()
    return ~occluded.astype(bool)


def seen_matrix(scene: o3d.t.geometry.RaycastingScene, points: np.ndarray,
                viewpoints: np.ndarray, tolerance: float) -> np.ndarray:
    """(V, N) bool: point n is seen from viewpoint v.

    points: (N, 3) on the scene's surfaces; viewpoints: (V, 3); metres, same frame. A point
    is seen when the first surface on the ray from the viewpoint lies within `tolerance`
    (metres) of it.
    """
    out = np.empty((len(viewpoints), len(points)), bool)
    per_batch = max(1, RAY_BATCH // max(len(points), 1))
    for start in range(0, len(viewpoints), per_batch):
        views = viewpoints[start:start + per_batch]
        origins = np.repeat(views, len(points), axis=0)
        targets = np.tile(points, (len(views), 1))
        out[start:start + len(views)] = _seen(scene, origins, targets, tolerance).reshape(
            len(views), len(points))
    return out


def seen_from_any(scene: o3d.t.geometry.RaycastingScene, points: np.ndarray,
                  viewpoints: np.ndarray, tolerance: float) -> np.ndarray:
    """(N,) bool: point n is seen from at least one of `viewpoints` (see `seen_matrix`).

    Viewpoints are tried in batches and points already seen are not cast again, so the
    cost falls as coverage grows.
    """
    seen = np.zeros(len(points), bool)
    batch = 8
    for start in range(0, len(viewpoints), batch):
        todo = np.flatnonzero(~seen)
        if len(todo) == 0:
            break
        hits = seen_matrix(scene, points[todo], viewpoints[start:start + batch], tolerance)
        seen[todo[hits.any(0)]] = True
    return seen
