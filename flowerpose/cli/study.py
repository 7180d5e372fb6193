"""The studies over settings and perturbations: `sweep` (a grid of settings), `stress`
(plants under seeded perturbations), `tune` (an Optuna search scored on plants it
never sees) and `guard` (the battery every pipeline change is checked on)."""

from __future__ import annotations

import argparse
import functools
from pathlib import Path

from flowerpose.cli.jobs import EVAL_RUN_KEYS, eval_plants
from flowerpose.cli.options import (
    PLANTS,
    POSITIVE,
    SEED,
    add_cache_options,
    add_config_options,
    add_output,
    add_preset,
    add_ray_option,
    add_workers,
    check_writable,
    configure,
    jobs_on,
    owned,
    positive_number,
    setting_layers,
    stage_cache,
)
from flowerpose.config import DEFAULT_PRESET
from flowerpose.errors import InputError
from flowerpose.eval.jobs.eval_run import TASKS, EvalRun
from flowerpose.eval.jobs.plant_set import SOURCES, SYNTHETIC_SOURCES, PlantSet


def cmd_sweep(args: argparse.Namespace) -> int:
    from flowerpose.eval.jobs.config import eval_config
    from flowerpose.eval.pool import Execution
    from flowerpose.eval.studies.sweep import parse_grid, run_sweep, sweep_outputs

    if args.folders and args.source != "real":
        raise InputError(args.folders[0], "plant folders are for --source real")
    config = configure(eval_config(args.preset), args, run_keys=EVAL_RUN_KEYS)
    if args.source != "real":
        from flowerpose.eval.studies.fresh_seeds import refuse_fresh

        refuse_fresh(args.seed, args.plants)
    grid = parse_grid(args.grid, config)
    cache = stage_cache(args)
    writes = sweep_outputs(grid, args.source, args.folders)
    run = EvalRun(eval_plants(args, config.sim.plant.name), task=args.task)
    with owned(args.out, "sweep", args.overwrite, writes), jobs_on(args):
        best = run_sweep(config, grid, run, args.out, Execution(args.workers, cache))
    if cache is not None:
        from flowerpose.cache import prune_to_limit

        prune_to_limit(cache)
    metrics = best["metrics"]
    measured = (f"pollinated {metrics['pollinated']}, from the true poses "
                f"{metrics['pollinated_ceiling']}" if args.task == "pollinate" else
                f"recall_visible {metrics['recall_visible']}, fp_rate {metrics['fp_rate']}, "
                f"plane {metrics['plane_mean_deg']}°")
    print("best: " + ", ".join(f"{k}={v}" for k, v in best["setting"].items())
          + f" ({measured}; its settings in {args.out / 'best.json'})"
          + ("" if best["vs_defaults"]["distinguishable"] else
             "; not distinguishable from the defaults on these plants"
             if best["vs_defaults"]["paired"] else
             "; not compared with the defaults flower by flower: the grid changes the plants"))
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
        "  flowerpose sweep --source real paper-plant-3 --grid "
        "cluster.eps=0.008,0.01 --out sweep-real\n"
        "  flowerpose sweep --task pollinate --preset field --plants 10 --grid "
        "pollinate.tool.reach_m=0.12,0.16 --set pollinate.look.views=0 --out sweep-tool")
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
    p.add_argument("--task", choices=TASKS, default="pose",
                   help="pose: rank the settings by the flowers found and their poses; "
                   "pollinate: also visit each setting's flowers as eval --task pollinate "
                   "does, and rank by the share pollinated (a study of the pollinator's "
                   "geometry or the planner's settings) (default: %(default)s)")
    add_preset(p)
    add_workers(p)
    add_output(p, "folder for sweep.csv, sweep.png and best.json")
    add_cache_options(p)
    add_ray_option(p)
    add_config_options(p)
    p.set_defaults(func=cmd_sweep)


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
    from flowerpose.eval.jobs.config import eval_config
    from flowerpose.eval.pool import Execution
    from flowerpose.eval.scoring.methods import ExternalMethod, parse_compare
    from flowerpose.eval.studies.stress import DEFAULT_LEVELS, STRESS_FILES, plan_from, run_stress

    if args.folders and args.source != "real":
        raise InputError(args.folders[0], "plant folders are for --source real")
    config = configure(eval_config(args.preset), args, run_keys=EVAL_RUN_KEYS)
    levels = {kind: getattr(args, kind) if getattr(args, kind) is not None
              else list(DEFAULT_LEVELS[kind]) for kind in DEFAULT_LEVELS}
    if args.source == "real":
        views = min(len(p.clouds) if p.stage == "candidates" else config.grid.views
                    for p in PlantSet("real", folders=tuple(args.folders),
                                      truth_scale=args.truth_scale).real_plants()
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
    compare = {name: what for name, what in (parse_compare(text, config)
                                             for text in args.compare)}
    for name, what in compare.items():
        if isinstance(what, ExternalMethod):
            raise InputError("--compare", f"{name}: stress compares settings (a profile or a "
                             "detector), not an external command")
    plan = plan_from(levels, args.channels, drop, capture, args.repeats, args.stress_seed,
                     compare)
    cache = stage_cache(args)
    with owned(args.out, "stress", args.overwrite, (*STRESS_FILES, *compare)), jobs_on(args):
        report = run_stress(config, plan, eval_plants(args, config.sim.plant.name), args.out,
                            Execution(args.workers, cache))
    if cache is not None and args.source != "real":
        from flowerpose.cache import prune_to_limit

        prune_to_limit(cache)
    from flowerpose.eval.studies.stress import compare_tables, stress_table

    print(stress_table(report))
    for name, table in compare_tables(report):
        print(f"\nagainst {name}, on the same perturbed clouds:\n{table}")
    print(f"stress: {args.out / 'stress.json'}, {args.out / 'stress.md'}, "
          f"{args.out / 'stress.png'}, {args.out / 'report.html'}")
    return 0


def add_stress(sub: argparse._SubParsersAction) -> None:
    """The `stress` subcommand's parser."""
    from flowerpose.eval.studies.stress import DEFAULT_LEVELS

    def levels(kind: str) -> str:
        return ",".join(f"{v:g}" for v in DEFAULT_LEVELS[kind])

    p = sub.add_parser(
        "stress", help="the robustness report: the pipeline over perturbed clouds",
        description="Run the pipeline on each plant as it is and under seeded perturbations "
        "of its cloud (thinned, darker or brighter, a colour cast, position noise, a view "
        "left out, each flower partly cut away; for --source scan also fewer frames and a "
        "lower resolution), scored "
        "against the same truth. Writes stress.json, stress.md, stress.png (a panel per "
        "perturbation: recall and plane error against its strength) and report.html.",
        epilog="examples:\n"
        "  flowerpose stress --source oracle --plants 3 --out stress-oracle\n"
        "  flowerpose stress --source real paper-plant-3 --repeats 3 "
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
    p.add_argument("--cut", type=_numbers("shares"), metavar="S,...",
                   help="each flower partly seen: the share of its disc removed beyond a "
                   "seeded plane across it, 0-1, needing the flowers' truth (default: "
                   f"{levels('cut')})")
    p.add_argument("--drop-views", default="all", metavar="N|all",
                   choices=["all", *(str(k) for k in range(27))],
                   help="leave out each of the first N views in turn (a real plant's "
                   "candidates files, else grid views); 0: none (default: %(default)s)")
    p.add_argument("--frames", type=_texts, metavar="N,...",
                   help="--source scan: frames chosen for photogrammetry (default: none)")
    p.add_argument("--resolution", type=_texts, metavar="WxH,...",
                   help="--source scan: camera resolutions, pixels (default: none)")
    p.add_argument("--compare", action="append", default=[], metavar="PROFILE",
                   help="other settings run on the very same perturbed clouds and compared "
                   "flower by flower at every level: a profile (upstream: the published "
                   "method) or a detector, as for eval; repeatable (default: none)")
    p.add_argument("--repeats", type=POSITIVE, default=1, metavar="N",
                   help="seeded repeats of each random perturbation (thinning, noise, cut) "
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
    from flowerpose.config import apply_overrides
    from flowerpose.eval.jobs.config import eval_config
    from flowerpose.eval.jobs.plant_set import PlantSet, parse_sets
    from flowerpose.eval.studies.fresh_seeds import refuse_fresh
    from flowerpose.eval.studies.tune import (
        DEFAULTS_FLIPPED,
        TUNE_FILES,
        TuneSpec,
        check_storage,
        clear_dead_trials,
        local_storage,
        open_study,
        report_study,
        run_trials,
        score_defaults,
        study_name,
        validation_default,
    )
    from flowerpose.eval.studies.tune_space import parse_objectives, read_space
    from flowerpose.eval.studies.tune_task import TASKS as TUNE_TASKS
    from flowerpose.stopwatch import Stopwatch

    preset_config = eval_config(args.preset or DEFAULT_PRESET)
    overrides = setting_layers(preset_config, args)
    base = functools.reduce(apply_overrides, overrides, preset_config)
    space = tuple(read_space(args.space, base))
    task = TUNE_TASKS[args.task]
    objectives = tuple(parse_objectives(args.objective, task.name))
    train = parse_sets(args.train) if args.train else [
        PlantSet(args.source, args.preset or DEFAULT_PRESET, args.plants, args.seed)]
    validate = parse_sets(args.validate) if args.validate else validation_default(train)
    for plant_set in (*train, *validate):
        EvalRun(plant_set, task=task.name)  # refuses a real set for the pollination task
        if not plant_set.real:
            refuse_fresh(plant_set.seed, plant_set.plants, "--train/--validate/--seed")
    storage = args.study or f"sqlite:///{(args.out / 'study.db').resolve()}"
    if args.study:
        check_storage(storage)  # the default's folder is made below
    if args.ray not in (None, "local", "auto") and local_storage(storage) and not any(
            host in args.ray for host in ("127.0.0.1", "localhost")):
        raise InputError("--study", f"{storage} is on this machine's disk, which a remote "
                         "Ray cluster does not reach: give a storage it reaches (an RDB URL, "
                         "e.g. postgresql://..., or journal:///PATH on a shared file system)")
    default_name, identity = study_name(space, tuple(train), objectives, task)
    cache = stage_cache(args)
    spec = TuneSpec(space, tuple(train), tuple(validate), objectives, overrides, storage,
                    args.study_name or default_name, args.sampler_seed, args.out, cache,
                    task)
    watch = Stopwatch()
    with owned(args.out, "tune", args.overwrite, TUNE_FILES), jobs_on(args):
        args.out.mkdir(parents=True, exist_ok=True)
        study = open_study(spec, identity, create=True)
        from flowerpose.log import LOG

        # The default storage lives in the locked --out: no other process runs its trials.
        dead = clear_dead_trials(study, args.out, owned=args.study is None)
        if dead:
            LOG.warning(f"tune: {dead} trial(s) left running by a process that stopped are "
                        "marked failed")

        LOG.info(f"tune: study {spec.study_name}: scoring the settings without a trial's on "
                 f"{len(train)} training and {len(validate)} validation sets")
        timer = Stopwatch()
        defaults = score_defaults(spec)
        study.set_user_attr(DEFAULTS_FLIPPED, (defaults["train"] or {}).get("flipped_flowers", []))
        each = timer.elapsed()
        workers = 1 if args.ray is not None else (args.workers or 1)
        LOG.info(f"tune: one trial takes about {each:.0f} s here: {args.trials} trials, about "
                 f"{each * args.trials / workers / 60:.1f} min on {workers} worker(s)")
        try:
            if args.ray is None and workers == 1:
                run_trials(spec, args.trials)
            else:
                from flowerpose.eval.pool import run_jobs

                tasks = args.trials if args.ray is not None else min(workers, args.trials)
                shares = [args.trials // tasks + (k < args.trials % tasks) for k in range(tasks)]
                run_jobs(run_trials, [(spec, n, k) for k, n in enumerate(shares)], workers,
                         stage="tune", labels=[f"worker {k}" for k in range(tasks)])
        finally:
            report = report_study(spec, defaults, watch.elapsed())
    from flowerpose.eval.studies.tune import tune_markdown

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
        "  flowerpose tune --space examples/tuning/space.toml --trials 40 --out tune --plants 3\n"
        "  flowerpose tune --space examples/tuning/space.toml --trials 100 --train oracle-10 "
        "--train field-10 --validate paper-plant-3 --workers 2 --out tune-field\n"
        "  flowerpose tune --task pollinate --space examples/tuning/tool.toml --trials 20 "
        "--preset field --plants 5 --out tune-tool")
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
    add_preset(p, None, DEFAULT_PRESET)
    p.add_argument("--study", metavar="STORAGE",
                   help="the Optuna storage: an RDB URL (sqlite:///FILE, postgresql://...) or "
                   "journal:///FILE (default: sqlite:///DIR/study.db)")
    p.add_argument("--study-name", metavar="NAME",
                   help="the study's name (default: made from the task, the space, the "
                   "training plants, the objectives and the code version)")
    p.add_argument("--task", choices=TASKS, default="pose",
                   help="pose: score each trial by the flowers found and their poses; "
                   "pollinate: also visit each plant's flowers as eval --task pollinate "
                   "does (synthetic plants only; a study of the pollinator's geometry or the "
                   "planner's settings) (default: %(default)s)")
    p.add_argument("--objective", action="append", default=[], metavar="max:KEY|min:KEY",
                   help="an objective over the report summary's keys (repeatable; default: "
                   "max:f1 and min:error_deg.plane.mean; with --task pollinate "
                   "max:pollination.success_rate and min:pollination.collision_share)")
    p.add_argument("--sampler-seed", type=SEED, default=None, metavar="N",
                   help="seed of the sampler: the same trials again, with one worker "
                   "(default: none)")
    p.add_argument("--workers", type=POSITIVE, default=None, metavar="N",
                   help="trials at once, each in a process of its own (default: 1)")
    add_cache_options(p)
    add_ray_option(p)
    add_config_options(p)
    p.set_defaults(func=cmd_tune)


def cmd_guard(args: argparse.Namespace) -> int:
    from flowerpose.eval.jobs.config import eval_config
    from flowerpose.eval.reports.report import markdown_table
    from flowerpose.eval.studies.guard import (
        ACCEPTED,
        GUARD_FILES,
        GuardRun,
        load_battery,
        real_folder,
        run_guard,
    )
    from flowerpose.eval.studies.guard_report import guard_rows
    from flowerpose.log import LOG

    if args.accept_loss is not None and not args.accept:
        raise InputError("--accept-loss", "records a loss when accepting: give --accept too")
    battery = load_battery(args.battery)
    entries = battery.select(args.only, args.quick)
    for entry in entries:
        if entry.real:
            real_folder(entry, args.real)
    overrides = setting_layers(eval_config(DEFAULT_PRESET), args)
    accepted = args.accepted or Path(str(ACCEPTED))
    if args.accepted is not None and not args.accepted.is_file() and not args.accept:
        if args.base is None:
            raise InputError(args.accepted, "no such accepted file (--accepted), so no base "
                             "to compare with: give --base REV (the first --accept makes "
                             "the file)")
        LOG.warning(f"guard: no accepted decisions at {args.accepted}: no drift reported")
    if args.accept:
        check_writable(accepted, "--accepted")
    setting_arguments = [*(["--profile", args.profile] if args.profile else []),
                         *(["--config", str(args.config.resolve())] if args.config else []),
                         *(item for text in args.set for item in ("--set", text))]
    run = GuardRun(entries, tuple(args.real), accepted, args.base, args.seed,
                   tuple(setting_arguments), overrides, args.workers, stage_cache(args),
                   args.trend, args.accept, args.accept_loss)
    with owned(args.out, "guard", args.overwrite,
               (*GUARD_FILES, *(e.name for e in entries))):
        report = run_guard(battery, run, args.out)
    print(markdown_table(*guard_rows(report)))
    for name, row in report["entries"].items():
        for reason in row["reasons"]:
            print(f"{name}: {reason}")
    failed = [name for name, row in report["entries"].items() if row["verdict"] == "fail"]
    print(f"guard: {'failed on ' + ', '.join(failed) if failed else 'passed'}; run seed "
          f"{report['run_seed']}; {args.out / 'guard.json'}, {args.out / 'guard.md'}"
          + (f"; recorded in {accepted}" if args.accept else ""))
    return 1 if failed and not args.accept else 0


def add_guard(sub: argparse._SubParsersAction) -> None:
    """The `guard` subcommand's parser."""
    p = sub.add_parser(
        "guard", help="a change against its base on fresh plants, within stated margins",
        description="Run the guard battery's entries (the full simulated loop, the oracle, "
        "the field and hard presets, pollination visits, and a real plant as it is, "
        "thinned and cut) on plants drawn afresh for this run from seeds nothing else "
        "uses, twice: with the base revision's code and with the working tree's. Each "
        "entry is judged flower by flower: it fails where a measure is not shown within its "
        "margin (the plane error's mean, the recall of visible flowers, false positives, "
        "the share pollinated) or where the change flips a normal, sends a flower over "
        "20 degrees or collides where the base did not. Settings given (--set, --config, "
        "--profile) apply over the working tree's side: a change of settings is guarded as "
        "a change of code is. Prints one table, writes guard.json and guard.md and each "
        "entry's runs; exit status 1 where an entry failed.",
        epilog="examples:\n"
        "  flowerpose guard --quick --real paper-plant-3 --out guard\n"
        "  flowerpose guard --real paper-plant-3 --base main --out guard\n"
        "  flowerpose guard --only oracle-20 --seed 1234 --out guard\n"
        "  flowerpose guard --set cluster.eps=0.009 --real paper-plant-3 --out guard-eps\n"
        "  flowerpose guard --real paper-plant-3 --trend --accept --out guard")
    p.add_argument("--real", type=Path, nargs="+", default=[], metavar="DIR",
                   help="the real plant folders the battery's real entries name, found by "
                   "their folder's name (default: none)")
    p.add_argument("--only", action="append", default=[], metavar="ENTRY",
                   help="run this entry only; repeatable (default: every entry)")
    p.add_argument("--quick", action="store_true",
                   help="the quick entries only (CI's: the oracle, field and hard presets and "
                   "the real plant as it is and thinned) (default: every entry)")
    p.add_argument("--base", metavar="REV",
                   help="the git revision to compare with (default: the commit of each "
                   "entry's newest accepted record)")
    p.add_argument("--seed", type=SEED, default=None, metavar="N",
                   help="the run seed the plants are drawn from: the same plants again "
                   "(default: drawn, and printed)")
    p.add_argument("--trend", action="store_true",
                   help="also run the working tree on the battery's fixed seeds: a trend "
                   "record beside the verdict, never part of it (default: no)")
    p.add_argument("--battery", type=Path, metavar="FILE",
                   help="another battery file (default: the shipped "
                   "assets/guard/battery.toml)")
    p.add_argument("--accepted", type=Path, metavar="FILE",
                   help="the accepted decisions (default: the shipped "
                   "assets/guard/accepted.json)")
    p.add_argument("--accept", action="store_true",
                   help="append this run's records to the accepted decisions: the base "
                   "of the next run; refused for a failed run without --accept-loss and for "
                   "uncommitted changes (default: compare only)")
    p.add_argument("--accept-loss", metavar="REASON",
                   help="with --accept: accept a failed run's loss as a decision, recorded "
                   "with this reason")
    add_workers(p)
    add_output(p, "folder for guard.json, guard.md and each entry's runs")
    add_cache_options(p)
    add_config_options(p, detector=False)
    p.set_defaults(func=cmd_guard)
