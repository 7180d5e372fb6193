"""Other methods, scored exactly like the built-in pipeline: an external command per plant.

`eval --method NAME='CMD {cloud} {out}'` runs CMD once per plant, with `{cloud}` the plant's
cloud (PLY, the frame and unit its flowers are scored in) and `{out}` a folder it must write
`flowers.json` into (DESIGN.md's format); the flowers are then matched and scored as the
pipeline's are, and printed beside it. A command that fails, runs past its timeout or writes
a bad file is reported for that plant (its entry says why, with nothing found), never a
traceback, and the other plants go on. An installed package can register a method by name
(entry points, group `flowerpose.methods`): `--method NAME` runs it the same way.
`--compare` takes any kind of method (`parse_compare`): a settings profile, an external or
registered method, or a 2D detector in place of the colour detector.
"""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from dataclasses import dataclass
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any

from flowerpose.errors import InputError
from flowerpose.eval.scoring.match import plant_entry, score_plant
from flowerpose.eval.scoring.truth import TruthFlower
from flowerpose.stopwatch import Stopwatch

#: Seconds an external method may take on one plant unless told otherwise.
DEFAULT_TIMEOUT_S = 600.0


@dataclass(frozen=True)
class ExternalMethod:
    """An external method: its name in the report and its command line (a template)."""

    name: str
    command: str
    timeout_s: float = DEFAULT_TIMEOUT_S

    def argv(self, cloud: Path, out: Path) -> list[str]:
        return [part.replace("{cloud}", str(cloud)).replace("{out}", str(out))
                for part in shlex.split(self.command)]


#: The entry-point group a package registers methods in: NAME = "module:function", a
#: function(cloud: Path, out: Path) that writes out/flowers.json.
ENTRY_POINTS = "flowerpose.methods"


def registered_methods() -> dict[str, Any]:
    """The methods installed packages register (entry points of ENTRY_POINTS), by name."""
    return {ep.name: ep for ep in entry_points(group=ENTRY_POINTS)}


def parse_method(text: str, timeout_s: float = DEFAULT_TIMEOUT_S) -> ExternalMethod:
    """--method NAME=CMD, checked: a name, and a command naming {cloud} and {out}; or
    --method NAME, a method an installed package registers (ENTRY_POINTS), which runs in a
    process of its own like a command."""
    name, sep, command = text.partition("=")
    name = name.strip()
    if not sep and name in registered_methods():
        return ExternalMethod(name, f"{shlex.quote(sys.executable)} -m "
                              "flowerpose.eval.scoring.methods "
                              f"{shlex.quote(name)} {{cloud}} {{out}}", timeout_s)
    if not sep or not name.replace("-", "").replace("_", "").isalnum():
        known = ", ".join(sorted(registered_methods())) or "none installed"
        raise InputError("method", f"'{text}': expected NAME='CMD {{cloud}} {{out}}', or "
                         f"the name of a registered method ({known})")
    try:
        parts = shlex.split(command)
    except ValueError as err:
        raise InputError("method", f"'{text}': {err}") from None
    if not parts or "{cloud}" not in command or "{out}" not in command:
        raise InputError("method", f"'{text}': the command must name {{cloud}} (the plant's "
                         "cloud) and {out} (the folder for its flowers.json)")
    return ExternalMethod(name, command, timeout_s)


def run_method(method: ExternalMethod, cloud: Path, truth: list[TruthFlower], out_dir: Path,
               name: str, max_distance: float) -> tuple[dict, dict[str, float]]:
    """Run the method on one plant's cloud and score what it wrote; the plant's report
    entry (with "error" when it failed, and then nothing found) and its timing."""
    from flowerpose.pipeline.flowers import read_flowers

    out_dir.mkdir(parents=True, exist_ok=True)
    watch = Stopwatch()
    error = None
    try:
        done = subprocess.run(method.argv(cloud, out_dir), capture_output=True, text=True,
                              timeout=method.timeout_s)
        if done.returncode != 0:
            last = (done.stderr.strip().splitlines() or ["no message"])[-1]
            error = f"exited with status {done.returncode}: {last[:200]}"
    except subprocess.TimeoutExpired:
        error = f"ran past its timeout of {method.timeout_s:g} s and was stopped"
    except OSError as err:
        error = f"could not start: {err.strerror or err}"
    seconds = watch.elapsed()
    estimates = []
    if error is None:
        try:
            estimates = read_flowers(out_dir / "flowers.json")
        except InputError as err:
            error = f"wrote no usable flowers.json ({err})"
    entry = plant_entry(name, score_plant(estimates, truth, max_distance))
    if error is not None:
        entry["error"] = f"{method.name}: {error}"
    return entry, {"method": round(seconds, 4), "total": round(seconds, 4)}


def _run_registered(argv: list[str]) -> int:
    """`python -m flowerpose.eval.scoring.methods NAME CLOUD OUT`: a registered method, in the
    process `run_method` started for it."""
    name, cloud, out = argv
    registered_methods()[name].load()(Path(cloud), Path(out))
    return 0


if __name__ == "__main__":
    sys.exit(_run_registered(sys.argv[1:]))


def parse_compare(text: str, config: Any, timeout_s: float = DEFAULT_TIMEOUT_S
                  ) -> tuple[str, Any]:
    """--compare's value as (name, what runs): a settings profile (`upstream`) or a 2D
    detector (`onnx:MODEL.onnx`, `MODULE:CLASS`) as the run's config with it applied, or an
    external method (`NAME='CMD {cloud} {out}'`, or a registered method's name) as an
    `ExternalMethod`. A detector that cannot load is one line before any work."""
    from flowerpose.config import apply_overrides, load_profile, profile_names
    from flowerpose.pipeline.detect import make_detector

    text = text.strip()
    if text in profile_names():
        return text, apply_overrides(config, load_profile(text))
    if "=" in text or text in registered_methods():
        method = parse_method(text, timeout_s)
        return method.name, method
    if ":" in text:
        compared = apply_overrides(config, {"detect.detector": text})
        make_detector(compared.detect, compared.colour)
        kind, _, spec = text.partition(":")
        label = Path(spec).stem if kind == "onnx" else spec
        return "detector-" + re.sub(r"[^A-Za-z0-9_.-]+", "_", label), compared
    known = ", ".join(profile_names())
    raise InputError("compare", f"'{text}': a profile ({known}), a registered method, "
                     "NAME='CMD {cloud} {out}', or a detector (onnx:MODEL.onnx or "
                     "MODULE:CLASS)")
