"""The scan camera's imperfections, applied to a clean render: what a real scan records.

In the order light meets them: motion blur while the camera moves during the exposure,
defocus while the autofocus settles after a stop, sensor noise (shot and read noise), the
camera's colour processing (white balance, exposure gain, saturation), and the video's JPEG
compression (the USB camera streams MJPEG at 1280 x 720 and 30 fps).
`apply_sensor` is deterministic given its random generator and returns a `SensorRecord`
of exactly what it applied, so tests can rank frames by the blur they really carry
(`sharpness_truth`).

Image coordinates and velocities are in pixels of the image given (u right, v down, as
`flowerpose.sim.camera`). The blur sizes in `SensorConfig` are for the 1280 x 720 video:
scale them with the image for smaller test renders.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from statistics import NormalDist

import cv2
import numpy as np

from flowerpose.config import require
from flowerpose.sim.camera import Intrinsics, project


@dataclass(frozen=True)
class SensorConfig:
    """The Arducam IMX219 USB camera as the scan records it (1280 x 720 video)."""

    exposure_s: float = 0.02
    """Exposure time, seconds: the image smears over the distance the scene moves in the
    image meanwhile. The paper fixes a manual exposure; 1/50 s is an assumption for a
    garden bed in daylight at 30 fps (at most 1/30 s)."""
    read_noise_dn: float = 1.5
    """Standard deviation of the signal-independent noise, 8-bit digital numbers."""
    shot_noise_dn: float = 3.0
    """Standard deviation of the photon (shot) noise at full white (255), digital
    numbers; it grows with the square root of the signal (Poisson). The small 1.12 um
    pixels of the IMX219 are noisy, but 720p is binned and scaled from the 8 MP sensor
    and the module's processor denoises, which leaves a few digital numbers."""
    jpeg_quality: int | None = 85
    """JPEG quality of the camera's MJPEG stream, 1-100; None: no compression."""
    autofocus_settle_s: float = 2.0
    """Seconds after the camera stops until the autofocus is sharp again. The paper's
    bot pauses about 3 s at each stop so the autofocus settles: the last second or so of
    each pause is sharp."""
    defocus_px: float = 4.0
    """Defocus blur radius (disc) when the camera has just stopped (and while it moves),
    pixels."""
    gain: float = 1.0
    """Exposure gain of the camera's processing: every channel times this, clipped at
    255 (1: the render's exposure, set for a sunlit scene; an auto-exposed camera in a
    shaded bed brightens)."""
    saturation: float = 1.0
    """Chroma of the processed image against the render's, about each pixel's luma
    (Rec. 601): 1 keeps colours, below 1 pales them (a low-saturation picture profile)."""
    white_balance: tuple[float, float, float] = (1.0, 1.0, 1.0)
    """Gains of the red, green and blue channels (after `gain`): above 1 in red and below
    in blue warms the picture, moving greens toward yellow."""

    def __post_init__(self):
        require(self.gain > 0, "sensor.gain", "must be positive")
        require(self.saturation >= 0, "sensor.saturation", "must be 0 or more")
        require(len(self.white_balance) == 3 and all(g > 0 for g in self.white_balance),
                "sensor.white_balance", "must be three positive gains (red, green, blue)")

    def colour_matrix(self) -> np.ndarray | None:
        """(3, 3) RGB -> RGB matrix of the colour processing, or None when it changes
        nothing: the saturation about luma, then white balance and gain."""
        if self.gain == 1.0 and self.saturation == 1.0 and self.white_balance == (1.0, 1.0, 1.0):
            return None
        luma = np.array([0.299, 0.587, 0.114])
        chroma = self.saturation * np.eye(3) + (1.0 - self.saturation) * np.outer(np.ones(3), luma)
        return self.gain * np.diag(self.white_balance) @ chroma


@dataclass(frozen=True)
class SensorRecord:
    """What `apply_sensor` applied to one frame."""

    motion_blur_px: float
    """Length of the motion-blur line, pixels (image speed x exposure time)."""
    motion_angle_rad: float
    """Direction of the motion blur in the image, radians from +u (right) toward +v
    (down)."""
    defocus_px: float
    """Radius of the defocus disc, pixels (below half a pixel the disc falls within one
    pixel and blurs nothing)."""
    blur_rms_px: float
    """RMS radius of the whole blur kernel applied (motion and defocus together), pixels:
    0 for a sharp frame."""
    sharpness: float
    """Share of a fine texture's Laplacian energy that the blur kept: 1 for a sharp
    frame, toward 0 the more it is blurred. The paper scores frames by the variance of
    their Laplacian, so this ranks blurs of different shapes as that score does (a streak
    keeps the detail across it, a disc of the same RMS radius does not)."""
    noise_sigma_dn: float
    """RMS of the per-pixel noise standard deviation added, digital numbers (0-255)."""
    jpeg_quality: int | None
    """JPEG quality of the compression, None for none."""


def defocus_radius(seconds_since_stop: float, config: SensorConfig) -> float:
    """Defocus disc radius (pixels) a given time after the camera stopped.

    r(t) = defocus_px * (1 - t / T)^2 for 0 <= t < T = autofocus_settle_s, 0 after: the
    contrast-detect autofocus closes in quickly, then creeps to focus (monotonic, smooth
    at T). Pass 0 while the camera moves: the autofocus only settles at rest.
    """
    t = max(float(seconds_since_stop), 0.0)
    if t >= config.autofocus_settle_s:
        return 0.0
    return config.defocus_px * (1.0 - t / config.autofocus_settle_s) ** 2


def image_velocity(camera_to_bed_0: np.ndarray, camera_to_bed_1: np.ndarray, dt: float,
                   intrinsics: Intrinsics, distance_m: float) -> np.ndarray:
    """(2,) image velocity (pixels per second) of the scene between two camera poses.

    The scene point on the optical axis `distance_m` in front of the camera at
    `camera_to_bed_0` ((4, 4), bed frame) is projected from `camera_to_bed_1`, `dt`
    seconds later; its image motion stands for the whole frame's (exact for rotation,
    depth-dependent for translation).
    """
    point = np.asarray(camera_to_bed_0, np.float64) @ np.array([0.0, 0.0, distance_m, 1.0])
    uv, _ = project(point[None, :3], camera_to_bed_1, intrinsics)
    return (uv[0] - [intrinsics.cx, intrinsics.cy]) / dt


def _line_kernel(length: float, angle: float) -> np.ndarray:
    """(k, k) float32 kernel of a centred line `length` pixels long at `angle` (radians,
    image coordinates), anti-aliased: equally spaced samples splatted bilinearly."""
    half = int(math.ceil(length / 2)) + 1
    n = max(2, int(math.ceil(4 * length)) + 1)
    s = np.linspace(-length / 2, length / 2, n)
    x, y = half + s * math.cos(angle), half + s * math.sin(angle)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    kernel = np.zeros((2 * half + 1, 2 * half + 1))
    for dx, dy, w in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)),
                      (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        np.add.at(kernel, (y0 + dy, x0 + dx), w)
    return (kernel / kernel.sum()).astype(np.float32)


def _disc_kernel(radius: float) -> np.ndarray:
    """(k, k) float32 kernel of a disc of `radius` pixels, its rim anti-aliased (each
    pixel weighted by the share of it inside, approximately)."""
    half = int(math.ceil(radius)) + 1
    y, x = np.mgrid[-half:half + 1, -half:half + 1]
    kernel = np.clip(radius + 0.5 - np.hypot(x, y), 0.0, 1.0)
    return (kernel / kernel.sum()).astype(np.float32)


_LAPLACIAN = np.array([[0, 1, 0], [1, -4, 1], [0, 1, 0]], np.float32)
"""The Laplacian of cv2.Laplacian (aperture 1), which frame selection scores with."""


def _laplacian_share(kernel: np.ndarray) -> float:
    """Share of white noise's Laplacian energy left after blurring with `kernel`."""
    response = cv2.filter2D(np.pad(kernel, 1), -1, _LAPLACIAN, borderType=cv2.BORDER_CONSTANT)
    return float((response.astype(np.float64) ** 2).sum() / (_LAPLACIAN ** 2).sum())


def _rms_radius(kernel: np.ndarray) -> float:
    """RMS distance of a normalised kernel's weight from its centroid, pixels."""
    y, x = np.mgrid[:kernel.shape[0], :kernel.shape[1]]
    cx, cy = (kernel * x).sum(), (kernel * y).sum()
    return float(math.sqrt((kernel * ((x - cx) ** 2 + (y - cy) ** 2)).sum()))


_SMALL_KERNEL = 25
"""Kernels of at most this many taps filter RGB directly (faster than the luma/chroma
split below that size)."""


def _trim(kernel: np.ndarray) -> np.ndarray:
    """The kernel without its all-zero outer rows and columns, kept centred (a line
    kernel is square however it is turned, and filtering costs its area)."""
    rows = np.flatnonzero(kernel.any(1))
    cols = np.flatnonzero(kernel.any(0))
    cr, cc = kernel.shape[0] // 2, kernel.shape[1] // 2
    r = max(cr - rows[0], rows[-1] - cr)
    c = max(cc - cols[0], cols[-1] - cc)
    return np.ascontiguousarray(kernel[cr - r:cr + r + 1, cc - c:cc + c + 1])


def _half_kernel(kernel: np.ndarray) -> np.ndarray:
    """The kernel on a grid of half the resolution (odd size, normalised)."""
    rows, cols = ((n // 2) // 2 * 2 + 1 for n in kernel.shape)
    half = cv2.resize(kernel, (cols, rows), interpolation=cv2.INTER_AREA)
    return half / half.sum()


def _blur(rgb: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 image convolved with a normalised (odd, odd) kernel.

    Small kernels filter the three channels. Larger ones filter luma (what sharpness
    measures) exactly and chroma at half resolution with the kernel resampled: the
    camera's 4:2:0 JPEG keeps chroma at half resolution anyway, and one luma channel
    costs a third of three RGB channels.
    """
    if kernel.size <= _SMALL_KERNEL:
        return cv2.filter2D(rgb, -1, kernel, borderType=cv2.BORDER_REFLECT_101)
    height, width = rgb.shape[:2]
    ycc = cv2.cvtColor(rgb, cv2.COLOR_RGB2YCrCb)
    luma = cv2.filter2D(ycc[..., 0].astype(np.float32), -1, kernel,
                        borderType=cv2.BORDER_REFLECT_101)
    half = cv2.resize(ycc, ((width + 1) // 2, (height + 1) // 2), interpolation=cv2.INTER_AREA)
    chroma = cv2.filter2D(half[..., 1:].astype(np.float32), -1, _half_kernel(kernel),
                          borderType=cv2.BORDER_REFLECT_101)
    chroma = cv2.resize(chroma, (width, height), interpolation=cv2.INTER_LINEAR)
    # Both are non-negative: convertScaleAbs rounds and saturates to uint8.
    ycc = cv2.merge([cv2.convertScaleAbs(luma), *cv2.split(cv2.convertScaleAbs(chroma))])
    return cv2.cvtColor(ycc, cv2.COLOR_YCrCb2RGB)


_GAUSSIAN = np.array([NormalDist().inv_cdf((k + 0.5) / 256) for k in range(256)], np.float32)
_GAUSSIAN /= _GAUSSIAN.std()
"""Unit-variance Gaussian quantiles at 256 equal-probability levels: a random byte looks
one up, an 8-bit-resolution normal draw (tails cut at 2.9 sigma) several times faster than
NumPy's normal generator."""


def _add_noise(image: np.ndarray, config: SensorConfig,
               rng: np.random.Generator) -> tuple[np.ndarray, float]:
    """(H, W, 3) uint8 image with Poisson-Gaussian noise (Gaussian approximation: variance
    read^2 + shot^2 * signal / 255, signal in digital numbers), and the RMS of its
    standard deviation over the pixels."""
    levels = np.arange(256, dtype=np.float64)
    variance = config.read_noise_dn ** 2 + config.shot_noise_dn ** 2 * levels / 255.0
    noise = cv2.LUT(np.frombuffer(rng.bytes(image.size), np.uint8).reshape(image.shape),
                    _GAUSSIAN)
    cv2.multiply(noise, cv2.LUT(image, np.sqrt(variance).astype(np.float32)), dst=noise)
    histogram = cv2.calcHist([image.reshape(image.shape[0], -1)], [0], None, [256],
                             [0, 256]).ravel()
    rms = float(np.sqrt(histogram @ variance / max(histogram.sum(), 1.0)))
    return cv2.add(image, noise, dtype=cv2.CV_8U), rms


def process_colour(image: np.ndarray, config: SensorConfig) -> np.ndarray:
    """The camera's colour processing (`SensorConfig.colour_matrix`) of an (..., 3) uint8
    RGB image or colour list, rounded and clipped to 0-255; unchanged without one."""
    matrix = config.colour_matrix()
    if matrix is None:
        return image
    shape = image.shape
    out = cv2.transform(np.ascontiguousarray(image, np.uint8).reshape(-1, 1, 3).astype(np.float32),
                        matrix.astype(np.float32))
    return np.clip(np.rint(out), 0, 255).astype(np.uint8).reshape(shape)


def apply_sensor(rgb: np.ndarray, image_velocity_px_s: np.ndarray, seconds_since_stop: float,
                 config: SensorConfig, rng: np.random.Generator
                 ) -> tuple[np.ndarray, SensorRecord]:
    """The frame the camera records of a clean render, and what was applied.

    rgb: (H, W, 3) uint8 clean render. image_velocity_px_s: (2,) image motion (u, v)
    during the exposure, pixels per second (see `image_velocity`). seconds_since_stop:
    time since the camera last came to rest (0 while it moves). rng: the only source of
    randomness (the noise). Returns (H, W, 3) uint8 and the record.
    """
    velocity = np.asarray(image_velocity_px_s, np.float64)
    length = float(np.hypot(*velocity)) * config.exposure_s
    angle = float(math.atan2(velocity[1], velocity[0]))
    radius = defocus_radius(seconds_since_stop, config)
    # Blur below a twentieth of a pixel changes nothing an 8-bit image can show.
    length = length if length >= 0.05 else 0.0
    radius = radius if radius >= 0.05 else 0.0
    kernel = _line_kernel(length, angle) if length else None
    if radius:
        disc = _disc_kernel(radius)
        kernel = disc if kernel is None else cv2.filter2D(
            np.pad(kernel, disc.shape[0] // 2), -1, disc, borderType=cv2.BORDER_CONSTANT)
    image = np.ascontiguousarray(rgb, np.uint8)
    if kernel is not None:
        kernel = _trim(kernel)
        image = _blur(image, kernel)
    if config.read_noise_dn > 0 or config.shot_noise_dn > 0:
        image, sigma = _add_noise(image, config, rng)
    else:
        sigma = 0.0
    image = process_colour(image, config)
    if config.jpeg_quality is not None:
        ok, data = cv2.imencode(".jpg", cv2.cvtColor(image, cv2.COLOR_RGB2BGR),
                                [cv2.IMWRITE_JPEG_QUALITY, int(config.jpeg_quality)])
        if not ok:
            raise RuntimeError("JPEG encoding failed")
        image = cv2.cvtColor(cv2.imdecode(data, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    blurred = kernel is not None
    record = SensorRecord(length, angle if length else 0.0, radius,
                          _rms_radius(kernel) if blurred else 0.0,
                          _laplacian_share(kernel) if blurred else 1.0, sigma,
                          config.jpeg_quality)
    return image, record


def sharpness_truth(record: SensorRecord) -> float:
    """How sharp a frame really is, from the blur applied to it: the share of fine
    detail (Laplacian energy) it kept, 1 for a sharp frame. Higher is sharper, as the
    paper's score; rank frames by it to check frame selection."""
    return record.sharpness
