"""A content-addressed cache of stage outputs, so a stage never runs twice on the same inputs.

An entry is a folder ROOT/STAGE/KEY/ holding the files the stage produced and entry.json
(what it was made from). KEY is a SHA-256 of the stage's name, the code version (every
flowerpose source file: a change to the code invalidates every entry, since a stage's
output depends on more code than its own module), the settings the stage reads (canonical
JSON) and the content of its input files, and of nothing else: the output folder, the
number of workers and the time of day do not enter it.

An entry is filled in a private folder beside it and renamed into place when whole, so a
killed fill leaves only that private folder, which no run ever reads; when two processes
fill one key, the first rename wins and the other's copy is dropped. Entries are never
changed once made; `restore` copies their files out (atomically, like every result file).
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import shutil
import uuid
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path

from flowerpose.atomic import write_file
from flowerpose.jsonio import read_json, write_json

#: The packages whose source makes the code version.
_PACKAGES = ("flowerpose", "flowerpose.pipeline", "flowerpose.eval", "flowerpose.sim",
             "flowerpose.hardware", "flowerpose.assets")
_CHUNK = 1 << 20


def default_cache_dir() -> Path:
    """$FLOWERPOSE_CACHE, else $XDG_CACHE_HOME/flowerpose, else ~/.cache/flowerpose."""
    if os.environ.get("FLOWERPOSE_CACHE"):
        return Path(os.environ["FLOWERPOSE_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "flowerpose"


def file_digest(path: Path) -> str:
    """SHA-256 of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while chunk := handle.read(_CHUNK):
            digest.update(chunk)
    return digest.hexdigest()


@functools.lru_cache(maxsize=1)
def code_version() -> str:
    """SHA-256 over the installed flowerpose's source files (.py, .toml, .xml), by path."""
    import importlib

    digest = hashlib.sha256()
    for name in _PACKAGES:
        folder = Path(importlib.import_module(name).__file__).parent
        files = sorted(p for p in folder.rglob("*") if p.suffix in (".py", ".toml", ".xml")
                       and "__pycache__" not in p.parts)
        for path in files:
            digest.update(f"{name}/{path.relative_to(folder).as_posix()}\0".encode())
            digest.update(file_digest(path).encode())
    return digest.hexdigest()


def stage_key(stage: str, settings: Mapping, inputs: Iterable[Path]) -> str:
    """The key of `stage` run on the files `inputs` with `settings` (JSON-able) by this code."""
    document = {"stage": stage, "code": code_version(),
                "settings": json.loads(json.dumps(settings, sort_keys=True, default=str)),
                "inputs": [file_digest(Path(p)) for p in inputs]}
    text = json.dumps(document, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


class StageCache:
    """Stage outputs under `root` (`default_cache_dir()` unless given)."""

    def __init__(self, root: Path | None = None):
        self.root = Path(root) if root is not None else default_cache_dir()

    def entry(self, stage: str, key: str) -> Path | None:
        """The whole entry for (stage, key), or None."""
        folder = self.root / stage / key
        return folder if (folder / "entry.json").is_file() else None

    def store(self, stage: str, key: str, files: Mapping[str, Path], about: Mapping) -> Path:
        """Copy `files` (name in the entry -> file) into a new entry with entry.json holding
        `about`; returns the entry (another process's, when it filled the key first)."""
        final = self.root / stage / key
        private = final.parent / f".{key}.partial-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        private.mkdir(parents=True)
        try:
            for name, source in files.items():
                target = private / name
                target.parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(source, target)
            write_json(private / "entry.json", {"stage": stage, "key": key, **about})
            try:
                os.rename(private, final)
            except OSError:
                if self.entry(stage, key) is None:  # not a lost race: a real failure
                    raise
        finally:
            if private.exists():
                shutil.rmtree(private)
        return final

    @staticmethod
    def about(entry: Path) -> dict:
        """An entry's entry.json."""
        return read_json(entry / "entry.json")

    @staticmethod
    def restore(entry: Path, files: Mapping[str, Path]) -> None:
        """Copy the entry's files (name in the entry -> destination) out, each whole."""
        for name, target in files.items():
            write_file(target, lambda tmp, name=name: shutil.copyfile(entry / name, tmp))

    def run(self, stage: str, settings: Mapping, inputs: Iterable[Path], folder: Path,
            outputs: Iterable[str], compute: Callable[[], dict]) -> tuple[dict, bool]:
        """(result, whether it came from the cache) of a stage that writes `outputs` (files
        or folders, relative to `folder`; those it wrote are kept) and returns a JSON-able
        result: from the entry for its key, its files copied back into folder, or computed
        and stored."""
        key = stage_key(stage, settings, inputs)
        entry = self.entry(stage, key)
        if entry is not None:
            about = self.about(entry)
            self.restore(entry, {name: folder / name for name in about["files"]})
            return about["result"], True
        result = compute()
        files = {}
        for name in outputs:
            path = folder / name
            found = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else (
                [path] if path.is_file() else [])
            files.update({p.relative_to(folder).as_posix(): p for p in found})
        self.store(stage, key, files, {"result": result, "settings": settings,
                                       "files": sorted(files)})
        return result, False
