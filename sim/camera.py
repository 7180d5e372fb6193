"""The scan camera: the paper's Arducam IMX219 USB module, its intrinsics and its pose.

Pose convention for the whole project: OpenCV camera axes, x to the image's right, y to
its bottom, z forward along the optical axis. A camera pose is `camera_to_bed`, a (4, 4)
matrix (metres) mapping camera-frame points into the bed frame, or the pair (position
(3,), rotation (3, 3) whose columns are the camera's x, y, z axes in the bed frame), as in
`flowerpose.hardware.kinematics.forward` and trajectory.csv.

Pixel convention of the intrinsics (COLMAP's, the camera model camera.json names):
pixel column i, row j covers u in [i, i + 1), v in [j, j + 1), so its centre is
(i + 0.5, j + 0.5) and a centred principal point is (W / 2, H / 2). A point at (x, y, z)
in the camera frame projects to u = fx x / z + cx, v = fy y / z + cy and lands in pixel
(floor(v), floor(u)). OpenCV's functions put pixel centres at integers: subtract 0.5 from
cx and cy before handing them a K.

The intrinsics class is camera.json's, `flowerpose.scanio.Intrinsics` (width, height, fx,
fy, cx, cy, fps; `matrix`, `scaled`, `to_json`), read back by
`flowerpose.scanio.read_intrinsics`; `intrinsics_from_config` builds it from a
`CameraConfig`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flowerpose.scanio import Intrinsics

__all__ = ["CameraConfig", "Intrinsics", "intrinsics_from_config", "intrinsics_from_json",
           "pose_matrix", "look_at", "opencv_to_opengl", "project", "unproject"]

#: Flips the y and z axes: OpenCV camera axes (y down, z forward) to OpenGL's (y up,
#: looking along -z), and back (it is its own inverse).
_CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


#: Widest or tallest image rendered, pixels: the framebuffer size every OpenGL driver we
#: render with takes (Mesa's GL_MAX_RENDERBUFFER_SIZE is 16384).
MAX_RENDER_SIDE = 16384


@dataclass(frozen=True)
class CameraConfig:
    """The scan camera: Arducam 8MP IMX219 USB autofocus module recording 1280x720 video."""

    width: int = 1280
    """Image width, pixels (the paper's 1280 x 720 video)."""
    height: int = 720
    """Image height, pixels."""
    hfov_deg: float = 62.2
    """Horizontal field of view, degrees. Arducam's datasheet of its 8MP IMX219 USB camera
    (SKU B0196) gives H 62.2, V 48.8 degrees for the full 4:3 sensor (the figures of the
    Raspberry Pi camera v2 with the same sensor and 3.04 mm lens). Assumption: the 16:9
    video modes keep the full sensor width (the module lists a 3264 x 1832 mode) and scale
    it down, so 1280 x 720 sees H 62.2 and V 37.5 degrees with square pixels (fx = fy =
    1061 px). A cropped 720p mode would narrow this: calibrate a real camera and write
    its camera.json instead."""
    principal_point: tuple[float, float] | None = None
    """(cx, cy) in pixels (see the module's pixel convention); None: the image centre
    (width / 2, height / 2)."""
    znear_m: float = 0.01
    """Near clipping distance of the renderer, metres (the camera head never comes closer
    to a leaf than this)."""
    zfar_m: float = 10.0
    """Far clipping distance of the renderer, metres (beyond the 3 m bed's diagonal)."""
    fps: float = 30.0
    """Video frame rate, frames per second."""

    @property
    def vfov_deg(self) -> float:
        """Vertical field of view, degrees (square pixels)."""
        half = math.atan(math.tan(math.radians(self.hfov_deg) / 2) * self.height / self.width)
        return math.degrees(2 * half)


def intrinsics_from_config(config: CameraConfig = CameraConfig()) -> Intrinsics:
    """Pinhole intrinsics (pixels) of a camera config: square pixels, fx from the
    horizontal field of view."""
    f = config.width / 2 / math.tan(math.radians(config.hfov_deg) / 2)
    cx, cy = (config.principal_point if config.principal_point is not None
              else (config.width / 2, config.height / 2))
    return Intrinsics(config.width, config.height, f, f, float(cx), float(cy), config.fps)


def intrinsics_from_json(data: dict) -> Intrinsics:
    """Intrinsics of a camera.json object (the inverse of `Intrinsics.to_json`); read a
    file with `flowerpose.scanio.read_intrinsics`, which checks it."""
    return Intrinsics(int(data["width"]), int(data["height"]), float(data["fx"]),
                      float(data["fy"]), float(data["cx"]), float(data["cy"]),
                      float(data.get("fps", 30.0)))


def pose_matrix(position: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """(4, 4) camera_to_bed of a position ((3,), metres, bed frame) and a rotation ((3, 3),
    columns the OpenCV camera axes in the bed frame)."""
    pose = np.eye(4)
    pose[:3, :3] = rotation
    pose[:3, 3] = position
    return pose


def look_at(position: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(4, 4) camera_to_bed of a camera at `position` looking at `target` ((3,) each,
    metres, bed frame), image upright (the bed's +z up in the image).

    Looking straight down (or up) the image's right is the bed's -y, as the camera head
    gives at yaw 0 (`flowerpose.hardware.kinematics.forward`).
    """
    position = np.asarray(position, np.float64)
    forward = np.asarray(target, np.float64) - position
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    if np.linalg.norm(right) < 1e-9:
        right = np.cross(forward, [1.0, 0.0, 0.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    return pose_matrix(position, np.stack([right, down, forward], 1))


def opencv_to_opengl(camera_to_bed: np.ndarray) -> np.ndarray:
    """(4, 4) pose with OpenGL camera axes (x right, y up, looking along -z, as pyrender
    wants) of a (4, 4) OpenCV camera_to_bed; the same matrix converts back."""
    return np.asarray(camera_to_bed, np.float64) @ _CV_TO_GL


def project(points: np.ndarray, camera_to_bed: np.ndarray,
            intrinsics: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Image coordinates and depth of bed-frame points.

    points: (N, 3) metres, bed frame; camera_to_bed: (4, 4). Returns uv (N, 2) float64
    pixels (the module's convention: pixel index (floor(v), floor(u))) and depth (N,)
    metres along the optical axis (negative behind the camera).
    """
    pose = np.asarray(camera_to_bed, np.float64)
    local = (np.asarray(points, np.float64) - pose[:3, 3]) @ pose[:3, :3]
    z = local[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.stack([intrinsics.fx * local[:, 0] / z + intrinsics.cx,
                       intrinsics.fy * local[:, 1] / z + intrinsics.cy], 1)
    return uv, z


def unproject(uv: np.ndarray, depth: np.ndarray, camera_to_bed: np.ndarray,
              intrinsics: Intrinsics) -> np.ndarray:
    """(N, 3) bed-frame points (metres) at image coordinates uv ((N, 2) pixels) and depth
    ((N,) metres along the optical axis): the inverse of `project`."""
    uv = np.asarray(uv, np.float64)
    depth = np.asarray(depth, np.float64)
    local = np.stack([(uv[:, 0] - intrinsics.cx) / intrinsics.fx * depth,
                      (uv[:, 1] - intrinsics.cy) / intrinsics.fy * depth, depth], 1)
    pose = np.asarray(camera_to_bed, np.float64)
    return local @ pose[:3, :3].T + pose[:3, 3]
