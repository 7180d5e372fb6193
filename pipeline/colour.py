"""Colour conversions, vectorised over points or pixels."""

from __future__ import annotations

import numpy as np


def rgb_to_hsv(rgb: np.ndarray) -> np.ndarray:
    """HSV of uint8 RGB colours.

    rgb: (..., 3) uint8. Returns (..., 3) float64: hue in degrees [0, 360), saturation
    and value in [0, 1] (the units upstream.md uses for every threshold).
    """
    c = np.asarray(rgb, dtype=np.float64) / 255.0
    r, g, b = c[..., 0], c[..., 1], c[..., 2]
    v = c.max(axis=-1)
    chroma = v - c.min(axis=-1)
    s = np.divide(chroma, v, out=np.zeros_like(v), where=v > 0)
    safe = np.where(chroma > 0, chroma, 1.0)
    h = np.where(
        v == r,
        ((g - b) / safe) % 6.0,
        np.where(v == g, (b - r) / safe + 2.0, (r - g) / safe + 4.0),
    )
    h = np.where(chroma > 0, h * 60.0, 0.0)
    return np.stack([h, s, v], axis=-1)
