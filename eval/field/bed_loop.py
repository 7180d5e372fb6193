"""The loop of a field run over a bed, whichever bot films it (`simulated_bed.py`: the
simulated bed, scored against its truth; `physical_bed.py`: the physical bot's): the bed's
journal, the plants filmed one after another in the planned order while a worker (a process,
or a Ray task inside `pool.on_ray`) processes the plant filmed before, and the bed's times.
The bot never waits for the computer: plant k is processed while plant k+1 is filmed, and
the last plants' work finishes after the bot is done.

`bed.json`, the bed's journal, is rewritten atomically after every step: the bed, the
order, and per plant its stage ("planned", "scanned", "detected" or "failed" with the
error) and seconds; its sessions as a flight's (`flight_journal`). Running the same command
again resumes: a detected plant is left alone, a scanned one only processed (one whose
processing failed too), a scan cut short resumed where its frames end. Another bed or
other settings in the same folder are refused.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Callable
from concurrent.futures import Future
from contextlib import AbstractContextManager
from pathlib import Path
from typing import Any

import numpy as np

from flowerpose.config import to_dict
from flowerpose.errors import InputError
from flowerpose.eval.pool import CAPTURE_CPUS, running_on_ray, spawn_pool, submit_job
from flowerpose.hardware.bot_errors import BotError
from flowerpose.hardware.flights.bed_plan import Bed, BedPlan
from flowerpose.hardware.flights.flight_journal import Journal
from flowerpose.log import eta
from flowerpose.stopwatch import Stopwatch

JOURNAL = "bed.json"
LOCK = ".bed.lock"
OTHER_BED = ("holds a field run of another bed, seed or settings; choose another --out (a "
             "run resumes only with the command that started it)")
#: What stops one plant's scan without ending the bed (with --keep-going): a bad request,
#: the disk, the bot or its camera.
SCAN_FAILURES = (InputError, OSError, RuntimeError, BotError)


def fingerprint(bed: Bed, settings: dict[str, Any]) -> str:
    """A bed run's identity (SHA-256): its bed, its scan path and `settings`, what its stages
    read of the config (the simulated bed: its seed and every setting; the physical bed:
    `physical_bed.settings_read`). A run resumes only under the same."""
    text_ = json.dumps({"plants": [dataclasses.asdict(p) for p in bed.plants],
                        "scan": to_dict(bed.scan), **settings}, sort_keys=True)
    return hashlib.sha256(text_.encode()).hexdigest()


def open_journal(out: Path, bed: Bed, fingerprint: str, fields: dict[str, Any]) -> Journal:
    """The bed's journal in `out` (a new one, or the run's own to resume; another run's
    refused), every plant "planned" at first."""
    if out.exists() and not out.is_dir():
        raise InputError(out, "is a file; --out is the bed's folder")
    return Journal.open(out / JOURNAL, fingerprint,
                        {**fields, "plants": {p.name: {"stage": "planned"} for p in bed.plants}},
                        kept=("plants", "timing_s"), other_plan=OTHER_BED,
                        redone="the plant being filmed resumes its scan")


@dataclasses.dataclass(frozen=True)
class BedOptions:
    """How a bed's field run goes, beside what it runs on and where its work runs."""

    keep_going: bool = False
    """Go on past a plant whose scan or processing fails (marked failed with its error);
    else the error ends the run."""
    pollinate: bool = False
    """Once every plant is processed, visit each detected plant's flowers."""
    say: Callable[[str], None] = print
    """Where the run's lines go."""


#: A bed's field run when not told: it stops at the first failure, pollinates nothing and
#: prints its lines.
WITHOUT_OPTIONS = BedOptions()


@dataclasses.dataclass(frozen=True)
class BedWork:
    """What a kind of bed brings to the loop."""

    plan: BedPlan
    folders: dict[str, Path]
    """Each plant's folder (its scan goes to folder/scan)."""
    film: Callable[[Any, int, Path], None]
    """(bot, the plant's index in the plan, its folder): film the plant into folder/scan,
    resuming a scan cut short."""
    job: Callable[[str], tuple[Callable, tuple]]
    """A plant's name -> the worker's function (module-level) and its arguments; it returns
    a dict with the plant's "seconds" per step, which go into the plant's journal entry with
    the rest."""
    said: Callable[[str, dict], str]
    """What is said of a plant once processed, given its name and the worker's result."""


def film_bed(journal: Journal, work: BedWork, bot: AbstractContextManager,
             keep_going: bool, say: Callable[[str], None],
             then: Callable[[Any], None] | None = None) -> None:
    """Film the bed's plants with `bot` (a context giving the bot, homed) in the plan's order,
    each processed in a worker as soon as it is filmed; into the journal as it goes. A plant
    whose scan or processing fails is marked failed with its error; with `keep_going` the
    bed goes on without it, else the error goes on (the bot's context closes: the
    connection dropped, the recording stopped). then: called with the bot once every plant
    is processed, before the bot's context closes (the physical bed's pollination)."""
    wall = Stopwatch()
    record, plan = journal.record, work.plan
    record["order"] = [p.name for p in plan.plants]
    record["plan"] = {"bot_s": round(plan.duration_s, 1),
                      "travel_s": [round(t, 1) for t in plan.travel_s]}
    journal.save()
    pool = None if running_on_ray() else spawn_pool(1)
    pending: dict[str, Future] = {}
    busy = _Busy()

    def submit(name: str) -> None:
        busy.start()
        function, arguments = work.job(name)
        pending[name] = submit_job(pool, function, arguments, cpus=CAPTURE_CPUS)
        pending[name].add_done_callback(lambda _: busy.stop())

    def collect(block: bool) -> None:
        for name in [n for n, f in pending.items() if block or f.done()]:
            entry = record["plants"][name]
            try:
                result = pending.pop(name).result()
            except Exception as error:  # a failed reconstruction or detection
                fail(entry, "reconstruct", error)
                recorded_failure(journal, say, f"{name}: failed ({entry['error']})",
                                 keep_going)
                continue
            seconds = {**entry.get("seconds", {}), **result.pop("seconds")}
            entry.update(stage="detected", **result, seconds=seconds)
            journal.save()
            say(f"{work.said(name, result)} ({detected(record)} of {len(plan.plants)} plants "
                f"done, the bed {wall.elapsed():.0f} s in)")

    # The bot waits for the computer between two plants' scans only: the frames are chosen
    # in the worker, with the rest of a plant's work.
    last_scan_end: float | None = None
    bot_waiting = first_filmed = 0.0
    filmed_before = _filmed_s(plan, record)
    try:
        with bot as flying, journal.session(flying):
            for index, (spot, scan_plan) in enumerate(zip(plan.plants, plan.scans,
                                                           strict=True)):
                entry = record["plants"][spot.name]
                if entry["stage"] == "detected":
                    continue
                if entry["stage"] == "scanned" or entry.get("failed_at") == "reconstruct":
                    submit(spot.name)  # filmed: its work is tried again, not its scan
                    continue
                # The bed's time left, at this session's pace through the plan's bot time.
                bed_time = eta(wall.elapsed(), _filmed_s(plan, record) - filmed_before,
                               plan.duration_s - filmed_before)
                say(f"[{index + 1}/{len(plan.plants)}] {spot.name}: filming "
                    f"{len(scan_plan.waypoints)} waypoints ({scan_plan.duration_s / 60:.1f} min "
                    f"of bot time); the bed {bed_time.strip('()')}")
                watch = Stopwatch()
                if last_scan_end is not None:
                    bot_waiting += wall.elapsed() - last_scan_end
                try:
                    work.film(flying, index, work.folders[spot.name])
                    watch.lap("scan")
                except SCAN_FAILURES as error:
                    fail(entry, "scan", error)
                    recorded_failure(journal, say, f"{spot.name}: failed ({entry['error']})",
                                     keep_going)
                    continue
                entry.update(stage="scanned", seconds=watch.report(digits=3, total=None))
                journal.save()
                submit(spot.name)
                last_scan_end = wall.elapsed()
                first_filmed = first_filmed or last_scan_end
                collect(block=False)
            filmed = wall.elapsed()
            collect(block=True)
            _add_times(record, {"bed": wall.elapsed(), "filming": filmed,
                                "after_filming": wall.elapsed() - filmed,
                                "computer_idle_while_filming": filmed - busy.total(filmed),
                                "bot_waiting": bot_waiting,
                                "after_first_plant": wall.elapsed() - first_filmed})
            if then is not None:
                then(flying)
    finally:
        if pool is not None:
            pool.shutdown(wait=False, cancel_futures=True)


def timing_text(times: dict[str, float]) -> str:
    """The bed's times in a sentence (report.md and report.html)."""
    waiting = times.get("bot_waiting", 0.0)
    share = waiting / times["after_first_plant"] if times.get("after_first_plant") else 0.0
    return (f"Bed: {times['bed']:.0f} s of wall time, {times['filming']:.0f} s of it "
            f"filming (the computer idle {times['computer_idle_while_filming']:.0f} s of "
            f"those), {times['after_filming']:.0f} s after the last plant was filmed. The "
            f"bot waited for the computer {waiting:.1f} s between plants "
            f"({100 * share:.1f} % of the bed's time after the first plant was filmed): "
            "each plant's frames are chosen, reconstructed and its flowers found in a "
            "worker while the next is filmed.")


def cut_to_plant(folder: Path, center_xy, radius_m: float) -> np.ndarray:
    """folder/reconstruction/cloud.ply cut to `radius_m` metres round the plant's axis at
    `center_xy` (bed frame, metres), written as plant_cloud.ply beside it; the kept points
    (N, 3), metres."""
    from flowerpose.cloudio import read_cloud, write_cloud

    cloud = read_cloud(folder / "reconstruction" / "cloud.ply", units="m")
    keep = np.hypot(*(cloud.points[:, :2] - np.asarray(center_xy, float)).T) <= radius_m
    write_cloud(folder / "reconstruction" / "plant_cloud.ply", cloud.subset(keep))
    return cloud.points[keep]


def _filmed_s(plan: BedPlan, record: dict) -> float:
    """The plan's bot seconds of the plants filmed so far (or given up on)."""
    return sum(scan.duration_s for scan, plant in zip(plan.scans, plan.plants, strict=True)
               if record["plants"][plant.name]["stage"] != "planned")


def _add_times(record: dict, seconds: dict[str, float]) -> None:
    """The bed's wall seconds, over every session that ran it."""
    times = record.setdefault("timing_s", {})
    for key, value in seconds.items():
        times[key] = round(times.get(key, 0.0) + value, 3)


class _Busy:
    """How long the worker has had a plant to process, between `start` and `stop` calls
    (the worker takes one plant at a time; a plant queued behind another counts once)."""

    def __init__(self) -> None:
        self._watch = Stopwatch()
        self._queued = 0
        self._since: float | None = None
        self._spans: list[tuple[float, float]] = []

    def start(self) -> None:
        if self._queued == 0:
            self._since = self._watch.elapsed()
        self._queued += 1

    def stop(self) -> None:
        self._queued -= 1
        if self._queued == 0 and self._since is not None:
            self._spans.append((self._since, self._watch.elapsed()))
            self._since = None

    def total(self, until: float) -> float:
        """Busy seconds up to `until` seconds after the run began."""
        spans = self._spans + ([(self._since, until)] if self._since is not None else [])
        return sum(max(0.0, min(end, until) - begin) for begin, end in spans)


def first_line(error: BaseException) -> str:
    """An error's first line: what a journal keeps of it."""
    return str(error).splitlines()[0]


def fail(entry: dict, stage: str, error: BaseException) -> None:
    """Mark a plant's journal entry failed at `stage`, with the error's first line."""
    entry.update(stage="failed", failed_at=stage, error=first_line(error))


def recorded_failure(journal: Journal, say: Callable[[str], None], line: str,
                     keep_going: bool) -> None:
    """Called in an `except` block once the journal's entry holds the error: the journal
    saved, `line` said, and the error raised again unless `keep_going`."""
    journal.save()
    say(line)
    if not keep_going:
        raise


def detected(record: dict) -> int:
    """The bed's plants processed so far."""
    return sum(p["stage"] == "detected" for p in record["plants"].values())


def text(value) -> str:
    """A table cell: "-" for nothing."""
    return "-" if value is None else str(value)
