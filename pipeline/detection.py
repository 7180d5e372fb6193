"""What a 2D detector returns, and the step every mask-based detector shares.

`Detection` is one flower found in one projected view (a pixel box, its mask, a score);
`components` turns a view's (H, W) pixel mask into detections within the `detect` stage's
area limits (square metres, through the view's metres per pixel). The colour detector
(`detect.py`) and the built-in ONNX detector (`onnx_detector.py`) both use them, and a
plug-in detector returns `Detection`s.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class Detection:
    """One flower found in one image."""

    box: tuple[int, int, int, int]
    """(x0, y0, x1, y1) pixel box, end exclusive."""
    mask: np.ndarray
    """(y1 - y0, x1 - x0) bool: the detection's pixels inside its box."""
    score: float
    """Confidence in [0, 1]; the colour detector gives the component's white share."""


def components(mask: np.ndarray, weights: np.ndarray, pixel_size_m: float,
               area_m2: tuple[float, float], min_score: float = 0.0) -> list[Detection]:
    """The 8-connected components of `mask` whose area lies within `area_m2` (smallest,
    largest: `detect.min_area_m2`, `detect.max_area_m2`), each a Detection scored by the
    mean of `weights` over it; those scoring below `min_score` are left out.

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
    min_area_m2, max_area_m2 = area_m2
    keep = ((area * pixel_area >= min_area_m2)
            & (area * pixel_area <= max_area_m2) & (score >= min_score))
    keep[0] = False
    detections = []
    for label in np.flatnonzero(keep):
        x, y, w, h = stats[label, :4]
        detections.append(Detection((int(x), int(y), int(x + w), int(y + h)),
                                    labels[y:y + h, x:x + w] == label, float(score[label])))
    return detections
