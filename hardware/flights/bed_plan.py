"""A bed of plants: where each stands, read from the file a user writes, every plant's scan
planned and checked against the bot's reach, its own envelope and its neighbours', and the
plants put in an order that keeps the gantry's travel between them short.

The bed file is TOML or CSV, positions in the bed frame's metres (DESIGN.md, "Frames"):

    # bed.toml
    [[plant]]
    name = "north-1"     # letters, digits, '.', '_' and '-': it names the plant's folder
    x = 0.75             # the stem, metres along the bed from its home end
    y = 0.75             # metres across the bed
    height = 0.25        # optional: the plant's reach the head keeps clear of, metres
    radius = 0.15        # optional

    [scan.path]          # optional: the scan's settings for this bed (ScanConfig's keys)
    cylinder_radius_m = 0.3

or, as CSV, a header `name,x,y` (with `height,radius` optional) and a row a plant, scanned
with the paper's path.
"""

from __future__ import annotations

import itertools
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from flowerpose.config import apply_overrides, load_toml
from flowerpose.csvio import read_csv_table
from flowerpose.errors import InputError
from flowerpose.hardware.flights.scan_plan import (
    ScanConfig,
    ScanPlan,
    check_clearance,
    check_plant_position,
    plan_scan,
    plant_envelope,
)
from flowerpose.hardware.geometry import PAPER_BOT, BotGeometry
from flowerpose.hardware.motion import MotionProfile, move_duration

PLANT_HEIGHT_M = 0.25
"""A plant's height where its bed file gives none: a grown strawberry plant's, metres."""
PLANT_RADIUS_M = 0.15
"""A plant's radius where its bed file gives none, metres."""

_KEYS = ("name", "x", "y", "height", "radius")
MAX_PLANTS = 500
"""Most plants a bed holds: a FarmBot Genesis XL's 3 x 6 m at strawberry spacing (25-30 cm)
is about 250; more is a file's mistake, refused before anything is planned."""
MAX_RADIUS_M = 1.0
"""A plant wider than this (metres, stem to the edge of its reach) is no strawberry plant: a
number in millimetres, most likely."""
EXACT_TOUR_UP_TO = 8
"""Beds of up to this many plants are ordered by trying every order (8! = 40,320)."""
_TIE_S_PER_M = 0.5
"""Seconds a metre of travel adds to a move's cost when ordering (`_short_tour`): between
plants the Z axis's descent from one dome's top to the next cylinder's lowest ring takes
about 21 s whatever the order, so without it tenths of a second of Z decide and the bot
zigzags along the bed."""
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*")


@dataclass(frozen=True)
class BedPlant:
    """One plant of a bed: its stem at (x, y) and the cylinder the camera head keeps clear
    of, metres, bed frame."""

    name: str
    x: float
    y: float
    height: float = PLANT_HEIGHT_M
    radius: float = PLANT_RADIUS_M

    @property
    def at(self) -> tuple[float, float]:
        return (self.x, self.y)

    def envelope(self) -> np.ndarray:
        """(N, 3) points on the plant's cylinder, metres, bed frame."""
        return plant_envelope(self.at, self.height, self.radius)


@dataclass(frozen=True)
class Bed:
    """A bed file's content: its plants in the file's order and how each is scanned."""

    plants: list[BedPlant]
    scan: ScanConfig = field(default_factory=ScanConfig)


def read_bed(path: Path) -> Bed:
    """A bed file (TOML or CSV by its suffix). InputError names the file, the plant and
    what is wrong: an unknown key or setting, a missing or non-numeric value, a name that
    cannot name a folder or is given twice, no plant at all."""
    path = Path(path)
    if not path.exists():
        raise InputError(path, "bed file not found")
    scan = ScanConfig()
    if path.suffix.lower() == ".csv":
        rows = read_csv_table(path, ("name", "x", "y"), "bed file", "height, radius")
    elif path.suffix.lower() == ".toml":
        data = load_toml(path)
        unknown = sorted(set(data) - {"plant", "scan"})
        if unknown:
            raise InputError(path, f"unknown key {unknown[0]!r}: a bed file holds [[plant]] "
                             "entries and an optional [scan] table")
        rows = data.get("plant", [])
        if not isinstance(rows, list) or not all(isinstance(row, dict) for row in rows):
            raise InputError(path, "'plant' must be an array of tables ([[plant]])")
        if not isinstance(data.get("scan", {}), dict):
            raise InputError(path, "'scan' must be a table of the scan's settings")
        try:
            scan = apply_overrides(scan, data.get("scan", {}), prefix="scan.")
        except InputError as error:
            raise InputError(path, f"{error.source}: {error.problem}") from None
    else:
        raise InputError(path, "a bed file is .toml or .csv")
    if not rows:
        raise InputError(path, "no plant in the bed")
    if len(rows) > MAX_PLANTS:
        raise InputError(path, f"{len(rows):,} plants: a bed holds at most {MAX_PLANTS}; "
                         "split it into beds")
    plants = [_plant(path, number, row) for number, row in enumerate(rows, start=1)]
    seen: set[str] = set()
    for plant in plants:
        if plant.name in seen:
            raise InputError(path, f"plant {plant.name!r} is named twice")
        seen.add(plant.name)
    bed = Bed(plants, scan)
    check_bed(bed, path)
    return bed


def check_bed(bed: Bed, source: str | Path = "bed",
              geometry: BotGeometry = PAPER_BOT) -> None:
    """Check a bed as a whole before anything is planned, for the simulated and the
    physical bot alike: each plant's size plausible in metres (a height above 0 and within
    the gantry's Z travel, a radius above 0 and at most MAX_RADIUS_M: larger is most likely
    millimetres), and no two plants overlapping (their stems nearer than their radii and
    the head's clearance between them: each plant's cut cloud would hold its neighbour's
    flowers). InputError naming `source`, the plants and the numbers."""
    clearance = bed.scan.head_clearance_m
    for plant in bed.plants:
        if not plant.height > 0 or plant.height > geometry.travel_m[2]:
            raise InputError(source, f"plant {plant.name!r}: height {plant.height:g} m is not "
                             f"between 0 and the gantry's Z travel, {geometry.travel_m[2]:g} "
                             "m (bed files are in metres: millimetres?)")
        if not plant.radius > 0 or plant.radius > MAX_RADIUS_M:
            raise InputError(source, f"plant {plant.name!r}: radius {plant.radius:g} m is not "
                             f"between 0 and {MAX_RADIUS_M:g} m (bed files are in metres: "
                             "millimetres?)")
    if len(bed.plants) < 2:
        return
    at = np.array([plant.at for plant in bed.plants])
    radius = np.array([plant.radius for plant in bed.plants])
    apart = np.linalg.norm(at[:, None] - at[None], axis=-1)
    needed = radius[:, None] + radius[None] + clearance
    close = np.argwhere(np.triu(apart < needed, k=1))
    if len(close):
        i, j = close[0]
        a, b = bed.plants[i], bed.plants[j]
        raise InputError(source, f"plants {a.name!r} and {b.name!r} overlap: their stems are "
                         f"{apart[i, j]:.3g} m apart, and with radii {a.radius:g} and "
                         f"{b.radius:g} m and the head's clearance {clearance:g} m they need "
                         f"{needed[i, j]:.3g} m (each plant's cloud would hold the other's "
                         "flowers): move them apart or give smaller radii")


def bed_from_points(points: list[dict], geometry: BotGeometry = PAPER_BOT,
                    source: str = "the FarmBot web app's plants") -> Bed:
    """A bed of a FarmBot account's plants (`cloud_bot.account_plants`: the web app's
    points, FarmBot millimetres): each stands at its x, y converted to the bed frame
    (`geometry.farmbot_mm_to_bed`), with the app's radius where it is larger than
    `PLANT_RADIUS_M` (the app's radius is the spread drawn on its map, 25 mm unless set:
    no grown plant's reach, and a smaller one would bring the head into the leaves) and
    the default height (the app keeps none). Each is named
    from its name and database id ("strawberry-412"), so plants of one crop get folders of
    their own. InputError naming `source` for no plant or a position that is not a
    number."""
    from flowerpose.hardware.geometry import farmbot_mm_to_bed

    plants = []
    for point in points:
        label = str(point.get("name") or "plant")
        name = f"{re.sub(r'[^A-Za-z0-9._-]+', '-', label).strip('-._').lower() or 'plant'}-" \
               f"{point.get('id', len(plants) + 1)}"
        try:
            x_mm, y_mm = float(point["x"]), float(point["y"])
            radius_mm = float(point.get("radius") or 0.0)
        except (KeyError, TypeError, ValueError):
            raise InputError(source, f"plant {label!r} (id {point.get('id')}) has no numeric "
                             "x and y") from None
        if not (math.isfinite(x_mm) and math.isfinite(y_mm) and math.isfinite(radius_mm)):
            raise InputError(source, f"plant {label!r} (id {point.get('id')}) is not at a "
                             "finite position")
        x, y, _ = farmbot_mm_to_bed([x_mm, y_mm, 0.0], geometry)
        radius = max(radius_mm / 1000.0, PLANT_RADIUS_M)
        plants.append(BedPlant(name, float(x), float(y), radius=radius))
    if not plants:
        raise InputError(source, "no plant in the garden: add the bed's plants in the web "
                         "app's Farm Designer, or give --bed FILE")
    if len(plants) > MAX_PLANTS:
        raise InputError(source, f"{len(plants):,} plants: a bed holds at most {MAX_PLANTS}")
    bed = Bed(plants)
    check_bed(bed, source, geometry)
    return bed


def _plant(path: Path, number: int, row: dict) -> BedPlant:
    where = f"plant {number}"
    unknown = sorted(set(row) - set(_KEYS), key=str)
    if unknown:
        raise InputError(path, f"{where}: unknown key {unknown[0]!r} (a plant has "
                         f"{', '.join(_KEYS)})")
    name = row.get("name")
    if not isinstance(name, str) or not _NAME.fullmatch(name):
        raise InputError(path, f"{where}: 'name' must be letters, digits, '.', '_' or '-' "
                         f"(it names the plant's folder), got {name!r}")
    values = {}
    for key in ("x", "y", "height", "radius"):
        if key not in row:
            if key in ("x", "y"):
                raise InputError(path, f"plant {name!r}: '{key}' is missing (metres, bed "
                                 "frame)")
            continue
        try:
            value = float(row[key]) if not isinstance(row[key], bool) else math.nan
        except (TypeError, ValueError):
            value = math.nan
        if not math.isfinite(value):
            raise InputError(path, f"plant {name!r}: '{key}' must be a number of metres, got "
                             f"{row[key]!r}")
        values[key] = value
    return BedPlant(name, **values)


@dataclass(frozen=True)
class BedPlan:
    """A bed's plants in the order the bot visits them, each with its checked scan.

    travel_s[i]: the gantry's seconds from the end of the scan before (or from `start` for
    the first) to the first waypoint of plant i's scan."""

    plants: list[BedPlant]
    scans: list[ScanPlan]
    travel_s: list[float]

    @property
    def duration_s(self) -> float:
        """The bed's bot time: every scan and the travel between them, seconds."""
        return sum(scan.duration_s for scan in self.scans) + sum(self.travel_s)

    def table(self) -> list[str]:
        """A line a plant in visiting order: where it stands, its waypoints, scan and travel
        minutes; then the bed's total."""
        lines = [f"{'order':>5s} {'plant':16s} {'x m':>6s} {'y m':>6s} {'waypoints':>9s} "
                 f"{'scan min':>8s} {'travel s':>8s}"]
        for order, (plant, scan, travel) in enumerate(
                zip(self.plants, self.scans, self.travel_s, strict=True), start=1):
            lines.append(f"{order:5d} {plant.name:16s} {plant.x:6.3f} {plant.y:6.3f} "
                         f"{len(scan.waypoints):9d} {scan.duration_s / 60:8.1f} {travel:8.1f}")
        lines.append(f"{len(self.plants)} plants, {self.duration_s / 60:.1f} min of bot time "
                     f"({sum(self.travel_s):.0f} s of it between plants)")
        return lines


def plan_bed(bed: Bed, geometry: BotGeometry = PAPER_BOT,
             profile: MotionProfile | None = None, start=None,
             surfaces: dict[str, np.ndarray] | None = None) -> BedPlan:
    """Plan and check every plant's scan (`bed.scan`) before anything moves, then order the
    visits.

    Each scan is checked against the bot's reach and its plant's envelope, then against
    every neighbour's envelope (the head keeps `head_clearance_m` from it); `surfaces`
    (name -> (M, 3) points, metres, bed frame: a simulated plant's own surface) stands in
    for the envelope of the plants it names. The order
    starts at the plant nearest `start` (the gantry's bed-frame position, metres; the home
    position when None) and keeps the travel short (`_short_tour`). Raises InputError
    naming the plant (and the neighbour) that cannot be scanned."""
    plants, config = bed.plants, bed.scan
    profile = profile or MotionProfile()
    if not plants:
        raise InputError("bed", "no plant in the bed")
    surfaces = surfaces or {}
    solid = {plant.name: surfaces.get(plant.name) if plant.name in surfaces
             else plant.envelope() for plant in plants}
    scans = [_plant_scan(plant, config, geometry, solid[plant.name]) for plant in plants]
    for plant, scan in zip(plants, scans, strict=True):
        for neighbour in plants:
            if neighbour is not plant and _near(plant, neighbour, config):
                try:
                    check_clearance(scan, solid[neighbour.name], f"plant {neighbour.name}",
                                    "move the plants apart or narrow the scan path's "
                                    "cylinder", geometry, profile)
                except InputError as error:
                    raise InputError(f"plant {plant.name}",
                                     f"{error.source}: {error.problem}") from None
    begin = np.array([scan.waypoints[0].pose.gantry for scan in scans])
    end = np.array([scan.waypoints[-1].pose.gantry for scan in scans])
    start = geometry.home if start is None else np.asarray(start, float)
    order = _short_tour(begin, end, start, profile)
    travel = [move_duration(start if k == 0 else end[order[k - 1]], begin[i], profile)
              for k, i in enumerate(order)]
    return BedPlan([plants[i] for i in order], [scans[i] for i in order], travel)


def _plant_scan(plant: BedPlant, config: ScanConfig, geometry: BotGeometry,
                surface: np.ndarray) -> ScanPlan:
    try:
        x, y = check_plant_position(plant.at, plant.height, plant.radius, geometry)
        return plan_scan(np.array([x, y]), plant.height, config, geometry, obstacles=surface)
    except InputError as error:
        raise InputError(f"plant {plant.name}", f"{error.source}: {error.problem}") from None


def _near(plant: BedPlant, neighbour: BedPlant, config: ScanConfig) -> bool:
    """Whether the neighbour's envelope can come within the head clearance of the plant's
    scan path (a circle of the path's widest radius round the plant)."""
    reach = max(config.path.cylinder_radius_m, config.path.dome_radius_m)
    gap = math.dist(plant.at, neighbour.at) - neighbour.radius
    return gap < reach + config.head_clearance_m + 0.1  # the head's own size, generously


def _short_tour(begin: np.ndarray, end: np.ndarray, start: np.ndarray,
                profile: MotionProfile) -> list[int]:
    """A visiting order of the scans (each entered at `begin[i]`, left at `end[i]`, (N, 3)
    metres) from `start` that keeps the gantry's travel short: the shortest of all orders
    for a bed of up to `EXACT_TOUR_UP_TO` plants, else nearest neighbour, then 2-opt
    reversals and single moves while one shortens it. A move's cost is its time, the
    slowest axis's, plus `_TIE_S_PER_M` for its length."""
    count = len(begin)

    def cost(a: np.ndarray, b: np.ndarray) -> float:
        return move_duration(a, b, profile) + _TIE_S_PER_M * float(np.linalg.norm(b - a))

    between = np.array([[cost(end[i], begin[j]) for j in range(count)] for i in range(count)])
    first = np.array([cost(start, begin[j]) for j in range(count)])

    def total(order: list[int]) -> float:
        return float(first[order[0]] + between[order[:-1], order[1:]].sum())

    if count <= EXACT_TOUR_UP_TO:
        orders = np.array(list(itertools.permutations(range(count))), dtype=np.intp)
        costs = first[orders[:, 0]] + between[orders[:, :-1], orders[:, 1:]].sum(axis=1)
        return [int(i) for i in orders[int(np.argmin(costs))]]
    order = [int(np.argmin(first))]
    while len(order) < count:
        left = [j for j in range(count) if j not in order]
        order.append(min(left, key=lambda j: between[order[-1], j]))
    improved = True
    while improved:
        improved = False
        for candidate in _neighbours(order):
            if total(candidate) < total(order) - 1e-9:
                order, improved = candidate, True
                break
    return order


def _neighbours(order: list[int]):
    """The orders one 2-opt reversal or one move of a plant elsewhere away from `order`."""
    count = len(order)
    for i in range(count - 1):
        for j in range(i + 2, count + 1):
            yield order[:i] + order[i:j][::-1] + order[j:]
    for i in range(count):
        rest = order[:i] + order[i + 1:]
        for j in range(count):
            if j != i:
                yield rest[:j] + [order[i]] + rest[j:]
