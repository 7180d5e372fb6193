"""The flowers a pollination plan visits: read from flowers.json, each with its pose and
whether its sign is certain, the others left alone with why; and the check that they are
the plant's at the place given. Metres, bed frame."""

from __future__ import annotations

import numpy as np

from flowerpose.errors import InputError
from flowerpose.hardware.flights.pollination_plan import Flower

#: Why a detected flower is not visited, before planning: it has no normal of the method, or
#: its normal's sign is uncertain (flowers.json `uncertain`) and uncertain flowers are left
#: alone (`PollinateConfig.visit_uncertain`).
NO_NORMAL, UNCERTAIN = "no normal", "uncertain"


def read_visit_flowers(entries: list[dict], method: str = "plane",
                       visit_uncertain: bool = False) -> tuple[list[Flower], dict[int, str]]:
    """The flowers of flowers.json entries (`pipeline.flowers.read_flowers`) to visit: those
    with a `method` normal (and, unless `visit_uncertain`, whose sign is not uncertain);
    and the others' ids with why each is left alone (NO_NORMAL, UNCERTAIN)."""
    flowers, skipped = [], {}
    for k, entry in enumerate(entries):
        normal = entry["normals"].get(method)
        flower = int(entry.get("id", k))
        if normal is None:
            skipped[flower] = NO_NORMAL
        elif entry.get("uncertain", False) and not visit_uncertain:
            skipped[flower] = UNCERTAIN
        else:
            flowers.append(Flower(flower, np.asarray(entry["center"], float),
                                  np.asarray(normal, float), _radius(entry),
                                  bool(entry.get("uncertain", False))))
    return flowers, skipped


def _radius(entry: dict) -> float | None:
    """A flowers.json flower's radius, metres: half the lesser of its box's two larger
    extents (the corolla's span; the least is its depth), or None without a box."""
    box = entry.get("box")
    if not isinstance(box, dict) or "extent" not in box:
        return None
    extent = np.sort(np.asarray(box["extent"], float))
    return float(extent[1] / 2) if extent[1] > 0 else None


def check_plant(flowers: list[Flower], plant_at, height: float, radius: float,
                source: object) -> None:
    """Refuse flowers that are not the plant's at `plant_at` (x, y), `height` x `radius`
    metres, with 5 cm to spare: a flowers.json of another plant, or not in the bed frame.
    InputError names `source` (the file), or the argument out of range."""
    from flowerpose.hardware.flights.scan_plan import check_plant_position

    x, y = check_plant_position(plant_at, height, radius)
    for flower in flowers:
        off = float(np.hypot(flower.center[0] - x, flower.center[1] - y))
        if off > radius + 0.05 or not -0.05 <= flower.center[2] <= height + 0.05:
            raise InputError(source, f"flower {flower.id} at ({flower.center[0]:.3f}, "
                             f"{flower.center[1]:.3f}, {flower.center[2]:.3f}) m is not on "
                             f"the plant at ({x:g}, {y:g}) m ({off:.2f} m from its stem; "
                             f"the plant {radius:g} m x {height:g} m): is it this plant's, "
                             "in the bed frame?")
