"""The plant generator: determinism, exact truth, sizes, colours and clearances."""

from __future__ import annotations

import dataclasses

import numpy as np
import open3d as o3d
import pytest
import trimesh
from simhelpers import cached_plant

from flowerpose.errors import InputError
from flowerpose.pipeline.colour import rgb_to_hsv
from flowerpose.sim.pieces import Part
from flowerpose.sim.placement import PEDICEL_RADIUS_M, STRAIGHT_BEYOND_RADIUS_M
from flowerpose.sim.plant import Plant, generate_plant
from flowerpose.sim.world_config import preset

SEEDS = {"easy": range(3), "realistic": range(5), "hard": range(2)}


def _scene(vertices: np.ndarray, faces: np.ndarray) -> o3d.t.geometry.RaycastingScene:
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)),
                        o3d.core.Tensor(faces.astype(np.uint32)))
    return scene


def _distance(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> float:
    """Exact least distance from points to a triangle set, metres."""
    query = o3d.core.Tensor(points.astype(np.float32))
    return float(_scene(vertices, faces).compute_distance(query).numpy().min())


def _edges_cross(vertices: np.ndarray, faces_a: np.ndarray, faces_b: np.ndarray) -> bool:
    """True when an edge of a triangle in `faces_a` passes through one in `faces_b`."""
    edges = np.concatenate([faces_a[:, [0, 1]], faces_a[:, [1, 2]], faces_a[:, [2, 0]]])
    start = vertices[edges[:, 0]]
    rays = np.concatenate([start, vertices[edges[:, 1]] - start], 1).astype(np.float32)
    hit = _scene(vertices, faces_b).test_occlusions(o3d.core.Tensor(rays), tnear=0.0, tfar=1.0)
    return bool(hit.numpy().any())


def _own_pedicel(plant: Plant, flower) -> np.ndarray:
    """(F,) bool: peduncle faces of the straight pedicel right behind `flower`."""
    tri = plant.mesh.vertices[plant.mesh.faces] - flower.center
    along = tri @ flower.normal
    radial = np.linalg.norm(tri - along[..., None] * flower.normal, axis=2)
    return ((plant.face_part == Part.PEDUNCLE)
            & (along <= 0.0).all(1)
            & (along >= -(flower.radius + STRAIGHT_BEYOND_RADIUS_M + 1e-4)).all(1)
            & (radial <= PEDICEL_RADIUS_M + 1e-4).all(1))


@pytest.mark.slow
def test_same_seed_gives_identical_plant():
    a = generate_plant(3, preset("realistic"))
    b = generate_plant(3, preset("realistic"))
    for name in ("vertices", "faces"):
        assert np.array_equal(getattr(a.mesh, name), getattr(b.mesh, name))
    assert np.array_equal(a.mesh.visual.vertex_colors, b.mesh.visual.vertex_colors)
    assert np.array_equal(a.face_part, b.face_part)
    assert np.array_equal(a.face_flower, b.face_flower)
    assert a.mesh.export(file_type="ply") == b.mesh.export(file_type="ply")
    assert [(f.center.tobytes(), f.normal.tobytes(), f.radius, f.petals) for f in a.flowers] == \
        [(f.center.tobytes(), f.normal.tobytes(), f.radius, f.petals) for f in b.flowers]
    other = generate_plant(4, preset("realistic"))
    assert len(other.mesh.faces) != len(a.mesh.faces) or not np.array_equal(
        other.mesh.vertices, a.mesh.vertices)


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(SEEDS))
def test_counts_within_preset_ranges(name):
    config = preset(name)
    for seed in SEEDS[name]:
        plant = cached_plant(seed, name)
        assert config.flowers[0] <= len(plant.flowers) <= config.flowers[1]
        assert [f.id for f in plant.flowers] == list(range(len(plant.flowers)))
        assert set(np.unique(plant.face_flower)) == {-1, *range(len(plant.flowers))}
        assert plant.buds <= config.buds[1] and plant.fruit <= config.fruit[1]
        assert all(f.petals in config.petal_counts for f in plant.flowers)
        diameters = [2 * f.radius for f in plant.flowers]
        assert min(diameters) >= config.flower_diameter_m[0]
        assert max(diameters) <= config.flower_diameter_m[1]


def test_plant_size_and_mesh_budget():
    plant = generate_plant(0, preset("realistic"))
    assert len(plant.mesh.faces) < 60_000
    vertices = plant.mesh.vertices
    above = np.unique(plant.mesh.faces[plant.face_part != Part.SOIL])
    assert 0.2 < plant.height < 0.33
    assert np.ptp(vertices[above, :2], axis=0).max() < 0.46
    soil = np.unique(plant.mesh.faces[plant.face_part == Part.SOIL])
    assert np.abs(vertices[soil, 2]).max() < 0.01
    assert abs(vertices[soil, 2].mean()) < 1e-3
    assert vertices[:, 2].min() > -0.01


def test_normals_unit_and_receptacle_along_normal():
    for seed in range(3):
        plant = cached_plant(seed, "realistic")
        centroids = plant.mesh.triangles_center
        for flower in plant.flowers:
            assert np.linalg.norm(flower.normal) == pytest.approx(1.0, abs=1e-12)
            rec = (plant.face_flower == flower.id) & (plant.face_part == Part.RECEPTACLE)
            rel = centroids[rec] - flower.center
            along = rel @ flower.normal
            radial = np.linalg.norm(rel - along[:, None] * flower.normal, axis=1)
            assert along.min() >= 0.0 and along.max() <= 0.0032
            assert along.mean() > 0.0008
            assert radial.max() <= 0.0041


def test_pedicel_arrives_from_behind():
    plant = cached_plant(1, "realistic")
    stem = np.unique(plant.mesh.faces[plant.face_part == Part.PEDUNCLE])
    for flower in plant.flowers:
        rel = plant.mesh.vertices[stem] - flower.center
        near = np.linalg.norm(rel, axis=1) < flower.radius
        assert near.any()
        assert (rel[near] @ flower.normal).max() < 0.0


def test_flat_flowers_fit_plane_of_truth_normal():
    config = dataclasses.replace(preset("realistic"), cup=(0.0, 0.0), petal_cup_jitter=0.0)
    for seed in range(2):
        plant = generate_plant(seed, config)
        centroids, areas = plant.mesh.triangles_center, plant.mesh.area_faces
        for flower in plant.flowers:
            petal = (plant.face_flower == flower.id) & (plant.face_part == Part.PETAL)
            weights = areas[petal] / areas[petal].sum()
            mean = weights @ centroids[petal]
            centred = centroids[petal] - mean
            _, _, axes = np.linalg.svd(centred * np.sqrt(weights)[:, None])
            angle = np.degrees(np.arccos(min(abs(axes[2] @ flower.normal), 1.0)))
            assert angle < 3.0
            assert abs((mean - flower.center) @ flower.normal) < 0.001
            tips = plant.mesh.vertices[np.unique(plant.mesh.faces[petal])] - flower.center
            reach = np.linalg.norm(tips - np.outer(tips @ flower.normal, flower.normal), axis=1)
            assert reach.max() == pytest.approx(flower.radius, rel=0.03)


def test_vertex_colours_sit_in_the_pipeline_ranges():
    plant = cached_plant(0, "realistic")
    hsv = rgb_to_hsv(plant.mesh.visual.vertex_colors[:, :3])
    for part, check in (
        (Part.PETAL, lambda h, s, v: (s <= 0.12) & (v >= 0.85)),
        (Part.RECEPTACLE, lambda h, s, v: (h >= 46) & (h <= 58) & (s >= 0.55) & (v >= 0.8)),
        (Part.LEAF, lambda h, s, v: (h >= 85) & (h <= 130) & (s >= 0.45) & (s <= 0.85)
         & (v >= 0.25) & (v <= 0.7)),
        (Part.SEPAL, lambda h, s, v: (h >= 85) & (h <= 125) & (s >= 0.45)),
        (Part.PEDUNCLE, lambda h, s, v: (h >= 60) & (h <= 88) & (s >= 0.4)),
    ):
        vertices = np.unique(plant.mesh.faces[plant.face_part == part])
        h, s, v = hsv[vertices].T
        # uint8 rounding moves hue by up to about a degree on saturated colours
        assert check(h, s, v).mean() > 0.99, part.name


@pytest.mark.slow
def test_flowers_keep_clearance_from_everything_else():
    for seed, name in ((0, "realistic"), (1, "realistic"), (2, "realistic"), (0, "hard")):
        plant = cached_plant(seed, name)
        vertices, faces = plant.mesh.vertices, plant.mesh.faces
        clearance = plant.config.flower_clearance_m
        rng = np.random.default_rng(seed)
        for flower in plant.flowers:
            own = plant.face_flower == flower.id
            partners = [b for a, b in plant.touching if a == flower.id]
            partners += [a for a, b in plant.touching if b == flower.id]
            other = ~own & ~_own_pedicel(plant, flower) & ~np.isin(plant.face_flower, partners)
            samples, _ = trimesh.sample.sample_surface(
                trimesh.Trimesh(vertices, faces[own], process=False), 5000, seed=rng)
            samples = np.concatenate([samples, vertices[np.unique(faces[own])]])
            assert _distance(samples, vertices, faces[other]) >= clearance, (seed, flower.id)
            near = np.unique(faces[other])
            near = near[np.linalg.norm(vertices[near] - flower.center, axis=1)
                        < flower.radius + 0.01]
            if len(near):
                assert _distance(vertices[near], vertices, faces[own]) >= clearance


def test_touching_flowers_touch_at_the_rim_without_intersecting():
    pairs = 0
    for seed in range(2):
        plant = cached_plant(seed, "hard")
        vertices, faces = plant.mesh.vertices, plant.mesh.faces
        for a, b in plant.touching:
            faces_a, faces_b = faces[plant.face_flower == a], faces[plant.face_flower == b]
            samples, _ = trimesh.sample.sample_surface(
                trimesh.Trimesh(vertices, faces_a, process=False), 20000, seed=0)
            assert _distance(samples, vertices, faces_b) < 0.0015
            assert not _edges_cross(vertices, faces_a, faces_b)
            assert not _edges_cross(vertices, faces_b, faces_a)
            pairs += 1
    assert pairs > 0


def test_unknown_preset_is_a_user_error():
    with pytest.raises(InputError, match="preset"):
        preset("medium")
