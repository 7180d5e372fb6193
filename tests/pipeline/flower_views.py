"""Small grid views drawn by the tests: green leaves with white flowers round yellow
centres, the colours the colour detector and a view model are tested on."""

import cv2
import numpy as np

WHITE, YELLOW, GREEN = (245, 245, 238), (240, 205, 40), (60, 120, 40)


def flower_view(centres, radius=12, size=(120, 160)):
    """A (H, W, 3) uint8 RGB view with a flower of `radius` px at each (x, y) of `centres`."""
    image = np.zeros((*size, 3), np.uint8)
    image[:] = GREEN
    for cx, cy in centres:
        cv2.circle(image, (cx, cy), radius, WHITE, -1)
        cv2.circle(image, (cx, cy), radius // 4, YELLOW, -1)
    return image
