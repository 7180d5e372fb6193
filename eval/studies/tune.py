"""`flowerpose tune`: settings searched with Optuna on training plants, proven on validation
plants the search never sees.

Each trial draws the settings of the space (`tune_space.py`) from Optuna's sampler (TPE,
seeded by `--sampler-seed`), scores them on every training plant and every validation
plant (`plants.py`), and returns the training objectives; the validation scores are
recorded beside them, never shown to the sampler. With one objective each training plant
reports the objective so far and a median pruner stops hopeless trials; with several the
study keeps their Pareto front. The study lives in an Optuna storage, so a rerun adds
trials to it and `optuna-dashboard STORAGE` shows it.

The chosen trial is picked by validation, not training: among the training front (the
Pareto front; with one objective the best CHOSEN_FROM trials) the highest validation F1,
ties broken by the lower validation plane error. Without validation plants it is the
training front's first, and the report says plainly that nothing was validated.

With `--task pollinate` every plant's flowers are also visited and judged as `eval --task
pollinate` does; the objectives by default are then the share pollinated and the share of
visits that collided, and the choice goes by their validation bounds (`tune_task.py`).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from flowerpose.atomic import write_text
from flowerpose.config import (
    DEFAULT_PRESET,
    settings_toml,
)
from flowerpose.errors import InputError
from flowerpose.eval.jobs.config import EvalConfig, eval_config
from flowerpose.eval.jobs.plant_set import PlantSet
from flowerpose.eval.jobs.plants import Plants, world_digest
from flowerpose.eval.reports.report import markdown_table, run_record, run_summary
from flowerpose.eval.scoring.paired import flower_errors
from flowerpose.eval.scoring.stats import FLIP_DEG, GROSS_DEG
from flowerpose.eval.studies.tune_space import Objective, Param, typed_settings
from flowerpose.eval.studies.tune_task import POSE, TASKS, TuneTask
from flowerpose.jsonio import write_json
from flowerpose.log import LOG
from flowerpose.outputs import check_folder_writable
from flowerpose.stopwatch import Stopwatch

#: With one objective, the chosen trial is the best validated among this many best trials.
CHOSEN_FROM = 5
#: What tune writes into its --out folder (the study's database too, when it is there).
TUNE_FILES = ("tune.json", "tune.md", "tune.html", "best.toml", "study.db", "plants",
              "trials")


@dataclass(frozen=True)
class TuneSpec:
    """Everything a trial needs, picklable for worker processes and Ray tasks."""

    space: tuple[Param, ...]
    train: tuple[PlantSet, ...]
    validate: tuple[PlantSet, ...]
    objectives: tuple[Objective, ...]
    overrides: tuple[dict, ...]
    """The user's settings (--profile, --config, --set), applied in order under a trial's."""
    storage: str
    study_name: str
    sampler_seed: int | None
    out_dir: Path
    cache: Path | None
    task: TuneTask = POSE
    """What a trial is scored on: the pose task, or the pollination task too (each plant's
    flowers visited as `eval --task pollinate` does)."""

    def layers(self, settings: dict) -> tuple[dict, ...]:
        """The user's settings and then a trial's (`settings`), in the order they apply."""
        return (*self.overrides, settings)


class SetScorer:
    """Scores settings on plant sets: each set's config is its preset's (a real set's: the
    defaults') with the settings' layers over it; captures are made once per world
    (`plants.Plants`) and detections come from the stage cache where the same cloud was
    detected with the same settings. With the pollination task each synthetic plant's
    flowers are then visited and judged (`pollination_task.pollinate_plants`)."""

    def __init__(self, out_dir: Path, cache: Path | None, workers: int | None = 1,
                 task: TuneTask = POSE):
        self.out_dir, self.cache, self.task = out_dir, cache, task
        self.plants = Plants(workers, cache)

    def config(self, plant_set: PlantSet, layers: tuple[dict, ...]) -> EvalConfig:
        return eval_config(DEFAULT_PRESET if plant_set.real else plant_set.preset, layers)

    def score(self, plant_set: PlantSet, layers: tuple[dict, ...], out_dir: Path
              ) -> Iterator[dict]:
        """Report.json plant entries of the settings on every plant of the set, one plant
        at a time (each scored, and visited, into out_dir/NAME/)."""
        config = self.config(plant_set, layers)
        world = (f"{plant_set.source}-{plant_set.preset}-"
                 f"{world_digest(config, plant_set.source)}")
        for job in self.plants.jobs(plant_set, config, self.out_dir / "plants" / world).jobs:
            entry = job.score(config, out_dir / job.name, self.cache)[0]
            if self.task.name == "pollinate":  # the plant's files where its truth is
                from flowerpose.eval.jobs.pollination_task import pollinate_plants

                pollinate_plants([job], [entry], config, out_dir / job.name, 1,
                                 [(job.truth.parent, out_dir / job.name)])
            yield entry


def study_name(spec_space: tuple[Param, ...], train: tuple[PlantSet, ...],
               objectives: tuple[Objective, ...], task: TuneTask = POSE) -> tuple[str, dict]:
    """The default study name and what it is made of: the task, the space, the training
    plants, the objectives and the code version (a study of another code is another
    study)."""
    from flowerpose.cache import code_version

    identity = {"task": task.name, "space": {p.key: p.to_json() for p in spec_space},
                "train": [{"label": s.label, **s.describe()} for s in train],
                "objectives": [o.text for o in objectives], "code": code_version()}
    digest = hashlib.sha256(json.dumps(identity, sort_keys=True).encode()).hexdigest()[:10]
    return f"flowerpose-tune-{digest}", identity


#: Seconds between a running trial's heartbeats in an RDB storage; a trial silent for
#: STALE_AFTER_S (its process killed) is marked failed when the study is next opened.
HEARTBEAT_S = 10
STALE_AFTER_S = 30
#: Storage URL schemes on this machine's disk (file paths after "///").
_FILE_SCHEMES = ("sqlite:///", "journal:///")


def check_storage(url: str) -> None:
    """Refuse, before any trial, a storage URL that cannot work: no scheme, or a file
    storage whose folder is missing or takes no file; one line naming the URL."""
    if "://" not in url:
        raise InputError("--study", f"{url!r} is not a storage URL: give sqlite:///PATH, "
                         "journal:///PATH or an RDB URL such as postgresql://HOST/DB")
    for scheme in _FILE_SCHEMES:
        if url.startswith(scheme):
            path = Path(url.removeprefix(scheme.rstrip("/")))
            if not path.parent.is_dir():
                raise InputError("--study", f"{url}: the folder {path.parent} is not there; "
                                 "make it first or give another path")
            check_folder_writable(path.parent)
            if path.exists() and not os.access(path, os.W_OK):
                raise InputError("--study", f"{url}: {path} is read-only")


def _storage(url: str) -> Any:
    """The Optuna storage of a URL: an RDB (sqlite waits for a lock instead of failing; a
    heartbeat marks trials of killed processes failed), or a journal file (journal:///PATH,
    no heartbeat). A storage that cannot be opened is one line naming the URL."""
    import optuna

    check_storage(url)
    if url.startswith("journal:///"):
        from optuna.storages.journal import JournalFileBackend

        return optuna.storages.JournalStorage(JournalFileBackend(url.removeprefix("journal://")))
    kwargs = {"connect_args": {"timeout": 60}} if url.startswith("sqlite") else {}
    try:
        return optuna.storages.RDBStorage(url, engine_kwargs=kwargs,
                                          heartbeat_interval=HEARTBEAT_S,
                                          grace_period=STALE_AFTER_S)
    except Exception as error:  # noqa: BLE001 - SQLAlchemy's and the drivers' errors alike
        raise InputError("--study", f"{url}: cannot open the storage: "
                         f"{str(error).splitlines()[0]}") from None


def open_study(spec: TuneSpec, identity: dict, create: bool, worker: int = 0) -> Any:
    """The spec's study: created (or, made by the same space, plants and objectives,
    loaded to add trials to); one of that name made otherwise is refused. `worker`: which
    of the processes adding trials at once opens it; each seeds its sampler apart
    (`--sampler-seed` plus the worker's number), or they would all draw the same
    settings."""
    import optuna

    quiet_optuna()
    sampler = optuna.samplers.TPESampler(
        seed=None if spec.sampler_seed is None else spec.sampler_seed + worker)
    pruner = (optuna.pruners.MedianPruner(n_startup_trials=5, n_warmup_steps=1)
              if len(spec.objectives) == 1 else optuna.pruners.NopPruner())
    storage = _storage(spec.storage)
    if not create:
        return optuna.load_study(study_name=spec.study_name, storage=storage, sampler=sampler,
                                 pruner=pruner)
    study = optuna.create_study(study_name=spec.study_name, storage=storage, sampler=sampler,
                                pruner=pruner, load_if_exists=True,
                                directions=[o.direction for o in spec.objectives])
    made = study.user_attrs.get("identity")
    if made is None:
        study.set_user_attr("identity", identity)
    else:
        mine = {k: v for k, v in identity.items() if k != "code"}
        theirs = {"task": "pose", **{k: v for k, v in made.items() if k != "code"}}
        if mine != theirs:
            differs = ", ".join(k for k in mine if mine[k] != theirs.get(k))
            raise InputError("--study-name", f"{spec.study_name}: that study was made with "
                             f"another {differs}; give another --study-name")
    return study


#: The study's record of the flowers the defaults flip on the training plants: a trial that
#: flips another is infeasible (its constraint `new_flipped` above 0).
DEFAULTS_FLIPPED = "defaults_flipped_train"


def _entries(scorer: SetScorer, sets: tuple[PlantSet, ...], layers: tuple[dict, ...],
             folder: Path, after_each: Any = None) -> list[dict] | None:
    """The plant entries of the settings (`layers`, applied in order) on every plant of the
    sets (None without sets), each plant named by its set; `after_each(entries)` after
    each plant's (the pruner's report)."""
    if not sets:
        return None
    entries: list[dict] = []
    for k, plant_set in enumerate(sets):
        for entry in scorer.score(plant_set, layers, folder / f"set-{k}"):
            entries.append({**entry, "plant": f"{plant_set.label}: {entry['plant']}"})
            if after_each is not None:
                after_each(entries)
    return entries


def _recorded(entries: list[dict] | None, task: TuneTask = POSE) -> dict | None:
    """A trial's recorded scores (the task's `recorded`) over its plant entries."""
    from flowerpose.eval.reports.gates import summary_value

    if entries is None:
        return None
    summary = run_summary(entries)
    recorded = {k: summary_value(summary, k) for k in task.recorded}
    recorded["flipped_flowers"] = sorted(f"{plant}: flower {truth}" for (plant, truth), error
                                         in flower_errors(entries, "plane").items()
                                         if error > FLIP_DEG)
    recorded["over_20"] = sum(e > GROSS_DEG for p in entries for e in p["error_deg"]["plane"])
    recall, precision = recorded["recall_visible_ci95.low"], recorded["precision_ci95.low"]
    recorded["f1_low"] = (None if recall is None or precision is None else 0.0
                          if recall + precision == 0 else
                          round(2 * recall * precision / (recall + precision), 4))
    return recorded


def _objective(spec: TuneSpec, scorer: SetScorer):
    import optuna

    def objective(trial: optuna.Trial) -> tuple[float, ...] | float:
        settings = typed_settings(list(spec.space),
                                  {p.key: p.suggest(trial) for p in spec.space})
        layers = spec.layers(settings)
        folder = Path(tempfile.mkdtemp(prefix=f"trial-{trial.number}-",
                                       dir=spec.out_dir / "trials"))
        try:
            def report(entries: list[dict]) -> None:
                if len(spec.objectives) == 1:
                    trial.report(spec.objectives[0].value(run_summary(entries, False)),
                                 len(entries))
                    if trial.should_prune():
                        raise optuna.TrialPruned()

            try:
                train_entries = _entries(scorer, spec.train, layers, folder / "train",
                                         report)
                train = run_summary(train_entries, False)
            except optuna.TrialPruned:
                raise
            except Exception as err:  # noqa: BLE001 - recorded as the failed trial's reason
                trial.set_user_attr("error", f"{type(err).__name__}: {err}"
                                    if not isinstance(err, InputError) else str(err))
                raise
            recorded = _recorded(train_entries, spec.task)
            trial.set_user_attr("train", recorded)
            added = len(set(recorded["flipped_flowers"])
                        - set(trial.study.user_attrs.get(DEFAULTS_FLIPPED, [])))
            trial.set_user_attr("new_flipped", added)
            # Infeasible to the sampler (a constraint above 0), whatever its objectives.
            trial.set_constraint("new_flipped", added)
            trial.set_user_attr("validate", _recorded(
                _entries(scorer, spec.validate, layers, folder / "validate"), spec.task))
        finally:
            shutil.rmtree(folder, ignore_errors=True)
        values = tuple(o.value(train) for o in spec.objectives)
        return values if len(values) > 1 else values[0]

    return objective


def run_trials(spec: TuneSpec, trials: int, worker: int = 0) -> int:
    """Add `trials` trials to the spec's study here (a worker process, a Ray task or the
    command itself; `worker`, its number among those adding trials at once, seeds its
    sampler apart); a trial that raises is recorded as failed with its reason and the
    study goes on. Returns the trials run."""
    import optuna

    quiet_optuna()
    study = open_study(spec, {}, create=False, worker=worker)
    scorer = SetScorer(spec.out_dir, spec.cache, workers=1, task=spec.task)
    watch = Stopwatch()

    def said(study: optuna.Study, trial: optuna.trial.FrozenTrial) -> None:
        done = trial.number + 1
        what = (trial.user_attrs.get("error") or ("pruned" if trial.state.name == "PRUNED"
                                                  else _values_text(spec, trial)))
        LOG.info(f"trial {trial.number} {trial.state.name.lower()}: {what} "
                 f"({watch.elapsed():.0f} s; study {done} trials)")

    (spec.out_dir / "trials").mkdir(parents=True, exist_ok=True)
    study.optimize(_objective(spec, scorer), n_trials=trials, catch=(Exception,),
                   callbacks=[said])
    return trials


def clear_dead_trials(study: Any, out_dir: Path, owned: bool) -> int:
    """Mark the trials whose process died failed, and remove the scratch folders
    (out_dir/trials/trial-N-*) of every trial not running; returns the trials marked. Run
    before a session's trials start. owned: this command holds the study alone (its own
    storage in its locked out_dir), so every trial still running is a dead process's;
    else those whose heartbeat stopped STALE_AFTER_S ago (an RDB storage)."""
    import optuna

    running_state = optuna.trial.TrialState.RUNNING
    before = {t.number for t in study.get_trials(deepcopy=False, states=(running_state,))}
    if owned:
        for number in before:
            study.tell(number, state=optuna.trial.TrialState.FAIL)
    else:
        optuna.storages.fail_stale_trials(study)
    running = {t.number for t in study.get_trials(deepcopy=False, states=(running_state,))}
    for folder in (out_dir / "trials").glob("trial-*-*"):
        number = folder.name.split("-")[1]
        if number.isdigit() and int(number) not in running:
            shutil.rmtree(folder, ignore_errors=True)
    return len(before - running)


def quiet_optuna() -> None:
    """Optuna's own log lines become the project's debug lines (`-v`): the project says
    what happened to each trial itself."""
    import optuna

    optuna.logging.disable_default_handler()
    optuna.logging.enable_propagation()


def _values_text(spec: TuneSpec, trial: Any) -> str:
    values = trial.values or []
    return ", ".join(f"{o.key} {v:.4g}" for o, v in zip(spec.objectives, values, strict=False))


def score_defaults(spec: TuneSpec) -> dict:
    """The user's settings without a trial's, on training and validation plants: the
    recorded scores, and the validation plant entries (`validate_entries`, for the
    paired comparison with the chosen trial)."""
    scorer = SetScorer(spec.out_dir, spec.cache, workers=None, task=spec.task)
    folder = spec.out_dir / "trials" / "defaults"
    layers = spec.layers({})
    try:
        validate = _entries(scorer, spec.validate, layers, folder / "validate")
        return {"train": _recorded(_entries(scorer, spec.train, layers, folder / "train"),
                                   spec.task),
                "validate": _recorded(validate, spec.task), "validate_entries": validate}
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def chosen_against_defaults(spec: TuneSpec, settings: dict, defaults: dict) -> dict | None:
    """The chosen trial's settings against the defaults on the validation plants, flower by
    flower (`sweep.against_defaults`): whether any difference is shown, and the verdicts;
    None without validation plants."""
    from flowerpose.eval.studies.sweep import against_defaults

    if not defaults.get("validate_entries"):
        return None
    scorer = SetScorer(spec.out_dir, spec.cache, workers=None, task=spec.task)
    folder = spec.out_dir / "trials" / "chosen"
    try:
        chosen = _entries(scorer, spec.validate, spec.layers(settings), folder)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    return against_defaults(chosen, defaults["validate_entries"], settings)


def trial_rows(study: Any, spec: TuneSpec) -> list[dict]:
    """Every trial of the study as tune.json records it."""
    rows = []
    for trial in study.trials:
        rows.append({"number": trial.number, "state": trial.state.name.lower(),
                     "settings": typed_settings(list(spec.space), trial.params),
                     "values": trial.values, "train": trial.user_attrs.get("train"),
                     "validate": trial.user_attrs.get("validate"),
                     "error": trial.user_attrs.get("error") or _failure(trial),
                     "seconds": (trial.duration.total_seconds()
                                 if trial.duration is not None else None)})
    return rows


def _failure(trial: Any) -> str | None:
    reason = trial.system_attrs.get("fail_reason")
    if reason is None and trial.state.name == "FAIL" and "error" not in trial.user_attrs:
        return "its process stopped (killed?) before the trial ended"
    return None if reason is None else str(reason).strip().splitlines()[-1]


def front(study: Any, spec: TuneSpec) -> list[Any]:
    """The training front among the trials that flip no normal the defaults did not: the
    Pareto front (several objectives) or the best CHOSEN_FROM trials (one)."""
    import optuna

    complete = [t for t in study.trials if t.state == optuna.trial.TrialState.COMPLETE
                and not t.user_attrs.get("new_flipped", 0)]
    if not complete:
        return []
    if len(spec.objectives) > 1:
        signs = [1.0 if o.direction == "minimize" else -1.0 for o in spec.objectives]
        costs = [[s * v for s, v in zip(signs, t.values, strict=True)] for t in complete]

        def dominated(k: int) -> bool:
            return any(all(a <= b for a, b in zip(other, costs[k], strict=True))
                       and other != costs[k] for other in costs)
        return [t for k, t in sorted(enumerate(complete), key=lambda kt: kt[1].number)
                if not dominated(k)]
    sign = -1.0 if spec.objectives[0].direction == "maximize" else 1.0
    return sorted(complete, key=lambda t: sign * t.values[0])[:CHOSEN_FROM]


def choose(candidates: list[Any], validated: bool, defaults_flipped: list[str] = (),
           task: TuneTask = POSE) -> Any | None:
    """The chosen trial (the task's `rule`), by the validation scores' 95 % bounds, not
    their point values (or, without validation, the front's first); never one that flips a
    normal on the validation plants that the defaults (`defaults_flipped`) did not."""
    if validated:
        candidates = [t for t in candidates if not set(
            (t.user_attrs.get("validate") or {}).get("flipped_flowers", []))
            - set(defaults_flipped)]
    if not candidates:
        return None
    if not validated:
        return candidates[0]

    return min(candidates, key=lambda trial: task.rank(trial.user_attrs.get("validate") or {}))


def best_toml(settings: dict) -> str:
    """A trial's settings as a --config file: one table per section."""
    return settings_toml(settings, "flowerpose tune: the chosen trial's settings "
                         "(flowerpose eval --config FILE)")


def tune_markdown(report: dict) -> str:
    """tune.md: the front (or top trials) with training and validation scores, the
    defaults' row, the chosen trial and its rule, the gaps and the warnings."""
    task = TASKS[report.get("task", POSE.name)]
    first = task.shown[0]
    header = ["trial", "settings", *(f"train {m.label}" for m in task.shown),
              *(f"validate {m.label}" for m in task.shown), *(m.label for m in task.ranked),
              f"gap {first.label}"]
    rows = []
    defaults = report["defaults"]
    for row in report["front"]:
        gap = ("-" if not row["validate"] or row["validate"].get(first.key) is None
               or row["train"].get(first.key) is None
               else f"{row['train'][first.key] - row['validate'][first.key]:+.3f}")
        chosen = (" (chosen)" if row["number"] == (report.get("chosen") or {}).get("number")
                  else "")
        rows.append([f"{row['number']}{chosen}",
                     ", ".join(f"{k}={_short(v)}" for k, v in row["settings"].items()),
                     *(m.cell(row["train"]) for m in task.shown),
                     *(m.cell(row["validate"]) for m in task.shown),
                     *(m.cell(row["validate"]) for m in task.ranked), gap])
    rows.append(["defaults", "(the settings without a trial's)",
                 *(m.cell(defaults["train"]) for m in task.shown),
                 *(m.cell(defaults["validate"]) for m in task.shown),
                 *(m.cell(defaults["validate"]) for m in task.ranked), "-"])
    counts = report["counts"]
    lines = [f"# flowerpose tune: {report['study']['name']}", "",
             f"`{report['run']['command']}` ({report['run']['date']}); storage "
             f"`{report['study']['storage']}`; {counts['complete']} complete, "
             f"{counts['pruned']} pruned, {counts['failed']} failed trials; objectives "
             f"{', '.join(report['objectives'])}.", "",
             "Training: " + "; ".join(s["label"] for s in report["train"]) + ". Validation: "
             + ("; ".join(s["label"] for s in report["validate"]) if report["validate"]
                else "**none: nothing was validated**, the choice is by training alone") + ".",
             "", markdown_table(header, rows), "", f"Rule: {report['rule']}."]
    against = report.get("chosen_vs_defaults")
    if against is not None:
        lines += ["", "The chosen trial against the defaults on the validation plants, flower "
                  "by flower: " + "; ".join(against["verdicts"]) + "."]
    lines += [f"**Warning:** {w}" for w in report["warnings"]]
    lines += ["", f"Open the study: `optuna-dashboard {report['study']['storage']}`"]
    return "\n".join(lines) + "\n"


def _short(value: Any) -> str:
    return f"{value:.4g}" if isinstance(value, float) else str(value)


def warnings_of(chosen: dict | None, defaults: dict, against: dict | None = None,
                task: TuneTask = POSE) -> list[str]:
    """What the report must say of the chosen trial against the defaults: worse point
    values (the task's `shown`), and, compared flower by flower on the validation plants
    (`against`), that no difference is shown."""
    if chosen is None or not chosen["validate"] or not defaults["validate"]:
        return []
    said = []
    if against is not None and not against["distinguishable"]:
        said.append("the chosen settings are not distinguishable from the defaults on the "
                    "validation plants (" + "; ".join(against["verdicts"]) + ")")
    return said + task.worse(chosen["validate"], defaults["validate"])


def write_html(path: Path, study: Any, spec: TuneSpec, markdown: str) -> Path:
    """tune.html: the study's optimisation history, parameter importances and parallel
    coordinates (and the Pareto front) as self-contained plotly figures."""
    import html

    import optuna
    from plotly.offline import get_plotlyjs

    figures = []
    names = [o.key for o in spec.objectives]
    complete = [t for t in study.trials if t.state == optuna.trial.TrialState.COMPLETE]
    for k, name in enumerate(names):
        target = None if len(names) == 1 else (lambda t, k=k: t.values[k])
        figures.append(optuna.visualization.plot_optimization_history(
            study, target=target, target_name=name))
        if len(complete) >= 2 and spec.space:
            try:
                figures.append(optuna.visualization.plot_param_importances(
                    study, target=target, target_name=name))
            except (RuntimeError, ValueError) as err:  # too few distinct trials to judge
                LOG.debug(f"tune: no parameter importances for {name}: {err}")
        figures.append(optuna.visualization.plot_parallel_coordinate(
            study, target=target, target_name=name))
    if len(names) == 2:
        figures.append(optuna.visualization.plot_pareto_front(study, target_names=names))
    body = "".join(f.to_html(full_html=False, include_plotlyjs=False) for f in figures)
    page = ("<!doctype html><html><head><meta charset='utf-8'><title>flowerpose tune</title>"
            f"<script>{get_plotlyjs()}</script></head><body><h1>flowerpose tune</h1>"
            f"<pre>{html.escape(markdown)}</pre>{body}</body></html>")
    return write_text(path, page)


def report_study(spec: TuneSpec, defaults: dict, seconds: float) -> dict:
    """Write tune.json, tune.md, tune.html and best.toml from the study as it stands."""
    import optuna

    quiet_optuna()
    study = open_study(spec, {}, create=False)
    rows = trial_rows(study, spec)
    candidates = front(study, spec)
    chosen_trial = choose(candidates, bool(spec.validate),
                          (defaults.get("validate") or {}).get("flipped_flowers", []), spec.task)
    by_number = {r["number"]: r for r in rows}
    chosen = None if chosen_trial is None else by_number[chosen_trial.number]
    against = (None if chosen is None or not spec.validate
               else chosen_against_defaults(spec, chosen["settings"], defaults))
    states = [t.state for t in study.trials]
    report = {"run": run_record(), "task": spec.task.name,
              "study": {"name": spec.study_name, "storage": spec.storage},
              "space": {p.key: p.to_json() for p in spec.space},
              "objectives": [o.text for o in spec.objectives],
              "train": [{"label": s.label, **s.describe()} for s in spec.train],
              "validate": [{"label": s.label, **s.describe()} for s in spec.validate],
              "counts": {"complete": states.count(optuna.trial.TrialState.COMPLETE),
                         "pruned": states.count(optuna.trial.TrialState.PRUNED),
                         "failed": states.count(optuna.trial.TrialState.FAIL)},
              "defaults": {k: v for k, v in defaults.items() if k != "validate_entries"},
              "trials": rows, "front": [by_number[t.number] for t in candidates],
              "rule": spec.task.rule if spec.validate else "nothing was validated: the training "
              "front's first", "chosen": chosen, "chosen_vs_defaults": against,
              "warnings": warnings_of(chosen, defaults, against, spec.task),
              "seconds": round(seconds, 1)}
    write_json(spec.out_dir / "tune.json", report)
    markdown = tune_markdown(report)
    write_text(spec.out_dir / "tune.md", markdown)
    write_html(spec.out_dir / "tune.html", study, spec, markdown)
    if chosen is not None:
        write_text(spec.out_dir / "best.toml", best_toml(chosen["settings"]))
    return report


def validation_default(train: list[PlantSet]) -> list[PlantSet]:
    """The validation plants when none are given: the next seeds after each synthetic
    training set (none for real plants)."""
    return [s.following() for s in train if not s.real]


def local_storage(url: str) -> bool:
    """Whether the storage lives on this machine's disk (sqlite, a journal file)."""
    return url.startswith(("sqlite:", "journal:"))

