"""A tuning study's search space (`flowerpose tune --space SPACE.toml`) and its objectives.

SPACE.toml has one entry per dotted setting key:

    "cluster.eps" = { low = 0.006, high = 0.016, log = true }
    "cluster.min_points" = { low = 5, high = 40, int = true }
    "grid.views" = { choices = [6, 14] }

A range (`low` < `high`; `log` for a log scale, `int` for whole numbers, which a setting
of whole numbers needs) or a list of `choices`, each a value the setting takes. Every
entry is checked against the settings before any trial runs: an unknown key, an empty
range, a range on a setting that is not a number, a choice the setting refuses.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from flowerpose.config import apply_overrides, current_name, load_toml, value_at
from flowerpose.errors import InputError

#: Keys a space entry may have.
_ENTRY_KEYS = {"low", "high", "log", "int", "choices"}


@dataclass(frozen=True)
class Param:
    """One setting of the space: a range or a set of choices."""

    key: str
    low: float | None = None
    high: float | None = None
    log: bool = False
    integer: bool = False
    choices: tuple = ()

    def suggest(self, trial: Any) -> Any:
        """The trial's value of this setting (Optuna's suggest_*)."""
        if self.choices:
            return trial.suggest_categorical(self.key, list(self.choices))
        if self.integer:
            return trial.suggest_int(self.key, int(self.low), int(self.high), log=self.log)
        return trial.suggest_float(self.key, self.low, self.high, log=self.log)

    def to_json(self) -> dict:
        if self.choices:
            return {"choices": list(self.choices)}
        return {"low": self.low, "high": self.high, "log": self.log, "int": self.integer}


def read_space(path: Path, config: Any) -> list[Param]:
    """The space in SPACE.toml, checked against `config` (an EvalConfig); InputError naming
    the file and the key for anything a trial could not run with."""
    data = load_toml(path)
    if not data:
        raise InputError(path, "the space is empty: give at least one setting to search")
    params = []
    for raw_key, entry in _flat(data).items():
        key = current_name(raw_key)
        where = f"{path}: {key}"
        if not isinstance(entry, dict) or not entry or set(entry) - _ENTRY_KEYS:
            raise InputError(path, f"{key}: expected {{ low = ..., high = ... }} or "
                             f"{{ choices = [...] }}, got {entry!r}")
        try:
            current = value_at(config, key)
        except (InputError, AttributeError, KeyError):
            raise InputError(path, f"{key}: no such setting") from None
        if dataclasses.is_dataclass(current):
            raise InputError(path, f"{key}: is a section; search one of its settings")
        params.append(_param(key, entry, current, config, where))
    return params


def _flat(data: dict, prefix: str = "") -> dict[str, Any]:
    """TOML's nested tables as dotted keys, a table with entry keys being an entry."""
    flat: dict[str, Any] = {}
    for key, value in data.items():
        dotted = f"{prefix}{key}"
        if isinstance(value, dict) and value and not set(value) & _ENTRY_KEYS:
            flat.update(_flat(value, f"{dotted}."))
        else:
            flat[dotted] = value
    return flat


def _param(key: str, entry: dict, current: Any, config: Any, where: str) -> Param:
    if "choices" in entry:
        choices = entry["choices"]
        if set(entry) != {"choices"} or not isinstance(choices, list) or not choices:
            raise InputError(where, "choices must be a non-empty list, alone")
        for choice in choices:
            _check(config, key, choice, where)
        return Param(key, choices=tuple(choices))
    if not {"low", "high"} <= set(entry):
        raise InputError(where, "a range needs low and high")
    low, high = entry["low"], entry["high"]
    numbers = all(isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
                  for v in (low, high))
    kind = _number_kind(current)
    if kind is None:
        raise InputError(where, f"is not a number ({current!r}): give its choices instead")
    if not numbers:
        raise InputError(where, f"low and high must be numbers, got {low!r} and {high!r}")
    if not low < high:
        raise InputError(where, f"the range {low}-{high} is empty (low must be below high)")
    for flag in ("int", "log"):
        if flag in entry and not isinstance(entry[flag], bool):
            raise InputError(where, f"{flag} must be true or false (no quotes), got "
                             f"{entry[flag]!r}")
    integer = bool(entry.get("int", False))
    if kind is int and not integer:
        raise InputError(where, "is a whole number: add int = true")
    if integer and not (float(low).is_integer() and float(high).is_integer()):
        raise InputError(where, "int = true needs whole-number low and high")
    log = bool(entry.get("log", False))
    if log and low <= 0:
        raise InputError(where, "log = true needs a positive low")
    for value in (low, high):
        _check(config, key, int(value) if integer else float(value), where)
    return Param(key, float(low), float(high), log, integer)


def _number_kind(value: Any) -> type | None:
    if isinstance(value, bool):
        return None
    if isinstance(value, int):
        return int
    if isinstance(value, float):
        return float
    return None


def _check(config: Any, key: str, value: Any, where: str) -> None:
    try:
        apply_overrides(config, {key: value})
    except InputError as err:
        raise InputError(where, f"{value!r}: {err.problem}") from None


#: The value an objective takes when its score is missing (no flower found, no error).
MISSING = {"maximize": 0.0, "minimize": 180.0}


@dataclass(frozen=True)
class Objective:
    """A report summary key (dotted, as --require takes it) and its direction."""

    direction: str
    """"maximize" or "minimize"."""
    key: str

    @property
    def text(self) -> str:
        return f"{self.direction[:3]}:{self.key}"

    def value(self, summary: dict) -> float:
        """The summary's value of the key (MISSING's where there is none)."""
        from flowerpose.eval.reports.gates import summary_value

        measured = summary_value(summary, self.key)
        return MISSING[self.direction] if measured is None else float(measured)


def parse_objectives(texts: list[str], task: str = "pose") -> list[Objective]:
    """--objective max:KEY / min:KEY, checked against the summary's keys of a run of `task`
    (none: the task's own objectives, `tune_task.TASKS`)."""
    from flowerpose.eval.reports.gates import check_key
    from flowerpose.eval.studies.tune_task import TASKS

    objectives = []
    for text in texts or TASKS[task].objectives:
        direction, sep, key = text.partition(":")
        if not sep or direction not in ("max", "min"):
            raise InputError("--objective", f"{text!r}: expected max:KEY or min:KEY, e.g. "
                             "max:f1")
        check_key(key, "--objective", task=task)
        objectives.append(Objective("maximize" if direction == "max" else "minimize", key))
    if len({o.key for o in objectives}) < len(objectives):
        raise InputError("--objective", "each objective once")
    return objectives


def typed_settings(params: list[Param], values: dict) -> dict:
    """A trial's values of the space, keyed as the space (whole numbers as int)."""
    return {p.key: (int(values[p.key]) if p.integer else values[p.key]) for p in params
            if p.key in values}

