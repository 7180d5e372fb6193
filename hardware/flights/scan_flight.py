"""Running a planned scan on any bot, and resuming one that was interrupted.

The executor moves through the plan's waypoints (move, turn the head, pause for the
autofocus) while the bot's camera records, and writes the scan folder (`flowerpose.scanio`).
After every waypoint `scan.json` records how far the scan got, atomically, so an interrupted
scan (an error, Ctrl-C, a dropped link) resumes at the next waypoint with every recorded
frame kept. A waypoint counts as done only once the camera has every frame of it on disk
with its pose (`Camera.recorded_until`): a power cut, which runs no clean-up, then costs
the waypoints still in the camera's queue or open bin a second flight, never a hole.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from flowerpose.errors import InputError
from flowerpose.hardware.bot import Bot
from flowerpose.hardware.flights.flight_journal import Journal, folder_lock
from flowerpose.hardware.flights.scan_plan import ScanPlan
from flowerpose.jsonio import read_json, write_json
from flowerpose.log import LOG, Tally


def plan_id(plan: ScanPlan) -> str:
    """A short fingerprint of the plan's head poses, so a resume never mixes two scans."""
    values = np.concatenate([np.r_[w.pose.gantry, w.pose.yaw, w.pose.pitch]
                             for w in plan.waypoints])
    return hashlib.sha1(np.round(values, 6).tobytes()).hexdigest()[:16]


def _progress(message: str) -> None:
    LOG.info(message)


#: What scan.json says when it belongs to another plan.
OTHER_SCAN = "holds a different scan (another plant or path); choose a new scan folder"

#: Held (flock) by the one scan recording into a folder; the OS lets go when it dies.
LOCK_NAME = ".scan.lock"


def check_scan_folder(out_dir: Path) -> None:
    """Refuse a folder that holds files but no scan (a plant folder, another stage's
    output): a scan writes camera.json, frames/ and trajectory.csv, and must not write them
    over what it did not record."""
    if not out_dir.is_dir() or (out_dir / "scan.json").is_file():
        return
    entries = sorted(p.name for p in out_dir.iterdir() if p.name != LOCK_NAME)
    if entries:
        listed = ", ".join(entries[:3]) + (", ..." if len(entries) > 3 else "")
        raise InputError(out_dir, f"holds files that are not a flowerpose scan ({listed}); "
                         "choose an empty or new folder (a scan folder of the same plan "
                         "resumes)")


def run_scan(bot: Bot, plan: ScanPlan, out_dir: Path, *, source: dict,
             progress: bool = True) -> dict:
    """Scan along `plan` with `bot`, recording into out_dir; resumes a scan of the same plan
    already in out_dir. Returns scan.json's content. `source` describes the bot and plant
    (written into scan.json). Refuses a folder another scan is recording into
    (`scan_lock`) and one that holds files but no scan (`check_scan_folder`)."""
    out_dir = Path(out_dir)
    check_scan_folder(out_dir)
    with folder_lock(out_dir, LOCK_NAME, "scan"):
        return _run_scan(bot, plan, out_dir, source, progress)


def _recorded(ends: list[float], recorded_until: float) -> int:
    """How many of the waypoints that ended at bot-clock `ends` (ascending) have every frame
    on disk."""
    return int(np.searchsorted(ends, recorded_until, side="right"))


def _run_scan(bot: Bot, plan: ScanPlan, out_dir: Path, source: dict, progress: bool) -> dict:
    journal = Journal.open(
        out_dir / "scan.json", plan_id(plan),
        {"source": source, "plan": plan.to_json(), "waypoints": len(plan.waypoints),
         "completed": 0}, kept=("completed", "source"),  # the first session's source
        other_plan=OTHER_SCAN,
        redone="waypoints whose frames were not yet on disk are flown again")
    manifest = journal.record
    start = int(manifest["completed"])
    if start >= len(plan.waypoints):
        if progress:
            _progress(f"scan: {out_dir} holds this plan's scan, complete: nothing recorded "
                      "(choose a new scan folder to scan again)")
        manifest["status"] = "complete"
        return manifest
    if start and progress:
        _progress(f"scan: resuming at waypoint {start} of {len(plan.waypoints)}"
                  + (" (the last session ended without closing)" if journal.cut else ""))
    out_dir.mkdir(parents=True, exist_ok=True)
    intrinsics = bot.camera.intrinsics()
    if journal.path.exists() and (out_dir / "camera.json").exists():
        recorded = read_json(out_dir / "camera.json")
        if any(not np.isclose(float(recorded.get(k, np.nan)), float(v))
               for k, v in intrinsics.items() if isinstance(v, int | float)):
            raise InputError(out_dir / "camera.json", "the scan was recorded with other camera "
                             "settings; resume with the same ones or choose a new scan folder")
    ends: list[float] = []  # bot-clock end of each waypoint flown in this session
    # The session is written first: a folder with anything in it is a scan.
    with journal.session(bot, started_waypoint=start, source=source) as session:
        recording = False
        try:
            write_json(out_dir / "camera.json", intrinsics)
            bot.camera.start_recording(out_dir / "video.mp4")
            recording = True
            with Tally(len(plan.waypoints) - start if progress else 0, "waypoints") as tally:
                for waypoint in plan.waypoints[start:]:
                    bot.move_to(waypoint.pose.gantry)
                    bot.set_head(float(waypoint.pose.yaw), float(waypoint.pose.pitch))
                    bot.dwell(plan.config.pause_s)
                    ends.append(bot.now())
                    # Done only once its frames are on disk with their poses: the camera may
                    # still hold some in a queue or an open bin, which a power cut would lose.
                    manifest["completed"] = start + _recorded(ends, bot.camera.recorded_until())
                    journal.save()
                    LOG.debug(f"scan: waypoint {waypoint.index + 1}/{len(plan.waypoints)} "
                              f"({waypoint.kind}) at bot clock {bot.now():.1f} s")
                    tally.advance(1, f"scan: waypoint {waypoint.index + 1}/"
                                  f"{len(plan.waypoints)} at bot clock {bot.now():.0f} s"
                                  if progress and (waypoint.index + 1) % 20 == 0 else None)
        finally:
            try:
                if recording:
                    session["frames"] = bot.camera.stop_recording().frames
            finally:
                manifest["completed"] = start + _recorded(ends, bot.camera.recorded_until())
    return manifest


def approach_start(bot: Bot, plan: ScanPlan, out_dir: Path) -> None:
    """Lift the head to the top of Z where the bot stands, then travel over the waypoint the
    scan starts (or resumes) at: the scan's first move then only descends, where a direct
    move from wherever the bot stood might sweep through the plant."""
    manifest = Journal.read(out_dir / "scan.json", plan_id(plan), OTHER_SCAN)
    start = 0 if manifest is None else int(manifest.get("completed", 0))
    if start >= len(plan.waypoints):
        return
    here = bot.position()
    if not np.all(np.isfinite(here)):
        raise InputError(bot.info.name, "the gantry's position is unknown: home the bot "
                         "before scanning")
    top = bot.info.travel_max[2]
    target = plan.waypoints[start].pose.gantry
    bot.move_to([here[0], here[1], top])
    bot.move_to([target[0], target[1], top])
