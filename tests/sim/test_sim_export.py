"""Files of a generated plant, and the one-call bundle."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from flowerpose.cloudio import read_cloud
from flowerpose.sim.bundle import make_plant


def test_make_plant_writes_truth_mesh_labels_and_cloud(tmp_path):
    bundle = make_plant(2, "easy", points=4000, out_dir=tmp_path / "a")
    paths = bundle.paths
    assert set(paths) == {"truth", "mesh", "labels", "cloud"}
    truth = json.loads(paths["truth"].read_text())
    assert truth["seed"] == 2 and truth["units"] == "m" and truth["frame"] == "bed"
    assert truth["preset"] == "easy"
    assert truth["plant_center"] == [1.5, 0.75, 0.0]
    assert truth["height"] == pytest.approx(bundle.plant.height)
    assert truth["distractors"] == {"buds": 0, "fruit": 0}
    assert len(truth["flowers"]) == len(bundle.plant.flowers)
    for entry, flower, seen, share in zip(truth["flowers"], bundle.plant.flowers, bundle.visible,
                                          bundle.fraction, strict=True):
        assert set(entry) == {"id", "center", "normal", "radius", "petals", "stage", "visible",
                              "visible_fraction"}
        assert entry["id"] == flower.id and entry["stage"] == "open"
        assert np.array_equal(entry["center"], flower.center)
        assert np.array_equal(entry["normal"], flower.normal)
        assert entry["visible"] == bool(seen) and entry["visible_fraction"] == float(share)

    mesh = trimesh.load(paths["mesh"], process=False)
    assert len(mesh.faces) == len(bundle.plant.mesh.faces)
    assert np.array_equal(mesh.visual.vertex_colors, bundle.plant.mesh.visual.vertex_colors)
    labels = np.load(paths["labels"])
    assert np.array_equal(labels["face_part"], bundle.plant.face_part)
    assert np.array_equal(labels["face_flower"], bundle.plant.face_flower)
    cloud = read_cloud(paths["cloud"])
    assert len(cloud) == 4000
    assert np.array_equal(cloud.colors, bundle.cloud.colors)
    assert np.allclose(cloud.points, bundle.cloud.points)

    again = make_plant(2, "easy", points=4000, out_dir=tmp_path / "b")
    for name, path in paths.items():
        assert path.read_bytes() == again.paths[name].read_bytes(), name


def test_read_plant_gives_back_the_mesh_labels_and_truth(tmp_path):
    from flowerpose.sim.export import read_plant

    bundle = make_plant(1, "easy", points=2000, out_dir=tmp_path)
    plant = read_plant(tmp_path)
    original = bundle.plant
    np.testing.assert_allclose(plant.mesh.vertices, original.mesh.vertices, atol=1e-6)
    np.testing.assert_array_equal(plant.mesh.faces, original.mesh.faces)
    np.testing.assert_array_equal(plant.mesh.visual.vertex_colors,
                                  original.mesh.visual.vertex_colors)
    np.testing.assert_array_equal(plant.face_flower, original.face_flower)
    assert [f.id for f in plant.flowers] == [f.id for f in original.flowers]
    np.testing.assert_allclose(plant.flowers[0].normal, original.flowers[0].normal)
    np.testing.assert_allclose(plant.center, original.center)
    assert plant.height == pytest.approx(original.height)
