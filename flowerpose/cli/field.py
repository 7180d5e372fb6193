"""The bot's subcommands: `scan` and `pollinate` on the simulated or the physical FarmBot
(--port, --cloud), `field` over a bed, and `farmduino`, a virtual Farmduino for any serial
client."""

from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path

from flowerpose.cli.field_bot import (
    add_camera_options,
    add_field_bot_options,
    check_field_bot_flags,
    field_bot,
    field_camera,
    home_field_bot,
    look_camera,
)
from flowerpose.cli.flags import add_setting_flags
from flowerpose.cli.options import (
    RENAMED_ATTRIBUTE,
    add_config_options,
    add_output,
    configure,
    jobs_on,
    moved_under,
    owned,
    plant_xy,
    positive_number,
    stage_cache,
    starting_config,
)
from flowerpose.errors import InputError
from flowerpose.hardware.backends import SERIAL_SIM_TIME_SCALE
from flowerpose.log import LOG
from flowerpose.pipeline.methods import METHODS

#: What `flowerpose scan --sim` reads of a config: the path (the oracle's cameras) and the
#: simulated camera (SCAN_FLAGS gives four of them flags).
SCAN_SETTINGS = ("sim.viewpoints", "scan.camera")


SCAN_FLAGS = {"--frame-rate": "scan.camera.frame_rate_hz", "--width": "scan.camera.width",
              "--height": "scan.camera.height", "--workers": "scan.camera.workers"}


def _scan_base():
    """`flowerpose scan`'s starting settings: an eval's, with the simulated camera's own
    frame rate (`SimCameraConfig`; an eval renders fewer, `EVAL_FRAME_RATE_HZ`)."""
    import dataclasses

    from flowerpose.eval.jobs.config import EvalConfig
    from flowerpose.hardware.backends.sim_camera import SimCameraConfig

    config = EvalConfig()
    return dataclasses.replace(config, scan=dataclasses.replace(config.scan,
                                                                camera=SimCameraConfig()))


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
    from flowerpose.eval.capture.scan_source import scan_plant
    from flowerpose.hardware.flights.scan_plan import plan_plant_scan, plan_table
    from flowerpose.sim.export import plant_obstacles, read_plant

    config = configure(_scan_base(), args, reads=SCAN_SETTINGS, command="scan --sim")
    plant = read_plant(args.plant)
    # The oracle's cameras, flown.
    plan = plan_plant_scan(plant.center[:2], plant.height, plant_obstacles(plant),
                           config.sim.viewpoints)
    print(f"plan: {len(plan.waypoints)} waypoints around the plant at "
          f"({plant.center[0]:.3f}, {plant.center[1]:.3f}) m, {plan.duration_s / 60:.1f} min "
          "of bot time; reach and collisions checked")
    if args.dry_run:
        print("\n".join(plan_table(plan)))
        return 0
    from flowerpose.hardware.backends.sim_bot import write_preview

    manifest = scan_plant(args.plant, args.out, config.scan, plan, args.via_farmduino,
                          progress=True)
    frames = len(frame_files(args.out))  # on disk: a killed session never counted its own
    truth = args.out / "plant.json"
    print(f"scan {manifest['status']}: {manifest['completed']}/{manifest['waypoints']} "
          f"waypoints, {frames} frames -> {args.out} (truth with the scan's visibility: "
          f"{truth})")
    if args.preview:
        print(f"preview: {write_preview(args.out, [plant.center], [plant.height])}")
    return 0


def _scan_field(args: argparse.Namespace) -> int:
    """scan --port / --cloud: the physical bot films a real plant with its USB camera."""
    from flowerpose.hardware.flights.scan_flight import approach_start, run_scan
    from flowerpose.hardware.flights.scan_plan import plan_field_scan, plan_table
    from flowerpose.scanio import frame_files

    if args.plant_at is None:
        raise InputError("--plant-at", "needed with --port and --cloud: where the plant's stem "
                         "stands, X,Y in metres in the bed frame")
    size = configure(_scan_base(), args, reads=("scan.camera.width", "scan.camera.height"),
                     command="scan --port/--cloud").scan.camera
    check_field_bot_flags(args)
    plan = plan_field_scan(args.plant_at, args.plant_height, args.plant_radius)
    x, y = args.plant_at
    print(f"plan: {len(plan.waypoints)} waypoints around the plant at ({x:.3f}, {y:.3f}) m, "
          f"{plan.duration_s / 60:.1f} min of bot time; the paper's bot's travel and servo "
          f"range, and clearance from a {args.plant_radius:g} m x {args.plant_height:g} m plant "
          "envelope, checked")
    if args.dry_run:
        print("\n".join(plan_table(plan)))
        return 0
    from flowerpose.hardware.backends.usb_camera import check_disk_space

    camera, recorder, source_camera = field_camera(args, size.width, size.height,
                                                    plan.duration_s)
    check_disk_space(args.out, camera, plan.duration_s)
    connect, source = field_bot(args, camera=recorder.bind, observer=recorder.observe)
    source["camera"] = source_camera
    source["plant"] = {"at": [x, y], "height": args.plant_height, "radius": args.plant_radius}
    try:
        with connect() as bot:
            home_field_bot(args, bot)
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


def add_scan(sub: argparse._SubParsersAction) -> None:
    """The `scan` subcommand's parser."""
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
    add_field_bot_options(p)
    add_camera_options(p, "--width x --height")
    p.add_argument("--plant-at", type=plant_xy, metavar="X,Y", help="--port/--cloud: where "
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
                   f"backend and a virtual Farmduino ({SERIAL_SIM_TIME_SCALE:g} x real time)")
    add_config_options(p, profile=False, detector=False,
                        example="sim.viewpoints.azimuth_step_deg=30 (degrees; --sim reads "
                        "sim.viewpoints.* and scan.camera.*; --port and --cloud "
                        "scan.camera.width and scan.camera.height)")
    p.set_defaults(func=cmd_scan)


_pollinate_base = starting_config("flowerpose.hardware.flights.pollination_plan:PollinateSettings")


def cmd_pollinate(args: argparse.Namespace) -> int:
    from flowerpose.cloudio import read_cloud
    from flowerpose.hardware.flights.pollination_flight import FLIGHT_NAME, read_flight
    from flowerpose.hardware.flights.pollination_plan import plan_pollination
    from flowerpose.hardware.flights.scan_plan import pose_header, pose_row
    from flowerpose.hardware.flights.visit_flowers import (
        NO_NORMAL,
        UNCERTAIN,
        check_plant,
        read_visit_flowers,
    )
    from flowerpose.jsonio import read_json, write_json
    from flowerpose.pipeline.flowers import read_flowers

    if args.port and args.cloud:
        raise InputError("pollinate", "choose one bot: --port PORT or --cloud, not both")
    flying = bool(args.port or args.cloud) and not args.dry_run
    check_field_bot_flags(args)
    settings = configure(_pollinate_base(), args)
    config = settings.pollinate
    document = read_json(args.flowers)
    if document.get("frame", "bed") != "bed":
        raise InputError(args.flowers, f"is in its cloud's own frame ({document['frame']}, a "
                         "phone scan's): pollination needs flowers in the bed frame, from a "
                         "FarmBot scan's reconstruction")
    flowers, skipped = read_visit_flowers(read_flowers(args.flowers), args.method,
                                          config.plans_uncertain)
    if not flowers:
        raise InputError(args.flowers, f"no flower has a {args.method} normal to approach "
                         "along" + (" that is certain (pollinate.visit_uncertain visits the "
                                    "others too)" if UNCERTAIN in skipped.values() else ""))
    check_plant(flowers, args.plant_at, args.plant_height, args.plant_radius, args.flowers)
    cloud_path = args.plant_cloud or (Path(document["source"]) if document.get("source")
                                      else None)
    corolla = None
    if cloud_path is not None and cloud_path.is_file():
        from flowerpose.pipeline.colour import flower_coloured

        cloud = read_cloud(cloud_path, units="m")
        obstacles, corolla = cloud.points, flower_coloured(cloud.colors, settings.colour)
    elif args.plant_cloud is not None:
        raise InputError(args.plant_cloud, "no such cloud")
    elif cloud_path is not None:
        raise InputError(cloud_path, f"no such cloud: {args.flowers} names it as the plant's "
                         "cloud, which the plan is checked against for collisions; give "
                         "--plant-cloud")
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
        camera = look_camera(args) if config.look.views else None  # checked before writing
        bot = field_bot(args, camera=camera)  # credentials and settings read before writing
    with owned(args.out, "pollinate", args.overwrite,
               ("pollination.json", FLIGHT_NAME, LOOK_FOLDER)) as output:
        output.record(write_json(args.out / "pollination.json", {
            **plan.to_json(), "flowers": str(args.flowers), "method": args.method,
            "no_normal": [f for f, why in skipped.items() if why == NO_NORMAL],
            "uncertain": [f for f, why in skipped.items() if why == UNCERTAIN],
            "cloud": None if obstacles is None else str(cloud_path),
            "plant": {"at": list(args.plant_at), "height": args.plant_height,
                      "radius": args.plant_radius}}))
    print(f"plan: {len(plan.planned)} of {len(flowers) + len(skipped)} flowers visited, "
          f"{plan.duration_s / 60:.1f} min of bot time; reach, the soil and "
          + ("clearance from the plant's cloud" if obstacles is not None else "no collisions")
          + f" checked -> {args.out / 'pollination.json'}")
    uncertain = {f.id for f in flowers if f.uncertain}
    for visit in plan.visits:
        if visit.status != "planned":
            print(f"flower {visit.flower}: unreachable {visit.reason}")
        elif visit.flower in uncertain:
            print(f"flower {visit.flower}: its normal's sign is uncertain: touched only if the "
                  "close look settles it")
    for flower, why in skipped.items():
        print(f"flower {flower}: no {args.method} normal" if why == NO_NORMAL else
              f"flower {flower}: its normal's sign is uncertain, left alone (--set "
              "pollinate.visit_uncertain=true visits it)")
    if args.dry_run:
        print(pose_header("move") + "  flower")
        for k, move in enumerate(plan.moves):
            label = "" if move.flower < 0 else f"{move.flower:7d}"
            print(f"{pose_row(k, move.kind, move.pose)} {label}")
    if flying and plan.planned:
        look = None
        if config.look.views:
            from flowerpose.hardware.flights.close_look import CloseLook
            from flowerpose.hardware.flights.pollination_plan import PlantObstacles

            look = CloseLook({f.id: f for f in flowers}, PlantObstacles.of(obstacles, corolla),
                             config, args.out / LOOK_FOLDER, settings.pose, settings.colour)
        return _fly_pollination(args, plan, look, *bot)
    return 0


#: The close look's frames, a folder per flower, in a pollinate --out folder.
LOOK_FOLDER = "look"


def _fly_pollination(args: argparse.Namespace, plan, look, connect, source: dict) -> int:
    """pollinate --port / --cloud: fly the plan on the physical bot (flight.json; a flight
    cut short resumes when rerun), looking again at each flower first with `look`, whose
    refined poses then join pollination.json's visits."""
    from flowerpose.hardware.flights.pollination_flight import fly_pollination
    from flowerpose.jsonio import read_json, write_json

    # flight.json and look/ are declared, never recorded: no later run of this stage
    # deletes them.
    with connect() as bot:
        home_field_bot(args, bot)
        flight = fly_pollination(bot, plan, args.out, source={
            **source, "bot": bot.info.name, "firmware": bot.info.firmware}, look=look)
    touched = sum(entry["rest"] is not None for entry in flight["done"])
    if look is not None:
        looks = {entry["flower"]: entry["look"] for entry in flight["done"] if "look" in entry}
        document = read_json(args.out / "pollination.json")
        for visit in document["visits"]:
            if visit["flower"] in looks:
                visit["look"] = looks[visit["flower"]]
        write_json(args.out / "pollination.json", document)
        counts = Counter(entry["status"] for entry in looks.values())
        print("close look: " + ", ".join(f"{n} {status}" for status, n in counts.items())
              + f" -> {args.out / 'pollination.json'}")
    flown = f" ({len(flight['done'])} visits flown)" if touched != len(flight["done"]) else ""
    print(f"flight {flight['status']}: {touched}/{len(flight['visits'])} flowers pollinated"
          f"{flown} -> {args.out / 'flight.json'}")
    return 0


def add_pollinate(sub: argparse._SubParsersAction) -> None:
    """The `pollinate` subcommand's parser."""
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
        "--port /dev/ttyACM0 --camera /dev/video0")
    p.add_argument("flowers", type=Path, metavar="FLOWERS.json",
                   help="flower poses in the bed frame (flowerpose detect on a FarmBot scan's "
                   "reconstruction, or a simulated one)")
    p.add_argument("--plant-at", type=plant_xy, required=True, metavar="X,Y",
                   help="where the plant's stem stands, metres in the bed frame (the flowers "
                   "must be the plant's)")
    p.add_argument("--plant-height", type=positive_number, default=0.25, metavar="H",
                   help="the plant's height above the soil, metres (default: %(default)s)")
    p.add_argument("--plant-radius", type=positive_number, default=0.15, metavar="R",
                   help="how far the plant reaches from its stem, metres (default: "
                   "%(default)s)")
    p.add_argument("--plant-cloud", type=Path, metavar="CLOUD.ply",
                   help="the plant's cloud in the bed frame, for collision checks (default: "
                   "the cloud flowers.json names as its source)")
    p.add_argument("--method", choices=METHODS,
                   default="plane", help="whose normal is the flower's axis (default: "
                   "%(default)s)")
    add_output(p, "folder for pollination.json")
    p.add_argument("--dry-run", action="store_true",
                   help="also print every move (FarmBot millimetres and servo commands), "
                   "and fly nothing")
    add_field_bot_options(p)
    p.add_argument("--camera", metavar="DEVICE", help="--port/--cloud: the head's USB camera "
                   "the close look takes its frames with (pollinate.look.*), best its stable "
                   "path /dev/v4l/by-id/...-video-index0")
    p.add_argument("--calibration", type=Path, metavar="CAMERA.json", help="--port/--cloud: "
                   "the camera's calibrated intrinsics at 1280 x 720 (default: estimated from "
                   "a 62.2 degree horizontal field of view)")
    p.add_argument("--focus", type=float, metavar="F", help="--camera: the manual focus "
                   "(V4L2 focus_absolute) that is sharp at the close look's 18 cm, calibrated "
                   "with it (default: locked where the autofocus settles as the camera opens, "
                   "which may be far)")
    add_config_options(p, profile=False, detector=False,
                        example="pollinate.standoff_m=0.04 (metres; pollinate reads "
                        "pollinate.*, pollination.json's config, and colour.*, which tells a "
                        "target's own corolla)")
    p.set_defaults(func=cmd_pollinate, **{RENAMED_ATTRIBUTE: moved_under(
        "flowerpose.hardware.flights.pollination_plan:PollinateConfig", "pollinate")})


def cmd_farmduino(args: argparse.Namespace) -> int:
    if not args.virtual:
        raise InputError("farmduino", "only --virtual is available: it serves a virtual "
                         "Farmduino on a pseudo-terminal")
    from flowerpose.hardware.backends.virtual_farmduino import FEEDBACK_PARAMETERS, VirtualFarmduino

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


def add_farmduino(sub: argparse._SubParsersAction) -> None:
    """The `farmduino` subcommand's parser."""
    p = sub.add_parser(
        "farmduino", help="serve a virtual Farmduino and print its device path (--virtual)",
        description="Serve a virtual Farmduino (FarmBot's firmware protocol over a simulated "
        "gantry) on a pseudo-terminal and print its device path, for any serial client, "
        "until Ctrl-C.",
        epilog="example:\n  flowerpose farmduino --virtual --time-scale 10")
    p.add_argument("--virtual", action="store_true",
                   help="serve a virtual Farmduino (the only kind there is)")
    p.add_argument("--time-scale", type=positive_number, default=1.0, metavar="K",
                   help="simulated seconds per wall second (default: %(default)g)")
    p.add_argument("--bare", action="store_true", help="the board on the firmware's defaults: "
                   "no endstops or encoders, so it cannot find home (default: encoders on, as "
                   "FarmBot OS sets a Genesis up)")
    p.set_defaults(func=cmd_farmduino)


def cmd_field(args: argparse.Namespace) -> int:
    from flowerpose.hardware.flights.bed_plan import plan_bed, read_bed

    if args.bed is None and not args.cloud:
        raise InputError("--bed", "give the bed: --bed FILE (TOML or CSV), or --cloud for the "
                         "plants of your FarmBot account's garden")
    if args.sim and args.port is not None:
        raise InputError("field", "choose one bot: --sim (simulated) or --port PORT, not both")
    if args.port is not None and args.cloud:
        raise InputError("field", "choose one bot: --port PORT or --cloud, not both (--cloud "
                         "without --bed also reads the bed from your account's garden)")
    if not args.sim:
        for flag, given in (("--seed", args.seed is not None),
                            ("--preset", args.preset is not None),
                            ("--via-farmduino", args.via_farmduino),
                            ("--time-scale", args.time_scale is not None)):
            if given:
                raise InputError(flag, "is for the simulated bed: add --sim")
    if args.token_file is not None and not args.cloud:
        raise InputError("--token-file", "is the web app's login: add --cloud")
    bed = read_bed(args.bed) if args.bed is not None else _account_bed(args)
    if args.sim:
        return _field_sim(args, bed)
    if args.dry_run:
        print("\n".join(plan_bed(bed).table()))
        return 0
    if args.port is None and not args.cloud:
        raise InputError("field", "choose the bot that films the bed: --port PORT (its "
                         "Farmduino on serial), --cloud (through FarmBot's web app) or --sim "
                         "(simulated); --dry-run plans it without one")
    return _field_physical(args, bed)


def _field_physical(args: argparse.Namespace, bed) -> int:
    """field --port / --cloud: the physical bot films the bed's plants with its USB camera,
    each reconstructed and its flowers found while it films the next."""
    import contextlib

    from flowerpose.eval.field.bed_loop import BedOptions
    from flowerpose.eval.field.physical_bed import (
        FieldBedRun,
        FieldRig,
        run_field_bed,
        settings_read,
    )
    from flowerpose.eval.jobs.config import EvalConfig
    from flowerpose.eval.pool import Execution
    from flowerpose.hardware.flights.bed_plan import plan_bed

    config = configure(EvalConfig(), args, reads=tuple(settings_read(EvalConfig())),
                       command="field --port/--cloud")
    plan = plan_bed(bed)  # a plant out of reach is refused before the camera opens
    print(f"bed: {len(plan.plants)} plants, {plan.duration_s / 60:.0f} min of bot time; "
          "every scan checked against the bot's reach and the neighbours")
    size = config.scan.camera
    camera, recorder, described = field_camera(args, size.width, size.height,
                                                 max(s.duration_s for s in plan.scans))
    connect, source = field_bot(args, camera=recorder.bind, observer=recorder.observe)
    source["camera"] = described

    @contextlib.contextmanager
    def session():
        try:
            with connect() as bot:
                home_field_bot(args, bot)
                yield bot
        finally:
            recorder.close()

    with jobs_on(args):
        report = run_field_bed(config, FieldBedRun(bed, plan, FieldRig(
            session, recorder, camera, source)), args.out, Execution(cache=stage_cache(args)),
            BedOptions(args.keep_going, args.pollinate))
    summary = report["summary"]
    print(f"bed: {summary['detected']} of {summary['plants']} plants detected, "
          f"{summary['flowers']} flowers found ({summary['with_normal']} with a normal) -> "
          f"{args.out / 'report.md'}")
    if "pollination" in summary:
        done = summary["pollination"]
        print(f"pollinated {done['done']} of {done['flowers']} flowers "
              f"({done['planned']} visits planned)")
    return 0


def _field_sim(args: argparse.Namespace, bed) -> int:
    """field --sim: the bed's plants generated and filmed in the simulator, scored."""
    from flowerpose.config import DEFAULT_PRESET
    from flowerpose.eval.field.bed_loop import BedOptions
    from flowerpose.eval.field.simulated_bed import (
        SimBedRun,
        make_bed_plants,
        plan_sim_bed,
        run_sim_bed,
    )
    from flowerpose.eval.jobs.config import eval_config
    from flowerpose.eval.jobs.plant_set import PlantSet
    from flowerpose.eval.pool import Execution
    from flowerpose.eval.reports.report import pollination_lines

    seed = 0 if args.seed is None else args.seed
    if seed < 0:
        raise InputError("--seed", f"must be 0 or more, got {seed}")
    if args.time_scale is not None and not args.via_farmduino:
        raise InputError("--time-scale", "is the virtual Farmduino's: add --via-farmduino")
    check_field_bot_flags(args)
    for flag in ("--camera", "--calibration", "--keep-all"):
        if getattr(args, flag[2:].replace("-", "_")):
            raise InputError(flag, "is the physical bot's camera: the simulated bed films "
                             "with the simulated one")
    time_scale = args.time_scale or SERIAL_SIM_TIME_SCALE
    config = configure(eval_config(args.preset or DEFAULT_PRESET), args, command="field --sim")
    if args.dry_run:
        plan = plan_sim_bed(make_bed_plants(bed, config, seed, None))
        print("\n".join(plan.table()))
        return 0
    scale = time_scale if args.via_farmduino else None
    with jobs_on(args):
        plants = PlantSet("scan", config.sim.plant.name, len(bed.plants), seed)
        report = run_sim_bed(config, SimBedRun(bed, plants, scale), args.out,
                             Execution(cache=stage_cache(args)),
                             BedOptions(args.keep_going, args.pollinate))
    summary = report["summary"]
    print(f"bed: {len(report['plants'])} of {len(bed.plants)} plants detected; "
          f"{summary['found_visible']} of {summary['visible']} visible flowers found, "
          f"{summary['fp']} false positives -> {args.out / 'report.md'}")
    for line in pollination_lines(report):
        print(line)
    return 0


def _account_bed(args: argparse.Namespace):
    """The bed of the plants in the FarmBot account's garden (--cloud: the web app's plant
    list, read with the same login as scan --cloud)."""
    from flowerpose.hardware.backends.cloud_bot import account_plants
    from flowerpose.hardware.backends.cloud_credentials import CloudCredentials
    from flowerpose.hardware.flights.bed_plan import bed_from_points

    credentials = CloudCredentials.from_environment(token_file=args.token_file)
    return bed_from_points(account_plants(credentials),
                           source=f"the garden of {credentials.server}")


def add_field(sub: argparse._SubParsersAction) -> None:
    """The `field` subcommand's parser."""
    from flowerpose.cli.options import add_cache_options, add_preset, add_ray_option
    from flowerpose.config import DEFAULT_PRESET

    p = sub.add_parser(
        "field", help="a field run over a bed of plants: each filmed, reconstructed while the "
        "bot films the next, its flowers found (--sim: scored against the truth)",
        description="Run a whole bed: the plants of a bed file (TOML or CSV; DESIGN.md, 'A bed "
        "file') or of your FarmBot account's garden (--cloud without --bed) planned and "
        "checked before anything moves, filmed one after another in the order that keeps "
        "the travel short, each reconstructed and its flowers found in a worker while the "
        "bot films the next; --pollinate then visits each plant's flowers. The physical bot "
        "films with its USB camera (--port or --cloud, with --camera); --sim generates a "
        "plant at each place, all in one simulated world, and scores each against its exact "
        "truth. Rerunning the command resumes the bed (bed.json): finished plants are left "
        "alone, a scan or a flight cut short resumes.",
        epilog="examples:\n"
        "  flowerpose field --sim --bed bed.toml --out bed4 --dry-run\n"
        "  flowerpose field --sim --bed bed.toml --out bed4 --set scan.frames.count=120\n"
        "  flowerpose field --sim --bed bed.toml --out bed4 --pollinate\n"
        "  flowerpose field --sim --bed bed.toml --out bed4 --ray\n"
        "  flowerpose field --cloud --out bed --dry-run\n"
        "  flowerpose field --port /dev/ttyACM0 --camera /dev/video0 --bed bed.toml --out bed")
    p.add_argument("--bed", type=Path, metavar="FILE",
                   help="the bed file: where each plant stands (an example: "
                   "assets/beds/example-4.toml in the package)")
    add_field_bot_options(p, cloud=" (without --bed, the bed is the plants of your "
                           "account's garden: the web app's plant list)")
    add_camera_options(p, "scan.camera.width x scan.camera.height (--set; 1280 x 720)")
    p.add_argument("--sim", action="store_true",
                   help="the simulated bot and generated plants, scored against their truth")
    p.add_argument("--seed", type=int, default=None, metavar="S",
                   help="--sim: the bed file's i-th plant is generated from seed S+i "
                   "(default: 0)")
    add_preset(p, default=None, shown=f"{DEFAULT_PRESET}; --sim only")
    p.add_argument("--out", type=Path, required=True, metavar="DIR",
                   help="the bed's folder (resumes the run already there)")
    p.add_argument("--keep-going", action="store_true",
                   help="a plant that fails is marked so in bed.json and the bed goes on "
                   "(default: the bed stops, the recording stopped and the bot let go)")
    p.add_argument("--dry-run", action="store_true",
                   help="print the bed's plan (order, waypoints, bot time), every scan checked "
                   "against the bot's reach and the neighbours, and stop: nothing connects "
                   "or moves")
    p.add_argument("--pollinate", action="store_true",
                   help="then plan each detected plant's visits from its flowers and fly them "
                   "(--sim: scored against the truth, with the visits from the true poses "
                   "beside them, pollination.png)")
    p.add_argument("--via-farmduino", action="store_true",
                   help="with --sim: drive the simulated bot through the physical bot's serial "
                   "backend and a virtual Farmduino (its firmware's motion timing)")
    p.add_argument("--time-scale", type=positive_number, default=None, metavar="K",
                   help="with --via-farmduino: the virtual Farmduino runs K times faster than "
                   f"real time (default: {SERIAL_SIM_TIME_SCALE:g}; 1 is the real bot's pace)")
    add_cache_options(p)
    add_ray_option(p)
    add_config_options(p, detector=False,
                       example="scan.frames.count=120 (--sim reads every section; --port and "
                       "--cloud the pipeline's, scan.frames, scan.reconstruct, "
                       "scan.camera.width and .height, and pollinate)")
    p.set_defaults(func=cmd_field)
