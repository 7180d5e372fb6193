"""A content-addressed cache of stage outputs, so a stage never runs twice on the same inputs.

An entry is a folder ROOT/STAGE/KEY/ holding the files the stage produced and entry.json
(what it was made from). KEY is a SHA-256 of the stage's name, the code version, the
settings the stage reads (canonical JSON) and the content of its input files, and of
nothing else: the output folder, the number of workers and the time of day do not enter it.

The code version is every flowerpose source file, unless the stage names the modules it
runs (`code`): then it is those modules' files and every flowerpose module they import,
at the top or inside a function, transitively (`module_closure`), and the shipped data
files that are not settings (the MuJoCo model). So a change to detection leaves a
reconstruction's entry valid, and a change to anything a reconstruction imports does not.

A stage that follows another in one chain (a reconstruction of a scan's chosen frames)
takes the earlier stage's key among its inputs (`parents`) rather than the digest of its
files: the earlier entry holds exactly those files, so the key says the same, and is known
before anything runs.

An entry is filled in a private folder beside it and renamed into place when whole, so a
killed fill leaves only that private folder, which no run ever reads; when two processes
fill one key, the first rename wins and the other's copy is dropped. Entries are never
changed once made; `restore` copies their files out (atomically, like every result file).

The cache is bounded: `prune` removes the least recently used entries (a hit counts as a
use) until the entries fit a size, by default DEFAULT_MAX_BYTES or
$FLOWERPOSE_CACHE_MAX_GB. It deletes only what it can prove it wrote: its root carries the
cache's own `CACHEDIR.TAG` (the Cache Directory Tagging Specification's, which backup
tools skip), an entry is a folder STAGE/KEY whose entry.json names that very stage and key
(a SHA-256), a fill's private folder (.KEY.partial-...) carries the cache's marker file
from its start, and a folder renamed away for deletion is named after an entry's key
(.KEY.pruned-...). A folder that is no cache (neither tagged nor holding an entry) is
refused whole: nothing in it is deleted. Whatever else is in the cache's folder stays.
"""

from __future__ import annotations

import ast
import functools
import hashlib
import importlib
import json
import os
import shutil
import sys
import time
import uuid
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

from flowerpose.atomic import write_file, write_text
from flowerpose.errors import InputError
from flowerpose.jsonio import read_json, write_json
from flowerpose.log import LOG, noted

#: The packages whose source makes the code version.
_PACKAGES = ("flowerpose", "flowerpose.pipeline", "flowerpose.eval", "flowerpose.sim",
             "flowerpose.hardware", "flowerpose.assets")
_CHUNK = 1 << 20

#: The size the entries are pruned to after an eval or a sweep: about 300 scan captures.
DEFAULT_MAX_BYTES = 20 * 10**9
#: A private folder of a fill older than this was left by a killed process.
_STALE_FILL_S = 24 * 3600
#: The cache's tag at its root (the Cache Directory Tagging Specification's signature line,
#: then what made it).
CACHE_TAG = "CACHEDIR.TAG"
_TAG_TEXT = ("Signature: 8a477f597d28d172789f06886806bc55\n"
             "# This folder is flowerpose's stage cache (flowerpose cache says what it holds).\n")
#: The file a fill's private folder carries from its start: the cache made it.
_FILL_MARK = ".flowerpose-fill"
_KEY_CHARS = frozenset("0123456789abcdef")


def _is_key(name: str) -> bool:
    """Whether `name` is a stage key: a SHA-256 in hex."""
    return len(name) == 64 and set(name) <= _KEY_CHARS


def is_entry(folder: Path) -> bool:
    """Whether `folder` is one of the cache's entries: STAGE/KEY whose entry.json names
    that very stage and key."""
    if not _is_key(folder.name):
        return False
    try:
        about = read_json(folder / "entry.json")
    except (InputError, OSError):
        return False
    return (isinstance(about, dict) and about.get("key") == folder.name
            and about.get("stage") == folder.parent.name)


def max_cache_bytes() -> int:
    """$FLOWERPOSE_CACHE_MAX_GB in bytes, else DEFAULT_MAX_BYTES."""
    text = os.environ.get("FLOWERPOSE_CACHE_MAX_GB")
    if not text:
        return DEFAULT_MAX_BYTES
    try:
        gigabytes = float(text)
    except ValueError:
        gigabytes = float("nan")
    if not gigabytes >= 0:
        raise InputError("FLOWERPOSE_CACHE_MAX_GB", f"must be a size in GB, 0 or more, got "
                         f"{text!r}")
    return gigabytes_to_bytes(gigabytes)


def gigabytes_to_bytes(gigabytes: float) -> int:
    """A size in GB as bytes; any size past what a disk holds is "no limit" (sys.maxsize)."""
    return int(min(gigabytes * 1e9, sys.maxsize))


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
def _package_folders() -> dict[str, Path]:
    """Each of `_PACKAGES`' installed folder."""
    return {name: Path(importlib.import_module(name).__file__).parent for name in _PACKAGES}


@functools.lru_cache(maxsize=1)
def _source_files() -> list[tuple[str, Path]]:
    """Every flowerpose source file (.py, .toml, .xml) once, as (its package/the path in
    it, path), named by the innermost package holding it: the same names whether the
    packages are installed from their own folders (pipeline/ as flowerpose.pipeline) or
    laid out one inside another (another revision's tree, `eval/studies/revision.py`), so the same
    code has the same version either way."""
    folders = _package_folders()
    found: dict[Path, tuple[str, Path]] = {}
    for folder in folders.values():
        for path in sorted(folder.rglob("*")):
            if path.suffix not in (".py", ".toml", ".xml") or "__pycache__" in path.parts:
                continue
            owner = max((n for n, f in folders.items() if path.is_relative_to(f)),
                        key=lambda n: len(folders[n].parts))
            found[path] = (f"{owner}/{path.relative_to(folders[owner]).as_posix()}", path)
    return sorted(found.values())


def _module_file(module: str) -> Path | None:
    """The source file of a flowerpose module (a package's __init__.py), None for a module
    of another distribution or a name that is no module (an imported function's)."""
    folders = _package_folders()
    package = max((name for name in folders if module == name or module.startswith(name + ".")),
                  key=len, default=None)
    if package is None:
        return None
    path = folders[package].joinpath(*module[len(package):].split(".")[1:])
    for candidate in (path.with_suffix(".py"), path / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


def _imports(module: str, path: Path) -> set[str]:
    """The flowerpose modules `module`'s source imports anywhere (inside functions too), but
    under `if TYPE_CHECKING:`, which runs nothing."""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    named: set[str] = set()

    class Imports(ast.NodeVisitor):
        def visit_If(self, node: ast.If) -> None:
            test = node.test
            if getattr(test, "id", getattr(test, "attr", None)) == "TYPE_CHECKING":
                for statement in node.orelse:
                    self.visit(statement)
                return
            self.generic_visit(node)

        def visit_Import(self, node: ast.Import) -> None:
            named.update(alias.name for alias in node.names)

        def visit_ImportFrom(self, node: ast.ImportFrom) -> None:
            base = node.module or ""
            if node.level:
                parts = package.split(".")[:len(package.split(".")) - node.level + 1]
                base = ".".join([*parts, base] if base else parts)
            named.add(base)
            named.update(f"{base}.{alias.name}" for alias in node.names)

    Imports().visit(ast.parse(path.read_text(encoding="utf-8")))
    return {name for name in named if _module_file(name) is not None}


@functools.cache
def module_closure(roots: tuple[str, ...]) -> tuple[str, ...]:
    """The flowerpose modules `roots` import, directly or through each other, with the
    roots, sorted."""
    seen: set[str] = set()
    waiting = list(roots)
    while waiting:
        module = waiting.pop()
        path = _module_file(module)
        if module in seen or path is None:
            continue
        seen.add(module)
        waiting += _imports(module, path)
    return tuple(sorted(seen))


@functools.cache
def code_version(roots: tuple[str, ...] | None = None) -> str:
    """SHA-256 over flowerpose's source, by path: every source file (.py, .toml, .xml), or,
    given the modules a stage runs (`roots`), their `module_closure`'s files and the
    shipped MuJoCo model (.xml)."""
    if roots is None:
        files = _source_files()
    else:
        modules = {_module_file(name) for name in module_closure(roots)}
        files = [(name, path) for name, path in _source_files()
                 if path in modules or path.suffix == ".xml"]
    digest = hashlib.sha256()
    for name, path in files:
        digest.update(f"{name}\0".encode())
        digest.update(file_digest(path).encode())
    return digest.hexdigest()


def stage_key(stage: str, settings: Mapping, inputs: Iterable[Path],
              parents: Iterable[str] = (), code: tuple[str, ...] | None = None) -> str:
    """The key of `stage` run on the files `inputs` and the outputs of the earlier stages
    whose keys are `parents`, with `settings` (JSON-able), by this code: all of it, or the
    modules `code` names and what they import (`code_version`)."""
    document = {"stage": stage, "code": code_version(code),
                "settings": json.loads(json.dumps(settings, sort_keys=True, default=str)),
                "inputs": [file_digest(Path(p)) for p in inputs], "parents": list(parents)}
    text = json.dumps(document, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


@dataclass(frozen=True)
class Entry:
    """One whole entry: its folder, stage, size in bytes and last use (Unix seconds)."""

    folder: Path
    stage: str
    size: int
    used: float


class StageCache:
    """Stage outputs under `root` (`default_cache_dir()` unless given)."""

    def __init__(self, root: Path | None = None):
        self.root = Path(root) if root is not None else default_cache_dir()

    def is_cache(self) -> bool:
        """Whether the root is the cache's: tagged by it, or (a cache from before the tag)
        holding an entry."""
        tag = self.root / CACHE_TAG
        if tag.is_file():
            try:
                return tag.read_text(encoding="utf-8").startswith(_TAG_TEXT.splitlines()[0])
            except (OSError, UnicodeDecodeError):
                return False
        return any(is_entry(about.parent) for about in self.root.glob("*/*/entry.json"))

    def _tag(self) -> None:
        """Tag the root as the cache's (once)."""
        tag = self.root / CACHE_TAG
        if not tag.exists():
            write_text(tag, _TAG_TEXT)

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
        self._tag()
        try:
            (private / _FILL_MARK).write_text("", encoding="utf-8")
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
            outputs: Iterable[str], compute: Callable[[], dict],
            parents: Iterable[str] = (), code: tuple[str, ...] | None = None
            ) -> tuple[dict, bool, str]:
        """(result, whether it came from the cache, key) of a stage that writes `outputs`
        (files or folders, relative to `folder`; those it wrote are kept) and returns a
        JSON-able result: from the entry for its key, its files copied back into folder, or
        computed and stored; the warnings the stage said (what it assumed) are stored
        with it and said again when it comes from the cache. `parents`: the keys of the
        earlier stages it reads the output of; `code`: the modules the stage runs, when
        not the whole of flowerpose (`stage_key`)."""
        key = stage_key(stage, settings, inputs, parents, code)
        entry = self.entry(stage, key)
        if entry is not None:
            try:
                about = self.about(entry)
                self.restore(entry, {name: folder / name for name in about["files"]})
                os.utime(entry / "entry.json")  # a use: pruned last
                for note in about.get("notes", []):  # what the stage assumed, said again
                    LOG.warning(note)
                return about["result"], True, key
            except FileNotFoundError:
                pass  # pruned by another process meanwhile: computed again below
        with noted() as notes:
            result = compute()
        files = {}
        for name in outputs:
            path = folder / name
            found = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else (
                [path] if path.is_file() else [])
            files.update({p.relative_to(folder).as_posix(): p for p in found})
        self.store(stage, key, files, {"result": result, "settings": settings,
                                       "files": sorted(files), "notes": notes})
        return result, False, key

    def entries(self) -> list[Entry]:
        """Every whole entry, least recently used first."""
        found = []
        if not self.root.is_dir():
            return found
        for about in self.root.glob("*/*/entry.json"):
            folder = about.parent
            if not is_entry(folder):  # someone else's entry.json: not the cache's
                continue
            try:
                size = sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())
                found.append(Entry(folder, folder.parent.name, size, about.stat().st_mtime))
            except FileNotFoundError:
                continue  # removed by another process while we looked
        return sorted(found, key=lambda e: e.used)

    def prune(self, max_bytes: int) -> list[Entry]:
        """Remove the least recently used entries until the rest take at most `max_bytes`,
        and the private folders of fills killed more than a day ago; returns the entries
        removed. An entry is renamed away before it is deleted, so no run reads half of
        one. InputError, and nothing removed, for a root that is not the cache's."""
        if not self.root.is_dir() or not any(self.root.iterdir()):
            return []  # nothing made yet, nothing to remove
        if not self.is_cache():
            raise InputError(self.root, "is not a flowerpose stage cache (no CACHEDIR.TAG of "
                             "its own and no entry it made): nothing in it is deleted")
        self._tag()
        entries = self.entries()
        total = sum(e.size for e in entries)
        removed = []
        for entry in entries:
            if total <= max_bytes:
                break
            doomed = entry.folder.parent / f".{entry.folder.name}.pruned-{uuid.uuid4().hex[:8]}"
            try:
                os.rename(entry.folder, doomed)
            except FileNotFoundError:
                continue
            shutil.rmtree(doomed, ignore_errors=True)
            total -= entry.size
            removed.append(entry)
        stale = time.time() - _STALE_FILL_S
        for private in self.root.glob("*/.*.partial-*"):
            if not (_is_key(private.name[1:].split(".partial-")[0])
                    and (private / _FILL_MARK).is_file()):
                continue  # not a fill of the cache's
            try:
                if private.stat().st_mtime < stale:
                    shutil.rmtree(private, ignore_errors=True)
            except FileNotFoundError:
                continue
        for doomed in self.root.glob("*/.*.pruned-*"):  # a prune killed while deleting
            key, _, tail = doomed.name[1:].partition(".pruned-")
            if _is_key(key) and len(tail) == 8 and set(tail) <= _KEY_CHARS:
                shutil.rmtree(doomed, ignore_errors=True)
        return removed


def prune_to_limit(root: Path) -> list[Entry]:
    """After a run that filled the cache at `root`: its least recently used entries
    removed until the rest fit `max_cache_bytes()`, said in a line when any were."""
    removed = StageCache(root).prune(max_cache_bytes())
    if removed:
        LOG.info(f"cache: removed {len(removed)} least recently used entries "
                 f"({sum(e.size for e in removed) / 1e6:.0f} MB) to stay within "
                 f"{max_cache_bytes() / 1e9:g} GB ({root}; FLOWERPOSE_CACHE_MAX_GB sets it)")
    return removed
