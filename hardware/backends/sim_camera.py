"""The simulated camera's recording settings (a module of its own: the harness's settings
embed them without importing the renderer)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from flowerpose.errors import InputError
from flowerpose.hardware.trajectory import SERVO_SPEED_RAD_S
from flowerpose.sim.camera import MAX_RENDER_SIDE
from flowerpose.sim.render_config import RenderConfig
from flowerpose.sim.sensor import SensorConfig


@dataclass(frozen=True)
class SimCameraConfig:
    """The simulated camera's recording (its optics: `sim.camera.CameraConfig`; its
    imperfections: `sim.sensor.SensorConfig`)."""

    width: int = 1280
    """Frame width, pixels (the paper's 1280 x 720 video)."""
    height: int = 720
    """Frame height, pixels."""
    frame_rate_hz: float = 0.6
    """Frames rendered per second of the bot's clock. The real camera records 30 fps, about
    36,000 frames in a 20-minute scan; rendering them all would take hours, and the frame
    stage keeps 200. 0.6 Hz gives about 700 frames taken at moments spread evenly over the
    scan: while moving (motion blur), just after stopping (defocus) and settled (sharp), in
    the proportions a real scan has. Each pause also gives its last video frame, the
    settled view the real camera records 90 of in a 3 s pause."""
    servo_speed_rad_s: float = SERVO_SPEED_RAD_S
    """Head turning speed, radians per second (35 kg servos: about 0.17 s per 60 degrees)."""
    velocity_dt_s: float = 1 / 30
    """Time step of the finite difference that gives the image's speed, seconds."""
    image_depth_m: float = 0.5
    """Depth of the scene point whose image motion stands for the frame's motion, metres
    (the plant's distance on the cylinder)."""
    visibility_width: int = 320
    """Width of the instance-mask renders that decide flower visibility, pixels."""
    visibility_samples: int = 200
    """Petal surface samples per flower for visibility."""
    workers: int | None = None
    """Render processes (default: every core)."""
    seed: int = 0
    """Seed of the sensor noise (frame k uses seed + k)."""
    sensor: SensorConfig = field(default_factory=SensorConfig)
    """The camera's imperfections and colour processing."""
    render: RenderConfig = field(default_factory=RenderConfig)
    """The light on the bed and its surroundings."""

    def __post_init__(self):
        if self.width < 16 or self.height < 16:
            raise InputError("width", "width and height must be at least 16 pixels, got "
                             f"{self.width} x {self.height}")
        if max(self.width, self.height) > MAX_RENDER_SIDE:
            raise InputError("width", f"width and height must be at most {MAX_RENDER_SIDE} "
                             f"pixels (OpenGL renders no larger), got {self.width} x "
                             f"{self.height}")
        if not (self.frame_rate_hz > 0 and math.isfinite(self.frame_rate_hz)):
            raise InputError("frame_rate_hz", f"must be positive, got {self.frame_rate_hz}")
        if self.workers is not None and self.workers < 1:
            raise InputError("workers", f"must be at least 1, got {self.workers}")
        if self.visibility_width < 16 or self.visibility_samples < 1:
            raise InputError("visibility", "needs at least 16 pixels and 1 sample per flower")
