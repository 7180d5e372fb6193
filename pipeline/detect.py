"""2D flower detection on the projected images: a `Detector` interface and a weight-free default.

The paper fine-tuned YOLOv10 through a hosted API whose weights were never published; the
default here needs no weights: white petal pixels around a yellow centre, grouped into
connected components, each giving a box and a mask. A user's exported model runs through
the built-in ONNX detector (`onnx:MODEL.onnx`, `pipeline/onnx_detector.py`), and any other
detector (a local YOLO, say) plugs in by implementing `Detector`. What a detector returns,
`Detection`, is in `pipeline/detection.py`.
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
from flowerpose.pipeline.detection import Detection, components
from flowerpose.pipeline.onnx_detector import OnnxConfig, OnnxDetector

#: The `detect.detector` prefix of the built-in ONNX detector: "onnx:MODEL.onnx".
ONNX_PREFIX = "onnx:"


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
        return components(flower.astype(bool), white, pixel_size_m,
                          (cfg.min_area_m2, cfg.max_area_m2), cfg.min_white_fraction)


def make_detector(config: DetectConfig, colour: ColourConfig) -> Detector:
    """The detector the config names; `colour` is the colour model the built-in one reads.
    An ONNX model is loaded here (`OnnxDetector`); a plug-in (MODULE:CLASS) is imported and
    made here, and its detections are checked as they come (`_Checked`), so a wrong one is
    one clear line naming it."""
    if config.detector == "colour":
        return ColourDetector(config, colour)
    model = _onnx_model(config.detector)
    if model is not None:
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
