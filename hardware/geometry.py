"""Dimensions of the paper's FarmBot Genesis v1.7 and its 2-DOF camera head: the one source.

Frames and units (DESIGN.md): SI throughout, metres and radians. The bed frame has its
origin at the soil-surface corner of the bed at FarmBot's home end (min X, min Y), x along
the bed (FarmBot X), y across it (FarmBot Y), z up, z = 0 on the soil; the bed covers
[0, 3.0] x [0, 1.5] m. FarmBot's own millimetres (home 0, 0, 0; z <= 0 downward from the
top of Z) are converted here, in `farmbot_mm_to_bed` and `bed_to_farmbot_mm`, and nowhere
else. The gantry position of a pose is the point the UTM bottom centre sits at.

The camera head (the paper's end effector on the universal tool mount, UTM):

- yaw: a hinge about the vertical axis through the UTM centre, at the UTM bottom. Geometric
  yaw 0 points the camera along +x; positive yaw turns it counter-clockwise seen from above
  (towards +y).
- pitch: a horizontal hinge `pitch_axis_below_utm_m` below the UTM bottom on the yaw axis,
  across the yawed camera direction. Geometric pitch 0 is level; positive pitch looks down;
  pitch 90 degrees looks straight down and pitch 180 degrees looks level backwards, upside
  down ("over the top").
- the camera's optical centre sits on its optical axis, `camera_forward_of_pitch_m` in front
  of the pitch axis, so the optical axis always passes through the pitch axis and the yaw
  axis: a camera position and a look-at point fix the head pose in closed form.

Servo commands (docs/guides/physical-bot.md, "The camera head"): command degrees 0-180 on
Farmduino pins 6 (yaw) and 5 (pitch) from the geometric angle a in degrees,
``yaw_cmd = (180 - a) / 180 * 120 + 40`` and ``pitch_cmd = (180 - a) / 180 * 120 + 30``:
120 command degrees per 180 geometric degrees (270-degree servos), the command falling as
the angle grows. Commands 0-180 therefore reach geometric yaw -30 to 240 degrees and
geometric pitch -45 to 225 degrees (`yaw_range_rad`, `pitch_range_rad`). Upstream drives
yaw directly only in [0, 180] degrees and reaches a look direction with yaw beyond 180 by
the flip ``yaw -= 180, pitch = 180 - pitch``: the same optical axis and camera position,
the image turned by 180 degrees. `kinematics.look_at` follows upstream; its
`servo_commands` drives any yaw the servo reaches as it is and flips only the rest.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib.resources import files
from pathlib import Path

import numpy as np

from flowerpose.errors import InputError

FARMBOT_ASSETS = Path(str(files("flowerpose.assets") / "farmbot"))
YAW_PIN, PITCH_PIN = 6, 5
"""Farmduino pins of the head's yaw and pitch servos (the paper's wiring)."""
"""Folder of the MuJoCo model (`farmbot.xml`, `scene.xml`), whose numbers agree with
`BotGeometry()` (tests/hardware/test_model.py checks it)."""


@dataclass(frozen=True)
class BotGeometry:
    """Dimensions of the bot, bed frame, metres (see the module docstring for the frames)."""

    bed_size_m: tuple[float, float] = (3.0, 1.5)
    """Soil surface of the raised bed along x and y, metres (the user's 10 ft x 5 ft)."""
    bed_depth_m: float = 0.3
    """Depth of the raised bed's soil below its surface (the model's floor), metres."""
    travel_m: tuple[float, float, float] = (2.7222, 1.23, 0.43164)
    """Gantry travel of FarmBot X, Y, Z from home, metres (the paper's calibrated bot)."""
    home_utm_m: tuple[float, float, float] = (0.1389, 0.135, 0.65)
    """Bed-frame position of the UTM bottom centre at FarmBot (0, 0, 0), metres. x and y
    centre the travel over the bed ((3.0 - 2.7222) / 2, (1.5 - 1.23) / 2). z: with Z fully
    up the UTM bottom is 0.65 m above the soil, so fully down (Z -431.64 mm) it is 0.218 m
    above it: room for the 0.1 m camera head over the lowest plants, and the dome over a
    0.25 m plant reachable."""
    utm_below_beam_m: float = 0.12
    """With Z fully up, the UTM bottom is this far below the gantry beam bottom, metres."""
    utm_radius_m: float = 0.035
    """Radius of the universal tool mount, metres."""
    pitch_axis_below_utm_m: float = 0.06
    """Pitch axis below the UTM bottom on the yaw axis, metres (yaw servo body and bracket,
    about 40 mm for a 35 kg servo plus 20 mm of bracket)."""
    camera_forward_of_pitch_m: float = 0.04
    """Optical centre in front of the pitch axis along the optical axis, metres (half the
    pitch servo's width, the camera board and its lens)."""
    servo_command_range_deg: tuple[float, float] = (0.0, 180.0)
    """Servo command range, degrees (FarmBot's tools allow only 0-180)."""
    command_per_geometric: float = 120.0 / 180.0
    """Command degrees per geometric degree (upstream's 120 / 180)."""
    yaw_command_offset_deg: float = 40.0
    """Yaw command at geometric yaw 180 degrees (upstream's + 40)."""
    pitch_command_offset_deg: float = 30.0
    """Pitch command at geometric pitch 180 degrees (upstream's + 30)."""
    head_yaw_box_m: tuple[tuple[float, float, float], tuple[float, float, float]] = (
        (0.0, 0.0, -0.02), (0.022, 0.012, 0.022))
    """The yaw servo's housing as a box: its centre in the yaw frame (origin the UTM bottom
    centre, x the yaw-0 heading, z up) and half sizes, metres (`farmbot.xml`'s collision
    geom of `head_yaw`)."""
    head_pitch_box_m: tuple[tuple[float, float, float], tuple[float, float, float]] = (
        (0.015, 0.0, 0.0), (0.03, 0.022, 0.022))
    """The pitch servo, bracket and camera as a box: its centre in the pitch frame (origin
    on the pitch axis, x the optical axis) and half sizes, metres (`head_pitch`'s)."""
    soil_clearance_m: float = 0.03
    """Least height of the camera's optical centre and of the pitch axis above the soil,
    metres (the head's housings reach about 2 cm around them)."""

    @property
    def home(self) -> np.ndarray:
        """(3,) bed-frame position of the UTM bottom centre at FarmBot home, metres."""
        return np.asarray(self.home_utm_m, np.float64)

    @property
    def gantry_min(self) -> np.ndarray:
        """(3,) lowest bed-frame UTM position on each axis the travel reaches, metres."""
        return self.home - np.array([0.0, 0.0, self.travel_m[2]])

    @property
    def gantry_max(self) -> np.ndarray:
        """(3,) highest bed-frame UTM position on each axis the travel reaches, metres."""
        return self.home + np.array([self.travel_m[0], self.travel_m[1], 0.0])

    @property
    def beam_bottom_m(self) -> float:
        """Height of the gantry beam's bottom above the soil, metres."""
        return self.home_utm_m[2] + self.utm_below_beam_m

    def command_to_angle(self, command_deg, offset_deg: float) -> np.ndarray:
        """Geometric angle, radians, of a servo command, degrees (upstream's mapping inverted).

        offset_deg: `yaw_command_offset_deg` or `pitch_command_offset_deg`.
        """
        command = np.asarray(command_deg, np.float64)
        return np.radians(180.0 - (command - offset_deg) / self.command_per_geometric)

    def angle_to_command(self, angle_rad, offset_deg: float) -> np.ndarray:
        """Servo command, degrees, of a geometric angle, radians (upstream's mapping).

        offset_deg: `yaw_command_offset_deg` or `pitch_command_offset_deg`.
        """
        angle = np.degrees(np.asarray(angle_rad, np.float64))
        return (180.0 - angle) * self.command_per_geometric + offset_deg

    def _range_rad(self, offset_deg: float) -> tuple[float, float]:
        low, high = self.servo_command_range_deg
        ends = self.command_to_angle(np.array([high, low]), offset_deg)
        return float(ends[0]), float(ends[1])

    @property
    def yaw_range_rad(self) -> tuple[float, float]:
        """Geometric yaw the yaw servo reaches with commands 0-180: -30 to 240 degrees, radians."""
        return self._range_rad(self.yaw_command_offset_deg)

    @property
    def pitch_range_rad(self) -> tuple[float, float]:
        """Geometric pitch the pitch servo reaches with commands 0-180: -45 to 225 degrees,
        radians."""
        return self._range_rad(self.pitch_command_offset_deg)


PAPER_BOT = BotGeometry()
"""The paper's bot: FarmBot Genesis v1.7 over a 3 x 1.5 m bed with the yaw / pitch head."""


@dataclass(frozen=True)
class PollinatorTool:
    """A soft swab on the pitch bracket under the camera, its shaft parallel to the optical
    axis (assets/farmbot/farmbot.xml, body `pollinator`): the head's yaw and pitch aim it,
    the gantry carries it. Metres, in the pitch bracket's frame: along the optical axis
    from the pitch axis, and towards the image's bottom from that axis."""

    reach_m: float = 0.15
    """The swab tip's centre ahead of the pitch axis along the shaft: 11 cm past the
    camera's optical centre, so the lens stays clear of the flower it touches. Chosen by
    `tune --task pollinate` (docs/guides/pollination.md) with `offset_down_m` and the
    standoff. From the true poses (the planner's ceiling, 10 field plants, seeds 0-9) a
    12 cm shaft 3 cm under the lens reached 110 of 134 flowers, this one 122."""
    offset_down_m: float = 0.054
    """The shaft's offset from the optical axis towards the image's bottom: 5.4 cm, so even
    its tip, 11 cm ahead of the lens, is 26 degrees off the axis, outside the camera's
    18.75 degree half field of view (the tool never shows in a scan frame); and the lower
    the swab hangs, the lower the flowers it reaches under the UTM's lowest Z."""
    shaft_start_m: float = 0.02
    """Where the shaft leaves the bracket, ahead of the pitch axis."""
    shaft_radius_m: float = 0.002
    """Radius of the shaft (a 4 mm rod)."""
    tip_radius_m: float = 0.004
    """Radius of the swab at its tip: an 8 mm head, about as wide as a strawberry flower's
    6-8 mm receptacle, the part a visit must touch."""

    def __post_init__(self):
        for name in ("reach_m", "shaft_start_m", "shaft_radius_m", "tip_radius_m"):
            if not getattr(self, name) > 0:
                raise InputError(f"pollinate.tool.{name}", f"must be positive, got "
                                 f"{getattr(self, name)}")
        if self.offset_down_m < 0:
            raise InputError("pollinate.tool.offset_down_m", f"must be 0 or more, got "
                             f"{self.offset_down_m}")
        if not self.shaft_start_m < self.reach_m - self.tip_radius_m:
            raise InputError("pollinate.tool.shaft_start_m", f"the shaft must start "
                             f"({self.shaft_start_m} m) before the swab "
                             f"({self.reach_m - self.tip_radius_m:g} m ahead of the pitch "
                             "axis)")


PAPER_TOOL = PollinatorTool()
"""The pollinator this project plans for (`hardware/flights/pollination_plan.py`)."""


def farmbot_mm_to_bed(xyz_mm, geometry: BotGeometry = PAPER_BOT) -> np.ndarray:
    """Bed-frame UTM position, metres, of FarmBot coordinates.

    xyz_mm: (..., 3) FarmBot X, Y, Z in millimetres (home 0, 0, 0; Z <= 0 downward).
    Returns (..., 3) float64, metres, bed frame, of the UTM bottom centre.
    """
    return geometry.home + np.asarray(xyz_mm, np.float64) / 1000.0


def bed_to_farmbot_mm(xyz_m, geometry: BotGeometry = PAPER_BOT) -> np.ndarray:
    """FarmBot coordinates, millimetres, that put the UTM bottom centre at a bed position.

    xyz_m: (..., 3) UTM bottom centre, metres, bed frame.
    Returns (..., 3) float64 FarmBot X, Y, Z in millimetres (Z <= 0 below the top of Z).
    """
    return (np.asarray(xyz_m, np.float64) - geometry.home) * 1000.0
