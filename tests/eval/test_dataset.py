"""`flowerpose dataset`: COCO and YOLO exports read back with their formats' own readers
(pycocotools; YAML and Ultralytics' label rules), masks checked against the plants' truth,
and the loop closed: a model trained on the export runs as the ONNX detector."""

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from pycocotools import mask as mask_utils
from pycocotools.coco import COCO

from flowerpose.cli import main
from flowerpose.cloudio import read_cloud
from flowerpose.config import apply_overrides
from flowerpose.errors import InputError
from flowerpose.eval.jobs.config import eval_config
from flowerpose.eval.jobs.plant_set import PlantSet
from flowerpose.eval.labelling.coco import rle
from flowerpose.eval.labelling.dataset import DatasetConfig, split_plants, write_dataset
from flowerpose.eval.labelling.yolo import outline
from flowerpose.pipeline.flowers import find_flowers, grid_views

# pycocotools' mask decoding under NumPy 2.
pytestmark = pytest.mark.filterwarnings("ignore:__array__ implementation:DeprecationWarning")

ROOT = Path(__file__).resolve().parents[2]
SEEDS = [0, 1]
#: Six views keep the tests short; the plants are the default (realistic) ones.
CONFIG = apply_overrides(eval_config("realistic"), {"grid.views": "6"})


@pytest.fixture(scope="module")
def exports(tmp_path_factory):
    """The same two plants exported as COCO and as YOLO: {format: (folder, manifest)}."""
    out = tmp_path_factory.mktemp("datasets")
    plants = PlantSet("oracle", "realistic", len(SEEDS), SEEDS[0])
    return {f: (out / f, write_dataset(CONFIG, plants, DatasetConfig(format=f), out / f))
            for f in ("coco", "yolo")}


def _exact_masks(folder: Path, split: str) -> dict[str, dict[int, np.ndarray]]:
    """Per image file of a COCO split: its flowers' masks as pycocotools decodes them."""
    coco = COCO(str(folder / "annotations" / f"instances_{split}.json"))
    return {image["file_name"]: {a["flower"]: coco.annToMask(a).astype(bool)
                                 for a in coco.loadAnns(coco.getAnnIds(imgIds=image["id"]))}
            for image in coco.loadImgs(coco.getImgIds())}


def test_rle_decodes_in_pycocotools_to_the_same_mask():
    rng = np.random.default_rng(0)
    for shape, first in (((7, 5), True), ((30, 41), False), ((1, 1), True)):
        mask = rng.random(shape) < 0.3
        mask[0, 0] = first
        encoded = rle(mask)
        decoded = mask_utils.decode(mask_utils.frPyObjects(encoded, *encoded["size"]))
        assert np.array_equal(decoded.astype(bool), mask)
        assert sum(encoded["counts"]) == mask.size


@pytest.mark.slow
def test_coco_export_loads_in_pycocotools_with_the_detectors_views_and_exact_masks(
        exports, plant0):
    folder, manifest = exports["coco"]
    bundle, plant_dir = plant0
    split = json.loads((folder / "split.json").read_text())
    assert sorted(split["train"] + split["val"]) == SEEDS and len(split["val"]) == 1
    assert manifest["seeds"] == SEEDS and {p["seed"] for p in manifest["plants"]} == set(SEEDS)
    total = 0
    for name in ("train", "val"):
        coco = COCO(str(folder / "annotations" / f"instances_{name}.json"))
        assert [c["name"] for c in coco.loadCats(coco.getCatIds())] == ["flower"]
        for image in coco.loadImgs(coco.getImgIds()):
            assert image["plant_seed"] in split[name]
            pixels = cv2.imread(str(folder / "images" / name / image["file_name"]))
            assert pixels.shape[:2] == (image["height"], image["width"])
        for a in coco.loadAnns(coco.getAnnIds()):
            encoded = coco.annToRLE(a)
            assert list(mask_utils.toBbox(encoded)) == a["bbox"]
            assert mask_utils.area(encoded) == a["area"] >= DatasetConfig().min_pixels
            assert a["iscrowd"] == 0 and a["category_id"] == 1
        total += len(coco.getImgIds())
    assert total == manifest["images"] == 6 * len(SEEDS)

    # Plant 0's images are the views detect makes of its cloud.ply, and each mask's
    # pixels are points of its own flower: within its radius of its true centre.
    seed0 = "train" if 0 in split["train"] else "val"
    cloud = read_cloud(plant_dir / "cloud.ply")
    result = find_flowers(cloud, CONFIG)
    plant = cloud.points[grid_views(cloud, CONFIG)[0]]  # the points the views index
    truth = {f.id: f for f in bundle.plant.flowers}
    masks = _exact_masks(folder, seed0)
    annotated = set()
    for projection in result.projections:
        file = f"seed-0_{projection.view.name}.png"
        image = cv2.cvtColor(cv2.imread(str(folder / "images" / seed0 / file)),
                             cv2.COLOR_BGR2RGB)
        assert np.array_equal(image, projection.image)
        for flower, mask in masks[file].items():
            points = plant[projection.index[mask]]
            distance = np.linalg.norm(points - truth[flower].center, axis=1)
            assert distance.max() < 1.2 * truth[flower].radius
            annotated.add(flower)
    assert annotated == {f.id for f in bundle.plant.flowers if bundle.visible[f.id]}


def test_yolo_export_follows_ultralytics_layout_and_its_polygons_cover_the_masks(exports):
    folder, _ = exports["yolo"]
    data = yaml.safe_load((folder / "data.yaml").read_text())
    assert Path(data["path"]) == folder.resolve() and data["names"] == {0: "flower"}
    assert data["nc"] == 1
    coco_folder, _ = exports["coco"]
    for name in ("train", "val"):
        images = sorted(p.stem for p in (folder / data[name]).iterdir())
        labels = sorted(p.stem for p in (folder / "labels" / name).iterdir())
        assert images == labels and len(images) == 6
        exact = _exact_masks(coco_folder, name)
        inside = union = 0
        for stem in labels:
            lines = (folder / "labels" / name / f"{stem}.txt").read_text().splitlines()
            masks = list(exact[f"{stem}.png"].values())
            assert len(lines) == len(masks)
            height, width = masks[0].shape if masks else (1, 1)
            for line, mask in zip(lines, masks, strict=True):
                values = line.split()
                corners = np.array(values[1:], float).reshape(-1, 2)
                assert values[0] == "0" and len(corners) >= 3
                assert (corners >= 0).all() and (corners <= 1).all()
                # Ultralytics' polygon2mask and segments2boxes.
                drawn = np.zeros((height, width), np.uint8)
                cv2.fillPoly(drawn, [(corners * [width, height]).astype(np.int32)], 1)
                drawn = drawn.astype(bool)
                # Every pixel of the mask, and more only along the bridges between pieces.
                assert (drawn & mask).sum() == mask.sum()
                pieces = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)[0] - 1
                assert pieces > 1 or drawn.sum() <= 1.05 * mask.sum()
                inside, union = inside + mask.sum(), union + drawn.sum()
                rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
                low, high = corners.min(0) * [width, height], corners.max(0) * [width, height]
                assert np.allclose(low, [cols[0] + 0.5, rows[0] + 0.5], atol=0.01)
                assert np.allclose(high, [cols[-1] + 0.5, rows[-1] + 0.5], atol=0.01)
        assert inside / union > 0.95


def test_a_mask_in_pieces_is_one_polygon_over_all_of_them():
    mask = np.zeros((40, 60), bool)
    mask[5:15, 5:20] = True
    mask[25:35, 40:55] = True
    mask[30:33, 2:6] = True
    corners = outline(mask)
    drawn = np.zeros(mask.shape, np.uint8)
    cv2.fillPoly(drawn, [corners.astype(np.int32)], 1)
    assert (drawn.astype(bool) & mask).sum() == mask.sum()  # every piece
    assert corners.min(0).tolist() == [2, 5] and corners.max(0).tolist() == [54, 34]


def test_the_split_is_by_plant_seeded_and_deterministic():
    seeds = list(range(10, 30))
    split = split_plants(seeds, 0.2, 0)
    assert split == split_plants(seeds, 0.2, 0) and len(split["val"]) == 4
    assert sorted(split["train"] + split["val"]) == seeds
    assert split_plants(seeds, 0.2, 1) != split
    assert split_plants(seeds[:3], 0.0, 0) == {"train": seeds[:3], "val": []}
    with pytest.raises(InputError, match="none to train on"):
        split_plants(seeds[:1], 0.2, 0)


@pytest.mark.slow
def test_frames_are_scan_camera_images_with_their_flowers_masks(tmp_path, capsys):
    out = tmp_path / "frames"
    assert main(["dataset", "--plants", "1", "--val-fraction", "0", "--views", "frames",
                 "--frames", "3", "--set", "scan.camera.width=320",
                 "--set", "scan.camera.height=180",
                 "--out", str(out)]) == 0
    assert "3 images" in capsys.readouterr().out
    coco = COCO(str(out / "annotations" / "instances_train.json"))
    images = coco.loadImgs(coco.getImgIds())
    assert [i["file_name"].endswith(".jpg") for i in images] == [True] * 3
    anns = coco.loadAnns(coco.getAnnIds())
    assert anns
    for a in anns:  # petals are lighter than the frame around them
        image = cv2.imread(str(out / "images" / "train" / coco.loadImgs(a["image_id"])[0][
            "file_name"]))
        assert image.shape[:2] == (180, 320)
        assert image[coco.annToMask(a) > 0].mean() > image.mean()
    manifest = json.loads((out / "dataset.json").read_text())
    assert manifest["views"] == "frames" and manifest["config"]["scan"]["width"] == 320


def test_bad_requests_are_one_line_before_any_work(tmp_path, capsys):
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("keep")
    for args, words in ((["--plants", "1"], "none to train on"),
                        (["--plants", "3", "--val-fraction", "1"], "--val-fraction"),
                        (["--plants", "2", "--out", str(foreign)], "choose an empty or new")):
        full = ["dataset", *args] + ([] if "--out" in args else ["--out", str(tmp_path / "d")])
        assert main(full) == 2
        err = capsys.readouterr().err
        assert words in err and err.count("\n") == 1, err
    assert (foreign / "notes.txt").read_text() == "keep"
    assert not (tmp_path / "d").exists()


@pytest.mark.slow
def test_a_model_trained_on_the_export_runs_as_the_onnx_detector(exports, tmp_path):
    folder, manifest = exports["coco"]
    model = tmp_path / "flower.onnx"
    trained = subprocess.run([sys.executable, str(ROOT / "scripts" / "train_pixel_model.py"),
                              str(folder), "--out", str(model)], capture_output=True,
                             text=True, timeout=300)
    assert trained.returncode == 0, trained.stderr
    iou = float(trained.stdout.rsplit("IoU", 1)[1])
    assert iou > 0.8  # on the val plant's pixels
    from flowerpose.sim.bundle import make_plant

    val = manifest["split"]["val"][0]
    plant = make_plant(val, config=CONFIG.sim, out_dir=tmp_path / "plant")
    onnx = dataclasses.replace(CONFIG, detect=dataclasses.replace(
        CONFIG.detect, detector=f"onnx:{model}"))
    found = find_flowers(read_cloud(tmp_path / "plant" / "cloud.ply"), onnx).flowers
    centres = np.array([f.pose.center for f in found])
    truth = np.array([f.center for f in plant.plant.flowers if plant.visible[f.id]])
    near = np.linalg.norm(truth[:, None] - centres[None], axis=2).min(1) < 0.01
    assert near.mean() >= 0.8
