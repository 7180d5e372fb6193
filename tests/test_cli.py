"""The command line: each job end to end on a small plant, and every error path."""

import argparse
import json
import re
import shlex
import subprocess
import sys

import numpy as np
import pytest
from cli_run import run_cli

from flowerpose import __version__
from flowerpose.cli import build_parser, main
from flowerpose.cloudio import Cloud, write_cloud


def _assert_one_line_error(code, err, *words):
    assert code == 2
    lines = [line for line in err.splitlines() if line.strip()]
    errors = [line for line in lines if line.startswith("flowerpose: error: ")]
    # Progress lines may come first; the error is one line, the last.
    assert len(errors) == 1 and lines[-1] == errors[0], err
    assert "Traceback" not in err
    for word in words:
        assert word in errors[0]


@pytest.mark.slow
def test_detect_pose_score_chain(plant0, tmp_path, capsys):
    _, plant_dir = plant0
    out = tmp_path / "det"
    code, text, _ = run_cli(capsys, "detect", plant_dir / "cloud.ply", "--out", out)
    assert code == 0 and "flowers" in text
    flowers = json.loads((out / "flowers.json").read_text())
    assert len(flowers["flowers"]) == 6
    assert (flowers["units"], flowers["frame"]) == ("m", "bed")
    assert flowers["source"] == str(plant_dir / "cloud.ply")
    assert {"center", "normals", "points", "petal_points", "pistil_found", "box"} <= set(
        flowers["flowers"][0])
    assert flowers["timing_s"]["total"] > 0
    assert (out / "views" / "views.png").exists()
    assert len(list((out / "views").glob("view_*.png"))) == 14  # the default grid.views
    # The normals for MeshLab / CloudCompare: centres with nx ny nz, and an arrow mesh.
    import open3d as o3d

    points = o3d.io.read_point_cloud(str(out / "flowers.ply"))
    np.testing.assert_allclose(np.asarray(points.points),
                               [f["center"] for f in flowers["flowers"]], atol=1e-9)
    np.testing.assert_allclose(np.asarray(points.normals),
                               [f["normals"]["plane"] for f in flowers["flowers"]], atol=1e-9)
    arrows = o3d.io.read_triangle_mesh(str(out / "normals.ply"))
    vertices = np.asarray(arrows.vertices)
    assert len(arrows.triangles) > 0 and len(vertices) % 6 == 0
    for flower, tip in zip(flowers["flowers"], np.split(vertices, 6), strict=True):
        # each arrow runs from its flower's centre along its normal
        along = (tip - flower["center"]) @ np.array(flower["normals"]["plane"])
        assert along.min() > -1e-3 and along.max() == pytest.approx(max(flower["box"]["extent"]))
    code, text, _ = run_cli(capsys, "pose", out / "crops" / "flower_00.ply")
    entry = json.loads(text)
    assert code == 0 and entry["pistil_found"] and len(entry["normals"]["plane"]) == 3
    assert set(entry) == set(flowers["flowers"][0])
    code, text, _ = run_cli(capsys, "score", out / "flowers.json", plant_dir / "plant.json",
                         "--out", tmp_path / "score")
    report = json.loads((tmp_path / "score" / "report.json").read_text())
    assert code == 0 and "Plane" in text
    assert report["summary"]["found"] == 6 and report["summary"]["fp"] == 0
    assert report["summary"]["error_deg"]["plane"]["mean"] < 4.0


@pytest.mark.slow
def test_eval_writes_the_report_contract(tmp_path, capsys):
    out = tmp_path / "eval"
    code, text, err = run_cli(capsys, "eval", "--source", "oracle", "--plants", 1, "--seed", 1,
                           "--workers", 1,
                           "--out", out, "--set", "cluster.eps=0.01")
    assert code == 0
    # Progress: a line per plant with the time it took (the last: nothing left).
    assert re.search(r"^\[1/1\] seed-1 scored: .* \(\d+ s in\)$", err, re.MULTILINE), err
    code, quiet_text, quiet_err = run_cli(capsys, "eval", "-q", "--source", "oracle", "--plants",
                                       1, "--seed", 1, "--workers", 1, "--out", out,
                                       "--set", "cluster.eps=0.01")
    def without_times(printed):
        return [line for line in printed.splitlines() if "wall time" not in line]

    assert code == 0 and quiet_err == ""  # -q: the result alone
    assert without_times(quiet_text) == without_times(text)
    assert "Superellipsoid" in text and "Total" in text and "Std Dev" in text
    report = json.loads((out / "report.json").read_text())
    assert set(report) >= {"config", "plants", "summary", "timing_s"}
    assert set(report["plants"][0]) >= {"plant", "gt", "visible", "detections", "found", "extra",
                                        "fp", "error_deg"}
    assert set(report["summary"]) >= {"gt", "visible", "detections", "found", "recall",
                                      "recall_visible", "extra", "fp", "error_deg"}
    assert set(report["summary"]["error_deg"]["plane"]) == {
        "mean", "median", "std", "n", "mean_ci95", "median_ci95", "p90", "p90_ci95",
        "over_20", "over_20_ci95", "over_90", "over_90_ci95"}
    assert set(report["summary"]["accuracy"]["plane"]) == {"thresholds_deg", "share", "n",
                                                           "auc", "auc_ci95"}
    assert report["config"]["cluster"]["eps"] == 0.01
    # An oracle run's settings: the pipeline's, the plants' and the scoring; no scan, RGB-D
    # or fusion settings, which it never used.
    assert set(report["config"]) == {"source", "preset", "plants", "seed", "colour", "ground",
                                     "grid",
                                     "detect", "outliers", "cluster", "pose", "sim", "score"}
    assert report["timing_s"]["total"] > 0
    assert report["summary"]["recall_visible"] >= 0.9
    assert (out / "report.md").read_text().startswith("# flowerpose eval")
    assert (out / "plants" / "seed-1" / "flowers.json").exists()


def test_plant_command(tmp_path, capsys):
    code, text, _ = run_cli(capsys, "plant", "--seed", 4, "--points", 5000, "--preset", "easy",
                         "--out", tmp_path / "p")
    assert code == 0 and "5000 cloud points" in text
    truth = json.loads((tmp_path / "p" / "plant.json").read_text())
    assert truth["units"] == "m" and truth["frame"] == "bed" and truth["seed"] == 4
    assert {"id", "center", "normal", "radius", "petals", "stage", "visible"} <= set(
        truth["flowers"][0])


def test_a_cloud_without_flowers_gives_an_empty_result(tmp_path, capsys):
    rng = np.random.default_rng(0)
    leaves = Cloud(rng.random((3000, 3)) * [0.3, 0.3, 0.2] + [0, 0, 0.05],
                   np.tile([50, 120, 40], (3000, 1)).astype(np.uint8))
    path = write_cloud(tmp_path / "leaves.ply", leaves)
    code, text, _ = run_cli(capsys, "detect", path, "--out", tmp_path / "out")
    assert code == 0 and text.startswith("0 flowers")
    assert json.loads((tmp_path / "out" / "flowers.json").read_text())["flowers"] == []
    import open3d as o3d

    assert len(o3d.io.read_point_cloud(str(tmp_path / "out" / "flowers.ply")).points) == 0


@pytest.mark.slow
def test_a_millimetre_cloud_is_converted_and_said(plant0, tmp_path, capsys):
    bundle, _ = plant0
    path = write_cloud(tmp_path / "mm.ply", Cloud(bundle.cloud.points * 1000, bundle.cloud.colors))
    code, text, err = run_cli(capsys, "detect", path, "--out", tmp_path / "out")
    assert code == 0 and "millimetres" in err and text.startswith("6 flowers")


def _grey_cloud(path):
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.random.default_rng(0).random(
        (20, 3))))
    o3d.io.write_point_cloud(str(path), pcd)
    return path


@pytest.mark.parametrize("argv, words", [
    (["detect", "{tmp}/missing.ply", "--out", "{tmp}/o"], ["missing.ply", "not found"]),
    (["detect", "{grey}", "--out", "{tmp}/o"], ["grey.ply", "no colours"]),
    (["detect", "{nan}", "--out", "{tmp}/o"], ["nan.ply", "NaN"]),
    (["detect", "{empty}", "--out", "{tmp}/o"], ["empty.ply", "no points"]),
    (["pose", "{tmp}/missing.ply"], ["missing.ply"]),
    (["detect", "{nan}", "--out", "{tmp}/o", "--set", "cluster.epz=1"], ["cluster.epz"]),
    (["detect", "{nan}", "--out", "{tmp}/o", "--set", "cluster.eps=big"], ["cluster.eps"]),
    (["detect", "{nan}", "--out", "{tmp}/o", "--config", "{tmp}/none.toml"], ["none.toml"]),
    (["score", "{badjson}", "{badjson}"], ["bad.json", "JSON"]),
    (["score", "{tmp}/missing.json", "{badjson}"], ["missing.json"]),
    (["score", "{badjson}", "{badjson}", "--truth-scale", "0"], ["--truth-scale"]),
    (["score", "{badjson}", "{badjson}", "--max-distance", "nan"], ["--max-distance"]),
    (["score", "{flowers_string}", "{badjson}"], ["flower 0: normals.plane"]),
    (["score", "{flowers_zero}", "{badjson}"], ["zero vector"]),
    (["score", "{flowers_nan}", "{badjson}"], ["flowers_nan", "NaN"]),
    (["score", "{flowers_bool}", "{badjson}"], ["normals.plane"]),
    (["score", "{flowers_nonormals}", "{badjson}"], ["'normals'"]),
    (["eval", "--source", "photos", "--out", "{tmp}/e"], ["--source"]),
    (["eval", "--set", "scan.frames=1", "--out", "{tmp}/e"], ["scan.frames"]),
    (["eval", "--plants", "0", "--out", "{tmp}/e"], ["--plants"]),
    (["sweep", "--grid", "cluster.eps", "--out", "{tmp}/s"], ["--grid"]),
    (["sweep", "--grid", "nope.eps=1,2", "--out", "{tmp}/s"], ["nope"]),
    (["sweep", "--task", "pollinate", "--grid", "pollinate.cone_azimuths=16,0", "--out",
      "{tmp}/s"], ["pollinate.cone_azimuths", "positive"]),
    (["eval", "--plants", "abc"], ["--plants", "whole number"]),
    (["frames", "{tmp}/scan", "--count", "0", "--out", "{tmp}/f"], ["--count", "at least 1"]),
    (["frames", "{tmp}/scan", "--set", "crop_px=2", "--out", "{tmp}/f"], ["--crop", "3 pixels"]),
    (["frames", "{tmp}/scan", "--set", "count=many", "--out", "{tmp}/f"], ["whole number"]),
    (["score", "{badjson}", "{badjson}", "--set", "cluster.eps=0.01"], ["score reads score.*"]),
    (["scan", "--sim", "--plant", "{tmp}", "--width", "8", "--out", "{tmp}/s"],
     ["--width", "16 pixels"]),
    (["detect"], ["required"]),
    (["frobnicate"], ["invalid choice"]),
    (["eval", "--source", "oracle", "--plants", "1", "--workers", "1", "--out", "{badjson}"],
     ["bad.json"]),
    # Raised inside worker processes: the error must cross back intact.
    (["eval", "--source", "oracle", "--plants", "2", "--workers", "2", "--out", "{tmp}/e",
      "--set", "grid.pixel_size_m=0.00001"], ["grid.pixel_size_m"]),
])
@pytest.mark.slow
def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys, argv, words):
    import open3d as o3d

    nan = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.array([[0, 0, 0], [np.nan, 0, 0]])))
    nan.colors = o3d.utility.Vector3dVector(np.full((2, 3), 0.5))
    o3d.io.write_point_cloud(str(tmp_path / "nan.ply"), nan)
    (tmp_path / "empty.ply").write_text("ply\nformat ascii 1.0\nelement vertex 0\nproperty float "
                                        "x\nproperty float y\nproperty float z\nend_header\n")
    (tmp_path / "bad.json").write_text("{not json")
    flowers = {"string": {"center": [0, 0, 0], "normals": {"plane": ["a", "b", "c"]}},
               "zero": {"center": [0, 0, 0], "normals": {"plane": [0, 0, 0]}},
               "nan": {"center": [float("nan"), 0, 0], "normals": {"plane": None}},
               "bool": {"center": [0, 0, 0], "normals": {"plane": [True, False, False]}},
               "nonormals": {"center": [0, 0, 0]}}
    for name, entry in flowers.items():
        (tmp_path / f"flowers_{name}.json").write_text(json.dumps({"flowers": [entry]}))
    names = {"tmp": tmp_path, "grey": _grey_cloud(tmp_path / "grey.ply"),
             **{f"flowers_{n}": tmp_path / f"flowers_{n}.json" for n in flowers},
             "nan": tmp_path / "nan.ply", "empty": tmp_path / "empty.ply",
             "badjson": tmp_path / "bad.json"}
    try:
        code, _, err = run_cli(capsys, *[a.format(**names) for a in argv])
    except SystemExit as exit_:
        code, err = exit_.code, capsys.readouterr().err
    _assert_one_line_error(code, err, *words)


@pytest.mark.parametrize("argv, message", [
    (["plant", "--seed", "0", "--points", "100000000000", "--out", "x"],
     "must be at most 20,000,000 (more does not fit in memory)"),
    (["eval", "--source", "oracle", "--plants", "1000000000"], "must be at most 10,000"),
    (["sweep", "--grid", "cluster.eps=0.01", "--grid", "cluster.eps=0.02", "--out", "x"],
     "cluster.eps is given twice"),
])
def test_sizes_and_repeated_keys_are_refused_before_any_work(argv, message, capsys):
    try:
        code = main(argv)
    except SystemExit as exit:  # argparse's own refusals
        code = exit.code
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]


def test_a_toml_file_that_is_not_utf8_is_one_line(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_bytes(b"[cluster]\neps = 0.01 # \xff\xfe\n")
    assert main(["detect", str(tmp_path / "none.ply"), "--out", str(tmp_path / "o"),
                 "--config", str(bad)]) == 2
    assert "not a UTF-8 text file" in capsys.readouterr().err


def test_a_bare_command_shows_the_help_and_the_version_is_one_line(capsys):
    assert main([]) == 0
    assert "COMMAND" in capsys.readouterr().out
    with pytest.raises(SystemExit) as done:
        main(["--version"])
    assert done.value.code == 0
    assert capsys.readouterr().out.strip() == f"flowerpose {__version__}"


@pytest.mark.slow
def test_python_dash_m_runs_the_command_line():
    result = subprocess.run([sys.executable, "-m", "flowerpose", "--version"],
                            capture_output=True, text=True)
    assert result.returncode == 0 and result.stdout.strip() == f"flowerpose {__version__}"


def _commands() -> dict:
    from flowerpose.cli import build_parser

    return next(a for a in build_parser()._actions
                if isinstance(a, argparse._SubParsersAction)).choices


def _examples(epilog: str) -> list[str]:
    """The example command lines of a help's epilog, without their comments."""
    return [line.split("  #")[0].strip() for line in epilog.splitlines()
            if line.strip().startswith("flowerpose")]


@pytest.mark.parametrize("name", sorted(_commands()))
def test_every_command_says_what_it_does_and_ends_with_an_example(name, capsys):
    from flowerpose.cli import build_parser

    command = _commands()[name]
    description = command.description or ""
    # One sentence of what it does first: a capital, and a full stop ending it.
    assert description[:1].isupper() and "." in description, (name, description)
    epilog = command.epilog or ""
    assert epilog.startswith(("example:", "examples:")), (name, epilog)
    examples = _examples(epilog)
    assert examples and all(e.startswith(f"flowerpose {name}") for e in examples), (name, epilog)
    for example in examples:  # each example is a command that parses as written
        build_parser().parse_args(shlex.split(example)[1:])
    for action in command._actions:
        if isinstance(action, argparse._HelpAction):
            continue
        assert action.help and action.help.strip(), (name, action.dest)
        if action.default not in (None, False, [], argparse.SUPPRESS) and action.nargs != 0:
            # A default the help states by hand goes stale when the code's changes.
            shows = "default: " if isinstance(action.default, list) else "%(default"
            assert shows in action.help, (name, action.dest)
    with pytest.raises(SystemExit) as done:
        build_parser().parse_args([name, "--help"])
    # a long example is shown on lines continued with a backslash, as a shell reads it
    shown = re.sub(r" \\\n +", " ", capsys.readouterr().out)
    assert done.value.code == 0 and shown.rstrip().endswith(examples[-1])


def test_the_command_list_has_a_description_and_examples():
    from flowerpose.cli import build_parser

    parser = build_parser()
    assert parser.description and parser.description[0].isupper()
    examples = _examples(parser.epilog or "")
    assert examples
    for example in examples:
        build_parser().parse_args(shlex.split(example)[1:] or ["eval"])


def test_a_setting_flag_is_its_setting_with_its_docstring_and_default(capsys):
    """frames' flags are --set under other names: the same config, the config's own default
    when not given, and help written from the setting's docstring."""
    from flowerpose.cli import build_parser
    from flowerpose.cli.options import configure
    from flowerpose.cli.stages import _scan_stage_base
    from flowerpose.config import setting_doc

    parser = build_parser()

    def configured(*extra):
        return configure(_scan_stage_base(), parser.parse_args(["frames", "s", "--out", "o",
                                                                 *extra])).scan.frames

    by_flag = configured("--count", "7", "--brightness-penalty")
    assert by_flag == configured("--set", "scan.frames.count=7",
                                 "--set", "scan.frames.brightness_penalty=true")
    assert (by_flag.count, by_flag.brightness_penalty) == (7, True)
    # The keys frames took before they were eval's keys work for a version, with a warning.
    assert configured("--set", "count=7", "--set", "brightness_penalty=true") == by_flag
    assert "the setting count is now scan.frames.count" in capsys.readouterr().err
    assert configured() == _scan_stage_base().scan.frames
    with pytest.raises(SystemExit):
        parser.parse_args(["frames", "--help"])
    shown = " ".join(capsys.readouterr().out.split())
    doc = setting_doc(_scan_stage_base(), "scan.frames.crop_px")
    assert doc and doc.rstrip(".") in shown
    crop = _scan_stage_base().scan.frames.crop_px
    assert f"default: {crop}; the same as --set scan.frames.crop_px=" in shown


def test_library_advice_names_settings_and_the_command_line_says_its_flags():
    """A library message quotes the setting or argument to change; each command says the
    flag it has for it, and keeps the quotes where it has none (a --set key)."""
    from flowerpose.cli import build_parser
    from flowerpose.cli.flags import say_flags

    parser = build_parser()
    scan = parser.parse_args(["scan", "--port", "p", "--out", "o"])
    advice = ("load `settings`, or take it as home (`home_here`); frames chosen while "
              "recording (`choose`) need less; `scan.camera.width` sets the size, `cluster.eps` no")
    assert say_flags(parser, scan, advice) == (
        "load --firmware-params, or take it as home (--home-here); frames chosen while "
        "recording (leaving out --keep-all) need less; --width sets the size, `cluster.eps` no")
    pollinate = parser.parse_args(["pollinate", "f.json", "--plant-at", "1,1", "--out", "o"])
    assert say_flags(parser, pollinate, advice).startswith(
        "load --firmware-params, or take it as home (--home-here); frames chosen while "
        "recording (`choose`)")



def _set_example(parser) -> str | None:
    """The KEY=VALUE a command's --set help gives as its example, if any."""
    for action in parser._actions:
        if "--set" in action.option_strings:
            found = re.search(r"e\.g\. (\S+=\S+)", str(action.help))
            return found.group(1) if found else None
    return None


def _subparsers():
    parser = build_parser()
    return next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices


#: The commands whose help examples run in seconds here, in the order one's output feeds
#: the next; each also runs with its --set example added.
QUICK = ("plant", "detect", "pose", "score", "cache")


@pytest.mark.slow
def test_the_quick_help_examples_run_as_written_with_their_set_example(tmp_path, monkeypatch,
                                                                      capsys):
    monkeypatch.chdir(tmp_path)
    commands = _subparsers()
    for name in QUICK:
        for example in _examples(commands[name].epilog or ""):
            if "candidates.ply" in example:  # a detector's candidates the user brings
                (tmp_path / "candidates.ply").write_bytes(
                    (tmp_path / "plant3" / "cloud.ply").read_bytes())
            argv = shlex.split(example)[1:]
            assert main(argv) == 0, (example, capsys.readouterr().err)
            setting = _set_example(commands[name])
            if setting is not None:
                again = argv + ["--set", setting]
                if "--out" in argv:
                    again += ["--overwrite"]
                assert main(again) == 0, (example, setting, capsys.readouterr().err)


def test_every_set_example_names_a_setting_its_command_reads():
    from flowerpose.config import apply_overrides, parse_set_options
    from flowerpose.eval.jobs.config import EvalConfig
    from flowerpose.hardware.flights.pollination_plan import PollinateSettings
    from flowerpose.pipeline.flowers import PipelineConfig

    bases = {"pollinate": PollinateSettings,
             "detect": PipelineConfig, "pose": PipelineConfig, "bench": PipelineConfig}
    checked = []
    for name, parser in _subparsers().items():
        setting = _set_example(parser)
        if setting is not None:
            base = bases.get(name, EvalConfig)()
            # A key the command does not read is refused; one it reads changes its settings.
            assert apply_overrides(base, parse_set_options([setting])) != base, (name, setting)
            checked.append(name)
    assert {"eval", "detect", "pollinate", "sweep"} <= set(checked)


def test_a_report_holding_nan_is_one_line_not_a_nan_in_a_table(tmp_path, capsys):
    from flowerpose.cli import main

    report = tmp_path / "report.json"
    report.write_text('{"run": {}, "summary": {"recall_visible": NaN}, "plants": []}')
    assert main(["results", str(report)]) == 2
    err = capsys.readouterr().err
    assert "report.json" in err and "NaN" in err and err.count("\n") == 1
