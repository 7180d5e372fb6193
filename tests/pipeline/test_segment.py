import numpy as np

from flowerpose.cloudio import Cloud
from flowerpose.pipeline.segment import (
    ClusterConfig,
    crop_flowers,
    oriented_box,
    split_by_centres,
)


def test_oriented_box_fits_a_rotated_slab():
    rng = np.random.default_rng(1)
    local = rng.uniform(-0.5, 0.5, (2000, 3)) * [0.03, 0.02, 0.004]
    angle = 0.7
    rot = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0],
                    [0, 0, 1]])
    points = local @ rot.T + [1.0, 2.0, 0.3]
    box = oriented_box(points)
    np.testing.assert_allclose(np.sort(box.extent), [0.004, 0.02, 0.03], atol=1e-3)
    assert box.contains(points).all()
    assert not box.contains(np.array([[1.0, 2.0, 0.31]])).any()
    assert np.isclose(np.linalg.det(box.rotation), 1.0)


def test_split_by_centres_merges_close_centres_and_splits_far_ones():
    points = np.c_[np.arange(0, 0.04, 0.002), np.zeros(20), np.zeros(20)]
    far = split_by_centres(points, [np.array([0]), np.array([15])], 0.012, 0.004)
    assert (far[:7] == far[0]).all() and (far[9:] == far[15]).all() and far[0] != far[15]
    close = split_by_centres(points, [np.array([0]), np.array([2])], 0.012, 0.004)
    assert (close == 0).all()


def test_split_follows_the_surface_not_the_straight_line():
    # Flower A: a disc in the plane z = 0 around the origin. Flower B: a vertical disc whose
    # pistil is 18 mm away and whose lower petals hang over A's centre side of the bisector.
    grid = np.arange(-0.015, 0.0151, 0.0015)
    u, v = np.meshgrid(grid, grid)
    disc = np.c_[u.ravel(), v.ravel()][np.hypot(u.ravel(), v.ravel()) <= 0.015]
    a = np.c_[disc, np.zeros(len(disc))]
    b = np.c_[np.full(len(disc), 0.018), disc[:, 0], disc[:, 1] + 0.016]
    points = np.vstack([a, b])
    centre_a = np.flatnonzero(np.linalg.norm(points, axis=1) < 0.002)
    centre_b = len(a) + np.flatnonzero(np.linalg.norm(b - [0.018, 0, 0.016], axis=1) < 0.002)
    labels = split_by_centres(points, [centre_a, centre_b], 0.012, 0.004)
    assert (labels[:len(a)] == labels[centre_a[0]]).mean() > 0.97
    assert (labels[len(a):] == labels[centre_b[0]]).mean() > 0.97


def test_crops_of_overlapping_boxes_do_not_share_points():
    rng = np.random.default_rng(2)
    a = rng.normal([0, 0, 0], 0.005, (300, 3))
    b = rng.normal([0.02, 0, 0], 0.005, (300, 3))
    points = np.vstack([a, b])
    cloud = Cloud(points, np.full((600, 3), 250, np.uint8))
    clusters = [np.arange(300), np.arange(300, 600)]
    boxes, crops = crop_flowers(cloud, clusters, ClusterConfig(crop_margin_m=0.004))
    assert len(boxes) == 2
    assert not set(crops[0]) & set(crops[1])
    assert np.mean(crops[0] < 300) > 0.95 and np.mean(crops[1] >= 300) > 0.95
    # Upstream's box crops overlap where the boxes do.
    _, crops = crop_flowers(cloud, clusters, ClusterConfig(crop="box"))
    assert set(crops[0]) & set(crops[1])
