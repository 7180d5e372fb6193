"""The `flowerpose` command line: one console script, one subcommand per stage or job."""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
from datetime import datetime
from pathlib import Path
from typing import Any

from flowerpose.cli_flags import SettingHelp, add_setting_flags, flag_for
from flowerpose.errors import InputError, JobsFailed, missing_extra
from flowerpose.hardware.bot_errors import BotError
from flowerpose.log import LOG

#: Plants of the default `flowerpose eval` (photogrammetry): about 5 minutes each here.
SCAN_PLANTS = 2

#: What `flowerpose scan --sim` reads of a config: the path (the oracle's cameras) and the
#: simulated camera (SCAN_FLAGS gives four of them flags).
SCAN_SETTINGS = ("sim.viewpoints.", "scan.sensor.", "scan.render.", "scan.frame_rate_hz",
                 "scan.workers", "scan.width", "scan.height")
SCAN_FLAGS = {"--frame-rate": "scan.frame_rate_hz", "--width": "scan.width",
              "--height": "scan.height", "--workers": "scan.workers"}
#: `scan --sim`'s frames per second of bot time: twice an eval's, for a user filming one
#: plant to choose frames from.
SCAN_SIM_FRAME_RATE_HZ = 0.6


def _scan_base():
    """`flowerpose scan`'s starting settings: an eval's, at SCAN_SIM_FRAME_RATE_HZ."""
    import dataclasses

    from flowerpose.eval.harness import EvalConfig

    config = EvalConfig()
    return dataclasses.replace(config, scan=dataclasses.replace(
        config.scan, frame_rate_hz=SCAN_SIM_FRAME_RATE_HZ))


def _frames_base():
    from flowerpose.pipeline.frames import FrameSelectConfig

    return FrameSelectConfig()


def _eval_base():
    from flowerpose.eval.harness import EvalConfig

    return EvalConfig()


def _reconstruct_base():
    from flowerpose.pipeline.reconstruct import ReconstructConfig

    return ReconstructConfig()


def _dataset_base():
    from flowerpose.eval.dataset import DatasetConfig

    return DatasetConfig()


def _only_settings(args: argparse.Namespace, command: str, prefixes: tuple[str, ...]) -> None:
    """Refuse --set keys the command does not read (they would be silently ignored)."""
    from flowerpose.config import parse_set_options

    for key in parse_set_options(args.set):
        if not key.startswith(prefixes):
            raise InputError(f"--set {key}", f"{command} takes "
                             f"{', '.join(k + '*' if k.endswith('.') else k for k in prefixes)}")


def _add_config_options(parser: argparse.ArgumentParser, profile: bool = True,
                        detector: bool = True,
                        example: str = "cluster.eps=0.008 (metres)") -> None:
    """--config and --set; --profile where the profiles' keys apply (the pipeline's), and
    --detector where a detector runs."""
    from flowerpose.config import profile_names

    if profile:
        parser.add_argument("--profile", choices=profile_names(), metavar="NAME",
                            help="start from a named settings profile: upstream = the "
                            "published method's settings (assets/configs/NAME.toml; default: "
                            "none, this project's defaults)")
    parser.add_argument("--config", type=Path, metavar="FILE.toml",
                        help="settings file (TOML, sections as in report.json's config)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override one setting by its dotted key, in the setting's own "
                        f"unit, e.g. {example}; repeatable")
    if detector:
        parser.add_argument("--detector", metavar="MODULE:CLASS|onnx:MODEL.onnx",
                            help="the 2D detector on the grid views instead of the colour "
                            "detector: onnx:MODEL.onnx, a box or segmentation model exported "
                            "to ONNX (the [onnx] extra; input, output and class in "
                            "pipeline/onnx_detector.py), or any importable class with the "
                            "Detector interface (pipeline/detect.py); the same as --set "
                            "detect.detector=... (default: the colour detector)")


@contextlib.contextmanager
def _owned(folder: Path, stage: str, overwrite: bool, writes: tuple[str, ...]):
    """The command's output folder, refused when it holds files the command did not
    write (`outputs`; with --overwrite, when one of them has a name in `writes`, the
    entries the command writes), and marked whole when the command succeeds."""
    from flowerpose.outputs import OutputFolder

    output = OutputFolder(folder, stage, overwrite, writes)
    yield output
    output.finish()


def _add_field_bot_options(p: argparse.ArgumentParser) -> None:
    """--port / --cloud and their options: the physical bot (scan, pollinate)."""
    p.add_argument("--port", metavar="PORT", help="the physical bot through its Farmduino on "
                   "this serial port (e.g. /dev/ttyACM0; best /dev/serial/by-id/...)")
    p.add_argument("--cloud", action="store_true", help="the physical bot through FarmBot's web "
                   "app; log in with FARMBOT_TOKEN, or FARMBOT_EMAIL and FARMBOT_PASSWORD "
                   "(FARMBOT_SERVER for another server), or --token-file")
    p.add_argument("--firmware-params", type=Path, metavar="FILE", help="--port: the bot's "
                   "firmware settings as the FarmBot web app exports them (JSON); written to "
                   "the Farmduino at connect and read back, as FarmBot OS does (default: the "
                   "settings the board holds)")
    p.add_argument("--home-here", action="store_true", help="--port: the gantry stands at "
                   "home (put there by hand): take it as home instead of homing, for a bot "
                   "without endstops or encoders")
    p.add_argument("--token-file", type=Path, metavar="FILE", help="--cloud: a file outside "
                   "the repository, readable by its owner alone, holding a FarmBot token (its "
                   "JSON or its JWT)")


def _add_cache_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--cache", type=Path, metavar="DIR",
                        help="the stage cache: scans and reconstructions of the same plant "
                        "with the same settings and code are taken from it, not run again "
                        "(default: $FLOWERPOSE_CACHE, else ~/.cache/flowerpose)")
    parser.add_argument("--no-cache", action="store_true",
                        help="run every stage, reading and filling no cache")


def _add_ray_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--ray", nargs="?", const="local", default=None, metavar="ADDRESS",
                        help="run the plants' jobs as Ray tasks: on a local Ray without an "
                        "address, else on the cluster at ADDRESS (host:port, ray://..., or "
                        "auto); a job that fails is tried once more, then reported by plant "
                        "(needs the [ray] extra; default: a local process pool)")


def _jobs_on(args: argparse.Namespace) -> contextlib.AbstractContextManager:
    """Where the command's jobs run: Ray (`--ray`), or the process pool."""
    if args.ray is None:
        return contextlib.nullcontext()
    from flowerpose.eval.runner import on_ray

    return on_ray(None if args.ray == "local" else args.ray)


def _cache(args: argparse.Namespace) -> Path | None:
    """The stage cache's folder the command's --cache / --no-cache choose."""
    from flowerpose.cache import default_cache_dir, max_cache_bytes

    if args.no_cache and args.cache is not None:
        raise InputError("--no-cache", "and --cache contradict each other: choose one")
    max_cache_bytes()  # a bad limit says so before any work
    return None if args.no_cache else (args.cache or default_cache_dir())


def _add_overwrite(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--overwrite", action="store_true",
                        help="write into a folder that holds files this command did not "
                        "write (they are kept; only its own earlier output is replaced)")


def _configure(base: Any, args: argparse.Namespace, flags: bool = True) -> Any:
    """`base` with the --profile, then the --config file, then the settings' flags
    (`flags`), then each --set, applied."""
    from flowerpose.cli_flags import given_settings
    from flowerpose.config import apply_overrides, load_profile, load_toml, parse_set_options

    config = base
    if getattr(args, "profile", None) is not None:
        config = apply_overrides(config, load_profile(args.profile))
    if args.config is not None:
        config = apply_overrides(config, load_toml(args.config))
    detector = getattr(args, "detector", None)
    sets = ((given_settings(args) if flags else []) + args.set
            + ([f"detect.detector={detector}"] if detector else []))
    return apply_overrides(config, parse_set_options(sets))


def _default_out() -> Path:
    return Path("runs") / datetime.now().strftime("%Y%m%d-%H%M%S")


#: eval's source, preset and first seed when neither the command line nor a suite says.
EVAL_DEFAULTS = {"source": "scan", "preset": "realistic", "seed": 0}


def cmd_eval(args: argparse.Namespace) -> int:
    from flowerpose.eval.harness import eval_config, run_eval

    suite = _apply_suite(args) if args.suite else None
    for key, default in EVAL_DEFAULTS.items():
        if getattr(args, key) is None:
            setattr(args, key, default)
    if args.folders and args.source != "real":
        raise InputError(args.folders[0], "plant folders are for --source real")
    if args.truth_scale is not None and args.source != "real":
        raise InputError("--truth-scale", "is for --source real")
    from flowerpose.eval.gates import parse_requirements
    from flowerpose.eval.methods import ExternalMethod, parse_compare, parse_method

    requirements = parse_requirements(args.require)  # a bad gate says so before any work
    if (args.junit or args.summary) and not requirements:
        raise InputError("--junit" if args.junit else "--summary", "needs --require")
    config = eval_config(args.preset, lambda base: _configure(base, args))
    from flowerpose.pipeline.detect import make_detector

    make_detector(config.detect, config.colour)  # one that cannot load says so before any work
    # A compared profile or detector shares the run's settings (scoring, plants) but its own.
    compared = [parse_compare(text, config, args.method_timeout) for text in args.compare]
    methods = [parse_method(text, args.method_timeout) for text in args.method] + [
        what for _, what in compared if isinstance(what, ExternalMethod)]
    compare = {name: what for name, what in compared if not isinstance(what, ExternalMethod)}
    cache = _cache(args)
    names = [m.name for m in methods] + list(compare)
    if len(set(names)) < len(names):
        raise InputError("--compare", "each compared method needs a name of its own")
    out = args.out or _default_out()
    plants = args.plants or (SCAN_PLANTS if args.source == "scan" else 10)
    from flowerpose.eval.harness import eval_outputs

    writes = eval_outputs(args.source, args.folders, [*compare, *(m.name for m in methods)])
    with _owned(out, "eval", args.overwrite, writes), _jobs_on(args):
        report = run_eval(config, source=args.source, plants=plants, seed=args.seed,
                          out_dir=out, workers=args.workers, folders=args.folders,
                          truth_scale=args.truth_scale, compare=compare, suite=suite,
                          methods=methods, cache=cache, task=args.task)
    if cache is not None and args.source != "real":
        from flowerpose.cache import prune_to_limit

        prune_to_limit(cache)
    from flowerpose.eval.report import comparison_table, summary_lines, table

    print(table(report))
    for line in summary_lines(report):
        print(line)
    if compare or methods:
        print(comparison_table(report, args.profile or "default"))
    for compared in report.get("compare", {}).values():
        for plant in compared["plants"]:
            if "error" in plant:
                print(f"{plant['plant']}: {plant['error']}")
    if args.task == "pollinate":
        from flowerpose.eval.report import pollination_lines

        for line in pollination_lines(report):
            print(line)
    print(f"report: {out / 'report.json'}, {out / 'report.md'}, {out / 'report.html'}")
    return _gates(report, requirements, args) if requirements else 0


def _apply_suite(args: argparse.Namespace) -> dict:
    """--suite NAME: the suite's source, preset, plants and seed for this eval; what it
    fixes may not be given too, nor settings that would change what it measures."""
    from flowerpose.config import load_suite

    suite = load_suite(args.suite)
    for key, value in suite["eval"].items():
        given = getattr(args, key)
        if given is not None and given != value:
            raise InputError(f"--{key}", f"is fixed by --suite {args.suite} ({value}); leave "
                             "it out")
        setattr(args, key, value)
    for flag, given in (("--set", args.set), ("--detector", args.detector),
                        ("--config", args.config), ("--profile", args.profile),
                        ("folders", args.folders)):
        if given:
            raise InputError(flag, f"--suite {args.suite} runs its own settings only, so its "
                             "numbers compare between versions and labs")
    return {k: suite[k] for k in ("name", "version", "description")}


def _gates(report: dict, requirements: list, args: argparse.Namespace) -> int:
    """eval's --require: the table of what failed (or that all hold), the JUnit and
    Markdown files when asked; 1 when a requirement does not hold."""
    from flowerpose.eval.gates import check, outcome_table, write_junit, write_summary

    outcomes = check(report, requirements)
    failed = [o for o in outcomes if not o.passed]
    title = f"flowerpose eval --source {args.source}"
    if args.junit:
        write_junit(args.junit, outcomes, title)
    if args.summary:
        write_summary(args.summary, outcomes, title)
    if failed:
        print(f"\n{len(failed)} of {len(outcomes)} requirements failed:")
        print(outcome_table(outcomes, failed_only=True))
        return 1
    print(f"\nall {len(outcomes)} requirements hold ({len(requirements)} on the run and on "
          f"each of {len(report['plants'])} plants)")
    return 0


def cmd_plant(args: argparse.Namespace) -> int:
    from flowerpose.eval.harness import eval_config
    from flowerpose.sim.bundle import make_plant
    from flowerpose.sim.export import PLANT_FILES

    for key in (item.split("=")[0].strip() for item in args.set):
        if not key.startswith("sim."):
            raise InputError(f"--set {key}", "plant takes the synthetic world's settings: "
                             "sim.plant.*, sim.oracle.*, sim.viewpoints.*")
    sim = eval_config(args.preset, lambda base: _configure(base, args)).sim
    with _owned(args.out, "plant", args.overwrite, PLANT_FILES):
        bundle = make_plant(args.seed, points=args.points, out_dir=args.out, config=sim)
    visible = int(sum(bundle.visible))
    print(f"seed {args.seed} ({args.preset}): {len(bundle.plant.flowers)} open flowers, "
          f"{visible} visible, {len(bundle.cloud)} cloud points -> {args.out}")
    return 0


def cmd_dataset(args: argparse.Namespace) -> int:
    from flowerpose.cli_flags import given_settings
    from flowerpose.config import apply_overrides, parse_set_options
    from flowerpose.eval.dataset import DatasetConfig, write_dataset
    from flowerpose.eval.harness import eval_config

    dataset = apply_overrides(DatasetConfig(), parse_set_options(given_settings(args)))
    config = eval_config(args.preset, lambda base: _configure(base, args, flags=False))
    seeds = list(range(args.seed, args.seed + args.plants))
    manifest = write_dataset(args.out, seeds, config, dataset, args.overwrite)
    split = manifest["split"]
    print(f"{manifest['images']} images, {manifest['instances']} flower instances of "
          f"{len(seeds)} plants ({len(split['train'])} train, {len(split['val'])} val: seeds "
          f"{', '.join(map(str, split['val'])) or 'none'}) as {dataset.format} -> "
          f"{args.out / 'dataset.json'}")
    return 0


def cmd_detect(args: argparse.Namespace) -> int:
    from flowerpose.cloudio import read_cloud, write_cloud
    from flowerpose.jsonio import write_json
    from flowerpose.outputs import OutputFolder, check_output
    from flowerpose.pipeline.flowers import (
        PipelineConfig,
        find_flowers,
        find_flowers_in_candidates,
        read_flowers,
        sections_run,
        write_flowers,
        write_normals_ply,
    )
    from flowerpose.pipeline.views import write_views

    config = _configure(PipelineConfig(), args)
    out: Path = args.out
    writes = ("flowers.json", "flowers.ply", "normals.ply", "config.json", "views", "crops",
              "report.html")
    check_output(out, "detect", args.overwrite, writes)
    cloud = read_cloud(args.cloud, units=args.units)
    result = (find_flowers_in_candidates if args.candidates else find_flowers)(cloud, config)
    # An earlier detection's files (crops of flowers this one may not have) go first.
    output = OutputFolder(out, "detect", args.overwrite, writes)
    output.record(write_flowers(out / "flowers.json", result, args.cloud,
                                "cloud" if args.candidates else "bed"),
                  *write_normals_ply(out, result.flowers),
                  write_json(out / "config.json", sections_run(
                      config, ["candidates" if args.candidates else "cloud"])))
    if result.projections:
        output.record(*write_views(out / "views", result.projections, result.detections,
                                   result.detection_flowers))
    output.record(*(write_cloud(out / "crops" / f"flower_{flower.id:02d}.ply",
                                cloud.subset(flower.crop)) for flower in result.flowers))
    from flowerpose.eval.html_report import PlantView, write_html_report

    output.record(write_html_report(
        out / "report.html", f"flowerpose detect: {args.cloud.name}", None,
        [PlantView(args.cloud.stem, cloud, read_flowers(out / "flowers.json"),
                   views_png=out / "views" / "views.png" if result.projections else None)]))
    output.finish()
    found = sum(f.pose.normals["plane"] is not None for f in result.flowers)
    views = f", {out / 'views' / 'views.png'}" if result.projections else ""
    print(f"{len(result.flowers)} flowers ({found} with a normal) in "
          f"{result.timing_s['total']:.2f} s -> {out / 'flowers.json'}{views}")
    return 0


def cmd_pose(args: argparse.Namespace) -> int:
    from flowerpose.cloudio import read_cloud
    from flowerpose.pipeline.flowers import PipelineConfig
    from flowerpose.pipeline.pose import estimate_pose
    from flowerpose.pipeline.segment import oriented_box

    config = _configure(PipelineConfig(), args)
    crop = read_cloud(args.crop, units=args.units)
    entry = {"id": 0, **estimate_pose(crop, config.pose, config.colour, config.cluster).to_json(),
             "box": oriented_box(crop.points).to_json()}
    print(json.dumps(entry, indent=1))
    return 0


def cmd_score(args: argparse.Namespace) -> int:
    from flowerpose.eval.harness import EvalConfig, score_files

    _only_settings(args, "score", ("score.",))
    config = _configure(EvalConfig(), args)
    report = score_files(args.flowers, args.truth, args.truth_format, args.truth_scale,
                         config.score.max_distance_m)
    from flowerpose.eval.report import REPORT_FILES, summary_lines, table, write_report

    print(table(report))
    for line in summary_lines(report):
        print(line)
    if args.out:
        with _owned(args.out, "score", args.overwrite, REPORT_FILES):
            paths = write_report(args.out, report, f"flowerpose score: {args.flowers.name}")
        print(f"report: {paths[0]}, {paths[1]}")
    return 0


def cmd_scan(args: argparse.Namespace) -> int:
    from flowerpose.scanio import frame_files

    if args.via_farmduino and not args.sim:
        raise InputError("scan --via-farmduino", "is for the simulated bot: add --sim")
    bots = [name for name, chosen in (("--sim", args.sim), ("--port", args.port),
                                      ("--cloud", args.cloud)) if chosen]
    if len(bots) != 1:
        raise InputError("scan", "choose one bot: --sim (simulated), --port PORT (a Farmduino "
                         "on serial) or --cloud (through FarmBot's web app)"
                         + (f", not {' and '.join(bots)}" if bots else ""))
    if not args.sim:
        return _scan_field(args)
    if args.plant is None:
        raise InputError("scan --sim", "needs --plant DIR (a folder from flowerpose plant)")
    from flowerpose.eval.scan_source import scan_plant
    from flowerpose.hardware.scan_plan import plan_table
    from flowerpose.hardware.sim_bot import plan_plant_scan
    from flowerpose.sim.export import read_plant

    _only_settings(args, "scan --sim", SCAN_SETTINGS)
    config = _configure(_scan_base(), args)
    camera = config.scan
    plant = read_plant(args.plant)
    plan = plan_plant_scan(plant, config.sim.viewpoints)  # the oracle's cameras, flown
    print(f"plan: {len(plan.waypoints)} waypoints around the plant at "
          f"({plant.center[0]:.3f}, {plant.center[1]:.3f}) m, {plan.duration_s / 60:.1f} min "
          "of bot time; reach and collisions checked")
    if args.dry_run:
        print("\n".join(plan_table(plan)))
        return 0
    from flowerpose.hardware.sim_bot import write_preview

    manifest = scan_plant(args.plant, args.out, camera, plan, args.via_farmduino,
                          progress=True)
    frames = len(frame_files(args.out))  # on disk: a killed session never counted its own
    truth = args.out / "plant.json"
    print(f"scan {manifest['status']}: {manifest['completed']}/{manifest['waypoints']} "
          f"waypoints, {frames} frames -> {args.out} (truth with the scan's visibility: "
          f"{truth})")
    if args.preview:
        print(f"preview: {write_preview(args.out, [plant.center], [plant.height])}")
    return 0


def cmd_farmduino(args: argparse.Namespace) -> int:
    if not args.virtual:
        raise InputError("farmduino", "only --virtual is available: it serves a virtual "
                         "Farmduino on a pseudo-terminal")
    from flowerpose.hardware.virtual_farmduino import FEEDBACK_PARAMETERS, VirtualFarmduino

    params = {} if args.bare else FEEDBACK_PARAMETERS
    with VirtualFarmduino(time_scale=args.time_scale, params=params) as device:
        try:  # from the moment its path is out, Ctrl-C is the way to stop it
            print(device.path, flush=True)
            LOG.info(f"virtual Farmduino on {device.path} (now {device.device}) at "
                     f"{args.time_scale:g} x real time; connect at 115200 baud; Ctrl-C stops it")
            device.wait()
        except KeyboardInterrupt:
            LOG.info("virtual Farmduino stopped")
    return 0


def _check_field_bot_flags(args: argparse.Namespace) -> None:
    """Refuse --port's and --cloud's options given to the other bot."""
    if args.token_file is not None and not args.cloud:
        raise InputError("--token-file", "is for --cloud")
    for flag, value in (("--firmware-params", args.firmware_params),
                        ("--home-here", args.home_here)):
        if value and args.port is None:
            raise InputError(flag, "is for --port (with --cloud, FarmBot OS holds the "
                             "bot's settings and finds home)")


def _field_bot(args: argparse.Namespace, camera=None, observer=None):
    """The physical bot of --port or --cloud: a function that connects to it, and what
    scan.json / flight.json record of it (no secret)."""
    _check_field_bot_flags(args)
    if args.cloud:
        from flowerpose.hardware.cloud_bot import CloudCredentials, FarmbotCloudBot

        credentials = CloudCredentials.from_environment(token_file=args.token_file)
        source = {"backend": "farmbot-cloud", "server": credentials.server}

        def connect():
            return FarmbotCloudBot(credentials, camera=camera, observer=observer)
    else:
        from flowerpose.hardware.farmduino import FarmduinoBot
        from flowerpose.hardware.protocol import read_settings

        settings = None
        if args.firmware_params is not None:
            settings = read_settings(args.firmware_params)
        else:
            LOG.warning("warning: no --firmware-params: the Farmduino runs on the settings it "
                        "holds, its firmware's defaults unless they were stored in its EEPROM "
                        "(FarmBot OS, which writes them, is not connected)")
        source = {"backend": "serial", "port": args.port,
                  "firmware_params": str(args.firmware_params or "the board's own")}

        def connect():
            return FarmduinoBot(args.port, camera=camera, observer=observer,
                                settings=settings)
    return connect, source


def _home_field_bot(args: argparse.Namespace, bot) -> None:
    """--port: home the bot just connected (or take where it stands, --home-here)."""
    if args.port is not None and args.home_here:
        LOG.warning(f"warning: --home-here: {bot.info.name} takes where the gantry "
                    "stands for home; every move is off by as much as it is not at home")
        bot.home_here()
    elif args.port is not None:
        # Opening the port reset the board, which lost the position: home, Z first.
        LOG.info(f"homing {bot.info.name} (Z, Y, X)")
        bot.home()


def _scan_field(args: argparse.Namespace) -> int:
    """scan --port / --cloud: the physical bot films a real plant with its USB camera."""
    from flowerpose.hardware.scan_flight import approach_start, run_scan
    from flowerpose.hardware.scan_plan import plan_field_scan, plan_table
    from flowerpose.scanio import frame_files

    if args.plant_at is None:
        raise InputError("--plant-at", "needed with --port and --cloud: where the plant's stem "
                         "stands, X,Y in metres in the bed frame")
    _only_settings(args, "scan --port/--cloud", ("scan.width", "scan.height"))
    size = _configure(_scan_base(), args).scan
    _check_field_bot_flags(args)
    plan = plan_field_scan(args.plant_at, args.plant_height, args.plant_radius)
    x, y = args.plant_at
    print(f"plan: {len(plan.waypoints)} waypoints around the plant at ({x:.3f}, {y:.3f}) m, "
          f"{plan.duration_s / 60:.1f} min of bot time; the paper's bot's travel and servo "
          f"range, and clearance from a {args.plant_radius:g} m x {args.plant_height:g} m plant "
          "envelope, checked")
    if args.dry_run:
        print("\n".join(plan_table(plan)))
        return 0
    if args.camera is None:
        raise InputError("--camera", "needed to scan: the head's USB camera, e.g. "
                         "/dev/v4l/by-id/usb-...-video-index0")
    if not Path(args.camera).exists():
        raise InputError(args.camera, "no such camera device; list them with "
                         "ls -l /dev/v4l/by-id/")
    from flowerpose.hardware.trajectory import TrajectoryRecorder
    from flowerpose.hardware.usb_camera import (
        FrameChoice,
        UsbCamera,
        UsbCameraConfig,
        check_disk_space,
    )
    from flowerpose.scanio import read_intrinsics

    if args.calibration is not None:
        read_intrinsics(args.calibration)  # a bad file stops us before the bot moves
    choose = None if args.keep_all else FrameChoice(plan.duration_s)
    camera = UsbCameraConfig(width=size.width, height=size.height, calibration=args.calibration,
                             choose=choose)
    check_disk_space(args.out, camera, plan.duration_s)
    recorder = TrajectoryRecorder(lambda clock: UsbCamera(args.camera, clock, camera))
    connect, source = _field_bot(args, camera=recorder.bind, observer=recorder.observe)
    source["camera"] = {"device": args.camera, "width": size.width, "height": size.height,
                        "intrinsics": str(args.calibration or "estimated from the field of view"),
                        "frames": "every frame" if choose is None else
                        f"the {choose.keep} sharpest of each of {choose.bins} bins of the path"}
    source["plant"] = {"at": [x, y], "height": args.plant_height, "radius": args.plant_radius}
    try:
        with connect() as bot:
            _home_field_bot(args, bot)
            approach_start(bot, plan, args.out)
            manifest = run_scan(bot, plan, args.out, source={
                **source, "bot": bot.info.name, "firmware": bot.info.firmware})
    finally:
        recorder.close()
    frames = len(frame_files(args.out))  # on disk: a killed session never counted its own
    print(f"scan {manifest['status']}: {manifest['completed']}/{manifest['waypoints']} "
          f"waypoints, {frames} frames ({recorder.rows} of this session's with a pose) -> "
          f"{args.out}")
    return 0


def _pollinate_base():
    from flowerpose.hardware.pollinate import PollinateConfig

    return PollinateConfig()


def cmd_pollinate(args: argparse.Namespace) -> int:
    from flowerpose.cloudio import read_cloud
    from flowerpose.hardware.pollinate import check_plant, plan_pollination, read_visit_flowers
    from flowerpose.hardware.pollination_flight import FLIGHT_NAME, read_flight
    from flowerpose.hardware.scan_plan import pose_header, pose_row
    from flowerpose.jsonio import read_json, write_json
    from flowerpose.pipeline.flowers import read_flowers

    if args.port and args.cloud:
        raise InputError("pollinate", "choose one bot: --port PORT or --cloud, not both")
    flying = bool(args.port or args.cloud) and not args.dry_run
    _check_field_bot_flags(args)
    config = _configure(_pollinate_base(), args)
    document = read_json(args.flowers)
    if document.get("frame", "bed") != "bed":
        raise InputError(args.flowers, f"is in its cloud's own frame ({document['frame']}, a "
                         "phone scan's): pollination needs flowers in the bed frame, from a "
                         "FarmBot scan's reconstruction")
    flowers, missing = read_visit_flowers(read_flowers(args.flowers), args.method)
    if not flowers:
        raise InputError(args.flowers, f"no flower has a {args.method} normal to approach "
                         "along")
    check_plant(flowers, args.plant_at, args.plant_height, args.plant_radius, args.flowers)
    cloud_path = args.plant_cloud or (Path(document["source"]) if document.get("source")
                                      else None)
    corolla = None
    if cloud_path is not None and cloud_path.is_file():
        from flowerpose.pipeline.colour import flower_coloured

        cloud = read_cloud(cloud_path, units="m")
        obstacles, corolla = cloud.points, flower_coloured(cloud.colors)
    elif args.plant_cloud is not None:
        raise InputError(args.plant_cloud, "no such cloud")
    else:
        obstacles = None
        LOG.warning("warning: no plant cloud (--plant-cloud, or the one flowers.json names): "
                    "the visits are checked for reach, not for collisions with the plant")
    plan = plan_pollination(flowers, obstacles, config, corolla=corolla)
    if flying:
        read_flight(args.out, plan)  # another plan's flight there: refused before writing
        if obstacles is None:
            raise InputError("--plant-cloud", "needed to fly: without the plant's cloud the "
                             "visits are not checked for collisions with the plant")
        bot = _field_bot(args)  # credentials and settings file read before writing
    with _owned(args.out, "pollinate", args.overwrite, ("pollination.json", FLIGHT_NAME)) \
            as output:
        output.record(write_json(args.out / "pollination.json", {
            **plan.to_json(), "flowers": str(args.flowers), "method": args.method,
            "no_normal": missing, "cloud": None if obstacles is None else str(cloud_path),
            "plant": {"at": list(args.plant_at), "height": args.plant_height,
                      "radius": args.plant_radius}}))
    print(f"plan: {len(plan.planned)} of {len(flowers) + len(missing)} flowers visited, "
          f"{plan.duration_s / 60:.1f} min of bot time; reach, the soil and "
          + ("clearance from the plant's cloud" if obstacles is not None else "no collisions")
          + f" checked -> {args.out / 'pollination.json'}")
    for visit in plan.visits:
        if visit.status != "planned":
            print(f"flower {visit.flower}: unreachable {visit.reason}")
    for flower in missing:
        print(f"flower {flower}: no {args.method} normal")
    if args.dry_run:
        print(pose_header("move") + "  flower")
        for k, move in enumerate(plan.moves):
            label = "" if move.flower < 0 else f"{move.flower:7d}"
            print(f"{pose_row(k, move.kind, move.pose)} {label}")
    if flying and plan.planned:
        return _fly_pollination(args, plan, *bot)
    return 0


def _fly_pollination(args: argparse.Namespace, plan, connect, source: dict) -> int:
    """pollinate --port / --cloud: fly the plan on the physical bot (flight.json; a flight
    cut short resumes when rerun)."""
    from flowerpose.hardware.pollination_flight import fly_pollination

    # flight.json is declared, never recorded: no later run of this stage deletes it.
    with connect() as bot:
        _home_field_bot(args, bot)
        flight = fly_pollination(bot, plan, args.out, source={
            **source, "bot": bot.info.name, "firmware": bot.info.firmware})
    print(f"flight {flight['status']}: {len(flight['done'])}/{len(flight['visits'])} "
          f"flowers pollinated -> {args.out / 'flight.json'}")
    return 0


def cmd_frames(args: argparse.Namespace) -> int:
    from flowerpose.pipeline.frames import select_frames

    config = _configure(_frames_base(), args)
    result = select_frames(args.scan, args.out, config, overwrite=args.overwrite)
    sharp = [f["sharpness"] for f in result["frames"]]
    print(f"{len(result['frames'])} of {result['recorded']} frames chosen in "
          f"{result['seconds']:.1f} s (sharpness median {sorted(sharp)[len(sharp) // 2]:.1f}) "
          f"-> {args.out / 'frames.json'}")
    return 0


def cmd_reconstruct(args: argparse.Namespace) -> int:
    from flowerpose.pipeline.reconstruct import reconstruct

    config = _configure(_reconstruct_base(), args)
    result = reconstruct(args.frames, args.out, config, overwrite=args.overwrite)
    report = result.report
    rms = report["alignment_rms_m"]
    print(f"{report['images_registered']}/{report['images_used']} images registered, "
          f"camera centres {1000 * rms:.2f} mm RMS from the recorded ones; "
          f"{report['points']} points in {report['seconds']['total']:.1f} s "
          f"(sparse {report['seconds']['sparse']:.1f} s, dense {report['seconds']['dense']:.1f} s)"
          f" -> {report['cloud']}, {args.out / 'reconstruction.json'}")
    return 0


def cmd_sweep(args: argparse.Namespace) -> int:
    from flowerpose.eval.harness import eval_config
    from flowerpose.eval.sweep import parse_grid, run_sweep, sweep_outputs

    config = eval_config(args.preset, lambda base: _configure(base, args))
    grid = parse_grid(args.grid, config)
    cache = _cache(args)
    with _owned(args.out, "sweep", args.overwrite, sweep_outputs(grid, args.source)), \
            _jobs_on(args):
        best = run_sweep(config, grid, plants=args.plants, seed=args.seed, out_dir=args.out,
                         workers=args.workers, source=args.source, cache=cache)
    if cache is not None:
        from flowerpose.cache import prune_to_limit

        prune_to_limit(cache)
    metrics = best["metrics"]
    print("best: " + ", ".join(f"{k}={v}" for k, v in best["setting"].items())
          + f" (recall_visible {metrics['recall_visible']}, fp_rate {metrics['fp_rate']}, "
          f"plane {metrics['plane_mean_deg']}°; its settings in {args.out / 'best.json'})")
    return 0


def cmd_fidelity(args: argparse.Namespace) -> int:
    from flowerpose.eval.fidelity import FIDELITY_FILES, run_fidelity, table
    from flowerpose.eval.harness import EvalConfig, pipeline_part

    config = _configure(EvalConfig(), args)
    with _owned(args.out, "fidelity", args.overwrite, FIDELITY_FILES):
        report = run_fidelity(args.real, args.synthetic, args.out, pipeline_part(config),
                              config.score.max_distance_m, args.truth_scale)
    print(table(report))
    print(f"{report['holds']} of {report['of']} statistics within tolerance "
          f"({report['real']['flowers']} real flowers, {report['synthetic']['flowers']} "
          f"synthetic) -> {args.out / 'fidelity.json'}, {args.out / 'fidelity.md'}, "
          f"{args.out / 'fidelity.png'}")
    return 0


def cmd_cache(args: argparse.Namespace) -> int:
    from flowerpose.cache import StageCache, default_cache_dir, max_cache_bytes
    from flowerpose.eval.report import markdown_table

    root = args.cache or default_cache_dir()
    if root.exists() and not root.is_dir():
        raise InputError(root, "is a file, not a cache folder")
    cache = StageCache(root)
    limit = 0 if args.clear else args.max_size
    if limit is not None:
        removed = cache.prune(int(limit * 1e9))
        print(f"removed {len(removed)} entries ({sum(e.size for e in removed) / 1e6:.1f} MB)")
    entries = cache.entries()
    rows = []
    for stage in sorted({e.stage for e in entries}):
        mine = [e for e in entries if e.stage == stage]
        rows.append([stage, str(len(mine)), f"{sum(e.size for e in mine) / 1e6:.1f} MB",
                     datetime.fromtimestamp(max(e.used for e in mine)).strftime("%Y-%m-%d %H:%M")])
    rows.append(["total", str(len(entries)), f"{sum(e.size for e in entries) / 1e6:.1f} MB",
                 ""])
    print(f"cache: {root} (entries kept within {max_cache_bytes() / 1e9:g} GB after an eval "
          "or sweep; FLOWERPOSE_CACHE_MAX_GB sets it)")
    print(markdown_table(["stage", "entries", "size", "last used"], rows, [len(rows) - 1]))
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from flowerpose.eval.bench import run_bench
    from flowerpose.pipeline.flowers import PipelineConfig

    run_bench(args.points, repeat=args.repeat, seed=args.seed, out=args.out,
              config=_configure(PipelineConfig(), args), cache=_cache(args))
    return 0


def _at_least(minimum: int, maximum: int | None = None, why: str = ""):
    """An argparse type: a whole number no smaller than `minimum` (nor larger than
    `maximum`, refused before anything is allocated)."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be at least {minimum}, got {value}")
        if maximum is not None and value > maximum:
            raise argparse.ArgumentTypeError(f"must be at most {maximum:,} ({why}), got "
                                             f"{value:,}")
        return value
    return parse


def _non_negative_number(text: str) -> float:
    """An argparse type: a finite number, 0 or more."""
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not (0 <= value < float("inf")):
        raise argparse.ArgumentTypeError(f"expected a number, 0 or more, got {text!r}")
    return value


def _positive_number(text: str) -> float:
    """An argparse type: a finite number above 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not (0 < value < float("inf")):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


def _plant_xy(text: str) -> tuple[float, float]:
    """An argparse type: X,Y, two finite numbers (metres)."""
    try:
        x, y = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y in metres (e.g. 1.5,0.75), got "
                                         f"{text!r}") from None
    if not (abs(x) < float("inf") and abs(y) < float("inf")):
        raise argparse.ArgumentTypeError(f"expected two finite numbers, got {text!r}")
    return x, y


#: Plant presets (sim/world_config.py): the README describes each.
PRESETS = ("easy", "realistic", "hard", "field")
PRESET_HELP = ("synthetic plants: easy, realistic (the benchmark), hard, or field (calibrated "
               "on a real scan, with the hand labels' error in the scoring)")

SEED = _at_least(0)
POSITIVE = _at_least(1)
#: Largest synthetic cloud: about 1 kB a point while it is sampled, so 20 million is 20 GB.
CLOUD_POINTS_MAX = 20_000_000
CLOUD_POINTS = _at_least(100, CLOUD_POINTS_MAX, "more does not fit in memory")
#: Most seeded plants a run takes: about 10 MB of files each, and hours of work per 1,000.
PLANTS = _at_least(1, 10_000, "a larger benchmark is several runs")


class _HelpFormatter(argparse.HelpFormatter):
    """argparse's help, with the description's and epilog's paragraphs filled to the
    terminal's width, a paragraph with indented lines (the examples) kept as written, and a
    setting's flag explained by the setting's own docstring."""

    def _get_help_string(self, action: argparse.Action) -> str:
        if isinstance(action.help, SettingHelp):
            return action.help.expanded()
        return super()._get_help_string(action)

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        import textwrap

        paragraphs = []
        for paragraph in text.split("\n\n"):
            lines = paragraph.splitlines()
            if any(line.startswith(" ") for line in lines):
                paragraphs.append("\n".join(indent + line for line in lines))
            else:
                paragraphs.append(textwrap.fill(" ".join(paragraph.split()), width,
                                                initial_indent=indent,
                                                subsequent_indent=indent))
        return "\n\n".join(paragraphs)


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (`flowerpose: error: ...`, exit status 2) and help
    whose examples keep their lines."""

    def __init__(self, *args: Any, **kwargs: Any):
        kwargs.setdefault("formatter_class", _HelpFormatter)
        super().__init__(*args, **kwargs)

    def error(self, message: str) -> None:  # type: ignore[override]
        command = self.prog.removeprefix("flowerpose").strip()
        where = f"{command}: " if command else ""
        self.exit(2, f"flowerpose: error: {where}{message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    from flowerpose.config import profile_names, suite_names

    parser = _Parser(
        prog="flowerpose",
        description="Estimate the 3D poses of strawberry flowers in point clouds, and score "
        "them against exact synthetic truth or hand labels. Each command is a stage of the "
        "method or a job made of them; `flowerpose COMMAND --help` says more.",
        epilog="examples:\n"
        "  flowerpose eval --source oracle --plants 2    # the pipeline on 2 synthetic plants\n"
        "  flowerpose eval                               # the full loop: about 10 minutes")
    from flowerpose import __version__

    parser.add_argument("--version", action="version", version=f"flowerpose {__version__}")
    _add_verbosity(parser, default=0)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND",
                                parser_class=_Parser)

    p = sub.add_parser(
        "eval", help="the benchmark: plants -> clouds -> flowers -> Table I",
        description="Run the benchmark: generate seeded plants (or read labelled real plant "
        "folders), turn each into a point cloud (--source), find its flowers and their "
        "normals, score them against the truth and print the paper's Table I. Writes "
        "report.json, report.md and report.html to --out, and per plant its files.",
        epilog="examples:\n"
        "  flowerpose eval --source oracle --plants 2 --out runs/oracle\n"
        "  flowerpose eval --source real ../shared/real/paper-plant-3 --compare upstream\n"
        "  flowerpose eval --suite oracle-10 --require 'recall_visible>=0.95'")
    p.add_argument("--source", choices=("scan", "oracle", "rgbd", "real"), default=None,
                   help="where clouds come from: scan = the simulated bot films each plant "
                   "and photogrammetry reconstructs it (default); oracle = the plant's "
                   "surfaces sampled directly; rgbd = a simulated depth camera's views fused; "
                   "real = labelled real plant folders (DIR ...)")
    p.add_argument("folders", nargs="*", type=Path, metavar="DIR",
                   help="--source real: labelled plant folders (labels.json and cloud.ply, "
                   "candidates/*.ply or crops/*.ply; README, \"Real plants\")")
    p.add_argument("--truth-scale", type=_positive_number, default=None, metavar="K",
                   help="--source real: the factor the labelled cloud was scaled by, no unit "
                   "(default: each folder's source.json, else 25 for SageMaker labels)")
    p.add_argument("--compare", action="append", default=[], metavar="METHOD",
                   help="also run another method on the same plants and print them side by "
                   f"side: a settings profile ({', '.join(profile_names())}), a 2D detector "
                   "(onnx:MODEL.onnx or MODULE:CLASS), an external command "
                   "(NAME='CMD {cloud} {out}', as --method) or a registered method's name "
                   "(repeatable; default: none)")
    p.add_argument("--plants", type=PLANTS, default=None, metavar="N",
                   help=f"number of seeded plants (default: {SCAN_PLANTS} for scan, 10 for "
                   "oracle and rgbd)")
    p.add_argument("--seed", type=SEED, default=None, metavar="S",
                   help=f"first plant seed; plants are S, S+1, ... (default: "
                   f"{EVAL_DEFAULTS['seed']})")
    p.add_argument("--preset", choices=PRESETS, default=None,
                   help=f"{PRESET_HELP} (default: {EVAL_DEFAULTS['preset']})")
    p.add_argument("--workers", type=POSITIVE, default=None, metavar="N",
                   help="worker processes (default: one per core)")
    p.add_argument("--out", type=Path, metavar="DIR",
                   help="output folder (default: runs/<date>-<time>/)")
    p.add_argument("--method", action="append", default=[], metavar="NAME=CMD",
                   help="also score another method on the same clouds, printed beside this "
                   "one: CMD runs once per plant with {cloud} (the plant's cloud, PLY) and "
                   "{out} (a folder to write flowers.json into), e.g. "
                   "mine='python detect.py {cloud} {out}', or NAME alone for a method an "
                   "installed package registers (repeatable; default: none)")
    p.add_argument("--task", choices=("pose", "pollinate"), default="pose",
                   help="pose: score the flower poses (Table I); pollinate: also plan, fly "
                   "and score a pollinator visit to each synthetic flower, from the "
                   "estimated poses and from the true ones (summary.pollination; "
                   "pollination.png) (default: %(default)s)")
    p.add_argument("--method-timeout", type=_positive_number, default=600.0, metavar="S",
                   help="seconds an external method may take on one plant (default: "
                   "%(default)g)")
    _add_cache_options(p)
    _add_ray_option(p)
    p.add_argument("--suite", choices=suite_names(), metavar="NAME",
                   help="a named, versioned benchmark suite that fixes the source, preset, "
                   f"plants and seeds ({', '.join(suite_names())}; assets/suites/); the report "
                   "records its name and version (default: none)")
    p.add_argument("--require", action="append", default=[], metavar="KEY>=NUMBER",
                   help="a CI gate on the report's summary, on the whole run and on each "
                   "plant, e.g. 'recall_visible>=0.95' or 'error_deg.plane.mean<=3' "
                   "(>=, <=, >, <, ==; repeatable): exit status 1 when one does not hold")
    p.add_argument("--junit", type=Path, metavar="FILE.xml",
                   help="with --require: write the gates as JUnit XML (a test case per plant "
                   "and requirement)")
    p.add_argument("--summary", type=Path, metavar="FILE.md",
                   help="with --require: write the gates as Markdown for a CI job's summary "
                   "page (e.g. $GITHUB_STEP_SUMMARY)")
    _add_overwrite(p)
    _add_config_options(p)
    p.set_defaults(func=cmd_eval)

    p = sub.add_parser(
        "plant", help="generate one plant: plant.json (truth), mesh, oracle cloud",
        description="Generate one seeded synthetic strawberry plant and write its exact "
        "truth (plant.json: flower centres and normals, metres, bed frame), its mesh "
        "(plant.ply) and its oracle cloud (cloud.ply) to --out.",
        epilog="example:\n  flowerpose plant --seed 3 --out plant3")
    p.add_argument("--seed", type=SEED, required=True, metavar="S",
                   help="the plant's seed: the same seed and preset give the same plant")
    p.add_argument("--points", type=CLOUD_POINTS, default=None, metavar="N",
                   help="points of the oracle cloud (default: the preset's, 60000; field "
                   "100000)")
    p.add_argument("--preset", choices=PRESETS, default="realistic",
                   help=f"{PRESET_HELP} (default: %(default)s)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR",
                   help="the plant folder to write")
    _add_overwrite(p)
    _add_config_options(p, profile=False, detector=False,
                        example="sim.plant.flower_diameter_m=[0.03,0.05] (metres; plant reads "
                        "sim.plant.*, sim.oracle.* and sim.viewpoints.*)")
    p.set_defaults(func=cmd_plant)

    p = sub.add_parser(
        "scan", help="film a plant along the cylinder and dome: the simulated FarmBot "
        "(--sim) or the physical one (--port, --cloud)",
        description="Film a plant along the paper's cylinder-and-dome path and write a scan "
        "folder (frames/, trajectory.csv, camera.json, scan.json): --sim with the simulated "
        "FarmBot, --port (a Farmduino on serial) or --cloud (FarmBot's web app) with the "
        "physical bot and its USB camera. Every move is checked before anything moves; an "
        "interrupted scan resumes when rerun.",
        epilog="examples:\n"
        "  flowerpose scan --sim --plant plant3 --out scan3\n"
        "  flowerpose scan --port /dev/ttyACM0 --plant-at 1.20,0.75 --out scan_field --dry-run")
    p.add_argument("--sim", action="store_true", help="the simulated bot (MuJoCo + renderer)")
    p.add_argument("--plant", type=Path, metavar="DIR",
                   help="--sim: the plant folder from flowerpose plant")
    _add_field_bot_options(p)
    p.add_argument("--keep-all", action="store_true", help="--port/--cloud: save every frame "
                   "(30 fps: several GB for a 20-minute scan) instead of the 3 sharpest of "
                   "each of 200 bins of the path, chosen while recording")
    p.add_argument("--camera", metavar="DEVICE", help="--port/--cloud: the head's USB camera, "
                   "best its stable path /dev/v4l/by-id/...-video-index0; records MJPG at "
                   "--width x --height, 30 fps, exposure and focus locked")
    p.add_argument("--calibration", type=Path, metavar="CAMERA.json", help="--port/--cloud: "
                   "the camera's calibrated intrinsics at that size (default: estimated from "
                   "a 62.2 degree horizontal field of view)")
    p.add_argument("--plant-at", type=_plant_xy, metavar="X,Y", help="--port/--cloud: where "
                   "the plant's stem stands, metres in the bed frame: x along the bed from "
                   "FarmBot's home end, y across it, (0, 0) the soil corner at home")
    p.add_argument("--plant-height", type=float, default=0.25, metavar="H",
                   help="--port/--cloud: the plant's height above the soil, metres (default: "
                   "%(default)s)")
    p.add_argument("--plant-radius", type=float, default=0.15, metavar="R",
                   help="--port/--cloud: how far the plant reaches from its stem, metres; the "
                   "head keeps 4 cm clear of it (default: %(default)s)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR",
                   help="the scan folder (resumes the scan already there)")
    p.add_argument("--dry-run", action="store_true",
                   help="print the planned moves (FarmBot millimetres and servo commands), "
                   "checked against the bot's limits, and stop: nothing connects or moves")
    add_setting_flags(p, _scan_base, SCAN_FLAGS,
                      metavars={"--frame-rate": "HZ", "--width": "PX", "--height": "PX",
                                "--workers": "N"},
                      extra={"--frame-rate": "--sim: ", "--workers": "--sim: "})
    p.add_argument("--no-preview", dest="preview", action="store_false",
                   help="--sim: skip preview.mp4 (the gantry scanning, seen from outside)")
    p.add_argument("--via-farmduino", action="store_true",
                   help="with --sim: drive the simulated bot through the serial Farmduino "
                   "backend and a virtual Farmduino (100 x real time)")
    _add_config_options(p, profile=False, detector=False,
                        example="sim.viewpoints.azimuth_step_deg=30 (degrees; --sim reads "
                        "sim.viewpoints.*, scan.sensor.*, scan.render.* and the four scan.* "
                        "its flags set; --port and --cloud scan.width and scan.height)")
    p.set_defaults(func=cmd_scan)

    p = sub.add_parser(
        "pollinate", help="plan a pollinator visit to each flower of a flowers.json",
        description="Plan a visit of the head's pollinator to each flower of a flowers.json "
        "(bed frame): a pre-approach pose on the flower's axis, a straight approach until the "
        "swab touches its centre, a rest and a retreat, every pose checked against the "
        "bot's reach and every move against the plant's cloud, in an order that keeps "
        "travel short. Writes pollination.json to --out; --dry-run also prints every move "
        "in FarmBot's units. With --port or --cloud the physical bot then flies the plan "
        "(flight.json records each visit; rerun to resume a flight cut short); without, "
        "nothing connects or moves.",
        epilog="examples:\n"
        "  flowerpose pollinate detect3/flowers.json --plant-at 1.50,0.75 --out visits3 "
        "--dry-run\n"
        "  flowerpose pollinate detect3/flowers.json --plant-at 1.50,0.75 --out visits3 "
        "--port /dev/ttyACM0")
    p.add_argument("flowers", type=Path, metavar="FLOWERS.json",
                   help="flower poses in the bed frame (flowerpose detect on a FarmBot scan's "
                   "reconstruction, or a simulated one)")
    p.add_argument("--plant-at", type=_plant_xy, required=True, metavar="X,Y",
                   help="where the plant's stem stands, metres in the bed frame (the flowers "
                   "must be the plant's)")
    p.add_argument("--plant-height", type=_positive_number, default=0.25, metavar="H",
                   help="the plant's height above the soil, metres (default: %(default)s)")
    p.add_argument("--plant-radius", type=_positive_number, default=0.15, metavar="R",
                   help="how far the plant reaches from its stem, metres (default: "
                   "%(default)s)")
    p.add_argument("--plant-cloud", type=Path, metavar="CLOUD.ply",
                   help="the plant's cloud in the bed frame, for collision checks (default: "
                   "the cloud flowers.json names as its source)")
    p.add_argument("--method", choices=("plane", "superellipsoid", "paraboloid"),
                   default="plane", help="whose normal is the flower's axis (default: "
                   "%(default)s)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR",
                   help="folder for pollination.json")
    p.add_argument("--dry-run", action="store_true",
                   help="also print every move (FarmBot millimetres and servo commands), "
                   "and fly nothing")
    _add_field_bot_options(p)
    _add_overwrite(p)
    _add_config_options(p, profile=False, detector=False,
                        example="standoff_m=0.04 (metres; the keys of pollination.json's "
                        "config)")
    p.set_defaults(func=cmd_pollinate)

    p = sub.add_parser(
        "farmduino", help="serve a virtual Farmduino and print its device path (--virtual)",
        description="Serve a virtual Farmduino (FarmBot's firmware protocol over the MuJoCo "
        "gantry) on a pseudo-terminal and print its device path, for any serial client, "
        "until Ctrl-C.",
        epilog="example:\n  flowerpose farmduino --virtual --time-scale 10")
    p.add_argument("--virtual", action="store_true",
                   help="serve a virtual Farmduino (the only kind there is)")
    p.add_argument("--time-scale", type=_positive_number, default=1.0, metavar="K",
                   help="simulated seconds per wall second (default: %(default)g)")
    p.add_argument("--bare", action="store_true", help="the board on the firmware's defaults: "
                   "no endstops or encoders, so it cannot find home (default: encoders on, as "
                   "FarmBot OS sets a Genesis up)")
    p.set_defaults(func=cmd_farmduino)

    p = sub.add_parser(
        "frames", help="choose the sharpest frame of each of N bins of a scan",
        description="Choose the sharpest frame of each of --count bins of a scan (Laplacian "
        "variance of a centre crop) and write them to --out with their recorded poses "
        "(frames.json) and the camera (camera.json).",
        epilog="example:\n  flowerpose frames scan3 --count 200 --out frames3")
    p.add_argument("scan", type=Path, metavar="SCAN_DIR",
                   help="a scan folder from flowerpose scan (frames/, trajectory.csv)")
    add_setting_flags(p, _frames_base, {"--count": "count", "--crop": "crop_px",
                                        "--brightness-penalty": "brightness_penalty"},
                      metavars={"--count": "N", "--crop": "PX"},
                      switches=("--brightness-penalty",))
    p.add_argument("--out", type=Path, required=True, metavar="DIR",
                   help="folder for the chosen frames, frames.json and camera.json")
    _add_overwrite(p)
    _add_config_options(p, profile=False, detector=False,
                        example="brightness_target=110 (HSV value, 0-255; the keys of "
                        "frames.json's config)")
    p.set_defaults(func=cmd_frames)

    p = sub.add_parser(
        "reconstruct", help="frames -> camera poses (pycolmap) -> dense coloured cloud",
        description="Reconstruct a frames folder: pycolmap poses the frames (guided by the "
        "recorded poses), dense stereo turns them into a coloured cloud in the bed frame "
        "(cloud.ply, metres), and reconstruction.json says how well it went.",
        epilog="example:\n  flowerpose reconstruct frames3 --out recon3")
    p.add_argument("frames", type=Path, metavar="FRAMES_DIR",
                   help="a folder from flowerpose frames (frames.json, frames/, camera.json)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR",
                   help="folder for cloud.ply, the sparse model and reconstruction.json")
    _add_overwrite(p)
    add_setting_flags(p, _reconstruct_base, {"--dense-poses": "dense_poses"},
                      metavars={"--dense-poses": "{refined,recorded}"})
    _add_config_options(p, profile=False, detector=False)
    p.set_defaults(func=cmd_reconstruct)

    p = sub.add_parser(
        "dataset", help="training data for a 2D detector: seeded plants' grid views (or scan "
        "frames) with exact per-flower masks and boxes, as COCO or YOLO",
        description="Write training data for a 2D flower detector from seeded synthetic "
        "plants. Each image is a grid view the detect stage sees (or a scan frame) with every "
        "flower's exact instance mask and box, as COCO or YOLO, split into train and val by "
        "plant; dataset.json records the seeds and settings.",
        epilog="examples:\n"
        "  flowerpose dataset --plants 20 --out flowers-coco\n"
        "  flowerpose dataset --plants 20 --format yolo --views frames --out flowers-yolo")
    p.add_argument("--plants", type=PLANTS, required=True, metavar="N",
                   help="number of seeded plants")
    p.add_argument("--seed", type=SEED, default=0, metavar="S",
                   help="first plant seed: the plants are seeds S to S+N-1 (default: "
                   "%(default)s)")
    p.add_argument("--preset", choices=PRESETS, default="realistic",
                   help=PRESET_HELP + " (default: %(default)s)")
    add_setting_flags(p, _dataset_base, {
        "--format": "format", "--views": "views", "--val-fraction": "val_fraction",
        "--split-seed": "split_seed", "--frames": "frames_per_plant",
        "--min-pixels": "min_pixels"},
        metavars={"--format": "{coco,yolo}", "--views": "{grid,frames}", "--val-fraction": "F",
                  "--split-seed": "S", "--frames": "N", "--min-pixels": "N"})
    p.add_argument("--out", type=Path, required=True, metavar="DIR",
                   help="the dataset folder (dataset.json says how it was made)")
    _add_overwrite(p)
    _add_config_options(p, profile=False, detector=False,
                        example="sim.plant.flower_diameter_m=[0.03,0.05] (metres)")
    p.set_defaults(func=cmd_dataset)

    p = sub.add_parser(
        "detect", help="find flowers and their normals in a coloured cloud",
        description="Find the flowers in a coloured point cloud and estimate each one's "
        "normal three ways (plane, superellipsoid, paraboloid). Writes flowers.json, "
        "flowers.ply and normals.ply, the grid views with their detections, each flower's "
        "crop and report.html to --out.",
        epilog="examples:\n"
        "  flowerpose detect plant3/cloud.ply --out detect3\n"
        "  flowerpose detect candidates.ply --candidates --units m --out detect")
    p.add_argument("cloud", type=Path, metavar="CLOUD.ply",
                   help="a coloured point cloud (PLY): a reconstruction, Polycam's, an oracle's")
    p.add_argument("--out", type=Path, required=True, metavar="DIR",
                   help="folder for flowers.json, the views, the crops and report.html")
    _add_overwrite(p)
    p.add_argument("--units", choices=("auto", "m", "mm"), default="auto",
                   help="the cloud's unit; auto decides from its extent (default: %(default)s)")
    p.add_argument("--candidates", action="store_true",
                   help="CLOUD.ply holds points a detector already took out of views (its "
                   "crops, merged): skip ground removal, the grid and detection")
    _add_config_options(p)
    p.set_defaults(func=cmd_detect)

    p = sub.add_parser(
        "pose", help="normals of one flower crop, printed as JSON",
        description="Estimate one flower's normals from its crop and print them on standard "
        "output as a flowers.json entry (JSON: centre, normals per method, points, box).",
        epilog="example:\n  flowerpose pose detect3/crops/flower_00.ply")
    p.add_argument("crop", type=Path, metavar="CROP.ply", help="one flower's points (PLY)")
    p.add_argument("--units", choices=("auto", "m", "mm"), default="auto",
                   help="the crop's unit; auto decides from its extent (default: %(default)s)")
    _add_config_options(p, detector=False)
    p.set_defaults(func=cmd_pose)

    p = sub.add_parser(
        "score", help="score flowers.json against truth (plant.json or SageMaker cuboids)",
        description="Score a flowers.json against its truth (a plant.json, or SageMaker "
        "Ground Truth cuboids): one-to-one matches on centre distance, angle errors per "
        "method, printed as Table I; --out also writes report.json and report.md.",
        epilog="example:\n  flowerpose score detect3/flowers.json plant3/plant.json")
    p.add_argument("flowers", type=Path, metavar="FLOWERS.json",
                   help="estimates, from flowerpose detect")
    p.add_argument("truth", type=Path, metavar="TRUTH.json",
                   help="the truth: a plant.json, or SageMaker Ground Truth cuboids")
    p.add_argument("--truth-format", choices=("plant", "sagemaker"), default="plant",
                   help="TRUTH.json's format: plant (the simulator's) or sagemaker (the "
                   "authors' hand labels) (default: %(default)s)")
    p.add_argument("--truth-scale", type=float, default=25.0, metavar="K",
                   help="sagemaker: the factor the labelled cloud was scaled by, no unit "
                   "(default: %(default)g)")
    add_setting_flags(p, _eval_base, {"--max-distance": "score.max_distance_m"},
                      metavars={"--max-distance": "M"})
    p.add_argument("--out", type=Path, metavar="DIR",
                   help="also write report.json and report.md here (default: print only)")
    _add_overwrite(p)
    _add_config_options(p, profile=False, detector=False,
                        example="score.max_distance_m=0.01 (metres; score reads score.*)")
    p.set_defaults(func=cmd_score)

    p = sub.add_parser(
        "sweep", help="evaluate a grid of settings over seeded plants",
        description="Evaluate every combination of the --grid settings on the same seeded "
        "plants' clouds (oracle, or filmed and reconstructed once for all settings). "
        "Writes sweep.csv (a row per setting), sweep.png (each metric "
        "per setting, spread over the plants) and best.json (the best setting: most visible "
        "flowers found, then fewest false positives, then the smallest plane error).",
        epilog="examples:\n"
        "  flowerpose sweep --grid cluster.eps=0.006,0.008 --grid grid.views=6,14 --plants 3 "
        "--out sweep\n"
        "  flowerpose sweep --source scan --plants 3 --grid cluster.eps=0.006,0.008,0.01,0.012 "
        "--out sweep-scan")
    p.add_argument("--grid", action="append", required=True, metavar="KEY=V1,V2,...",
                   help="a setting's dotted key and its values; repeat for a grid over several")
    p.add_argument("--source", choices=("oracle", "scan", "rgbd"), default="oracle",
                   help="where the clouds come from, as for eval; scan and rgbd film each "
                   "plant once for every setting that does not change the plants or the "
                   "capture (default: %(default)s)")
    p.add_argument("--plants", type=PLANTS, default=5, metavar="N",
                   help="seeded plants per setting (default: %(default)s)")
    p.add_argument("--seed", type=SEED, default=0, metavar="S",
                   help="first plant seed (default: %(default)s)")
    p.add_argument("--preset", choices=PRESETS, default="realistic",
                   help=f"{PRESET_HELP} (default: %(default)s)")
    p.add_argument("--workers", type=POSITIVE, default=None, metavar="N",
                   help="worker processes (default: one per core)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR",
                   help="folder for sweep.csv, sweep.png and best.json")
    _add_overwrite(p)
    _add_cache_options(p)
    _add_ray_option(p)
    _add_config_options(p)
    p.set_defaults(func=cmd_sweep)

    p = sub.add_parser(
        "fidelity", help="the same statistics of real and synthetic flowers side by side",
        description="Describe a real labelled plant's flowers and synthetic plants' flowers "
        "by the same statistics (size, thickness, cupping, colours) and say which agree "
        "within a stated tolerance. Writes fidelity.json, fidelity.md and fidelity.png.",
        epilog="example:\n"
        "  flowerpose fidelity ../shared/real/paper-plant-3 runs/oracle --out fidelity")
    p.add_argument("real", type=Path, metavar="REAL_DIR",
                   help="a labelled real plant folder (cloud.ply or candidates/)")
    p.add_argument("synthetic", type=Path, nargs="+", metavar="SYNTH_DIR",
                   help="plant folders from flowerpose plant, or eval runs (their plants/); a "
                   "scan or RGB-D run is described by its reconstructed cloud")
    p.add_argument("--truth-scale", type=_positive_number, default=None, metavar="K",
                   help="the real labels' scale, no unit (default: source.json's, else 25)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR",
                   help="folder for fidelity.json, fidelity.md and fidelity.png")
    _add_overwrite(p)
    _add_config_options(p)
    p.set_defaults(func=cmd_fidelity)

    p = sub.add_parser(
        "cache", help="what the stage cache holds, and pruning it",
        description="Say what the stage cache holds (entries and size per stage, and when "
        "each stage's was last used) and, with --max-size or --clear, remove the least "
        "recently used entries first. Only the cache's own entries are removed.",
        epilog="examples:\n"
        "  flowerpose cache\n"
        "  flowerpose cache --max-size 5")
    p.add_argument("--cache", type=Path, metavar="DIR",
                   help="the stage cache's folder (default: $FLOWERPOSE_CACHE, else "
                   "~/.cache/flowerpose)")
    p.add_argument("--max-size", type=_non_negative_number, metavar="GB",
                   help="remove the least recently used entries until the rest take at most "
                   "GB gigabytes (default: remove nothing)")
    p.add_argument("--clear", action="store_true", help="remove every entry")
    p.set_defaults(func=cmd_cache)

    p = sub.add_parser(
        "bench", help="time the pipeline from cloud to flower poses",
        description="Time the pipeline from cloud to flower poses on one seeded plant's "
        "oracle cloud at each --points size: wall seconds per stage, the median of --repeat "
        "runs, imports and file reading excluded.",
        epilog="example:\n  flowerpose bench --points 125000 --repeat 3")
    p.add_argument("--points", type=_at_least(1000, CLOUD_POINTS_MAX, "more does not fit in "
                                               "memory"), nargs="+",
                   default=[125_000, 1_000_000], metavar="N",
                   help="cloud sizes to time, points (default: 125000 1000000)")
    p.add_argument("--repeat", type=POSITIVE, default=3, metavar="N",
                   help="runs per size; the median is reported (default: %(default)s)")
    p.add_argument("--seed", type=SEED, default=3, metavar="S",
                   help="plant seed (default: %(default)s, a realistic plant with 18 open "
                   "flowers)")
    p.add_argument("--out", type=Path, metavar="DIR",
                   help="also write bench.json here (default: print only)")
    _add_cache_options(p)
    _add_config_options(p, detector=False)
    p.set_defaults(func=cmd_bench)
    for command in sub.choices.values():
        _add_verbosity(command, default=argparse.SUPPRESS)
    return parser


def _add_verbosity(parser: argparse.ArgumentParser, default: Any) -> None:
    """-q / -v, before or after the command (`flowerpose -q eval`, `flowerpose eval -q`)."""
    parser.add_argument("-q", "--quiet", action="count", default=default,
                        help="say only warnings and errors (no progress)")
    parser.add_argument("-v", "--verbose", action="count", default=default,
                        help="say more: debugging detail")


def main(argv: list[str] | None = None) -> int:
    from flowerpose.log import configure as configure_log
    from flowerpose.log import third_party
    from flowerpose.processes import Terminated, terminate_cleanly

    parser = build_parser()
    if not (sys.argv[1:] if argv is None else argv):
        parser.print_help()  # a bare `flowerpose`: what it can do, not an error
        return 0
    args = parser.parse_args(argv)
    configure_log(args.verbose - args.quiet)
    terminate_cleanly()
    try:
        with third_party():  # other libraries' warnings: debug lines (-v), not the user's
            return args.func(args)
    except InputError as err:
        # Library code names the setting or argument; say the flag the user typed for it.
        flag = flag_for(parser, args, err.source)
        print(f"flowerpose: error: {f'{flag}: {err.problem}' if flag else err}",
              file=sys.stderr)
        return 2
    except BotError as err:
        # A fault of the bot or its link, said in one line that names the device.
        print(f"flowerpose: error: {err}", file=sys.stderr)
        return 2
    except JobsFailed as err:
        # Plants whose jobs failed on every try (Ray); the others' results are kept.
        print(f"flowerpose: error: {err}", file=sys.stderr)
        return 2 if err.user_error else 1
    except ModuleNotFoundError as err:
        # An optional package of an extra the install left out: say which extra.
        missing = missing_extra(err.name or "", f"flowerpose {args.command}")
        if missing is None:
            raise
        print(f"flowerpose: error: {missing}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        # The reader went away (`flowerpose ... | head`): nothing left to tell anyone.
        sys.stdout = open(os.devnull, "w")  # noqa: SIM115
        return 0
    except OSError as err:
        # A path the user gave that cannot be written or read (an --out that is a file, a
        # read-only folder, a full disk): their problem to fix, not a bug.
        where = err.filename or "file system"
        print(f"flowerpose: error: {where}: {err.strerror or err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("flowerpose: interrupted", file=sys.stderr)
        return 130
    except Terminated:
        print("flowerpose: terminated", file=sys.stderr)
        return 143


if __name__ == "__main__":
    sys.exit(main())
