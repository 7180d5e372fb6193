"""Nested config dataclasses: dotted overrides (`cluster.eps=0.008`), TOML files, plain dicts.

Every stage has its own documented dataclass; a top-level dataclass nests them. The helpers
here only know dataclasses, so the pipeline and the harness share them.
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import inspect
import json
import textwrap
import tomllib
import typing
from pathlib import Path
from typing import Any

from flowerpose.errors import InputError


def to_dict(config: Any) -> dict[str, Any]:
    """The config as plain JSON-ready data (tuples become lists)."""
    return _plain(dataclasses.asdict(config))


def _plain(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    return value


def value_at(config: Any, key: str) -> Any:
    """The value of a dotted key ("cluster.eps") in a config, typed as the field is and
    JSON-ready (tuples as lists, a section as a dict)."""
    value = functools.reduce(getattr, key.split("."), config)
    return to_dict(value) if dataclasses.is_dataclass(value) else _plain(value)


def setting_doc(config: Any, key: str) -> str:
    """The docstring under a setting's field in its dataclass (its meaning and unit), for
    a dotted key of `config`; "" when the field has none."""
    head, _, rest = key.partition(".")
    if rest:
        return setting_doc(getattr(config, head), rest)
    return _field_docs(type(config)).get(key, "")


@functools.cache
def _field_docs(cls: type) -> dict[str, str]:
    """Each field's docstring (the string literal under it) in the class or its bases."""
    docs: dict[str, str] = {}
    for base in reversed(cls.__mro__[:-1]):
        try:
            tree = ast.parse(textwrap.dedent(inspect.getsource(base)))
        except (OSError, TypeError):
            continue
        body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
        for field_node, doc_node in zip(body, body[1:], strict=False):
            if (isinstance(field_node, ast.AnnAssign) and isinstance(field_node.target, ast.Name)
                    and isinstance(doc_node, ast.Expr) and isinstance(doc_node.value, ast.Constant)
                    and isinstance(doc_node.value.value, str)):
                docs[field_node.target.id] = " ".join(doc_node.value.value.split())
    return docs


def _field_types(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _coerce(raw: Any, annotation: Any, key: str) -> Any:
    """Turn a TOML value or a `--set` string into the field's declared type."""
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin is typing.Literal:
        value = raw if not isinstance(raw, str) else _parse_scalar(raw)
        if value not in args and str(value) not in [str(a) for a in args]:
            raise InputError(key, f"must be one of {', '.join(map(str, args))}, got {raw!r}")
        return next(a for a in args if str(a) == str(value))
    if origin in (typing.Union, getattr(__import__("types"), "UnionType", None)):
        non_none = [a for a in args if a is not type(None)]
        if isinstance(raw, str) and raw.lower() in ("none", "null"):
            return None
        return _coerce(raw, non_none[0], key)
    if origin is tuple:
        items = _parse_scalar(raw) if isinstance(raw, str) else raw
        if not isinstance(items, list | tuple):
            items = [items]
        if args and args[-1] is not Ellipsis and len(items) != len(args):
            raise InputError(key, f"expected {len(args)} values, got {raw!r}")
        inner = args[0] if args else float
        return tuple(_coerce(v, inner, key) for v in items)
    if annotation is bool:
        if isinstance(raw, bool):
            return raw
        text = str(raw).strip().lower()
        if text in ("1", "true", "yes", "on"):
            return True
        if text in ("0", "false", "no", "off"):
            return False
        raise InputError(key, f"expected true or false, got {raw!r}")
    if annotation is int:
        parsed = _parse_scalar(raw) if isinstance(raw, str) else raw
        if isinstance(parsed, bool) or not isinstance(parsed, int | float) or (
                isinstance(parsed, float) and not parsed.is_integer()):
            raise InputError(key, f"expected a whole number, got {raw!r}")
        return int(parsed)
    if annotation in (float, str):
        try:
            parsed = _parse_scalar(raw) if isinstance(raw, str) and annotation is not str else raw
            value = annotation(parsed)
        except (TypeError, ValueError):
            raise InputError(key, f"expected {annotation.__name__}, got {raw!r}") from None
        if annotation is float and not (value == value and abs(value) != float("inf")):
            raise InputError(key, f"expected a finite number, got {raw!r}")
        return value
    return raw


def _parse_scalar(text: str) -> Any:
    try:
        return ast.literal_eval(text)
    except (ValueError, SyntaxError):
        return text


def apply_overrides(config: Any, overrides: dict[str, Any], prefix: str = "") -> Any:
    """A copy of `config` with `overrides` applied.

    `overrides` maps dotted keys ("cluster.eps") or nested dicts (from TOML) to values;
    unknown keys raise InputError naming the key, so typos never pass silently.
    """
    nested: dict[str, Any] = {}
    for key, value in overrides.items():
        head, _, rest = key.partition(".")
        if rest:
            nested.setdefault(head, {})[rest] = value
        elif isinstance(value, dict):
            nested.setdefault(head, {}).update(value)
        else:
            nested[head] = value
    hints = _field_types(type(config))
    changes: dict[str, Any] = {}
    for name, value in nested.items():
        key = f"{prefix}{name}"
        if name not in hints:
            known = ", ".join(f"{prefix}{f.name}" for f in dataclasses.fields(config))
            raise InputError(key, f"no such setting (known: {known})")
        current = getattr(config, name)
        if dataclasses.is_dataclass(current):
            if not isinstance(value, dict):
                raise InputError(key, "is a section; set one of its fields, e.g. "
                                 f"{key}.{dataclasses.fields(current)[0].name}=...")
            changes[name] = apply_overrides(current, value, prefix=f"{key}.")
        else:
            changes[name] = _coerce(value, hints[name], key)
    try:
        return dataclasses.replace(config, **changes)
    except InputError as error:
        # A section's own check names its field; the user set it under its full key.
        if prefix and error.source in hints:
            raise InputError(f"{prefix}{error.source}", error.problem) from None
        raise


def require(condition: bool, key: str, problem: str) -> None:
    """Raise InputError(key, problem) unless `condition`: for config __post_init__ checks."""
    if not condition:
        raise InputError(key, problem)


#: Settings renamed in this version, {old key: new key}, taken under the new name with a
#: warning until the next: a key ending ".*" renames every key under it.
RENAMED_SETTINGS = {
    "scan.frames": "scan.frames.count",
    "scan.width": "scan.camera.width",
    "scan.height": "scan.camera.height",
    "scan.frame_rate_hz": "scan.camera.frame_rate_hz",
    "scan.workers": "scan.camera.workers",
    "scan.sensor.*": "scan.camera.sensor.*",
    "scan.render.*": "scan.camera.render.*",
}


def renamed(overrides: dict[str, Any],
            renames: dict[str, str] = RENAMED_SETTINGS) -> dict[str, Any]:
    """`overrides` (dotted keys, or nested tables from TOML) as dotted keys, each under its
    current name (`current_name`)."""
    return {current_name(key, renames): value for key, value in _dotted(overrides).items()}


def current_name(key: str, renames: dict[str, str] = RENAMED_SETTINGS) -> str:
    """A dotted setting key under its current name: a renamed one (`renames`, {old: new};
    "KEY.*" for every key under KEY) under its new name, with a warning that names it, so
    an old key keeps working for a version."""
    from flowerpose.log import LOG

    new = renames.get(key)
    for old, replacement in renames.items():
        if new is None and old.endswith(".*") and key.startswith(old[:-1]):
            new = replacement[:-1] + key[len(old) - 1:]
    if new is None:
        return key
    LOG.warning(f"warning: the setting {key} is now {new}; the old name works until the "
                "next version")
    return new


def _dotted(overrides: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in overrides.items():
        if isinstance(value, dict):
            out.update(_dotted(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def settings_toml(settings: dict[str, Any], header: str) -> str:
    """Settings (nested sections or dotted keys) as a --config file: `header` as a comment,
    top-level keys first, then one table per section; None is written "none", which every
    setting that takes None reads back as None."""
    sections: dict[str, dict[str, Any]] = {}
    for key, value in _dotted(settings).items():
        section, _, name = key.rpartition(".")
        sections.setdefault(section, {})[name] = value
    lines = [f"# {line}" if line else "#" for line in header.splitlines()]
    for section in sorted(sections, key=lambda name: name != ""):
        lines.append(f"\n[{section}]" if section else "")
        lines += [f"{name} = {_toml_value(value)}" for name, value in sections[section].items()]
    return "\n".join(lines) + "\n"


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{json.dumps(str(k))} = {_toml_value(v)}"
                               for k, v in value.items()) + "}"
    if value is None:
        return '"none"'
    return json.dumps(str(value))


def parse_set_options(items: list[str]) -> dict[str, str]:
    """`["cluster.eps=0.008", ...]` to `{"cluster.eps": "0.008"}`."""
    out: dict[str, str] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise InputError("set", f"expected key=value, got {item!r}")
        out[key.strip()] = value.strip()
    return out


def _asset_names(folder: str) -> list[str]:
    """The names of the TOML files shipped in assets/FOLDER."""
    from importlib.resources import files

    return sorted(p.name.removesuffix(".toml") for p in (files("flowerpose.assets") / folder)
                  .iterdir() if p.name.endswith(".toml"))


def _asset(folder: str, kind: str, name: str) -> tuple[dict[str, Any], str]:
    """A shipped TOML file's settings and its content's SHA-256 (hex); errors name the
    file, or the known names for a name that is not there."""
    import hashlib
    from importlib.resources import as_file, files

    known = _asset_names(folder)
    if name not in known:
        raise InputError(kind, f"no {kind} {name!r} (known: {', '.join(known)})")
    with as_file(files("flowerpose.assets") / folder / f"{name}.toml") as path:
        return load_toml(path), hashlib.sha256(path.read_bytes()).hexdigest()


def profile_names() -> list[str]:
    """The named settings profiles shipped in assets/configs (`--profile NAME`)."""
    return _asset_names("configs")


def load_profile(name: str) -> dict[str, Any]:
    """The settings of a named profile (assets/configs/NAME.toml), as nested dicts."""
    return _asset("configs", "profile", name)[0]


def profile_hash(name: str) -> str:
    """The SHA-256 (hex) of a named profile's file, recorded in reports made with it."""
    return _asset("configs", "profile", name)[1]


#: The synthetic world's preset where none is named: plants like the paper's, scanned cleanly.
DEFAULT_PRESET = "realistic"


def preset_names() -> list[str]:
    """The synthetic world's presets shipped in assets/presets (`--preset NAME`)."""
    return _asset_names("presets")


def load_preset(name: str) -> tuple[dict[str, Any], str]:
    """A named preset (assets/presets/NAME.toml): its settings over the eval config's keys
    (`sim.*`, `score.*`, `scan.*`), nested, and its description (the `[preset]` table)."""
    data = dict(_asset("presets", "preset", name)[0])
    header = data.pop("preset", {})
    return data, str(header.get("description", "")) if isinstance(header, dict) else ""


def preset_hash(name: str) -> str:
    """The SHA-256 (hex) of a named preset's file, recorded in reports made with it."""
    return _asset("presets", "preset", name)[1]


def load_toml(path: Path) -> dict[str, Any]:
    """Read a TOML config file; errors name the file."""
    try:
        with open(path, "rb") as handle:
            return tomllib.load(handle)
    except FileNotFoundError:
        raise InputError(path, "config file not found") from None
    except tomllib.TOMLDecodeError as err:
        raise InputError(path, f"not valid TOML ({err})") from None
    except UnicodeDecodeError:
        raise InputError(path, "not a UTF-8 text file (TOML is UTF-8)") from None
    except OSError as err:
        raise InputError(path, f"cannot read ({err.strerror})") from None


def suite_names() -> list[str]:
    """The named benchmark suites shipped in assets/suites (`eval --suite NAME`)."""
    return _asset_names("suites")


#: What a suite fixes of an eval, and the type of each.
SUITE_KEYS = {"source": str, "preset": str, "plants": int, "seed": int}


def load_suite(name: str) -> dict[str, Any]:
    """A named suite (assets/suites/NAME.toml), or a suite file (a path ending .toml, whose
    [suite] version may be left out): {"name", "version", "description", "eval": {source,
    preset, plants, seed}}; errors name the file, and a preset that is not one of
    assets/presets."""
    from importlib.resources import files

    if name.endswith(".toml"):
        path: Any = Path(name)
        data, versioned, name = load_toml(path), False, Path(name).stem
    else:
        data, versioned = _asset("suites", "suite", name)[0], True
        path = files("flowerpose.assets") / "suites" / f"{name}.toml"
    header, fixed = data.get("suite", {}), data.get("eval", {})
    version = header.get("version")
    if (versioned or version is not None) and (
            not isinstance(version, int) or isinstance(version, bool) or version < 1):
        raise InputError(path, "[suite] needs a version, a whole number from 1")
    if not isinstance(fixed, dict) or set(fixed) != set(SUITE_KEYS) or not all(
            isinstance(fixed[k], t) and not isinstance(fixed[k], bool)
            for k, t in SUITE_KEYS.items()):
        raise InputError(path, f"[eval] must give exactly {', '.join(SUITE_KEYS)}")
    if fixed["preset"] not in preset_names():
        raise InputError(path, f"preset {fixed['preset']!r} is not one of assets/presets "
                         f"({', '.join(preset_names())})")
    return {"name": name, "version": version,
            "description": str(header.get("description", "")), "eval": fixed}
