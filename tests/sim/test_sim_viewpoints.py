"""The cylinder + dome scan path."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from flowerpose.sim.config import ViewpointConfig
from flowerpose.sim.viewpoints import scan_viewpoints


def test_cylinder_and_dome_layout():
    config = ViewpointConfig()
    center = np.array([0.4, 0.3])
    views = scan_viewpoints(center, 0.30, config)
    rings = len(np.arange(0.05, 0.32 + 1e-9, 0.02))
    assert rings == 14
    assert views.shape == (rings * 18 + 4 * 18, 3)
    cylinder, dome = views[:rings * 18], views[rings * 18:]
    assert np.linalg.norm(cylinder[:, :2] - center, axis=1) == pytest.approx(0.5)
    assert cylinder[:, 2].min() == pytest.approx(0.05) and cylinder[:, 2].max() <= 0.32 + 1e-9
    assert np.linalg.norm(dome - [*center, 0.30], axis=1) == pytest.approx(0.3)
    polar = np.degrees(np.arccos((dome[:, 2] - 0.30) / 0.3))
    assert sorted(set(np.round(polar, 6))) == [10.0, 30.0, 50.0, 70.0]
    azimuth = np.degrees(np.arctan2(*(cylinder[:18, :2] - center).T[::-1])) % 360
    assert np.allclose(np.sort(azimuth), np.arange(0, 360, 20))


def test_dome_at_half_height():
    config = dataclasses.replace(ViewpointConfig(), dome_center="half")
    views = scan_viewpoints(np.zeros(2), 0.3, config)
    dome = views[-72:]
    assert np.linalg.norm(dome - [0.0, 0.0, 0.15], axis=1) == pytest.approx(0.3)
