"""A plant's oracle cloud degraded like a field scan: thinned to a density, exposed, cast and
jittered, each drawn per plant from the ranges `DegradeConfig` gives (seeded by the plant).

The perturbations are the stress report's (`flowerpose/perturb.py`), so a preset's
degradation and a stress level mean the same thing. Density is said as the pipeline's
envelope says it: points a flower, here the median over the plant's visible flowers of
the cloud points sampled on them (petals, receptacle, stamens, sepals).
"""

from __future__ import annotations

import math

import numpy as np

from flowerpose.cloudio import Cloud
from flowerpose.perturb import CHANNELS, channel_gain, jitter, relit
from flowerpose.sim.world_config import DegradeConfig


def points_per_flower(point_flower: np.ndarray, visible: np.ndarray) -> float | None:
    """The median points of the visible flowers (None: none visible or none sampled)."""
    counts = np.bincount(point_flower[point_flower >= 0], minlength=len(visible))
    counts = counts[: len(visible)][np.asarray(visible, bool)]
    counts = counts[counts > 0]
    return float(np.median(counts)) if len(counts) else None


def degrade(cloud: Cloud, point_part: np.ndarray, point_flower: np.ndarray,
            visible: np.ndarray, config: DegradeConfig, rng: np.random.Generator
            ) -> tuple[Cloud, np.ndarray, np.ndarray, dict]:
    """The cloud (and its per-point labels) under one draw of `config`, and the draw: the
    points a flower it was thinned to (None: not thinned), the exposure, the cast's
    channel and change, and the noise (metres); nothing for the default (no degradation)."""
    drawn: dict = {}
    if config == DegradeConfig():
        return cloud, point_part, point_flower, drawn
    if config.points_per_flower is not None:
        low, high = config.points_per_flower
        target = float(math.exp(rng.uniform(math.log(low), math.log(high))))
        current = points_per_flower(point_flower, visible)
        drawn["points_per_flower"] = round(target, 1)
        if current is not None and target < current:
            keep = np.sort(rng.choice(len(cloud), max(1, round(len(cloud) * target / current)),
                                      replace=False))
            cloud = cloud.subset(keep)
            point_part, point_flower = point_part[keep], point_flower[keep]
    exposure = float(rng.uniform(*config.exposure))
    channel = CHANNELS[int(rng.integers(3))] if config.cast > 0 else ""
    cast = float(rng.uniform(-config.cast, config.cast)) if config.cast > 0 else 0.0
    if exposure != 1.0 or cast != 0.0:
        cloud = relit(cloud, channel_gain(exposure, channel, cast))
    noise = float(rng.uniform(*config.noise_m))
    if noise > 0:
        cloud = jitter(cloud, noise, rng)
    drawn.update(exposure=round(exposure, 4), cast={"channel": channel, "change": round(cast, 4)},
                 noise_m=round(noise, 6))
    return cloud, point_part, point_flower, drawn
