import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from flowerpose.pipeline.fit import fit_paraboloid, fit_plane, fit_superellipsoid

RADIUS = 0.015  # corolla radius, metres
INNER = 0.003  # receptacle radius: no petals inside it


def petal_disc(seed: int, rim: float, n: int = 300, noise: float = 3e-4):
    """Petals of a cupped disc (rim raised by `rim` metres; negative curls down), rotated
    at random: points (n, 3) metres, the true normal and a point on the flower axis."""
    rng = np.random.default_rng(seed)
    r = RADIUS * np.sqrt(rng.uniform((INNER / RADIUS) ** 2, 1.0, n))
    theta = rng.uniform(0.0, 2.0 * np.pi, n)
    local = np.column_stack([r * np.cos(theta), r * np.sin(theta), rim * (r / RADIUS) ** 2])
    local += rng.normal(0.0, noise, local.shape)
    rotation = Rotation.random(random_state=seed)
    offset = np.array([0.4, 0.3, 0.2])
    return rotation.apply(local) + offset, rotation.apply([0.0, 0.0, 1.0]), offset


def axis_error_deg(axis, normal):
    """Angle between an unoriented axis and the normal, degrees."""
    return float(np.degrees(np.arccos(min(1.0, abs(float(axis @ normal))))))


@pytest.mark.parametrize("rim", [0.003, -0.003, 0.0], ids=["cupped", "curled", "flat"])
@pytest.mark.parametrize("seed", range(4))
def test_each_fit_recovers_the_axis(rim, seed):
    points, normal, centre = petal_disc(seed, rim)
    axes = {"plane": fit_plane(points),
            "superellipsoid": fit_superellipsoid(points, axis_point=centre),
            "paraboloid": fit_paraboloid(points, axis_point=centre)}
    for method, axis in axes.items():
        assert axis is not None, method
        assert np.isclose(np.linalg.norm(axis), 1.0)
        assert axis_error_deg(axis, normal) < 1.0, method


@pytest.mark.parametrize("rim", [0.003, -0.003], ids=["cupped", "curled"])
def test_a_free_centre_still_finds_the_axis_roughly(rim):
    # Without a point on the axis, a sideways shift of the centre or vertex mimics a tilt
    # of the shallow cap, which leaves a few degrees of error.
    for seed in range(4):
        points, normal, _ = petal_disc(seed, rim)
        assert axis_error_deg(fit_superellipsoid(points), normal) < 5.0
        assert axis_error_deg(fit_paraboloid(points), normal) < 5.0


def test_upstream_start_fits_a_flat_disc():
    points, normal, _ = petal_disc(0, 0.0)
    assert axis_error_deg(fit_superellipsoid(points, init="upstream"), normal) < 1.0


def test_too_few_or_bad_points_give_none():
    points, _, centre = petal_disc(0, 0.003)
    few = points[:9]
    assert fit_plane(few) is None
    assert fit_superellipsoid(few, axis_point=centre) is None
    assert fit_paraboloid(few, axis_point=centre) is None
    broken = points.copy()
    broken[5, 1] = np.nan
    assert fit_plane(broken) is None
    assert fit_superellipsoid(broken) is None
    assert fit_paraboloid(broken) is None
    assert fit_paraboloid(points, axis_point=np.array([np.nan, 0.0, 0.0])) is None


@pytest.mark.parametrize("shape", ["blob", "line"])
def test_points_without_a_surface_give_no_normal(shape):
    rng = np.random.default_rng(3)
    if shape == "blob":
        points = np.tile([0.1, 0.2, 0.3], (500, 1)) + rng.normal(0, 1e-12, (500, 3))
    else:
        points = np.outer(np.linspace(0, 0.02, 200), [1.0, 2.0, 0.5]) + [0.1, 0.2, 0.3]
    assert fit_plane(points) is None
    assert fit_superellipsoid(points) is None
    assert fit_paraboloid(points) is None


@pytest.mark.parametrize("seed", range(3))
def test_a_sheet_above_and_a_stem_below_do_not_tilt_the_robust_plane(seed):
    # A corolla of 1,000 points (radius 12 mm) with a tilted sheet of 250 petal-coloured
    # points 16 mm above part of it (a leaf's sheen) and 160 points of stem below its
    # centre, as a reconstruction's crop can hold: the least-squares start leans to them.
    rng = np.random.default_rng(seed)
    r, angle = 0.012 * np.sqrt(rng.uniform(0, 1, 1000)), rng.uniform(0, 2 * np.pi, 1000)
    disc = np.column_stack([r * np.cos(angle), r * np.sin(angle), rng.normal(0, 3e-4, 1000)])
    u, v = rng.uniform(-0.004, 0.012, 250), rng.uniform(-0.01, 0.01, 250)
    sheet = np.column_stack([u, v, 0.016 + 0.6 * u])
    stem = np.column_stack([rng.normal(0, 0.002, (160, 2)), rng.uniform(-0.016, -0.006, 160)])
    rotation = Rotation.random(random_state=seed)
    points = rotation.apply(np.vstack([disc, sheet, stem]))
    normal = rotation.apply([0.0, 0.0, 1.0])
    fitted = fit_plane(points, robust_iterations=5)
    assert np.degrees(np.arccos(abs(fitted @ normal))) < 3.0
    # A floor on the cut-off of a third of the corolla's radius still drops them.
    floored = fit_plane(points, robust_iterations=5, min_scale=0.35 * 0.012)
    assert np.degrees(np.arccos(abs(floored @ normal))) < 3.0
    least_squares = fit_plane(points)
    assert np.degrees(np.arccos(abs(least_squares @ normal))) > 10.0


def test_points_nearer_the_plane_than_the_floor_all_count():
    # A sparse corolla (26 points, radius 12 mm): three fifths flat to 0.05 mm, the rest a
    # petal curled up by up to 2.5 mm. Their tight spread makes the reweighting drop the
    # curled petal; with a floor of 4.2 mm every point counts, as in least squares.
    rng = np.random.default_rng(0)
    r, angle = 0.012 * np.sqrt(rng.uniform(0.05, 1.0, 26)), rng.uniform(0, 2 * np.pi, 26)
    x, y, z = r * np.cos(angle), r * np.sin(angle), rng.normal(0, 5e-5, 26)
    edge = np.quantile(x, 0.6)
    z = np.where(x > edge, z + 0.25 * (x - edge), z)
    points = Rotation.random(random_state=0).apply(np.column_stack([x, y, z]))

    def apart(a, b):
        return np.degrees(np.arccos(min(1.0, abs(a @ b))))

    least_squares = fit_plane(points)
    assert apart(fit_plane(points, robust_iterations=5), least_squares) > 3.0
    assert apart(fit_plane(points, robust_iterations=5, min_scale=0.0042), least_squares) < 0.2


# Seeds whose least-median plane (over its discrete directions) is the row's.
@pytest.mark.parametrize("seed", [0, 4, 5, 6])
def test_a_least_median_plane_through_a_row_of_a_sparse_corolla_is_no_start(seed):
    # Twelve petal points, seven of them in a row across the flower: the thinnest slab
    # that holds half the points is the row's, on a plane standing across the corolla,
    # and the other five lie beyond the reweighting's cut-off from it. Too few points are
    # left near it for a fit, so the plane is the least-squares one.
    rng = np.random.default_rng(seed)
    row = np.column_stack([np.linspace(-0.012, 0.012, 7), rng.normal(0, 2e-5, 7),
                           rng.normal(0, 3e-4, 7)])
    angle = rng.uniform(np.pi / 3, 2 * np.pi / 3, 5) + np.pi * rng.integers(0, 2, 5)
    r = rng.uniform(0.010, 0.014, 5)
    rest = np.column_stack([r * np.cos(angle), r * np.sin(angle), rng.normal(0, 3e-4, 5)])
    rotation = Rotation.random(random_state=seed)
    points = rotation.apply(np.vstack([row, rest]))
    normal = rotation.apply([0.0, 0.0, 1.0])
    robust = fit_plane(points, robust_iterations=5, min_scale=0.35 * RADIUS)
    assert axis_error_deg(robust, normal) < 5.0
