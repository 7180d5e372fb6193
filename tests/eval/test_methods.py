"""Another method as an external command, scored like the pipeline: itself gives the same
scores; one that crashes, hangs past its timeout or writes garbage is reported for that
plant and the run goes on."""

import json
import sys
from pathlib import Path

import pytest
from realplants import write_real_plant

from flowerpose.cli import main
from flowerpose.errors import InputError
from flowerpose.eval.scoring.methods import parse_method

SCRIPT = '''
import json, shutil, subprocess, sys, time
cloud, out, how = sys.argv[1:4]
if how == "crash":
    raise SystemExit("a method that crashes")
if how == "hang":
    time.sleep(60)
if how == "garbage":
    open(out + "/flowers.json", "w").write("{not json")
    raise SystemExit(0)
subprocess.run([sys.executable, "-m", "flowerpose", "detect", cloud, "--out", out + "/d",
                "-q"], check=True)
shutil.copy(out + "/d/flowers.json", out + "/flowers.json")
'''


@pytest.mark.slow
def test_external_methods_are_scored_beside_the_pipeline_and_failures_reported(tmp_path,
                                                                             capsys):
    script = tmp_path / "method.py"
    script.write_text(SCRIPT)
    plants = [write_real_plant(tmp_path / name, "cloud") for name in ("one", "two")]
    run = f"{sys.executable} {script} {{cloud}} {{out}}"

    def evaluate(out: str, timeout_s: int, *methods: str) -> dict:
        argv = ["eval", "-q", "--source", "real", *map(str, plants), "--workers", "1",
                "--out", str(tmp_path / out), "--method-timeout", str(timeout_s)]
        assert main(argv + [arg for m in methods for arg in ("--method", f"{m}={run} {m}")]) == 0
        return json.loads((tmp_path / out / "report.json").read_text())

    # A method that runs the pipeline itself gets all the time a loaded machine needs; the
    # one that hangs is stopped at a short timeout, in a run of its own.
    report = evaluate("out", 600, "itself", "crash", "garbage")
    compared = report["compare"]
    compared["hang"] = evaluate("hang", 5, "hang")["compare"]["hang"]
    out = capsys.readouterr().out
    assert compared["itself"]["summary"] == report["summary"]  # the same scores
    for name, words in (("crash", "a method that crashes"), ("hang", "past its timeout"),
                        ("garbage", "no usable flowers.json")):
        plants = compared[name]["plants"]
        assert [p["found"] for p in plants] == [0, 0] and all(words in p["error"] for p in plants)
        assert f"one: {name}:" in out and f"two: {name}:" in out


@pytest.mark.parametrize("text, words", [("nameless", "expected NAME="),
                                         ("x=detect {cloud}", "{out}"),
                                         ("x=detect '{cloud} {out}", "quotation")])
def test_a_malformed_method_is_bad_input(text, words):
    with pytest.raises(InputError, match=words):
        parse_method(text)


@pytest.mark.slow
def test_a_package_registers_a_method_by_name(tmp_path, monkeypatch):
    # An installed package as importlib.metadata finds one: its module and its dist-info.
    site = tmp_path / "site"
    (site / "mymethods-0.1.dist-info").mkdir(parents=True)
    (site / "mymethods-0.1.dist-info" / "METADATA").write_text(
        "Metadata-Version: 2.1\nName: mymethods\nVersion: 0.1\n")
    (site / "mymethods-0.1.dist-info" / "entry_points.txt").write_text(
        "[flowerpose.methods]\nnothing = mymethods:find_nothing\n")
    (site / "mymethods.py").write_text(
        "import json\n\ndef find_nothing(cloud, out):\n"
        "    (out / 'flowers.json').write_text(json.dumps({'flowers': []}))\n")
    monkeypatch.syspath_prepend(str(site))
    monkeypatch.setenv("PYTHONPATH", str(site))
    plant = write_real_plant(tmp_path / "plant", "cloud")
    assert main(["eval", "-q", "--source", "real", str(plant), "--workers", "1",
                 "--out", str(tmp_path / "out"), "--method", "nothing"]) == 0
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    nothing = report["compare"]["nothing"]
    assert nothing["summary"]["detections"] == 0 and "error" not in nothing["plants"][0]
    with pytest.raises(InputError, match="registered method .*nothing"):
        parse_method("unknown")


@pytest.mark.slow
def test_compare_takes_a_profile_a_detector_and_a_command_side_by_side(tmp_path, capsys,
                                                                      monkeypatch):
    monkeypatch.setenv("PYTHONPATH", str(Path(__file__).parent.parent))  # for the workers
    script = tmp_path / "method.py"
    script.write_text(SCRIPT)
    plant = write_real_plant(tmp_path / "one", "cloud")
    code = main(["eval", "-q", "--source", "real", str(plant), "--workers", "1",
                 "--out", str(tmp_path / "out"), "--compare", "upstream",
                 "--compare", "detector_plugins:Same",
                 "--compare", f"itself={sys.executable} {script} {{cloud}} {{out}} itself"])
    out = capsys.readouterr().out
    assert code == 0
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert set(report["compare"]) == {"upstream", "detector-Same", "itself"}
    for same in ("detector-Same", "itself"):  # the pipeline under other names: its scores
        assert report["compare"][same]["summary"] == report["summary"]
    assert report["compare"]["upstream"]["config"]["cluster"]["candidates"] == "all"
    assert report["config"]["cluster"]["candidates"] != "all"
    assert all(name in out for name in ("upstream", "detector-Same", "itself"))
    for bad, words in (("nothing-known", "a profile (upstream)"),
                       ("no_such_module:X", "cannot load it")):
        assert main(["eval", "--source", "real", str(plant), "--out", str(tmp_path / "bad"),
                     "--compare", bad]) == 2
        err = capsys.readouterr().err
        assert words in err and err.count("\n") == 1, err
    assert not (tmp_path / "bad").exists()
