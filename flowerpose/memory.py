"""Sizes checked before they are allocated: an array whose size follows from settings is
refused in one line naming the setting when this machine cannot hold it, instead of a
library's traceback minutes later."""

from __future__ import annotations

import os

from flowerpose.errors import InputError

#: Largest array OpenCV's functions take, bytes: they index with 32-bit integers.
OPENCV_MAX_BYTES = 2**31 - 1
#: Share of the memory available now that one step may ask for.
MAX_SHARE = 0.8


def available_bytes() -> int | None:
    """Memory available to new allocations now, bytes (Linux's MemAvailable; else the free
    physical pages); None where the system does not say."""
    try:
        with open("/proc/meminfo") as handle:
            for line in handle:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def require_fits(nbytes: int, setting: str, what: str, opencv_array: int = 0) -> None:
    """Refuse `what` (nbytes in all; its largest single OpenCV array `opencv_array` bytes)
    where OpenCV cannot take that array or this machine lacks the memory, naming `setting`."""
    if opencv_array > OPENCV_MAX_BYTES:
        raise InputError(setting, f"{what} needs an array of {opencv_array / 1e9:.1f} GB, more "
                         f"than OpenCV takes ({OPENCV_MAX_BYTES / 1e9:.1f} GB); change {setting}")
    free = available_bytes()
    if free is not None and nbytes > MAX_SHARE * free:
        raise InputError(setting, f"{what} needs {nbytes / 1e9:.1f} GB, more than this machine "
                         f"has free ({free / 1e9:.1f} GB); change {setting}")
