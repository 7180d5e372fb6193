"""The one clock behind every `timing_s` and `seconds` a stage reports: wall seconds of its
named steps and of the whole, from `time.perf_counter`."""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Iterator
from pathlib import Path


class Stopwatch:
    """Wall seconds of a stage's steps, kept by name, and of the stage since the watch was
    made. A step timed twice (triangulation before and after bundle adjustment) adds up."""

    def __init__(self) -> None:
        self.started = self._lapped = time.perf_counter()
        self.seconds: dict[str, float] = {}

    def elapsed(self) -> float:
        """Seconds since the watch was made."""
        return time.perf_counter() - self.started

    @contextlib.contextmanager
    def step(self, name: str) -> Iterator[None]:
        """Time the block as step `name`, even when it raises."""
        began = time.perf_counter()
        try:
            yield
        finally:
            self.add(name, time.perf_counter() - began)

    def lap(self, name: str) -> None:
        """The time since the last lap (or since the start) is step `name`: for a stage
        that runs its steps one after another."""
        now = time.perf_counter()
        self.add(name, now - self._lapped)
        self._lapped = now

    def add(self, name: str, seconds: float) -> None:
        """`seconds` more for step `name` (a step timed elsewhere, a worker's)."""
        self.seconds[name] = self.seconds.get(name, 0.0) + seconds

    def report(self, digits: int | None = None, total: str | None = "total") -> dict[str, float]:
        """The steps' seconds and, under `total`, the whole's so far; rounded to `digits`
        places when given."""
        seconds = dict(self.seconds)
        if total is not None:
            seconds[total] = self.elapsed()
        if digits is None:
            return seconds
        return {name: round(value, digits) for name, value in seconds.items()}


def process_age() -> float:
    """Seconds since this process was launched (Linux: /proc), so a command's printed wall
    time includes the interpreter's start and imports, as the user waited them; 0 where the
    system does not say."""
    try:
        ticks = int(Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()[19])
        uptime = float(Path("/proc/uptime").read_text().split()[0])
        return max(0.0, uptime - ticks / os.sysconf("SC_CLK_TCK"))
    except (OSError, ValueError, IndexError):
        return 0.0

