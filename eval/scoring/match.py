"""Matching estimated flowers to true ones and scoring one plant (DESIGN.md's report fields),
and a flowers.json scored against a truth file (`flowerpose score`).

Centres are in metres and normals unit vectors, estimates and truth in the same frame
(the bed frame for generated plants).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment

from flowerpose.errors import InputError
from flowerpose.eval.scoring.truth import TruthFlower
from flowerpose.pipeline.methods import METHODS
from flowerpose.pipeline.pose import FlowerPose

#: Largest centre distance of a match, metres (DESIGN.md and the paper: 2 cm).
MAX_MATCH_DISTANCE = 0.02

#: An estimated flower: a FlowerPose, or a flowers.json entry ("center", "normals").
Estimate = FlowerPose | Mapping[str, Any]


def match_flowers(est_centers: np.ndarray, gt_centers: np.ndarray,
                  max_distance: float = MAX_MATCH_DISTANCE) -> list[tuple[int, int]]:
    """One-to-one matches (estimate index, truth index) by centre distance, Hungarian.

    est_centers: (M, 3), gt_centers: (K, 3), metres, one frame. Pairs farther apart than
    `max_distance` (metres) are never matched. Among the assignments with the most
    matches, the one with the least total distance is returned, sorted by estimate index;
    [] when either side is empty.
    """
    est = np.asarray(est_centers, dtype=np.float64).reshape(-1, 3)
    gt = np.asarray(gt_centers, dtype=np.float64).reshape(-1, 3)
    if len(est) == 0 or len(gt) == 0:
        return []
    distance = np.linalg.norm(est[:, None, :] - gt[None, :, :], axis=2)
    feasible = distance <= max_distance
    # An infeasible pair costs more than any set of feasible pairs together, so the
    # assignment first maximises the number of feasible pairs, then minimises their sum.
    infeasible_cost = (min(len(est), len(gt)) + 1) * max(float(max_distance), 1.0)
    rows, cols = linear_sum_assignment(np.where(feasible, distance, infeasible_cost))
    keep = feasible[rows, cols]
    return [(int(r), int(c)) for r, c in zip(rows[keep], cols[keep], strict=True)]


def angle_error_deg(est: np.ndarray, gt: np.ndarray) -> float:
    """Angle between two normals, degrees in [0, 180]: a flipped normal scores 180.

    est, gt: (3,) direction vectors (normalised here).
    """
    est = np.asarray(est, dtype=np.float64)
    gt = np.asarray(gt, dtype=np.float64)
    cosine = float(est @ gt) / float(np.linalg.norm(est) * np.linalg.norm(gt))
    return float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))))


@dataclass
class PlantScore:
    """One plant's scores (DESIGN.md's report.json plant fields, plus details).

    gt: truth flowers. visible: visible truth flowers. detections: estimates. found: truth
    flowers matched. found_visible: visible truth flowers matched (recall_visible's
    numerator). extra: estimates matched to a truth flower that is not visible. fp:
    estimates matching no flower. error_deg: per method, the angle errors (degrees) of the
    estimates matched to visible flowers, in match order. failed: per method, how many of
    those estimates have no normal (None) for it. pairs: the matches (estimate index,
    truth index).
    """

    gt: int
    visible: int
    detections: int
    found: int
    found_visible: int
    extra: int
    fp: int
    error_deg: dict[str, list[float]] = field(default_factory=dict)
    failed: dict[str, int] = field(default_factory=dict)
    pairs: list[tuple[int, int]] = field(default_factory=list)
    matches: list[dict[str, Any]] = field(default_factory=list)
    """Per match: the estimate's index ("detection"), the truth flower's id ("truth"),
    the centre distance ("distance_m") and, for a visible flower, each method's error
    in degrees or None for a failed fit ("error_deg")."""


def _center(estimate: Estimate) -> np.ndarray:
    return np.asarray(estimate.center if isinstance(estimate, FlowerPose)
                      else estimate["center"], dtype=np.float64)


def _normals(estimate: Estimate) -> Mapping[str, Any]:
    return estimate.normals if isinstance(estimate, FlowerPose) else estimate["normals"]


def score_plant(estimates: Sequence[Estimate], truth: Sequence[TruthFlower],
                max_distance: float = MAX_MATCH_DISTANCE) -> PlantScore:
    """Match one plant's estimated flowers to its truth and measure their normals.

    estimates: FlowerPose objects or flowers.json entries (centre metres, normals unit or
    None per method). Like the paper, which scored only flowers with a hand label, angle
    errors come from matches to visible flowers; matches to hidden ones count as `extra`.
    """
    est_centers = np.array([_center(e) for e in estimates]).reshape(-1, 3)
    gt_centers = np.array([t.center for t in truth]).reshape(-1, 3)
    pairs = match_flowers(est_centers, gt_centers, max_distance)
    scored = [(i, j) for i, j in pairs if truth[j].visible]
    error_deg: dict[str, list[float]] = {m: [] for m in METHODS}
    failed = dict.fromkeys(METHODS, 0)
    matches = []
    for i, j in pairs:
        match: dict[str, Any] = {
            "detection": i, "truth": truth[j].id,
            "distance_m": round(float(np.linalg.norm(est_centers[i] - gt_centers[j])), 6)}
        if truth[j].visible:
            normals = _normals(estimates[i])
            errors: dict[str, float | None] = {}
            for method in METHODS:
                normal = normals.get(method)
                if normal is None:
                    failed[method] += 1
                    errors[method] = None
                else:
                    errors[method] = angle_error_deg(np.asarray(normal), truth[j].normal)
                    error_deg[method].append(errors[method])
            match["error_deg"] = errors
        matches.append(match)
    return PlantScore(
        gt=len(truth), visible=sum(t.visible for t in truth), detections=len(estimates),
        found=len(pairs), found_visible=len(scored), extra=len(pairs) - len(scored),
        fp=len(estimates) - len(pairs), error_deg=error_deg, failed=failed, pairs=pairs,
        matches=matches)


def plant_entry(name: str, score: Any) -> dict:
    """One plant's row of report.json from a PlantScore; "matches" names the truth flower
    and the detection behind each error."""
    matches = [{**m, "error_deg": {k: None if e is None else round(e, 4)
                                   for k, e in m["error_deg"].items()}}
               if "error_deg" in m else m for m in score.matches]
    return {"plant": name, "gt": score.gt, "visible": score.visible,
            "detections": score.detections, "found": score.found,
            "found_visible": score.found_visible, "extra": score.extra, "fp": score.fp,
            "error_deg": {m: [round(e, 4) for e in score.error_deg[m]] for m in METHODS},
            "failed": {m: score.failed[m] for m in METHODS}, "matches": matches}


def barely_matched(score: Any) -> str | None:
    """Why detections and truth that overlap may still not be of one plant: most
    detections match no flower and most visible flowers are missed (None where they
    match)."""
    if score.detections < 2 or score.visible < 2:
        return None
    if 2 * score.fp > score.detections and 2 * score.found_visible < score.visible:
        return (f"{score.fp} of {score.detections} detections match no flower and "
                f"{score.visible - score.found_visible} of {score.visible} visible flowers "
                "are missed: is this the right plant's truth, in the right unit and scale?")
    return None


def read_scored(flowers_path: Path, truth_path: Path, truth_format: str, truth_scale: float
                 ) -> tuple[list[dict], list]:
    """The detections and the truth of a flowers.json scored against a truth file
    (`reports.score_report.score_files`)."""
    from flowerpose.eval.scoring.truth import read_plant_truth, read_sagemaker_truth
    from flowerpose.pipeline.flowers import read_flowers

    estimates = read_flowers(flowers_path)
    if truth_format == "plant":
        from flowerpose.eval.scoring.truth import is_sagemaker
        from flowerpose.jsonio import read_json

        document = read_json(truth_path)
        if isinstance(document, dict) and "flowers" not in document and is_sagemaker(document):
            raise InputError(truth_path, "holds SageMaker Ground Truth cuboids, not a "
                             "plant.json: add `truth_format` sagemaker")
    truth = (read_plant_truth(truth_path) if truth_format == "plant"
             else read_sagemaker_truth(truth_path, truth_scale))
    return estimates, truth


def check_overlap(estimates: Sequence[Estimate], truth: Sequence[TruthFlower],
                   max_distance: float, flowers_path: Path, truth_path: Path) -> None:
    """Refuse detections and truth that cannot be of one plant in one frame: their
    extents, grown by the match distance, do not meet (another plant's truth, another
    frame or another unit), so every detection would count as a false positive."""
    if not estimates or not truth:
        return
    found = np.array([_center(e) for e in estimates]).reshape(-1, 3)
    true = np.array([t.center for t in truth]).reshape(-1, 3)
    apart = np.maximum(found.min(axis=0) - true.max(axis=0), true.min(axis=0) - found.max(axis=0))
    if (apart > max_distance).any():

        def span(points: np.ndarray) -> str:
            return " x ".join(f"{lo:.3g}..{hi:.3g}" for lo, hi in zip(
                points.min(axis=0), points.max(axis=0), strict=True))

        raise InputError(flowers_path, f"its detections ({span(found)} m) and the truth in "
                         f"{truth_path} ({span(true)} m) do not overlap: another plant's "
                         "truth, another frame or another unit?")
