"""Surface fits to a flower's petal points: plane, superellipsoid and paraboloid axes.

Each fit returns the unit axis of its surface that is parallel to the flower normal, or
None when the fit fails (too few points, non-finite input, optimiser failure): a failed
fit never yields a made-up vector. The sign of the axis is arbitrary here; the pistil
decides it (`flowerpose.pipeline.pose`).

Every `points` argument is (N, 3) float64, metres, in any right-handed frame (the bed
frame in the pipeline); the returned axis is in the same frame.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from scipy.optimize import least_squares

#: Fewest petal points any fit accepts.
MIN_FIT_POINTS = 10
#: Superellipsoid half-axis bounds a, b, c (metres). Upstream's lower bound 0 divides by zero.
SIZE_BOUNDS = (1e-4, 0.1)
#: Superellipsoid shape exponent bounds e1, e2 (the paper's).
EXPONENT_BOUNDS = (0.9, 1.1)
#: Most residual evaluations one nonlinear fit may spend.
MAX_EVALUATIONS = 200
#: Largest ratio of the superellipsoid's half-axis across the petals to the lesser one
#: along them, at the principal-axes start.
MAX_FLATNESS = 0.5
#: Relative cost reduction that ends the superellipsoid fit: against scipy's 1e-8 it saves
#: a quarter of the iterations and changed no axis error of the test flowers (0.01 degree).
SUPERELLIPSOID_FTOL = 1e-4

FitInit = Literal["pca", "upstream"]

# Upstream's start: half-axes 5 mm, exponents 1, zero Euler angles (the bed axes).
_UPSTREAM_SIZE = 0.005
# Keeps logarithms and negative powers finite for a point on an axis plane or at the centre.
_TINY = 1e-12


def principal_axes(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centroid, covariance eigenvalues and eigenvectors of a point set.

    points: (N, 3) float64, metres. Returns centroid (3,), eigenvalues (3,) in m^2
    descending, and a right-handed rotation (3, 3) whose columns are the matching
    eigenvectors (the third column is the direction of least spread).
    """
    centroid = points.mean(axis=0)
    centred = points - centroid
    values, vectors = np.linalg.eigh(centred.T @ centred / len(points))
    values, vectors = values[::-1], vectors[:, ::-1]
    if np.linalg.det(vectors) < 0:
        vectors[:, 2] = -vectors[:, 2]
    return centroid, values, vectors


#: Tukey biweight cut-off of the robust plane, in standard deviations (from the MAD).
ROBUST_SCALE = 4.685

MIN_SPREAD_RATIO = 0.03
"""Least standard deviation along the second widest principal axis, as a share of that
along the widest, for any fit: below it the points are a line (a stem, a petal's edge),
not a surface, and no normal is defined, so the fit gives None rather than a made-up
vector. A share, not a length, so it holds in any unit (a corolla's two spreads are
alike; a 0.2 mm wide strip of a 7 mm spread is 0.03)."""
#: ... and the widest spread must stand out of the coordinates' rounding (a share of their
#: size): a blob of rounding noise round one point is no surface either.
ROUNDING = 1e-9


def _usable(points: np.ndarray, min_points: int) -> bool:
    if len(points) < max(min_points, MIN_FIT_POINTS) or not np.isfinite(points).all():
        return False
    points = np.asarray(points, np.float64)
    spread = np.linalg.eigvalsh(np.cov(points.T))
    size = float(np.abs(points).max())
    return bool(spread[2] > (ROUNDING * max(size, 1e-300)) ** 2
                and spread[1] > MIN_SPREAD_RATIO ** 2 * spread[2])


def _unit_or_none(axis: np.ndarray) -> np.ndarray | None:
    norm = float(np.linalg.norm(axis))
    if not np.isfinite(norm) or norm == 0.0:
        return None
    return axis / norm


#: Plane directions the robust plane's start is chosen among (a Fibonacci hemisphere, about
#: 7 degrees apart), and the most points it judges them on (an even subsample).
START_DIRECTIONS = 256
START_SAMPLE = 500


def _hemisphere(count: int) -> np.ndarray:
    """(count, 3) unit directions spread evenly over the hemisphere z >= 0."""
    k = np.arange(count) + 0.5
    z = 1.0 - k / count
    angle = np.pi * (3.0 - np.sqrt(5.0)) * k
    ring = np.sqrt(1.0 - z ** 2)
    return np.column_stack([ring * np.cos(angle), ring * np.sin(angle), z])


def _least_median_plane(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The plane whose thinnest slab holds half the points (least median of squares, over
    START_DIRECTIONS directions): a point on it (the centroid of that half) and its unit
    normal. Unlike the least-squares plane it ignores up to half the points wherever they
    lie, so a leaf's sheen above a corolla or a stem below it cannot tilt the start of
    the reweighted fit. points: (N, 3), any unit."""
    sample = points[::max(1, len(points) // START_SAMPLE)]
    directions = _hemisphere(START_DIRECTIONS)
    # (direction, point): each direction's heights sorted along a contiguous row.
    heights = np.sort(directions @ sample.T, axis=1)
    half = (len(sample) + 1) // 2
    widths = heights[:, half - 1:] - heights[:, :len(sample) - half + 1]
    start = widths.argmin(axis=1)
    best = int(widths[np.arange(len(directions)), start].argmin())
    normal = directions[best]
    low = heights[best, start[best]]
    height = points @ normal
    inside = (height >= low) & (height <= low + widths[best, start[best]])
    return points[inside].mean(axis=0), normal


def fit_plane(points: np.ndarray, min_points: int = MIN_FIT_POINTS,
              robust_iterations: int = 0, min_scale: float = 0.0) -> np.ndarray | None:
    """Normal of the least-squares plane: the covariance eigenvector of least spread.

    With `robust_iterations`, the fit starts from the least-median plane
    (`_least_median_plane`) and that many reweighted refits follow (Tukey's biweight on
    the distance to the plane, scaled by ROBUST_SCALE median absolute deviations), so
    points off the corolla (a drooping rim, a leaf edge, a leaf's sheen above it, a stem
    below) stop pulling the plane: started from the least-squares plane, a quarter of the
    points 16 mm off tilted it past what the reweighting could undo. points: (N, 3)
    float64, any unit. min_scale: the least cut-off of the reweighting, in the points'
    unit: points nearer the plane always count, however tightly the rest hug it. Where
    fewer points than a fit needs lie within the cut-off of the least-median plane, it is
    no start, and the plane is the least-squares one. Returns a unit (3,) axis, or None
    for fewer than `min_points` points or non-finite input.
    """
    if not _usable(points, min_points):
        return None
    if robust_iterations:
        centroid, normal = _least_median_plane(points)
    else:
        centroid, values, vectors = principal_axes(points)
        if not np.isfinite(values).all():
            return None
        normal = vectors[:, 2]
    for iteration in range(robust_iterations):
        distance = (points - centroid) @ normal
        spread = float(np.median(np.abs(distance - np.median(distance))))
        scale = max(ROBUST_SCALE * 1.4826 * spread, min_scale)
        if not scale > 0:
            break
        weight = np.clip(1.0 - (distance / scale) ** 2, 0.0, None) ** 2
        if np.count_nonzero(weight) < max(min_points, MIN_FIT_POINTS):
            if iteration == 0:
                # Fewer points near the least-median plane than a fit needs (under 20
                # points in all): its half can be a few petal points in a row, which a
                # plane standing across the corolla holds as thinly as the corolla's.
                normal = principal_axes(points)[2][:, 2]
            break
        centroid = weight @ points / weight.sum()
        centred = points - centroid
        normal = np.linalg.eigh((weight[:, None] * centred).T @ centred)[1][:, 0]
    return _unit_or_none(normal)


def _exp_and_right_jacobian(omega: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation exp([omega]x) and the SO(3) right Jacobian J_r(omega).

    exp(omega + d) = exp(omega) exp(J_r(omega) d) to first order in d. Written out
    because scipy's Rotation costs more than the rest of a residual evaluation.
    """
    wx, wy, wz = (float(v) for v in omega)
    theta2 = wx * wx + wy * wy + wz * wz
    k = np.array([[0.0, -wz, wy], [wz, 0.0, -wx], [-wy, wx, 0.0]])
    k2 = np.outer(omega, omega) - theta2 * np.eye(3)
    if theta2 < 1e-12:
        sin_term, cos_term, cubic_term = 1.0, 0.5, 1.0 / 6.0
    else:
        theta = math.sqrt(theta2)
        sin_term = math.sin(theta) / theta
        cos_term = (1.0 - math.cos(theta)) / theta2
        cubic_term = (1.0 - sin_term) / theta2
    eye = np.eye(3)
    return eye + sin_term * k + cos_term * k2, eye - cos_term * k + cubic_term * k2


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (N, 3) arrays (np.cross is several times slower)."""
    return np.column_stack([u[:, 1] * v[:, 2] - u[:, 2] * v[:, 1],
                            u[:, 2] * v[:, 0] - u[:, 0] * v[:, 2],
                            u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]])


class _RigidFrame:
    """Points in a local frame R = R0 exp(omega) with origin t, in scaled coordinates.

    The input points are centred on `origin` and divided by `scale` (metres), so every
    parameter is of order one. With `anchored`, t = s R[:, 2] has one parameter s: the
    local z axis passes through `origin`. `chain` turns a gradient with respect to the
    local points into gradients with respect to omega and t, so every fit below has an
    analytic Jacobian (a numerical one costs a residual evaluation per parameter).
    """

    def __init__(self, points: np.ndarray, origin: np.ndarray, scale: float,
                 rotation0: np.ndarray, anchored: bool):
        self.points = (points - origin) / scale
        self.rotation0 = rotation0
        self.anchored = anchored
        self.n_translation = 1 if anchored else 3

    def rotation(self, omega: np.ndarray) -> np.ndarray:
        return self.rotation0 @ _exp_and_right_jacobian(omega)[0]

    def local(self, omega: np.ndarray, t: np.ndarray):
        """Local points p (N, 3) and `chain`, mapping dr/dp (N, 3) to (dr/domega, dr/dt)."""
        exp, right_jacobian = _exp_and_right_jacobian(omega)
        rotation = self.rotation0 @ exp
        if self.anchored:
            # p = exp(omega)^T y - s e_z: dp/domega = [p + s e_z]x J_r, dp/ds = -e_z.
            rotated = self.points @ rotation
            p = rotated.copy()
            p[:, 2] -= t[0]

            def chain(grad_p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
                return _cross(grad_p, rotated) @ right_jacobian, -grad_p[:, 2:3]
        else:
            # p = exp(omega)^T R0^T (y - t): dp/domega = [p]x J_r, dp/dt = -R^T.
            p = (self.points - t) @ rotation

            def chain(grad_p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
                return _cross(grad_p, p) @ right_jacobian, -grad_p @ rotation.T
        return p, chain


def _superellipsoid(params: np.ndarray, frame: _RigidFrame):
    """Radial distances d = |p| (1 - F(p)^(-e1/2)) of the points to the surface F = 1.

    F(p) = (|px/a|^(2/e2) + |py/b|^(2/e2))^(e2/e1) + |pz/c|^(2/e1), in the frame's scaled
    units. The distance is signed (negative inside) so it is smooth; its square is the
    plain squared distance. Returns the residuals (N,) and a function giving their
    Jacobian (N, P) from the same intermediates.
    """
    a, b, c, e1, e2 = params[:5]
    p, chain = frame.local(params[5:8], params[8:])
    abs_p = np.maximum(np.abs(p), _TINY)
    logs = np.log(abs_p / np.array([a, b, c]))
    pow_a, pow_b = np.exp(2.0 / e2 * logs[:, 0]), np.exp(2.0 / e2 * logs[:, 1])
    f1 = np.maximum(pow_a + pow_b, _TINY)
    log_f1 = np.log(f1)
    g = np.exp(e2 / e1 * log_f1)
    h = np.exp(2.0 / e1 * logs[:, 2])
    f = np.maximum(g + h, _TINY)
    log_f = np.log(f)
    s = np.exp(-0.5 * e1 * log_f)
    n = np.linalg.norm(p, axis=1)
    residual = n * (1.0 - s)

    def jacobian() -> np.ndarray:
        k = 0.5 * e1 * n * s / f  # dr/dF
        g_a, g_b = g * pow_a / f1, g * pow_b / f1  # the x and y shares of g
        jac = np.empty((len(p), len(params)))
        jac[:, 0] = k * (-2.0 / e1) * g_a / a
        jac[:, 1] = k * (-2.0 / e1) * g_b / b
        jac[:, 2] = k * (-2.0 / e1) * h / c
        d_f_e1 = -(e2 / e1**2) * log_f1 * g - (2.0 / e1**2) * logs[:, 2] * h
        jac[:, 3] = 0.5 * n * s * log_f + k * d_f_e1
        jac[:, 4] = k * (g * log_f1 / e1 - 2.0 / (e1 * e2) * (g_a * logs[:, 0] + g_b * logs[:, 1]))
        grad_f = (2.0 / e1) * np.sign(p) / abs_p * np.column_stack([g_a, g_b, h])
        grad_p = ((1.0 - s) / np.maximum(n, _TINY))[:, None] * p + k[:, None] * grad_f
        jac[:, 5:8], jac[:, 8:] = chain(grad_p)
        return jac

    return residual, jacobian


def _paraboloid(params: np.ndarray, frame: _RigidFrame):
    """Height residuals pz - (k1 px^2 + k2 py^2) in the local frame, scaled units.

    Returns the residuals (N,) and a function giving their Jacobian (N, P).
    """
    k1, k2 = params[:2]
    p, chain = frame.local(params[2:5], params[5:])
    x2, y2 = p[:, 0] ** 2, p[:, 1] ** 2
    residual = p[:, 2] - k1 * x2 - k2 * y2

    def jacobian() -> np.ndarray:
        jac = np.empty((len(p), len(params)))
        jac[:, 0], jac[:, 1] = -x2, -y2
        grad_p = np.column_stack([-2.0 * k1 * p[:, 0], -2.0 * k2 * p[:, 1], np.ones(len(p))])
        jac[:, 2:5], jac[:, 5:] = chain(grad_p)
        return jac

    return residual, jacobian


def _solve(model, frame: _RigidFrame, x0: np.ndarray, **options) -> np.ndarray | None:
    """least_squares on model(x, frame); the solution, or None on failure.

    The Jacobian reuses the intermediates of the residual evaluation at the same x, which
    least_squares always makes just before asking for it.
    """
    last: dict = {}

    def residuals(x: np.ndarray) -> np.ndarray:
        last["x"] = x.copy()
        residual, last["jacobian"] = model(x, frame)
        return residual

    def jacobian(x: np.ndarray) -> np.ndarray:
        if "x" not in last or not np.array_equal(last["x"], x):
            residuals(x)
        return last["jacobian"]()

    try:
        result = least_squares(residuals, x0, jac=jacobian, **options)
    except (ValueError, np.linalg.LinAlgError):
        return None
    if result.status <= 0 or not np.isfinite(result.x).all():
        return None
    return result.x


def _frame(points: np.ndarray, axis_point: np.ndarray | None,
           rotation0: np.ndarray | None = None) -> tuple[_RigidFrame, np.ndarray, float]:
    """The fitting frame of petal points, their principal spreads (scaled units) and scale."""
    centroid, values, vectors = principal_axes(points)
    scale = float(np.sqrt(values.sum()))
    anchored = axis_point is not None
    origin = np.asarray(axis_point, dtype=np.float64) if anchored else centroid
    rotation0 = vectors if rotation0 is None else rotation0
    return _RigidFrame(points, origin, scale, rotation0, anchored), values / scale**2, scale


def fit_superellipsoid(
    points: np.ndarray,
    axis_point: np.ndarray | None = None,
    init: FitInit = "pca",
    size_bounds: tuple[float, float] = SIZE_BOUNDS,
    exponent_bounds: tuple[float, float] = EXPONENT_BOUNDS,
    max_flatness: float = MAX_FLATNESS,
    max_evaluations: int = MAX_EVALUATIONS,
    min_points: int = MIN_FIT_POINTS,
) -> np.ndarray | None:
    """Axis of the shortest half-axis of a superellipsoid fitted to the petals.

    Parameters: half-axes a, b, c (metres, within `size_bounds`), shape exponents e1, e2
    (within `exponent_bounds`), a rotation and the centre, by bounded trust-region
    reflective least squares on the plain radial distance. The centre is a deviation from
    upstream, which centred the petals on their centroid and fitted none: a cupped corolla
    is a cap of the surface, whose centre lies off the petal centroid along the normal.

    init="pca" starts from the petals' principal axes and spreads (upstream's zero-angle
    start gets stuck in local minima, as the paper says) and bounds c, the half-axis along
    the least spread, by `max_flatness` times the lesser in-plane half-axis estimate (twice
    its standard deviation, the radius of a uniform disc): a corolla is flatter than wide,
    and a fit free of that prefers a cap of a long ellipsoid whose shortest axis lies in
    the petal plane. With `axis_point` (the pistil centroid, (3,) metres) the c axis passes
    through it and only the centre's position along the axis is free: a sideways shift of
    the centre mimics a tilt of a shallow cap, so a free centre leaves the tilt weakly
    determined. init="upstream" starts from 5 mm half-axes along the frame axes with the
    plain bounds and a free centre (it ignores `axis_point`).

    points: (N, 3) float64, metres. Returns a unit (3,) axis or None on failure.
    """
    if not _usable(points, min_points):
        return None
    if init == "upstream":
        frame, _, scale = _frame(points, None, np.eye(3))
        sizes = np.full(3, _UPSTREAM_SIZE / scale)
    else:
        frame, spreads, scale = _frame(points, axis_point)
        sizes = 2.0 * np.sqrt(np.maximum(spreads, 0.0))
    lo, hi = size_bounds[0] / scale, size_bounds[1] / scale
    lower = np.array([lo] * 3 + [exponent_bounds[0]] * 2 + [-np.inf] * (3 + frame.n_translation))
    upper = np.array([hi] * 3 + [exponent_bounds[1]] * 2 + [np.inf] * (3 + frame.n_translation))
    x0 = np.concatenate([sizes, [1.0, 1.0], np.zeros(3 + frame.n_translation)])
    if init == "pca":
        # Start as the thickest allowed lens whose near face holds the petals: the centre
        # lies off the petals on the side they curve toward (z = z0 + k r^2 locally).
        upper[2] = min(hi, max(max_flatness * sizes[1], 2.0 * lo))
        x0[2] = upper[2]
        p = frame.points @ frame.rotation0
        design = np.column_stack([np.ones(len(p)), p[:, 0] ** 2 + p[:, 1] ** 2])
        (z0, k), *_ = np.linalg.lstsq(design, p[:, 2], rcond=None)
        centre = z0 + np.copysign(upper[2], k)
        x0[8:] = [centre] if frame.anchored else centre * frame.rotation0[:, 2]
    inset = 1e-3 * (upper[:5] - lower[:5])
    x0[:5] = np.clip(x0[:5], lower[:5] + inset, upper[:5] - inset)
    x = _solve(_superellipsoid, frame, x0, bounds=(lower, upper), method="trf",
               max_nfev=max_evaluations, ftol=SUPERELLIPSOID_FTOL)
    if x is None:
        return None
    return _unit_or_none(frame.rotation(x[5:8])[:, int(np.argmin(x[:3]))])


def fit_paraboloid(
    points: np.ndarray,
    axis_point: np.ndarray | None = None,
    max_evaluations: int = MAX_EVALUATIONS,
    min_points: int = MIN_FIT_POINTS,
    init: FitInit = "pca",
) -> np.ndarray | None:
    """Axis (local +z) of a paraboloid z = k1 x^2 + k2 y^2 fitted to the petals.

    Parameters: curvatures k1, k2 (1/metres, either sign, so petals curling down fit as
    well as cupped ones; upstream's z = (x/a)^2 + (y/b)^2 can only open upward), a
    rotation and the vertex, by Levenberg-Marquardt on the height residual, from the
    petals' principal axes (local z along the least spread). With `axis_point` (the pistil
    centroid, (3,) metres) the axis passes through it and only the vertex's position along
    the axis is free: a sideways shift of the vertex adds the same slope as a tilt, so a
    free vertex leaves the tilt to the weak cubic terms (degrees off on a shallow cup).
    init="upstream" starts from the frame's own axes (zero Euler angles) at the petal
    centroid, as the authors' code did, and ignores `axis_point`.

    points: (N, 3) float64, metres. Returns a unit (3,) axis or None on failure.
    """
    if not _usable(points, min_points):
        return None
    if init == "upstream":
        frame, _, _ = _frame(points, None, np.eye(3))
    else:
        frame, _, _ = _frame(points, axis_point)
    x = _solve(_paraboloid, frame, np.zeros(5 + frame.n_translation), method="lm",
               max_nfev=max_evaluations)
    if x is None:
        return None
    return _unit_or_none(frame.rotation(x[2:5])[:, 2])
