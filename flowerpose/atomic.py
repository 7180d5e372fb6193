"""One way to write a result file: whole, or not at all.

Every writer (JSON, CSV, Markdown, PNG, PLY, meshes, figures) fills a temporary file in the
target's folder, which is flushed to disk and renamed over the target. An interruption or
a full disk leaves the previous file as it was and no half-written file that a later run
could trust; a failure is an InputError naming the file (one line, exit status 2).
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

from flowerpose.errors import InputError

#: The process's umask (read once: os.umask can only be read by setting it): written files
#: get the mode an ordinary open() would give them, not mkstemp's 0600.
_UMASK = os.umask(0o022)
os.umask(_UMASK)


def _fsync(path: str | Path, directory: bool = False) -> None:
    flags = os.O_RDONLY | (getattr(os, "O_DIRECTORY", 0) if directory else 0)
    try:
        handle = os.open(path, flags)
    except OSError:
        if directory:  # some file systems cannot open a folder; the rename still stands
            return
        raise
    try:
        os.fsync(handle)
    except OSError:
        if not directory:
            raise
    finally:
        os.close(handle)


def temporary_beside(path: Path, suffix: str) -> Path:
    """A new empty file in `path`'s folder, named after it and hidden (raises OSError where
    the folder takes no file): where a write goes before it is renamed over `path`."""
    handle, name = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=suffix, dir=path.parent)
    os.close(handle)
    return Path(name)


def write_file(path: str | Path, write: Callable[[Path], object]) -> Path:
    """Write `path` through `write(temporary)`, which fills a temporary path in the same
    folder with the same suffix (writers that go by the suffix see the right one). A
    writer that returns False has failed, as has one that raises OSError."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        temporary = temporary_beside(path, f".tmp{path.suffix}")
        os.chmod(temporary, 0o666 & ~_UMASK)
    except OSError as err:
        raise InputError(path, f"cannot write ({err.strerror or err})") from None
    try:
        if write(temporary) is False:
            raise InputError(path, "cannot write (the writer failed: is the disk full?)")
        _fsync(temporary)
        os.replace(temporary, path)
        _fsync(path.parent, directory=True)
    except OSError as err:
        raise InputError(path, f"cannot write ({err.strerror or err})") from None
    finally:
        with contextlib.suppress(FileNotFoundError):
            temporary.unlink()
    return path


def write_text(path: str | Path, text: str) -> Path:
    """Write UTF-8 text whole."""
    return write_file(path, lambda tmp: tmp.write_text(text, encoding="utf-8"))


def write_bytes(path: str | Path, data: bytes) -> Path:
    """Write bytes whole."""
    return write_file(path, lambda tmp: tmp.write_bytes(data))


def write_image(path: str | Path, rgb: np.ndarray, params: list[int] | None = None) -> Path:
    """Write an RGB (or grey, or 16-bit) image whole, in the format of the path's suffix.

    rgb: (H, W, 3) uint8 RGB, or (H, W) uint8/uint16. OpenCV encodes in memory, so an image
    it cannot encode is an error before anything is written.
    """
    path = Path(path)
    import cv2

    image = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR) if rgb.ndim == 3 else rgb
    try:
        ok, encoded = cv2.imencode(path.suffix, image, params or [])
    except cv2.error:
        ok = False
    if not ok:
        raise InputError(path, f"cannot encode the image as {path.suffix}")
    return write_bytes(path, encoded.tobytes())


def write_figure(path: str | Path, figure, dpi: int = 100) -> Path:
    """Save a matplotlib figure whole, in the format of the path's suffix."""
    path = Path(path)
    return write_file(path, lambda tmp: figure.savefig(tmp, dpi=dpi,
                                                       format=path.suffix.lstrip(".")))
