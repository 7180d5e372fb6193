"""A field run over a bed of simulated plants (`flowerpose field --sim`): a plant generated
at each of the bed file's places, all of them in one simulated world, the bot filming them
one after another in the planned order while, in a worker (`bed_loop.film_bed`), each
filmed plant is reconstructed, its cloud cut to the plant, its flowers found and scored
against its exact truth.

The run's folder (`out`):

- `bed.json`: the bed's journal (`bed_loop`): each plant's stage and seconds; rerunning
  the command resumes.
- `plants/NAME/`: the plant (plant.json, its mesh), `scan/` (the recording, and the truth
  with this scan's visibility), `frames/`, `reconstruction/` (the whole cloud and
  `plant_cloud.ply`, cut to the plant), `flowers.json`, `normals.ply`.
- `report.json`, `report.md`: Table I over the bed and per plant, the bed's times;
  `report.html`: the same with each plant's cloud, flowers and truth in 3D.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

import numpy as np

from flowerpose.config import to_dict
from flowerpose.errors import InputError
from flowerpose.eval.capture.photogrammetry import frames_and_cloud
from flowerpose.eval.field.bed_loop import (
    LOCK,
    WITHOUT_OPTIONS,
    BedOptions,
    BedWork,
    cut_to_plant,
    film_bed,
    fingerprint,
    open_journal,
    text,
    timing_text,
)
from flowerpose.eval.jobs.config import EvalConfig
from flowerpose.eval.jobs.plant_set import PlantSet
from flowerpose.eval.pool import LOCAL, Execution
from flowerpose.hardware.flights.bed_plan import Bed, BedPlan, BedPlant, plan_bed
from flowerpose.hardware.flights.flight_journal import folder_lock
from flowerpose.log import noted
from flowerpose.stopwatch import Stopwatch

CROP_MARGIN_M = 0.03
"""How far beyond a simulated plant's own reach (its mesh's widest distance from its axis)
its cloud is kept: a neighbour's leaves that reach into it stay, its flowers mostly not."""


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


def make_bed_plants(bed: Bed, config: EvalConfig, seed: int, out: Path | None,
                    cache: Path | None = None) -> SimBed:
    """A plant of seed `seed + i` for the i-th plant of the bed file, standing at its
    place, written to out/plants/NAME by eval's plant stage (`generate_plant_files`, from
    the stage cache at `cache` where made before), or kept in memory where `out` is None
    (a dry run, which writes nothing). The bed's heights and radii become the generated
    plants' own."""
    from flowerpose.eval.jobs.plants import generate_plant_files
    from flowerpose.sim.bundle import make_plant
    from flowerpose.sim.export import plant_obstacles, read_plant
    from flowerpose.sim.render import instance_offsets

    plants, made, folders, surfaces = [], [], {}, {}
    for index, spot in enumerate(bed.plants):
        sim = dataclasses.replace(config.sim, plant=dataclasses.replace(
            config.sim.plant, center_xy_m=(spot.x, spot.y)))
        folder = None if out is None else out / "plants" / spot.name
        if folder is None:
            plant = make_plant(seed + index, config=sim).plant
        else:
            if not (folder / "plant.json").exists():  # else made by this run before
                generate_plant_files(seed + index, sim, folder, cache)
            plant = read_plant(folder)
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
        built, cached = frames_and_cloud(folder, config.scan.frames, config.scan.reconstruct,
                                         cache, watch)
        registered = built["images_registered"]
        points, quality = _cut_to_plant(folder, crop_radius)
        watch.lap("crop")
        entry, timing = _job(folder, name).score(config, folder, cache)
        watch.lap("detect")
    seconds = watch.report(digits=3, total=None)
    seconds.update(dict.fromkeys(cached, 0.0))
    return {"entry": {**entry, "notes": notes}, "points": points, "registered": registered,
            "quality": quality, "seconds": seconds,
            "pipeline_s": {k: round(v, 3) for k, v in timing.items()}}


def _cut_to_plant(folder: Path, crop_radius: float) -> tuple[int, dict]:
    """folder/reconstruction/cloud.ply cut to `crop_radius` metres round the plant's axis
    (plant_cloud.ply); the points kept and the cut cloud's quality against the mesh."""
    from flowerpose.eval.capture.quality import reconstruction_quality
    from flowerpose.sim.export import read_plant

    plant = read_plant(folder)
    kept = cut_to_plant(folder, plant.center[:2], crop_radius)
    quality = reconstruction_quality(kept, plant.mesh, plant.face_part, samples=100_000)
    return len(kept), quality


@dataclasses.dataclass(frozen=True)
class SimBedRun:
    """What a simulated bed's field run runs on: the bed file's places and the seeded
    plants standing at them (`plants`: the i-th place's plant is seed `plants.seed + i`
    of its preset), filmed by the simulated bot directly (`serial_time_scale` None) or
    through the physical bot's serial backend on a virtual Farmduino running at K times
    real time."""

    bed: Bed
    plants: PlantSet
    serial_time_scale: float | None = None

    def __post_init__(self):
        if self.plants.real or self.plants.plants != len(self.bed.plants):
            raise InputError("bed", f"{len(self.bed.plants)} places need as many seeded "
                             f"synthetic plants, not {self.plants.label}")


def run_sim_bed(config: EvalConfig, run: SimBedRun, out: Path, execution: Execution = LOCAL,
                options: BedOptions = WITHOUT_OPTIONS) -> dict:
    """The bed's field run in the simulator, resumable (the module's docstring). Returns
    report.json's content. InputError where the bed cannot be scanned (naming the plant) or
    the folder holds another run; a plant whose scan or reconstruction fails is marked
    failed with its error and, with `options.keep_going`, the bed goes on without it. With
    `options.pollinate` each detected plant's visits are then planned from its flowers,
    flown and scored against its truth (`eval --task pollinate`'s step), into its entry.
    The execution's stage cache keeps each plant's frames, reconstruction and detection
    (`process_plant`)."""
    from flowerpose.eval.capture.scan_source import write_scan_truth
    from flowerpose.hardware.flights.scan_flight import run_scan

    bed, seed, cache, say = run.bed, run.plants.seed, execution.cache, options.say
    with folder_lock(out, LOCK, "field run"):
        journal = open_journal(out, bed, fingerprint(bed, {"seed": seed,
                                                            "config": to_dict(config)}),
                               {"seed": seed})
        sim_bed = make_bed_plants(bed, config, seed, out, cache)
        plan = plan_sim_bed(sim_bed)
        reach = {p.name: p.radius + CROP_MARGIN_M for p in sim_bed.bed.plants}
        names = [p.name for p in bed.plants]

        def film(bot, index: int, folder: Path) -> None:
            run_scan(bot, plan.scans[index], folder / "scan", progress=False,
                     source={**bot.describe(), "plants": [str(folder.resolve())]})
            write_scan_truth(folder / "scan", folder,
                             sim_bed.first_instance[plan.plants[index].name])

        def said(name: str, result: dict) -> str:
            score = result["entry"]
            return (f"{name}: {score['found_visible']} of {score['visible']} visible flowers "
                    f"found, {score['fp']} false positives, {result['points']} points")

        work = BedWork(plan, sim_bed.folders, film, lambda name: (process_plant, (
            sim_bed.folders[name], name, config, reach[name], cache)), said)
        film_bed(journal, work, _bot([sim_bed.folders[n] for n in names], config,
                                     run.serial_time_scale), options.keep_going, say)
        if options.pollinate:
            _pollinate(out, journal.record, config, say)
            journal.save()
        return _report(out, journal.record, sim_bed.bed, config)


def _bot(folders: list[Path], config: EvalConfig, serial_time_scale: float | None):
    """The simulated bot filming the bed's plants: direct, or through the serial backend."""
    from flowerpose.hardware.backends.sim_bot import SimBot, SimBotConfig

    bot_config = SimBotConfig(camera=config.scan.camera)
    if serial_time_scale is None:
        return SimBot(folders, bot_config)
    from flowerpose.hardware.backends.serial_sim_bot import SimulatedSerialBot

    return SimulatedSerialBot(folders, bot_config, time_scale=serial_time_scale)


def _pollinate(out: Path, record: dict, config: EvalConfig, say: Callable[[str], None]) -> None:
    """Each detected plant's visits planned from its flowers (its cut cloud as the
    obstacles), flown on a simulated bot and scored against its truth, and the same from
    its true poses (the planner's ceiling): into its entry, as `eval --task pollinate`
    does; out/pollination.png draws the success against the pose error. Run again on a
    resumed bed, it gives the same visits."""
    from flowerpose.eval.jobs.pollination_task import pollinate_plants

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


def _report(out: Path, record: dict, bed: Bed, config: EvalConfig) -> dict:
    """report.json, report.md and report.html: Table I over the bed's detected plants, a
    row a plant, each plant's 3D view."""
    from flowerpose.atomic import write_text
    from flowerpose.eval.reports.html_report import BedSection, BedSpot, write_html_report
    from flowerpose.eval.reports.report import (
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
        from flowerpose.eval.jobs.pollination_task import pollination_summary

        report["summary"].update(pollination_summary(entries))
    write_report(out, report, "flowerpose field --sim: the bed")
    header = ["plant", "x m", "y m", "stage", "found (visible)", "FP", "pollinated", "points",
              "scan s", "reconstruct s", "detect s"]
    table = markdown_table(header, [[r["plant"], f"{r['x']:.2f}", f"{r['y']:.2f}", r["stage"],
                                     r["found"], text(r["fp"]), text(r["pollinated"]),
                                     text(r["points"]),
                                     *(f"{r['seconds'].get(k, 0):.0f}" for k in
                                       ("scan", "reconstruct", "detect"))] for r in rows])
    times = record["timing_s"]
    md = (out / "report.md").read_text()
    timing = timing_text(times)
    visits = [f"- {line}" for line in pollination_lines(report)]
    write_text(out / "report.md", md + "\n".join(["", "## The bed", "", table, "", timing, "",
                                                  *visits, ""]))
    views = [_job(out / "plants" / n, n).view(config, out) for n in record["order"]
             if record["plants"][n]["stage"] == "detected"]
    section = BedSection(
        [BedSpot(p.name, p.x, p.y, p.radius) for p in bed.plants],
        [*header, "error"],
        [[r["plant"], f"{r['x']:.2f}", f"{r['y']:.2f}", r["stage"], r["found"],
          text(r["fp"]), text(r["pollinated"]), text(r["points"]),
          *(f"{r['seconds'].get(k, 0):.0f}" for k in ("scan", "reconstruct", "detect")),
          r["error"] or ""] for r in rows],
        [timing, *pollination_lines(report)])
    write_html_report(out / "report.html", "flowerpose field --sim: the bed", report, views,
                      section)
    return report


def _job(folder: Path, name: str):
    """A filmed plant as eval scores it: its cut cloud and the truth with its scan's
    visibility."""
    from flowerpose.eval.jobs.plants import SyntheticJob

    return SyntheticJob(name, folder / "reconstruction" / "plant_cloud.ply",
                        folder / "scan" / "plant.json", source="scan")


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
