"""Flower visibility from the scan viewpoints, on hand-made scenes with a known answer."""

from __future__ import annotations

import numpy as np
from simhelpers import box, cached_plant, handmade_plant

from flowerpose.scan_geometry import path_cameras
from flowerpose.sim.visibility import flower_visibility

UP = np.array([0.0, 0.0, 1.0])


def _views(height: float = 0.2) -> np.ndarray:
    return path_cameras(np.zeros(2), height)[1]


def test_boxed_flower_is_invisible_and_open_one_visible():
    plant = handmade_plant([(np.array([0.0, 0.0, 0.1]), UP), (np.array([0.1, 0.0, 0.1]), UP)],
                           [box([0.1, 0.0, 0.1], [0.06, 0.06, 0.04])])
    visible, fraction = flower_visibility(plant, _views())
    assert visible.tolist() == [True, False]
    assert fraction[0] > 0.9 and fraction[1] == 0.0


def test_flower_under_a_wide_plate_is_invisible():
    # A flower just above the soil under a plate 0.8 m wide: every camera (z >= 0.05 m,
    # at most 0.5 m out) looks at it through the plate.
    plant = handmade_plant([(np.array([0.0, 0.0, 0.02]), UP)],
                           [box([0.0, 0.0, 0.036], [0.8, 0.8, 0.002])])
    visible, fraction = flower_visibility(plant, _views())
    assert not visible[0] and fraction[0] == 0.0


def test_sideways_flower_seen_from_both_faces():
    side = np.array([1.0, 0.0, 0.0])
    # A wall right in front of the flower hides its face; its back is seen from behind.
    plant = handmade_plant([(np.array([0.0, 0.0, 0.1]), side)],
                           [box([0.03, 0.0, 0.1], [0.004, 0.2, 0.2])])
    visible, fraction = flower_visibility(plant, _views())
    assert visible[0] and fraction[0] > 0.8


def test_generated_plant_fractions():
    plant = cached_plant(0, "realistic")
    views = path_cameras(plant.center[:2], plant.height)[1]
    visible, fraction = flower_visibility(plant, views)
    assert visible.shape == fraction.shape == (len(plant.flowers),)
    assert ((fraction >= 0.0) & (fraction <= 1.0)).all()
    assert np.array_equal(visible, fraction >= 0.5)
    again = flower_visibility(plant, views)
    assert np.array_equal(again[1], fraction)
