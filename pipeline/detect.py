"""2D flower detection on the projected images: a `Detector` interface and a weight-free default.

The paper fine-tuned YOLOv10 through a hosted API whose weights were never published; the
default here needs no weights: white petal pixels around a yellow centre, grouped into
connected components, each giving a box and a mask. Any other detector (a local YOLO, say)
plugs in by implementing `Detector`.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Literal, Protocol

import cv2
import numpy as np

from flowerpose.config import require
from flowerpose.errors import InputError
from flowerpose.pipeline.colour import ColourConfig, petal_mask, pistil_mask, rgb_to_hsv


@dataclass(frozen=True)
class DetectConfig:
    """Which detector runs and how its detections return to 3D."""

    detector: str = "colour"
    """The detector: "colour" (white petals around a yellow centre; needs no weights), or
    "MODULE:CLASS", any importable class with the `Detector` interface (made with no
    arguments, called once per view), e.g. a YOLO model wrapped in a few lines."""
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

    def __post_init__(self):
        require(self.detector == "colour" or _plugin_name(self.detector) is not None,
                "detect.detector", 'must be "colour" or MODULE:CLASS')
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
        count, labels, stats, _ = cv2.connectedComponentsWithStats(flower, connectivity=8)
        if count <= 1:
            return []
        white_per_label = np.bincount(labels.ravel(), weights=white.ravel(), minlength=count)
        area = stats[:, cv2.CC_STAT_AREA].astype(np.float64)
        pixel_area = pixel_size_m**2
        share = white_per_label / np.maximum(area, 1)
        keep = ((area * pixel_area >= cfg.min_area_m2) & (area * pixel_area <= cfg.max_area_m2)
                & (share >= cfg.min_white_fraction))
        keep[0] = False
        detections = []
        for label in np.flatnonzero(keep):
            x, y, w, h = stats[label, :4]
            mask = labels[y:y + h, x:x + w] == label
            detections.append(Detection((int(x), int(y), int(x + w), int(y + h)), mask,
                                        float(share[label])))
        return detections


def make_detector(config: DetectConfig, colour: ColourConfig) -> Detector:
    """The detector the config names; `colour` is the colour model the built-in one reads.
    A plug-in (MODULE:CLASS) is imported and made here; its detections are checked as
    they come (`_Checked`), so a wrong one is one clear line naming it."""
    if config.detector == "colour":
        return ColourDetector(config, colour)
    module_name, class_name = _plugin_name(config.detector)
    try:
        factory = getattr(importlib.import_module(module_name), class_name)
        return _Checked(factory(), config.detector)
    except (ImportError, AttributeError) as err:
        raise InputError("detect.detector", f"{config.detector}: cannot load it ({err})") from None
    except Exception as err:  # noqa: BLE001 - the plug-in's own failure, said in one line
        raise InputError("detect.detector", f"{config.detector}: making it failed "
                         f"({type(err).__name__}: {err})") from None


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
