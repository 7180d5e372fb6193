"""The project's own label file: a real plant's flowers as a person labelled them.

    {"format": "flowerpose-labels", "version": 1,
     "truth_scale": 1,            labels are the cloud's coordinates times this
     "flowers": [{"id": 0, "center": [x, y, z], "normal": [nx, ny, nz] or null,
                  "state": "labelled" | "unlabelled" | "rejected",
                  "labeller": "ana", "time": "2026-12-05T10:00:00+00:00"}, ...],
     "sessions": [{"labeller": ..., "started": ..., "saved": ..., "seconds": ...,
                   "actions": {"accept": 3, ...}}, ...]}

A "labelled" flower has a centre and a unit normal (the direction its face looks, away
from the plant); an "unlabelled" one is a flower that is there but whose pose cannot be
told (the paper's "No. Extra": a detection on it counts as extra, not as a false
positive); a "rejected" one is a detection the labeller said is not a flower (kept so the
file says what was looked at; never scored). Coordinates are the cloud's own, in its unit,
times `truth_scale`. `write_labels` keeps the file it replaces as labels.json.N.bak (the
first free N), so no save loses an earlier one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from flowerpose.atomic import write_bytes
from flowerpose.errors import InputError
from flowerpose.eval.scoring.truth import TruthFlower
from flowerpose.jsonio import object_list, read_json, unit3, vector3, write_json

LABEL_FORMAT = "flowerpose-labels"
State = Literal["labelled", "unlabelled", "rejected"]
STATES: tuple[State, ...] = ("labelled", "unlabelled", "rejected")


@dataclass
class Label:
    """One flower as labelled: centre and normal in the cloud's coordinates times the
    file's truth scale; normal None unless "labelled"."""

    id: int | str
    center: np.ndarray
    normal: np.ndarray | None
    state: State = "labelled"
    labeller: str = ""
    time: str = ""


@dataclass
class LabelFile:
    """A labels.json of this format."""

    flowers: list[Label]
    truth_scale: float = 1.0
    sessions: list[dict[str, Any]] = field(default_factory=list)

    def labelled(self) -> list[TruthFlower]:
        """The labelled flowers as truth, in label units."""
        return [TruthFlower(f.id, f.center, f.normal) for f in self.flowers
                if f.state == "labelled" and f.normal is not None]

    def unlabelled(self) -> np.ndarray:
        """(K, 3) centres of the flowers that are there without a pose, label units."""
        return np.array([f.center for f in self.flowers if f.state == "unlabelled"],
                        float).reshape(-1, 3)


def is_label_file(data: Any) -> bool:
    """Whether parsed JSON is this project's label file."""
    return isinstance(data, dict) and data.get("format") == LABEL_FORMAT


#: The keys a label file and each of its flowers may have: another (a "units" written by
#: hand, say) is refused, never silently ignored.
FILE_KEYS = {"format", "version", "truth_scale", "flowers", "sessions"}
FLOWER_KEYS = {"id", "center", "normal", "state", "labeller", "time"}


def read_labels(path: str | Path) -> LabelFile:
    """A label file, checked (`parse_labels`)."""
    path = Path(path)
    return parse_labels(read_json(path), path)


def parse_labels(data: Any, path: Path) -> LabelFile:
    """A label file's parsed JSON, checked; InputError naming the file and the flower for
    anything malformed (a key the format has not, a labelled flower without a normal, an
    unknown state, ids given twice)."""
    if not is_label_file(data):
        raise InputError(path, f'not a flowerpose label file ("format": "{LABEL_FORMAT}")')
    if data.get("version") != 1:
        raise InputError(path, f"label file version {data.get('version')!r}: this flowerpose "
                         "reads version 1")
    unknown = sorted(set(data) - FILE_KEYS)
    if unknown:
        raise InputError(path, f"unknown key {unknown[0]!r} (a label file has "
                         f"{', '.join(sorted(FILE_KEYS))}; coordinates are the cloud's own, "
                         "in its unit, times truth_scale)")
    scale = data.get("truth_scale", 1.0)
    if (isinstance(scale, bool) or not isinstance(scale, int | float)
            or not math.isfinite(scale) or scale <= 0):
        raise InputError(path, f'"truth_scale" must be a positive number, got {scale!r}')
    flowers = []
    for k, entry in enumerate(object_list(data, "flowers", path, "flower")):
        where = f"flower {k}"
        unknown = sorted(set(entry) - FLOWER_KEYS)
        if unknown:
            raise InputError(path, f"{where}: unknown key {unknown[0]!r} (a flower has "
                             f"{', '.join(sorted(FLOWER_KEYS))})")
        state = entry.get("state", "labelled")
        if state not in STATES:
            raise InputError(path, f'{where}: "state" must be one of {", ".join(STATES)}, '
                             f"got {state!r}")
        normal = entry.get("normal")
        if state == "labelled" and normal is None:
            raise InputError(path, f'{where}: a labelled flower needs a "normal"')
        flowers.append(Label(
            id=entry.get("id", k),
            center=vector3(entry.get("center"), path, f'{where}: "center"'),
            normal=None if normal is None else unit3(
                vector3(normal, path, f'{where}: "normal"'), path, f'{where}: "normal"'),
            state=state, labeller=str(entry.get("labeller", "")),
            time=str(entry.get("time", ""))))
    ids = [f.id for f in flowers]
    repeated = next((i for i in ids if ids.count(i) > 1), None)
    if repeated is not None:
        raise InputError(path, f"flower id {repeated!r} is given {ids.count(repeated)} times")
    sessions = data.get("sessions", [])
    if not isinstance(sessions, list):
        raise InputError(path, '"sessions" must be a list')
    return LabelFile(flowers, float(scale), sessions)


def labels_document(labels: LabelFile) -> dict[str, Any]:
    """labels.json's content."""
    return {"format": LABEL_FORMAT, "version": 1, "truth_scale": labels.truth_scale,
            "flowers": [{"id": f.id, "center": [float(v) for v in f.center],
                         "normal": None if f.normal is None else [float(v) for v in f.normal],
                         "state": f.state, "labeller": f.labeller, "time": f.time}
                        for f in labels.flowers],
            "sessions": labels.sessions}


def write_labels(path: str | Path, labels: LabelFile) -> Path | None:
    """Write a label file atomically; an earlier file there is first copied whole to
    PATH.N.bak (the first N free), so no save loses one. Returns that backup's path (None
    where there was no earlier file). What would not read back (ids given twice, a zero
    normal) is refused before anything is written: InputError."""
    path = Path(path)
    document = labels_document(labels)
    parse_labels(document, path)
    backup = None
    if path.exists():
        n = 1
        while path.with_name(f"{path.name}.{n}.bak").exists():
            n += 1
        backup = write_bytes(path.with_name(f"{path.name}.{n}.bak"), path.read_bytes())
    write_json(path, document)
    return backup
