"""The close look's centre: the ring of stamens seen from one side gives the flower's centre
where the centroid of what is seen does not."""

import numpy as np

from flowerpose.pipeline.close_look import ring_centre


def _ring(normal: np.ndarray, centre: np.ndarray, radius: float, arc_deg: float,
          seed: int = 0) -> np.ndarray:
    """Points on an arc of a ring about `normal` through `centre`, a little noisy."""
    rng = np.random.default_rng(seed)
    u = np.cross(normal, [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    angle = np.radians(rng.uniform(0.0, arc_deg, 200))
    ring = (centre + radius * (np.cos(angle)[:, None] * u + np.sin(angle)[:, None] * v)
            + rng.normal(0.0, 0.0003, (200, 3)))
    return ring + np.outer(rng.uniform(0.0, 0.002, 200), normal)  # the anthers' height


def test_the_centre_of_a_half_seen_ring_is_its_circles_not_its_centroid():
    normal = np.array([0.0, 0.6, 0.8])
    centre = np.array([1.5, 0.7, 0.2])
    seen = _ring(normal, centre, 0.007, 200.0)
    centroid = seen.mean(axis=0)
    found = ring_centre(seen, centroid, normal)
    across = found - centre - ((found - centre) @ normal) * normal
    assert np.linalg.norm(centroid - centre) > 0.003
    assert np.linalg.norm(across) < 0.0005
    # The height along the axis stays the centroid's.
    assert abs((found - centroid) @ normal) < 1e-12


def test_points_on_no_circle_keep_the_centroid():
    normal = np.array([0.0, 0.0, 1.0])
    rng = np.random.default_rng(1)
    blob = np.array([1.5, 0.7, 0.2]) + rng.normal(0.0, 0.004, (200, 3)) * [1.0, 0.2, 0.1]
    centroid = blob.mean(axis=0)
    assert np.allclose(ring_centre(blob, centroid, normal), centroid)
    assert np.allclose(ring_centre(blob[:5], centroid, normal), centroid)
    wide = _ring(normal, np.array([1.5, 0.7, 0.2]), 0.03, 360.0)  # no flower's stamens
    assert np.allclose(ring_centre(wide, wide.mean(axis=0), normal), wide.mean(axis=0))
