import cv2
import numpy as np
import pytest
from flower_views import WHITE, YELLOW, flower_view

from flowerpose.pipeline.colour import ColourConfig
from flowerpose.pipeline.detect import ColourDetector, DetectConfig, backproject


def test_finds_each_separate_flower_with_a_mask_of_its_disc():
    image = flower_view([(40, 40), (110, 70)])
    occupied = np.ones(image.shape[:2], bool)
    dets = ColourDetector(DetectConfig(), ColourConfig())(image, occupied, 0.001)
    assert len(dets) == 2
    for det in dets:
        assert abs(det.mask.sum() - np.pi * 12**2) < 0.1 * np.pi * 12**2
        assert det.score > 0.8


def test_ignores_specks_yellow_blobs_and_empty_pixels():
    image = flower_view([])
    cv2.circle(image, (30, 30), 1, WHITE, -1)          # below the minimum area
    cv2.circle(image, (100, 60), 12, YELLOW, -1)       # yellow alone: not a flower
    occupied = np.ones(image.shape[:2], bool)
    assert ColourDetector(DetectConfig(), ColourConfig())(image, occupied, 0.001) == []
    flower = flower_view([(60, 60)])
    detector = ColourDetector(DetectConfig(), ColourConfig())
    assert detector(flower, np.zeros_like(occupied), 0.001) == []


def test_minimum_area_is_physical():
    image = flower_view([(60, 60)], radius=4)  # 50 px: 50 mm^2 at 1 mm pixels, 12.5 mm^2 at 0.5 mm
    occupied = np.ones(image.shape[:2], bool)
    detector = ColourDetector(DetectConfig(min_area_m2=2e-5), ColourConfig())
    assert len(detector(image, occupied, 0.001)) == 1
    assert detector(image, occupied, 0.0005) == []


def test_mask_backprojection_returns_fewer_points_than_the_box():
    image = flower_view([(60, 60)])
    occupied = np.ones(image.shape[:2], bool)
    index = np.arange(image.shape[0] * image.shape[1], dtype=np.int32).reshape(image.shape[:2])
    index[0, :] = -1
    det = ColourDetector(DetectConfig(), ColourConfig())(image, occupied, 0.001)
    mask_pts, = backproject(det, index, "mask")
    box_pts, = backproject(det, index, "box")
    assert set(mask_pts) < set(box_pts)
    x0, y0, x1, y1 = det[0].box
    assert len(box_pts) == (x1 - x0) * (y1 - y0)
    assert len(mask_pts) == det[0].mask.sum()


def test_each_detection_is_numbered_with_the_flower_it_became(plant0):
    from flowerpose.cloudio import read_cloud
    from flowerpose.pipeline.flowers import find_flowers
    from flowerpose.pipeline.views import draw_detections

    _, folder = plant0
    result = find_flowers(read_cloud(folder / "cloud.ply"))
    ids = {f.id for f in result.flowers}
    named = [i for view in result.detection_flowers for i in view if i is not None]
    assert [len(v) for v in result.detection_flowers] == [len(d) for d in result.detections]
    assert set(named) == ids  # every flower is some view's box, every number a flower
    plain = draw_detections(result.projections[0], result.detections[0])
    numbered = draw_detections(result.projections[0], result.detections[0],
                               result.detection_flowers[0])
    assert (plain != numbered).any()  # the numbers are drawn


@pytest.mark.slow
def test_a_plugin_detector_runs_in_place_of_the_colour_detector(plant0, tmp_path, capsys):
    import json

    from flowerpose.cli import main

    _, folder = plant0
    assert main(["detect", str(folder / "cloud.ply"), "--out", str(tmp_path / "a")]) == 0
    assert main(["detect", str(folder / "cloud.ply"), "--out", str(tmp_path / "b"),
                 "--detector", "detector_plugins:Same"]) == 0
    flowers = [json.loads((tmp_path / d / "flowers.json").read_text())["flowers"]
               for d in ("a", "b")]
    assert [f["center"] for f in flowers[0]] == [f["center"] for f in flowers[1]]
    capsys.readouterr()
    for name, words in (("detector_plugins:Garbage", "returned a bad detection"),
                        ("detector_plugins:Missing", "cannot load it"),
                        ("no_such_module:X", "cannot load it"), ("not a name", "MODULE:CLASS")):
        assert main(["detect", str(folder / "cloud.ply"), "--out", str(tmp_path / "c"),
                     "--detector", name]) == 2
        err = capsys.readouterr().err
        assert words in err and err.count("\n") == 1, err
