"""The oracle cloud: exact size, determinism, colours the pipeline expects, only seen points."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from simhelpers import box, cached_plant, handmade_plant

from flowerpose.pipeline.colour import rgb_to_hsv
from flowerpose.scan_geometry import path_cameras
from flowerpose.sim.oracle import sample_oracle_cloud
from flowerpose.sim.pieces import Part
from flowerpose.sim.raycast import make_scene, seen_from_any
from flowerpose.sim.world_config import OracleCloudConfig


def _viewpoints(plant):
    return path_cameras(plant.center[:2], plant.height)[1]


def test_exact_count_and_same_rng_gives_same_cloud():
    plant = cached_plant(1, "realistic")
    config = OracleCloudConfig(points=20_000)
    views = _viewpoints(plant)
    a = sample_oracle_cloud(plant, config, views, np.random.default_rng(5))
    b = sample_oracle_cloud(plant, config, views, np.random.default_rng(5))
    assert len(a[0]) == len(a[1]) == len(a[2]) == 20_000
    assert a[0].points.dtype == np.float64 and a[0].colors.dtype == np.uint8
    assert a[1].dtype == np.int8 and a[2].dtype == np.int32
    for x, y in zip((a[0].points, a[0].colors, a[1], a[2]), (b[0].points, b[0].colors, b[1], b[2]),
                    strict=True):
        assert np.array_equal(x, y)


def test_default_cloud_size_colours_and_speed(bundle0):
    cloud, part = bundle0.cloud, bundle0.point_part
    assert len(cloud) == 60_000
    h, s, v = rgb_to_hsv(cloud.colors).T
    petal_rule = (v > 0.75) & ~((h >= 40) & (h <= 140) & (s >= 0.15)) & (s <= 0.39)
    pistil_rule = (h >= 40) & (h <= 63) & (s >= 0.30) & (v >= 0.65)
    petal = part == Part.PETAL
    yellow = np.isin(part, [Part.RECEPTACLE, Part.STAMEN])
    leaf = part == Part.LEAF
    assert petal.sum() > 500 and yellow.sum() > 100
    assert petal_rule[petal].mean() >= 0.95
    assert pistil_rule[yellow].mean() >= 0.90
    assert not petal_rule[leaf].any()
    assert (s[leaf] <= 0.39).mean() < 0.005
    assert not pistil_rule[leaf].any()
    # every flower the scan can see carries points of its own
    flowers = bundle0.point_flower
    assert set(np.flatnonzero(bundle0.visible)) <= set(np.unique(flowers[flowers >= 0]))



def test_every_point_is_seen_and_nothing_lies_under_the_soil(bundle0):
    plant, cloud = bundle0.plant, bundle0.cloud
    scene = make_scene(plant.mesh.vertices, plant.mesh.faces)
    assert seen_from_any(scene, cloud.points, bundle0.viewpoints, 0.0011).all()
    assert cloud.points[:, 2].min() > -0.01
    assert np.abs(cloud.points[bundle0.point_part == Part.SOIL, 2]).max() < 0.01


def test_enclosed_flower_gets_no_points():
    up = np.array([0.0, 0.0, 1.0])
    plant = handmade_plant([(np.array([0.0, 0.0, 0.1]), up), (np.array([0.1, 0.0, 0.1]), up)],
                           [box([0.1, 0.0, 0.1], [0.06, 0.06, 0.04])])
    views = path_cameras(np.zeros(2), 0.2)[1]
    config = OracleCloudConfig(points=5000)
    _, _, flower = sample_oracle_cloud(plant, config, views, np.random.default_rng(0))
    assert (flower == 0).sum() > 100 and not (flower == 1).any()
    everything = dataclasses.replace(config, visible_only=False)
    _, _, flower = sample_oracle_cloud(plant, everything, views, np.random.default_rng(0))
    assert (flower == 1).sum() > 100


def test_position_noise_moves_points_by_its_std():
    plant = cached_plant(0, "easy")
    views = _viewpoints(plant)
    config = OracleCloudConfig(points=5000)
    clean = sample_oracle_cloud(plant, config, views, np.random.default_rng(1))[0]
    noisy = sample_oracle_cloud(plant, dataclasses.replace(config, position_noise_m=0.001), views,
                                np.random.default_rng(1))[0]
    assert np.std(noisy.points - clean.points) == pytest.approx(0.001, rel=0.05)


def _hue_shift(delta: np.ndarray) -> np.ndarray:
    return (delta + 180.0) % 360.0 - 180.0


def test_the_stalks_hue_moves_apart_from_the_leaves():
    plant = cached_plant(0, "easy")
    views = _viewpoints(plant)
    config = OracleCloudConfig(points=5000, color_jitter=0.0)
    clean = sample_oracle_cloud(plant, config, views, np.random.default_rng(1))
    moved = sample_oracle_cloud(plant, dataclasses.replace(
        config, foliage_hue_shift_deg=-17.0, stalk_hue_shift_deg=0.0), views,
        np.random.default_rng(1))
    shift = _hue_shift(rgb_to_hsv(moved[0].colors)[:, 0] - rgb_to_hsv(clean[0].colors)[:, 0])
    leaf, stalk = clean[1] == Part.LEAF, np.isin(clean[1], (Part.PEDUNCLE, Part.PETIOLE))
    assert leaf.sum() > 100 and stalk.sum() > 20
    assert np.median(shift[leaf]) == pytest.approx(-17.0, abs=2.0)
    assert np.abs(np.median(shift[stalk])) < 2.0
    # Unset, the stalks move with the leaves.
    together = sample_oracle_cloud(plant, dataclasses.replace(
        config, foliage_hue_shift_deg=-17.0), views, np.random.default_rng(1))
    shift = _hue_shift(rgb_to_hsv(together[0].colors)[:, 0] - rgb_to_hsv(clean[0].colors)[:, 0])
    assert np.median(shift[stalk]) == pytest.approx(-17.0, abs=2.0)
