"""The built-in ONNX detector on tiny models the tests build with onnx.helper: a
segmentation model (light pixels by a colour threshold) and a box model (fixed rows)."""

from pathlib import Path

import numpy as np
import onnx
import pytest
from flower_views import flower_view
from onnx import TensorProto, helper, numpy_helper

from flowerpose.errors import InputError
from flowerpose.pipeline.colour import ColourConfig
from flowerpose.pipeline.detect import ColourDetector, DetectConfig
from flowerpose.pipeline.onnx_detector import OnnxConfig, OnnxDetector, letterbox


def _save(path: Path, nodes, output_shape, input_shape=(1, 3, "H", "W"), initializers=()):
    graph = helper.make_graph(
        nodes, "tiny", [helper.make_tensor_value_info("images", TensorProto.FLOAT, input_shape)],
        [helper.make_tensor_value_info("output", TensorProto.FLOAT, output_shape)],
        initializer=list(initializers))
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    onnx.checker.check_model(model)
    onnx.save(model, path)
    return path


def flower_model(path: Path, threshold: float = 0.55) -> Path:
    """A segmentation model: flower probability 1 where red and green are both above
    `threshold` (white petals and yellow centres, not leaves or soil), else 0; (1, 1, H, W)
    at any input size."""
    constants = {"starts": [0], "ends": [2], "axes": [1]}
    nodes = [helper.make_node("Slice", ["images", "starts", "ends", "axes"], ["red_green"]),
             helper.make_node("ReduceMin", ["red_green"], ["darker"], axes=[1], keepdims=1),
             helper.make_node("Greater", ["darker", "threshold"], ["light"]),
             helper.make_node("Cast", ["light"], ["output"], to=TensorProto.FLOAT)]
    return _save(path, nodes, (1, 1, "H", "W"), initializers=[
        numpy_helper.from_array(np.array(threshold, np.float32), "threshold"),
        *(numpy_helper.from_array(np.array(v, np.int64), k) for k, v in constants.items())])


def box_model(path: Path, rows: np.ndarray, size: int = 320) -> Path:
    """A box model with a fixed (1, 3, size, size) input whose output is always `rows`
    ((N, 6) [x1, y1, x2, y2, score, class], input pixels), times 1 when the image holds
    any light (so the graph reads its input)."""
    nodes = [helper.make_node("ReduceMax", ["images"], ["brightest"], keepdims=0),
             helper.make_node("Ceil", ["brightest"], ["one"]),
             helper.make_node("Mul", ["rows", "one"], ["output"])]
    return _save(path, nodes, (1, len(rows), 6), input_shape=(1, 3, size, size),
                 initializers=[numpy_helper.from_array(rows[None].astype(np.float32), "rows")])


def test_letterbox_scales_to_fit_and_pads_like_ultralytics():
    image = np.full((120, 160, 3), 255, np.uint8)
    tensor, scale, pad = letterbox(image, (320, 320))
    assert tensor.shape == (1, 3, 320, 320) and tensor.dtype == np.float32
    assert scale == 2.0 and pad == (0, 40)
    assert tensor[0, :, 40:280].min() == 1.0  # the image, 0-1
    assert np.allclose(tensor[0, :, :40], 114 / 255) and np.allclose(tensor[0, :, 280:], 114 / 255)


def test_a_segmentation_model_finds_the_flowers_the_colour_detector_finds(tmp_path):
    image = flower_view([(40, 40), (110, 70)])
    occupied = np.ones(image.shape[:2], bool)
    occupied[:, 150:] = False
    detector = OnnxDetector(flower_model(tmp_path / "flower.onnx"), DetectConfig())
    assert detector.size == (640, 640)  # dynamic input: detect.onnx.input_px
    found = sorted(detector(image, occupied, 0.001), key=lambda d: d.box)
    colour = sorted(ColourDetector(DetectConfig(), ColourConfig())(image, occupied, 0.001),
                    key=lambda d: d.box)
    assert len(found) == len(colour) == 2
    for det, ref in zip(found, colour, strict=True):
        assert np.abs(np.subtract(det.box, ref.box)).max() <= 1
        assert det.mask.shape == (det.box[3] - det.box[1], det.box[2] - det.box[0])
        assert 0.5 <= det.score <= 1
        assert abs(int(det.mask.sum()) - int(ref.mask.sum())) <= 0.05 * ref.mask.sum()
    assert found[1].box[2] <= 150  # nothing where no point is


def test_a_box_model_gives_its_flower_boxes_in_the_views_pixels(tmp_path):
    # Input 320 x 320 for a 120 x 160 view: scale 2, 40 px of padding on top.
    rows = np.array([[40, 100, 120, 180, 0.9, 0],    # the flower at (20, 30)-(60, 70)
                     [200, 100, 260, 160, 0.1, 0],   # below the score threshold
                     [0, 40, 60, 100, 0.95, 1],      # another class
                     [300, 300, 320, 320, 0.8, 0]])  # only padding: outside the view
    detector = OnnxDetector(box_model(tmp_path / "boxes.onnx", rows), DetectConfig())
    assert detector.size == (320, 320)  # the model's own fixed size
    image = flower_view([(40, 50)])
    occupied = np.ones(image.shape[:2], bool)
    occupied[30:40, 20:60] = False
    found = detector(image, occupied, 0.001)
    assert [d.box for d in found] == [(20, 30, 60, 70)]
    assert found[0].score == pytest.approx(0.9)
    assert np.array_equal(found[0].mask, occupied[30:70, 20:60])
    lower = DetectConfig(onnx=OnnxConfig(score_threshold=0.05, flower_class=0))
    assert len(OnnxDetector(tmp_path / "boxes.onnx", lower)(image, occupied, 0.001)) == 2


def test_bad_models_are_one_line_naming_the_file(tmp_path):
    image, occupied = flower_view([(40, 40)]), np.ones((120, 160), bool)
    (tmp_path / "garbage.onnx").write_bytes(b"not a model")
    for path, words in ((tmp_path / "missing.onnx", "no such ONNX model"),
                        (tmp_path / "garbage.onnx", "cannot load it")):
        with pytest.raises(InputError, match=words) as caught:
            OnnxDetector(path, DetectConfig())
        assert str(path) in str(caught.value) and "\n" not in str(caught.value)
    flat = _save(tmp_path / "flat.onnx", [helper.make_node(
        "ReduceMean", ["images"], ["output"], axes=[2, 3], keepdims=0)], (1, 3))
    scaled = _save(tmp_path / "scaled.onnx", [helper.make_node(
        "Mul", ["images", "five"], ["output"])], (1, 3, "H", "W"),
        initializers=[numpy_helper.from_array(np.array(5.0, np.float32), "five")])
    for path, words in ((flat, "expected boxes"), (scaled, "not a probability")):
        with pytest.raises(InputError, match=words):
            OnnxDetector(path, DetectConfig())(image, occupied, 0.001)


@pytest.mark.slow
def test_detect_runs_an_onnx_model_in_place_of_the_colour_detector(plant0, tmp_path, capsys):
    import json

    from flowerpose.cli import main

    _, folder = plant0
    model = flower_model(tmp_path / "flower.onnx")
    cloud = str(folder / "cloud.ply")
    assert main(["detect", cloud, "--out", str(tmp_path / "colour"), "--set", "grid.views=6"]) == 0
    assert main(["detect", cloud, "--out", str(tmp_path / "onnx"), "--set", "grid.views=6",
                 "--detector", f"onnx:{model}"]) == 0
    found = [np.array([f["center"] for f in json.loads(
        (tmp_path / name / "flowers.json").read_text())["flowers"]]) for name in ("colour", "onnx")]
    truth = np.array([f["center"] for f in json.loads((folder / "plant.json").read_text())[
        "flowers"]])
    for centres in found:  # every flower found is a true one, within 1 cm
        assert len(centres) >= 5
        assert np.linalg.norm(centres[:, None] - truth[None], axis=2).min(1).max() < 0.01
    # The model's output decides: one that sees no flower finds none.
    blind = flower_model(tmp_path / "blind.onnx", threshold=1.0)
    assert main(["detect", cloud, "--out", str(tmp_path / "blind"), "--set", "grid.views=6",
                 "--detector", f"onnx:{blind}"]) == 0
    assert json.loads((tmp_path / "blind" / "flowers.json").read_text())["flowers"] == []
    capsys.readouterr()
    assert main(["detect", cloud, "--out", str(tmp_path / "bad"), "--detector",
                 f"onnx:{tmp_path / 'missing.onnx'}"]) == 2
    err = capsys.readouterr().err
    assert "missing.onnx: no such ONNX model file" in err and err.count("\n") == 1
    # eval says so before it makes any plant.
    assert main(["eval", "--source", "oracle", "--plants", "1", "--out", str(tmp_path / "ev"),
                 "--detector", f"onnx:{tmp_path / 'missing.onnx'}"]) == 2
    assert "no such ONNX model file" in capsys.readouterr().err
    assert not (tmp_path / "ev" / "plants").exists()
