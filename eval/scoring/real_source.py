"""Real labelled plants: the folder format, its reader, and one folder's evaluation.

A real plant is a folder:

    labels.json        this project's label file (`labels.py`, what a labeller saves), AWS
                       SageMaker Ground Truth 3D cuboid labels (the authors' outputN.json)
                       or a plant.json as the simulator writes it
    cloud.ply          a whole plant's cloud: the whole pipeline runs
 or candidates/*.ply   points already taken out of grid views (a detector's crops, one file
                       a view): outlier removal, clustering and pose run on them merged
 or crops/*.ply        one flower a file: the pose stage alone, each crop matched to a label
    source.json        optional: {"truth_scale": 25, "units": "m", "note": "...",
                       "unlabelled": [[x, y, z], ...]}

The first of cloud.ply, candidates/, crops/ that is there decides the stage. Coordinates
are the cloud's own (a Polycam cloud: arbitrary origin and axes, about metres); labels are
divided by the truth scale (SageMaker labels were drawn on a cloud scaled by it; the
authors used 25). "unlabelled" lists centres, in label units, of flowers that are there but
carry no pose label (the paper's "extra" column): a detection on one counts as extra, not as
a false positive. A hand label counts as visible where the folder's cloud holds its flower
(`real_truth`: points near its labelled centre); one on a flower the cloud lost counts
neither as found nor as missed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from scipy.spatial import cKDTree

from flowerpose.cloudio import Cloud, Units, read_cloud, require_hue
from flowerpose.errors import InputError
from flowerpose.eval.scoring.labels import LabelFile, is_label_file, read_labels
from flowerpose.eval.scoring.match import MAX_MATCH_DISTANCE, plant_entry, score_plant
from flowerpose.eval.scoring.truth import (
    TruthFlower,
    is_sagemaker,
    read_plant_truth,
    read_sagemaker_truth,
    vector_list,
)
from flowerpose.jsonio import read_json, write_json
from flowerpose.pipeline.flowers import (
    PipelineConfig,
    Start,
    find_flowers,
    find_flowers_in_candidates,
    flowers_document,
    pose_crops,
    write_flowers,
)
from flowerpose.stopwatch import Stopwatch

#: The authors' labelling scale (their clouds were scaled by 25 for SageMaker).
DEFAULT_TRUTH_SCALE = 25.0
_SOURCE_KEYS = {"truth_scale", "units", "note", "unlabelled"}


@dataclass(frozen=True)
class RealPlant:
    """One labelled real plant folder, checked."""

    folder: Path
    name: str
    labels: Path
    label_format: Literal["flowerpose", "sagemaker", "plant"]
    stage: Start
    clouds: tuple[Path, ...]
    """cloud.ply, or the candidates/*.ply or crops/*.ply files, sorted."""
    truth_scale: float
    units: Units
    note: str
    unlabelled: np.ndarray
    """(K, 3) centres of flowers without a pose label, label units."""

    def describe(self) -> dict[str, Any]:
        return {"folder": str(self.folder), "stage": self.stage, "labels": self.label_format,
                "files": len(self.clouds), "truth_scale": self.truth_scale,
                "units": self.units, "note": self.note}


def _source(folder: Path) -> dict[str, Any]:
    path = folder / "source.json"
    if not path.exists():
        return {}
    source = read_json(path)
    unknown = sorted(set(source) - _SOURCE_KEYS)
    if unknown:
        raise InputError(path, f"unknown key {unknown[0]!r} (known: "
                         f"{', '.join(sorted(_SOURCE_KEYS))})")
    return source


def _scale(value: Any, where: str | Path) -> float:
    if (isinstance(value, bool) or not isinstance(value, int | float)
            or not math.isfinite(value) or value <= 0):
        raise InputError(where, f"the truth scale must be a positive number, got {value!r}")
    return float(value)


def source_units(folder: Path) -> Any:
    """The cloud unit a real plant folder's source.json gives ("m", "mm", "auto" or the
    metres one unit is), checked; "auto" where it gives none."""
    units = _source(folder).get("units", "auto")
    numeric = isinstance(units, int | float) and not isinstance(units, bool)
    if not (units in ("auto", "m", "mm") or (numeric and math.isfinite(units) and units > 0)):
        raise InputError(folder / "source.json", f'"units" must be "m", "mm", "auto" or the '
                         f"metres one unit is (a positive number), got {units!r}")
    return units


def source_truth_scale(folder: Path) -> float | None:
    """The truth scale a real plant folder's source.json gives (labels' units per metre,
    checked), or None where it gives none."""
    source = _source(folder)
    return _scale(source["truth_scale"], folder / "source.json") \
        if "truth_scale" in source else None


def folder_clouds(folder: Path) -> tuple[Start, tuple[Path, ...]]:
    """Where a real plant folder's points are, and the stage they start at: cloud.ply, else
    candidates/*.ply, else crops/*.ply (sorted); InputError naming the folder for none."""
    if (folder / "cloud.ply").is_file():
        return "cloud", (folder / "cloud.ply",)
    for name in ("candidates", "crops"):
        found = tuple(sorted((folder / name).glob("*.ply")))
        if found:
            return name, found  # type: ignore[return-value]
    raise InputError(folder, "no cloud.ply, candidates/*.ply or crops/*.ply")


def read_real_plant(folder: str | Path, truth_scale: float | None = None) -> RealPlant:
    """Check a real plant folder and say what it holds; `truth_scale` overrides
    source.json's. Raises InputError naming the folder or file for a missing folder, no
    labels, labels of another format, no clouds, or a bad source.json."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(folder, "no such folder (a real plant is a folder with labels.json "
                         "and cloud.ply, candidates/ or crops/)")
    labels = folder / "labels.json"
    if not labels.is_file():
        raise InputError(folder, "no labels.json (a flowerpose label file, SageMaker "
                         "Ground Truth cuboids or a plant.json)")
    data = read_json(labels)
    own: LabelFile | None = None
    if is_label_file(data):
        label_format: Literal["flowerpose", "sagemaker", "plant"] = "flowerpose"
        own = read_labels(labels)
    elif "flowers" in data:
        label_format = "plant"
    elif is_sagemaker(data):
        label_format = "sagemaker"
    else:
        raise InputError(labels, "neither a flowerpose label file, SageMaker Ground Truth "
                         'cuboid labels ("boundingCuboids") nor a plant.json ("flowers")')
    stage, clouds = folder_clouds(folder)
    source = _source(folder)
    where = folder / "source.json"
    if own is not None:  # the file states its own scale: applied once, never another's
        scale = own.truth_scale
        if truth_scale is not None and _scale(truth_scale, "truth_scale") != scale:
            raise InputError(labels, f"states truth_scale {scale:g}; --truth-scale "
                             f"{truth_scale:g} contradicts it (a label file's scale is its "
                             "own; source.json's is for labels that state none)")
    elif truth_scale is not None:
        scale = _scale(truth_scale, "truth_scale")
    elif "truth_scale" in source:
        scale = _scale(source["truth_scale"], where)
    else:
        scale = DEFAULT_TRUTH_SCALE if label_format == "sagemaker" else 1.0
    units = source_units(folder)
    note = source.get("note", "")
    if not isinstance(note, str):
        raise InputError(where, '"note" must be text')
    unlabelled = vector_list(source.get("unlabelled", []), where, "unlabelled")
    if own is not None:
        unlabelled = np.r_[unlabelled.reshape(-1, 3), own.unlabelled()]
    return RealPlant(folder, folder.resolve().name, labels, label_format, stage, clouds,
                     scale, units, note, unlabelled)


#: A labelled flower is in the cloud when at least this many of the folder's points lie
#: within the match distance of its labelled centre. A flower the cloud holds has hundreds
#: there (plant 3's 11 labels: 543 to 2,192 points within 2 cm, 38 to 533 within 1 cm); a
#: label on a flower the reconstruction lost has none within several centimetres, and no
#: method can find it.
IN_CLOUD_MIN_POINTS = 10


def real_truth(plant: RealPlant, max_distance: float = MAX_MATCH_DISTANCE
               ) -> list[TruthFlower]:
    """The plant's labelled flowers and its unlabelled ones, in the cloud's unit: labels
    divided by the truth scale. A labelled flower is visible when the folder's own clouds
    (as read, unperturbed) hold it: IN_CLOUD_MIN_POINTS points within `max_distance` (the
    match distance, the cloud's unit) of its centre; unlabelled flowers are never visible
    (a detection on one counts as extra)."""
    if plant.label_format in ("plant", "flowerpose"):
        truth = (read_plant_truth(plant.labels) if plant.label_format == "plant"
                 else read_labels(plant.labels).labelled())
        for flower in truth:
            flower.center = flower.center / plant.truth_scale
    else:
        truth = read_sagemaker_truth(plant.labels, plant.truth_scale)
    if truth:
        held = cKDTree(plant_cloud(plant).points).query_ball_point(
            np.array([t.center for t in truth]), r=max_distance, return_length=True)
        for flower, points in zip(truth, held, strict=True):
            flower.visible = bool(points >= IN_CLOUD_MIN_POINTS)
    extra = [TruthFlower(id=f"unlabelled:{k}", center=c / plant.truth_scale,
                         normal=np.array([0.0, 0.0, 1.0]), visible=False)
             for k, c in enumerate(plant.unlabelled)]
    if truth and extra:
        distance, nearest = cKDTree([t.center for t in truth]).query([e.center for e in extra])
        both = int(np.argmin(distance))
        if distance[both] <= SAME_FLOWER_M * _metres_to_units(plant):
            raise InputError(plant.folder / "source.json", f"unlabelled flower {both} lies "
                             f"{distance[both]:.3g} from the labelled flower "
                             f"{truth[nearest[both]].id!r}: a flower is labelled or unlabelled, "
                             "not both; remove it from \"unlabelled\"")
    return truth + extra


#: Two flower centres nearer than this are one flower, metres.
SAME_FLOWER_M = 0.003


def _metres_to_units(plant: RealPlant) -> float:
    """Cloud units a metre is, as far as the folder says (1 where it does not)."""
    units = plant.units
    if units == "mm":
        return 1000.0
    if isinstance(units, int | float) and not isinstance(units, bool):
        return 1.0 / float(units)
    return 1.0


def _check_scale(plant: RealPlant, truth: list[TruthFlower], points: np.ndarray,
                 max_distance: float) -> None:
    """A scale that puts no label near any point is a wrong scale, not a bad pipeline."""
    nearest = cKDTree(points).query(np.array([t.center for t in truth]))[0]
    if not (nearest <= max_distance).any():
        raise InputError(plant.labels, f"no label lies within {max_distance:g} of any point "
                         f"at truth scale {plant.truth_scale:g} (the nearest is "
                         f"{nearest.min():.3g} away): is the scale right? (`truth_scale`, "
                         "or truth_scale in source.json)")


def plant_cloud(plant: RealPlant) -> Cloud:
    """The folder's points as one cloud: cloud.ply, the candidates merged, or the crops
    together."""
    if plant.stage == "cloud":
        return read_cloud(plant.clouds[0], units=plant.units)
    if plant.stage == "candidates":
        return merged_candidates(plant.clouds, plant.units)
    crops = [read_cloud(p, units=plant.units) for p in plant.clouds]
    return Cloud(np.concatenate([c.points for c in crops]),
                 np.concatenate([c.colors for c in crops]))


def merged_candidates(paths: tuple[Path, ...], units: Units) -> Cloud:
    """The candidate files as one cloud (a point several views took is there several
    times; the candidates stage counts it once)."""
    clouds = [read_cloud(p, units=units) for p in paths]
    return Cloud(np.concatenate([c.points for c in clouds]),
                 np.concatenate([c.colors for c in clouds]))


def read_plant_clouds(plant: RealPlant) -> list[Cloud]:
    """The folder's clouds as read: cloud.ply, each candidates file, or each crop; a whole
    cloud without hue is refused (`require_hue`: a flower's crop may be white alone)."""
    clouds = [read_cloud(p, units=plant.units) for p in plant.clouds]
    if plant.stage == "cloud":
        require_hue(clouds[0], plant.clouds[0])
    return clouds


def evaluate_real_plant(plant: RealPlant, config: PipelineConfig, out_dir: Path,
                        max_distance: float, clouds: list[Cloud] | None = None,
                        drop_views: tuple[int, ...] = ()) -> tuple[dict, dict[str, float]]:
    """Run the pipeline from the stage the folder's data allows, write flowers.json to
    out_dir, and score it against the labels; returns the report's plant entry (with its
    stage) and the stage timings. `clouds`: the folder's clouds as `read_plant_clouds`
    gives them, perhaps changed (`flowerpose stress`); None reads them. `drop_views`: grid
    views whose detections are left out, for a whole cloud."""
    truth = real_truth(plant, max_distance)
    clouds = read_plant_clouds(plant) if clouds is None else clouds
    if plant.stage == "crops":
        _check_scale(plant, truth, np.concatenate([c.points for c in clouds]), max_distance)
        poses, timing = pose_crops(clouds, config)
        flowers = {"flowers": [{"id": k, "crop": p.name, **pose.to_json()}
                               for k, (p, pose) in enumerate(zip(plant.clouds, poses,
                                                                 strict=True))],
                   "timing_s": timing}
        write_json(out_dir / "flowers.json", flowers_document(flowers, plant.folder, "cloud"))
    else:
        cloud = clouds[0] if plant.stage == "cloud" else Cloud(
            np.concatenate([c.points for c in clouds]), np.concatenate([c.colors for c in clouds]))
        _check_scale(plant, truth, cloud.points, max_distance)
        # A real cloud is in its scanner's frame: its up is not known to be z.
        result = (find_flowers(cloud, config, up=None, drop_views=drop_views)
                  if plant.stage == "cloud" else find_flowers_in_candidates(cloud, config))
        write_flowers(out_dir / "flowers.json", result, plant.folder, "cloud")
        poses, timing = [f.pose for f in result.flowers], dict(result.timing_s)
    watch = Stopwatch()
    entry = plant_entry(plant.name, score_plant(poses, truth, max_distance))
    timing["score"] = watch.elapsed()
    return {**entry, "stage": plant.stage}, timing
