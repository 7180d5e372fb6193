"""Running a planned scan on any bot, and resuming one that was interrupted.

The executor moves through the plan's waypoints (move, turn the head, pause for the
autofocus) while the bot's camera records, and writes the scan folder (`flowerpose.scanio`).
After every waypoint `scan.json` records how far the scan got, atomically, so an interrupted
scan (an error, Ctrl-C, a dropped link) resumes at the next waypoint with every recorded
frame kept.
"""

from __future__ import annotations

import hashlib
import sys
import time
from pathlib import Path

import numpy as np

from flowerpose.errors import InputError
from flowerpose.hardware.bot import Bot
from flowerpose.hardware.scanpath import ScanPlan
from flowerpose.jsonio import read_json, write_json


def plan_id(plan: ScanPlan) -> str:
    """A short fingerprint of the plan's head poses, so a resume never mixes two scans."""
    values = np.concatenate([np.r_[w.pose.gantry, w.pose.yaw, w.pose.pitch]
                             for w in plan.waypoints])
    return hashlib.sha1(np.round(values, 6).tobytes()).hexdigest()[:16]


def _progress(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def run_scan(bot: Bot, plan: ScanPlan, out_dir: Path, *, source: dict,
             progress: bool = True) -> dict:
    """Scan along `plan` with `bot`, recording into out_dir; resumes a scan of the same plan
    already in out_dir. Returns scan.json's content. `source` describes the bot and plant
    (written into scan.json)."""
    out_dir = Path(out_dir)
    manifest_path = out_dir / "scan.json"
    fingerprint = plan_id(plan)
    manifest = {"version": 1, "plan_id": fingerprint, "source": source, "plan": plan.to_json(),
                "waypoints": len(plan.waypoints), "completed": 0, "status": "running",
                "sessions": []}
    if manifest_path.exists():
        previous = read_json(manifest_path)
        if previous.get("plan_id") != fingerprint:
            raise InputError(out_dir, "holds a different scan (another plant or path); "
                             "choose a new --out folder")
        manifest.update(completed=int(previous.get("completed", 0)),
                        sessions=list(previous.get("sessions", [])))
    start = manifest["completed"]
    if start >= len(plan.waypoints):
        manifest["status"] = "complete"
        return manifest
    if start and progress:
        _progress(f"scan: resuming at waypoint {start} of {len(plan.waypoints)}")
    out_dir.mkdir(parents=True, exist_ok=True)
    intrinsics = bot.camera.intrinsics()
    if start and (out_dir / "camera.json").exists():
        recorded = read_json(out_dir / "camera.json")
        if any(not np.isclose(float(recorded.get(k, np.nan)), float(v))
               for k, v in intrinsics.items() if isinstance(v, int | float)):
            raise InputError(out_dir / "camera.json", "the scan was recorded with other camera "
                             "settings; resume with the same ones or choose a new --out folder")
    write_json(out_dir / "camera.json", intrinsics)
    session = {"started_waypoint": start, "bot_time_start": bot.now(),
               "wall_start": time.time()}
    manifest["sessions"].append(session)
    write_json(manifest_path, manifest)
    bot.camera.start_recording(out_dir / "video.mp4")
    wall = time.perf_counter()
    try:
        for waypoint in plan.waypoints[start:]:
            bot.move_to(waypoint.pose.gantry)
            bot.set_head(float(waypoint.pose.yaw), float(waypoint.pose.pitch))
            bot.dwell(plan.config.pause_s)
            manifest["completed"] = waypoint.index + 1
            write_json(manifest_path, manifest)
            if progress and (waypoint.index + 1) % 20 == 0:
                _progress(f"scan: waypoint {waypoint.index + 1}/{len(plan.waypoints)} "
                          f"(bot clock {bot.now():.0f} s, {time.perf_counter() - wall:.1f} s)")
        manifest["status"] = "complete"
    except BaseException as err:
        manifest["status"] = "interrupted"
        session["error"] = f"{type(err).__name__}: {err}"
        raise
    finally:
        recording = bot.camera.stop_recording()
        session.update(bot_time_end=bot.now(), frames=recording.frames,
                       wall_s=round(time.perf_counter() - wall, 3))
        write_json(manifest_path, manifest)
    return manifest
