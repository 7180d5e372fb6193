"""A field run over a bed of simulated plants (`flowerpose field --sim`): a plant generated
at each of the bed file's places, all of them in one simulated world, the bot filming them
one after another in the planned order while, in a worker process (or a Ray task, inside
`runner.on_ray`), each filmed plant is reconstructed, its cloud cut to the plant, its
flowers found and scored against its exact truth. The bot never waits for the computer:
plant k is reconstructed while plant k+1 is filmed, and the last plants' reconstructions
finish after the bot parks.

The run's folder (`out`):

- `bed.json`: the bed's journal, rewritten atomically after every step: the bed, the
  order, and per plant its stage ("planned", "scanned", "detected" or "failed" with the
  error) and seconds; its sessions as a flight's (`flight_journal`). Running the same
  command again resumes: a detected plant is left alone, a scanned one only reconstructed,
  a scan cut short resumed where its frames end. Another bed or other settings in the same
  folder are refused.
- `plants/NAME/`: the plant (plant.json, its mesh), `scan/` (the recording, and the truth
  with this scan's visibility), `frames/`, `reconstruction/` (the whole cloud and
  `plant_cloud.ply`, cut to the plant), `flowers.json`, `normals.ply`.
- `report.json`, `report.md`: Table I over the bed and per plant, the bed's times;
  `report.html`: the same with each plant's cloud, flowers and truth in 3D.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Callable
from concurrent.futures import Future
from pathlib import Path

import numpy as np

from flowerpose.config import to_dict
from flowerpose.errors import InputError
from flowerpose.eval.config import EvalConfig
from flowerpose.eval.runner import CAPTURE_CPUS, running_on_ray, spawn_pool, submit_job
from flowerpose.hardware.flights.bed_plan import Bed, BedPlan, BedPlant, plan_bed
from flowerpose.hardware.flights.flight_journal import Journal, folder_lock
from flowerpose.log import eta, noted
from flowerpose.stopwatch import Stopwatch

JOURNAL = "bed.json"
LOCK = ".bed.lock"
CROP_MARGIN_M = 0.03
"""How far beyond a simulated plant's own reach (its mesh's widest distance from its axis)
its cloud is kept: a neighbour's leaves that reach into it stay, its flowers mostly not."""
OTHER_BED = ("holds a field run of another bed, seed or settings; choose another --out (a "
             "run resumes only with the command that started it)")


@dataclasses.dataclass(frozen=True)
class SimBed:
    """A bed's simulated plants: the bed with each plant's own height and reach, their
    folders and surfaces (what the scans keep clear of)."""

    bed: Bed
    folders: dict[str, Path]
    surfaces: dict[str, np.ndarray]
    first_instance: dict[str, int]
    """Each plant's flower ids' offset in a render of the whole bed
    (`render.instance_offsets`)."""


def fingerprint(bed: Bed, config: EvalConfig, seed: int) -> str:
    """The run's identity: its bed, scan settings, seed and every setting (SHA-256)."""
    text = json.dumps({"plants": [dataclasses.asdict(p) for p in bed.plants],
                       "scan": to_dict(bed.scan), "seed": seed, "config": to_dict(config)},
                      sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


def make_bed_plants(bed: Bed, config: EvalConfig, seed: int, out: Path | None) -> SimBed:
    """A plant of seed `seed + i` for the i-th plant of the bed file, standing at its
    place, written to out/plants/NAME (None: kept in memory, for a dry run). The bed's
    heights and radii become the generated plants' own."""
    from flowerpose.sim.bundle import make_plant
    from flowerpose.sim.export import plant_obstacles, read_plant
    from flowerpose.sim.render import instance_offsets

    plants, made, folders, surfaces = [], [], {}, {}
    for index, spot in enumerate(bed.plants):
        sim = dataclasses.replace(config.sim, plant=dataclasses.replace(
            config.sim.plant, center_xy_m=(spot.x, spot.y)))
        folder = None if out is None else out / "plants" / spot.name
        if folder is not None and (folder / "plant.json").exists():
            plant = read_plant(folder)  # made by this run before (the journal says whose)
        else:
            plant = make_plant(seed + index, config=sim, out_dir=folder).plant
        reach = float(np.hypot(*(np.asarray(plant.mesh.vertices)[:, :2]
                                 - np.asarray(plant.center[:2])).T).max())
        made.append(plant)
        plants.append(dataclasses.replace(spot, height=float(plant.height), radius=reach))
        if folder is not None:
            folders[spot.name] = folder
        surfaces[spot.name] = plant_obstacles(plant)
    offsets = dict(zip([p.name for p in bed.plants], instance_offsets(made), strict=True))
    return SimBed(dataclasses.replace(bed, plants=plants), folders, surfaces, offsets)


def plan_sim_bed(sim_bed: SimBed) -> BedPlan:
    """The bed's scans round the simulated plants' own surfaces, ordered (`plan_bed`)."""
    return plan_bed(sim_bed.bed, surfaces=sim_bed.surfaces)


def process_plant(folder: Path, name: str, config: EvalConfig, crop_radius: float,
                  cache: Path | None = None) -> dict:
    """A filmed plant's frames chosen (folder/scan -> folder/frames), its reconstruction
    (folder/frames -> folder/reconstruction), its cloud
    cut to `crop_radius` metres round the plant's axis (plant_cloud.ply), measured against
    its mesh, then its flowers found and scored against the truth with the scan's
    visibility. Runs in a worker: returns the report's plant entry (with the warnings said
    on the way, its "notes"), the reconstruction's counts and quality, and seconds per
    step. cache: the stage cache's folder (None: none); the frame choice (keyed by the
    recording), the reconstruction (by the frames) and the detection and score (by the cut
    cloud) are taken from it where the same files, settings and code ran before, and put
    into it; a step taken from it counts 0 seconds."""
    watch = Stopwatch()
    with noted() as notes:
        registered, cached = _frames_and_cloud(folder, config, cache, watch)
        points, quality = _cut_to_plant(folder, crop_radius)
        watch.lap("crop")
        entry, timing = _job(folder, name).score(config, folder, cache)
        watch.lap("detect")
    seconds = watch.report(digits=3, total=None)
    seconds.update(dict.fromkeys(cached, 0.0))
    return {"entry": {**entry, "notes": notes}, "points": points, "registered": registered,
            "quality": quality, "seconds": seconds,
            "pipeline_s": {k: round(v, 3) for k, v in timing.items()}}


#: What the stage cache keeps of a bed plant's reconstruction: the cloud and its report.
BED_RECONSTRUCTION_FILES = ("reconstruction/cloud.ply", "reconstruction/reconstruction.json")


def _frames_and_cloud(folder: Path, config: EvalConfig, cache: Path | None,
                      watch: Stopwatch) -> tuple[int, list[str]]:
    """folder/frames chosen from folder/scan and reconstructed into folder/reconstruction,
    each from the stage cache where it can be, `watch` lapped after each ("frames",
    "reconstruct"); the images registered, and the steps taken from the cache."""
    from flowerpose.cache import StageCache
    from flowerpose.pipeline.frames import select_frames
    from flowerpose.pipeline.reconstruct import reconstruct

    def frames() -> dict:
        select_frames(folder / "scan", folder / "frames", config.scan.frames, progress=False,
                      overwrite=True)
        return {}

    def cloud() -> dict:
        built = reconstruct(folder / "frames", folder / "reconstruction",
                            config.scan.reconstruct, progress=False, overwrite=True)
        return {"registered": built.report["images_registered"]}

    if cache is None:
        frames()
        watch.lap("frames")
        registered = cloud()["registered"]
        watch.lap("reconstruct")
        return registered, []
    stages = StageCache(cache)
    recording = sorted(p for p in (folder / "scan").rglob("*") if p.is_file()
                       and p.name not in ("plant.json", "visibility.json"))
    _, frames_cached, key = stages.run("bed-frames", to_dict(config.scan.frames), recording,
                                       folder, ("frames",), frames, code=BED_CODE)
    watch.lap("frames")
    built, built_cached, _ = stages.run("bed-reconstruct", to_dict(config.scan.reconstruct),
                                        [], folder, BED_RECONSTRUCTION_FILES, cloud,
                                        parents=[key], code=BED_CODE)
    watch.lap("reconstruct")
    return built["registered"], [step for step, hit in (("frames", frames_cached),
                                                        ("reconstruct", built_cached)) if hit]


#: The code a bed plant's frame choice and reconstruction run (the stage cache's code
#: version): frame choice and photogrammetry, not the detection or the simulator.
BED_CODE = ("flowerpose.pipeline.frames", "flowerpose.pipeline.reconstruct")


def _cut_to_plant(folder: Path, crop_radius: float) -> tuple[int, dict]:
    """folder/reconstruction/cloud.ply cut to `crop_radius` metres round the plant's axis
    (plant_cloud.ply); the points kept and the cut cloud's quality against the mesh."""
    from flowerpose.cloudio import read_cloud, write_cloud
    from flowerpose.eval.quality import reconstruction_quality
    from flowerpose.sim.export import read_plant

    plant = read_plant(folder)
    cloud = read_cloud(folder / "reconstruction" / "cloud.ply", units="m")
    keep = np.hypot(*(cloud.points[:, :2] - np.asarray(plant.center[:2])).T) <= crop_radius
    write_cloud(folder / "reconstruction" / "plant_cloud.ply", cloud.subset(keep))
    quality = reconstruction_quality(cloud.points[keep], plant.mesh, plant.face_part,
                                     samples=100_000)
    return int(keep.sum()), quality


def run_sim_bed(bed: Bed, config: EvalConfig, seed: int, out: Path, keep_going: bool = False,
                say: Callable[[str], None] = print,
                serial_time_scale: float | None = None, pollinate: bool = False,
                cache: Path | None = None) -> dict:
    """The bed's field run in the simulator, resumable (the module's docstring). Returns
    report.json's content. InputError where the bed cannot be scanned (naming the plant) or
    the folder holds another run; a plant whose scan or reconstruction fails is marked
    failed with its error and, with `keep_going`, the bed goes on without it.
    serial_time_scale: None films with the simulated bot directly; K through the physical
    bot's serial backend on a virtual Farmduino running at K times real time.
    pollinate: then each detected plant's visits are planned from its flowers, flown and
    scored against its truth (`eval --task pollinate`'s step), into its entry. cache: the
    stage cache's folder for each plant's frames, reconstruction and detection (None:
    none; `process_plant`)."""
    if out.exists() and not out.is_dir():
        raise InputError(out, "is a file; --out is the bed's folder")
    with folder_lock(out, LOCK, "field run"):
        return _run(bed, config, seed, out, keep_going, say, serial_time_scale, pollinate,
                    cache)


def _bot(folders: list[Path], config: EvalConfig, serial_time_scale: float | None):
    """The simulated bot filming the bed's plants: direct, or through the serial backend."""
    from flowerpose.hardware.backends.sim_bot import SimBot, SimBotConfig

    bot_config = SimBotConfig(camera=config.scan.camera)
    if serial_time_scale is None:
        return SimBot(folders, bot_config)
    from flowerpose.hardware.backends.serial_sim_bot import SimulatedSerialBot

    return SimulatedSerialBot(folders, bot_config, time_scale=serial_time_scale)


def _run(bed: Bed, config: EvalConfig, seed: int, out: Path, keep_going: bool,
         say: Callable[[str], None], serial_time_scale: float | None, pollinate: bool,
         cache: Path | None) -> dict:
    from flowerpose.eval.scan_source import write_scan_truth
    from flowerpose.hardware.flights.scan_flight import run_scan

    wall = Stopwatch()
    journal = Journal.open(out / JOURNAL, fingerprint(bed, config, seed),
                           {"seed": seed, "plants": {p.name: {"stage": "planned"}
                                                     for p in bed.plants}},
                           kept=("plants", "timing_s"), other_plan=OTHER_BED,
                           redone="the plant being filmed resumes its scan")
    record = journal.record
    sim_bed = make_bed_plants(bed, config, seed, out)
    plan = plan_sim_bed(sim_bed)
    record["order"] = [p.name for p in plan.plants]
    record["plan"] = {"bot_s": round(plan.duration_s, 1),
                      "travel_s": [round(t, 1) for t in plan.travel_s]}
    journal.save()
    names = [p.name for p in bed.plants]
    reach = {p.name: p.radius + CROP_MARGIN_M for p in sim_bed.bed.plants}
    pool = None if running_on_ray() else spawn_pool(1)
    pending: dict[str, Future] = {}
    busy = _Busy()

    def submit(name: str) -> None:
        busy.start()
        pending[name] = submit_job(pool, process_plant, (sim_bed.folders[name], name, config,
                                                         reach[name], cache), cpus=CAPTURE_CPUS)
        pending[name].add_done_callback(lambda _: busy.stop())

    def collect(block: bool) -> None:
        for name in [n for n, f in pending.items() if block or f.done()]:
            entry = record["plants"][name]
            try:
                result = pending.pop(name).result()
            except Exception as error:  # a failed reconstruction or detection
                _fail(entry, "reconstruct", error)
                journal.save()
                say(f"{name}: failed ({entry['error']})")
                if not keep_going:
                    raise
                continue
            seconds = {**entry.get("seconds", {}), **result.pop("seconds")}
            entry.update(stage="detected", **result, seconds=seconds)
            journal.save()
            score = result["entry"]
            say(f"{name}: {score['found_visible']} of {score['visible']} visible flowers "
                f"found, {score['fp']} false positives, {result['points']} points "
                f"({_done(record)} of {len(names)} plants done, the bed "
                f"{wall.elapsed():.0f} s in)")

    # The bot waits for the computer between two plants' scans only: the frames are chosen
    # in the worker, with the rest of a plant's work.
    last_scan_end: float | None = None
    bot_waiting = first_filmed = 0.0
    filmed_before = _filmed_s(plan, record)
    bot = _bot([sim_bed.folders[n] for n in names], config, serial_time_scale)
    try:
        with bot, journal.session(bot):
            for order, (spot, scan_plan) in enumerate(zip(plan.plants, plan.scans,
                                                           strict=True), start=1):
                entry = record["plants"][spot.name]
                if entry["stage"] == "detected":
                    continue
                if entry["stage"] == "scanned":
                    submit(spot.name)
                    continue
                folder = sim_bed.folders[spot.name]
                # The bed's time left, at this session's pace through the plan's bot time.
                bed_time = eta(wall.elapsed(), _filmed_s(plan, record) - filmed_before,
                               plan.duration_s - filmed_before)
                say(f"[{order}/{len(names)}] {spot.name}: filming {len(scan_plan.waypoints)} "
                    f"waypoints ({scan_plan.duration_s / 60:.1f} min of bot time); the bed "
                    f"{bed_time.strip('()')}")
                watch = Stopwatch()
                if last_scan_end is not None:
                    bot_waiting += wall.elapsed() - last_scan_end
                try:
                    run_scan(bot, scan_plan, folder / "scan", progress=False,
                             source={**bot.describe(), "plants": [str(folder.resolve())]})
                    write_scan_truth(folder / "scan", folder, sim_bed.first_instance[spot.name])
                    watch.lap("scan")
                except (InputError, OSError, RuntimeError) as error:
                    _fail(entry, "scan", error)
                    journal.save()
                    say(f"{spot.name}: failed ({entry['error']})")
                    if not keep_going:
                        raise
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
    finally:
        if pool is not None:
            pool.shutdown(wait=False, cancel_futures=True)
    if pollinate:
        _pollinate(out, record, config, say)
        journal.save()
    return _report(out, record, sim_bed.bed, config)


def _pollinate(out: Path, record: dict, config: EvalConfig, say: Callable[[str], None]) -> None:
    """Each detected plant's visits planned from its flowers (its cut cloud as the
    obstacles), flown on a simulated bot and scored against its truth, and the same from
    its true poses (the planner's ceiling): into its entry, as `eval --task pollinate`
    does; out/pollination.png draws the success against the pose error. Run again on a
    resumed bed, it gives the same visits."""
    from flowerpose.eval.pollination_task import pollinate_plants

    names = [n for n in record["order"] if record["plants"][n]["stage"] == "detected"]
    if not names:
        return
    watch = Stopwatch()
    entries = [record["plants"][n]["entry"] for n in names]
    pollinate_plants([_job(out / "plants" / n, n) for n in names], entries, config, out, None)
    record["timing_s"]["pollinate"] = round(watch.elapsed(), 3)
    for name, entry in zip(names, entries, strict=True):
        done = entry["pollination"]
        say(f"{name}: pollinated {done['successes']} of {len(done['flowers'])} flowers in "
            f"{done['visits']} visits")


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


def _fail(entry: dict, stage: str, error: BaseException) -> None:
    entry.update(stage="failed", failed_at=stage, error=str(error).splitlines()[0])


def _done(record: dict) -> int:
    return sum(p["stage"] == "detected" for p in record["plants"].values())


def _report(out: Path, record: dict, bed: Bed, config: EvalConfig) -> dict:
    """report.json, report.md and report.html: Table I over the bed's detected plants, a
    row a plant, each plant's 3D view."""
    from flowerpose.atomic import write_text
    from flowerpose.eval.html_report import BedSection, BedSpot, write_html_report
    from flowerpose.eval.report import (
        build_report,
        markdown_table,
        pollination_lines,
        write_report,
    )

    spots: dict[str, BedPlant] = {p.name: p for p in bed.plants}
    entries = [record["plants"][n]["entry"] for n in record["order"]
               if record["plants"][n]["stage"] == "detected"]
    rows = [_bed_row(n, spots[n], record["plants"][n]) for n in record["order"]]
    report = build_report(to_dict(config), entries, record["timing_s"],
                          {"bed": {"order": record["order"], "plants": rows,
                                   "plan": record["plan"]}})
    if entries and all("pollination" in e for e in entries):
        from flowerpose.eval.pollination_task import pollination_summary

        report["summary"].update(pollination_summary(entries))
    write_report(out, report, "flowerpose field --sim: the bed")
    header = ["plant", "x m", "y m", "stage", "found (visible)", "FP", "pollinated", "points",
              "scan s", "reconstruct s", "detect s"]
    table = markdown_table(header, [[r["plant"], f"{r['x']:.2f}", f"{r['y']:.2f}", r["stage"],
                                     r["found"], _text(r["fp"]), _text(r["pollinated"]),
                                     _text(r["points"]),
                                     *(f"{r['seconds'].get(k, 0):.0f}" for k in
                                       ("scan", "reconstruct", "detect"))] for r in rows])
    times = record["timing_s"]
    md = (out / "report.md").read_text()
    waiting = times.get("bot_waiting", 0.0)
    share = waiting / times["after_first_plant"] if times.get("after_first_plant") else 0.0
    timing = (f"Bed: {times['bed']:.0f} s of wall time, {times['filming']:.0f} s of it "
              f"filming (the computer idle {times['computer_idle_while_filming']:.0f} s of "
              f"those), {times['after_filming']:.0f} s after the last plant was filmed. The "
              f"bot waited for the computer {waiting:.1f} s between plants "
              f"({100 * share:.1f} % of the bed's time after the first plant was filmed): "
              "each plant's frames are chosen, reconstructed and its flowers found in a "
              "worker while the next is filmed.")
    visits = [f"- {line}" for line in pollination_lines(report)]
    write_text(out / "report.md", md + "\n".join(["", "## The bed", "", table, "", timing, "",
                                                  *visits, ""]))
    views = [_job(out / "plants" / n, n).view(config, out) for n in record["order"]
             if record["plants"][n]["stage"] == "detected"]
    section = BedSection(
        [BedSpot(p.name, p.x, p.y, p.radius) for p in bed.plants],
        [*header, "error"],
        [[r["plant"], f"{r['x']:.2f}", f"{r['y']:.2f}", r["stage"], r["found"],
          _text(r["fp"]), _text(r["pollinated"]), _text(r["points"]),
          *(f"{r['seconds'].get(k, 0):.0f}" for k in ("scan", "reconstruct", "detect")),
          r["error"] or ""] for r in rows],
        [timing, *pollination_lines(report)])
    write_html_report(out / "report.html", "flowerpose field --sim: the bed", report, views,
                      section)
    return report


def _job(folder: Path, name: str):
    """A filmed plant as eval scores it: its cut cloud and the truth with its scan's
    visibility."""
    from flowerpose.eval.plants import SyntheticJob

    return SyntheticJob(name, folder / "reconstruction" / "plant_cloud.ply",
                        folder / "scan" / "plant.json", source="scan")


def _text(value) -> str:
    return "-" if value is None else str(value)


def _bed_row(name: str, spot: BedPlant, entry: dict) -> dict:
    score = entry.get("entry")
    found = "-" if score is None else f"{score['found_visible']} of {score['visible']}"
    done = None if score is None else score.get("pollination")
    return {"plant": name, "x": spot.x, "y": spot.y, "stage": entry["stage"],
            "error": entry.get("error"), "found": found,
            "fp": None if score is None else score["fp"], "points": entry.get("points"),
            "pollinated": None if done is None else
            f"{done['successes']} of {len(done['flowers'])}",
            "seconds": entry.get("seconds", {})}
