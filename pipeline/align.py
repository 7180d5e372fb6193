"""Similarity transforms between point sets: closed form (Umeyama) and robust (RANSAC).

A reconstruction from images alone has an arbitrary frame and scale. Its camera centres
against the bot's recorded camera positions (metres, bed frame) fix both: the similarity
that maps one set onto the other puts the cloud in the bed frame, metric and z-up, and the
residual says how well the two agree.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flowerpose.errors import InputError

#: Smallest ratio of the second to the first principal spread for points to span a plane;
#: below it they are collinear and a rotation about their line is undetermined.
COLLINEAR_RATIO = 1e-6


@dataclass(frozen=True)
class Similarity:
    """target = scale * rotation @ source + translation."""

    scale: float
    rotation: np.ndarray
    """(3, 3) proper rotation."""
    translation: np.ndarray
    """(3,) in target units."""

    def apply(self, points: np.ndarray) -> np.ndarray:
        """points: (N, 3) or (3,) in source units and frame; returns them in the target's."""
        points = np.asarray(points, dtype=np.float64)
        return self.scale * points @ self.rotation.T + self.translation

    def inverse(self) -> Similarity:
        """The similarity from target back to source."""
        rotation = self.rotation.T
        return Similarity(1.0 / self.scale, rotation,
                          -(rotation @ self.translation) / self.scale)

    @property
    def matrix(self) -> np.ndarray:
        """(4, 4) homogeneous matrix of the transform."""
        out = np.eye(4)
        out[:3, :3] = self.scale * self.rotation
        out[:3, 3] = self.translation
        return out


def _check_pairs(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    source = np.asarray(source, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    if source.ndim != 2 or source.shape[1] != 3 or source.shape != target.shape:
        raise InputError("alignment", f"needs two (N, 3) point sets of equal length, got "
                         f"{source.shape} and {target.shape}")
    if not (np.isfinite(source).all() and np.isfinite(target).all()):
        raise InputError("alignment", "NaN or infinite coordinates")
    if len(source) < 3:
        raise InputError("alignment", f"needs at least 3 point pairs, got {len(source)}")
    return source, target


def _spread_ratio(points: np.ndarray) -> float:
    """Second over first singular value of the centred points (0 when collinear)."""
    singular = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    return float(singular[1] / singular[0]) if singular[0] > 0 else 0.0


def _umeyama_batch(source: np.ndarray, target: np.ndarray, with_scale: bool
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closed-form similarities for stacks of point sets (B, N, 3): scales (B,),
    rotations (B, 3, 3), translations (B, 3)."""
    mean_s = source.mean(axis=1, keepdims=True)
    mean_t = target.mean(axis=1, keepdims=True)
    centred_s, centred_t = source - mean_s, target - mean_t
    covariance = np.einsum("bni,bnj->bij", centred_t, centred_s) / source.shape[1]
    u, d, vt = np.linalg.svd(covariance)
    sign = np.sign(np.linalg.det(u) * np.linalg.det(vt))
    sign[sign == 0] = 1.0
    s = np.ones((len(source), 3))
    s[:, 2] = sign
    rotation = np.einsum("bij,bj,bjk->bik", u, s, vt)
    if with_scale:
        variance = (centred_s ** 2).sum(axis=2).mean(axis=1)
        scale = (d * s).sum(axis=1) / np.where(variance > 0, variance, 1.0)
    else:
        scale = np.ones(len(source))
    translation = mean_t[:, 0] - scale[:, None] * np.einsum("bij,bj->bi", rotation,
                                                           mean_s[:, 0])
    return scale, rotation, translation


def umeyama(source: np.ndarray, target: np.ndarray, with_scale: bool = True) -> Similarity:
    """The least-squares similarity mapping source onto target (Umeyama 1991).

    source, target: (N, 3) float64 corresponding points, N >= 3 and not collinear; target
    units (metres for the bed frame) are those of the translation.
    """
    source, target = _check_pairs(source, target)
    if _spread_ratio(source) < COLLINEAR_RATIO or _spread_ratio(target) < COLLINEAR_RATIO:
        raise InputError("alignment", f"the {len(source)} points are collinear (or all "
                         "equal): the rotation about their line is undetermined")
    scale, rotation, translation = _umeyama_batch(source[None], target[None], with_scale)
    return Similarity(float(scale[0]), rotation[0], translation[0])


def robust_similarity(source: np.ndarray, target: np.ndarray, threshold_m: float,
                      iterations: int = 1000, seed: int = 0, with_scale: bool = True
                      ) -> tuple[Similarity, np.ndarray]:
    """A similarity from source to target that ignores gross outliers; (it, inlier mask).

    RANSAC on minimal 3-point samples (the same samples for the same seed), then a least-
    squares refit on the inliers repeated until the inlier set settles.
    source, target: (N, 3) float64 corresponding points; threshold_m: largest distance
    (target units, metres) from a mapped source point to its target that is an inlier.
    """
    source, target = _check_pairs(source, target)
    if threshold_m <= 0:
        raise InputError("alignment", f"threshold must be positive, got {threshold_m}")
    if _spread_ratio(source) < COLLINEAR_RATIO or _spread_ratio(target) < COLLINEAR_RATIO:
        raise InputError("alignment", f"the {len(source)} points are collinear (or all "
                         "equal): the rotation about their line is undetermined")
    rng = np.random.default_rng(seed)
    n = len(source)
    samples = np.argsort(rng.random((max(1, iterations), n)), axis=1)[:, :3]
    # Near-collinear samples give an arbitrary rotation about their line: skip them.
    a, b, c = (source[samples[:, k]] for k in range(3))
    area = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    extent = float(np.ptp(source, axis=0).max())
    samples = samples[area > 1e-6 * extent ** 2]
    best = np.zeros(n, dtype=bool)
    if len(samples):
        scale, rotation, translation = _umeyama_batch(source[samples], target[samples],
                                                      with_scale)
        mapped = scale[:, None, None] * np.einsum("bij,nj->bni", rotation, source) \
            + translation[:, None]
        errors = np.linalg.norm(mapped - target[None], axis=2)
        inliers = errors < threshold_m
        counts = inliers.sum(axis=1)
        # Most inliers; among equals the smallest inlier error, so the choice is stable.
        cost = np.where(inliers, errors, 0.0).sum(axis=1)
        winner = np.lexsort((cost, -counts))[0]
        best = inliers[winner]
    if best.sum() < 3:
        raise InputError("alignment", f"no similarity brings 3 of the {n} points within "
                         f"{threshold_m:g} of their targets")
    for _ in range(10):
        try:
            model = umeyama(source[best], target[best], with_scale)
        except InputError:
            raise InputError("alignment", f"the {int(best.sum())} inliers are collinear: "
                             "the rotation about their line is undetermined") from None
        refit = np.linalg.norm(model.apply(source) - target, axis=1) < threshold_m
        if refit.sum() < 3 or np.array_equal(refit, best):
            break
        best = refit
    return model, best


def residuals(similarity: Similarity, source: np.ndarray, target: np.ndarray,
              mask: np.ndarray | None = None) -> dict:
    """Distances from mapped source points to their targets over `mask` (default all):
    {"rms_m", "median_m", "max_m", "inliers", "points"}, in target units (metres)."""
    source, target = np.asarray(source, np.float64), np.asarray(target, np.float64)
    mask = np.ones(len(source), dtype=bool) if mask is None else np.asarray(mask, bool)
    distance = np.linalg.norm(similarity.apply(source[mask]) - target[mask], axis=1)
    if len(distance) == 0:
        return {"rms_m": None, "median_m": None, "max_m": None, "inliers": 0,
                "points": len(source)}
    return {"rms_m": float(np.sqrt(np.mean(distance ** 2))),
            "median_m": float(np.median(distance)), "max_m": float(distance.max()),
            "inliers": int(mask.sum()), "points": len(source)}


#: Largest ratio of the smallest to the middle principal spread of the camera centres for
#: them to lie on a plane (a circle or dome ring round the plant) whose normal is up.
PLANAR_RATIO = 0.2
#: The plane's normal is up only within this of the cameras' mean image-up, degrees
#: (cameras on a short arc at several heights span an upright plane).
PLANE_UP_AGREEMENT_DEG = 45.0


def rotation_onto(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(3, 3) the smallest rotation taking unit vector a onto unit vector b (Rodrigues)."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    axis, cosine = np.cross(a, b), float(a @ b)
    if cosine < -1 + 1e-12:  # opposite: half a turn about any axis normal to a
        normal = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])
        normal /= np.linalg.norm(normal)
        return 2 * np.outer(normal, normal) - np.eye(3)
    skew = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + skew + skew @ skew / (1 + cosine)


def level_similarity(centres: np.ndarray, image_up: np.ndarray,
                     ground: np.ndarray | None = None) -> tuple[Similarity, str]:
    """The rigid transform that puts a pose-less reconstruction upright: up becomes +z and
    the camera centres' mean the origin; the scale is kept. Returns it and how up was found.

    Up is, in order: the normal of `ground` (the table's or the soil's plane under the plant,
    found by the caller) turned to the cameras' side; the normal of the plane the camera
    centres lie on where they do (a ring round the plant: photos taken walking round it);
    the cameras' mean image-up direction (a camera held upright). A plane's normal counts
    only within PLANE_UP_AGREEMENT_DEG of the mean image-up, since a camera held upright
    tells roughly where up is.
    centres: (N, 3) camera centres; image_up: (N, 3) each camera's -y axis; ground: (3,)
    a plane's unit normal, either sign; all in the model frame.
    """
    centres = np.asarray(centres, np.float64)
    mean_up = np.asarray(image_up, np.float64).mean(axis=0)
    mean_norm = np.linalg.norm(mean_up)

    def agrees(normal: np.ndarray) -> bool:
        return mean_norm > 0 and normal @ mean_up / mean_norm >= np.cos(np.radians(
            PLANE_UP_AGREEMENT_DEG))

    spread = centres - centres.mean(axis=0)
    _, singular, vt = np.linalg.svd(spread, full_matrices=False)
    ring = vt[2] if vt[2] @ mean_up >= 0 else -vt[2]
    if ground is not None:
        ground = np.asarray(ground, np.float64) / np.linalg.norm(ground)
        ground = ground if ground @ mean_up >= 0 else -ground
    if ground is not None and agrees(ground):
        up, how = ground, "the ground's plane"
    elif len(centres) >= 4 and singular[1] > 0 and singular[2] / singular[1] <= PLANAR_RATIO \
            and agrees(ring):
        up, how = ring, "the plane of the camera centres"
    else:
        up, how = mean_up, "the cameras' mean image-up direction"
    if np.linalg.norm(up) < 1e-9:
        raise InputError("alignment", "the cameras' up directions cancel: cannot tell up")
    rotation = rotation_onto(up, np.array([0.0, 0.0, 1.0]))
    return Similarity(1.0, rotation, -rotation @ centres.mean(axis=0)), how
