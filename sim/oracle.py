"""The oracle cloud: the coloured points a flawless photogrammetry run would give of a plant."""

from __future__ import annotations

import cv2
import numpy as np
import trimesh

from flowerpose.cloudio import Cloud
from flowerpose.perturb import smooth_noise
from flowerpose.sim.pieces import Part
from flowerpose.sim.plant import Plant
from flowerpose.sim.raycast import make_scene, seen_from_any
from flowerpose.sim.world_config import OracleCloudConfig

#: First draw is this many times the requested count (hidden points are dropped).
OVERSAMPLE = 1.5


#: Parts whose colours the photogrammetry texture pales (`OracleCloudConfig.foliage_*`).
FOLIAGE = (Part.LEAF, Part.PETIOLE, Part.PEDUNCLE, Part.SEPAL, Part.BUD, Part.CROWN)
#: The foliage whose hue moves by `OracleCloudConfig.stalk_hue_shift_deg`.
STALKS = (Part.PETIOLE, Part.PEDUNCLE, Part.SEPAL)


#: The sky's pale grey that sheen on leaves blends toward, 8-bit RGB.
SHEEN_RGB = np.array([205.0, 210.0, 218.0])


def _pale(colors: np.ndarray, hue_shift_deg: np.ndarray | float,
          config: OracleCloudConfig) -> np.ndarray:
    """(N, 3) uint8 colours with their saturation and value scaled and hue shifted (degrees,
    one for all or (N,))."""
    from flowerpose.sim.plant_colours import hsv_to_rgb

    hsv = cv2.cvtColor(colors.reshape(-1, 1, 3).astype(np.float32) / 255.0,
                       cv2.COLOR_RGB2HSV).reshape(-1, 3).astype(np.float64)
    hsv[:, 0] += hue_shift_deg
    hsv[:, 1] = np.clip(hsv[:, 1] * config.foliage_saturation, 0.0, 1.0)
    hsv[:, 2] = np.clip(hsv[:, 2] * config.foliage_value, 0.0, 1.0)
    return np.clip(np.rint(hsv_to_rgb(hsv) * 255.0), 0, 255).astype(np.uint8)


def spread_subset(viewpoints: np.ndarray, count: int) -> np.ndarray:
    """At most `count` of `viewpoints` ((V, 3)), evenly along the path, in an order that
    covers the scan early (golden-ratio interleaving)."""
    if len(viewpoints) > count:
        viewpoints = viewpoints[np.unique(np.linspace(0, len(viewpoints) - 1, count).round()
                                          .astype(int))]
    order = np.argsort((np.arange(len(viewpoints)) * 0.6180339887) % 1.0, kind="stable")
    return viewpoints[order]


def sample_oracle_cloud(plant: Plant, config: OracleCloudConfig, viewpoints: np.ndarray,
                        rng: np.random.Generator) -> tuple[Cloud, np.ndarray, np.ndarray]:
    """Sample the plant's surfaces as a coloured cloud of exactly `config.points` points.

    viewpoints: (V, 3) camera positions, metres, bed frame (used when `visible_only`).
    Points are area-weighted (soil at `soil_density`), coloured by barycentric
    interpolation of vertex colours, shaded (two-sided Lambert) and jittered. Returns the
    cloud (bed frame, metres, uint8 RGB), point_part (N,) int8 `Part` and point_flower (N,)
    int32 flower id or -1, both taken from the face each point was sampled on.
    """
    mesh = plant.mesh
    weights = mesh.area_faces * np.where(plant.face_part == Part.SOIL, config.soil_density, 1.0)
    scene = make_scene(mesh.vertices, mesh.faces) if config.visible_only else None
    views = spread_subset(np.asarray(viewpoints, np.float64), config.max_viewpoints)

    points, faces, bary = [], [], []
    kept, rate = 0, 1.0
    while kept < config.points:
        draw = int(np.ceil((config.points - kept) * OVERSAMPLE / max(rate, 0.05)))
        p, f, b = trimesh.sample.sample_surface(mesh, draw, face_weight=weights,
                                                return_barycentric=True, seed=rng)
        if scene is not None:
            seen = seen_from_any(scene, p, views, config.visibility_tolerance_m)
            if not seen.any():
                raise ValueError("no surface of the plant is seen from the viewpoints")
            p, f, b = p[seen], f[seen], b[seen]
            rate = max(seen.mean(), 1e-3)
        points.append(p)
        faces.append(f)
        bary.append(b)
        kept += len(p)
    points, faces, bary = np.concatenate(points), np.concatenate(faces), np.concatenate(bary)
    chosen = np.sort(rng.choice(len(points), config.points, replace=False))
    points, faces, bary = points[chosen], faces[chosen], bary[chosen]

    corner_colors = mesh.visual.vertex_colors[mesh.faces[faces], :3].astype(np.float64) / 255.0
    rgb = np.einsum("nk,nkc->nc", bary, corner_colors)
    light = np.asarray(config.light_direction, np.float64)
    light /= np.linalg.norm(light)
    facing = np.abs(mesh.face_normals[faces] @ light)
    rgb = rgb * (1.0 - config.shading * (1.0 - facing))[:, None]
    rgb = rgb + rng.normal(0.0, config.color_jitter, rgb.shape)
    colors = np.clip(np.rint(rgb * 255.0), 0, 255).astype(np.uint8)
    foliage = np.isin(plant.face_part[faces], FOLIAGE)
    stalk_shift = (config.foliage_hue_shift_deg if config.stalk_hue_shift_deg is None
                   else config.stalk_hue_shift_deg)
    if foliage.any() and (config.foliage_saturation, config.foliage_value,
                          config.foliage_hue_shift_deg, stalk_shift) != (1.0, 1.0, 0.0, 0.0):
        stalk = np.isin(plant.face_part[faces[foliage]], STALKS)
        colors[foliage] = _pale(colors[foliage], np.where(
            stalk, stalk_shift, config.foliage_hue_shift_deg), config)
    if config.foliage_sheen > 0:
        sheened = foliage & (rng.random(len(colors)) < config.foliage_sheen)
        weight = rng.random(int(sheened.sum()))[:, None]
        colors[sheened] = np.rint((1.0 - weight) * colors[sheened] + weight * SHEEN_RGB
                                  ).astype(np.uint8)
    if config.position_noise_m > 0 and config.position_noise_wavelength_m > 0:
        points = points + smooth_noise(points, config.position_noise_m,
                                       config.position_noise_wavelength_m, rng)
    elif config.position_noise_m > 0:
        points = points + rng.normal(0.0, config.position_noise_m, points.shape)
    return Cloud(points, colors), plant.face_part[faces].copy(), plant.face_flower[faces].copy()
