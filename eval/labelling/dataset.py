"""Training data from the simulator: seeded plants' grid views (or scan frames) with exact
per-flower instance masks and boxes, as COCO or YOLO, split into train and val by plant.

    DIR/dataset.json                  how it was made: the run, the plants' seeds and
                                      split, counts, the settings, what a mask holds
    DIR/split.json                    the train and val plant seeds
    DIR/images/{train,val}/NAME       grid: seed-3_+x.png (a view as detect sees it);
                                      frames: seed-3_frame-017.jpg (scan waypoint 17)
    coco: DIR/annotations/instances_{train,val}.json   (`eval/labelling/coco.py`)
    yolo: DIR/labels/{train,val}/NAME.txt, DIR/data.yaml (`eval/labelling/yolo.py`)

Grid views are the detect stage's own (`pipeline.flowers.grid_views` of the plant's oracle
cloud, as `eval --source oracle` feeds it), so the masks are exact for the images a
detector gets: every pixel is owned by one cloud point, and a point belongs to the flower
its surface was sampled on. Frames are the simulated scan camera's (`scan.*` settings:
size, sensor, light) at evenly spaced waypoints of the plant's planned scan, at rest, with
the renderer's instance masks of the same pixels. A flower's mask is its petals,
receptacle and stamens as seen (occluded by whatever is in front, its own sepals
included); sepals, buds, fruit and leaves are background, so a flower seen only from
behind is no instance.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import cv2
import numpy as np

from flowerpose.atomic import write_image
from flowerpose.config import require, to_dict
from flowerpose.errors import InputError
from flowerpose.eval.jobs.config import EvalConfig
from flowerpose.eval.jobs.plant_set import PlantSet
from flowerpose.eval.labelling.coco import annotation, write_instances
from flowerpose.eval.labelling.yolo import label_line, write_data_yaml, write_labels
from flowerpose.eval.reports.report import run_record
from flowerpose.jsonio import write_json
from flowerpose.log import Tally
from flowerpose.outputs import OutputFolder
from flowerpose.pipeline.flowers import grid_views
from flowerpose.sim.pieces import Part

if TYPE_CHECKING:  # the plant's mesh needs trimesh, which the core install lacks
    from flowerpose.sim.bundle import PlantBundle

#: The parts of a flower its mask holds (`Part`): what a labeller outlines as the flower.
MASK_PARTS = (Part.PETAL, Part.RECEPTACLE, Part.STAMEN)

#: The one category: COCO's id 1, YOLO's (and a trained model's) class 0.
CATEGORIES = [{"id": 1, "name": "flower", "supercategory": "plant"}]


@dataclass(frozen=True)
class DatasetConfig:
    """What `flowerpose dataset` writes (the world and the views: `EvalConfig`'s `sim`,
    `ground`, `grid` and `scan` settings)."""

    format: Literal["coco", "yolo"] = "coco"
    """COCO instances JSON (RLE masks) or YOLO polygon labels with data.yaml."""
    views: Literal["grid", "frames"] = "grid"
    """The grid views the detect stage sees, or the scan camera's frames."""
    val_fraction: float = 0.2
    """Share of the plants (at least one when above 0) in the val split; 0: train only."""
    split_seed: int = 0
    """Seed of the shuffle that chooses the val plants."""
    min_pixels: int = 20
    """A flower showing fewer pixels is no instance (it stays in the image): a sliver behind
    a leaf. 20 px is the detect stage's smallest component at 1 mm pixels (20 mm^2)."""
    frames_per_plant: int = 24
    """Frames of each plant's scan with `views="frames"`, evenly spaced along it."""

    def __post_init__(self):
        require(0 <= self.val_fraction < 1, "val_fraction", "must be 0 or more, below 1")
        require(self.min_pixels >= 1, "min_pixels", "must be at least 1")
        require(self.frames_per_plant >= 1, "frames_per_plant", "must be at least 1")


@dataclass(frozen=True)
class Sample:
    """One image and its flowers."""

    name: str
    """File name without suffix: seed-S_VIEW."""
    image: np.ndarray
    """(H, W, 3) uint8 RGB."""
    instance: np.ndarray
    """(H, W) int32: the plant.json id of the flower (its `MASK_PARTS`) at each pixel, -1
    for anything else."""


def split_plants(seeds: list[int], val_fraction: float, seed: int) -> dict[str, list[int]]:
    """The train and val plant seeds: a seeded shuffle, round(val_fraction x plants) of
    them (at least one when val_fraction > 0) to val; each list sorted."""
    count = len(seeds)
    val = 0 if val_fraction == 0 else max(1, int(round(val_fraction * count)))
    if val >= count:
        raise InputError("plants", f"{count} plant(s) leave none to train on with a val "
                         f"fraction of {val_fraction:g}: give more plants, or a val "
                         "fraction of 0")
    order = np.random.default_rng(seed).permutation(count)
    chosen = set(order[:val].tolist())
    return {"train": sorted(s for k, s in enumerate(seeds) if k not in chosen),
            "val": sorted(s for k, s in enumerate(seeds) if k in chosen)}


def grid_samples(bundle: PlantBundle, config: EvalConfig) -> list[Sample]:
    """The plant's grid views, as the detect stage makes them of its oracle cloud, with
    each pixel's flower: that of the cloud point owning it."""
    above, projections = grid_views(bundle.cloud, config)
    flower = np.where(np.isin(bundle.point_part[above], MASK_PARTS),
                      bundle.point_flower[above], -1).astype(np.int32)
    return [Sample(f"seed-{bundle.plant.seed}_{p.view.name}", p.image,
                   np.where(p.occupied, flower[p.index], -1)) for p in projections]


def frame_samples(bundle: PlantBundle, config: EvalConfig, count: int) -> list[Sample]:
    """`count` frames of the plant's planned scan, evenly spaced along it, as the scan
    camera records them at rest (`config.scan`: size, sensor, light), with each pixel's
    flower from the renderer's instance masks."""
    from flowerpose.hardware.backends.sim_bot import MujocoPoser
    from flowerpose.hardware.flights.scan_plan import plan_plant_scan
    from flowerpose.sim.camera import CameraConfig, intrinsics_from_config
    from flowerpose.sim.export import plant_obstacles
    from flowerpose.sim.render import Output, PlantRenderer
    from flowerpose.sim.sensor import apply_sensor

    plant, scan = bundle.plant, config.scan
    masked = dataclasses.replace(plant, face_flower=np.where(
        np.isin(plant.face_part, MASK_PARTS), plant.face_flower, -1).astype(np.int32))
    plan = plan_plant_scan(plant.center[:2], plant.height, plant_obstacles(plant),
                           config.sim.viewpoints)
    picked = np.unique(np.linspace(0, len(plan.waypoints) - 1, count).round().astype(int))
    intrinsics = intrinsics_from_config(CameraConfig(width=scan.camera.width,
                                                     height=scan.camera.height))
    poser = MujocoPoser()
    samples = []
    with PlantRenderer([masked], scan.camera.render) as renderer:
        for k in picked:
            waypoint = plan.waypoints[k]
            pose = poser.camera_to_bed(waypoint.pose.gantry, float(waypoint.pose.yaw),
                                       float(waypoint.pose.pitch))
            out = renderer.render(pose, intrinsics, Output.RGB | Output.INSTANCE)
            rgb, _ = apply_sensor(out.rgb, np.zeros(2), plan.config.pause_s, scan.camera.sensor,
                                  np.random.default_rng([plant.seed, int(k)]))
            samples.append(Sample(f"seed-{plant.seed}_frame-{k:03d}", rgb, out.instance))
    return samples


def flower_masks(instance: np.ndarray, min_pixels: int) -> list[tuple[int, np.ndarray]]:
    """(flower id, (H, W) bool full-image mask) of each flower with at least `min_pixels`
    pixels in an instance image ((H, W) int, -1 for none), by id."""
    ids, counts = np.unique(instance[instance >= 0], return_counts=True)
    return [(int(f), instance == f) for f in ids[counts >= min_pixels]]


def dataset_writes(dataset: DatasetConfig) -> tuple[str, ...]:
    """The top-level entries a dataset of this format writes in its folder."""
    formats = {"coco": ("annotations",), "yolo": ("labels", "data.yaml")}
    return ("dataset.json", "split.json", "images", *formats[dataset.format])


def write_dataset(config: EvalConfig, plants: PlantSet, dataset: DatasetConfig, out: Path,
                  overwrite: bool = False) -> dict:
    """Generate the seeded `plants` (`config.sim`'s world; kept in memory, their renders
    read straight from the scene), write their images and annotations into `out` in
    `dataset.format`, split by plant, with split.json and dataset.json; returns the
    manifest (dataset.json's content)."""
    from flowerpose.sim.bundle import make_plant  # trimesh: the [sim] extra

    if plants.real:
        raise InputError("source", "a dataset is made of synthetic plants, whose masks are "
                         "exact: not real folders")
    seeds = plants.seeds
    plant_records = []
    split = split_plants(seeds, dataset.val_fraction, dataset.split_seed)
    splits = [name for name in ("train", "val") if split[name]]
    of_seed = {s: name for name in splits for s in split[name]}
    output = OutputFolder(out, "dataset", overwrite, dataset_writes(dataset))
    output.record(*(out / name for name in dataset_writes(dataset)))
    suffix = ".png" if dataset.views == "grid" else ".jpg"
    params = [] if dataset.views == "grid" else [cv2.IMWRITE_JPEG_QUALITY, 95]
    images: dict[str, list[dict]] = {name: [] for name in splits}
    annotations: dict[str, list[dict]] = {name: [] for name in splits}
    instances = 0
    with Tally(len(seeds), "plants") as tally:
        for seed in seeds:
            bundle = make_plant(seed, config=config.sim)
            samples = (grid_samples(bundle, config) if dataset.views == "grid"
                       else frame_samples(bundle, config, dataset.frames_per_plant))
            name = of_seed[seed]
            seen: set[int] = set()
            for sample in samples:
                file = f"{sample.name}{suffix}"
                write_image(out / "images" / name / file, sample.image, params)
                masks = flower_masks(sample.instance, dataset.min_pixels)
                seen.update(f for f, _ in masks)
                instances += len(masks)
                if dataset.format == "yolo":
                    write_labels(out / "labels" / name / f"{sample.name}.txt",
                                 [label_line(0, mask) for _, mask in masks])
                    continue
                image_id = sum(len(v) for v in images.values()) + 1
                height, width = sample.instance.shape
                images[name].append({"id": image_id, "file_name": file, "width": width,
                                     "height": height, "plant_seed": seed})
                first = sum(len(v) for v in annotations.values()) + 1
                annotations[name] += [annotation(first + k, image_id, 1, mask, flower=f)
                                      for k, (f, mask) in enumerate(masks)]
            plant_records.append({"seed": seed, "split": name,
                                  "flowers": len(bundle.plant.flowers),
                                  "annotated_flowers": len(seen), "images": len(samples)})
            tally.finished(f"seed {seed}: {len(samples)} images, {len(seen)} of "
                           f"{len(bundle.plant.flowers)} flowers annotated")
    files = {}
    for name in splits:
        if dataset.format == "coco":
            files[name] = write_instances(
                out / "annotations" / f"instances_{name}.json", images[name],
                annotations[name], CATEGORIES, f"flowerpose dataset, {name} split")
        else:
            files[name] = out / "images" / name
    if dataset.format == "yolo":
        # Ultralytics needs a val split: with none, it validates on the training images.
        files["data.yaml"] = write_data_yaml(out / "data.yaml", {
            "train": "images/train", "val": f"images/{splits[-1]}"}, ["flower"])
    write_json(out / "split.json", {"seed": dataset.split_seed,
                                    "val_fraction": dataset.val_fraction, **split})
    manifest = {
        "run": run_record(), "format": dataset.format, "views": dataset.views,
        "preset": config.sim.plant.name, "seeds": seeds, "split": split,
        "images": sum(p["images"] for p in plant_records), "instances": instances,
        "categories": CATEGORIES,
        "mask": "a flower's petals, receptacle and stamens as seen; its sepals, buds, fruit, "
                "leaves and soil are background",
        "files": {k: str(Path(v).relative_to(out)) for k, v in files.items()},
        "plants": plant_records,
        "config": {"dataset": to_dict(dataset), "sim": to_dict(config.sim),
                   "ground": to_dict(config.ground), "grid": to_dict(config.grid),
                   **({"scan": {"width": config.scan.camera.width,
                                "height": config.scan.camera.height,
                                "sensor": to_dict(config.scan.camera.sensor),
                                "render": to_dict(config.scan.camera.render)}}
                      if dataset.views == "frames" else {})}}
    write_json(out / "dataset.json", manifest)
    output.finish()
    return manifest
