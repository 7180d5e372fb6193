"""Which flowers the scan can see: at least half of the petals unoccluded from one viewpoint."""

from __future__ import annotations

import numpy as np
import trimesh

from flowerpose.sim.pieces import Part
from flowerpose.sim.plant import Plant
from flowerpose.sim.raycast import make_scene, seen_matrix

#: Petal samples per flower.
SAMPLES_PER_FLOWER = 200
#: A sample is seen when the first hit is within this distance of it, metres.
TOLERANCE_M = 0.001
#: Share of the petal samples that must be seen from one viewpoint.
VISIBLE_SHARE = 0.5
#: Stream of the plant seed's random numbers used for the petal samples.
_STREAM = 2


def flower_visibility(plant: Plant, viewpoints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Visibility of each open flower of `plant` (DESIGN.md's rule).

    viewpoints: (V, 3) camera positions, metres, bed frame. Each flower's petals get
    `SAMPLES_PER_FLOWER` area-weighted samples (seeded from the plant seed); a sample is
    seen from a viewpoint when the first surface on the ray to it lies within 1 mm of it
    (either side of the petal). Returns visible (n_flowers,) bool (fraction >= 0.5) and
    fraction (n_flowers,) float: the largest share of samples seen from one viewpoint.
    """
    n = len(plant.flowers)
    if n == 0:
        return np.zeros(0, bool), np.zeros(0)
    rng = np.random.default_rng([plant.seed, _STREAM])
    mesh = plant.mesh
    petal = plant.face_part == Part.PETAL
    samples = []
    for flower in plant.flowers:
        weight = mesh.area_faces * (petal & (plant.face_flower == flower.id))
        points, _ = trimesh.sample.sample_surface(mesh, SAMPLES_PER_FLOWER, face_weight=weight,
                                                  seed=rng)
        samples.append(points)
    scene = make_scene(mesh.vertices, mesh.faces)
    seen = seen_matrix(scene, np.concatenate(samples), np.asarray(viewpoints, np.float64),
                       TOLERANCE_M)
    fraction = seen.reshape(len(viewpoints), n, SAMPLES_PER_FLOWER).mean(2).max(0)
    return fraction >= VISIBLE_SHARE, fraction


def petal_samples(plants: list[Plant], instance_id, samples: int = SAMPLES_PER_FLOWER,
                  seed: int = 0) -> list[tuple[int, np.ndarray]]:
    """(instance id, (S, 3) petal surface points, metres, bed frame) per open flower.

    instance_id(plant_index, flower_id) -> int: the renderer's numbering of the flowers.
    """
    out = []
    rng = np.random.default_rng(seed)
    for index, plant in enumerate(plants):
        for flower in plant.flowers:
            faces = np.flatnonzero((plant.face_flower == flower.id)
                                   & (plant.face_part == Part.PETAL))
            sub = trimesh.Trimesh(plant.mesh.vertices, plant.mesh.faces[faces], process=False)
            points, _ = trimesh.sample.sample_surface(sub, samples, seed=int(rng.integers(2**31)))
            out.append((instance_id(index, flower.id), np.asarray(points)))
    return out


def seen_in_render(instance: np.ndarray, depth: np.ndarray, camera_to_bed: np.ndarray,
                   intrinsics, petals: list[tuple[int, np.ndarray]],
                   tolerance_m: float = 0.005) -> dict[int, float]:
    """Per flower instance, the share of its petal samples one rendered view sees: inside
    the image, on a pixel of its own instance mask, at the rendered depth.

    instance: (H, W) int32 instance ids; depth: (H, W) metres along the optical axis;
    camera_to_bed: (4, 4) OpenCV axes; intrinsics: the render's; petals: `petal_samples`.
    """
    from flowerpose.sim.camera import project

    fractions = {}
    for flower, points in petals:
        uv, z = project(points, camera_to_bed, intrinsics)
        col, row = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        inside = (z > 0) & (col >= 0) & (row >= 0) & (col < intrinsics.width) & (
            row < intrinsics.height)
        seen = np.zeros(len(points), bool)
        c, r = col[inside], row[inside]
        seen[inside] = (instance[r, c] == flower) & (np.abs(depth[r, c] - z[inside])
                                                      < tolerance_m)
        fractions[flower] = float(seen.mean())
    return fractions
