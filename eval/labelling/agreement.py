"""How far two labellings of one plant agree (`flowerpose agree A B`): the label noise that
scoring assumes (`score.label_error_deg`), measured on a user's own data.

Both labellings' flowers (with a pose, or marked as there without one) are matched one to
one by centre (Hungarian, within `max_distance`, as detections are matched to truth). For
each pair where both gave a pose, the angle between the two normals; the statistics of
those angles with their 95 % intervals (`stats.error_summary`, a bootstrap over the
flowers); and the flowers only one labelling holds, or gave a pose to.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from flowerpose.errors import InputError
from flowerpose.eval.scoring.labels import is_label_file, read_labels
from flowerpose.eval.scoring.match import MAX_MATCH_DISTANCE, angle_error_deg, match_flowers
from flowerpose.eval.scoring.real_source import DEFAULT_TRUTH_SCALE
from flowerpose.eval.scoring.stats import error_summary
from flowerpose.eval.scoring.truth import is_sagemaker, read_plant_truth, read_sagemaker_truth
from flowerpose.jsonio import read_json
from flowerpose.log import LOG


@dataclass
class Labelling:
    """One labelling of a plant, in the cloud's coordinates (labels / truth scale)."""

    path: Path
    format: str
    ids: list[Any]
    centers: np.ndarray
    """(N, 3) every flower's centre: those with a pose first, then those without."""
    normals: list[np.ndarray | None]
    """Each flower's unit normal, None for a flower marked as there without a pose."""


def read_labelling(path: str | Path, truth_scale: float | None = None,
                   folder: bool = False) -> Labelling:
    """A label file of any format a real plant folder takes (this project's, SageMaker
    cuboids, a plant.json), its coordinates divided by its truth scale: this project's
    file states its own, which is never applied twice (`truth_scale`, given, must agree
    with it, unless it is a folder's source.json's, `folder`, which describes labels that
    state none); else `truth_scale` where given, 25 (SageMaker) or 1 (plant.json)."""
    path = Path(path)
    data = read_json(path)
    if is_label_file(data):
        labels = read_labels(path)
        scale = labels.truth_scale
        if truth_scale is not None and not folder and truth_scale != scale:
            raise InputError(path, f"states truth_scale {scale:g}; the scale given, "
                             f"{truth_scale:g}, contradicts it (a label file's scale is its own)")
        posed = labels.labelled()
        unposed = [(f.id, f.center) for f in labels.flowers if f.state == "unlabelled"]
        kind = "flowerpose"
    elif isinstance(data, dict) and "flowers" in data:
        scale, posed, unposed, kind = truth_scale or 1.0, read_plant_truth(path), [], "plant"
    elif is_sagemaker(data):
        scale = truth_scale or DEFAULT_TRUTH_SCALE
        posed, unposed, kind = read_sagemaker_truth(path, scale), [], "sagemaker"
        scale = 1.0  # the reader divided already
    else:
        raise InputError(path, "not a label file (a flowerpose label file, SageMaker Ground "
                         "Truth cuboids or a plant.json)")
    centers = [f.center / scale for f in posed] + [c / scale for _, c in unposed]
    return Labelling(path, kind, [f.id for f in posed] + [i for i, _ in unposed],
                     np.array(centers, float).reshape(-1, 3),
                     [f.normal for f in posed] + [None] * len(unposed))


def labelling_unit(path: str | Path, units: Any = "auto") -> tuple[float, str]:
    """The metres one unit of a labelling's coordinates is (the cloud's unit), and how it
    was told: `units` where given (m, mm, metres a unit); else its folder's source.json
    "units"; else the folder's cloud read as the pipeline reads it (its extent); else,
    with no cloud beside it, metres, said as a warning."""
    from flowerpose.cloudio import read_cloud_and_unit
    from flowerpose.eval.scoring.real_source import folder_clouds, source_units

    if units != "auto":
        return (1.0 if units == "m" else 0.001 if units == "mm" else float(units)), "given"
    folder = Path(path).parent
    stated = source_units(folder)
    if stated not in (None, "auto"):
        return (1.0 if stated == "m" else 0.001 if stated == "mm" else float(stated),
                f"{folder / 'source.json'}")
    try:
        _, clouds = folder_clouds(folder)
    except InputError:
        LOG.warning(f"{path}: no cloud beside it tells its unit: its coordinates are taken as "
                    "metres (--units says otherwise)")
        return 1.0, "assumed"
    return read_cloud_and_unit(clouds[0])[1], f"{clouds[0]}"


def agreement(a: Labelling, b: Labelling, max_distance: float = MAX_MATCH_DISTANCE,
              metres_per_unit: float = 1.0) -> dict[str, Any]:
    """The two labellings compared (the module's docstring); `max_distance` in metres,
    `metres_per_unit` the labellings' unit (their cloud's)."""
    pairs = match_flowers(a.centers, b.centers, max_distance / metres_per_unit)
    rows, angles, pose_in_one = [], [], []
    for i, j in pairs:
        row: dict[str, Any] = {"a": a.ids[i], "b": b.ids[j],
                               "distance": round(float(np.linalg.norm(a.centers[i]
                                                                      - b.centers[j])), 5)}
        if a.normals[i] is not None and b.normals[j] is not None:
            row["angle_deg"] = round(angle_error_deg(a.normals[i], b.normals[j]), 3)
            angles.append(row["angle_deg"])
        else:
            pose_in_one.append(row)
        rows.append(row)
    matched_a = {i for i, _ in pairs}
    matched_b = {j for _, j in pairs}
    return {"a": {"file": str(a.path), "format": a.format, "flowers": len(a.ids),
                  "posed": sum(n is not None for n in a.normals)},
            "b": {"file": str(b.path), "format": b.format, "flowers": len(b.ids),
                  "posed": sum(n is not None for n in b.normals)},
            "max_distance_m": max_distance, "metres_per_unit": metres_per_unit,
            "matched": len(pairs),
            "angle_deg": error_summary([angles]),
            "pairs": rows,
            "pose_in_one": pose_in_one,
            "only_a": [a.ids[i] for i in range(len(a.ids)) if i not in matched_a],
            "only_b": [b.ids[j] for j in range(len(b.ids)) if j not in matched_b]}


def agreement_lines(result: dict[str, Any]) -> list[str]:
    """The comparison in a few lines of text."""
    from flowerpose.eval.scoring.stats import interval_text

    angle = result["angle_deg"]
    lines = [f"A: {result['a']['file']} ({result['a']['flowers']} flowers, "
             f"{result['a']['posed']} with a pose)",
             f"B: {result['b']['file']} ({result['b']['flowers']} flowers, "
             f"{result['b']['posed']} with a pose)",
             f"matched within {1000 * result['max_distance_m']:g} mm: {result['matched']}"]
    if angle["n"]:
        lines.append(f"angle between their normals on {angle['n']} flowers: mean "
                     f"{angle['mean']:.1f}° {interval_text(angle['mean_ci95'], unit='°')}, "
                     f"median {angle['median']:.1f}°, p90 {angle['p90']:.1f}°, "
                     f"over 20°: {100 * angle['over_20']:.0f} %")
    else:
        lines.append("no flower has a pose in both: no angle to measure")
    for key, what in (("only_a", "only in A"), ("only_b", "only in B")):
        if result[key]:
            lines.append(f"{what}: {', '.join(map(str, result[key]))}")
    if result["pose_in_one"]:
        lines.append("a pose in one only: " + ", ".join(
            f"{r['a']}/{r['b']}" for r in result["pose_in_one"]))
    return lines
