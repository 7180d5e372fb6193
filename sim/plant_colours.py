"""Plant colours in HSV, chosen to sit where the pipeline's thresholds expect them.

Hue in degrees, saturation and value in [0, 1], the colour model's units. Petals are white
(S <= 0.12, V >= 0.86), the receptacle and anthers yellow (H 48-58, S >= 0.6), leaves
green (H 85-130, S 0.5-0.85, V 0.27-0.62, never whitish), peduncles yellow-green (H 62-86,
so a few points fall in the pistil hue range as on real stems). Limits hold per vertex,
before the oracle cloud's shading and jitter.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Tone:
    """A colour family: one base colour per object, jittered per vertex, clipped to limits."""

    hue: tuple[float, float]
    """Range of the object's base hue, degrees (may start below 0 for reds)."""
    sat: tuple[float, float]
    """Range of the base saturation."""
    val: tuple[float, float]
    """Range of the base value."""
    jitter: tuple[float, float, float]
    """Per-vertex standard deviation of hue (degrees), saturation and value."""
    hue_limits: tuple[float, float]
    """Hue is clipped to this range, degrees."""
    sat_limits: tuple[float, float]
    """Saturation is clipped to this range."""
    val_limits: tuple[float, float]
    """Value is clipped to this range."""


PETAL_CREAM = Tone((42, 58), (0.02, 0.07), (0.93, 0.99), (2, 0.015, 0.02),
                   (30, 65), (0.0, 0.12), (0.86, 1.0))
PETAL_PINK = Tone((330, 350), (0.02, 0.07), (0.93, 0.99), (3, 0.015, 0.02),
                  (320, 358), (0.0, 0.12), (0.86, 1.0))
RECEPTACLE = Tone((50, 56), (0.75, 0.88), (0.88, 0.97), (1.5, 0.04, 0.03),
                  (48, 58), (0.6, 0.95), (0.82, 1.0))
ANTHER = Tone((49, 55), (0.8, 0.92), (0.9, 0.98), (1.5, 0.03, 0.03),
              (48, 58), (0.65, 0.98), (0.82, 1.0))
FILAMENT = Tone((52, 58), (0.5, 0.6), (0.9, 0.97), (1.5, 0.03, 0.02),
                (48, 60), (0.45, 0.7), (0.85, 1.0))
LEAF = Tone((95, 118), (0.58, 0.8), (0.3, 0.5), (3, 0.04, 0.04),
            (85, 130), (0.5, 0.85), (0.27, 0.62))
PETIOLE = Tone((80, 100), (0.5, 0.68), (0.35, 0.55), (3, 0.04, 0.04),
               (70, 110), (0.45, 0.8), (0.27, 0.62))
PEDUNCLE = Tone((68, 80), (0.5, 0.65), (0.5, 0.66), (3, 0.04, 0.04),
                (62, 86), (0.4, 0.75), (0.4, 0.72))
SEPAL = Tone((95, 112), (0.55, 0.72), (0.38, 0.55), (3, 0.04, 0.04),
             (85, 125), (0.45, 0.85), (0.3, 0.62))
BUD = Tone((85, 105), (0.5, 0.65), (0.45, 0.6), (3, 0.04, 0.04),
           (80, 115), (0.45, 0.8), (0.35, 0.66))
FRUIT_RED = Tone((-6, 6), (0.75, 0.88), (0.6, 0.82), (3, 0.04, 0.05),
                 (-14, 14), (0.6, 0.95), (0.45, 0.9))
FRUIT_GREEN = Tone((72, 90), (0.45, 0.58), (0.55, 0.7), (3, 0.04, 0.04),
                   (66, 98), (0.4, 0.7), (0.45, 0.74))
SOIL = Tone((22, 32), (0.4, 0.55), (0.22, 0.32), (3, 0.05, 0.04),
            (14, 40), (0.25, 0.7), (0.1, 0.45))
CROWN = Tone((18, 30), (0.5, 0.65), (0.25, 0.35), (3, 0.04, 0.03),
              (10, 40), (0.4, 0.75), (0.15, 0.45))


def hsv_to_rgb(hsv: np.ndarray) -> np.ndarray:
    """RGB in [0, 1] of HSV colours.

    hsv: (..., 3) float: hue in degrees (any real, taken modulo 360), saturation and
    value in [0, 1]. Returns (..., 3) float64.
    """
    hsv = np.asarray(hsv, dtype=np.float64)
    h = np.mod(hsv[..., 0], 360.0) / 60.0
    s, v = hsv[..., 1], hsv[..., 2]
    chroma = v * s
    x = chroma * (1.0 - np.abs(np.mod(h, 2.0) - 1.0))
    zero = np.zeros_like(h)
    sector = np.floor(h).astype(int) % 6
    choices = [
        np.stack([chroma, x, zero], -1), np.stack([x, chroma, zero], -1),
        np.stack([zero, chroma, x], -1), np.stack([zero, x, chroma], -1),
        np.stack([x, zero, chroma], -1), np.stack([chroma, zero, x], -1),
    ]
    rgb = np.choose(sector[..., None], choices)
    return rgb + (v - chroma)[..., None]


def rgba8(rgb: np.ndarray) -> np.ndarray:
    """(N, 4) uint8 opaque RGBA of (N, 3) float RGB in [0, 1]."""
    out = np.full((len(rgb), 4), 255, dtype=np.uint8)
    out[:, :3] = np.clip(np.rint(np.asarray(rgb) * 255.0), 0, 255).astype(np.uint8)
    return out


def tone_colors(rng: np.random.Generator, tone: Tone, n: int,
                shift: np.ndarray | None = None) -> np.ndarray:
    """(n, 4) uint8 RGBA vertex colours of one object of `tone`.

    shift: optional (n, 3) HSV offsets per vertex (degrees, -, -) for spatial patterns
    such as a lighter midrib or darker soil patches, added before clipping.
    """
    base = np.array([rng.uniform(*tone.hue), rng.uniform(*tone.sat), rng.uniform(*tone.val)])
    hsv = base + rng.normal(size=(n, 3)) * np.asarray(tone.jitter)
    if shift is not None:
        hsv = hsv + shift
    lo = np.array([tone.hue_limits[0], tone.sat_limits[0], tone.val_limits[0]])
    hi = np.array([tone.hue_limits[1], tone.sat_limits[1], tone.val_limits[1]])
    return rgba8(hsv_to_rgb(np.clip(hsv, lo, hi)))
