"""The paper's cylinder + dome scan path as geometry: where the camera stops and what it
looks at. One definition shared by the bot's planner (`flowerpose.hardware.flights.scan_plan`) and
the simulator's visibility truth, so both use the path the bot flies."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from flowerpose.errors import InputError


@dataclass(frozen=True)
class ScanPathConfig:
    """The cylinder + dome scan path (docs/guides/simulated-farmbot.md, "Filming a
    plant"), in metres and degrees."""

    cylinder_radius_m: float = 0.5
    """Distance of the cylinder's cameras from the plant axis (the paper: 500 mm)."""
    cylinder_bottom_m: float = 0.16
    """Height of the lowest ring above the soil. The paper's bot, with its Z travel, takes a
    level camera no lower than about 0.158 m (hardware/geometry.py)."""
    cylinder_top_margin_m: float = 0.0
    """The highest ring sits at most this far above the plant's top."""
    cylinder_step_m: float = 0.02
    """Height between rings (the paper: 20 mm)."""
    azimuth_step_deg: float = 20.0
    """Angle between neighbouring views on a ring (the paper: 20 degrees)."""
    dome_radius_m: float = 0.3
    """Radius of the dome (the paper: 300 mm)."""
    dome_center: Literal["half", "top"] = "half"
    """The dome's centre on the plant axis: at half the plant's height (default) or at its
    top. The paper does not say; over a 0.3 m plant a dome centred on its top puts the
    highest views beyond the paper's Z travel."""
    dome_polar_deg: tuple[float, ...] = (70.0, 50.0, 30.0, 10.0)
    """Polar angles of the dome's rings from the vertical, lowest ring first (the paper)."""


def path_cameras(center_xy, plant_height: float,
                 config: ScanPathConfig = ScanPathConfig()) -> tuple[list[str], np.ndarray,
                                                                      np.ndarray]:
    """(kinds, cameras (N, 3), targets (N, 3)) in travel order, metres, bed frame.

    Cylinder rings bottom to top, aimed level at the plant axis, each ring turning the other
    way from the last (the path never jumps a full turn); then the dome's rings from the
    lowest, aimed at the dome centre. kinds: "cylinder" or "dome" per stop.
    """
    if not (np.isfinite(plant_height) and plant_height > 0):
        raise InputError("plant height", f"must be positive, got {plant_height}")
    cx, cy = (float(v) for v in np.asarray(center_xy, float)[:2])
    azimuths = np.radians(np.arange(0.0, 360.0 - 1e-9, config.azimuth_step_deg))
    top = plant_height + config.cylinder_top_margin_m
    heights = np.arange(config.cylinder_bottom_m, top + 1e-9, config.cylinder_step_m)
    if len(heights) == 0:
        heights = np.array([config.cylinder_bottom_m])
    dome_z = plant_height / 2 if config.dome_center == "half" else plant_height
    polars = np.radians(np.asarray(config.dome_polar_deg, float))
    kinds, cameras, targets = [], [], []
    for ring, z in enumerate(heights):
        a = azimuths[::-1] if ring % 2 else azimuths
        cameras.append(np.c_[cx + config.cylinder_radius_m * np.cos(a),
                             cy + config.cylinder_radius_m * np.sin(a), np.full(len(a), z)])
        targets.append(np.tile([cx, cy, z], (len(a), 1)))
        kinds += ["cylinder"] * len(a)
    for ring, polar in enumerate(polars):
        a = azimuths[::-1] if (len(heights) + ring) % 2 else azimuths
        r = config.dome_radius_m
        cameras.append(np.c_[cx + r * np.sin(polar) * np.cos(a),
                             cy + r * np.sin(polar) * np.sin(a),
                             np.full(len(a), dome_z + r * np.cos(polar))])
        targets.append(np.tile([cx, cy, dome_z], (len(a), 1)))
        kinds += ["dome"] * len(a)
    return kinds, np.concatenate(cameras), np.concatenate(targets)
