"""HSV conversions of the generator agree with the pipeline's."""

from __future__ import annotations

import numpy as np

from flowerpose.pipeline.colour import rgb_to_hsv
from flowerpose.sim.plant_colours import hsv_to_rgb, rgba8


def test_hsv_round_trip_through_the_pipeline_conversion():
    rng = np.random.default_rng(0)
    hsv = np.column_stack([rng.uniform(0, 360, 2000), rng.uniform(0.2, 1, 2000),
                           rng.uniform(0.3, 1, 2000)])
    back = rgb_to_hsv(rgba8(hsv_to_rgb(hsv))[:, :3])
    hue_error = np.abs((back[:, 0] - hsv[:, 0] + 180.0) % 360.0 - 180.0)
    assert hue_error.max() < 2.0
    assert np.abs(back[:, 1:] - hsv[:, 1:]).max() < 0.02
    assert np.allclose(hsv_to_rgb([[0.0, 1.0, 1.0], [120.0, 1.0, 1.0], [240.0, 0.0, 0.5]]),
                       [[1, 0, 0], [0, 1, 0], [0.5, 0.5, 0.5]])
