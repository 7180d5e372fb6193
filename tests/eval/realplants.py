"""Small real-plant folders in the documented format, written by the tests themselves: disc
flowers with known centres and normals, labelled as SageMaker Ground Truth cuboids (the
authors' Euler convention and x25 scale), as candidates, crops or a whole cloud."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from flowerpose.cloudio import Cloud, write_cloud

WHITE, YELLOW, GREEN, LEAF = (240, 242, 236), (232, 200, 45), (70, 130, 50), (55, 95, 40)
#: Flower centres (metres) and normals of the test plant: facing up, sideways, tilted.
CENTRES = np.array([[0.00, 0.00, 0.30], [0.09, 0.01, 0.27], [-0.05, 0.08, 0.33],
                    [0.03, -0.09, 0.25]])
NORMALS = np.array([[0.1, 0.05, 1.0], [0.8, 0.1, 0.3], [-0.3, 0.6, 0.7], [0.2, -0.9, 0.1]])
NORMALS = NORMALS / np.linalg.norm(NORMALS, axis=1, keepdims=True)
SCALE = 25.0


def flower(centre: np.ndarray, normal: np.ndarray, rng: np.random.Generator,
           radius: float = 0.02, spacing: float = 0.0012) -> Cloud:
    """A corolla of white petals round a yellow dome, green sepals behind and a leaf patch
    further behind, about `spacing` metres apart, facing `normal`."""
    frame = Rotation.align_vectors([normal], [[0.0, 0.0, 1.0]])[0]
    count = int(np.pi * radius ** 2 / spacing ** 2)
    r = radius * np.sqrt(rng.uniform(0.04, 1.0, count))
    theta = rng.uniform(0, 2 * np.pi, count)
    petals = np.column_stack([r * np.cos(theta), r * np.sin(theta), 0.1 * r ** 2 / radius])
    dome_r = 0.2 * radius * np.sqrt(rng.uniform(0, 1, count // 20))
    dome_t = rng.uniform(0, 2 * np.pi, len(dome_r))
    dome = np.column_stack([dome_r * np.cos(dome_t), dome_r * np.sin(dome_t),
                            0.12 * radius * (1 - (dome_r / (0.2 * radius)) ** 2)])
    sepal_r = rng.uniform(0.1, 0.35, count // 25) * radius
    sepal_t = rng.uniform(0, 2 * np.pi, len(sepal_r))
    sepals = np.column_stack([sepal_r * np.cos(sepal_t), sepal_r * np.sin(sepal_t),
                              np.full(len(sepal_r), -0.1 * radius)])
    leaf = np.column_stack([rng.uniform(-radius, radius, (count // 3, 2)),
                            np.full(count // 3, -0.6 * radius)])
    local = np.vstack([petals, dome, sepals, leaf])
    local += rng.normal(0, 2e-4, local.shape)
    colours = np.array([WHITE] * len(petals) + [YELLOW] * len(dome) + [GREEN] * len(sepals)
                       + [LEAF] * len(leaf), np.uint8)
    return Cloud(frame.apply(local) + centre, colours)


def cuboids(centres: np.ndarray, normals: np.ndarray, scale: float = SCALE) -> dict:
    """SageMaker Ground Truth 3D cuboid labels whose x axis is each normal, in the authors'
    convention (Rotation.from_euler("XYZ", [roll, pitch, yaw]).apply([1, 0, 0])), on a
    cloud scaled by `scale`."""
    labels = []
    for k, (centre, normal) in enumerate(zip(centres, normals, strict=True)):
        # Any roll about the cuboid's own x axis keeps the normal: 0.4 exercises all three.
        turn = Rotation.align_vectors([normal], [[1.0, 0.0, 0.0]])[0] * Rotation.from_euler(
            "x", 0.4)
        roll, pitch, yaw = turn.as_euler("XYZ")
        labels.append({"centerX": centre[0] * scale, "centerY": centre[1] * scale,
                       "centerZ": centre[2] * scale, "length": 1.2, "width": 1.2,
                       "height": 1.2, "label": "Flower", "labelCategoryAttributes": {},
                       "objectName": f"Flower:{k + 1}", "roll": roll, "pitch": pitch,
                       "yaw": yaw})
    return {"answers": [{"answerContent": {"boundingCuboids": {"boundingCuboids": labels}}}]}


def write_real_plant(folder: Path, stage: str, seed: int = 0, labelled: int | None = None,
                     source: dict | None = None) -> Path:
    """A labelled real-plant folder of the CENTRES/NORMALS flowers at `stage` ("cloud",
    "candidates" or "crops"); only the first `labelled` flowers get a label."""
    rng = np.random.default_rng(seed)
    flowers = [flower(c, n, rng) for c, n in zip(CENTRES, NORMALS, strict=True)]
    folder.mkdir(parents=True, exist_ok=True)
    count = len(CENTRES) if labelled is None else labelled
    (folder / "labels.json").write_text(json.dumps(cuboids(CENTRES[:count], NORMALS[:count])))
    if source is not None:
        (folder / "source.json").write_text(json.dumps(source))
    if stage == "crops":
        for k, f in enumerate(flowers):
            write_cloud(folder / "crops" / f"flower_{k}.ply", f)
    elif stage == "candidates":
        # Two views' detections, each with some of the flowers (one flower in both), and a
        # leaf the first view's detector took for a flower.
        leaf = Cloud(np.column_stack([rng.uniform(0.12, 0.18, (800, 2)),
                                      rng.normal(0.2, 0.001, 800)]),
                     np.tile(np.array(LEAF, np.uint8), (800, 1)))
        for view, picked in enumerate(([0, 1, 2], [2, 3])):
            parts = [flowers[k] for k in picked] + ([leaf] if view == 0 else [])
            write_cloud(folder / "candidates" / f"pcd_{view}.ply",
                        Cloud(np.vstack([p.points for p in parts]),
                              np.vstack([p.colors for p in parts])))
    else:
        soil = np.column_stack([rng.uniform(-0.2, 0.2, (6000, 2)), rng.normal(0, 0.001, 6000)])
        write_cloud(folder / "cloud.ply",
                    Cloud(np.vstack([soil] + [f.points for f in flowers]),
                          np.vstack([np.full((len(soil), 3), (90, 70, 50), np.uint8)]
                                    + [f.colors for f in flowers])))
    return folder
