"""Images of any COLMAP camera model made images of a pinhole (dense stereo needs one).

The pinhole is pycolmap's own choice for the camera (`pycolmap.undistort_camera`: the
largest image without blank borders); the pixel map from it back into the distorted image
is computed once per camera (the camera's own unprojection and projection, so every model
COLMAP has works) and applied to each image with OpenCV's remap, which is many times faster
than undistorting image by image.
"""

from __future__ import annotations

# cv2 before pycolmap (sfm.py says why).
import cv2  # isort: skip

import numpy as np
import pycolmap

from flowerpose.scanio import Intrinsics


class Undistorter:
    """A distorted camera's images as images of its pinhole."""

    def __init__(self, camera: pycolmap.Camera):
        self.camera = camera
        self.pinhole = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), camera)
        width, height = self.pinhole.width, self.pinhole.height
        u, v = np.meshgrid(np.arange(width, dtype=np.float64),
                           np.arange(height, dtype=np.float64))
        # COLMAP's pixel centres are at +0.5; OpenCV's remap samples at integer positions.
        rays = self.pinhole.cam_from_img(np.c_[u.ravel() + 0.5, v.ravel() + 0.5])
        source = camera.img_from_cam(np.c_[rays, np.ones(len(rays))]) - 0.5
        self._map_x = source[:, 0].reshape(height, width).astype(np.float32)
        self._map_y = source[:, 1].reshape(height, width).astype(np.float32)

    @property
    def intrinsics(self) -> Intrinsics:
        """The pinhole, as a frames folder's camera.json holds it."""
        p = self.pinhole
        return Intrinsics(p.width, p.height, p.focal_length_x, p.focal_length_y,
                          p.principal_point_x, p.principal_point_y)

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """An image of the distorted camera (H, W[, 3]) as one of the pinhole."""
        return cv2.remap(image, self._map_x, self._map_y, cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0)
