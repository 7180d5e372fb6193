"""sRGB colours and linear light: the transfer function, and gains on linear light.

8-bit colours in clouds and images are sRGB-encoded; a camera's exposure and white balance
act on linear light, so a change of either is a gain applied between decoding and
encoding (`relight`). The simulator's renderer, the pipeline's white balance and the
stress report's perturbations all use these.
"""

from __future__ import annotations

import numpy as np


def srgb_to_linear(rgb: np.ndarray) -> np.ndarray:
    """Linear light of sRGB values in [0, 1] (any shape)."""
    rgb = np.asarray(rgb, np.float64)
    return np.where(rgb <= 0.04045, rgb / 12.92, ((rgb + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    """sRGB values in [0, 1] of linear light (any shape), clipped (over-exposure)."""
    c = np.clip(linear, 0.0, 1.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)


def relight(colors: np.ndarray, gain: np.ndarray) -> np.ndarray:
    """(..., 3) uint8 sRGB colours with each channel's linear light multiplied by gain (3,),
    clipped at white. A lookup table per channel: 256 values, whatever the count."""
    levels = srgb_to_linear(np.arange(256) / 255.0)
    tables = np.clip(np.rint(linear_to_srgb(levels[:, None] * np.asarray(gain, np.float64))
                             * 255.0), 0, 255).astype(np.uint8)
    colors = np.asarray(colors, np.uint8)
    return np.stack([tables[colors[..., c], c] for c in range(3)], axis=-1)
