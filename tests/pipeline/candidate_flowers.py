"""Small seeded candidate clouds for the operating envelope's tests: flowers as a detector's
candidates give them (white petals round a yellow centre, green sepals behind, a leaf of
sheen nearby), each sampled with a chosen number of points."""

from __future__ import annotations

import numpy as np

from flowerpose.cloudio import Cloud

PETAL, PISTIL, SEPAL = (235, 235, 228), (225, 190, 40), (70, 130, 45)


def plane_axes(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors spanning the plane normal to `normal`."""
    helper = np.array([1.0, 0, 0]) if abs(normal[0]) < 0.9 else np.array([0, 1.0, 0])
    u = np.cross(normal, helper)
    u /= np.linalg.norm(u)
    return u, np.cross(normal, u)


def candidate_flowers(points_per_flower: int, seed: int = 0, flowers: int = 6,
                      radius: float = 0.022) -> tuple[Cloud, np.ndarray, np.ndarray]:
    """Candidate points of `flowers` flowers in a row 8 cm apart, metres, each of about
    `points_per_flower` points: a corolla of `radius` cupped a little (petals), a receptacle
    of a quarter of it standing 2 mm in front (pistil) and a calyx 3 mm behind (sepals).
    Returns the cloud, the centres (F, 3) and the unit normals (F, 3)."""
    rng = np.random.default_rng(seed)
    points, colors, centres, normals = [], [], [], []
    for k in range(flowers):
        normal = rng.normal(size=3)
        normal /= np.linalg.norm(normal)
        u, v = plane_axes(normal)
        centre = np.array([0.08 * k, 0.0, 0.3])
        # Areas: the petal disc, the receptacle (a sixteenth) and the calyx behind.
        counts = np.array([0.8, 0.1, 0.1]) * points_per_flower
        for (inner, outer, height, colour), count in zip(
                ((0.25, 1.0, 0.0, PETAL), (0.0, 0.25, 0.002, PISTIL),
                 (0.0, 0.45, -0.003, SEPAL)), np.maximum(2, np.round(counts)).astype(int),
                strict=True):
            r = radius * np.sqrt(rng.uniform(inner ** 2, outer ** 2, count))
            angle = rng.uniform(0, 2 * np.pi, count)
            rise = height + (0.12 * r ** 2 / radius if colour == PETAL else 0.0)
            points.append(centre + np.outer(r * np.cos(angle), u) + np.outer(r * np.sin(angle), v)
                          + np.outer(rise + rng.normal(0, 3e-4, count), normal))
            colors.append(np.tile(colour, (count, 1)))
        centres.append(centre + 0.002 * normal)
        normals.append(normal)
    return (Cloud(np.concatenate(points), np.concatenate(colors).astype(np.uint8)),
            np.array(centres), np.array(normals))
