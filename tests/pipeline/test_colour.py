import colorsys

import numpy as np

from flowerpose.pipeline.colour import rgb_to_hsv


def test_matches_colorsys_in_degrees_and_unit_range():
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (500, 3)).astype(np.uint8)
    hsv = rgb_to_hsv(rgb)
    expected = np.array([colorsys.rgb_to_hsv(*(c / 255.0)) for c in rgb]) * [360, 1, 1]
    hue_gap = np.abs(hsv[:, 0] - expected[:, 0])
    assert np.minimum(hue_gap, 360 - hue_gap).max() < 0.01
    np.testing.assert_allclose(hsv[:, 1:], expected[:, 1:], atol=1e-5)


def test_keeps_image_shape_and_handles_empty_input():
    assert rgb_to_hsv(np.zeros((4, 5, 3), np.uint8)).shape == (4, 5, 3)
    assert rgb_to_hsv(np.zeros((0, 3), np.uint8)).shape == (0, 3)
