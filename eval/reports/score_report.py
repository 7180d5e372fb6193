"""A flowers.json scored against a truth file as a one-plant report (`flowerpose score`):
plant.json or SageMaker labels, the detections and truth checked to be of one plant in
one frame first."""

from __future__ import annotations

import math
from pathlib import Path

from flowerpose.errors import InputError
from flowerpose.eval.reports.report import build_report
from flowerpose.eval.scoring.match import (
    MAX_MATCH_DISTANCE,
    barely_matched,
    check_overlap,
    plant_entry,
    read_scored,
    score_plant,
)
from flowerpose.log import LOG


def score_files(flowers_path: Path, truth_path: Path, truth_format: str = "plant",
                truth_scale: float = 25.0, max_distance: float = MAX_MATCH_DISTANCE) -> dict:
    """A one-plant report for a flowers.json against plant.json or SageMaker labels."""
    if not (truth_scale > 0 and math.isfinite(truth_scale)):
        raise InputError("truth_scale", f"must be positive, got {truth_scale}")
    if not (max_distance > 0 and math.isfinite(max_distance)):
        raise InputError("score.max_distance_m", f"must be positive, got {max_distance}")
    from flowerpose.log import noted
    from flowerpose.pipeline.flowers import read_flower_notes
    from flowerpose.stopwatch import Stopwatch

    with noted() as notes:
        estimates, truth = read_scored(flowers_path, truth_path, truth_format, truth_scale)
    check_overlap(estimates, truth, max_distance, flowers_path, truth_path)
    watch = Stopwatch()
    score = score_plant(estimates, truth, max_distance)
    doubt = barely_matched(score)
    if doubt is not None:
        LOG.warning(f"{flowers_path}: {doubt}")
        notes.append(f"warning: {doubt}")
    config = {"truth_format": truth_format, "truth_scale": truth_scale,
              "max_distance_m": max_distance}
    seconds = round(watch.elapsed(), 6)
    entry = {**plant_entry(flowers_path.parent.name or "plant", score),
             "notes": [*read_flower_notes(flowers_path), *notes]}
    return build_report(config, [entry], {"score": seconds, "total": seconds})
