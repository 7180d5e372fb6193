"""CI gates: --require on the run and each plant, exit status 1 with a table of what
failed, JUnit XML and a Markdown summary; a bad gate is bad input (exit 2) before any work."""

import xml.etree.ElementTree as ET

import pytest
from realplants import write_real_plant

from flowerpose.cli import main
from flowerpose.errors import InputError
from flowerpose.eval.jobs.plant_set import PlantSet
from flowerpose.eval.pool import Execution
from flowerpose.eval.reports.gates import parse_requirements


@pytest.mark.slow
def test_a_run_that_meets_its_gates_exits_0_and_one_that_misses_exits_1(tmp_path, capsys):
    one = write_real_plant(tmp_path / "one", "crops")
    two = write_real_plant(tmp_path / "two", "crops", labelled=3)  # its 4th flower: a FP
    common = ["eval", "-q", "--source", "real", str(one), str(two), "--workers", "1"]
    assert main([*common, "--out", str(tmp_path / "a"), "--require", "recall_visible>=1",
                 "--require", "error_deg.plane.mean<=2"]) == 0
    assert "all 6 requirements hold" in capsys.readouterr().out
    junit, summary = tmp_path / "gates.xml", tmp_path / "gates.md"
    code = main([*common, "--out", str(tmp_path / "b"), "--require", "fp<=0",
                 "--require", "found>=4", "--junit", str(junit), "--summary", str(summary)])
    out = capsys.readouterr().out
    assert code == 1
    failed = out.split("requirements failed:")[1]
    assert "| all " in failed and "| two " in failed and "| one " not in failed
    suite = ET.parse(junit).getroot().find("testsuite")
    # fp<=0 fails on the run and on "two"; found>=4 fails on "two" only.
    assert (suite.get("tests"), suite.get("failures")) == ("6", "3")
    names = {(c.get("classname"), c.get("name")): c.find("failure") is not None
             for c in suite.iter("testcase")}
    assert names[("flowerpose.two", "found>=4")] and not names[("flowerpose.one", "found>=4")]
    assert summary.read_text().startswith("## flowerpose eval") and "3 of 6" in summary.read_text()


@pytest.mark.parametrize("gate, words", [
    ("recall", "expected KEY>=NUMBER"),
    ("error_deg.plane>=1", "not a number of the report's summary"),
    ("recall>=high", "is not a number"),
    ("nope<=3", "error_deg.plane.mean"),
])
def test_a_bad_gate_is_one_line_before_any_work(gate, words, tmp_path, capsys):
    with pytest.raises(InputError, match=words):
        parse_requirements([gate])
    assert main(["eval", "--source", "oracle", "--require", gate,
                 "--out", str(tmp_path / "never")]) == 2
    assert not (tmp_path / "never").exists()
    assert capsys.readouterr().err.count("\n") == 1


def test_every_shipped_suite_loads_and_what_it_fixes_cannot_be_given_too(tmp_path, capsys):
    from flowerpose.config import SUITE_KEYS, load_suite, suite_names

    assert {"oracle-10", "field-10", "scan-3"} <= set(suite_names())
    for name in suite_names():
        suite = load_suite(name)
        assert suite["version"] >= 1 and set(suite["eval"]) == set(SUITE_KEYS)
    for extra in (["--plants", "3"], ["--source", "scan"], ["--set", "cluster.eps=0.01"]):
        assert main(["eval", "--suite", "oracle-10", *extra, "--out", str(tmp_path / "n")]) == 2
        assert "--suite oracle-10" in capsys.readouterr().err
    assert not (tmp_path / "n").exists()


def test_the_report_records_the_suite(tmp_path):
    from flowerpose.eval.jobs.config import EvalConfig
    from flowerpose.eval.jobs.eval_run import EvalRun
    from flowerpose.eval.studies.eval_recipe import run_eval

    suite = {"name": "mine", "version": 3, "description": "a test"}
    run = EvalRun(PlantSet("real", folders=(write_real_plant(tmp_path / "plant", "crops"),)),
                  suite=suite)
    report = run_eval(EvalConfig(), run, tmp_path / "out", Execution(1))
    assert report["suite"] == suite


def test_a_pollination_gate_is_a_number_only_of_a_pollination_run():
    """The pollination task's summary adds `pollination.*`: a gate on it is checked where
    the visits are flown, and refused before any work where they are not."""
    gate = "pollination.success_rate>=0.8"
    assert parse_requirements([gate, "pollination.collision_share<=0.02"], "pollinate")
    with pytest.raises(InputError, match="the pollination task's summary only"):
        parse_requirements([gate])


def test_each_plants_gate_reads_its_own_pollination():
    from flowerpose.eval.reports.gates import check

    def plant(name, outcomes, visits):
        return {"plant": name, "gt": 0, "visible": 0, "detections": 0, "found": 0,
                "found_visible": 0, "extra": 0, "fp": 0, "matches": [],
                "error_deg": {m: [] for m in ("plane", "superellipsoid", "paraboloid")},
                "failed": {m: 0 for m in ("plane", "superellipsoid", "paraboloid")},
                **{key: {"visits": visits, "flowers": [{"flower": k, "outcome": o}
                                                       for k, o in enumerate(outcomes)]}
                   for key in ("pollination", "pollination_ceiling")}}

    plants = [plant("a", ["success", "success"], 2), plant("b", ["success", "collision"], 2)]
    [gate] = parse_requirements(["pollination.success_rate>=0.9"], "pollinate")
    report = {"summary": {"pollination": {"success_rate": 0.75}}, "plants": plants}
    measured = {o.scope: o.measured for o in check(report, [gate])}
    assert measured == {"all": 0.75, "a": 1.0, "b": 0.5}
    # A section this run has not (no close look: no scan-pose flight) fails, no traceback.
    [looked] = parse_requirements(["pollination_scan_pose.success_rate>=0.5"], "pollinate")
    outcomes = check(report, [looked])
    assert all(o.measured is None and not o.passed for o in outcomes)
