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
