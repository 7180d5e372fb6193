"""Seeded perturbations of a coloured cloud: what a real scan does differently from a clean one.

Each perturbation models one way a field cloud departs from the one the pipeline was
measured on, at a strength that has a unit:

- ``thin``: a seeded uniform subsample keeping this fraction of the points (a faster scan,
  fewer frames, a coarser reconstruction, a phone scan);
- ``exposure``: linear light multiplied by this factor (log2 of it is the change in stops;
  0.6 is about -0.7 EV), clipped at white;
- ``cast``: one channel's linear light multiplied by (1 + this), a white-balance error
  (``channel`` names it: r, g or b);
- ``noise``: Gaussian noise of this standard deviation added to every coordinate, in the
  cloud's unit (metres for a metric cloud);
- ``drop_view``: one grid view's detections left out (a whole cloud) or one candidates file
  left out (a real plant's candidates); the value is the view's position in the list;
- ``cut``: each flower partly seen, as a leaf in front or a one-sided view leaves it: the
  points of its disc beyond a plane across it removed, this share of the disc's area
  (0.5: the plane through its centre; the pistil may go too). The plane's direction in
  the disc is drawn per flower; it needs the flowers' centres, normals and radii (the
  truth: `draw_cuts`).

Colours are 8-bit sRGB: exposure and cast act on linear light, as a camera's do. The
stress report (`eval/studies/stress.py`) and the `field` preset's per-plant degradation both use
these, so a perturbation means the same in both.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from flowerpose.cloudio import Cloud
from flowerpose.errors import InputError
from flowerpose.srgb import relight

Kind = Literal["thin", "exposure", "cast", "noise", "drop_view", "cut"]

#: Every perturbation kind, in the order reports list them.
KINDS: tuple[Kind, ...] = ("thin", "exposure", "cast", "noise", "drop_view", "cut")
#: The colour channels a cast may act on.
CHANNELS = "rgb"
#: What each kind's value means, for reports and errors.
UNITS: dict[str, str] = {
    "thin": "fraction of points kept", "exposure": "factor on linear light",
    "cast": "relative change of one channel's linear light",
    "noise": "standard deviation, the cloud's unit (metres)", "drop_view": "view index",
    "cut": "share of each flower's disc removed on one side"}


@dataclass(frozen=True)
class Perturbation:
    """One perturbation of a cloud (the module docstring says what each kind does)."""

    kind: Kind
    value: float
    channel: str = ""
    """The cast's channel (r, g or b); empty for the other kinds."""

    def __post_init__(self):
        if self.kind not in KINDS:
            raise InputError("perturbation", f"unknown kind {self.kind!r} (one of "
                             f"{', '.join(KINDS)})")
        value = self.value
        problem = {
            "thin": None if 0 < value <= 1 else "a fraction of points kept, above 0, at most 1",
            "exposure": None if value > 0 else "a positive factor",
            "cast": None if -1 < value else "above -1 (a relative change)",
            "noise": None if value >= 0 else "0 or more",
            "drop_view": None if value >= 0 and float(value).is_integer() else
            "a view's index, 0 or more",
            "cut": None if 0 <= value < 1 else "a share of the disc, 0 or more, below 1",
        }[self.kind]
        if problem is not None or not np.isfinite(value):
            raise InputError(f"{self.kind}", f"{value!r}: must be {problem or 'finite'}")
        if (self.kind == "cast") != bool(self.channel) or (
                self.channel and self.channel not in CHANNELS):
            raise InputError(self.kind, "a cast needs its channel (r, g or b), and only a "
                             "cast has one")

    @property
    def label(self) -> str:
        """A short name: "thin 0.1", "cast b+0.15", "drop_view 2"."""
        if self.kind == "cast":
            return f"cast {self.channel}{self.value:+g}"
        return f"{self.kind} {self.value:g}"

    def is_identity(self) -> bool:
        """Whether this perturbation leaves a cloud as it is."""
        return {"thin": self.value == 1, "exposure": self.value == 1, "cast": self.value == 0,
                "noise": self.value == 0, "drop_view": False, "cut": self.value == 0}[self.kind]

    def to_json(self) -> dict:
        entry = {"kind": self.kind, "value": self.value, "unit": UNITS[self.kind]}
        if self.channel:
            entry["channel"] = self.channel
        return entry


def thin(cloud: Cloud, fraction: float, rng: np.random.Generator) -> Cloud:
    """A seeded uniform subsample of round(fraction x N) points (at least one), in the
    cloud's order."""
    keep = max(1, int(round(fraction * len(cloud))))
    if keep >= len(cloud):
        return cloud
    return cloud.subset(np.sort(rng.choice(len(cloud), keep, replace=False)))


def relit(cloud: Cloud, gain: np.ndarray) -> Cloud:
    """The cloud with each channel's linear light multiplied by gain (3,), clipped at white."""
    return Cloud(cloud.points, relight(cloud.colors, gain))


def channel_gain(exposure: float = 1.0, channel: str = "", cast: float = 0.0) -> np.ndarray:
    """(3,) the per-channel gain on linear light of an exposure and a cast of one channel."""
    gain = np.full(3, float(exposure))
    if channel:
        gain[CHANNELS.index(channel)] *= 1.0 + cast
    return gain


def jitter(cloud: Cloud, sigma: float, rng: np.random.Generator) -> Cloud:
    """The cloud with Gaussian noise of standard deviation sigma (its unit) on every
    coordinate."""
    if sigma == 0:
        return cloud
    return Cloud(cloud.points + rng.normal(0.0, sigma, cloud.points.shape), cloud.colors)


#: Plane waves summed into a smooth displacement field (`smooth_noise`).
WAVES = 24


def smooth_noise(points: np.ndarray, sigma: float, wavelength: float,
                 rng: np.random.Generator) -> np.ndarray:
    """(N, 3) a smooth random displacement of points (N, 3): per axis a sum of WAVES plane
    waves of random directions and phases, wavelengths within x0.7-1.4 of `wavelength`,
    scaled to a standard deviation of `sigma` (the points' unit). Neighbouring points move
    together, as a reconstruction's surface errors do; independent noise moves each alone."""
    if sigma == 0 or len(points) == 0:
        return np.zeros_like(points)
    directions = rng.normal(size=(3, WAVES, 3))
    directions /= np.linalg.norm(directions, axis=2, keepdims=True)
    lengths = wavelength * rng.uniform(0.7, 1.4, (3, WAVES, 1))
    phases = rng.uniform(0, 2 * np.pi, (3, WAVES))
    waves = np.einsum("nd,awd->anw", points, directions * (2 * np.pi / lengths)) + phases[:, None]
    return (np.cos(waves).sum(axis=2) * (sigma * np.sqrt(2.0 / WAVES))).T


@dataclass(frozen=True)
class Cut:
    """One flower's cut: its points within `reach` of `centre` whose offset along
    `direction` (a unit vector in the flower's disc) exceeds `offset` are removed. Lengths
    in the cloud's unit."""

    centre: np.ndarray
    direction: np.ndarray
    offset: float
    reach: float


def segment_offset(share: float) -> float:
    """The distance from a unit disc's centre of the chord that cuts off `share` of its
    area (0.5: 0, through the centre)."""
    from scipy.optimize import brentq

    if share <= 0:
        return 1.0
    segment = lambda h: (np.arccos(h) - h * np.sqrt(1 - h * h)) / np.pi - share  # noqa: E731
    return float(brentq(segment, -1.0, 1.0))


def draw_cuts(flowers: list[tuple[np.ndarray, np.ndarray, float]], share: float,
              rng: np.random.Generator) -> list[Cut]:
    """A cut of `share` of each flower's disc, each (centre, unit normal, radius) in the
    cloud's unit, along a direction in its disc drawn from `rng`: what `cut` removes, the
    same for every cloud of one plant (each candidates file)."""
    cuts = []
    offset = segment_offset(share)
    for centre, normal, radius in flowers:
        normal = np.asarray(normal, float) / np.linalg.norm(normal)
        direction = rng.normal(size=3)
        direction -= (direction @ normal) * normal
        direction /= np.linalg.norm(direction)
        cuts.append(Cut(np.asarray(centre, float), direction, offset * radius, radius))
    return cuts


def cut(cloud: Cloud, cuts: list[Cut]) -> Cloud:
    """The cloud without each cut's side of its flower (`Cut`)."""
    if not cuts or len(cloud) == 0:
        return cloud
    removed = np.zeros(len(cloud), bool)
    for one in cuts:
        offset = cloud.points - one.centre
        near = np.einsum("ij,ij->i", offset, offset) <= one.reach ** 2
        removed |= near & (offset @ one.direction > one.offset)
    return cloud.subset(np.flatnonzero(~removed))


def perturb(cloud: Cloud, perturbation: Perturbation, rng: np.random.Generator,
            cuts: list[Cut] | None = None) -> Cloud:
    """The cloud under one perturbation (a view dropped acts on detections or files, not
    on a cloud: the cloud comes back as it is; a cut takes its flowers' `cuts`, drawn once
    for all of a plant's clouds by `draw_cuts`)."""
    if perturbation.kind == "cut":
        if cuts is None:
            raise InputError("cut", "a cut needs the flowers it cuts (their truth)")
        return cut(cloud, cuts)
    kind, value = perturbation.kind, perturbation.value
    if kind == "thin":
        return thin(cloud, value, rng)
    if kind == "exposure":
        return relit(cloud, channel_gain(exposure=value))
    if kind == "cast":
        return relit(cloud, channel_gain(channel=perturbation.channel, cast=value))
    if kind == "noise":
        return jitter(cloud, value, rng)
    return cloud


def parse_perturbation(text: str) -> Perturbation:
    """A perturbation from its label's form, "KIND VALUE" or "KIND=VALUE" ("thin=0.1",
    "cast=b+0.15", "noise=0.0015", "drop_view=2")."""
    kind, sep, value = text.replace(" ", "=", 1).partition("=")
    if not sep:
        raise InputError("perturbation", f"{text!r}: expected KIND=VALUE, e.g. thin=0.1")
    channel = ""
    if kind == "cast" and value[:1] in tuple(CHANNELS):
        channel, value = value[0], value[1:]
    try:
        number = float(value)
    except ValueError:
        raise InputError("perturbation", f"{text!r}: {value!r} is not a number") from None
    return Perturbation(kind, number, channel)  # type: ignore[arg-type]
