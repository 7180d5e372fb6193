"""How closely synthetic flowers resemble real ones: the same statistics on both.

For each labelled flower the pipeline finds, its crop is described in the frame of the
true normal round the pipeline's centre (the pistil): r is the distance from the axis, h the
height along it, R the corolla radius (`segment.corolla`). The corolla is the ring
0.3 R <= r <= R within 0.3 R of the petal surface (h = a + b r^2 fitted to the ring); the
centre is r < 0.3 R, from just behind the petal base to 0.3 R in front of it; the stalk is
r < 0.6 R from 0.3 R to 1.5 R behind the petal base (sepals and peduncle, and petals that
curl back); leaves are the points farther than 1.5 typical radii from every flower.
Statistics per flower: points, diameter 2R, petal thickness (RMS distance of the corolla
to its plane), roughness (the median distance of a corolla point from its 8 neighbours'
plane), cupping b R (rim rise over radius, positive cupped up), the share of corolla points
that fail the petal colour test and the share of the crop that is neither corolla nor
centre (leaves and stems inside the crop); per point class, the HSV distribution, and the
share of stalk points of pistil colour. Geometry, not colour,
decides the classes, so the colour tests can be judged by them.
"""

from __future__ import annotations

import json
import math
import tempfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from flowerpose.atomic import write_figure, write_text
from flowerpose.cloudio import Cloud, read_cloud
from flowerpose.errors import InputError
from flowerpose.eval.jobs.config import EvalConfig, pipeline_part
from flowerpose.eval.jobs.plant_set import PlantSet
from flowerpose.eval.reports.report import markdown_table, run_record
from flowerpose.eval.scoring.match import match_flowers
from flowerpose.eval.scoring.real_source import (
    RealPlant,
    merged_candidates,
    read_real_plant,
    real_truth,
)
from flowerpose.eval.scoring.stats import interval_text
from flowerpose.eval.scoring.truth import TruthFlower, read_plant_truth
from flowerpose.jsonio import write_json
from flowerpose.pipeline.colour import petal_mask, pistil_mask, rgb_to_hsv
from flowerpose.pipeline.flowers import PipelineConfig, find_flowers, find_flowers_in_candidates
from flowerpose.pipeline.ground import remove_ground
from flowerpose.pipeline.segment import corolla

#: Percentiles every distribution is summarised by.
PERCENTILES = (5, 25, 50, 75, 95)
#: Inner edge of the corolla ring and the half-width of its slab, in corolla radii.
RING_INNER = 0.3
SLAB = 0.3
#: The centre reaches this many corolla radii behind the petal base (the receptacle's foot).
BASE_DEPTH = 0.05
#: The stalk: within this many corolla radii of the axis, from SLAB to STALK_DEPTH radii
#: behind the petal base.
STALK_ACROSS = 0.6
STALK_DEPTH = 1.5
#: Leaves: points farther than this many typical radii from every flower.
LEAF_DISTANCE = 1.5

#: Statistic -> (what is compared, tolerance, why). "ratio" tolerances bound real/synthetic.
TOLERANCES: dict[str, tuple[str, float, str]] = {
    "points_per_flower": ("ratio", 2.0, "density moves DBSCAN and the corolla test only "
                          "through counts; a factor 2 keeps both in their measured range"),
    "diameter": ("ratio", 1.2, "the radius limits are in flower radii, but the fixed ones "
                 "(DBSCAN eps, the split distance) are not"),
    "thickness": ("ratio", 1.3, "petal thickness against diameter is the plane fit's noise"),
    "roughness": ("ratio", 1.5, "how far a petal point lies off the plane of its 8 nearest "
                  "neighbours: a reconstruction's smooth surface or a jittered one, which "
                  "decides how fast the orientation cues fade when the cloud is thinned"),
    "cupping": ("difference", 0.05, "the median rim rise per radius decides the curved fits"),
    "petal_colour_fail": ("difference", 0.05, "a petal point lost to colour is lost to the fit"),
    "leaf_in_crop": ("difference", 0.10, "leaves in a crop pull the crop-centroid offset"),
    "leaf_petal_colour": ("difference", 0.05, "leaf points of petal colour are what the "
                          "flower test and the corolla coverage must reject"),
    "stalk_pistil_colour": ("difference", 0.05, "a stalk point of pistil colour behind the "
                            "corolla can stand in for a pistil the cloud lost and flip the "
                            "normal"),
    "hue": ("difference", 10.0, "degrees: the colour bands are 15-20 degrees wide"),
    "saturation": ("difference", 0.05, "the petal band ends at 0.39, the pistil's at 0.30"),
    "value": ("difference", 0.05, "the petal band starts at 0.40"),
}


@dataclass
class Sample:
    """One plant's data for the statistics: the cloud, its truth, the crops the pipeline
    found for labelled flowers (truth index -> cloud indices) and their centres."""

    name: str
    cloud: Cloud
    truth: list[TruthFlower]
    crops: dict[int, np.ndarray]
    centres: dict[int, np.ndarray]
    background: np.ndarray
    """Indices of points that may be leaves (above the soil)."""


def _matched(name: str, cloud: Cloud, truth: list[TruthFlower], flowers: list,
             background: np.ndarray, max_distance: float) -> Sample:
    centres = np.array([f.pose.center for f in flowers]).reshape(-1, 3)
    pairs = match_flowers(centres, np.array([t.center for t in truth]).reshape(-1, 3),
                          max_distance)
    visible = [(i, j) for i, j in pairs if truth[j].visible]
    return Sample(name, cloud, truth, {j: flowers[i].crop for i, j in visible},
                  {j: flowers[i].pose.center for i, j in visible}, background)


def real_sample(plant: RealPlant, config: PipelineConfig, max_distance: float) -> Sample:
    """A real plant folder's sample (cloud or candidates; crops are one flower each)."""
    truth = real_truth(plant, max_distance)
    if plant.stage == "crops":
        raise InputError(plant.folder, "fidelity needs cloud.ply or candidates/: crops hold "
                         "no leaves to compare")
    if plant.stage == "cloud":
        cloud = read_cloud(plant.clouds[0], units=plant.units)
        result = find_flowers(cloud, config)
        background = remove_ground(cloud, config.ground)
    else:
        merged = merged_candidates(plant.clouds, plant.units)
        cloud = merged.subset(merged.first_copies())
        result = find_flowers_in_candidates(cloud, config)
        background = np.arange(len(cloud))
    return _matched(plant.name, cloud, truth, result.flowers, background, max_distance)


#: Where a synthetic plant folder keeps the cloud a source made and the truth it saw, most
#: realistic first: the scan source's reconstruction, the RGB-D source's fusion, the oracle.
SYNTHETIC_CLOUDS = (("reconstruction/cloud.ply", "scan/plant.json"),
                    ("rgbd/cloud.ply", "rgbd/plant.json"),
                    ("cloud.ply", "plant.json"))


def synthetic_cloud(folder: Path) -> tuple[Path, Path] | None:
    """The (cloud, truth) a plant folder holds, the first of SYNTHETIC_CLOUDS it has: an
    eval run's scan or RGB-D plant is described by what its source reconstructed, not by
    the oracle cloud every plant folder also keeps."""
    for cloud, truth in SYNTHETIC_CLOUDS:
        if (folder / cloud).is_file() and (folder / truth).is_file():
            return folder / cloud, folder / truth
    return None


def synthetic_sample(folder: Path, config: PipelineConfig, max_distance: float) -> Sample:
    """A generated plant's sample: its most realistic cloud (`synthetic_cloud`)."""
    found = synthetic_cloud(folder)
    if found is None:
        raise InputError(folder, "not a plant folder (no plant.json with a cloud.ply)")
    cloud_path, truth_path = found
    truth = read_plant_truth(truth_path)
    cloud = read_cloud(cloud_path)
    result = find_flowers(cloud, config)
    return _matched(folder.name, cloud, truth, result.flowers,
                    remove_ground(cloud, config.ground), max_distance)


#: Synthetic clouds denser than the real plant by more than this factor (points a flower)
#: are thinned to its density before their outcomes are predicted; sparser ones by more
#: than it are said not to match.
DENSITY_MATCH = 1.25


def real_outcome(plant: RealPlant, settings: EvalConfig) -> dict:
    """The real plant's report.json plant entry: the pipeline's flowers scored against its
    labels, as eval scores it (`RealJob`)."""
    from flowerpose.eval.jobs.plants import RealJob

    with tempfile.TemporaryDirectory() as scratch:
        return RealJob(plant.name, plant).score(settings, Path(scratch))[0]


def predicted_outcome(folder: Path, settings: EvalConfig, points_per_flower: float | None,
                      label_error_deg: float) -> dict:
    """A synthetic plant's report.json plant entry at the real plant's density, scored as
    eval scores it (`SyntheticJob`): its cloud thinned (seeded) where its flowers hold more
    than DENSITY_MATCH times `points_per_flower`, its truth tilted as hand labels are
    (`label_error_deg`)."""
    import dataclasses

    from flowerpose.cloudio import write_cloud
    from flowerpose.eval.jobs.plants import SyntheticJob
    from flowerpose.eval.jobs.plants import points_per_flower as median_points
    from flowerpose.perturb import thin

    cloud_path, truth_path = synthetic_cloud(folder)  # type: ignore[misc]
    scored = dataclasses.replace(settings, score=dataclasses.replace(
        settings.score, label_error_deg=label_error_deg))
    with tempfile.TemporaryDirectory() as scratch:
        entry, _ = SyntheticJob(folder.name, cloud_path, truth_path).score(scored, Path(scratch))
        own_points = median_points(Path(scratch) / "flowers.json")
        if (points_per_flower is not None and own_points is not None
                and own_points > DENSITY_MATCH * points_per_flower):
            rng = np.random.default_rng(zlib.crc32(folder.name.encode()))
            thinned = write_cloud(Path(scratch) / "thinned.ply", thin(
                read_cloud(cloud_path), points_per_flower / own_points, rng))
            entry, _ = SyntheticJob(folder.name, thinned, truth_path).score(scored,
                                                                            Path(scratch))
            own_points = median_points(Path(scratch) / "flowers.json")
    return {**entry, "points_per_flower": own_points}


def outcomes(real_entry: dict, predicted: list[dict], real_points: float | None) -> dict:
    """The real plant's recall of visible flowers and plane error with their 95 % intervals
    beside the synthetic plants' at the real density, and whether each prediction falls
    inside the real interval."""
    from flowerpose.eval.reports.report import summarise

    real, synthetic = summarise([real_entry]), summarise(predicted, intervals=False)
    densities = [p["points_per_flower"] for p in predicted if p["points_per_flower"]]
    synthetic_points = float(np.median(densities)) if densities else None
    matched = (real_points is not None and synthetic_points is not None
               and synthetic_points * DENSITY_MATCH >= real_points)

    def inside(value: float | None, interval: dict) -> bool | None:
        if value is None or interval["low"] is None:
            return None
        return bool(interval["low"] <= value <= interval["high"])

    plane, predicted_plane = real["error_deg"]["plane"], synthetic["error_deg"]["plane"]
    return {"real": {"recall_visible": real["recall_visible"],
                     "recall_visible_ci95": real["recall_visible_ci95"],
                     "visible": real["visible"], "plane_mean": plane["mean"],
                     "plane_mean_ci95": plane["mean_ci95"], "flowers": plane["n"],
                     "points_per_flower": real_points},
            "predicted": {"recall_visible": synthetic["recall_visible"],
                          "visible": synthetic["visible"],
                          "plane_mean": predicted_plane["mean"],
                          "flowers": predicted_plane["n"],
                          "points_per_flower": synthetic_points},
            "density_matched": bool(matched),
            "recall_inside": inside(synthetic["recall_visible"], real["recall_visible_ci95"]),
            "plane_inside": inside(predicted_plane["mean"], plane["mean_ci95"])}


def outcome_lines(outcome: dict) -> list[str]:
    """The prediction against the real plant's intervals, in words."""
    real, predicted = outcome["real"], outcome["predicted"]
    if predicted["recall_visible"] is None or real["recall_visible"] is None:
        return ["no flower to predict from"]

    def said(inside: bool | None) -> str:
        return "-" if inside is None else "inside" if inside else "outside"

    lines = [f"recall of visible flowers: real {real['recall_visible']:.3f} "
             f"{interval_text(real['recall_visible_ci95'], 2)} ({real['visible']} flowers), "
             f"predicted {predicted['recall_visible']:.3f} ({predicted['visible']} flowers): "
             f"{said(outcome['recall_inside'])} the real interval",
             "plane error's mean: real "
             + ("-" if real["plane_mean"] is None else
                f"{real['plane_mean']:.2f}° {interval_text(real['plane_mean_ci95'])}")
             + f" ({real['flowers']} flowers), predicted "
             + ("-" if predicted["plane_mean"] is None else f"{predicted['plane_mean']:.2f}°")
             + f" ({predicted['flowers']} flowers): {said(outcome['plane_inside'])} the real "
             "interval"]
    if not outcome["density_matched"]:
        lines.append(f"the synthetic flowers hold {predicted['points_per_flower']} points "
                     f"(median), the real ones {real['points_per_flower']}: too sparse to "
                     "predict at the real density (generate them denser, e.g. --set "
                     f"'sim.degrade.points_per_flower=[{real['points_per_flower']:.0f}, "
                     f"{real['points_per_flower']:.0f}]')")
    return lines


def synthetic_folders(paths: list[Path]) -> list[Path]:
    """Plant folders given directly or inside an eval run's plants/ folder (oracle, scan or
    RGB-D source)."""
    folders = []
    for path in paths:
        if synthetic_cloud(path) is not None:
            folders.append(path)
        elif found := sorted(p for p in (path / "plants").glob("seed-*")
                             if synthetic_cloud(p) is not None):
            folders.extend(found)
        else:
            raise InputError(path, "neither a plant folder (plant.json and cloud.ply, from "
                             "flowerpose plant) nor an eval run with plants/seed-*/")
    return folders


def _flower_stats(sample: Sample, j: int, config: PipelineConfig) -> dict[str, Any] | None:
    crop_index = sample.crops[j]
    points, colors = sample.cloud.points[crop_index], sample.cloud.colors[crop_index]
    hsv = rgb_to_hsv(colors)
    shape = corolla(points, petal_mask(hsv, config.colour), pistil_mask(hsv, config.colour),
                    config.cluster)
    radius = shape.radius
    if radius <= 0:
        return None
    normal = sample.truth[j].normal
    offset = points - sample.centres[j]
    height = offset @ normal
    across = np.linalg.norm(offset - np.outer(height, normal), axis=1)
    ring = (across >= RING_INNER * radius) & (across <= radius)
    if ring.sum() < 10:
        return None
    design = np.column_stack([np.ones(ring.sum()), across[ring] ** 2])
    (base, curve), *_ = np.linalg.lstsq(design, height[ring], rcond=None)
    surface = base + curve * across ** 2
    petals = ring & (np.abs(height - surface) <= SLAB * radius)
    # The pistil stands in front of the petal base; the sepals behind it are not centre.
    lift = height - base
    centre = (across < RING_INNER * radius) & (lift >= -BASE_DEPTH * radius) & (
        lift <= SLAB * radius)
    stalk = (across < STALK_ACROSS * radius) & (lift < -SLAB * radius) & (
        lift >= -STALK_DEPTH * radius)
    if petals.sum() < 10:
        return None
    corolla_points = points[petals] - points[petals].mean(axis=0)
    plane = np.linalg.eigh(corolla_points.T @ corolla_points)[1][:, 0]
    return {
        "points": len(points), "diameter": 2 * radius,
        "thickness": float(np.sqrt(np.mean((corolla_points @ plane) ** 2))),
        "roughness": local_roughness(points[petals]),
        "cupping": float(curve * radius),
        "petal_colour_fail": float(1.0 - petal_mask(hsv[petals], config.colour).mean()),
        "leaf_in_crop": float(1.0 - (petals | centre).mean()),
        "hsv": {"petal": hsv[petals], "centre": hsv[centre], "stalk": hsv[stalk]},
    }


#: Neighbours of the local plane `local_roughness` measures each point against.
ROUGHNESS_NEIGHBOURS = 8


def local_roughness(points: np.ndarray) -> float:
    """The median distance of points (N, 3) from the least-squares plane of their
    ROUGHNESS_NEIGHBOURS nearest neighbours (themselves among them), the cloud's unit: near
    0 for a smooth reconstructed surface, about the noise for a jittered one."""
    from scipy.spatial import cKDTree

    k = min(ROUGHNESS_NEIGHBOURS, len(points) - 1)
    if k < 3:
        return float("nan")
    _, nearest = cKDTree(points).query(points, k=k + 1)
    around = points[nearest] - points[nearest].mean(axis=1, keepdims=True)
    normals = np.linalg.eigh(np.einsum("nki,nkj->nij", around, around))[1][:, :, 0]
    return float(np.median(np.abs(np.einsum("ni,ni->n", around[:, 0], normals))))


def _leaf_hsv(sample: Sample, typical: float) -> np.ndarray:
    candidates = sample.background
    centres = np.array([t.center for t in sample.truth]).reshape(-1, 3)
    if len(centres):
        from scipy.spatial import cKDTree

        nearest = cKDTree(centres).query(sample.cloud.points[candidates])[0]
        candidates = candidates[nearest > LEAF_DISTANCE * typical]
    return rgb_to_hsv(sample.cloud.colors[candidates])


def _summary(values: np.ndarray) -> dict[str, float]:
    if len(values) == 0:
        return {f"p{q}": None for q in PERCENTILES}
    return {f"p{q}": float(f"{v:.4g}") for q, v in
            zip(PERCENTILES, np.percentile(values, PERCENTILES), strict=True)}


def statistics(samples: list[Sample], config: PipelineConfig) -> dict[str, Any]:
    """The statistics of one side (real or synthetic), over its plants' flowers; raw
    values for the plots under "_raw"."""
    flowers = [s for sample in samples for j in sample.crops
               if (s := _flower_stats(sample, j, config)) is not None]
    if not flowers:
        raise InputError(samples[0].name if samples else "fidelity",
                         "no labelled flower was found, so there is nothing to describe")
    typical = float(np.median([f["diameter"] for f in flowers])) / 2
    raw = {key: np.array([f[key] for f in flowers], np.float64)
           for key in ("points", "diameter", "thickness", "roughness", "cupping",
                       "petal_colour_fail", "leaf_in_crop")}
    hsv = {"petal": np.concatenate([f["hsv"]["petal"] for f in flowers]),
           "centre": np.concatenate([f["hsv"]["centre"] for f in flowers]),
           "stalk": np.concatenate([f["hsv"]["stalk"] for f in flowers]),
           "leaf": np.concatenate([_leaf_hsv(s, typical) for s in samples])}
    out: dict[str, Any] = {"plants": [s.name for s in samples], "flowers": len(flowers)}
    out.update({key: _summary(values) for key, values in raw.items()})
    out["hsv"] = {part: {channel: _summary(values[:, k]) for k, channel in
                         enumerate(("hue", "saturation", "value"))}
                  for part, values in hsv.items()}
    out["leaf_petal_colour"] = round(float(petal_mask(hsv["leaf"], config.colour).mean()), 4) \
        if len(hsv["leaf"]) else None
    out["stalk_pistil_colour"] = round(float(
        pistil_mask(hsv["stalk"], config.colour).mean()), 4) if len(hsv["stalk"]) else None
    out["_raw"] = {**raw, **{f"hsv_{part}": values for part, values in hsv.items()}}
    return out


def compare(real: dict[str, Any], synthetic: dict[str, Any]) -> list[dict[str, Any]]:
    """Each statistic's medians side by side, its tolerance and whether it holds."""
    rows = []

    def row(name: str, key: str, real_value: float | None, synth_value: float | None) -> None:
        kind, tolerance, why = TOLERANCES[key]
        if real_value is None or synth_value is None:
            holds, gap = False, None
        elif kind == "ratio":
            gap = (max(real_value, synth_value) / min(real_value, synth_value)
                   if min(real_value, synth_value) > 0 else math.inf)
            holds = gap <= tolerance
        else:
            gap = abs(real_value - synth_value)
            holds = gap <= tolerance
        rows.append({"statistic": name, "real": real_value, "synthetic": synth_value,
                     "compared": kind, "gap": None if gap is None else round(gap, 4),
                     "tolerance": tolerance, "holds": bool(holds), "why": why})

    mapping = {"points": "points_per_flower", "diameter": "diameter", "thickness": "thickness",
               "roughness": "roughness", "cupping": "cupping",
               "petal_colour_fail": "petal_colour_fail", "leaf_in_crop": "leaf_in_crop"}
    for key, tolerance_key in mapping.items():
        row(f"{key} (median)", tolerance_key, real[key]["p50"], synthetic[key]["p50"])
    row("leaf points of petal colour", "leaf_petal_colour", real["leaf_petal_colour"],
        synthetic["leaf_petal_colour"])
    row("stalk points of pistil colour", "stalk_pistil_colour", real["stalk_pistil_colour"],
        synthetic["stalk_pistil_colour"])
    for part in ("petal", "centre", "leaf"):
        # The hue of a white is noise (its saturation is near 0): petals are judged by
        # saturation and value only.
        for channel in ("saturation", "value") if part == "petal" else ("hue", "saturation",
                                                                          "value"):
            row(f"{part} {channel} (median)", channel, real["hsv"][part][channel]["p50"],
                synthetic["hsv"][part][channel]["p50"])
    return rows


def _plot(path: Path, real: dict[str, Any], synthetic: dict[str, Any], names: tuple[str, str]
          ) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [("points", "points per flower", None), ("diameter", "diameter", None),
              ("thickness", "petal thickness (RMS to plane)", None),
              ("roughness", "roughness (off the local plane)", None),
              ("cupping", "cupping (rim rise / radius)", None)]
    for part in ("petal", "centre", "stalk", "leaf"):
        for k, channel in enumerate(("hue (degrees)", "saturation", "value")):
            panels.append((f"hsv_{part}", f"{part} {channel}", k))
    fig, axes = plt.subplots(5, 4, figsize=(16, 15))
    for ax, (key, title, channel) in zip(axes.ravel(), panels, strict=False):
        for side, colour, label in ((real, "tab:red", names[0]), (synthetic, "tab:blue",
                                                                   names[1])):
            values = side["_raw"][key]
            values = values[:, channel] if channel is not None else values
            if len(values):
                ax.hist(values, bins=30, density=True, alpha=0.5, color=colour, label=label)
        ax.set_title(title, fontsize=9)
    for ax in axes.ravel()[len(panels):]:
        ax.axis("off")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle("flowerpose fidelity: real (red) and synthetic (blue) flowers")
    fig.tight_layout()
    write_figure(path, fig, dpi=80)
    plt.close(fig)


def table(report: dict[str, Any]) -> str:
    """The comparison as a Markdown table."""
    def show(value: float | None) -> str:
        return "-" if value is None else f"{value:.4g}"

    rows = []
    for row in report["comparison"]:
        ratio = row["compared"] == "ratio"
        tolerance = f"x{row['tolerance']:g}" if ratio else f"±{row['tolerance']:g}"
        gap = "-" if row["gap"] is None else (f"x{row['gap']:.3g}" if ratio
                                              else f"{row['gap']:.3g}")
        rows.append([row["statistic"], show(row["real"]), show(row["synthetic"]), gap,
                     tolerance, "yes" if row["holds"] else "no"])
    return markdown_table(["statistic", "real", "synthetic", "gap", "tolerance", "holds"], rows)


#: What `run_fidelity` writes into its folder.
FIDELITY_FILES = ("fidelity.json", "fidelity.md", "fidelity.png")


def run_fidelity(settings: EvalConfig, real: PlantSet, synthetic_dirs: list[Path],
                 out_dir: Path) -> dict[str, Any]:
    """Statistics of a real plant folder (`real`, one) and of synthetic plants, compared,
    and the synthetic plants' predicted recall and plane error at the real density against
    the real plant's 95 % intervals (`outcomes`; the synthetic truth tilted by the
    settings' `score.label_error_deg`, or by the eval run's own where a synthetic folder is
    a run); writes fidelity.json, fidelity.md and fidelity.png to out_dir and returns the
    report."""
    if not real.real or len(real.folders) != 1:
        raise InputError("--real", "fidelity compares one real plant folder")
    config, max_distance = pipeline_part(settings), settings.score.max_distance_m
    label_error_deg = settings.score.label_error_deg
    real_plant = read_real_plant(real.folders[0], real.truth_scale)
    folders = synthetic_folders(synthetic_dirs)
    real = statistics([real_sample(real_plant, config, max_distance)], config)
    synthetic = statistics([synthetic_sample(f, config, max_distance) for f in folders], config)
    rows = compare(real, synthetic)
    real_points = real["points"]["p50"]
    predicted = [predicted_outcome(f, settings, real_points,
                                   run_label_error(f, label_error_deg)) for f in folders]
    outcome = outcomes(real_outcome(real_plant, settings), predicted, real_points)
    out_dir.mkdir(parents=True, exist_ok=True)
    _plot(out_dir / "fidelity.png", real, synthetic, (real_plant.name, "synthetic"))
    report = {"run": run_record(), "real_plant": real_plant.name,
              "real": {k: v for k, v in real.items() if k != "_raw"},
              "synthetic": {k: v for k, v in synthetic.items() if k != "_raw"},
              "comparison": rows, "holds": sum(r["holds"] for r in rows), "of": len(rows),
              "outcomes": outcome}
    write_json(out_dir / "fidelity.json", json.loads(json.dumps(report)))
    write_text(out_dir / "fidelity.md",
        f"# flowerpose fidelity: {real_plant.name} against {len(folders)} synthetic plants\n\n"
        f"{table(report)}\n\n## Predicted scores at the real density\n\n"
        + "".join(f"- {line}\n" for line in outcome_lines(outcome))
        + "\nTolerances and why:\n\n"
        + "".join(f"- {key}: {kind} within {tolerance:g}: {why}\n"
                  for key, (kind, tolerance, why) in TOLERANCES.items()))
    return report


def run_label_error(folder: Path, default: float) -> float:
    """The hand labels' error the eval run a synthetic plant folder belongs to scored
    against (its report.json's `score.label_error_deg`), else `default`."""
    from flowerpose.jsonio import read_json

    for run in (folder.parent.parent, folder.parent):
        if (run / "report.json").is_file():
            score = read_json(run / "report.json").get("config", {}).get("score", {})
            return float(score.get("label_error_deg", default))
    return default
