"""The colour model: which point and pixel colours are petal, pistil and support.

One model for every stage: detection (white petal pixels around a yellow centre), the
flower test on clusters, and the per-flower petal / pistil split of the pose stage all
read the same `ColourConfig`. HSV with hue in degrees [0, 360) and saturation and value
in [0, 1], the units the published method states its thresholds in (docs/deviations.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from flowerpose.config import require
from flowerpose.srgb import relight, srgb_to_linear


def rgb_to_hsv(rgb: np.ndarray) -> np.ndarray:
    """HSV of uint8 RGB colours.

    rgb: (..., 3) uint8. Returns (..., 3) float32: hue in degrees [0, 360), saturation
    and value in [0, 1] (the published method's units).
    """
    rgb = np.asarray(rgb)
    if rgb.size == 0:
        return np.zeros(rgb.shape, np.float32)
    # OpenCV's float conversion: the same definition as colorsys, ~30x faster than NumPy.
    flat = rgb.reshape(-1, 1, 3).astype(np.float32) * np.float32(1 / 255)
    return cv2.cvtColor(flat, cv2.COLOR_RGB2HSV).reshape(rgb.shape)


@dataclass(frozen=True)
class ColourConfig:
    """Colour bands of petals (white), pistils (yellow) and support (green sepals, stems)."""

    petal_max_saturation: float = 0.39
    """Petal: saturation at most this (upstream's whitish threshold of the flower filter)."""
    petal_min_value: float = 0.40
    """Petal: value at least this. Deviation: upstream's 0.75 suits petals in full light
    only; in images of a scan most of a petal is seen from its shaded side or edge-on (value
    0.4-0.7), so photogrammetry clouds were missing half their flowers
    (docs/deviations.md, "Colour thresholds"). Saturation separates white from green and
    brown."""
    petal_reject_hue: tuple[float, float] = (40.0, 140.0)
    """Petal: a point in this hue band (degrees: yellow to green) is no petal once its
    saturation reaches `petal_reject_saturation` (upstream's petal rule)."""
    petal_reject_saturation: float = 0.15
    """Saturation from which a point in `petal_reject_hue` is no petal."""
    pistil_hue: tuple[float, float] = (40.0, 60.0)
    """Pistil (yellow receptacle and anthers): hue band, degrees. Upstream: 40-63 (its
    detector's "yellow" too); shaded yellow-green sepals reach down to 60 and, once darker
    pistil points count (`pistil_min_value`), pulled a pistil below its petals and flipped
    a normal. Detection used 63 and pose 60 until both read this one band."""
    pistil_min_saturation: float = 0.30
    """Pistil: saturation at least this (upstream)."""
    pistil_min_value: float = 0.30
    """Pistil: value at least this (upstream 0.65, which drops a receptacle in shade)."""
    support_hue: tuple[float, float] = (40.0, 180.0)
    """Support (sepals and peduncle behind a flower): hue band, degrees."""
    support_min_saturation: float = 0.15
    """Support: saturation at least this."""
    white_balance: bool = True
    """Neutralise a colour cast before any colour test (`white_gain`): the brightest
    unclipped points of petal colour (petals are white in any light) are made grey by a
    gain per channel on linear light, applied to every point. A camera's white balance or
    a photogrammetry texture moves every hue: 15 % more red or less green turns
    yellow-green sepals pistil-yellow and pale leaves petal-white (`flowerpose stress`).
    Deviation: upstream took the colours as they came."""

    def __post_init__(self):
        for name in ("petal_max_saturation", "petal_min_value", "petal_reject_saturation",
                     "pistil_min_saturation", "pistil_min_value", "support_min_saturation"):
            require(0 <= getattr(self, name) <= 1, f"colour.{name}", "must be within 0-1")
        for name in ("petal_reject_hue", "pistil_hue", "support_hue"):
            low, high = getattr(self, name)
            require(0 <= low <= high <= 360, f"colour.{name}", "must be (low, high) degrees")


#: The white reference: this share of the unclipped petal-coloured points, brightest first.
WHITE_REFERENCE_SHARE = 0.2
#: Fewest unclipped petal-coloured points that measure a cast; with fewer, none is removed.
MIN_WHITE_POINTS = 50
#: A channel at this 8-bit level is clipped, so its ratio says nothing of a cast.
CLIPPED_LEVEL = 255
#: Most colours a cast is measured on (an even subsample).
WHITE_SAMPLE = 100_000
#: Largest gain on any channel: a stronger "cast" is not one, but a cloud without white.
MAX_WHITE_GAIN = 1.5


def white_gain(colors: np.ndarray, config: ColourConfig) -> np.ndarray:
    """(3,) the gain per channel on linear light that makes the cloud's white reference
    grey, keeping its mean: the median linear colour of the brightest WHITE_REFERENCE_SHARE
    of its unclipped petal-coloured points. Ones when white balance is off or too few such
    points measure it. colors: (N, 3) uint8 sRGB."""
    colors = np.asarray(colors, np.uint8).reshape(-1, 3)
    if not config.white_balance or len(colors) == 0:
        return np.ones(3)
    colors = colors[::max(1, len(colors) // WHITE_SAMPLE)]
    hsv = rgb_to_hsv(colors)
    white = petal_mask(hsv, config) & (colors.max(axis=1) < CLIPPED_LEVEL)
    if white.sum() < MIN_WHITE_POINTS:
        return np.ones(3)
    value = hsv[white, 2]
    bright = value >= np.quantile(value, 1.0 - WHITE_REFERENCE_SHARE)
    reference = np.median(srgb_to_linear(colors[white][bright] / 255.0), axis=0)
    if not (reference > 0).all():
        return np.ones(3)
    return np.clip(reference.mean() / reference, 1 / MAX_WHITE_GAIN, MAX_WHITE_GAIN)


def white_balanced(colors: np.ndarray, config: ColourConfig) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) uint8 colours with the cloud's cast removed, and the gain that removed it
    (`white_gain`; colours as they were where it is one)."""
    gain = white_gain(colors, config)
    colors = np.asarray(colors, np.uint8)
    return (colors if np.allclose(gain, 1.0) else relight(colors, gain)), gain


def _in_band(values: np.ndarray, band: tuple[float, float]) -> np.ndarray:
    return (values >= band[0]) & (values <= band[1])


def petal_mask(hsv: np.ndarray, config: ColourConfig) -> np.ndarray:
    """(...,) bool: HSV colours (..., 3) in the petal band."""
    hue, sat, val = hsv[..., 0], hsv[..., 1], hsv[..., 2]
    return ((sat <= config.petal_max_saturation) & (val >= config.petal_min_value)
            & ~(_in_band(hue, config.petal_reject_hue) & (sat >= config.petal_reject_saturation)))


def pistil_mask(hsv: np.ndarray, config: ColourConfig) -> np.ndarray:
    """(...,) bool: HSV colours (..., 3) in the pistil band."""
    return (_in_band(hsv[..., 0], config.pistil_hue) & (hsv[..., 1] >= config.pistil_min_saturation)
            & (hsv[..., 2] >= config.pistil_min_value))


def support_mask(hsv: np.ndarray, config: ColourConfig) -> np.ndarray:
    """(...,) bool: HSV colours (..., 3) in the support band (petals excluded by the caller)."""
    return (_in_band(hsv[..., 0], config.support_hue)
            & (hsv[..., 1] >= config.support_min_saturation))


def sepal_mask(hsv: np.ndarray, config: ColourConfig) -> np.ndarray:
    """(...,) bool: HSV colours (..., 3) in the support band and neither a petal's nor a
    pistil's: a sepal, stem or leaf point, never part of a corolla."""
    return support_mask(hsv, config) & ~petal_mask(hsv, config) & ~pistil_mask(hsv, config)


def flower_coloured(rgb: np.ndarray, config: ColourConfig | None = None) -> np.ndarray:
    """(N,) bool: RGB colours (N, 3) uint8 of a cloud that are a petal's or a pistil's, its
    cast removed first as the detector removes it (`white_balanced`): a pollination
    visit's target corolla may be only these."""
    config = config or ColourConfig()
    hsv = rgb_to_hsv(white_balanced(rgb, config)[0])
    return petal_mask(hsv, config) | pistil_mask(hsv, config)
