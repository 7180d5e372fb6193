"""2D detector plug-ins for the tests (`--detector detector_plugins:CLASS`): tests/ is on
the import path, as the folder of the suite's conftest.py."""

from flowerpose.pipeline.colour import ColourConfig
from flowerpose.pipeline.detect import ColourDetector, DetectConfig


class Same:
    """Another detector: here, the colour detector under another name."""

    def __init__(self):
        self.inner = ColourDetector(DetectConfig(), ColourConfig())

    def __call__(self, image, occupied, pixel_size_m):
        return self.inner(image, occupied, pixel_size_m)


class Garbage:
    def __call__(self, image, occupied, pixel_size_m):
        return [(0, 0, 5, 5)]
