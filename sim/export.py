"""Writing a generated plant: truth (plant.json), mesh (plant.ply), labels, oracle cloud."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from flowerpose.cloudio import Cloud, write_cloud
from flowerpose.sim.plant import Plant


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


def write_plant(plant: Plant, out_dir: str | Path, cloud: Cloud | None = None,
                visible: np.ndarray | None = None,
                fraction: np.ndarray | None = None) -> dict[str, Path]:
    """Write plant.json, plant.ply (mesh with vertex colours), plant_labels.npz (face_part,
    face_flower) and, when given, cloud.ply into `out_dir`; returns the paths by name.

    visible, fraction: (n_flowers,) from `flower_visibility`, written per flower.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"truth": out / "plant.json", "mesh": out / "plant.ply",
             "labels": out / "plant_labels.npz"}
    paths["truth"].write_text(json.dumps(truth_dict(plant, visible, fraction), indent=1) + "\n")
    plant.mesh.export(paths["mesh"])
    np.savez_compressed(paths["labels"], face_part=plant.face_part, face_flower=plant.face_flower)
    if cloud is not None:
        paths["cloud"] = write_cloud(out / "cloud.ply", cloud)
    return paths
