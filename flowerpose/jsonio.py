"""JSON files the project reads and writes: checked reading, atomic writing, and validation
of the vectors they hold. Every error names the file and what is wrong."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from flowerpose.atomic import write_text
from flowerpose.errors import InputError


def read_text(path: str | Path) -> str:
    """A UTF-8 text file's content; errors name the file."""
    path = Path(path)
    if not path.exists():
        raise InputError(path, "file not found")
    if not path.is_file():
        raise InputError(path, "not a file")
    try:
        return path.read_text(encoding="utf-8")
    except OSError as err:
        raise InputError(path, f"cannot read ({err.strerror})") from None
    except UnicodeDecodeError:
        raise InputError(path, "not a UTF-8 text file") from None


def read_json(path: str | Path) -> dict:
    """A JSON object from a file; errors name the file. NaN and Infinity are refused:
    they are not JSON (strict readers reject them, and `write_json` never writes them), and
    a number that is none would print as "nan" in a report."""
    def refuse(constant: str) -> None:
        raise InputError(path, f"holds {constant}, which is not a JSON number: every number "
                         "must be finite")

    try:
        data = json.loads(read_text(path), parse_constant=refuse)
    except json.JSONDecodeError as err:
        raise InputError(path, f"not valid JSON ({err.msg} at line {err.lineno})") from None
    if not isinstance(data, dict):
        raise InputError(path, "expected a JSON object")
    return data


def write_json(path: str | Path, data: dict) -> Path:
    """Write JSON whole (`atomic.write_text`); NaN is refused, since strict JSON readers
    reject it."""
    return write_text(path, json.dumps(data, indent=1, allow_nan=False))


def vector3(value: Any, source: str | Path, where: str) -> np.ndarray:
    """Three finite numbers (not booleans) as a (3,) float64 array, or an InputError naming
    `source` and `where`."""
    numbers = value if isinstance(value, list | tuple) else None
    if (numbers is None or len(numbers) != 3
            or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in numbers)
            or not all(math.isfinite(v) for v in numbers)):
        raise InputError(source, f"{where} must be 3 finite numbers, got {value!r}")
    return np.array(numbers, dtype=np.float64)


def unit3(vector: np.ndarray, source: str | Path, where: str) -> np.ndarray:
    """`vector` normalised; InputError for the zero vector."""
    norm = float(np.linalg.norm(vector))
    if norm < 1e-9:
        raise InputError(source, f"{where} is the zero vector")
    return vector / norm


def object_list(data: dict, key: str, source: str | Path, item: str) -> list[dict]:
    """data[key] as a list of JSON objects, or an InputError naming `source` and the
    offending entry (`item` names one: "flower", "frame")."""
    entries = data.get(key)
    if not isinstance(entries, list):
        raise InputError(source, f'expected a JSON object with a "{key}" list')
    for k, entry in enumerate(entries):
        if not isinstance(entry, dict):
            raise InputError(source, f"{item} {k} is not a JSON object")
    return entries
