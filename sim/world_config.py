"""Configuration of the synthetic world: plant generator, oracle cloud, scan viewpoints.

The defaults are the realistic plant (the benchmark's) and a clean oracle cloud. The
presets (easy, realistic, hard, field) are data, not code: each is a TOML file of settings
in assets/presets, over these and the harness's keys, and its description says what it
varies; `sim_preset` reads one.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from flowerpose.config import DEFAULT_PRESET, apply_overrides, load_preset
from flowerpose.errors import InputError
from flowerpose.scan_geometry import ScanPathConfig

#: A preset's name: one of assets/presets (`flowerpose.config.preset_names`).
PresetName = str


@dataclass(frozen=True)
class PlantConfig:
    """Everything the procedural strawberry-plant generator varies (ranges are inclusive)."""

    name: str = DEFAULT_PRESET
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
    stalk_hue_shift_deg: float | None = None
    """The hue shift of stems and sepals (petioles, peduncles, sepals), degrees; None: the
    foliage's. A texture yellows leaves and stalks differently: on the authors' plant 3
    the points behind a flower (its sepals and peduncle) are as green as its leaves and
    none of 237 has a pistil's colour (`flowerpose fidelity`, "stalk points of pistil
    colour"), while the generator's yellower peduncle, moved with the leaves, turned a quarter of
    its points pistil-coloured."""
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
    """The plant config of a named preset (`sim_preset`)."""
    return sim_preset(name).plant


@dataclass(frozen=True)
class WorldSettings:
    """The config tree of a command that reads only the synthetic world (`flowerpose
    plant`): its keys are `sim.*`, as in eval's."""

    sim: SimConfig = field(default_factory=SimConfig)


def sim_preset(name: PresetName) -> SimConfig:
    """The whole synthetic world of a named preset: its `sim.*` settings in
    assets/presets/NAME.toml over the defaults (the realistic plant and a clean oracle
    cloud)."""
    settings, _ = load_preset(name)
    return apply_overrides(SimConfig(), settings.get("sim", {}), prefix="sim.")
