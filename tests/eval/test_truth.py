import json

import numpy as np
import pytest

from flowerpose.errors import InputError
from flowerpose.eval.scoring.truth import read_plant_truth, read_sagemaker_truth, sagemaker_normal


def rx(a):
    return np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])


def ry(a):
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


def rz(a):
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])


def cuboid(name, centre, roll, pitch, yaw):
    return {"centerX": centre[0], "centerY": centre[1], "centerZ": centre[2],
            "length": 0.8, "width": 1.3, "height": 1.5, "label": "Flower",
            "labelCategoryAttributes": {}, "objectName": name,
            "roll": roll, "pitch": pitch, "yaw": yaw}


def worker_response(*cuboids):
    """The shape of a SageMaker Ground Truth 3D cuboid worker response (as the authors')."""
    return {"answers": [{"answerContent": {"boundingCuboids": {
        "boundingCuboids": list(cuboids)}}, "workerId": "private.x"}]}


def test_plant_json_round_trip(tmp_path):
    flowers = [{"id": 0, "center": [0.1, 0.2, 0.3], "normal": [0.0, 0.6, 0.8], "radius": 0.013,
                "petals": 5, "stage": "open", "visible": False},
               {"id": 1, "center": [0.4, 0.5, 0.25], "normal": [0.0, 0.0, 2.0], "radius": 0.011,
                "petals": 6, "stage": "open"}]
    path = tmp_path / "plant.json"
    path.write_text(json.dumps({"seed": 7, "units": "m", "frame": "bed", "flowers": flowers}))
    truth = read_plant_truth(path)
    assert [t.id for t in truth] == [0, 1]
    np.testing.assert_allclose(truth[0].center, [0.1, 0.2, 0.3])
    np.testing.assert_allclose(truth[0].normal, [0.0, 0.6, 0.8])
    np.testing.assert_allclose(truth[1].normal, [0.0, 0.0, 1.0])
    assert [t.radius for t in truth] == [0.013, 0.011]
    assert [t.visible for t in truth] == [False, True]


def test_sagemaker_cuboid_gives_scaled_centre_and_x_axis_normal(tmp_path):
    roll, pitch, yaw = 0.4, -0.7, 2.2
    path = tmp_path / "output.json"
    path.write_text(json.dumps(worker_response(cuboid("Flower:1", [25.0, -50.0, 75.0], 0.0, 0.0,
                                                      np.pi / 2),
                                               cuboid("Flower:2", [2.5, 5.0, 10.0], roll, pitch,
                                                      yaw))))
    first, second = read_sagemaker_truth(path)
    assert (first.id, second.id) == ("Flower:1", "Flower:2")
    np.testing.assert_allclose(first.center, [1.0, -2.0, 3.0])
    np.testing.assert_allclose(first.normal, [0.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(second.center, [0.1, 0.2, 0.4])
    # Upstream: intrinsic x-y'-z'' rotations by roll, pitch, yaw, applied to the x axis.
    np.testing.assert_allclose(second.normal, rx(roll) @ ry(pitch) @ rz(yaw) @ [1, 0, 0])
    # The radius: half the larger extent across the normal (width, height), scaled.
    assert first.radius == pytest.approx(0.5 * 1.5 / 25) and first.visible
    scaled = read_sagemaker_truth(path, scale=10.0)
    np.testing.assert_allclose(scaled[0].center, [2.5, -5.0, 7.5])


def test_sagemaker_documented_convention_differs_from_upstream():
    documented = sagemaker_normal(0.4, -0.7, 2.2, convention="sagemaker")
    np.testing.assert_allclose(documented, rz(2.2) @ ry(-0.7) @ rx(0.4) @ [1, 0, 0])
    assert documented @ sagemaker_normal(0.4, -0.7, 2.2) < np.cos(np.radians(10))
    np.testing.assert_allclose(sagemaker_normal(0.0, 0.0, 1.1, convention="sagemaker"),
                               sagemaker_normal(0.0, 0.0, 1.1), atol=1e-12)


def test_sagemaker_json_lines_and_nesting(tmp_path):
    lines = [{"source-ref": "s3://bucket/plant1.txt",
              "flower-labels": worker_response(cuboid("a", [1.0, 2.0, 3.0], 0.0, 0.0, 0.0))},
             worker_response(cuboid("b", [4.0, 5.0, 6.0], 0.0, 0.0, 0.0))]
    path = tmp_path / "output.manifest"
    path.write_text("\n".join(json.dumps(line) for line in lines) + "\n")
    truth = read_sagemaker_truth(path)
    assert [t.id for t in truth] == ["a", "b"]
    np.testing.assert_allclose(truth[1].center, [0.16, 0.2, 0.24])


@pytest.mark.parametrize(("text", "problem"), [
    (None, "file not found"),
    ('{"answers": [', "not valid JSON"),
    ('{"answers": []}', "no \"boundingCuboids\""),
    ("", "not valid JSON"),
    (json.dumps(worker_response(cuboid("n", [1.0, 2.0, 3.0], 0.0, 0.0, 0.0)))
     .replace('"roll": 0.0', '"roll": NaN'), "non-finite roll"),
    (json.dumps(worker_response({"centerX": 1.0, "objectName": "m"})), "'m': missing"),
])
def test_bad_sagemaker_files_are_refused(tmp_path, text, problem):
    path = tmp_path / "labels.json"
    if text is not None:
        path.write_text(text)
    with pytest.raises(InputError, match=problem) as error:
        read_sagemaker_truth(path)
    assert str(path) in str(error.value)


@pytest.mark.parametrize(("flowers", "problem"), [
    ('{"flower": []}', '"flowers" list'),
    ('{"flowers": [{"center": [0, 0], "normal": [0, 0, 1]}]}', 'flower 0: "center"'),
    ('{"flowers": [{"center": [0, 0, 0], "normal": [0, 0, 0]}]}', "zero vector"),
    ('{"flowers": [{"center": [0, 0, NaN], "normal": [0, 0, 1]}]}', "finite"),
    ("[1, 2", "not valid JSON"),
])
def test_bad_plant_files_are_refused(tmp_path, flowers, problem):
    path = tmp_path / "plant.json"
    path.write_text(flowers)
    with pytest.raises(InputError, match=problem):
        read_plant_truth(path)
    with pytest.raises(InputError, match="file not found"):
        read_plant_truth(tmp_path / "missing.json")
