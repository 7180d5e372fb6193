"""What the subcommands share: --config, --set and --profile and the configuration they
build, the output folder a command owns, the stage cache and Ray options, and the argument
types that refuse a bad number in one line."""

from __future__ import annotations

import argparse
import contextlib
import functools
import math
import os
import typing
from collections.abc import Callable
from pathlib import Path
from typing import Any

from flowerpose.atomic import temporary_beside
from flowerpose.config import DEFAULT_PRESET
from flowerpose.errors import InputError


def add_config_options(parser: argparse.ArgumentParser, profile: bool = True,
                        detector: bool = True,
                        example: str = "cluster.eps=0.008 (metres)") -> None:
    """--config and --set; --profile where the profiles' keys apply (the pipeline's), and
    --detector where a detector runs."""
    from flowerpose.config import profile_names

    if profile:
        parser.add_argument("--profile", choices=profile_names(), metavar="NAME",
                            help="start from a named settings profile: upstream = the "
                            "published method's settings (assets/configs/NAME.toml; default: "
                            "none, this project's defaults)")
    parser.add_argument("--config", type=Path, metavar="FILE.toml",
                        help="settings file (TOML, sections as in report.json's config)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override one setting by its dotted key, in the setting's own "
                        f"unit, e.g. {example}; repeatable")
    if detector:
        parser.add_argument("--detector", metavar="MODULE:CLASS|onnx:MODEL.onnx",
                            help="the 2D detector on the grid views instead of the colour "
                            "detector: onnx:MODEL.onnx, a box or segmentation model exported "
                            "to ONNX (the [onnx] extra; input, output and class in "
                            "pipeline/onnx_detector.py), or any importable class with the "
                            "Detector interface (pipeline/detect.py); the same as --set "
                            "detect.detector=... (default: the colour detector)")


@contextlib.contextmanager
def owned(folder: Path, stage: str, overwrite: bool, writes: tuple[str, ...]):
    """The command's output folder, refused when it holds files the command did not
    write (`outputs`; with --overwrite, when one of them has a name in `writes`, the
    entries the command writes), and marked whole when the command succeeds."""
    from flowerpose.outputs import OutputFolder

    output = OutputFolder(folder, stage, overwrite, writes)
    try:
        yield output
    except BaseException:
        output.abandon()
        raise
    output.finish()


def check_writable(path: Path, flag: str) -> None:
    """Refuse, before any work, a file path the command could not write at its end: a
    folder, a missing or read-only parent folder."""
    parent = path.parent if str(path.parent) else Path(".")
    if path.is_dir():
        raise InputError(path, f"{flag} is a folder; give a file path")
    if not parent.is_dir():
        raise InputError(path, f"{flag}: the folder {parent} does not exist")
    if not os.access(parent, os.W_OK) or (path.exists() and not os.access(path, os.W_OK)):
        raise InputError(path, f"{flag}: cannot be written here (permission denied)")
    # Permissions do not tell all (root, read-only or special file systems): the end of the
    # run writes through a temporary file beside the path, so make one now.
    try:
        temporary_beside(parent / path.name, ".check").unlink()
    except OSError as err:
        raise InputError(path, f"{flag}: cannot be written here ({err.strerror or err})"
                         ) from None


def add_cache_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--cache", type=Path, metavar="DIR",
                        help="the stage cache: scans and reconstructions of the same plant "
                        "with the same settings and code are taken from it, not run again "
                        "(default: $FLOWERPOSE_CACHE, else ~/.cache/flowerpose)")
    parser.add_argument("--no-cache", action="store_true",
                        help="run every stage, reading and filling no cache")


def add_ray_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--ray", nargs="?", const="local", default=None, metavar="ADDRESS",
                        help="run the plants' jobs as Ray tasks: on a local Ray without an "
                        "address, else on the cluster at ADDRESS (host:port, ray://..., or "
                        "auto); a job that fails is tried once more, then reported by plant "
                        "(needs the [ray] extra; default: a local process pool)")


def jobs_on(args: argparse.Namespace) -> contextlib.AbstractContextManager:
    """Where the command's jobs run: Ray (`--ray`), or the process pool."""
    if args.ray is None:
        return contextlib.nullcontext()
    from flowerpose.eval.pool import on_ray

    return on_ray(None if args.ray == "local" else args.ray)


def stage_cache(args: argparse.Namespace) -> Path | None:
    """The stage cache's folder the command's --cache / --no-cache choose."""
    from flowerpose.cache import StageCache, default_cache_dir, max_cache_bytes

    if args.no_cache and args.cache is not None:
        raise InputError("--no-cache", "and --cache contradict each other: choose one")
    max_cache_bytes()  # a bad limit says so before any work
    if args.no_cache:
        return None
    folder = args.cache or default_cache_dir()
    source = "--cache" if args.cache is not None else "FLOWERPOSE_CACHE"
    if folder.exists() and not folder.is_dir():
        raise InputError(folder, f"the stage cache ({source}) is a file, not a folder")
    if folder.is_dir() and not os.access(folder, os.W_OK):
        raise InputError(folder, f"the stage cache ({source}) cannot be written "
                         "(permission denied)")
    if folder.is_dir() and any(folder.iterdir()) and not StageCache(folder).is_cache():
        raise InputError(folder, f"the stage cache ({source}) is a folder of other files, not "
                         "a flowerpose stage cache: give an empty or new folder (the cache "
                         "tags its own with CACHEDIR.TAG)")
    return folder


def add_overwrite(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--overwrite", action="store_true",
                        help="write into a folder that holds files this command did not "
                        "write (they are kept; only its own earlier output is replaced)")


def add_output(parser: argparse.ArgumentParser, help: str, required: bool = True) -> None:
    """--out DIR (what the folder gets: `help`) and --overwrite."""
    parser.add_argument("--out", type=Path, required=required, metavar="DIR", help=help)
    add_overwrite(parser)


def add_preset(parser: argparse.ArgumentParser, default: str | None = DEFAULT_PRESET,
               shown: str = "%(default)s") -> None:
    """--preset: the synthetic plants' preset (`shown`: the default the help says, where
    `default` None leaves it to the command)."""
    names, described = _presets_described()
    parser.add_argument("--preset", choices=names, default=default, metavar="NAME",
                        help=f"the synthetic world, one of assets/presets ({described}) "
                             f"(default: {shown})")


@functools.cache
def _presets_described() -> tuple[list[str], str]:
    """The shipped presets' names and "name: description; ...", read once for every
    command's --preset."""
    from flowerpose.config import load_preset, preset_names

    names = preset_names()
    return names, "; ".join(f"{name}: {load_preset(name)[1]}" for name in names)


def add_workers(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--workers", type=POSITIVE, default=None, metavar="N",
                        help="worker processes (default: one per core)")


def units_type(text: str) -> str | float:
    """An argparse type: auto, m, mm, or a positive number of metres a unit."""
    if text in ("auto", "m", "mm"):
        return text
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: auto, m, mm or the metres one unit of "
                                         "the cloud is (a number)") from None
    if not (value > 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"{text!r}: metres a unit must be positive")
    return value


def add_units(parser: argparse.ArgumentParser, what: str) -> None:
    """--units of the cloud the command reads (`what`: "cloud", "crop")."""
    parser.add_argument("--units", type=units_type, default="auto", metavar="auto|m|mm|M",
                        help=f"the {what}'s unit: m, mm, M metres a unit (a photogrammetry "
                        "cloud's own unit, e.g. 0.04), or auto, decided from its extent "
                        "(default: %(default)s)")


#: The argparse attribute that holds a function giving a command's renamed setting keys,
#: {old key: new key} (`config.renamed`).
RENAMED_ATTRIBUTE = "renamed_settings"


def moved_under(where: str, section: str) -> Callable[[], dict[str, str]]:
    """A command's renamed keys (`RENAMED_ATTRIBUTE`) where its settings, the dataclass
    "module:Class" at the top once, now sit under `section` as they do in eval:
    {"count": "scan.frames.count", "dense.*": "scan.reconstruct.dense.*", ...}."""
    module, name = where.split(":")

    def renames() -> dict[str, str]:
        import dataclasses
        import importlib

        cls = getattr(importlib.import_module(module), name)
        hints = typing.get_type_hints(cls)
        return {(f"{f.name}.*" if dataclasses.is_dataclass(hints[f.name]) else f.name):
                (f"{section}.{f.name}.*" if dataclasses.is_dataclass(hints[f.name])
                 else f"{section}.{f.name}") for f in dataclasses.fields(cls)}
    return renames


def starting_config(where: str) -> Callable[[], Any]:
    """A command's starting settings, "module:Class" made with its defaults, imported when
    first asked for, so the command line starts without importing every stage."""
    module, name = where.split(":")

    def base() -> Any:
        import importlib

        return getattr(importlib.import_module(module), name)()
    return base


def configure(base: Any, args: argparse.Namespace, flags: bool = True,
              reads: tuple[str, ...] | None = None, command: str = "",
              run_keys: tuple[str, ...] = ()) -> Any:
    """`base` with the user's settings applied, layer by layer (`setting_layers`)."""
    from flowerpose.config import apply_overrides

    return functools.reduce(apply_overrides,
                            setting_layers(base, args, flags, reads, command, run_keys), base)


def setting_layers(base: Any, args: argparse.Namespace, flags: bool = True,
                   reads: tuple[str, ...] | None = None, command: str = "",
                   run_keys: tuple[str, ...] = ()) -> tuple[dict[str, Any], ...]:
    """The user's settings over `base`, as dotted keys in the order they apply: the
    --profile, then the --config file, then the settings' flags (`flags`) and --detector,
    then each --set; renamed keys (`config.RENAMED_SETTINGS`, and the command's own,
    `RENAMED_ATTRIBUTE`) are taken under their new names, with a warning. The one way a
    command layers them: `configure` applies them, `tune` and `guard` pass them on (a
    trial's settings over them; each side's command line).
    `reads`: the sections ("pose") and keys ("scan.camera.width") `command` reads; a --config or
    --set key outside them is refused in one line, since it would be silently ignored.
    `run_keys`: a --config file's top-level keys that are the command's own arguments
    (eval's source, plants, seed, as a report's config records them), taken by the command
    itself, not as settings."""
    from flowerpose.cli.flags import given_settings
    from flowerpose.config import (
        RENAMED_SETTINGS,
        load_profile,
        load_toml,
        parse_set_options,
        renamed,
    )

    command_renames = getattr(args, RENAMED_ATTRIBUTE, None)
    renames = {**RENAMED_SETTINGS, **(command_renames() if command_renames else {})}
    layers = []
    if getattr(args, "profile", None) is not None:
        layers.append(renamed(load_profile(args.profile), renames))
    if args.config is not None:
        settings = {key: value for key, value in load_toml(args.config).items()
                    if key not in run_keys}
        layers.append(_read_only(renamed(settings, renames), reads, command,
                                 str(args.config), base))
    detector = getattr(args, "detector", None)
    sets = _read_only(renamed(parse_set_options(args.set), renames), reads, command, "--set",
                      base)
    flagged = ((given_settings(args) if flags else [])
               + ([f"detect.detector={detector}"] if detector else []))
    layers += [parse_set_options(flagged), sets]
    return tuple(layer for layer in layers if layer)


def _read_only(settings: dict[str, Any], reads: tuple[str, ...] | None, command: str,
               where: str, base: Any) -> dict[str, Any]:
    """`settings` (dotted keys), each one of `reads`' sections or keys, else InputError."""
    if reads is None:
        return settings
    import dataclasses

    def shown(name: str) -> str:
        section = dataclasses.is_dataclass(functools.reduce(getattr, name.split("."), base))
        return f"{name}.*" if section else name

    for key in settings:
        if not any(key == r or key.startswith(r + ".") for r in reads):
            source = f"--set {key}" if where == "--set" else where
            raise InputError(source, f"{'' if where == '--set' else key + ': '}{command} "
                             f"reads {', '.join(shown(r) for r in reads)}, not this")
    return settings


def at_least(minimum: int, maximum: int | None = None, why: str = ""):
    """An argparse type: a whole number no smaller than `minimum` (nor larger than
    `maximum`, refused before anything is allocated)."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be at least {minimum}, got {value}")
        if maximum is not None and value > maximum:
            raise argparse.ArgumentTypeError(f"must be at most {maximum:,} ({why}), got "
                                             f"{value:,}")
        return value
    return parse


def non_negative_number(text: str) -> float:
    """An argparse type: a finite number, 0 or more."""
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not (0 <= value < float("inf")):
        raise argparse.ArgumentTypeError(f"expected a number, 0 or more, got {text!r}")
    return value


def positive_number(text: str) -> float:
    """An argparse type: a finite number above 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not (0 < value < float("inf")):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


def plant_xy(text: str) -> tuple[float, float]:
    """An argparse type: X,Y, two finite numbers (metres)."""
    try:
        x, y = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y in metres (e.g. 1.5,0.75), got "
                                         f"{text!r}") from None
    if not (abs(x) < float("inf") and abs(y) < float("inf")):
        raise argparse.ArgumentTypeError(f"expected two finite numbers, got {text!r}")
    return x, y


SEED = at_least(0)


POSITIVE = at_least(1)


#: Largest synthetic cloud: about 1 kB a point while it is sampled, so 20 million is 20 GB.
CLOUD_POINTS_MAX = 20_000_000


CLOUD_POINTS = at_least(100, CLOUD_POINTS_MAX, "more does not fit in memory")


#: Most seeded plants a run takes: about 10 MB of files each, and hours of work per 1,000.
PLANTS = at_least(1, 10_000, "a larger benchmark is several runs")
