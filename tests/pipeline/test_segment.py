import numpy as np
from candidate_flowers import PETAL, candidate_flowers, plane_axes

from flowerpose.cloudio import Cloud
from flowerpose.pipeline import segment
from flowerpose.pipeline.cluster_config import ClusterConfig
from flowerpose.pipeline.flowers import PipelineConfig
from flowerpose.pipeline.segment import (
    Grouping,
    cluster_flowers,
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


def _grouped(cloud: Cloud) -> Grouping:
    """The grouping of every point of `cloud` under the default settings."""
    config = PipelineConfig()
    return cluster_flowers(cloud, np.arange(len(cloud)), config.outliers, config.cluster,
                           config.colour)


def _split_corolla(gap: float, radius: float = 0.022, points: int = 800
                   ) -> tuple[Cloud, np.ndarray, np.ndarray]:
    """Six seeded candidate flowers (`candidate_flowers`, `points` a flower of `radius`
    metres) with a band `gap` metres wide taken out across the first one's petals, 6 mm
    beside its centre: the petals beyond the band are a piece without a pistil. Returns the
    cloud, the first flower's centre and the piece's indices."""
    cloud, centres, normals = candidate_flowers(points, seed=2, radius=radius)
    u, _ = plane_axes(normals[0])
    across = (cloud.points - centres[0]) @ u
    first = np.linalg.norm(cloud.points - centres[0], axis=1) < 1.4 * radius
    kept = ~(first & (np.abs(across - 0.006 - gap / 2) < gap / 2))
    petal = (cloud.colors == PETAL).all(axis=1)
    cloud = cloud.subset(np.flatnonzero(kept))
    piece = np.flatnonzero(first[kept] & (across[kept] >= 0.006 + gap) & petal[kept])
    return cloud, centres[0], piece


def _first_crop(cloud: Cloud, centre: np.ndarray) -> np.ndarray:
    """The crop (indices into `cloud`) of the flower whose cluster lies nearest `centre`."""
    grouping = _grouped(cloud)
    assert len(grouping.clusters) == 6
    _, crops = crop_flowers(cloud, grouping.clusters, grouping.config)
    return min(crops, key=lambda c: np.linalg.norm(cloud.points[c].mean(axis=0) - centre))


def test_a_corolla_cut_in_two_by_a_gap_wider_than_dbscan_keeps_both_pieces(monkeypatch):
    """A gap across a corolla wider than DBSCAN's radius leaves the piece without the
    pistil too small to be a flower; it joins the flower whose centre it lies within reach
    of, so the crop holds the whole corolla."""
    cloud, centre, piece = _split_corolla(gap=0.012)
    assert len(piece) >= 20
    assert np.isin(piece, _first_crop(cloud, centre)).mean() > 0.9
    # Without the join the piece is lost: the gap does cut the corolla.
    monkeypatch.setattr(segment, "_with_fragments", lambda points, flowers, *_: flowers)
    assert np.isin(piece, _first_crop(cloud, centre)).mean() < 0.1


def test_the_pieces_joined_to_a_flower_do_not_size_the_next_grouping(monkeypatch):
    """Flowers larger than the size band are grouped again with limits sized to them; the
    spacing that sizes that pass is the flowers' own, without the pieces joined to them,
    so joining a piece changes a crop and not the limits the cloud is grouped with."""
    cloud, _, piece = _split_corolla(gap=0.016, radius=0.045, points=400)
    joined = _grouped(cloud)
    assert joined.scale > 1
    monkeypatch.setattr(segment, "_with_fragments", lambda points, flowers, *_: flowers)
    alone = _grouped(cloud)
    # The join took pieces of the cut corolla into a flower ...
    joined_piece = np.isin(piece, np.concatenate(joined.clusters)).sum()
    assert joined_piece > np.isin(piece, np.concatenate(alone.clusters)).sum()
    # ... and left the limits as they were.
    assert (alone.config, alone.density, alone.scale) == (joined.config, joined.density,
                                                          joined.scale)


def test_a_speck_of_petal_colour_beyond_a_flowers_reach_joins_no_flower():
    """A piece without a pistil joins a flower only within reach of its centre: a speck of
    petal colour between two flowers, 4 cm from each, stays out of both crops."""
    cloud, centres, _ = candidate_flowers(800, seed=2)
    rng = np.random.default_rng(0)
    speck = (centres[0] + centres[1]) / 2 + np.c_[rng.uniform(-0.004, 0.004, (40, 2)),
                                                   rng.normal(0, 3e-4, 40)]
    cloud = Cloud(np.vstack([cloud.points, speck]),
                  np.vstack([cloud.colors, np.tile(PETAL, (40, 1))]).astype(np.uint8))
    grouping = _grouped(cloud)
    _, crops = crop_flowers(cloud, grouping.clusters, grouping.config)
    assert len(crops) == 6
    assert not np.isin(np.arange(len(cloud) - 40, len(cloud)), np.concatenate(crops)).any()
