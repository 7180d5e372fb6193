"""Colour conversions, vectorised over points or pixels."""

from __future__ import annotations

import cv2
import numpy as np


def rgb_to_hsv(rgb: np.ndarray) -> np.ndarray:
    """HSV of uint8 RGB colours.

    rgb: (..., 3) uint8. Returns (..., 3) float32: hue in degrees [0, 360), saturation
    and value in [0, 1] (the units upstream.md uses for every threshold).
    """
    rgb = np.asarray(rgb)
    if rgb.size == 0:
        return np.zeros(rgb.shape, np.float32)
    # OpenCV's float conversion: the same definition as colorsys, ~30x faster than NumPy.
    flat = rgb.reshape(-1, 1, 3).astype(np.float32) * np.float32(1 / 255)
    return cv2.cvtColor(flat, cv2.COLOR_RGB2HSV).reshape(rgb.shape)
