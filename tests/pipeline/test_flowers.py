from dataclasses import replace

import numpy as np

from flowerpose.cloudio import Cloud
from flowerpose.pipeline.flowers import PipelineConfig, _sepals_round
from flowerpose.pipeline.pose import PoseConfig

WHITE, YELLOW, GREEN = (245, 245, 240), (230, 200, 40), (60, 140, 50)


def test_the_cloud_round_a_crop_gives_its_sepals_and_nothing_else():
    # A crop of petals at the origin; round it, green points near and far, and a
    # neighbour's petals and pistil as near as the near green ones.
    points = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [-0.01, 0.0, 0.0],  # the crop
                       [0.002, 0.0, -0.004], [0.0, 0.003, -0.005],  # sepals behind it
                       [0.0, 0.0, 0.2],  # a leaf far off
                       [0.004, 0.0, 0.004], [0.0, 0.004, 0.004],  # a neighbour's petal, pistil
                       [0.0, -0.001, 0.0]])  # the crop's own sepal
    colours = np.array([WHITE, WHITE, WHITE, GREEN, GREEN, GREEN, WHITE, YELLOW, GREEN],
                       np.uint8)
    crop = np.array([0, 1, 2, 8])
    [found] = _sepals_round(Cloud(points, colours), [crop], PipelineConfig(), radius=0.012)
    assert sorted(map(tuple, found)) == sorted(map(tuple, points[[3, 4]]))
    # Where the pose reads its crop alone, or has no flower size, there is nothing to read.
    alone = replace(PipelineConfig(), pose=replace(PoseConfig(), support_from_cloud=False))
    assert _sepals_round(Cloud(points, colours), [crop], alone, radius=0.012) == [None]
    assert _sepals_round(Cloud(points, colours), [crop], PipelineConfig(), radius=None) == [None]
