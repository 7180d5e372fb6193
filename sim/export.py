"""Writing and reading a generated plant: truth (plant.json), mesh (plant.ply), labels,
oracle cloud."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import trimesh

from flowerpose.atomic import write_file, write_text
from flowerpose.cloudio import Cloud, write_cloud
from flowerpose.config import DEFAULT_PRESET
from flowerpose.errors import InputError
from flowerpose.jsonio import read_json
from flowerpose.sim.plant import FlowerTruth, Plant
from flowerpose.sim.world_config import preset


def truth_dict(plant: Plant, visible: np.ndarray | None = None,
               fraction: np.ndarray | None = None) -> dict:
    """plant.json's content: DESIGN.md's truth format plus visibility and plant facts."""
    flowers = []
    for f in plant.flowers:
        entry = {"id": f.id, "center": [float(v) for v in f.center],
                 "normal": [float(v) for v in f.normal], "radius": float(f.radius),
                 "petals": int(f.petals), "stage": f.stage}
        if visible is not None:
            entry["visible"] = bool(visible[f.id])
        if fraction is not None:
            entry["visible_fraction"] = float(fraction[f.id])
        flowers.append(entry)
    return {"seed": int(plant.seed), "units": "m", "frame": "bed", "preset": plant.config.name,
            "plant_center": [float(v) for v in plant.center], "height": float(plant.height),
            "distractors": {"buds": int(plant.buds), "fruit": int(plant.fruit)},
            "flowers": flowers}


#: What `write_plant` writes into a plant folder (cloud.ply when given a cloud).
PLANT_FILES = ("plant.json", "plant.ply", "plant_labels.npz", "cloud.ply")


def write_plant(plant: Plant, out_dir: str | Path, cloud: Cloud | None = None,
                visible: np.ndarray | None = None,
                fraction: np.ndarray | None = None,
                degradation: dict | None = None) -> dict[str, Path]:
    """Write plant.json, plant.ply (mesh with vertex colours), plant_labels.npz (face_part,
    face_flower) and, when given, cloud.ply into `out_dir`; returns the paths by name.

    visible, fraction: (n_flowers,) from `flower_visibility`, written per flower;
    degradation: how cloud.ply was degraded (`sim/degrade.py`), written as plant.json's
    "degradation".
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"truth": out / "plant.json", "mesh": out / "plant.ply",
             "labels": out / "plant_labels.npz"}
    truth = truth_dict(plant, visible, fraction)
    if degradation:
        truth["degradation"] = degradation
    write_text(paths["truth"], json.dumps(truth, indent=1) + "\n")
    write_file(paths["mesh"], lambda tmp: plant.mesh.export(tmp))
    write_file(paths["labels"], lambda tmp: np.savez_compressed(
        tmp, face_part=plant.face_part, face_flower=plant.face_flower))
    if cloud is not None:
        paths["cloud"] = write_cloud(out / "cloud.ply", cloud)
    return paths


def read_plant(plant_dir: str | Path) -> Plant:
    """The plant a `write_plant` folder holds: mesh, face labels and truth, as a `Plant`.

    The config is the named preset's with the recorded crown position; generator settings
    beyond those are not stored, but nothing that reads a written plant needs them.
    """
    folder = Path(plant_dir)
    truth = read_json(folder / "plant.json")
    for name in ("plant.ply", "plant_labels.npz"):
        if not (folder / name).exists():
            raise InputError(folder / name, "missing: not a folder written by flowerpose plant")
    try:
        mesh = trimesh.load(folder / "plant.ply", process=False, force="mesh")
        labels = np.load(folder / "plant_labels.npz")
        face_part, face_flower = labels["face_part"], labels["face_flower"]
        flowers = [FlowerTruth(int(f["id"]), np.asarray(f["center"], float),
                               np.asarray(f["normal"], float), float(f["radius"]),
                               int(f["petals"]), str(f.get("stage", "open")))
                   for f in truth["flowers"]]
        center = truth["plant_center"]
        config = dataclasses.replace(preset(truth.get("preset", DEFAULT_PRESET)),
                                     center_xy_m=(float(center[0]), float(center[1])))
        seed, height = int(truth["seed"]), float(truth["height"])
        distractors = truth.get("distractors", {})
    except (KeyError, TypeError, ValueError, OSError) as err:
        raise InputError(folder, f"unreadable plant files ({err})") from None
    if len(face_part) != len(mesh.faces) or len(face_flower) != len(mesh.faces):
        raise InputError(folder / "plant_labels.npz", "labels do not match the mesh's faces")
    return Plant(mesh, face_part, face_flower, flowers, seed, config, height,
                 buds=int(distractors.get("buds", 0)), fruit=int(distractors.get("fruit", 0)))


def plant_obstacles(plant: Plant, points: int = 20_000, seed: int = 0) -> np.ndarray:
    """(N, 3) points on the plant's surfaces above the soil, bed frame, metres: what a scan
    path must keep clear of."""
    from flowerpose.sim.pieces import Part

    above = np.flatnonzero(plant.face_part != Part.SOIL)
    body = trimesh.Trimesh(plant.mesh.vertices, plant.mesh.faces[above], process=False)
    samples, _ = trimesh.sample.sample_surface(body, points, seed=seed)
    return np.asarray(samples)
