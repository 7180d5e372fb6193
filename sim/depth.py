"""The depth camera's imperfections: what an active-stereo RGB-D sensor makes of a rendered
depth image. Deterministic from its random generator.

Modelled on close-range active stereo (an Intel RealSense D4xx with its depth aligned to the
colour image): the depth error grows with the square of the distance (stereo disparity
error), depth comes in 1 mm units, pixels at depth jumps turn into "flying pixels" between
the surfaces or drop out, and a few pixels drop out at random.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class DepthSensorConfig:
    """Depth noise of the simulated RGB-D camera (metres unless noted)."""

    sigma_at_1m_m: float = 0.002
    """Depth standard deviation at 1 m; it scales with depth squared (0.5 mm at 0.5 m,
    about a D405/D435's RMS error at that range)."""
    unit_m: float = 0.001
    """Depth quantisation step (the sensor's depth unit)."""
    min_m: float = 0.07
    """Nearest depth measured; nearer surfaces read as no depth."""
    max_m: float = 2.0
    """Farthest depth measured."""
    edge_jump_m: float = 0.01
    """A pixel whose neighbours differ in depth by more than this sits on an edge."""
    edge_flying_share: float = 0.5
    """Share of edge pixels that become flying pixels (depth between the two surfaces);
    the rest read as no depth."""
    dropout_share: float = 0.02
    """Share of the other pixels with no depth (speckle in the projector pattern)."""


def apply_depth_sensor(depth: np.ndarray, config: DepthSensorConfig,
                       rng: np.random.Generator) -> np.ndarray:
    """The depth image the sensor reports for a clean render.

    depth: (H, W) float32 metres along the optical axis, 0 where nothing is seen. Returns
    (H, W) float32 metres, 0 for no measurement.
    """
    clean = np.asarray(depth, np.float32)
    valid = clean > 0
    kernel = np.ones((3, 3), np.uint8)
    far = cv2.dilate(np.where(valid, clean, 0).astype(np.float32), kernel)
    near = -cv2.dilate(np.where(valid, -clean, -np.inf).astype(np.float32), kernel)
    near = np.where(np.isfinite(near), near, clean)  # no valid neighbour: no jump either
    edge = valid & ((far - near) > config.edge_jump_m)
    out = clean + (config.sigma_at_1m_m * clean**2 * rng.standard_normal(clean.shape)).astype(
        np.float32)
    flying = edge & (rng.random(clean.shape) < config.edge_flying_share)
    blend = rng.random(clean.shape).astype(np.float32)
    out = np.where(flying, near + blend * (far - near), out)
    drop = (edge & ~flying) | (~edge & (rng.random(clean.shape) < config.dropout_share))
    out = np.round(out / config.unit_m) * config.unit_m
    keep = valid & ~drop & (out >= config.min_m) & (out <= config.max_m)
    return np.where(keep, out, 0.0).astype(np.float32)
