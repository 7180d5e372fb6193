"""Output folders that a command owns: it deletes only what it wrote itself.

A command's output folder holds a marker, `.flowerpose-output.json`, naming the stage that
wrote it, the files it recorded and the top-level entries it declared it writes. A folder
that does not exist or is empty becomes the stage's; one with the same stage's marker is
its own earlier output, whose recorded files are set aside (moved into
`.flowerpose-previous/` in the folder) while the new ones are written and deleted only
when the new output is whole: a run that fails puts them back, and a run killed before it
finished has them put back by the next one before it starts, so a finished output is never
lost to an unfinished one. Anything else (another stage's output, or files flowerpose did
not write) is refused with one line, unless the user says `--overwrite`, and even then
nothing of it is deleted or written over: a stage names the top-level entries it writes
(`writes`), and one of them already there that is not its own earlier output is refused,
--overwrite or not.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import weakref
from pathlib import Path

from flowerpose.atomic import temporary_beside
from flowerpose.errors import InputError
from flowerpose.jsonio import read_json, write_json

MARKER = ".flowerpose-output.json"
#: The lock a command holds on its output folder while it runs: a second command into the
#: same folder is refused (the operating system releases it when the process ends).
LOCK = ".flowerpose-output.lock"
#: Where a run sets its stage's earlier output aside until its own is whole.
PREVIOUS = ".flowerpose-previous"
#: The folder's own bookkeeping, never counted as its contents.
BOOKKEEPING = (MARKER, LOCK, PREVIOUS)


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


def _own_earlier(folder: Path, stage: str) -> set[str]:
    """Top-level names of this stage's earlier output in `folder`: the files its marker
    lists, and the entries that run declared (`writes`), which it found absent or its own
    before it wrote them."""
    previous = _previous(folder)
    if previous is None or previous["stage"] != stage:
        return set()
    declared = previous.get("writes", [])
    names = previous["files"] + (declared if isinstance(declared, list) else [])
    return {Path(name).parts[0] for name in names if isinstance(name, str) and Path(name).parts}


def _refuse_foreign(folder: Path, stage: str, writes: tuple[str, ...], own: set[str]) -> None:
    for name in writes:
        if (folder / name).exists() and name not in own:
            raise InputError(folder / name, f"was not written by flowerpose {stage}, and "
                             "nothing is ever written over what flowerpose did not write: "
                             "choose an empty or new folder")


def check_output(folder: str | Path, stage: str, overwrite: bool = False,
                 writes: tuple[str, ...] = ()) -> None:
    """Refuse, before any work, a folder that this stage may not write into: one holding
    what it did not write (unless `overwrite`), or, even with `overwrite`, one where an
    entry the stage writes (`writes`, top-level names) exists and is not its own."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise InputError(folder, "is a file, not a folder")
    check_folder_writable(folder)
    if not folder.is_dir():
        return
    entries = sorted(p.name for p in folder.iterdir() if p.name not in BOOKKEEPING)
    previous = _previous(folder)
    _refuse_foreign(folder, stage, writes, _own_earlier(folder, stage))
    if not entries or overwrite or (previous is not None and previous["stage"] == stage):
        return
    what = (f"the output of flowerpose {previous['stage']}" if previous is not None
            else f"files flowerpose {stage} did not write ({', '.join(entries[:3])}"
            + (", ..." if len(entries) > 3 else "") + ")")
    raise InputError(folder, f"holds {what}; choose an empty or new folder, or add --overwrite")


def check_folder_writable(folder: Path) -> None:
    """Refuse, before any work, a folder nothing can be written into: it, or where it is
    not there yet the nearest folder above it, takes a file (made beside where the run's
    files go, then removed: permissions alone miss root and read-only mounts).
    `cli.options.check_writable` is the same for a file path."""
    target = folder
    while not target.exists() and target != target.parent:
        target = target.parent
    try:
        temporary_beside(target / "write-test", ".check").unlink()
    except OSError as error:
        raise InputError(folder, f"cannot write into {target} ({error.strerror or error}); "
                         "choose another folder") from None


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    else:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()


class OutputFolder:
    """A stage's claim on its output folder; `record` each file written, then `finish`.

    writes: the top-level entries the stage will write (`check_output`). Whatever else was
    in the folder is foreign: `record` refuses it, so it never becomes the stage's to
    delete on the next run."""

    def __init__(self, folder: str | Path, stage: str, overwrite: bool = False,
                 writes: tuple[str, ...] = ()):
        self.folder = Path(folder)
        self.stage = stage
        self.writes = tuple(writes)
        check_output(self.folder, stage, overwrite, writes)
        self.created = not self.folder.exists()
        self.folder.mkdir(parents=True, exist_ok=True)
        self._lock = _lock(self.folder, stage)
        # A command that fails without finishing still lets go of the folder.
        self._unlock = weakref.finalize(self, os.close, self._lock)
        _put_back(self.folder)  # a run killed before it finished: the earlier output again
        previous = _previous(self.folder)
        own = _own_earlier(self.folder, stage)
        if previous is not None and previous["stage"] == stage:
            _set_aside(self.folder, previous)
        self._foreign = {p.name for p in self.folder.iterdir()
                         if p.name not in BOOKKEEPING} - own
        self.files: list[str] = []
        self._write(complete=False)

    def _write(self, complete: bool) -> None:
        write_json(self.folder / MARKER, {"stage": self.stage, "complete": complete,
                                          "files": sorted(set(self.files)),
                                          "writes": list(self.writes)})

    def record(self, *paths: str | Path) -> None:
        """Note files (or folders) this stage wrote in its folder; one inside an entry that
        was there before the stage claimed the folder is refused (it is not the stage's)."""
        for path in paths:
            relative = os.path.relpath(Path(path), self.folder)
            if Path(relative).parts[0] in self._foreign or relative.startswith(".."):
                raise InputError(Path(path), f"was not written by flowerpose {self.stage}; "
                                 "it is kept and not claimed")
            self.files.append(relative)
        self._write(complete=False)

    def finish(self) -> None:
        """The stage's output is whole: the earlier one set aside goes."""
        self._write(complete=True)
        _remove(self.folder / PREVIOUS)
        self.release()

    def release(self) -> None:
        """Give up the folder's lock (the process ending does too)."""
        self._unlock()

    def abandon(self) -> None:
        """The command ended without output: the earlier output it set aside goes back,
        and a folder it made and left holding only its bookkeeping is removed, so a refused
        command leaves nothing behind."""
        _put_back(self.folder)
        self.release()
        if self.created and self.folder.is_dir() and all(
                p.name in BOOKKEEPING for p in self.folder.iterdir()):
            for name in BOOKKEEPING:
                with contextlib.suppress(FileNotFoundError):
                    (self.folder / name).unlink()
            with contextlib.suppress(OSError):
                self.folder.rmdir()


def _set_aside(folder: Path, previous: dict) -> None:
    """Move a stage's earlier recorded output, and its marker, into folder/PREVIOUS."""
    aside = folder / PREVIOUS
    _remove(aside)
    aside.mkdir()
    for name in previous["files"]:
        source = (folder / name).resolve()
        if folder.resolve() not in source.parents or not source.exists():
            continue  # never outside the folder
        target = aside / "files" / name
        target.parent.mkdir(parents=True, exist_ok=True)
        os.replace(source, target)
    write_json(aside / "marker.json", previous)


def _put_back(folder: Path) -> None:
    """Where an earlier output is set aside (a run that did not finish), put it back: what
    the unfinished run wrote at its names goes, its files return, and its marker."""
    aside = folder / PREVIOUS
    if not (aside / "marker.json").is_file():
        _remove(aside)  # set aside and not yet marked: nothing was moved
        return
    previous = read_json(aside / "marker.json")
    unfinished = _previous(folder)
    if unfinished is not None and unfinished.get("stage") == previous.get("stage"):
        for name in unfinished["files"]:
            partial = (folder / name).resolve()
            if folder.resolve() in partial.parents:
                _remove(partial)
    kept = aside / "files"
    if kept.is_dir():
        for entry in kept.iterdir():
            _merge_back(entry, folder / entry.name)
    write_json(folder / MARKER, previous)
    _remove(aside)


def _merge_back(source: Path, target: Path) -> None:
    """Move `source` (a file or folder set aside) back to `target`, into what is there."""
    if source.is_dir() and target.is_dir():
        for entry in source.iterdir():
            _merge_back(entry, target / entry.name)
        return
    _remove(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    os.replace(source, target)


def _lock(folder: Path, stage: str) -> int:
    """An exclusive lock on the folder for this process; InputError when another command
    holds it."""
    import fcntl

    handle = os.open(folder / LOCK, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(handle)
        raise InputError(folder, f"is in use by another running flowerpose command; wait for "
                         f"it or choose another folder for {stage}") from None
    return handle


def publish(staging: Path, folder: str | Path, stage: str, overwrite: bool = False) -> Path:
    """Move a stage's finished output from `staging` (a folder it filled) into `folder`,
    replacing only its own earlier output there; staging is removed. An entry there that is
    not its own refuses the whole move, before anything moves."""
    entries = sorted(staging.iterdir())
    output = OutputFolder(folder, stage, overwrite, tuple(e.name for e in entries))
    for entry in entries:
        target = output.folder / entry.name
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
