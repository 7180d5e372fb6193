import numpy as np
import pytest

from flowerpose.cloudio import Cloud
from flowerpose.errors import InputError
from flowerpose.pipeline.grid import GridConfig, project, view_directions


def _cloud(points, colors=None):
    points = np.asarray(points, float)
    if colors is None:
        colors = np.tile([200, 200, 200], (len(points), 1))
    return Cloud(points, np.asarray(colors, np.uint8))


def _view(name, count=6):
    return next(v for v in view_directions(count) if v.name == name)


@pytest.mark.parametrize("count", [6, 14, 26])
def test_views_are_distinct_orthonormal_right_handed(count):
    views = view_directions(count)
    assert len(views) == count
    assert len({v.name for v in views}) == count
    for v in views:
        basis = np.stack([v.right, v.up, v.direction])
        np.testing.assert_allclose(basis @ basis.T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(np.cross(v.direction, v.up), v.right, atol=1e-12)


def test_side_views_have_z_up():
    for name in ("+x", "-x", "+y", "-y"):
        np.testing.assert_allclose(_view(name).up, [0, 0, 1])


def test_zbuffer_nearest_point_along_travel_direction_owns_the_pixel():
    # Two points on one line of sight along x, different colours.
    cloud = _cloud([[0.0, 0.05, 0.05], [0.1, 0.05, 0.05]], [[255, 0, 0], [0, 0, 255]])
    config = GridConfig(splat_radius_px=0)
    forward = project(cloud, _view("+x"), config)
    backward = project(cloud, _view("-x"), config)
    assert set(np.unique(forward.index[forward.occupied])) == {0}
    assert set(np.unique(backward.index[backward.occupied])) == {1}
    assert (forward.image[forward.occupied] == [255, 0, 0]).all()
    assert (backward.image[backward.occupied] == [0, 0, 255]).all()


def test_every_splat_pixel_maps_to_a_point_within_the_splat_radius():
    rng = np.random.default_rng(1)
    points = rng.random((3000, 3)) * [0.1, 0.08, 0.06]
    config = GridConfig(pixel_size_m=0.001, splat_radius_px=3)
    proj = project(_cloud(points), _view("+z"), config)
    rows, cols = np.nonzero(proj.occupied)
    owner = points[proj.index[rows, cols]]
    # Pixel centres back in bed-frame (right, up) coordinates.
    px, r = config.pixel_size_m, config.splat_radius_px
    u = proj.origin[0] + (cols - r + 0.5) * px
    v = proj.origin[1] - (rows - r + 0.5) * px
    du = np.abs(owner @ proj.view.right - u)
    dv = np.abs(owner @ proj.view.up - v)
    assert (np.hypot(du, dv) <= (r + 1) * px * np.sqrt(2)).all()
    # The owner is the nearest of all points whose splat covers the pixel: check on a sample.
    up_owner = owner @ proj.view.direction
    for k in rng.choice(len(rows), 50, replace=False):
        covers = np.hypot(points @ proj.view.right - u[k], points @ proj.view.up - v[k]) \
            <= (r - 1) * px
        if covers.any():
            assert up_owner[k] <= (points[covers] @ proj.view.direction).min() + 1e-12


def test_a_single_point_splat_covers_the_disc_and_keeps_its_index():
    proj = project(_cloud([[0.0, 0.0, 0.0]]), _view("+z"), GridConfig(splat_radius_px=2))
    assert proj.image.shape[:2] == (5, 5)
    assert proj.occupied.sum() == 21  # the 5x5 square less its 4 corners
    assert set(np.unique(proj.index[proj.occupied])) == {0}


def test_pixels_are_square_in_metres():
    rng = np.random.default_rng(2)
    points = rng.random((20000, 3)) * [0.2, 0.1, 0.05]
    proj = project(_cloud(points), _view("+z"), GridConfig(pixel_size_m=0.001, splat_radius_px=0))
    height, width = proj.image.shape[:2]
    assert abs(width - 200) <= 2 and abs(height - 100) <= 2


def test_too_fine_a_grid_is_refused():
    cloud = _cloud([[0, 0, 0], [5.0, 0, 0]])
    with pytest.raises(InputError, match="pixel_size_m"):
        project(cloud, _view("+z"), GridConfig(pixel_size_m=0.0001))
