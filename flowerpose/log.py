"""What flowerpose says on stderr besides its errors: progress, notes and warnings, through
one logger, and progress bars with the time left.

The result of a command goes to stdout (tables, paths, JSON); everything said along the
way goes to the `flowerpose` logger, at INFO for progress and WARNING for notes and
warnings. `configure` (the command line's `-q` / `-v`) sets what is shown, for the command
and for the worker processes it starts. `Tally` counts the parts of a long job (an eval's
plants): a line per part with the time left (`eta`), under a tqdm bar on a terminal,
nothing with `-q`. Errors are not logged: the command line prints them as one line whatever the
verbosity. Used as a library without `configure`, only warnings show.

Other libraries speak in their own words, and not to this project's users: while a command
runs (`third_party`, and in its workers), Python warnings (numpy's RuntimeWarnings among
them) and other libraries' log records become debug lines, shown with -v only; Open3D's own
log is kept to errors (`open3d`), and what a C library prints where it matters (Open3D's and
RPly's complaints about a file being read) is taken (`library_output`) and said by the
reader in its own words, as one error line naming the file.
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
import re
import sys
import warnings
from collections.abc import Iterator

from flowerpose.stopwatch import Stopwatch

LOG = logging.getLogger("flowerpose")

#: How `configure` hands its verbosity to spawned worker processes.
VERBOSITY_ENV = "FLOWERPOSE_VERBOSITY"

_LEVELS = {-1: logging.WARNING, 0: logging.INFO, 1: logging.DEBUG}

class _CurrentStderr(logging.StreamHandler):
    """A handler writing to whatever sys.stderr is when a record comes (a test, or tqdm,
    may have replaced it since)."""

    def __init__(self):
        super().__init__(sys.stderr)

    @property
    def stream(self):  # type: ignore[override]
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:
        pass


def configure(verbosity: int = 0) -> None:
    """Show warnings only (-1, `-q`), progress too (0, the default) or debugging detail (1,
    `-v`), here and in the worker processes started from now on."""
    verbosity = max(-1, min(1, int(verbosity)))
    LOG.setLevel(_LEVELS[verbosity])
    os.environ[VERBOSITY_ENV] = str(verbosity)


def _install() -> None:
    """flowerpose's own stderr handler, warnings only until `configure`: notes reach the
    user whatever handlers the application gave the root logger."""
    if not any(isinstance(h, _CurrentStderr) for h in LOG.handlers):
        handler = _CurrentStderr()
        handler.setFormatter(logging.Formatter("%(message)s"))
        LOG.addHandler(handler)
    LOG.setLevel(logging.WARNING)
    LOG.propagate = False


def configure_worker() -> None:
    """In a worker process: the verbosity its command was given (`configure`), and other
    libraries' warnings as debug lines (`third_party`) for as long as it lives."""
    if VERBOSITY_ENV in os.environ:
        configure(int(os.environ[VERBOSITY_ENV]))
    warnings.showwarning = _warning_as_debug
    logging.getLogger().addHandler(_LIBRARY_HANDLER)


def _warning_as_debug(message, category, filename, lineno, file=None, line=None) -> None:
    LOG.debug(f"{category.__name__} ({filename}:{lineno}): {message}")


class _LibraryRecords(logging.Handler):
    """Other libraries' log records (matplotlib's font cache, trimesh, paho) as debug
    lines of this logger, where Python would print their warnings to stderr."""

    def emit(self, record: logging.LogRecord) -> None:
        LOG.debug(f"{record.name}: {record.getMessage()}")


_LIBRARY_HANDLER = _LibraryRecords()


@contextlib.contextmanager
def third_party() -> Iterator[None]:
    """While a command runs: Python warnings (each once per place, as Python's filters
    say) and other libraries' log records become this logger's debug lines (-v); the code
    that knows when one matters catches it and says so in its own words."""
    root = logging.getLogger()
    with warnings.catch_warnings():
        warnings.showwarning = _warning_as_debug
        root.addHandler(_LIBRARY_HANDLER)
        try:
            yield
        finally:
            root.removeHandler(_LIBRARY_HANDLER)


class _Notes(logging.Handler):
    """The warnings said while it is attached, as their lines."""

    def __init__(self):
        super().__init__(logging.WARNING)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        if record.getMessage() not in self.lines:
            self.lines.append(record.getMessage())


@contextlib.contextmanager
def noted() -> Iterator[list[str]]:
    """The warnings this process says meanwhile (whatever the verbosity shows), each once,
    in order: what a run assumed about its inputs, for its report to state beside its
    numbers (flowers.json's and report.json's "notes")."""
    notes = _Notes()
    LOG.addHandler(notes)
    try:
        yield notes.lines
    finally:
        LOG.removeHandler(notes)


def open3d():
    """The open3d module, its own log kept to errors (which it raises as exceptions too),
    its warnings only with -v: where one matters (a file that cannot be read) the reader
    says so itself (`library_output`)."""
    import open3d as o3d

    level = (o3d.utility.VerbosityLevel.Warning if LOG.isEnabledFor(logging.DEBUG)
             else o3d.utility.VerbosityLevel.Error)
    o3d.utility.set_verbosity_level(level)
    return o3d


_ANSI = re.compile(r"\x1b\[[0-9;]*m")


@contextlib.contextmanager
def library_output(taken: str) -> Iterator[list[str]]:
    """The lines libraries print meanwhile that match the regular expression `taken`,
    colour codes removed, given to the caller instead of shown: Open3D's log (printed
    through Python's sys.stdout) and what C code prints on the descriptors (RPly, on
    stderr; taken by wurlitzer). Whatever else was printed meanwhile (another thread's
    lines) is passed on."""
    from wurlitzer import pipes

    lines: list[str] = []
    python_out, python_err = io.StringIO(), io.StringIO()
    c_out = c_err = io.StringIO()
    try:
        with pipes() as (c_out, c_err), contextlib.redirect_stdout(python_out), \
                contextlib.redirect_stderr(python_err):
            yield lines
    finally:
        pattern = re.compile(taken)
        for said, stream in ((python_out.getvalue() + c_out.read(), sys.stdout),
                             (python_err.getvalue() + c_err.read(), sys.stderr)):
            printed = _ANSI.sub("", said).splitlines()
            lines.extend(line for line in printed if pattern.search(line))
            rest = [line for line in printed if not pattern.search(line)]
            if rest:
                stream.write("\n".join(rest) + "\n")


def eta(elapsed: float, done: int, total: int) -> str:
    """"(12 s in, about 30 s left)": the `elapsed` seconds and, at the rate so far, the
    time the rest of `total` will take."""
    left = elapsed / done * (total - done) if done else float("nan")
    return f"({_duration(elapsed)} in" + (f", about {_duration(left)} left)" if done < total
                                          else ")")


def _duration(seconds: float) -> str:
    if seconds != seconds:  # NaN: nothing done yet
        return "?"
    if seconds < 60:
        return f"{seconds:.0f} s"
    minutes, seconds = divmod(round(seconds), 60)
    return f"{minutes} min {seconds:02d} s" if minutes < 60 else \
        f"{minutes // 60} h {minutes % 60:02d} min"


class Tally:
    """Finished parts of a job that ends in `total` of them (plants of an eval, settings of
    a sweep, a scan's waypoints, images of a matching), said in lines with the time left,
    under a bar on a terminal."""

    def __init__(self, total: int, what: str = ""):
        self.total, self.done, self.watch = total, 0, Stopwatch()
        self._bar = None
        if total and LOG.isEnabledFor(logging.INFO) and sys.stderr.isatty():
            from tqdm import tqdm

            self._bar = tqdm(total=total, desc=what, leave=False, dynamic_ncols=True)

    def __enter__(self) -> Tally:
        return self

    def __exit__(self, *exc) -> None:
        if self._bar is not None:
            self._bar.close()

    def finished(self, message: str) -> None:
        """One more part is done: `message` says what came of it."""
        self.advance(1, f"[{self.done + 1}/{self.total}] {message}")

    def advance(self, parts: int, message: str | None = None) -> None:
        """`parts` more are done (frames, pairs, waypoints of a loop that reports now and
        then); `message`, when given, is said with the time left."""
        self.done += parts
        if self._bar is not None:
            self._bar.update(parts)
        if message is None:
            return
        line = f"{message} {eta(self.watch.elapsed(), self.done, self.total)}"
        if self._bar is not None:
            self._bar.write(line, file=sys.stderr)
        else:
            LOG.info(line)


_install()
