"""The jobs made of stages: `eval` (the benchmark), `sweep`, `fidelity`, `bench`, and
`cache`, which looks after their stage cache."""

from __future__ import annotations

import argparse
from datetime import datetime
from pathlib import Path

from flowerpose.cli_options import (
    CLOUD_POINTS_MAX,
    PLANTS,
    POSITIVE,
    SEED,
    add_cache_options,
    add_config_options,
    add_output,
    add_preset,
    add_ray_option,
    add_workers,
    at_least,
    check_writable,
    configure,
    jobs_on,
    non_negative_number,
    owned,
    positive_number,
    stage_cache,
)
from flowerpose.config import profile_names, suite_names
from flowerpose.errors import InputError
from flowerpose.eval.kinds import SOURCES, SYNTHETIC_SOURCES, TASKS

#: Plants of the default `flowerpose eval` (photogrammetry): about 5 minutes each here.
SCAN_PLANTS = 2


#: eval's source, preset and first seed when neither the command line nor a suite says.
EVAL_DEFAULTS = {"source": "scan", "preset": "realistic", "seed": 0, "task": "pose"}
#: What a report's config (and so its config.toml) records of the run beside the settings,
#: which `eval --config` takes as the run's own where the command line does not say.
EVAL_RUN_KEYS = ("source", "folders", "plants", "seed", "task")


def _default_out() -> Path:
    return Path("runs") / datetime.now().strftime("%Y%m%d-%H%M%S")


def cmd_eval(args: argparse.Namespace) -> int:
    from flowerpose.eval.harness import eval_config, run_eval

    suite = _apply_suite(args) if args.suite else None
    _run_from_config(args)
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
    for path, flag in ((args.junit, "--junit"), (args.summary, "--summary")):
        if path is not None:
            check_writable(path, flag)
    config = eval_config(args.preset,
                         lambda base: configure(base, args, run_keys=EVAL_RUN_KEYS))
    from flowerpose.pipeline.detect import make_detector

    make_detector(config.detect, config.colour)  # one that cannot load says so before any work
    # A compared profile or detector shares the run's settings (scoring, plants) but its own.
    compared = [parse_compare(text, config, args.method_timeout) for text in args.compare]
    methods = [parse_method(text, args.method_timeout) for text in args.method] + [
        what for _, what in compared if isinstance(what, ExternalMethod)]
    compare = {name: what for name, what in compared if not isinstance(what, ExternalMethod)}
    cache = stage_cache(args)
    names = [m.name for m in methods] + list(compare)
    if len(set(names)) < len(names):
        raise InputError("--compare", "each compared method needs a name of its own")
    out = args.out or _default_out()
    plants = args.plants or (SCAN_PLANTS if args.source == "scan" else 10)
    from flowerpose.eval.harness import eval_outputs
    from flowerpose.eval.report import assets_record

    writes = eval_outputs(args.source, args.folders, [*compare, *(m.name for m in methods)])
    with owned(out, "eval", args.overwrite, writes), jobs_on(args):
        report = run_eval(config, source=args.source, plants=plants, seed=args.seed,
                          out_dir=out, workers=args.workers, folders=args.folders,
                          truth_scale=args.truth_scale, compare=compare, suite=suite,
                          methods=methods, cache=cache, task=args.task,
                          assets=assets_record(None if args.source == "real" else args.preset,
                                               args.profile))
    if cache is not None and args.source != "real":
        from flowerpose.cache import prune_to_limit

        prune_to_limit(cache)
    import time

    from flowerpose.eval.report import comparison_table, summary_lines, table

    report["timing_s"]["wall"] = round(time.monotonic() - getattr(args, "started",
                                                                  time.monotonic()), 1)
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


def _run_from_config(args: argparse.Namespace) -> None:
    """A --config file's run keys (`EVAL_RUN_KEYS`, as a report's config.toml holds them)
    taken as this run's where the command line leaves them out; each checked as its flag
    is, the error naming the file."""
    if args.config is None:
        return
    from flowerpose.config import load_toml

    where = args.config
    for key, value in load_toml(where).items():
        if key not in EVAL_RUN_KEYS or getattr(args, key) not in (None, []):
            continue
        if key in ("source", "task"):
            choices = SOURCES if key == "source" else TASKS
            if value not in choices:
                raise InputError(where, f"{key}: must be one of {', '.join(choices)}, got "
                                 f"{value!r}")
        elif key in ("plants", "seed"):
            if not isinstance(value, int) or isinstance(value, bool) or value < (
                    1 if key == "plants" else 0):
                raise InputError(where, f"{key}: must be a whole number, at least "
                                 f"{1 if key == 'plants' else 0}, got {value!r}")
        else:
            paths = [entry.get("folder") if isinstance(entry, dict) else entry
                     for entry in (value if isinstance(value, list) else [value])]
            if not all(isinstance(path, str) for path in paths):
                raise InputError(where, "folders: must be a list of folder paths (or of "
                                 "tables with a folder, as a report records them)")
            value = [Path(path) for path in paths]
        setattr(args, key, value)


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
    if failed:
        print(f"\n{len(failed)} of {len(outcomes)} requirements failed:")
        print(outcome_table(outcomes, failed_only=True))
    else:
        print(f"\nall {len(outcomes)} requirements hold ({len(requirements)} on the run and on "
              f"each of {len(report['plants'])} plants)")
    unwritten = []
    for path, write in ((args.junit, write_junit), (args.summary, write_summary)):
        if path is not None:
            try:
                write(path, outcomes, title)
            except InputError as err:  # the disk changed during the run: said, gates kept
                unwritten.append(str(err))
    for line in unwritten:
        from flowerpose.log import LOG

        LOG.error(f"flowerpose: error: {line}")
    return 1 if failed else 2 if unwritten else 0


def add_eval(sub: argparse._SubParsersAction) -> None:
    """The `eval` subcommand's parser."""
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
    p.add_argument("--source", choices=SOURCES, default=None,
                   help="where clouds come from: scan = the simulated bot films each plant "
                   "and photogrammetry reconstructs it (default); oracle = the plant's "
                   "surfaces sampled directly; rgbd = a simulated depth camera's views fused; "
                   "real = labelled real plant folders (DIR ...)")
    p.add_argument("folders", nargs="*", type=Path, metavar="DIR",
                   help="--source real: labelled plant folders (labels.json and cloud.ply, "
                   "candidates/*.ply or crops/*.ply; docs/guides/own-scan.md)")
    p.add_argument("--truth-scale", type=positive_number, default=None, metavar="K",
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
    add_preset(p, None, EVAL_DEFAULTS["preset"])
    add_workers(p)
    add_output(p, "output folder (default: runs/<date>-<time>/)", required=False)
    p.add_argument("--method", action="append", default=[], metavar="NAME=CMD",
                   help="also score another method on the same clouds, printed beside this "
                   "one: CMD runs once per plant with {cloud} (the plant's cloud, PLY) and "
                   "{out} (a folder to write flowers.json into), e.g. "
                   "mine='python detect.py {cloud} {out}', or NAME alone for a method an "
                   "installed package registers (repeatable; default: none)")
    p.add_argument("--task", choices=TASKS, default=None,
                   help="pose: score the flower poses (Table I); pollinate: also plan, fly "
                   "and score a pollinator visit to each synthetic flower, from the "
                   "estimated poses and from the true ones (summary.pollination; "
                   f"pollination.png) (default: {EVAL_DEFAULTS['task']})")
    p.add_argument("--method-timeout", type=positive_number, default=600.0, metavar="S",
                   help="seconds an external method may take on one plant (default: "
                   "%(default)g)")
    add_cache_options(p)
    add_ray_option(p)
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
    add_config_options(p)
    p.set_defaults(func=cmd_eval)


def cmd_sweep(args: argparse.Namespace) -> int:
    from flowerpose.eval.harness import eval_config
    from flowerpose.eval.sweep import parse_grid, run_sweep, sweep_outputs

    if args.folders and args.source != "real":
        raise InputError(args.folders[0], "plant folders are for --source real")
    config = eval_config(args.preset,
                         lambda base: configure(base, args, run_keys=EVAL_RUN_KEYS))
    grid = parse_grid(args.grid, config)
    cache = stage_cache(args)
    writes = sweep_outputs(grid, args.source, args.folders)
    with owned(args.out, "sweep", args.overwrite, writes), \
            jobs_on(args):
        best = run_sweep(config, grid, plants=args.plants, seed=args.seed, out_dir=args.out,
                         workers=args.workers, source=args.source, cache=cache,
                         folders=args.folders)
    if cache is not None:
        from flowerpose.cache import prune_to_limit

        prune_to_limit(cache)
    metrics = best["metrics"]
    print("best: " + ", ".join(f"{k}={v}" for k, v in best["setting"].items())
          + f" (recall_visible {metrics['recall_visible']}, fp_rate {metrics['fp_rate']}, "
          f"plane {metrics['plane_mean_deg']}°; its settings in {args.out / 'best.json'})")
    return 0


def add_sweep(sub: argparse._SubParsersAction) -> None:
    """The `sweep` subcommand's parser."""
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
        "--out sweep-scan\n"
        "  flowerpose sweep --source real ../shared/real/paper-plant-3 --grid "
        "cluster.eps=0.008,0.01 --out sweep-real")
    p.add_argument("--grid", action="append", required=True, metavar="KEY=V1,V2,...",
                   help="a setting's dotted key and its values; repeat for a grid over several")
    p.add_argument("--source", choices=SOURCES, default="oracle",
                   help="where the clouds come from, as for eval; scan and rgbd film each "
                   "plant once for every setting that does not change the plants or the "
                   "capture; real: labelled plant folders (DIR ...) (default: %(default)s)")
    p.add_argument("folders", nargs="*", type=Path, metavar="DIR",
                   help="--source real: labelled plant folders")
    p.add_argument("--plants", type=PLANTS, default=5, metavar="N",
                   help="seeded plants per setting (default: %(default)s)")
    p.add_argument("--seed", type=SEED, default=0, metavar="S",
                   help="first plant seed (default: %(default)s)")
    add_preset(p)
    add_workers(p)
    add_output(p, "folder for sweep.csv, sweep.png and best.json")
    add_cache_options(p)
    add_ray_option(p)
    add_config_options(p)
    p.set_defaults(func=cmd_sweep)


def cmd_fidelity(args: argparse.Namespace) -> int:
    from flowerpose.eval.fidelity import FIDELITY_FILES, run_fidelity, table
    from flowerpose.eval.harness import EvalConfig, pipeline_part

    config = configure(EvalConfig(), args)
    with owned(args.out, "fidelity", args.overwrite, FIDELITY_FILES):
        report = run_fidelity(args.real, args.synthetic, args.out, pipeline_part(config),
                              config.score.max_distance_m, args.truth_scale)
    print(table(report))
    print(f"{report['holds']} of {report['of']} statistics within tolerance "
          f"({report['real']['flowers']} real flowers, {report['synthetic']['flowers']} "
          f"synthetic) -> {args.out / 'fidelity.json'}, {args.out / 'fidelity.md'}, "
          f"{args.out / 'fidelity.png'}")
    return 0


def add_fidelity(sub: argparse._SubParsersAction) -> None:
    """The `fidelity` subcommand's parser."""
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
    p.add_argument("--truth-scale", type=positive_number, default=None, metavar="K",
                   help="the real labels' scale, no unit (default: source.json's, else 25)")
    add_output(p, "folder for fidelity.json, fidelity.md and fidelity.png")
    add_config_options(p)
    p.set_defaults(func=cmd_fidelity)


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


def add_cache(sub: argparse._SubParsersAction) -> None:
    """The `cache` subcommand's parser."""
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
    p.add_argument("--max-size", type=non_negative_number, metavar="GB",
                   help="remove the least recently used entries until the rest take at most "
                   "GB gigabytes (default: remove nothing)")
    p.add_argument("--clear", action="store_true", help="remove every entry")
    p.set_defaults(func=cmd_cache)


def cmd_bench(args: argparse.Namespace) -> int:
    from flowerpose.eval.bench import run_bench
    from flowerpose.pipeline.flowers import PipelineConfig

    run_bench(args.points, repeat=args.repeat, seed=args.seed, out=args.out,
              config=configure(PipelineConfig(), args), cache=stage_cache(args))
    return 0


def add_bench(sub: argparse._SubParsersAction) -> None:
    """The `bench` subcommand's parser."""
    p = sub.add_parser(
        "bench", help="time the pipeline from cloud to flower poses",
        description="Time the pipeline from cloud to flower poses on one seeded plant's "
        "oracle cloud at each --points size: wall seconds per stage, the median of --repeat "
        "runs, imports and file reading excluded.",
        epilog="example:\n  flowerpose bench --points 125000 --repeat 3")
    p.add_argument("--points", type=at_least(1000, CLOUD_POINTS_MAX, "more does not fit in "
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
    add_cache_options(p)
    add_config_options(p, detector=False)
    p.set_defaults(func=cmd_bench)


def _numbers(what: str):
    """An argparse type: a comma-separated list of numbers."""
    def parse(text: str) -> list[float]:
        try:
            values = [float(v) for v in text.split(",") if v.strip()]
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r}: {what} as numbers separated by "
                                             "commas") from None
        if not values:
            raise argparse.ArgumentTypeError(f"{text!r}: no {what}")
        return values
    return parse


def _texts(text: str) -> list[str]:
    return [v.strip() for v in text.split(",") if v.strip()]


def cmd_stress(args: argparse.Namespace) -> int:
    from flowerpose.eval.harness import eval_config, real_plants
    from flowerpose.eval.stress import DEFAULT_LEVELS, STRESS_FILES, plan_from, run_stress

    if args.folders and args.source != "real":
        raise InputError(args.folders[0], "plant folders are for --source real")
    config = eval_config(args.preset,
                         lambda base: configure(base, args, run_keys=EVAL_RUN_KEYS))
    levels = {kind: getattr(args, kind) if getattr(args, kind) is not None
              else list(DEFAULT_LEVELS[kind]) for kind in DEFAULT_LEVELS}
    if args.source == "real":
        views = min(len(p.clouds) if p.stage == "candidates" else config.grid.views
                    for p in real_plants(args.folders, args.truth_scale)
                    if p.stage != "crops") if any(
            True for _ in args.folders) else 0
    else:
        views = config.grid.views
    drop = views if args.drop_views == "all" else int(args.drop_views)
    if drop > views:
        raise InputError("--drop-views", f"{drop}: there are {views} views to drop")
    capture = {k: v for k, v in (("frames", args.frames), ("resolution", args.resolution)) if v}
    for value in capture.get("resolution", []):
        width, _, height = value.partition("x")
        if not (width.isdigit() and height.isdigit()):
            raise InputError("--resolution", f"{value!r}: WIDTHxHEIGHT in pixels, e.g. 640x360")
    for value in capture.get("frames", []):
        if not value.isdigit():
            raise InputError("--frames", f"{value!r}: a whole number of frames")
    plan = plan_from(levels, args.channels, drop, capture, args.repeats, args.stress_seed)
    cache = stage_cache(args)
    with owned(args.out, "stress", args.overwrite, STRESS_FILES), jobs_on(args):
        report = run_stress(config, plan, args.out, args.source, args.folders, args.plants,
                            args.seed, args.workers, cache, args.truth_scale)
    if cache is not None and args.source != "real":
        from flowerpose.cache import prune_to_limit

        prune_to_limit(cache)
    from flowerpose.eval.stress import stress_markdown

    print(stress_markdown(report).split("\n\n", 2)[2].split("\n\n")[0])
    print(f"stress: {args.out / 'stress.json'}, {args.out / 'stress.md'}, "
          f"{args.out / 'stress.png'}, {args.out / 'report.html'}")
    return 0


def add_stress(sub: argparse._SubParsersAction) -> None:
    """The `stress` subcommand's parser."""
    from flowerpose.eval.stress import DEFAULT_LEVELS

    def levels(kind: str) -> str:
        return ",".join(f"{v:g}" for v in DEFAULT_LEVELS[kind])

    p = sub.add_parser(
        "stress", help="the robustness report: the pipeline over perturbed clouds",
        description="Run the pipeline on each plant as it is and under seeded perturbations "
        "of its cloud (thinned, darker or brighter, a colour cast, position noise, a view "
        "left out; for --source scan also fewer frames and a lower resolution), scored "
        "against the same truth. Writes stress.json, stress.md, stress.png (a panel per "
        "perturbation: recall and plane error against its strength) and report.html.",
        epilog="examples:\n"
        "  flowerpose stress --source oracle --plants 3 --out stress-oracle\n"
        "  flowerpose stress --source real ../shared/real/paper-plant-3 --repeats 3 "
        "--out stress-real")
    p.add_argument("--source", choices=SOURCES, default="oracle",
                   help="where the clouds come from, as for eval (default: %(default)s)")
    p.add_argument("folders", nargs="*", type=Path, metavar="DIR",
                   help="--source real: labelled plant folders")
    p.add_argument("--truth-scale", type=positive_number, default=None, metavar="K",
                   help="--source real: the labels' scale, no unit (default: each folder's "
                   "source.json, else 25 for SageMaker labels)")
    p.add_argument("--plants", type=PLANTS, default=3, metavar="N",
                   help="seeded synthetic plants (default: %(default)s)")
    p.add_argument("--seed", type=SEED, default=0, metavar="S",
                   help="first plant seed (default: %(default)s)")
    add_preset(p)
    p.add_argument("--thin", type=_numbers("fractions"), metavar="F,...",
                   help="fractions of the points kept, 0-1 (default: "
                   f"{levels('thin')})")
    p.add_argument("--exposure", type=_numbers("factors"), metavar="K,...",
                   help="factors on linear light (default: "
                   f"{levels('exposure')})")
    p.add_argument("--cast", type=_numbers("changes"), metavar="C,...",
                   help="relative changes of one channel's linear light, each on every "
                   f"--channels (default: {levels('cast')})")
    p.add_argument("--channels", default="rgb", choices=("r", "g", "b", "rg", "rb", "gb", "rgb"),
                   help="the channels a cast acts on, one at a time (default: %(default)s)")
    p.add_argument("--noise", type=_numbers("standard deviations"), metavar="M,...",
                   help="Gaussian position noise, standard deviation in the cloud's unit "
                   f"(metres) (default: {levels('noise')})")
    p.add_argument("--drop-views", default="all", metavar="N|all",
                   choices=["all", *(str(k) for k in range(27))],
                   help="leave out each of the first N views in turn (a real plant's "
                   "candidates files, else grid views); 0: none (default: %(default)s)")
    p.add_argument("--frames", type=_texts, metavar="N,...",
                   help="--source scan: frames chosen for photogrammetry (default: none)")
    p.add_argument("--resolution", type=_texts, metavar="WxH,...",
                   help="--source scan: camera resolutions, pixels (default: none)")
    p.add_argument("--repeats", type=POSITIVE, default=1, metavar="N",
                   help="seeded repeats of each random perturbation (thinning, noise) "
                   "(default: %(default)s)")
    p.add_argument("--stress-seed", type=SEED, default=0, metavar="S",
                   help="seed of the perturbations (default: %(default)s)")
    add_workers(p)
    add_output(p, "folder for stress.json, stress.md, stress.png and report.html")
    add_cache_options(p)
    add_ray_option(p)
    add_config_options(p)
    p.set_defaults(func=cmd_stress)


def cmd_tune(args: argparse.Namespace) -> int:
    from flowerpose.config import parse_set_options
    from flowerpose.eval.harness import eval_config
    from flowerpose.eval.plant_sets import parse_sets, synthetic_set
    from flowerpose.eval.tune import (
        TUNE_FILES,
        TuneSpec,
        local_storage,
        open_study,
        report_study,
        run_trials,
        score_defaults,
        study_name,
        user_overrides,
        validation_default,
    )
    from flowerpose.eval.tune_space import parse_objectives, read_space
    from flowerpose.stopwatch import Stopwatch

    overrides = user_overrides(args.profile, args.config, parse_set_options(args.set))
    base = eval_config(args.preset or "realistic", lambda c: configure(c, args))
    space = tuple(read_space(args.space, base))
    objectives = tuple(parse_objectives(args.objective))
    train = parse_sets(args.train) if args.train else [
        synthetic_set(args.source, args.preset or "realistic", args.plants, args.seed)]
    validate = parse_sets(args.validate) if args.validate else validation_default(train)
    storage = args.study or f"sqlite:///{(args.out / 'study.db').resolve()}"
    if args.ray not in (None, "local", "auto") and local_storage(storage) and not any(
            host in args.ray for host in ("127.0.0.1", "localhost")):
        raise InputError("--study", f"{storage} is on this machine's disk, which a remote "
                         "Ray cluster does not reach: give a storage it reaches (an RDB URL, "
                         "e.g. postgresql://..., or journal:///PATH on a shared file system)")
    default_name, identity = study_name(space, tuple(train), objectives)
    cache = stage_cache(args)
    spec = TuneSpec(space, tuple(train), tuple(validate), objectives, overrides, storage,
                    args.study_name or default_name, args.sampler_seed, args.out, cache)
    watch = Stopwatch()
    with owned(args.out, "tune", args.overwrite, TUNE_FILES), jobs_on(args):
        args.out.mkdir(parents=True, exist_ok=True)
        open_study(spec, identity, create=True)
        from flowerpose.log import LOG

        LOG.info(f"tune: study {spec.study_name}: scoring the settings without a trial's on "
                 f"{len(train)} training and {len(validate)} validation sets")
        timer = Stopwatch()
        defaults = score_defaults(spec)
        each = timer.elapsed()
        workers = 1 if args.ray is not None else (args.workers or 1)
        LOG.info(f"tune: one trial takes about {each:.0f} s here: {args.trials} trials, about "
                 f"{each * args.trials / workers / 60:.1f} min on {workers} worker(s)")
        try:
            if args.ray is None and workers == 1:
                run_trials(spec, args.trials)
            else:
                from flowerpose.eval.runner import run_jobs

                tasks = args.trials if args.ray is not None else min(workers, args.trials)
                shares = [args.trials // tasks + (k < args.trials % tasks) for k in range(tasks)]
                run_jobs(run_trials, [(spec, n) for n in shares], workers, stage="tune",
                         labels=[f"worker {k}" for k in range(tasks)])
        finally:
            report = report_study(spec, defaults, watch.elapsed())
    from flowerpose.eval.tune import tune_markdown

    print(tune_markdown(report))
    print(f"tune: {args.out / 'tune.json'}, {args.out / 'tune.md'}, {args.out / 'tune.html'}"
          + (f", {args.out / 'best.toml'}" if report["chosen"] else ""))
    return 0


def add_tune(sub: argparse._SubParsersAction) -> None:
    """The `tune` subcommand's parser."""
    p = sub.add_parser(
        "tune", help="search the settings with Optuna on training plants, validate elsewhere",
        description="Search the settings of --space with Optuna: each trial scores its "
        "settings on the training plants (the objectives the sampler sees) and on "
        "validation plants it never sees. The chosen trial is the training front's best on "
        "validation. The study lives in --study, so running the command again adds trials. "
        "Writes tune.json, tune.md, tune.html (Optuna's figures) and best.toml (the chosen "
        "settings, for --config).",
        epilog="examples:\n"
        "  flowerpose tune --space space.toml --trials 40 --out tune --plants 3\n"
        "  flowerpose tune --space space.toml --trials 100 --train oracle-10 --train "
        "field-10 --validate ../shared/real/paper-plant-3 --workers 2 --out tune-field")
    p.add_argument("--space", type=Path, required=True, metavar="SPACE.toml",
                   help="the settings to search: \"KEY\" = { low = L, high = H [, log = true]"
                   " [, int = true] } or { choices = [...] }, one line per dotted key")
    p.add_argument("--trials", type=POSITIVE, required=True, metavar="N",
                   help="trials this run adds to the study")
    add_output(p, "folder for tune.json, tune.md, tune.html, best.toml (and study.db, the "
               "default storage)")
    p.add_argument("--train", action="append", default=[], metavar="SUITE|DIR",
                   help="training plants: a suite's name or file, or real plant folders "
                   "(repeatable; default: --source/--plants/--seed/--preset)")
    p.add_argument("--validate", action="append", default=[], metavar="SUITE|DIR",
                   help="validation plants, never shown to the search (repeatable; default: "
                   "the seeds after each synthetic training set, none for real ones)")
    p.add_argument("--source", choices=SYNTHETIC_SOURCES, default="oracle",
                   help="without --train: where the training plants' clouds come from "
                   "(default: %(default)s)")
    p.add_argument("--plants", type=PLANTS, default=3, metavar="N",
                   help="without --train: seeded training plants (default: %(default)s)")
    p.add_argument("--seed", type=SEED, default=0, metavar="S",
                   help="without --train: the first training seed (default: %(default)s)")
    add_preset(p, None, "realistic")
    p.add_argument("--study", metavar="STORAGE",
                   help="the Optuna storage: an RDB URL (sqlite:///FILE, postgresql://...) or "
                   "journal:///FILE (default: sqlite:///DIR/study.db)")
    p.add_argument("--study-name", metavar="NAME",
                   help="the study's name (default: made from the space, the training "
                   "plants, the objectives and the code version)")
    p.add_argument("--objective", action="append", default=[], metavar="max:KEY|min:KEY",
                   help="an objective over the report summary's keys (repeatable; default: "
                   "max:f1 and min:error_deg.plane.mean)")
    p.add_argument("--sampler-seed", type=SEED, default=None, metavar="N",
                   help="seed of the sampler: the same trials again, with one worker "
                   "(default: none)")
    p.add_argument("--workers", type=POSITIVE, default=None, metavar="N",
                   help="trials at once, each in a process of its own (default: 1)")
    add_cache_options(p)
    add_ray_option(p)
    add_config_options(p)
    p.set_defaults(func=cmd_tune)


def cmd_results(args: argparse.Namespace) -> int:
    from flowerpose.eval.results import results_markdown

    print(results_markdown(args.reports, args.title, not args.no_paper), end="")
    return 0


def add_results(sub: argparse._SubParsersAction) -> None:
    """The `results` subcommand's parser."""
    p = sub.add_parser(
        "results", help="a results page (Markdown) made from runs' reports",
        description="Print a Markdown results page made from runs' own files: a table row "
        "per eval report.json (what ran, flowers found of the visible, false positives, the "
        "fits' errors) beside the paper's own numbers, then a robustness section per "
        "stress.json and a speed section per bench.json, each run's command, code version, "
        "date and machine under its table.",
        epilog="example:\n  flowerpose results runs/oracle-10/report.json "
        "runs/stress3/stress.json runs/bench/bench.json > results.md")
    p.add_argument("reports", type=Path, nargs="+", metavar="REPORT.json",
                   help="eval report.json, stress.json or bench.json files, in the page's "
                   "order")
    p.add_argument("--title", default="Results", help="the page's title (default: %(default)s)")
    p.add_argument("--no-paper", action="store_true",
                   help="leave out the paper's own row (default: include it)")
    p.set_defaults(func=cmd_results)
