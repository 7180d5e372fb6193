"""One subcommand a stage of the method: `plant` (a synthetic plant), `frames`,
`reconstruct`, `dataset` (training data), `detect`, `pose` and `score`."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from flowerpose.cli.flags import add_setting_flags
from flowerpose.cli.options import (
    CLOUD_POINTS,
    PLANTS,
    RENAMED_ATTRIBUTE,
    SEED,
    add_config_options,
    add_output,
    add_preset,
    add_units,
    at_least,
    configure,
    moved_under,
    owned,
    positive_number,
    starting_config,
)
from flowerpose.errors import InputError


def cmd_plant(args: argparse.Namespace) -> int:
    from flowerpose.sim.bundle import make_plant
    from flowerpose.sim.export import PLANT_FILES
    from flowerpose.sim.world_config import WorldSettings, sim_preset

    sim = configure(WorldSettings(sim_preset(args.preset)), args, reads=("sim",),
                    command="plant").sim
    with owned(args.out, "plant", args.overwrite, PLANT_FILES):
        bundle = make_plant(args.seed, points=args.points, out_dir=args.out, config=sim)
    visible = int(sum(bundle.visible))
    print(f"seed {args.seed} ({args.preset}): {len(bundle.plant.flowers)} open flowers, "
          f"{visible} visible, {len(bundle.cloud)} cloud points -> {args.out}")
    return 0


def add_plant(sub: argparse._SubParsersAction) -> None:
    """The `plant` subcommand's parser."""
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
    add_preset(p)
    add_output(p, "the plant folder to write")
    add_config_options(p, profile=False, detector=False,
                        example="sim.plant.flower_diameter_m=[0.03,0.05] (metres; plant reads "
                        "sim.plant.*, sim.oracle.* and sim.viewpoints.*)")
    p.set_defaults(func=cmd_plant)


#: `frames` and `reconstruct` read their sections of an eval's settings, under the keys an
#: eval gives them (`scan.frames.*`, `scan.reconstruct.*`).
_scan_stage_base = starting_config("flowerpose.pipeline.scan_stages:ScanStagesConfig")


def cmd_frames(args: argparse.Namespace) -> int:
    from flowerpose.pipeline.frames import select_frames

    config = configure(_scan_stage_base(), args, reads=("scan.frames",),
                       command="frames").scan.frames
    if (args.scan is None) == (args.images is None):
        raise InputError(args.scan or args.images or "frames", "give a scan folder or "
                         "--images PHOTOS_DIR_OR_VIDEO, one of them")
    photo_flags = [f for f, v in (("--colmap", args.colmap), ("--calibration", args.calibration),
                                  ("--poses", args.poses), ("--max-size", args.max_size))
                   if v is not None]
    if args.images is None and photo_flags:
        raise InputError(args.scan, f"{photo_flags[0]} is for --images; a scan folder has "
                         "its camera and poses")
    if args.images is not None:
        return _frames_from_photos(args, config.count)
    result = select_frames(args.scan, args.out, config, overwrite=args.overwrite)
    sharp = [f["sharpness"] for f in result["frames"]]
    print(f"{len(result['frames'])} of {result['recorded']} frames chosen in "
          f"{result['seconds']:.1f} s (sharpness median {sorted(sharp)[len(sharp) // 2]:.1f}) "
          f"-> {args.out / 'frames.json'}")
    return 0


def _frames_from_photos(args: argparse.Namespace, count: int) -> int:
    from flowerpose.pipeline.photos import PhotoImportConfig, import_photos

    config = PhotoImportConfig(count=count, max_size=args.max_size, units=args.pose_units)
    result = import_photos(args.images, args.out, config, colmap=args.colmap,
                           calibration=args.calibration, poses=args.poses,
                           overwrite=args.overwrite)
    camera = {"colmap": "the COLMAP model's camera", "calibration": "the calibration",
              "exif": "a focal length from EXIF (refined by reconstruct)",
              "default": "an estimated camera (refined by reconstruct)"}[result["camera"]]
    print(f"{len(result['frames'])} frames from {result['kind']} in {result['seconds']:.1f} s, "
          f"{camera}{', undistorted' if result['undistorted'] else ''}, poses: "
          f"{result['poses']} -> {args.out / 'frames.json'}")
    return 0


def add_frames(sub: argparse._SubParsersAction) -> None:
    """The `frames` subcommand's parser."""
    p = sub.add_parser(
        "frames", help="choose the sharpest frames of a scan, or take in photos or a video",
        description="Choose the sharpest frame of each of --count bins of a scan (Laplacian "
        "variance of a centre crop) and write them to --out with their recorded poses "
        "(frames.json) and the camera (camera.json). Or, with --images, make the same "
        "folder from photographs or a video of any camera: its calibration from --colmap or "
        "--calibration (distortion removed) or estimated, poses from --colmap (calibrated), "
        "--poses (rough) or none.",
        epilog="examples:\n  flowerpose frames scan3 --count 200 --out frames3\n"
        "  flowerpose frames --images photos/ --out frames-photos\n"
        "  flowerpose frames --images photos/ --colmap sparse/0 --pose-units mm --out f\n"
        "  flowerpose frames --images plant.mp4 --count 120 --out frames-video")
    p.add_argument("scan", type=Path, metavar="SCAN_DIR", nargs="?",
                   help="a scan folder from flowerpose scan (frames/, trajectory.csv)")
    p.add_argument("--images", type=Path, metavar="DIR|VIDEO",
                   help="instead of a scan: a folder of JPEG/PNG photographs (all kept) or a "
                   "video file (the sharpest frame of each of --count bins)")
    p.add_argument("--colmap", type=Path, metavar="MODEL_DIR",
                   help="--images: a COLMAP model (text or binary: COLMAP, Metashape, "
                   "RealityCapture, hloc exports) giving the camera and each photo's pose")
    p.add_argument("--calibration", type=Path, metavar="CAMERA.json",
                   help="--images: the camera, as camera.json (PINHOLE fx, fy, cx, cy) or with "
                   '"model" (any COLMAP camera model) and "params" in COLMAP\'s order')
    p.add_argument("--poses", type=Path, metavar="POSES.csv",
                   help="--images: rough poses, columns file, x, y, z (z up), pan (degrees "
                   "counter-clockwise from +x), tilt (degrees below the horizontal), as a "
                   "gantry logs them; reconstruct refines them")
    p.add_argument("--pose-units", choices=("m", "cm", "mm"), default="m",
                   help="the unit of the positions in --colmap or --poses (default: %(default)s)")
    p.add_argument("--max-size", type=at_least(16), metavar="PX",
                   help="--images: downscale to at most this longest side, pixels")
    add_setting_flags(p, _scan_stage_base, {"--count": "scan.frames.count",
                                            "--crop": "scan.frames.crop_px",
                                            "--brightness-penalty":
                                                "scan.frames.brightness_penalty"},
                      metavars={"--count": "N", "--crop": "PX"},
                      switches=("--brightness-penalty",))
    add_output(p, "folder for the chosen frames, frames.json and camera.json")
    add_config_options(p, profile=False, detector=False,
                        example="scan.frames.brightness_target=110 (HSV value, 0-255; frames "
                        "reads scan.frames.*, frames.json's config)")
    p.set_defaults(func=cmd_frames, **{RENAMED_ATTRIBUTE: moved_under(
        "flowerpose.pipeline.frames:FrameSelectConfig", "scan.frames")})


def cmd_marker(args: argparse.Namespace) -> int:
    from flowerpose.cli.options import check_writable
    from flowerpose.pipeline.board import PRINT_DPI, BoardSpec, board_image

    suffix = args.out.suffix.lower()
    if suffix not in (".png", ".pdf"):
        raise InputError(args.out, "the board is written as .png or .pdf")
    check_writable(args.out, "--out")
    if args.out.exists() and not args.overwrite:
        raise InputError(args.out, "exists: choose another file, or --overwrite")
    spec = BoardSpec(squares_x=args.squares[0], squares_y=args.squares[1],
                     square_m=args.square_mm / 1000, marker_m=args.square_mm * 0.73 / 1000)
    _write_board(args.out, board_image(spec), PRINT_DPI)
    print(f"a {spec.squares_x} x {spec.squares_y} ChArUco board of {args.square_mm:g} mm "
          f"squares ({spec.dictionary}) -> {args.out}; print it at 100 % (no fit to page), "
          "measure a square, and lay it flat beside the plant"
          + ("" if (spec.squares_x, spec.squares_y, args.square_mm) == (7, 5, 30) else
             f"; tell reconstruct: --set scan.reconstruct.sfm.board_spec.squares_x="
             f"{spec.squares_x} --set scan.reconstruct.sfm.board_spec.squares_y="
             f"{spec.squares_y} --set scan.reconstruct.sfm.board_spec.square_m="
             f"{spec.square_m:g} --set scan.reconstruct.sfm.board_spec.marker_m="
             f"{spec.marker_m:g}"))
    return 0


def _write_board(path: Path, grey, dpi: int) -> None:
    """The board image as PNG or PDF, its resolution recorded, so it prints to size."""
    import io

    from PIL import Image

    from flowerpose.atomic import write_bytes

    buffer = io.BytesIO()
    Image.fromarray(grey).save(buffer, format=path.suffix.lstrip(".").upper(),
                               dpi=(dpi, dpi), resolution=dpi)
    write_bytes(path, buffer.getvalue())


def _squares(text: str) -> tuple[int, int]:
    try:
        x, y = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: give COLSxROWS, e.g. 7x5") from None
    if x < 3 or y < 3:
        raise argparse.ArgumentTypeError(f"{text!r}: at least 3x3 squares")
    return x, y


def add_marker(sub: argparse._SubParsersAction) -> None:
    """The `marker` subcommand's parser."""
    p = sub.add_parser(
        "marker", help="a ChArUco board to print and lay beside the plant (scale and up)",
        description="Write a ChArUco board (a chessboard with ArUco markers) as a PNG or "
        "PDF that prints to size at 300 dpi. Laid flat beside the plant in photos without "
        "poses, it gives reconstruct the cloud's scale and up (scan.reconstruct.sfm.board).",
        epilog="example:\n  flowerpose marker --out board.pdf")
    p.add_argument("--out", type=Path, required=True, metavar="FILE.pdf|FILE.png",
                   help="the board's file")
    p.add_argument("--squares", type=_squares, default="7x5", metavar="COLSxROWS",
                   help="squares along and across (default: %(default)s, an A4 page)")
    p.add_argument("--square-mm", type=positive_number, default=30.0, metavar="MM",
                   help="a square's side as printed, millimetres (default: %(default)g)")
    p.add_argument("--overwrite", action="store_true", help="replace the file if it exists")
    p.set_defaults(func=cmd_marker)


def cmd_reconstruct(args: argparse.Namespace) -> int:
    from flowerpose.pipeline.reconstruct import reconstruct

    config = configure(_scan_stage_base(), args, reads=("scan.reconstruct",),
                       command="reconstruct").scan.reconstruct
    result = reconstruct(args.frames, args.out, config, overwrite=args.overwrite)
    report = result.report
    rms = report["alignment_rms_m"]
    placed = (f"camera centres {1000 * rms:.2f} mm RMS from the given ones" if rms is not None
              else f"no poses given: levelled, scale from {report['alignment']['scale_from']}")
    print(f"{report['images_registered']}/{report['images_used']} images registered, "
          f"{placed}; "
          f"{report['points']} points in {report['seconds']['total']:.1f} s "
          f"(sparse {report['seconds']['sparse']:.1f} s, dense {report['seconds']['dense']:.1f} s)"
          f" -> {report['cloud']}, {args.out / 'reconstruction.json'}")
    return 0


def add_reconstruct(sub: argparse._SubParsersAction) -> None:
    """The `reconstruct` subcommand's parser."""
    p = sub.add_parser(
        "reconstruct", help="frames -> camera poses (pycolmap) -> dense coloured cloud",
        description="Reconstruct a frames folder: pycolmap poses the frames (guided by the "
        "recorded poses), dense stereo turns them into a coloured cloud in the bed frame "
        "(cloud.ply, metres), and reconstruction.json says how well it went.",
        epilog="example:\n  flowerpose reconstruct frames3 --out recon3")
    p.add_argument("frames", type=Path, metavar="FRAMES_DIR",
                   help="a folder from flowerpose frames (frames.json, frames/, camera.json)")
    add_output(p, "folder for cloud.ply, the sparse model and reconstruction.json")
    add_setting_flags(p, _scan_stage_base, {"--dense-poses": "scan.reconstruct.dense_poses"},
                      metavars={"--dense-poses": "{refined,recorded}"})
    add_config_options(p, profile=False, detector=False,
                       example="scan.reconstruct.dense.voxel_size_m=0.0025 (metres; "
                       "reconstruct reads scan.reconstruct.*, reconstruction.json's config)")
    p.set_defaults(func=cmd_reconstruct, **{RENAMED_ATTRIBUTE: moved_under(
        "flowerpose.pipeline.reconstruct:ReconstructConfig", "scan.reconstruct")})


_dataset_base = starting_config("flowerpose.eval.labelling.dataset:DatasetConfig")


def cmd_dataset(args: argparse.Namespace) -> int:
    from flowerpose.cli.flags import given_settings
    from flowerpose.config import apply_overrides, parse_set_options
    from flowerpose.eval.jobs.config import eval_config
    from flowerpose.eval.jobs.plant_set import PlantSet
    from flowerpose.eval.labelling.dataset import DatasetConfig, write_dataset

    dataset = apply_overrides(DatasetConfig(), parse_set_options(given_settings(args)))
    config = configure(eval_config(args.preset), args, flags=False)
    plants = PlantSet("oracle", config.sim.plant.name, args.plants, args.seed)
    manifest = write_dataset(config, plants, dataset, args.out, args.overwrite)
    split = manifest["split"]
    print(f"{manifest['images']} images, {manifest['instances']} flower instances of "
          f"{plants.plants} plants ({len(split['train'])} train, {len(split['val'])} val: seeds "
          f"{', '.join(map(str, split['val'])) or 'none'}) as {dataset.format} -> "
          f"{args.out / 'dataset.json'}")
    return 0


def add_dataset(sub: argparse._SubParsersAction) -> None:
    """The `dataset` subcommand's parser."""
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
    add_preset(p)
    add_setting_flags(p, _dataset_base, {
        "--format": "format", "--views": "views", "--val-fraction": "val_fraction",
        "--split-seed": "split_seed", "--frames": "frames_per_plant",
        "--min-pixels": "min_pixels"},
        metavars={"--format": "{coco,yolo}", "--views": "{grid,frames}", "--val-fraction": "F",
                  "--split-seed": "S", "--frames": "N", "--min-pixels": "N"})
    add_output(p, "the dataset folder (dataset.json says how it was made)")
    add_config_options(p, profile=False, detector=False,
                        example="sim.plant.flower_diameter_m=[0.03,0.05] (metres)")
    p.set_defaults(func=cmd_dataset)


def cmd_detect(args: argparse.Namespace) -> int:
    from flowerpose.cloudio import read_cloud, require_hue, write_cloud
    from flowerpose.jsonio import write_json
    from flowerpose.log import noted
    from flowerpose.outputs import OutputFolder, check_output
    from flowerpose.pipeline.flowers import (
        SECTIONS_FROM,
        PipelineConfig,
        find_flowers,
        find_flowers_in_candidates,
        read_flowers,
        sections_run,
        write_flowers,
        write_normals_ply,
    )
    from flowerpose.pipeline.views import write_views

    config = configure(PipelineConfig(), args, reads=SECTIONS_FROM[
        "candidates" if args.candidates else "cloud"], command="detect"
        + (" --candidates" if args.candidates else ""))
    out: Path = args.out
    writes = ("flowers.json", "flowers.ply", "normals.ply", "config.json", "views", "crops",
              "report.html")
    check_output(out, "detect", args.overwrite, writes)
    with noted() as notes:
        cloud = read_cloud(args.cloud, units=args.units)
        if not args.candidates:  # a detector's candidates may be white petals alone
            require_hue(cloud, args.cloud)
        result = (find_flowers_in_candidates if args.candidates else find_flowers)(cloud,
                                                                                   config)
    # An earlier detection's files (crops of flowers this one may not have) go first.
    output = OutputFolder(out, "detect", args.overwrite, writes)
    output.record(write_flowers(out / "flowers.json", result, args.cloud,
                                "cloud" if args.candidates else "bed", notes),
                  *write_normals_ply(out, result.flowers),
                  write_json(out / "config.json", sections_run(
                      config, ["candidates" if args.candidates else "cloud"])))
    if result.projections:
        output.record(*write_views(out / "views", result.projections, result.detections,
                                   result.detection_flowers))
    output.record(*(write_cloud(out / "crops" / f"flower_{flower.id:02d}.ply",
                                cloud.subset(flower.crop)) for flower in result.flowers))
    from flowerpose.eval.reports.html_report import PlantView, write_html_report

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


def add_detect(sub: argparse._SubParsersAction) -> None:
    """The `detect` subcommand's parser."""
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
    add_output(p, "folder for flowers.json, the views, the crops and report.html")
    add_units(p, "cloud")
    p.add_argument("--candidates", action="store_true",
                   help="CLOUD.ply holds points a detector already took out of views (its "
                   "crops, merged): skip ground removal, the grid and detection")
    add_config_options(p)
    p.set_defaults(func=cmd_detect)


def cmd_pose(args: argparse.Namespace) -> int:
    from flowerpose.cloudio import read_cloud
    from flowerpose.pipeline.flowers import SECTIONS_FROM, PipelineConfig
    from flowerpose.pipeline.pose import estimate_pose
    from flowerpose.pipeline.segment import oriented_box

    config = configure(PipelineConfig(), args, reads=SECTIONS_FROM["crops"], command="pose")
    crop = read_cloud(args.crop, units=args.units)
    entry = {"id": 0, **estimate_pose(crop, config.pose, config.colour, config.cluster).to_json(),
             "box": oriented_box(crop.points).to_json()}
    print(json.dumps(entry, indent=1))
    return 0


def add_pose(sub: argparse._SubParsersAction) -> None:
    """The `pose` subcommand's parser."""
    p = sub.add_parser(
        "pose", help="normals of one flower crop, printed as JSON",
        description="Estimate one flower's normals from its crop and print them on standard "
        "output as a flowers.json entry (JSON: centre, normals per method, points, box).",
        epilog="example:\n  flowerpose pose detect3/crops/flower_00.ply")
    p.add_argument("crop", type=Path, metavar="CROP.ply", help="one flower's points (PLY)")
    add_units(p, "crop")
    add_config_options(p, detector=False)
    p.set_defaults(func=cmd_pose)


_eval_base = starting_config("flowerpose.eval.studies.eval_recipe:EvalConfig")


def cmd_score(args: argparse.Namespace) -> int:
    from flowerpose.eval.jobs.config import EvalConfig
    from flowerpose.eval.reports.score_report import score_files

    config = configure(EvalConfig(), args, reads=("score",), command="score")
    report = score_files(args.flowers, args.truth, args.truth_format, args.truth_scale,
                         config.score.max_distance_m)
    from flowerpose.eval.reports.report import REPORT_FILES, summary_lines, table, write_report

    print(table(report))
    for line in summary_lines(report):
        print(line)
    if args.out:
        with owned(args.out, "score", args.overwrite, REPORT_FILES):
            paths = write_report(args.out, report, f"flowerpose score: {args.flowers.name}")
        print(f"report: {paths[0]}, {paths[1]}")
    return 0


def add_score(sub: argparse._SubParsersAction) -> None:
    """The `score` subcommand's parser."""
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
    add_output(p, "also write report.json and report.md here (default: print only)", required=False)
    add_config_options(p, profile=False, detector=False,
                        example="score.max_distance_m=0.01 (metres; score reads score.*)")
    p.set_defaults(func=cmd_score)


def cmd_label(args: argparse.Namespace) -> int:
    import getpass
    import webbrowser

    from flowerpose.eval.labelling.label_server import make_server, open_session

    session = open_session(args.folder, args.labeller or getpass.getuser(), args.units,
                           args.detections)
    try:
        server = make_server(session, args.port)
    except OSError as error:  # the port taken, or not ours to bind
        raise InputError("--port", f"{args.port}: cannot serve there "
                         f"({error.strerror or error}); give another, or 0 for a free one"
                         ) from None
    url = f"http://127.0.0.1:{server.server_address[1]}/"
    print(f"label: {args.folder} ({len(session.cloud)} points, {len(session.start)} flowers "
          f"from {session.started_from}) at {url}; Ctrl-C stops (save in the page first)",
          flush=True)
    if args.browser:
        webbrowser.open(url)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        print("label: stopped", flush=True)
    finally:
        server.server_close()
    return 0


def add_label(sub: argparse._SubParsersAction) -> None:
    """The `label` subcommand's parser."""
    p = sub.add_parser(
        "label", help="label a plant's flowers in a local web page (pre-filled with its "
        "detections)",
        description="Open a local web page (127.0.0.1, a free port; nothing loaded from the "
        "internet) to label a plant folder's flowers: its cloud in 3D, pre-filled with its "
        "labels.json, or its detections (flowers.json, or --detections) to accept, reject, "
        "turn, flip, snap "
        "to the points under them, move or add. Saving writes the folder's labels.json "
        "(DESIGN.md, 'A label file'; the earlier file kept as labels.json.N.bak) with the "
        "time spent and the actions taken; flowerpose eval --source real reads it.",
        epilog="examples:\n"
        "  flowerpose label plant --detections plant/detect/flowers.json\n"
        "  flowerpose label plant --labeller ana --no-browser")
    p.add_argument("folder", type=Path, metavar="DIR",
                   help="a plant folder: cloud.ply (or candidates/, crops/), and the "
                   "labels.json to go on with, if any")
    p.add_argument("--detections", type=Path, default=None, metavar="FLOWERS.json",
                   help="detections to start from where the folder has no labels.json "
                   "(default: DIR/flowers.json)")
    p.add_argument("--labeller", default=None, metavar="NAME",
                   help="who labels, as the file records it (default: the login name)")
    p.add_argument("--port", type=at_least(0, 65535, "a TCP port"), default=0, metavar="N",
                   help="the port on 127.0.0.1, 1-65535 (default: 0, a free one)")
    p.add_argument("--no-browser", dest="browser", action="store_false",
                   help="print the page's address only; open no browser")
    add_units(p, "cloud")
    p.set_defaults(func=cmd_label)


def cmd_agree(args: argparse.Namespace) -> int:
    from flowerpose.eval.labelling.agreement import (
        agreement,
        agreement_lines,
        labelling_unit,
        read_labelling,
    )
    from flowerpose.jsonio import write_json

    a, b = read_labelling(args.a, args.truth_scale), read_labelling(args.b, args.truth_scale)
    metres, _ = labelling_unit(args.a, args.units)
    result = agreement(a, b, args.max_distance, metres)
    print("\n".join(agreement_lines(result)))
    if args.json is not None:
        write_json(args.json, result)
    return 0


def add_agree(sub: argparse._SubParsersAction) -> None:
    """The `agree` subcommand's parser."""
    from flowerpose.eval.scoring.match import MAX_MATCH_DISTANCE

    p = sub.add_parser(
        "agree", help="how far two labellings of one plant agree (label noise, measured)",
        description="Compare two labellings of one plant (each a flowerpose label file, "
        "SageMaker Ground Truth cuboids or a plant.json): their flowers matched one to one "
        "by centre, the angle between their normals (mean with its 95 %% interval, median, "
        "p90, share over 20 degrees), and the flowers only one of them holds or gave a "
        "pose. The mean is the label noise that score.label_error_deg assumes.",
        epilog="example:\n  flowerpose agree plant3/labels.json plant3/labels-second.json")
    p.add_argument("a", type=Path, metavar="A.json", help="the first labelling")
    p.add_argument("b", type=Path, metavar="B.json", help="the second labelling")
    p.add_argument("--truth-scale", type=positive_number, default=None, metavar="K",
                   help="the factor both were drawn at over the cloud's coordinates (default: "
                   "a flowerpose file's own, 25 for SageMaker, 1 for a plant.json)")
    p.add_argument("--max-distance", type=positive_number, default=MAX_MATCH_DISTANCE,
                   metavar="M", help="farthest two centres of one flower lie apart, metres, "
                   "whatever the cloud's unit (default: %(default)g)")
    add_units(p, "labels' cloud (auto: A's folder's source.json, else its cloud)")
    p.add_argument("--json", type=Path, default=None, metavar="FILE",
                   help="also write the comparison here as JSON (default: print only)")
    p.set_defaults(func=cmd_agree)
