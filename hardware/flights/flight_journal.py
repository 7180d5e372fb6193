"""The record of a resumable flight (a scan's scan.json, a pollination's flight.json): one
owner for what both executors keep.

A journal is one JSON file, rewritten atomically after every step, that names the plan it
flies by a fingerprint (a resume never mixes two plans), keeps what is done, and lists the
sessions that flew it: each with its start and end on the bot's clock and the wall clock
and, where it ended by an error, the error. A folder is flown by one process at a time (a
lock the OS lets go when the process dies), so a last session that never recorded its end
died without closing (a power cut, a kill): the next session says so in it.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from flowerpose.errors import InputError
from flowerpose.jsonio import read_json, write_json
from flowerpose.stopwatch import Stopwatch

#: What a session that never closed is marked with when the next one opens the journal.
CUT_SHORT = "ended without closing (power cut or killed)"


@contextlib.contextmanager
def folder_lock(folder: Path, name: str, what: str) -> Iterator[None]:
    """`folder` for this process alone while the block runs (flock on folder/name): a
    second flight into it is refused with one line instead of interleaving with the first.
    `what`: the flight, as the refusal says it ("scan")."""
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / name, "a+") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            lock.seek(0)
            holder = lock.read().strip() or "another process"
            raise InputError(folder, f"another {what} ({holder}) is under way in this "
                             "folder; wait for it to end or choose another folder") from None
        lock.seek(0)
        lock.truncate()
        lock.write(f"pid {os.getpid()}")
        lock.flush()
        yield


class Journal:
    """One flight's record (`record`, the JSON document) at `path`."""

    def __init__(self, path: Path, record: dict[str, Any], cut: bool):
        self.path = path
        self.record = record
        self.cut = cut
        """The last session before this one died without closing."""

    @classmethod
    def open(cls, path: Path, fingerprint: str, fresh: dict[str, Any],
             kept: tuple[str, ...], other_plan: str, redone: str) -> Journal:
        """The journal of the plan `fingerprint` at `path`: a new record of `fresh`'s fields
        (status "running", no sessions), or, where one exists, that one's sessions and its
        `kept` fields (what is done) on top; a record of another plan is refused with
        `other_plan` (what to do instead); a session cut short is marked with what the
        resume flies again (`redone`). Nothing is written yet."""
        record = {"version": 1, "plan_id": fingerprint, **fresh, "status": "running",
                  "sessions": []}
        cut = False
        previous = cls.read(path, fingerprint, other_plan)
        if previous is not None:
            record.update({key: previous[key] for key in kept if key in previous},
                          sessions=list(previous.get("sessions", [])))
            cut = (previous.get("status") == "running" and bool(record["sessions"])
                   and "bot_time_end" not in record["sessions"][-1])
            if cut:  # the lock is ours, so that session is not running: it died
                record["sessions"][-1].setdefault("error", f"{CUT_SHORT}; {redone}")
        return cls(path, record, cut)

    @staticmethod
    def read(path: Path, fingerprint: str, other_plan: str) -> dict[str, Any] | None:
        """The record at `path` of the plan `fingerprint` (None: none yet); one of another
        plan is refused with `other_plan`, so a resume never mixes two plans."""
        if not path.exists():
            return None
        previous = read_json(path)
        if previous.get("plan_id") != fingerprint:
            raise InputError(path, other_plan)
        return previous

    def save(self) -> None:
        """Write the record (atomically: a cut write leaves the last one whole)."""
        write_json(self.path, self.record)

    @contextlib.contextmanager
    def session(self, bot: Any, **fields: Any) -> Iterator[dict[str, Any]]:
        """A session of flying with `bot` (its clock: `now()`): recorded as it starts, then
        the record's status "complete" when the block ends, "interrupted" with the first
        error when it raises (the error goes on), and the session's end written either
        way. Yields the session's entry, for the caller's fields."""
        session = {**fields, "bot_time_start": bot.now(), "wall_start": time.time()}
        self.record["sessions"].append(session)
        self.save()
        wall = Stopwatch()
        try:
            yield session
            self.record["status"] = "complete"
        except BaseException as err:
            self.record["status"] = "interrupted"
            session.setdefault("error", f"{type(err).__name__}: {err}")
            raise
        finally:
            session.update(bot_time_end=bot.now(), wall_s=round(wall.elapsed(), 3))
            self.save()
