"""Output folders that a command owns: it deletes only what it wrote itself.

A command's output folder holds a marker, `.flowerpose-output.json`, naming the stage that
wrote it and the files it wrote. A folder that does not exist or is empty becomes the
stage's; one with the same stage's marker is its own earlier output, whose files are
removed (stale) before the new ones are written; anything else (another stage's output, or
files flowerpose did not write) is refused with one line, unless the user says
`--overwrite`, and even then nothing of it is deleted.
"""

from __future__ import annotations

import contextlib
import os
import shutil
from pathlib import Path

from flowerpose.errors import InputError
from flowerpose.jsonio import read_json, write_json

MARKER = ".flowerpose-output.json"


def _previous(folder: Path) -> dict | None:
    marker = folder / MARKER
    if not marker.is_file():
        return None
    try:
        data = read_json(marker)
    except InputError:
        return None
    files = data.get("files")
    if not isinstance(data.get("stage"), str) or not isinstance(files, list) or not all(
            isinstance(f, str) for f in files):
        return None
    return data


def check_output(folder: str | Path, stage: str, overwrite: bool = False) -> None:
    """Refuse, before any work, a folder that this stage may not write into."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise InputError(folder, "is a file, not a folder")
    if not folder.is_dir():
        return
    entries = sorted(p.name for p in folder.iterdir() if p.name != MARKER)
    previous = _previous(folder)
    if not entries or overwrite or (previous is not None and previous["stage"] == stage):
        return
    what = (f"the output of flowerpose {previous['stage']}" if previous is not None
            else f"files flowerpose {stage} did not write ({', '.join(entries[:3])}"
            + (", ..." if len(entries) > 3 else "") + ")")
    raise InputError(folder, f"holds {what}; choose an empty or new folder, or add --overwrite")


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    else:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()


class OutputFolder:
    """A stage's claim on its output folder; `record` each file written, then `finish`."""

    def __init__(self, folder: str | Path, stage: str, overwrite: bool = False):
        self.folder = Path(folder)
        self.stage = stage
        check_output(self.folder, stage, overwrite)
        previous = _previous(self.folder) if self.folder.is_dir() else None
        if previous is not None and previous["stage"] == stage:
            for name in previous["files"]:
                stale = (self.folder / name).resolve()
                if self.folder.resolve() in stale.parents:  # never outside the folder
                    _remove(stale)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.files: list[str] = []
        self._write(complete=False)

    def _write(self, complete: bool) -> None:
        write_json(self.folder / MARKER, {"stage": self.stage, "complete": complete,
                                          "files": sorted(set(self.files))})

    def record(self, *paths: str | Path) -> None:
        """Note files (or folders) this stage wrote in its folder."""
        for path in paths:
            self.files.append(os.path.relpath(Path(path), self.folder))
        self._write(complete=False)

    def finish(self) -> None:
        """The stage's output is whole."""
        self._write(complete=True)


def publish(staging: Path, folder: str | Path, stage: str, overwrite: bool = False) -> Path:
    """Move a stage's finished output from `staging` (a folder it filled) into `folder`,
    replacing only its own earlier output there; staging is removed."""
    output = OutputFolder(folder, stage, overwrite)
    for entry in sorted(staging.iterdir()):
        target = output.folder / entry.name
        _remove(target)
        os.replace(entry, target)
        output.record(target)
    staging.rmdir()
    output.finish()
    return output.folder


def staging_folder(folder: str | Path) -> Path:
    """A new, empty folder beside `folder` for a long stage to fill before `publish`."""
    folder = Path(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    staging = folder.parent / f".{folder.name}.partial-{os.getpid()}"
    _remove(staging)
    staging.mkdir()
    return staging
