"""Configuration of the synthetic world: plant generator, oracle cloud, scan viewpoints.

Three plant presets. All share the plant's size (26-31 cm high, 34-42 cm across, like the
paper's 38 x 30 cm plants), the flower size (2-3.5 cm across, a yellow receptacle 6-8 mm
wide), the 25 cm soil disc and the colours. They differ in:

- ``easy``: a tidy plant for smoke tests. 7-10 leaves; 4-8 open flowers, all with 5
  petals, facing at most 45 degrees off straight up; nearly flat corollas (petal tips
  between 0.1 of the petal length below and 0.2 above the petal base); no flower under a
  leaf, no touching flowers, no buds or fruit.
- ``realistic`` (the benchmark default): 12-18 trifoliate leaves; 6-20 open flowers on
  inflorescences of 1-3, 5 petals (6-8 in about one flower in seven); corollas from curled
  down (-0.45) to cupped up (+0.4); normals from facing up through sideways to facing down
  (0-150 degrees from vertical, 80% within 90 degrees of up, azimuth mostly away from the
  plant axis); 15% of inflorescences start a few centimetres under a leaflet; 15% of second
  and third flowers touch their neighbour at the rim; 0-4 green buds and 0-3 green or red
  fruit as distractors.
- ``field``: the realistic plant calibrated on a real scan (the authors' plant 3, with
  `flowerpose fidelity`): 4.2-5.8 cm flowers, corollas from curled down (-0.35) to cupped
  (+0.2) and uneven, and an oracle cloud like a photogrammetry one: denser, noisier, its
  foliage paled and yellowed. Its scoring adds the hand labels' error (`score`).
- ``hard``: a crowded plant. 16-24 leaves; 10-24 flowers; stronger curl (-0.6 to +0.5);
  more flowers sideways and facing down (up to 170 degrees from vertical, 30% beyond 90)
  and a wider azimuth spread; 30% of inflorescences under leaflets; 35% touching; 2-8 buds
  and 2-6 fruit.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Literal

from flowerpose.errors import InputError
from flowerpose.scan_geometry import ScanPathConfig

PresetName = Literal["easy", "realistic", "hard", "field"]


@dataclass(frozen=True)
class PlantConfig:
    """Everything the procedural strawberry-plant generator varies (ranges are inclusive)."""

    name: str = "realistic"
    """Preset this config was made from (informational, written into plant.json)."""
    center_xy_m: tuple[float, float] = (1.5, 0.75)
    """Crown position on the bed, metres, bed frame (the crown stands at z = 0): the middle
    of the 3 x 1.5 m bed, where the gantry's scan path reaches all round it."""
    height_m: tuple[float, float] = (0.26, 0.31)
    """Range of the plant's target height (top of leaves and flowers), metres."""
    spread_m: tuple[float, float] = (0.34, 0.42)
    """Range of the plant's diameter (leaf tip to leaf tip), metres."""
    leaves: tuple[int, int] = (12, 18)
    """Range of the number of trifoliate leaves."""
    leaflet_length_m: tuple[float, float] = (0.045, 0.08)
    """Range of the central leaflet's length, metres (lateral leaflets are 85-95% of it)."""
    leaflet_aspect: tuple[float, float] = (0.6, 0.8)
    """Range of leaflet width / length."""
    leaflet_teeth: tuple[int, int] = (8, 13)
    """Range of the number of serration teeth along each leaflet edge."""
    leaf_fold_deg: tuple[float, float] = (5.0, 30.0)
    """Range of the fold of each leaflet half about its midrib, degrees (upward V)."""
    leaf_droop: tuple[float, float] = (-0.05, 0.25)
    """Range of leaflet curvature: drop of the tip below the base plane / leaflet length."""
    flowers: tuple[int, int] = (6, 20)
    """Range of the number of open flowers (the truth)."""
    flower_diameter_m: tuple[float, float] = (0.020, 0.035)
    """Range of open-flower diameters (petal tip to petal tip, projected), metres."""
    receptacle_radius_m: tuple[float, float] = (0.003, 0.004)
    """Range of the yellow receptacle's radius, metres (6-8 mm wide)."""
    petal_counts: tuple[int, ...] = (5, 6, 7, 8)
    """Possible numbers of petals per flower."""
    petal_count_weights: tuple[float, ...] = (0.86, 0.08, 0.04, 0.02)
    """Probabilities of `petal_counts` (normalised)."""
    cup: tuple[float, float] = (-0.45, 0.4)
    """Range of the corolla shape: petal tip height above the petal base along the normal,
    as a fraction of the petal length; positive is cupped up, negative curled down."""
    petal_cup_jitter: float = 0.06
    """Standard deviation of each petal's own cup around its flower's cup (same units)."""
    polar_bins_deg: tuple[float, ...] = (0.0, 30.0, 60.0, 90.0, 120.0, 150.0)
    """Bin edges of the angle between a flower normal and +z, degrees (0 faces up, 180 down)."""
    polar_bin_weights: tuple[float, ...] = (0.3, 0.3, 0.2, 0.12, 0.08)
    """Probability of each polar-angle bin (the angle is uniform inside a bin)."""
    azimuth_spread_deg: float = 50.0
    """Standard deviation of a normal's azimuth around the outward direction from the plant
    axis through the flower, degrees."""
    flowers_per_inflorescence_weights: tuple[float, float, float] = (0.4, 0.4, 0.2)
    """Probabilities of 1, 2 and 3 flowers on one inflorescence (peduncle)."""
    hidden_probability: float = 0.15
    """Probability that an inflorescence's first flower is placed 1.5-6 cm under a leaflet
    (its other flowers grow next to it)."""
    cluster_probability: float = 0.15
    """Probability that the second or third flower of an inflorescence touches the previous
    one at the rim (a touching cluster)."""
    cluster_normal_spread_deg: float = 25.0
    """Largest angle between the normals of two touching flowers, degrees."""
    flower_clearance_m: float = 0.004
    """Least distance from a flower's surface (petals, sepals, receptacle, stamens) to any
    leaf, stem (except its own pedicel behind it), distractor or other flower, metres."""
    touch_gap_m: float = 0.0006
    """Gap left between the rims of two touching flowers, metres (they never interpenetrate)."""
    buds: tuple[int, int] = (0, 4)
    """Range of the number of closed green buds (distractors, not in the truth)."""
    fruit: tuple[int, int] = (0, 3)
    """Range of the number of fruit (distractors, not in the truth)."""
    ripe_fruit_probability: float = 0.5
    """Probability that a fruit is red (ripe) rather than green."""
    soil_radius_m: float = 0.25
    """Radius of the soil disc around the crown, metres."""
    soil_roughness_m: float = 0.0015
    """Standard deviation of the soil height around z = 0, metres."""


@dataclass(frozen=True)
class OracleCloudConfig:
    """The oracle cloud: what a perfect photogrammetry reconstruction of the plant would give."""

    points: int = 60_000
    """Exact number of points returned (plant and soil together)."""
    position_noise_m: float = 0.0
    """Standard deviation of Gaussian noise added to every coordinate, metres."""
    position_noise_wavelength_m: float = 0.0
    """0: the noise is independent point to point; above 0, a smooth displacement field of
    about this wavelength, metres (`perturb.smooth_noise`): a reconstruction's surface
    errors, shared by neighbouring points, which thinning the cloud does not make worse."""
    color_jitter: float = 0.02
    """Standard deviation of independent noise per RGB channel, in [0, 1] colour units."""
    shading: float = 0.12
    """Darkening of a surface lit edge-on: two-sided Lambert factor 1 - shading * (1 - |n.l|)."""
    light_direction: tuple[float, float, float] = (0.3, 0.2, 0.93)
    """Direction towards the light, bed frame (normalised internally)."""
    soil_density: float = 0.5
    """Points per unit area on soil relative to the plant: photogrammetry remeshing (Polycam
    "max polygons") keeps fewer vertices on flat, plain soil than on the plant."""
    visible_only: bool = True
    """Keep only points seen from at least one scan viewpoint (photogrammetry reconstructs
    nothing no camera saw)."""
    visibility_tolerance_m: float = 0.001
    """A point is seen when the first surface hit on the ray from a viewpoint lies within
    this distance of it, metres."""
    max_viewpoints: int = 72
    """Viewpoints used for the visibility test, evenly chosen along the scan path (speed)."""
    foliage_saturation: float = 1.0
    """Saturation of leaves, stems, sepals, buds and the crown is multiplied by this: a
    photogrammetry cloud's texture pales foliage (the authors' plant 3: leaf saturation
    median 0.39, the generator's 0.63)."""
    foliage_value: float = 1.0
    """... their value multiplied by this."""
    foliage_hue_shift_deg: float = 0.0
    """... and their hue moved by this many degrees (negative: toward yellow)."""
    foliage_sheen: float = 0.0
    """This share of the foliage points is blended toward the sky's pale grey by a uniform
    random weight: sheen on leaves, which a photogrammetry texture keeps (the authors' plant
    3: 14% of its leaf points have a petal's colour, the generator's none)."""


@dataclass(frozen=True)
class DegradeConfig:
    """How each plant's oracle cloud departs from a clean one, drawn per plant (seeded by
    the plant) from these ranges (`sim/degrade.py`): a model of how field clouds vary, in
    the operating envelope's terms. Equal ends fix a value, so a run can be matched to a
    real cloud (e.g. `--set 'sim.degrade.points_per_flower=[113, 113]'`)."""

    points_per_flower: tuple[float, float] | None = None
    """Range of the points a visible flower holds (the median over the plant's visible
    flowers), drawn log-uniformly; the cloud is thinned to it, never thickened. None: as
    sampled (`oracle.points`)."""
    exposure: tuple[float, float] = (1.0, 1.0)
    """Range of the exposure, a factor on linear light."""
    cast: float = 0.0
    """Largest colour cast: one channel, drawn, has its linear light changed by a share
    drawn uniformly within +-cast."""
    noise_m: tuple[float, float] = (0.0, 0.0)
    """Range of Gaussian position noise added to every coordinate, metres (on top of
    `oracle.position_noise_m`)."""

    def __post_init__(self):
        if self.points_per_flower is not None and not (
                0 < self.points_per_flower[0] <= self.points_per_flower[1]):
            raise InputError("sim.degrade.points_per_flower", "must be two counts, "
                             "0 < low <= high, or none")
        if not 0 < self.exposure[0] <= self.exposure[1]:
            raise InputError("sim.degrade.exposure", "must be two factors, 0 < low <= high")
        if not 0 <= self.cast < 1:
            raise InputError("sim.degrade.cast", "must be 0 or more, below 1")
        if not 0 <= self.noise_m[0] <= self.noise_m[1]:
            raise InputError("sim.degrade.noise_m", "must be two lengths, 0 <= low <= high")


@dataclass(frozen=True)
class SimConfig:
    """The whole synthetic world: plant, scan path and oracle cloud."""

    plant: PlantConfig = field(default_factory=PlantConfig)
    """Plant generator."""
    viewpoints: ScanPathConfig = field(default_factory=ScanPathConfig)
    """Scan path whose cameras decide visibility (the one the bot's planner flies)."""
    oracle: OracleCloudConfig = field(default_factory=OracleCloudConfig)
    """Oracle point cloud."""
    degrade: DegradeConfig = field(default_factory=DegradeConfig)
    """How the oracle cloud is degraded like a field scan, per plant (none by default)."""


def preset(name: PresetName) -> PlantConfig:
    """The plant config of a named preset (see the module docstring)."""
    realistic = PlantConfig()
    if name == "realistic":
        return realistic
    if name == "easy":
        return dataclasses.replace(
            realistic, name="easy", leaves=(7, 10), flowers=(4, 8), petal_counts=(5,),
            petal_count_weights=(1.0,), cup=(-0.1, 0.2), petal_cup_jitter=0.03,
            polar_bins_deg=(0.0, 20.0, 45.0), polar_bin_weights=(0.6, 0.4),
            azimuth_spread_deg=30.0, hidden_probability=0.0, cluster_probability=0.0,
            buds=(0, 0), fruit=(0, 0))
    if name == "hard":
        return dataclasses.replace(
            realistic, name="hard", leaves=(16, 24), flowers=(10, 24), cup=(-0.6, 0.5),
            petal_cup_jitter=0.1, polar_bins_deg=(0.0, 30.0, 60.0, 90.0, 120.0, 170.0),
            polar_bin_weights=(0.2, 0.25, 0.25, 0.17, 0.13), azimuth_spread_deg=70.0,
            hidden_probability=0.3, cluster_probability=0.35, buds=(2, 8), fruit=(2, 6))
    if name == "field":
        return dataclasses.replace(
            realistic, name="field", flower_diameter_m=FIELD_FLOWER_DIAMETER_M,
            receptacle_radius_m=FIELD_RECEPTACLE_RADIUS_M, cup=FIELD_CUP,
            petal_cup_jitter=FIELD_PETAL_CUP_JITTER)
    raise InputError("preset", f"unknown plant preset {name!r} (easy, realistic, hard, field)")


#: The field preset, calibrated on the authors' plant 3 with `flowerpose fidelity`
#: (DESIGN.md, "The simulator against the field"): its flowers (artificial ones among them)
#: are 4-6 cm across, their corollas more often curl down than cup, unevenly.
FIELD_FLOWER_DIAMETER_M = (0.042, 0.058)
FIELD_RECEPTACLE_RADIUS_M = (0.006, 0.0075)
FIELD_CUP = (-0.45, 0.1)
FIELD_PETAL_CUP_JITTER = 0.3
#: ... and its cloud: denser, noisier, foliage paled and yellowed by the texture.
#: Its surface errors are smooth (`flowerpose fidelity`'s roughness: a real
#: reconstruction's petal points lie 0.06 mm off their neighbours' plane, an independently
#: jittered cloud's 0.6 mm), and thinning them does not make them worse; the petals' own
#: unevenness gives the corolla its thickness.
FIELD_ORACLE = {"points": 100_000, "position_noise_m": 0.0005,
                "position_noise_wavelength_m": 0.01, "foliage_saturation": 0.6,
                "foliage_value": 0.85, "foliage_hue_shift_deg": -17.0, "foliage_sheen": 0.1}
#: ... and how its plants' clouds vary, plant by plant (`DegradeConfig`; DESIGN.md,
#: "The simulator against the field"): from about 100 points a flower (a fast or phone scan,
#: the authors' plant 3 thinned to a tenth) to about 1,000 (that plant as published),
#: exposure and white balance as an auto-exposed camera leaves them.
FIELD_DEGRADE = {"points_per_flower": (100.0, 1000.0), "exposure": (0.8, 1.2), "cast": 0.1}


def sim_preset(name: PresetName) -> SimConfig:
    """The whole synthetic world of a named preset: its plants and, for "field", the
    degraded oracle cloud too."""
    config = SimConfig(plant=preset(name))
    if name == "field":
        config = dataclasses.replace(
            config, oracle=dataclasses.replace(config.oracle, **FIELD_ORACLE),
            degrade=DegradeConfig(**FIELD_DEGRADE))
    return config
