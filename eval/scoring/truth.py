"""Ground-truth flower poses: the generator's plant.json, or hand labels from SageMaker.

Centres are in metres and normals are unit vectors, both in the frame of the scored cloud
(the bed frame for plant.json). A normal points from the flower centre along the axis the
corolla opens toward (away from the peduncle).
"""

from __future__ import annotations

import json
import math
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from scipy.spatial.transform import Rotation

from flowerpose.errors import InputError
from flowerpose.jsonio import object_list, read_json, read_text, unit3, vector3
from flowerpose.log import LOG

EulerConvention = Literal["upstream", "sagemaker"]


@dataclass
class TruthFlower:
    """One true flower pose.

    center: (3,) float64, metres. normal: (3,) float64, unit. radius: corolla radius in
    metres, or None when the source has none. visible: whether the flower counts as seen
    from the scan's viewpoints (DESIGN.md); hand labels are all visible.
    """

    id: int | str
    center: np.ndarray
    normal: np.ndarray
    radius: float | None = None
    visible: bool = True


def read_plant_truth(path: str | Path) -> list[TruthFlower]:
    """The flowers of a generator's plant.json (DESIGN.md): centres and normals, bed frame.

    A flower without "visible" counts as visible; normals are normalised. Raises
    InputError naming the file for a missing or invalid file or a malformed flower.
    """
    path = Path(path)
    truth = []
    for i, entry in enumerate(object_list(read_json(path), "flowers", path, "flower")):
        where = f"flower {i}"
        radius = entry.get("radius")
        if radius is not None and (not isinstance(radius, int | float)
                                   or not math.isfinite(radius)):
            raise InputError(path, f'{where}: "radius" must be a finite number or null')
        visible = entry.get("visible", True)
        if not isinstance(visible, bool):
            raise InputError(path, f'{where}: "visible" must be true or false')
        truth.append(TruthFlower(
            id=entry.get("id", i),
            center=vector3(entry.get("center"), path, f'{where}: "center"'),
            normal=unit3(vector3(entry.get("normal"), path, f'{where}: "normal"'), path,
                         f'{where}: "normal"'),
            radius=None if radius is None else float(radius),
            visible=visible))
    ids = [t.id for t in truth]
    repeated = next((i for i in ids if ids.count(i) > 1), None)
    if repeated is not None:
        raise InputError(path, f"flower id {repeated!r} is given {ids.count(repeated)} times: "
                         "each flower needs an id of its own")
    units = read_json(path).get("units", "m")
    if units not in ("m", "mm"):
        raise InputError(path, f'"units" must be "m" or "mm", got {units!r}')
    if units == "mm":
        for flower in truth:
            flower.center = flower.center * 1e-3
            flower.radius = None if flower.radius is None else flower.radius * 1e-3
    return truth


def as_labelled(truth: list[TruthFlower], mean_error_deg: float,
                seed: str) -> list[TruthFlower]:
    """The truth with each normal tilted as a hand label's: toward a random direction, by
    an angle with the given mean (Rayleigh, as the angle of an isotropic Gaussian tilt),
    seeded by `seed` (the plant's name) and the flower's position in the list."""
    import zlib

    sigma = math.radians(mean_error_deg) / math.sqrt(math.pi / 2)
    labelled = []
    for k, flower in enumerate(truth):
        rng = np.random.default_rng([zlib.crc32(seed.encode()), k])
        tilt = rng.normal(0.0, sigma, 2)
        side = np.cross(flower.normal, [1.0, 0.0, 0.0])
        if np.linalg.norm(side) < 0.1:
            side = np.cross(flower.normal, [0.0, 1.0, 0.0])
        side /= np.linalg.norm(side)
        other = np.cross(flower.normal, side)
        rotation = Rotation.from_rotvec(tilt[0] * side + tilt[1] * other)
        labelled.append(TruthFlower(flower.id, flower.center, rotation.apply(flower.normal),
                                    flower.radius, flower.visible))
    return labelled


def _json_documents(text: str, path: Path) -> list[Any]:
    """One JSON document, or JSON lines (one document a line, as SageMaker manifests)."""
    try:
        return [json.loads(text)]
    except json.JSONDecodeError as whole:
        documents = []
        for n, line in enumerate(text.splitlines(), 1):
            if not line.strip():
                continue
            try:
                documents.append(json.loads(line))
            except json.JSONDecodeError as err:
                if not documents:
                    raise InputError(path, f"not valid JSON ({whole.msg}, line {whole.lineno})") \
                        from None
                raise InputError(path, f"not valid JSON lines (line {n}: {err.msg})") from None
        if not documents:
            raise InputError(path, f"not valid JSON ({whole.msg}, line {whole.lineno})") \
                from None
        return documents


def _cuboid_lists(value: Any) -> list[list[Any]]:
    """Every list held under a "boundingCuboids" key, at any depth of nested dicts and lists."""
    found = []
    if isinstance(value, dict):
        for key, item in value.items():
            if key == "boundingCuboids" and isinstance(item, list):
                found.append(item)
            else:
                found.extend(_cuboid_lists(item))
    elif isinstance(value, list):
        for item in value:
            found.extend(_cuboid_lists(item))
    return found


def is_sagemaker(data: Any) -> bool:
    """Whether a JSON document holds SageMaker Ground Truth cuboids ("boundingCuboids")."""
    return bool(_cuboid_lists(data))


def vector_list(value: Any, source: str | Path, key: str) -> np.ndarray:
    """A JSON list of 3-vectors as (K, 3) float64; errors name `source` and `key`."""
    if not isinstance(value, list):
        raise InputError(source, f'"{key}" must be a list of [x, y, z] points')
    return np.array([vector3(v, source, f"{key}[{k}]") for k, v in enumerate(value)],
                    dtype=np.float64).reshape(-1, 3)


def sagemaker_normal(roll: float, pitch: float, yaw: float,
                     convention: EulerConvention = "upstream") -> np.ndarray:
    """The unit normal of a labelled cuboid: its local x axis, in the cloud's frame.

    roll, pitch, yaw: radians. "upstream" is the authors' code: intrinsic rotations about
    x, then y', then z'' by roll, pitch, yaw; their 7.7 degree plane error says it matches
    their labels. "sagemaker" is the order the SageMaker documentation gives for its
    labelling tool: yaw about z, then pitch about y', then roll about x''. The two agree
    for yaw-only cuboids; on the authors' first plant they differ by 1 to 119 degrees.
    """
    if convention == "sagemaker":
        rotation = Rotation.from_euler("ZYX", [yaw, pitch, roll])
    else:
        rotation = Rotation.from_euler("XYZ", [roll, pitch, yaw])
    return rotation.apply([1.0, 0.0, 0.0])


_CUBOID_KEYS = ("centerX", "centerY", "centerZ", "roll", "pitch", "yaw")


def _cuboid_radius(cuboid: dict, scale: float) -> float | None:
    """Half the larger of a cuboid's extents across its x axis (the normal), metres."""
    across = [cuboid.get(key) for key in ("width", "height")]
    if not all(isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
               and v > 0 for v in across):
        return None
    return 0.5 * max(across) / scale


#: The SageMaker label a flower's cuboid carries (the authors' category).
FLOWER_CATEGORY = "flower"


def _flower_cuboids(cuboids: list, path: Path) -> list:
    """The cuboids labelled as flowers (or with no label): others (buds, fruit) are left
    out and named in one line; none at all is refused."""
    def category(cuboid) -> str:
        label = cuboid.get("label") if isinstance(cuboid, dict) else None
        return FLOWER_CATEGORY if label is None else str(label)

    kept = [c for c in cuboids if category(c).lower() == FLOWER_CATEGORY]
    others = Counter(category(c) for c in cuboids if category(c).lower() != FLOWER_CATEGORY)
    if not kept:
        raise InputError(path, f"no cuboid is labelled Flower (labels: "
                         f"{', '.join(f'{k} ({n})' for k, n in others.most_common())})")
    if others:
        LOG.warning(f"note: {path}: {len(kept)} Flower cuboids scored; left out "
                    + ", ".join(f"{n} labelled {k}" for k, n in others.most_common()))
    return kept


def read_sagemaker_truth(path: str | Path, scale: float = 25.0,
                         convention: EulerConvention = "upstream") -> list[TruthFlower]:
    """Flower poses from AWS SageMaker Ground Truth 3D point cloud cuboid labels.

    The labels sit at answers[].answerContent.boundingCuboids.boundingCuboids[] (a worker
    response) with centerX/Y/Z and roll/pitch/yaw in radians; any "boundingCuboids" list in
    the file is read, from one JSON document or JSON lines. The cloud was scaled by `scale`
    for labelling, so centres are divided by it (metres); the normal is the cuboid's x
    axis (`sagemaker_normal`); the radius is half the cuboid's larger extent across it
    (width, height: the corolla's span), None where the cuboid has no size. Every flower is
    visible (`real_source.real_truth` decides what the cloud holds).
    Raises InputError naming the file for a missing file, invalid JSON, no cuboids or a
    cuboid with a missing or non-finite value.
    """
    path = Path(path)
    if not (isinstance(scale, int | float) and math.isfinite(scale) and scale > 0):
        raise InputError(path, f"the truth scale must be a positive number, got {scale!r}")
    cuboids = [c for document in _json_documents(read_text(path), path)
               for found in _cuboid_lists(document) for c in found]
    if not cuboids:
        raise InputError(path, 'no "boundingCuboids" labels found')
    cuboids = _flower_cuboids(cuboids, path)
    truth = []
    for i, cuboid in enumerate(cuboids):
        name = cuboid.get("objectName", i) if isinstance(cuboid, dict) else i
        values = [cuboid.get(key) if isinstance(cuboid, dict) else None for key in _CUBOID_KEYS]
        bad = [key for key, value in zip(_CUBOID_KEYS, values, strict=True)
               if not isinstance(value, int | float) or isinstance(value, bool)
               or not math.isfinite(value)]
        if bad:
            raise InputError(path, f"cuboid {name!r}: missing or non-finite {', '.join(bad)}")
        turned = max(abs(v) for v in values[3:])
        if turned > 2 * math.pi + 1e-6:
            raise InputError(path, f"cuboid {name!r}: an angle of {turned:.4g} is beyond a "
                             "rotation's range in radians (2 pi): degrees? SageMaker's roll, "
                             "pitch and yaw are radians; convert them with math.radians")
        center = np.array(values[:3], dtype=np.float64) / scale
        truth.append(TruthFlower(id=name, center=center,
                                 normal=sagemaker_normal(*values[3:], convention=convention),
                                 radius=_cuboid_radius(cuboid, scale)))
    seen: dict[tuple, str] = {}
    for cuboid, flower in zip(cuboids, truth, strict=True):
        whole = tuple(cuboid.get(key) for key in _CUBOID_KEYS)
        for key in ("length", "width", "height"):
            whole += (cuboid.get(key),)
        if whole in seen:
            raise InputError(path, f"cuboids {seen[whole]!r} and {flower.id!r} are the same "
                             "cuboid (centre, size and angles): a label given twice")
        seen[whole] = flower.id
    return truth
