"""2D flower detection on the projected images: a `Detector` interface and a weight-free default.

The paper fine-tuned YOLOv10 through a hosted API whose weights were never published; the
default here needs no weights: white petal pixels around a yellow centre, grouped into
connected components, each giving a box and a mask. A user's exported model runs through
the built-in ONNX detector (`onnx:MODEL.onnx`, `pipeline/onnx_detector.py`), and any other
detector (a local YOLO, say) plugs in by implementing `Detector`.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Protocol

import cv2
import numpy as np

from flowerpose.config import require
from flowerpose.errors import InputError
from flowerpose.pipeline.colour import ColourConfig, petal_mask, pistil_mask, rgb_to_hsv

#: The `detect.detector` prefix of the built-in ONNX detector: "onnx:MODEL.onnx".
ONNX_PREFIX = "onnx:"


@dataclass(frozen=True)
class OnnxConfig:
    """The built-in ONNX detector (`detect.detector=onnx:MODEL.onnx`): how a user's model
    is fed and read (`pipeline/onnx_detector.py` documents the contract)."""

    input_px: int = 640
    """Side of the square input, pixels, for a model whose input size is not fixed (a
    fixed-size model gets its own size); each view is letterboxed to it (Ultralytics'
    default image size)."""
    score_threshold: float = 0.25
    """A box model's rows scoring below this are dropped (Ultralytics' default
    confidence)."""
    mask_threshold: float = 0.5
    """A segmentation model's pixels count as flower from this probability on."""
    flower_class: int = 0
    """The flower's class index: a box row's class, or a segmentation output's channel. 0
    for a model trained on `flowerpose dataset` (YOLO class 0; COCO category 1, class 0 of
    a model trained with contiguous class indices)."""

    def __post_init__(self):
        require(self.input_px >= 32, "detect.onnx.input_px", "must be at least 32 pixels")
        require(0 <= self.score_threshold <= 1, "detect.onnx.score_threshold",
                "must be within 0-1")
        require(0 < self.mask_threshold <= 1, "detect.onnx.mask_threshold",
                "must be above 0, at most 1")
        require(self.flower_class >= 0, "detect.onnx.flower_class", "must be 0 or more")


@dataclass(frozen=True)
class DetectConfig:
    """Which detector runs and how its detections return to 3D."""

    detector: str = "colour"
    """The detector: "colour" (white petals around a yellow centre; needs no weights),
    "onnx:MODEL.onnx" (a user's exported box or segmentation model on onnxruntime, the
    [onnx] extra; `detect.onnx`), or "MODULE:CLASS", any importable class with the
    `Detector` interface (made with no arguments, called once per view), e.g. a YOLO model
    wrapped in a few lines."""
    backproject: Literal["mask", "box"] = "mask"
    """What returns to 3D: the detection's pixel mask (the paper's suggested improvement;
    default) or every pixel of its box (the paper)."""
    close_radius_px: int = 1
    """Morphological closing radius joining a flower's pixels across small gaps, pixels."""
    min_area_m2: float = 2.0e-5
    """Smallest component kept, square metres (20 mm^2: a 2 cm flower seen edge-on)."""
    max_area_m2: float = 5.0e-3
    """Largest component kept, square metres (a cluster of a dozen touching flowers)."""
    min_white_fraction: float = 0.5
    """A component's share of white (petal) pixels, at least this: yellow alone is a bud or
    a stem, not a flower."""
    onnx: OnnxConfig = field(default_factory=OnnxConfig)

    def __post_init__(self):
        require(self.detector == "colour" or _onnx_model(self.detector) is not None
                or _plugin_name(self.detector) is not None, "detect.detector",
                'must be "colour", onnx:MODEL.onnx or MODULE:CLASS')
        require(0 <= self.min_white_fraction <= 1, "detect.min_white_fraction",
                "must be within 0-1")
        require(self.close_radius_px >= 0, "detect.close_radius_px", "must be 0 or more")
        require(0 < self.min_area_m2 < self.max_area_m2, "detect.min_area_m2",
                "needs 0 < detect.min_area_m2 < detect.max_area_m2")


@dataclass(frozen=True)
class Detection:
    """One flower found in one image."""

    box: tuple[int, int, int, int]
    """(x0, y0, x1, y1) pixel box, end exclusive."""
    mask: np.ndarray
    """(y1 - y0, x1 - x0) bool: the detection's pixels inside its box."""
    score: float
    """Confidence in [0, 1]; the colour detector gives the component's white share."""


class Detector(Protocol):
    """Finds flowers in one projected image."""

    def __call__(self, image: np.ndarray, occupied: np.ndarray,
                 pixel_size_m: float) -> list[Detection]:
        """image: (H, W, 3) uint8 RGB; occupied: (H, W) bool, pixels that hold a point;
        pixel_size_m: metres per pixel (for physical size limits)."""
        ...


class ColourDetector:
    """White petals and yellow centres grouped into connected components."""

    def __init__(self, config: DetectConfig, colour: ColourConfig):
        self.config = config
        self.colour = colour

    def __call__(self, image: np.ndarray, occupied: np.ndarray,
                 pixel_size_m: float) -> list[Detection]:
        cfg = self.config
        hsv = rgb_to_hsv(image)
        white = occupied & petal_mask(hsv, self.colour)
        yellow = occupied & pistil_mask(hsv, self.colour)
        flower = (white | yellow).astype(np.uint8)
        if cfg.close_radius_px > 0:
            size = 2 * cfg.close_radius_px + 1
            kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
            flower = cv2.morphologyEx(flower, cv2.MORPH_CLOSE, kernel) & occupied
        return components(flower.astype(bool), white, pixel_size_m, cfg, cfg.min_white_fraction)


def components(mask: np.ndarray, weights: np.ndarray, pixel_size_m: float,
               config: DetectConfig, min_score: float = 0.0) -> list[Detection]:
    """The 8-connected components of `mask` within the config's area limits, each a
    Detection scored by the mean of `weights` over it; those scoring below `min_score`
    are left out.

    mask: (H, W) bool; weights: (H, W) float or bool in 0-1; pixel_size_m: metres per
    pixel (the limits are in square metres)."""
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8),
                                                                connectivity=8)
    if count <= 1:
        return []
    area = stats[:, cv2.CC_STAT_AREA].astype(np.float64)
    score = np.bincount(labels.ravel(), weights=np.asarray(weights, np.float64).ravel(),
                        minlength=count) / np.maximum(area, 1)
    pixel_area = pixel_size_m**2
    keep = ((area * pixel_area >= config.min_area_m2)
            & (area * pixel_area <= config.max_area_m2) & (score >= min_score))
    keep[0] = False
    detections = []
    for label in np.flatnonzero(keep):
        x, y, w, h = stats[label, :4]
        detections.append(Detection((int(x), int(y), int(x + w), int(y + h)),
                                    labels[y:y + h, x:x + w] == label, float(score[label])))
    return detections


def make_detector(config: DetectConfig, colour: ColourConfig) -> Detector:
    """The detector the config names; `colour` is the colour model the built-in one reads.
    An ONNX model is loaded here (`OnnxDetector`); a plug-in (MODULE:CLASS) is imported and
    made here, and its detections are checked as they come (`_Checked`), so a wrong one is
    one clear line naming it."""
    if config.detector == "colour":
        return ColourDetector(config, colour)
    model = _onnx_model(config.detector)
    if model is not None:
        from flowerpose.pipeline.onnx_detector import OnnxDetector

        return OnnxDetector(model, config)
    module_name, class_name = _plugin_name(config.detector)
    try:
        factory = getattr(importlib.import_module(module_name), class_name)
        return _Checked(factory(), config.detector)
    except (ImportError, AttributeError) as err:
        raise InputError("detect.detector", f"{config.detector}: cannot load it ({err})") from None
    except Exception as err:  # noqa: BLE001 - the plug-in's own failure, said in one line
        raise InputError("detect.detector", f"{config.detector}: making it failed "
                         f"({type(err).__name__}: {err})") from None


def _onnx_model(name: str) -> Path | None:
    """The model file of an "onnx:MODEL.onnx" detector name (the prefix is the ONNX
    detector's, whatever follows), or None for another name."""
    model = name.removeprefix(ONNX_PREFIX)
    return Path(model) if name.startswith(ONNX_PREFIX) and model else None


def _plugin_name(name: str) -> tuple[str, str] | None:
    module, sep, cls = name.partition(":")
    valid = sep and all(part.isidentifier() for part in module.split(".")) and cls.isidentifier()
    return (module, cls) if valid else None


class _Checked:
    """A plug-in detector whose output is checked: a list of Detection, boxes inside the
    image, masks the size of their boxes."""

    def __init__(self, detector: Detector, name: str):
        self.detector, self.name = detector, name

    def __call__(self, image: np.ndarray, occupied: np.ndarray,
                 pixel_size_m: float) -> list[Detection]:
        try:
            found = self.detector(image, occupied, pixel_size_m)
        except Exception as err:  # noqa: BLE001 - the plug-in's own failure, in one line
            raise InputError("detect.detector", f"{self.name} failed on a view "
                             f"({type(err).__name__}: {err})") from None
        height, width = image.shape[:2]
        for k, det in enumerate(found if isinstance(found, list) else [None]):
            box = getattr(det, "box", None)
            mask = np.asarray(getattr(det, "mask", None))
            ok = (isinstance(det, Detection) and len(box) == 4
                  and 0 <= box[0] < box[2] <= width and 0 <= box[1] < box[3] <= height
                  and mask.shape == (box[3] - box[1], box[2] - box[0]))
            if not ok:
                raise InputError("detect.detector", f"{self.name} returned a bad detection "
                                 f"({k}): expected a list of Detection(box=(x0, y0, x1, y1) "
                                 "inside the image, mask of the box's shape, score)")
        return found


def backproject(detections: list[Detection], index: np.ndarray,
                mode: Literal["mask", "box"]) -> list[np.ndarray]:
    """Cloud indices under each detection.

    index: (H, W) int32 pixel-to-point map of the projection (-1 where empty). Returns one
    sorted unique int array per detection.
    """
    out = []
    for det in detections:
        x0, y0, x1, y1 = det.box
        window = index[y0:y1, x0:x1]
        picked = window[det.mask] if mode == "mask" else window.ravel()
        out.append(np.unique(picked[picked >= 0]))
    return out
