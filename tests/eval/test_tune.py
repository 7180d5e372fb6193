"""`flowerpose tune`: a seeded study over a tiny space, resumed, refused and failing
cleanly, and its chosen settings taken by eval --config."""

import json

import pytest
from realplants import write_real_plant

from flowerpose.cli import main
from flowerpose.errors import InputError
from flowerpose.eval.studies import tune

SPACE = '"cluster.eps" = { low = 0.006, high = 0.014, log = true }\n' \
        '"cluster.min_coverage" = { low = 0.2, high = 0.5 }\n'


@pytest.fixture(scope="module")
def plants(tmp_path_factory):
    root = tmp_path_factory.mktemp("tune-plants")
    return (write_real_plant(root / "train", "candidates", seed=1),
            write_real_plant(root / "validate", "candidates", seed=2))


def _tune(tmp_path, plants, space=SPACE, trials=4, *extra):
    (tmp_path / "space.toml").write_text(space)
    return main(["tune", "--space", str(tmp_path / "space.toml"), "--trials", str(trials),
                 "--train", str(plants[0]), "--validate", str(plants[1]),
                 "--sampler-seed", "3", "--out", str(tmp_path / "out"), *extra])


@pytest.mark.slow
def test_a_seeded_study_resumes_and_its_choice_runs_in_eval(tmp_path, plants, capsys):
    assert _tune(tmp_path, plants) == 0
    report = json.loads((tmp_path / "out" / "tune.json").read_text())
    assert report["counts"] == {"complete": 4, "pruned": 0, "failed": 0}
    assert all(t["train"]["f1"] is not None and t["validate"]["f1"] is not None
               for t in report["trials"])
    chosen = report["chosen"]
    assert chosen is not None and chosen["number"] in [t["number"] for t in report["front"]]
    assert "validation F1" in report["rule"] and "defaults" in capsys.readouterr().out
    # Chosen by the bounds, and compared with the defaults flower by flower.
    assert chosen["validate"]["f1_low"] == max(t["validate"]["f1_low"] for t in report["front"])
    against = report["chosen_vs_defaults"]
    assert against["verdicts"][0].startswith("plane") and against["plane"]["n"] > 0
    if not against["distinguishable"]:
        assert any("not distinguishable" in w for w in report["warnings"])
    # The same command again adds trials to the same study.
    assert _tune(tmp_path, plants, SPACE, 2) == 0
    again = json.loads((tmp_path / "out" / "tune.json").read_text())
    assert again["study"] == report["study"] and again["counts"]["complete"] == 6
    assert [t["settings"] for t in again["trials"][:4]] == [t["settings"]
                                                            for t in report["trials"]]
    # best.toml is a --config file eval takes, and it holds the chosen settings.
    best = tmp_path / "out" / "best.toml"
    assert main(["eval", "--source", "real", str(plants[1]), "--config", str(best),
                 "--out", str(tmp_path / "eval")]) == 0
    config = json.loads((tmp_path / "eval" / "report.json").read_text())["config"]
    assert config["cluster"]["eps"] == pytest.approx(again["chosen"]["settings"]["cluster.eps"])


@pytest.mark.slow
def test_a_study_of_another_space_under_the_same_name_is_refused(tmp_path, plants, capsys):
    assert _tune(tmp_path, plants, SPACE, 1, "--study-name", "mine") == 0
    other = '"cluster.eps" = { low = 0.006, high = 0.02 }\n'
    assert _tune(tmp_path, plants, other, 1, "--study-name", "mine", "--overwrite") == 2
    assert "made with another space" in capsys.readouterr().err


@pytest.mark.slow
def test_a_trial_that_raises_is_recorded_as_failed_and_the_study_goes_on(tmp_path, plants,
                                                                         monkeypatch):
    score = tune.SetScorer.score
    calls = {"n": 0}

    def flaky(self, plant_set, layers, out_dir):
        calls["n"] += 1
        if calls["n"] == 3:  # the first trial's training plants (the defaults took 1 and 2)
            raise RuntimeError("a broken reconstruction")
        return score(self, plant_set, layers, out_dir)

    monkeypatch.setattr(tune.SetScorer, "score", flaky)
    assert _tune(tmp_path, plants, SPACE, 3) == 0
    report = json.loads((tmp_path / "out" / "tune.json").read_text())
    assert report["counts"] == {"complete": 2, "pruned": 0, "failed": 1}
    failed = next(t for t in report["trials"] if t["state"] == "fail")
    assert "a broken reconstruction" in failed["error"]


@pytest.mark.parametrize("space, said", [
    ('"cluster.epsilon" = { low = 0.006, high = 0.01 }\n', "no such setting"),
    ('"cluster.eps" = { low = 0.01, high = 0.01 }\n', "is empty"),
    ('"cluster.crop" = { low = 1, high = 2 }\n', "is not a number"),
    ('"cluster.min_points" = { low = 5, high = 40 }\n', "int = true"),
    ('"cluster.crop" = { choices = ["near", "sideways"] }\n', "sideways"),
    ('"cluster.eps" = 0.01\n', "expected"),
    ('"cluster.eps" = { low = 0.006, high = 0.01, log = "false" }\n', "true or false"),
    ("", "empty"),
])
def test_a_bad_space_is_one_line_and_exit_2(tmp_path, plants, capsys, space, said):
    assert _tune(tmp_path, plants, space, 1) == 2
    err = capsys.readouterr().err
    assert said in err and err.count("\n") == 1 and "space.toml" in err
    assert not (tmp_path / "out" / "tune.json").exists()


def test_a_bad_objective_is_refused_before_any_trial(tmp_path, plants, capsys):
    assert _tune(tmp_path, plants, SPACE, 1, "--objective", "max:f2") == 2
    assert "not a number of the report's summary" in capsys.readouterr().err


@pytest.mark.parametrize("study, said", [
    ("study.db", "is not a storage URL"),
    ("sqlite:///{tmp}/missing/study.db", "is not there"),
    ("journal:///{tmp}/missing/study.log", "is not there"),
])
def test_a_storage_that_cannot_work_is_one_line_before_any_trial(tmp_path, plants, capsys,
                                                                  study, said):
    assert _tune(tmp_path, plants, SPACE, 1, "--study", study.format(tmp=tmp_path)) == 2
    err = capsys.readouterr().err
    assert said in err and err.count("\n") == 1 and "--study" in err
    assert not (tmp_path / "out" / "tune.json").exists()


@pytest.mark.slow
def test_a_trial_left_running_by_a_killed_tune_is_marked_failed_and_its_scratch_goes(
        tmp_path, plants, capsys):
    import os
    import signal
    import subprocess
    import sys
    import time

    (tmp_path / "space.toml").write_text(SPACE)
    command = [sys.executable, "-m", "flowerpose", "tune", "--space",
               str(tmp_path / "space.toml"), "--trials", "50", "--train", str(plants[0]),
               "--validate", str(plants[1]), "--sampler-seed", "3", "--out",
               str(tmp_path / "out"), "-q"]
    killed = subprocess.Popen(command, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    scratch = tmp_path / "out" / "trials"
    while not list(scratch.glob("trial-*-*")):
        assert killed.poll() is None, "tune ended before a trial started"
        time.sleep(0.02)
    killed.send_signal(signal.SIGKILL)
    killed.wait()
    assert list(scratch.glob("trial-*-*"))  # a dead trial's scratch is left behind
    assert _tune(tmp_path, plants, SPACE, 1) == 0
    assert "marked failed" in capsys.readouterr().err
    report = json.loads((tmp_path / "out" / "tune.json").read_text())
    stopped = [t for t in report["trials"] if t["state"] == "fail"]
    assert stopped and "its process stopped" in stopped[-1]["error"]
    assert report["counts"]["failed"] >= 1
    assert not [t for t in report["trials"] if t["state"] == "running"]
    assert not list(scratch.glob("trial-*-*"))



class _Trial:
    def __init__(self, number, values, new_flipped=0, validate_flipped=()):
        self.number, self.values = number, values
        self.user_attrs = {"new_flipped": new_flipped,
                           "validate": {"f1_low": values[0], "flipped_flowers":
                                        list(validate_flipped),
                                        "error_deg.plane.mean_ci95.high": 2.0}}


def test_a_trial_that_adds_a_flip_is_infeasible_and_never_chosen():
    from flowerpose.eval.studies.tune import choose

    flips = _Trial(1, [0.95], validate_flipped=["val: seed-10 flower 3"])
    clean = _Trial(2, [0.90], validate_flipped=["val: seed-11 flower 1"])
    # A flip the defaults made too is no new one; one they did not make rules a trial out.
    assert choose([flips, clean], True, ["val: seed-11 flower 1"]) is clean
    assert choose([flips], True, []) is None
    assert choose([flips, clean], False) is flips


def _scored(number, pollinated_low, collisions_high, values=(0.9, 0.01)):
    trial = _Trial(number, list(values))
    trial.user_attrs["validate"].update({
        "pollination.success_rate_ci95.low": pollinated_low,
        "pollination.collision_share_ci95.high": collisions_high})
    return trial


def test_a_pollination_study_chooses_by_the_validation_bounds_of_pollinated_then_collided():
    from flowerpose.eval.studies.tune import choose
    from flowerpose.eval.studies.tune_task import POLLINATE

    more = _scored(1, 0.80, 0.05)
    fewer_collisions = _scored(2, 0.80, 0.02)
    less = _scored(3, 0.75, 0.0)
    assert choose([more, less], True, [], POLLINATE) is more
    assert choose([more, fewer_collisions, less], True, [], POLLINATE) is fewer_collisions
    # A trial without the scores (its visits never flown) ranks last.
    assert choose([_scored(4, None, None), less], True, [], POLLINATE) is less


def test_a_pollination_studys_warnings_name_what_got_worse():
    from flowerpose.eval.studies.tune import warnings_of
    from flowerpose.eval.studies.tune_task import POLLINATE

    defaults = {"validate": {"pollination.success_rate": 0.8,
                             "pollination.collision_share": 0.01}}
    chosen = {"validate": {"pollination.success_rate": 0.75,
                           "pollination.collision_share": 0.03}}
    said = warnings_of(chosen, defaults, None, POLLINATE)
    assert said == ["the chosen settings' validation share pollinated (0.750) is below the "
                    "defaults' (0.800)",
                    "the chosen settings' validation share of visits that collided (0.030) "
                    "is above the defaults' (0.010)"]
    assert warnings_of(defaults, defaults, None, POLLINATE) == []


def test_a_pollination_study_takes_its_own_objectives_and_refuses_real_plants(
        tmp_path, plants, capsys):
    from flowerpose.eval.studies.tune_space import parse_objectives

    assert [o.text for o in parse_objectives([], "pollinate")] == [
        "max:pollination.success_rate", "min:pollination.collision_share"]
    with pytest.raises(InputError, match="run with --task pollinate"):
        parse_objectives(["max:pollination.success_rate"])
    assert _tune(tmp_path, plants, SPACE, 1, "--task", "pollinate") == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "pollinate needs synthetic plants" in err
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_a_pollination_studys_scorer_visits_each_plant_and_records_the_share_pollinated(
        tmp_path):
    from flowerpose.eval.jobs.plant_set import PlantSet
    from flowerpose.eval.studies.tune import SetScorer, _recorded
    from flowerpose.eval.studies.tune_task import POLLINATE

    # No path search and no close look: the scorer's wiring is on trial here.
    layers = ({"pollinate.path_checks": 0, "pollinate.look.views": 0},)
    scorer = SetScorer(tmp_path, None, task=POLLINATE)
    [entry] = scorer.score(PlantSet("oracle", "easy", 1, 2), layers, tmp_path / "trial")
    visited = entry["pollination"]
    assert len(visited["flowers"]) == entry["gt"] and "pollination_ceiling" in entry
    assert (tmp_path / "trial" / entry["plant"] / "flight.json").exists()
    recorded = _recorded([entry], POLLINATE)
    assert recorded["pollination.successes"] == visited["successes"] > 0
    assert recorded["pollination.success_rate"] == round(
        visited["successes"] / len(visited["flowers"]), 4)
    assert 0 <= recorded["pollination.success_rate_ci95.low"] <= recorded[
        "pollination.success_rate"]
    assert recorded["pollination.collision_share"] == round(
        visited["failures"]["collision"] / visited["visits"], 4)


def test_workers_adding_trials_at_once_draw_different_settings(tmp_path):
    """--sampler-seed with several workers: each worker's sampler is seeded apart, so the
    first (random) trials of two workers are not the same settings twice."""
    from flowerpose.eval.jobs.config import eval_config
    from flowerpose.eval.studies.tune import TuneSpec, open_study, study_name
    from flowerpose.eval.studies.tune_space import parse_objectives, read_space

    (tmp_path / "space.toml").write_text(SPACE)
    space = tuple(read_space(tmp_path / "space.toml", eval_config("field")))
    objectives = tuple(parse_objectives([]))
    name, identity = study_name(space, (), objectives)
    spec = TuneSpec(space, (), (), objectives, (), f"sqlite:///{tmp_path / 'study.db'}", name,
                    3, tmp_path, None)
    open_study(spec, identity, create=True)

    def first_draw(worker):
        study = open_study(spec, {}, create=False, worker=worker)
        trial = study.ask()
        return {p.key: p.suggest(trial) for p in space}

    assert first_draw(0) == first_draw(0)  # one worker: the same trials again
    assert first_draw(0) != first_draw(1)


def test_a_study_made_before_tasks_is_the_pose_tasks_and_resumes(tmp_path):
    from flowerpose.eval.jobs.config import eval_config
    from flowerpose.eval.studies.tune import TuneSpec, open_study, study_name
    from flowerpose.eval.studies.tune_space import parse_objectives, read_space
    from flowerpose.eval.studies.tune_task import POLLINATE

    (tmp_path / "space.toml").write_text(SPACE)
    space = tuple(read_space(tmp_path / "space.toml", eval_config("field")))
    objectives = tuple(parse_objectives([]))
    name, identity = study_name(space, (), objectives)
    spec = TuneSpec(space, (), (), objectives, (), f"sqlite:///{tmp_path / 'study.db'}", name,
                    None, tmp_path, None)
    older = {k: v for k, v in identity.items() if k != "task"}  # as an older version made it
    open_study(spec, older, create=True)
    assert open_study(spec, identity, create=True).user_attrs["identity"] == older
    with pytest.raises(InputError, match="another task"):
        open_study(spec, study_name(space, (), objectives, POLLINATE)[1], create=True)
