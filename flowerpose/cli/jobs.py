"""The jobs made of stages: `eval` (the benchmark), `fidelity`, `bench`, `results`, and
`cache`, which looks after their stage cache (the studies over settings: `study`)."""

from __future__ import annotations

import argparse
from datetime import datetime
from pathlib import Path

from flowerpose.cli.options import (
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
from flowerpose.config import DEFAULT_PRESET, preset_names, profile_names, suite_names
from flowerpose.errors import InputError
from flowerpose.eval.jobs.eval_run import DEFAULT_PLANTS, DEFAULT_SOURCE, TASKS, EvalRun
from flowerpose.eval.jobs.plant_set import SOURCES, PlantSet

#: eval's source, preset, first seed and task when neither the command line nor a suite
#: says (the run's from `EvalRun`).
EVAL_DEFAULTS = {"source": DEFAULT_SOURCE, "preset": DEFAULT_PRESET, "seed": 0,
                 "task": EvalRun.task}
#: What a report's config (and so its config.toml) records of the run beside the settings,
#: which `eval --config` takes as the run's own where the command line does not say.
EVAL_RUN_KEYS = ("source", "preset", "folders", "plants", "seed", "task")


def _default_out() -> Path:
    return Path("runs") / datetime.now().strftime("%Y%m%d-%H%M%S")


def cmd_eval(args: argparse.Namespace) -> int:
    from flowerpose.eval.jobs.config import eval_config
    from flowerpose.eval.studies.eval_recipe import run_eval

    suite = _apply_suite(args) if args.suite else None
    _run_from_config(args)
    for key, default in EVAL_DEFAULTS.items():
        if getattr(args, key) is None:
            setattr(args, key, default)
    if args.folders and args.source != "real":
        raise InputError(args.folders[0], "plant folders are for --source real")
    if args.truth_scale is not None and args.source != "real":
        raise InputError("--truth-scale", "is for --source real")
    from flowerpose.eval.reports.gates import parse_requirements
    from flowerpose.eval.scoring.methods import ExternalMethod, parse_compare, parse_method

    requirements = parse_requirements(args.require, args.task)  # a bad gate: said first
    if (args.junit or args.summary) and not requirements:
        raise InputError("--junit" if args.junit else "--summary", "needs --require")
    for path, flag in ((args.junit, "--junit"), (args.summary, "--summary")):
        if path is not None:
            check_writable(path, flag)
    config = configure(eval_config(args.preset), args, run_keys=EVAL_RUN_KEYS)
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
    from flowerpose.eval.pool import Execution
    from flowerpose.eval.reports.report import assets_record
    from flowerpose.eval.studies.eval_recipe import eval_outputs

    run = EvalRun(eval_plants(args, config.sim.plant.name), task=args.task, compare=compare,
                  methods=tuple(methods), suite=suite,
                  assets=assets_record(None if args.source == "real" else args.preset,
                                       args.profile))
    writes = eval_outputs(args.source, args.folders, [*compare, *(m.name for m in methods)])
    with owned(out, "eval", args.overwrite, writes) as output, jobs_on(args):
        report = run_eval(config, run, out, Execution(args.workers, cache))
        # All of it is this run's, so a rerun into the folder replaces all of it (plants this
        # run made that the next does not make go too).
        output.record(*(out / name for name in writes if (out / name).exists()))
    if cache is not None and args.source != "real":
        from flowerpose.cache import prune_to_limit

        prune_to_limit(cache)
    import time

    from flowerpose.eval.reports.report import comparison_table, summary_lines, table

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
        from flowerpose.eval.reports.report import pollination_lines

        for line in pollination_lines(report):
            print(line)
    print(f"report: {out / 'report.json'}, {out / 'report.md'}, {out / 'report.html'}")
    return _gates(report, requirements, args) if requirements else 0


def eval_plants(args: argparse.Namespace, preset: str) -> PlantSet:
    """The plants a run of eval, stress or sweep names: the --source's seeded plants of
    `preset` (the config's `sim.plant.name`; --plants, else eval's `DEFAULT_PLANTS`;
    --seed), or the real folders."""
    if args.source == "real":
        return PlantSet("real", folders=tuple(args.folders),
                        truth_scale=getattr(args, "truth_scale", None))
    return PlantSet(args.source, preset,
                    DEFAULT_PLANTS[args.source] if args.plants is None else args.plants,
                    args.seed)


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
        if key in ("source", "task", "preset"):
            choices = {"source": SOURCES, "task": TASKS, "preset": preset_names()}[key]
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
    from flowerpose.eval.reports.gates import check, outcome_table, write_junit, write_summary

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
        "  flowerpose eval --source real paper-plant-3 --compare upstream\n"
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
                   help="number of seeded plants (default: "
                   + ", ".join(f"{n} for {source}" for source, n in DEFAULT_PLANTS.items())
                   + ")")
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


def cmd_fidelity(args: argparse.Namespace) -> int:
    from flowerpose.eval.jobs.config import EvalConfig
    from flowerpose.eval.studies.fidelity import FIDELITY_FILES, outcome_lines, run_fidelity, table

    config = configure(EvalConfig(), args)
    real = PlantSet("real", folders=(args.real,), truth_scale=args.truth_scale)
    with owned(args.out, "fidelity", args.overwrite, FIDELITY_FILES):
        report = run_fidelity(config, real, args.synthetic, args.out)
    print(table(report))
    for line in outcome_lines(report["outcomes"]):
        print(f"predicted at the real density: {line}")
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
        "within a stated tolerance; then say whether the synthetic plants' recall and plane "
        "error, at the real plant's density (denser clouds thinned to it), fall inside the "
        "real plant's 95 % intervals. Writes fidelity.json, fidelity.md and fidelity.png.",
        epilog="example:\n"
        "  flowerpose fidelity paper-plant-3 runs/oracle --out fidelity")
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
    from flowerpose.cache import (
        StageCache,
        default_cache_dir,
        gigabytes_to_bytes,
        max_cache_bytes,
    )
    from flowerpose.eval.reports.report import markdown_table

    root = args.cache or default_cache_dir()
    if root.exists() and not root.is_dir():
        raise InputError(root, "is a file, not a cache folder")
    cache = StageCache(root)
    limit = 0 if args.clear else args.max_size
    if limit is not None:
        removed = cache.prune(gigabytes_to_bytes(limit))
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
    print(markdown_table(["stage", "entries", "size", "last used"], rows))
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
    from flowerpose.eval.pool import Execution
    from flowerpose.eval.studies.bench import BenchPlan, run_bench
    from flowerpose.pipeline.flowers import PipelineConfig

    if args.photos is not None:
        return _bench_photos(args)

    run_bench(configure(PipelineConfig(), args), BenchPlan(tuple(args.points), args.repeat),
              PlantSet("oracle", DEFAULT_PRESET, 1, args.seed), args.out,
              Execution(cache=stage_cache(args)))
    return 0


def _bench_photos(args: argparse.Namespace) -> int:
    from flowerpose.errors import InputError
    from flowerpose.eval.studies.photo_bench import run_photo_bench
    from flowerpose.pipeline.scan_stages import ScanStagesConfig

    if args.out is None:
        raise InputError(args.photos, "--photos needs --out DIR (the three reconstructions "
                         "are written there)")
    config = configure(ScanStagesConfig(), args, reads=("scan.reconstruct",),
                       command="bench --photos").scan.reconstruct
    run_photo_bench(args.photos, args.out, args.max_size, config, args.overwrite)
    return 0


def add_bench(sub: argparse._SubParsersAction) -> None:
    """The `bench` subcommand's parser."""
    p = sub.add_parser(
        "bench", help="time the pipeline from cloud to flower poses",
        description="Time the pipeline from cloud to flower poses on one seeded plant's "
        "oracle cloud at each --points size: wall seconds per stage, the median of --repeat "
        "runs, imports and file reading excluded.",
        epilog="examples:\n  flowerpose bench --points 125000 --repeat 3\n"
        "  flowerpose bench --photos ~/.cache/flowerpose-data/romi-arabidopsis --out bench-photos")
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
    p.add_argument("--photos", type=Path, metavar="SET_DIR",
                   help="instead: time real photographs to a cloud, a set laid out as "
                   "flowerpose data fetch romi-arabidopsis makes it, three ways (its calibrated "
                   "model, its rough poses, the images alone), each checked against the "
                   "calibrated cameras; writes photo_bench.json and the runs to --out")
    p.add_argument("--max-size", type=POSITIVE, metavar="PX",
                   help="--photos: downscale the photos to this longest side (default: full "
                   "size)")
    p.add_argument("--overwrite", action="store_true",
                   help="--photos: replace an earlier photo bench's runs in --out")
    add_cache_options(p)
    add_config_options(p, detector=False)
    p.set_defaults(func=cmd_bench)


def cmd_results(args: argparse.Namespace) -> int:
    from flowerpose.eval.studies.results import results_markdown

    print(results_markdown(args.reports, args.title, not args.no_paper, args.figure), end="")
    return 0


def add_results(sub: argparse._SubParsersAction) -> None:
    """The `results` subcommand's parser."""
    p = sub.add_parser(
        "results", help="a results page (Markdown) made from runs' reports",
        description="Print a Markdown results page made from runs' own files: a table row "
        "per eval report.json (what ran, flowers found of the visible, false positives, the "
        "fits' errors, with their 95 % intervals) beside the paper's own numbers, then a "
        "robustness section per stress.json, a speed section per bench.json, a real-photos "
        "section per photo_bench.json and a sim-to-real section per fidelity.json, each "
        "run's command, code version, date and "
        "machine under its table.",
        epilog="example:\n  flowerpose results runs/oracle-10/report.json "
        "runs/stress3/stress.json runs/bench/bench.json > results.md")
    p.add_argument("reports", type=Path, nargs="+", metavar="REPORT.json",
                   help="eval report.json, stress.json or bench.json files, in the page's "
                   "order")
    p.add_argument("--title", default="Results", help="the page's title (default: %(default)s)")
    p.add_argument("--no-paper", action="store_true",
                   help="leave out the paper's own row (default: include it)")
    p.add_argument("--figure", type=Path, metavar="FILE.png",
                   help="also draw the runs' plane accuracy curves into this PNG, which the "
                   "page shows by its file name (so it lies beside the page) (default: no "
                   "figure)")
    p.set_defaults(func=cmd_results)
