"""Camera positions of the paper's FarmBot scan path: a cylinder, then a dome over the plant."""

from __future__ import annotations

import numpy as np

from flowerpose.sim.config import ViewpointConfig


def scan_viewpoints(center_xy: np.ndarray, plant_height_m: float,
                    config: ViewpointConfig) -> np.ndarray:
    """(V, 3) float64 camera positions, metres, bed frame, in scan order.

    center_xy: (2,) plant axis on the bed, metres. Cylinder rings (radius
    `cylinder_radius_m`) from `cylinder_z_min_m` up in `cylinder_z_step_m` steps to at most
    `plant_height_m + cylinder_top_margin_m`, one camera every `cylinder_azimuth_step_deg`;
    then dome rings at `dome_polar_deg` from the vertical, radius `dome_radius_m`, centred
    on the axis at the plant height ("top") or half of it ("half"). Every camera aims at the
    plant axis; visibility uses positions only.
    """
    cx, cy = (float(v) for v in center_xy)
    top = plant_height_m + config.cylinder_top_margin_m
    heights = np.arange(config.cylinder_z_min_m, top + 1e-9, config.cylinder_z_step_m)
    azimuth = np.radians(np.arange(0.0, 360.0 - 1e-9, config.cylinder_azimuth_step_deg))
    z, a = np.meshgrid(heights, azimuth, indexing="ij")
    cylinder = np.stack([cx + config.cylinder_radius_m * np.cos(a).ravel(),
                         cy + config.cylinder_radius_m * np.sin(a).ravel(), z.ravel()], 1)

    dome_z = plant_height_m if config.dome_center == "top" else 0.5 * plant_height_m
    polar = np.radians(np.asarray(config.dome_polar_deg, np.float64))
    azimuth = np.radians(np.arange(0.0, 360.0 - 1e-9, config.dome_azimuth_step_deg))
    p, a = np.meshgrid(polar, azimuth, indexing="ij")
    r = config.dome_radius_m
    dome = np.stack([cx + r * (np.sin(p) * np.cos(a)).ravel(),
                     cy + r * (np.sin(p) * np.sin(a)).ravel(),
                     dome_z + r * np.cos(p).ravel()], 1)
    return np.concatenate([cylinder, dome])
