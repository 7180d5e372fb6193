"""A field run over a bed with the physical bot (`flowerpose field --port` or `--cloud`):
the bed's plants filmed one after another with the head's USB camera, each reconstructed
and its flowers found in a worker while the bot films the next (`bed_loop.film_bed`), then,
with `pollinate`, each plant's flowers visited by the same bot. There is no truth: the
report says what was found and done, not how well.

The run's folder (`out`):

- `bed.json`: the bed's journal (`bed_loop`): each plant's stage and seconds; rerunning
  the command resumes (a plant cut short mid-scan resumes its scan, a pollination flight
  cut short its flight).
- `plants/NAME/`: `scan/` (frames, trajectory.csv, camera.json, scan.json), `frames/`,
  `reconstruction/` (cloud.ply, and plant_cloud.ply: the points within the plant's radius
  of its stem, plus `CUT_MARGIN_M`), `flowers.json`, `normals.ply`; with `pollinate`,
  `pollination/` (pollination.json, the plan; flight.json, the visits flown).
- `report.json`, `report.md`: a row a plant (flowers found, with a normal, uncertain,
  visits, times) and the bed's times; `report.html`: the same with the bed's map and
  each plant's cloud and flowers in 3D.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from contextlib import AbstractContextManager
from pathlib import Path
from typing import Any

import numpy as np

from flowerpose.config import to_dict, value_at
from flowerpose.errors import InputError
from flowerpose.eval.capture.photogrammetry import frames_and_cloud
from flowerpose.eval.field.bed_loop import (
    LOCK,
    SCAN_FAILURES,
    WITHOUT_OPTIONS,
    BedOptions,
    BedWork,
    cut_to_plant,
    film_bed,
    fingerprint,
    first_line,
    open_journal,
    recorded_failure,
    text,
    timing_text,
)
from flowerpose.eval.jobs.config import EvalConfig, pipeline_part
from flowerpose.eval.pool import LOCAL, Execution
from flowerpose.hardware.backends.usb_camera import FrameChoice, UsbCameraConfig
from flowerpose.hardware.flights.bed_plan import Bed, BedPlan, BedPlant
from flowerpose.hardware.flights.flight_journal import folder_lock
from flowerpose.log import LOG, noted
from flowerpose.pipeline.flowers import PipelineConfig
from flowerpose.stopwatch import Stopwatch

CUT_MARGIN_M = 0.03
"""How far beyond a plant's radius (the bed's, from its stem) its cloud is kept for
detection, metres: a plant reaching a little past its stated radius keeps its flowers."""


@dataclasses.dataclass(frozen=True)
class FieldRig:
    """The physical bot as a bed's run drives it."""

    connect: Callable[[], AbstractContextManager]
    """Connects to the bot and homes it; the context gives the bot and, on leaving, stops
    the recording and drops the connection."""
    recorder: object
    """The `TrajectoryRecorder` the bot films with (its camera a `UsbCamera`)."""
    camera: UsbCameraConfig
    """How the camera records; `choose` set (to any duration): the sharpest frames of each
    bin of each plant's own scan are kept while recording; None: every frame."""
    source: dict
    """What scan.json and flight.json record of the bot and camera (no secret)."""


#: What a physical bed's run reads of the settings: the frame choice, photogrammetry, the
#: camera's frame size and the visits, besides the pipeline's own sections
#: (`settings_read`); the command line takes no other, and the run's identity is these.
FIELD_SETTINGS = ("scan.frames", "scan.reconstruct", "scan.camera.width",
                  "scan.camera.height", "pollinate")


def settings_read(config: EvalConfig) -> dict[str, Any]:
    """The settings a physical bed's run reads (`FIELD_SETTINGS` and the pipeline's
    sections), by dotted key: what `bed_loop.fingerprint` keys the run by."""
    pipeline = tuple(f.name for f in dataclasses.fields(PipelineConfig))
    return {key: value_at(config, key) for key in (*FIELD_SETTINGS, *pipeline)}


def process_field_plant(folder: Path, name: str, at: tuple[float, float], radius: float,
                        config: EvalConfig, cache: Path | None = None) -> dict:
    """A filmed plant's frames chosen (folder/scan -> folder/frames), reconstructed
    (folder/reconstruction), its cloud cut to `radius` metres round its stem at `at` (bed
    frame, metres; plant_cloud.ply) and its flowers found (folder/flowers.json). Runs in a
    worker: returns the plant's counts, the warnings said on the way ("notes") and seconds
    per step. cache: the stage cache's folder (None: none), as `simulated_bed.process_plant`."""
    from flowerpose.eval.capture.detection import detect_cloud
    from flowerpose.pipeline.flowers import read_flowers

    watch = Stopwatch()
    with noted() as notes:
        built, cached = frames_and_cloud(folder, config.scan.frames, config.scan.reconstruct,
                                         cache, watch)
        registered = built["images_registered"]
        points = len(cut_to_plant(folder, at, radius))
        watch.lap("crop")
        timing, _ = detect_cloud(folder / "reconstruction" / "plant_cloud.ply",
                                 pipeline_part(config), folder, cache)
        watch.lap("detect")
    flowers = read_flowers(folder / "flowers.json")
    seconds = watch.report(digits=3, total=None)
    seconds.update(dict.fromkeys(cached, 0.0))
    return {"entry": {"name": name, "flowers": len(flowers),
                      "with_normal": sum(f["normals"].get("plane") is not None
                                         for f in flowers),
                      "uncertain": sum(bool(f.get("uncertain")) for f in flowers),
                      "notes": notes},
            "points": points, "registered": registered, "seconds": seconds,
            "pipeline_s": {k: round(v, 3) for k, v in timing.items()}}


@dataclasses.dataclass(frozen=True)
class FieldBedRun:
    """What a physical bed's field run runs on: the bed, its plan (checked, `plan_bed`,
    before the camera opens or the bot connects) and the bot and camera that film it."""

    bed: Bed
    plan: BedPlan
    rig: FieldRig


def run_field_bed(config: EvalConfig, run: FieldBedRun, out: Path,
                  execution: Execution = LOCAL, options: BedOptions = WITHOUT_OPTIONS) -> dict:
    """The bed's field run with the physical bot, resumable (the module's docstring).
    Returns report.json's content. A plant whose scan (the bot, its camera, the disk) or
    processing fails is marked failed with its error and, with `options.keep_going`, the
    bed goes on without it; else the error goes on, the recording stopped and the
    connection dropped. With `options.pollinate` each detected plant's flowers are then
    visited (`pollinate`'s plan and flight) before the bot is let go. The execution's
    stage cache keeps each plant's frames, reconstruction and detection."""
    bed, plan, rig = run.bed, run.plan, run.rig
    cache, keep_going, say = execution.cache, options.keep_going, options.say
    with folder_lock(out, LOCK, "field run"):
        journal = open_journal(out, bed, fingerprint(bed, settings_read(config)),
                               {"bot": rig.source})
        folders = {p.name: out / "plants" / p.name for p in bed.plants}
        spots = {p.name: p for p in bed.plants}

        def film(bot, index: int, folder: Path) -> None:
            _film(bot, rig, plan.plants[index], plan.scans[index], folder / "scan")

        def job(name: str):
            spot = spots[name]
            return process_field_plant, (folders[name], name, spot.at, spot.radius + CUT_MARGIN_M,
                                         config, cache)

        def said(name: str, result: dict) -> str:
            entry = result["entry"]
            return (f"{name}: {entry['flowers']} flowers found, {entry['with_normal']} with a "
                    f"normal ({entry['uncertain']} of uncertain sign), {result['points']} "
                    "points")

        then = None
        if options.pollinate:
            def then(bot) -> None:
                _pollinate(bot, rig, journal, folders, spots, config, keep_going, say)

        film_bed(journal, BedWork(plan, folders, film, job, said), rig.connect(), keep_going,
                 say, then=then)
        return _report(out, journal.record, bed, config)


def _film(bot, rig: FieldRig, spot: BedPlant, scan_plan, scan_dir: Path) -> None:
    """One plant filmed into scan_dir: the camera's frame choice set to its scan, the disk
    checked, the head lifted and brought over the scan's start, the scan flown (resumed)."""
    from flowerpose.hardware.backends.usb_camera import check_disk_space
    from flowerpose.hardware.flights.scan_flight import approach_start, run_scan

    camera = rig.camera
    if camera.choose is not None:
        camera = dataclasses.replace(camera, choose=FrameChoice(scan_plan.duration_s))
    rig.recorder.camera.choose_frames(camera.choose)
    check_disk_space(scan_dir, camera, scan_plan.duration_s)
    try:
        approach_start(bot, scan_plan, scan_dir)
        run_scan(bot, scan_plan, scan_dir, progress=False, source={
            **rig.source, "bot": bot.info.name, "firmware": bot.info.firmware,
            "plant": {"name": spot.name, "at": list(spot.at), "height": spot.height,
                      "radius": spot.radius}})
    except SCAN_FAILURES:
        _park(bot)
        raise


def _park(bot) -> None:
    """After a failed scan: the head lifted to the top of Z where the gantry stands, clear
    of the plants, where the bot still can move (after an emergency stop or a lost link it
    cannot, and stands where the error left it: said in a warning)."""
    try:
        here = bot.position()
        if not np.all(np.isfinite(here)):
            raise InputError(bot.info.name, "its position is unknown")
        bot.move_to([here[0], here[1], bot.info.travel_max[2]])
    except SCAN_FAILURES as error:
        LOG.warning(f"warning: {bot.info.name} not parked ({first_line(error)}): "
                    "it stands where the scan stopped")


def _pollinate(bot, rig: FieldRig, journal, folders: dict[str, Path],
               spots: dict[str, BedPlant], config: EvalConfig, keep_going: bool,
               say: Callable[[str], None]) -> None:
    """Each detected plant's flowers visited, in the bed's order: the plan from its
    flowers.json (plane normals; those of uncertain sign planned only where the close look
    will settle them, or `pollinate.visit_uncertain`) round its cut cloud, from over where
    the head stands, flown with the close look (`pollinate.look`) and resumed where
    flight.json says. Into its journal entry as "pollination"."""
    record = journal.record
    for name in record["order"]:
        entry = record["plants"][name]
        if entry["stage"] != "detected" or entry.get("pollination", {}).get("status") == \
                "complete":
            continue
        watch = Stopwatch()
        try:
            done = _pollinate_plant(bot, rig, folders[name], spots[name], config)
        except SCAN_FAILURES as error:
            # The plant stays detected: its flowers are found, their visits are not flown.
            entry["pollination"] = {"status": "failed", "error": first_line(error)}
            recorded_failure(journal, say, f"{name}: pollination failed "
                             f"({entry['pollination']['error']})", keep_going)
            continue
        entry["pollination"] = done
        entry["seconds"]["pollinate"] = round(watch.elapsed(), 3)
        journal.save()
        say(f"{name}: pollinated {done['done']} of {done['flowers']} flowers "
            f"({done['planned']} visits planned)")


def _pollinate_plant(bot, rig: FieldRig, folder: Path, spot: BedPlant,
                     config: EvalConfig) -> dict:
    """One plant's visits planned and flown; what its journal entry keeps of them."""
    from flowerpose.cloudio import read_cloud
    from flowerpose.hardware.flights.close_look import CloseLook
    from flowerpose.hardware.flights.pollination_flight import fly_pollination, read_flight
    from flowerpose.hardware.flights.pollination_plan import PlantObstacles, plan_pollination
    from flowerpose.hardware.flights.visit_flowers import check_plant, read_visit_flowers
    from flowerpose.jsonio import write_json
    from flowerpose.pipeline.colour import flower_coloured
    from flowerpose.pipeline.flowers import read_flowers

    out = folder / "pollination"
    flowers, skipped = read_visit_flowers(read_flowers(folder / "flowers.json"), "plane",
                                          config.pollinate.plans_uncertain)
    summary = {"flowers": len(flowers) + len(skipped), "skipped": len(skipped)}
    if not flowers:
        return {**summary, "planned": 0, "flown": 0, "done": 0, "status": "complete"}
    check_plant(flowers, spot.at, spot.height, spot.radius + CUT_MARGIN_M,
                folder / "flowers.json")
    cloud = read_cloud(folder / "reconstruction" / "plant_cloud.ply", units="m")
    # The same plan every time (ordered from home, as `pollinate` plans): a flight cut
    # short resumes it. The flight lifts the head to the top before every visit.
    plant = PlantObstacles.of(cloud.points, flower_coloured(cloud.colors, config.colour))
    plan = plan_pollination(flowers, cloud.points, config.pollinate, corolla=plant.corolla)
    if read_flight(out, plan) is None:
        write_json(out / "pollination.json", {**plan.to_json(), "flowers":
                                              str(folder / "flowers.json"), "method": "plane"})
    if plan.planned:
        look = (CloseLook({f.id: f for f in flowers}, plant, config.pollinate, out / "look",
                          config.pose, config.colour)
                if config.pollinate.look.views else None)
        flight = fly_pollination(bot, plan, out, source={
            **rig.source, "bot": bot.info.name, "firmware": bot.info.firmware},
            progress=False, look=look)
        flown, status = len(flight["done"]), flight["status"]
        done = sum(entry["rest"] is not None for entry in flight["done"])
    else:
        flown, done, status = 0, 0, "complete"
    return {**summary, "planned": len(plan.planned), "flown": flown, "done": done,
            "status": status}


def _report(out: Path, record: dict, bed: Bed, config: EvalConfig) -> dict:
    """report.json, report.md and report.html: a row a plant, the bed's times, the map and
    each detected plant's cloud and flowers in 3D."""
    from flowerpose.atomic import write_text
    from flowerpose.cloudio import read_cloud
    from flowerpose.eval.reports.html_report import (
        BedSection,
        BedSpot,
        PlantView,
        write_html_report,
    )
    from flowerpose.eval.reports.report import markdown_table, run_record
    from flowerpose.jsonio import write_json
    from flowerpose.pipeline.flowers import read_flowers

    rows = [_row(spot, record["plants"][spot.name]) for spot in
            sorted(bed.plants, key=lambda p: record["order"].index(p.name))]
    detected = [r for r in rows if r["stage"] == "detected"]
    summary = {"plants": len(rows), "detected": len(detected),
               "failed": sum(r["stage"] == "failed" for r in rows),
               **{key: sum(r[key] for r in detected)
                  for key in ("flowers", "with_normal", "uncertain")}}
    visited = [r["pollination"] for r in detected if r["pollination"]]
    if visited:
        summary["pollination"] = {key: sum(v.get(key, 0) for v in visited)
                                  for key in ("flowers", "skipped", "planned", "done")}
        summary["pollination"]["failed"] = sum(v["status"] == "failed" for v in visited)
    report = {"run": run_record(), "kind": "field bed", "config": to_dict(config),
              "bed": {"order": record["order"], "plan": record["plan"], "plants": rows,
                      "bot": record.get("bot")},
              "summary": summary, "timing_s": record.get("timing_s", {})}
    write_json(out / "report.json", report)
    header = ["plant", "x m", "y m", "stage", "flowers", "with normal", "uncertain",
              "pollinated", "points", "scan s", "reconstruct s", "detect s"]
    cells = [[r["plant"], f"{r['x']:.2f}", f"{r['y']:.2f}", r["stage"], text(r["flowers"]),
              text(r["with_normal"]), text(r["uncertain"]),
              _visits(r["pollination"]),
              text(r["points"]),
              *(f"{r['seconds'].get(k, 0):.0f}" for k in ("scan", "reconstruct", "detect"))]
             for r in rows]
    lines = [f"{summary['detected']} of {summary['plants']} plants detected, "
             f"{summary.get('flowers', 0)} flowers found, {summary.get('with_normal', 0)} "
             f"with a normal ({summary.get('uncertain', 0)} of uncertain sign); no truth, so "
             "no score: `flowerpose label` and `flowerpose score` measure them"]
    if "pollination" in summary:
        done = summary["pollination"]
        lines.append(f"pollinated {done['done']} of {done['flowers']} flowers "
                     f"({done['planned']} visits planned, {done['skipped']} left alone)")
    if report["timing_s"]:
        lines.append(timing_text(report["timing_s"]))
    failed = [f"{r['plant']}: failed at {r['failed_at']} ({r['error']})" for r in rows
              if r["stage"] == "failed"]
    write_text(out / "report.md", "\n".join([
        "# flowerpose field: the bed", "", markdown_table(header, cells), "",
        *[f"- {line}" for line in [*lines, *failed]], ""]))
    views = [PlantView(r["plant"], read_cloud(out / "plants" / r["plant"] / "reconstruction" /
                                              "plant_cloud.ply"),
                       read_flowers(out / "plants" / r["plant"] / "flowers.json"))
             for r in detected]
    section = BedSection([BedSpot(p.name, p.x, p.y, p.radius) for p in bed.plants],
                         [*header, "error"],
                         [[*row, rows[k]["error"] or ""] for k, row in enumerate(cells)],
                         [*lines, *failed])
    write_html_report(out / "report.html", "flowerpose field: the bed", None, views, section)
    return report


def _visits(done: dict | None) -> str:
    """A plant's pollination in a table cell."""
    if not done:
        return "-"
    return "failed" if done["status"] == "failed" else f"{done['done']} of {done['flowers']}"


def _row(spot: BedPlant, entry: dict) -> dict:
    found = entry.get("entry") or {}
    return {"plant": spot.name, "x": spot.x, "y": spot.y, "stage": entry["stage"],
            "failed_at": entry.get("failed_at"), "error": entry.get("error"),
            "flowers": found.get("flowers"), "with_normal": found.get("with_normal"),
            "uncertain": found.get("uncertain"), "notes": found.get("notes", []),
            "points": entry.get("points"), "pollination": entry.get("pollination"),
            "seconds": entry.get("seconds", {})}
