"""Train the smallest model that closes the loop: a per-pixel flower classifier fitted on a
`flowerpose dataset --format coco` export, saved as ONNX for `--detector onnx:MODEL.onnx`.

    python scripts/train_pixel_model.py DATASET_DIR --out flower.onnx

The model is logistic regression on the quadratic terms of a pixel's RGB (10 weights): it
learns which colours the dataset's masks hold (petals, receptacle and stamens), nothing of
shape or context. It shows the path a real model takes (dataset -> training -> ONNX export
-> the pipeline's detector) and stands in for one where no deep-learning framework is
installed; a YOLO or Mask R-CNN trained on the same folder plugs in the same way. Needs
numpy, scipy, OpenCV, pycocotools and onnx (`pip install -e '.[test]'`).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
from scipy.optimize import minimize

#: Pixels of each class drawn from the training images (enough for 10 weights).
SAMPLES = 200_000


def features(rgb: np.ndarray) -> np.ndarray:
    """(N, 9) float64: r, g, b, their squares and pairwise products, of (N, 3) RGB in 0-1."""
    r, g, b = rgb.T
    return np.column_stack([r, g, b, r * r, g * g, b * b, r * g, r * b, g * b])


def pixels(dataset: Path, split: str) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) RGB 0-1 of every non-empty pixel of a split's images, and (N,) bool: inside a
    flower's mask. Empty pixels (the grid's background grey) are left out: the detector
    never takes them."""
    from pycocotools.coco import COCO

    background = json.loads((dataset / "dataset.json").read_text())["config"]["grid"][
        "background"]
    coco = COCO(str(dataset / "annotations" / f"instances_{split}.json"))
    colours, labels = [], []
    for image in coco.loadImgs(coco.getImgIds()):
        rgb = cv2.cvtColor(cv2.imread(str(dataset / "images" / split / image["file_name"])),
                           cv2.COLOR_BGR2RGB)
        flower = np.zeros(rgb.shape[:2], bool)
        for annotation in coco.loadAnns(coco.getAnnIds(imgIds=image["id"])):
            flower |= coco.annToMask(annotation).astype(bool)
        used = ~(rgb == background).all(2)
        colours.append(rgb[used] / 255.0)
        labels.append(flower[used])
    return np.concatenate(colours), np.concatenate(labels)


def fit(x: np.ndarray, y: np.ndarray, l2: float = 1e-4) -> tuple[np.ndarray, float]:
    """Weights (9,) and bias of a logistic regression of y ((N,) bool) on x ((N, 9)), the
    two classes weighted equally."""
    weight = np.where(y, 0.5 / max(y.mean(), 1e-9), 0.5 / max(1 - y.mean(), 1e-9)) / len(y)

    def loss(theta: np.ndarray) -> tuple[float, np.ndarray]:
        z = x @ theta[:-1] + theta[-1]
        p = 1 / (1 + np.exp(-z))
        value = np.sum(weight * (np.logaddexp(0, z) - y * z)) + l2 * theta[:-1] @ theta[:-1]
        residual = weight * (p - y)
        return value, np.append(x.T @ residual + 2 * l2 * theta[:-1], residual.sum())

    theta = minimize(loss, np.zeros(x.shape[1] + 1), jac=True, method="L-BFGS-B").x
    return theta[:-1], float(theta[-1])


def export(path: Path, weights: np.ndarray, bias: float) -> Path:
    """The classifier as ONNX: (1, 3, H, W) RGB 0-1 in, (1, 1, H, W) flower probability out."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    r, g, b = "r", "g", "b"
    pairs = [(r, r), (g, g), (b, b), (r, g), (r, b), (g, b)]
    nodes = [helper.make_node("Split", ["images", "sizes"], [r, g, b], axis=1)]
    nodes += [helper.make_node("Mul", list(pair), [f"{pair[0]}{pair[1]}"]) for pair in pairs]
    nodes += [helper.make_node("Concat", [r, g, b] + [f"{u}{v}" for u, v in pairs],
                               ["terms"], axis=1),
              helper.make_node("Conv", ["terms", "weights", "bias"], ["logit"]),
              helper.make_node("Sigmoid", ["logit"], ["output"])]
    graph = helper.make_graph(
        nodes, "pixel_flower",
        [helper.make_tensor_value_info("images", TensorProto.FLOAT, [1, 3, "H", "W"])],
        [helper.make_tensor_value_info("output", TensorProto.FLOAT, [1, 1, "H", "W"])],
        initializer=[numpy_helper.from_array(np.array([1, 1, 1], np.int64), "sizes"),
                     numpy_helper.from_array(weights.reshape(1, -1, 1, 1).astype(np.float32),
                                             "weights"),
                     numpy_helper.from_array(np.array([bias], np.float32), "bias")])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    onnx.checker.check_model(model)
    onnx.save(model, path)
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", type=Path, help="a flowerpose dataset folder (--format coco)")
    parser.add_argument("--out", type=Path, required=True, help="the ONNX model to write")
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    colours, inside = pixels(args.dataset, "train")
    chosen = np.concatenate([rng.permutation(np.flatnonzero(inside == k))[:SAMPLES]
                             for k in (True, False)])
    weights, bias = fit(features(colours[chosen]), inside[chosen])
    export(args.out, weights, bias)
    print(f"trained on {inside.sum()} flower and {(~inside).sum()} other pixels -> {args.out}")
    if (args.dataset / "annotations" / "instances_val.json").exists():
        colours, inside = pixels(args.dataset, "val")
        said = features(colours) @ weights + bias > 0
        both = np.sum(said & inside)
        print(f"val pixels: precision {both / max(said.sum(), 1):.3f}, recall "
              f"{both / max(inside.sum(), 1):.3f}, IoU {both / max(np.sum(said | inside), 1):.3f}")


if __name__ == "__main__":
    main()
