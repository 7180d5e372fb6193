"""One config tree: a setting has one dotted key in every command, old keys keep working a
version with a warning, a command refuses keys it does not read, and a section's check
names the full key."""

import argparse

import pytest

from flowerpose.cli import build_parser, main
from flowerpose.cli.options import configure


def _configured(base, *argv):
    return configure(base, build_parser().parse_args(list(argv)))


def test_an_evals_renamed_scan_keys_reach_the_embedded_sections_with_a_warning(capsys):
    from flowerpose.eval.jobs.config import EvalConfig

    old = _configured(EvalConfig(), "eval", "--set", "scan.frame_rate_hz=0.1",
                      "--set", "scan.sensor.gain=1.2", "--set", "scan.frames=50",
                      "--set", "scan.width=640")
    err = capsys.readouterr().err
    new = _configured(EvalConfig(), "eval", "--set", "scan.camera.frame_rate_hz=0.1",
                      "--set", "scan.camera.sensor.gain=1.2", "--set", "scan.frames.count=50",
                      "--set", "scan.camera.width=640")
    assert old == new and new.scan.camera.sensor.gain == 1.2 and new.scan.frames.count == 50
    assert new.scan.camera.width == 640
    assert "the setting scan.frames is now scan.frames.count" in err
    assert "the setting scan.width is now scan.camera.width" in err
    assert "the setting scan.sensor.gain is now scan.camera.sensor.gain" in err
    assert capsys.readouterr().err == ""  # the new keys: no warning


def test_pollinate_takes_eval_keys_and_the_runs_colour_model(capsys):
    from flowerpose.cli.field import _pollinate_base

    argv = ["pollinate", "f.json", "--plant-at", "1.5,0.75", "--out", "o"]
    settings = _configured(_pollinate_base(), *argv, "--set", "pollinate.standoff_m=0.04",
                           "--set", "colour.petal_min_value=0.5")
    assert settings.pollinate.standoff_m == 0.04 and settings.colour.petal_min_value == 0.5
    assert capsys.readouterr().err == ""
    assert _configured(_pollinate_base(), *argv, "--set", "standoff_m=0.04") .pollinate == \
        settings.pollinate
    assert "the setting standoff_m is now pollinate.standoff_m" in capsys.readouterr().err


@pytest.mark.parametrize("argv, words", [
    (["pose", "crop.ply", "--set", "grid.views=6"], "pose reads colour.*, cluster.*, pose.*"),
    (["detect", "c.ply", "--candidates", "--out", "{tmp}/d", "--set", "ground.plane_distance_m=1"],
     "detect --candidates reads colour.*, outliers.*, cluster.*, pose.*"),
    (["frames", "s", "--out", "{tmp}/f", "--set", "cluster.eps=0.1"], "frames reads scan.frames.*"),
    (["eval", "--set", "scan.camera.frame_rate_hz=-1", "--out", "{tmp}/e"],
     "scan.camera.frame_rate_hz: must be positive"),
    (["pollinate", "f.json", "--plant-at", "1.5,0.75", "--out", "{tmp}/p",
      "--set", "pollinate.cone_deg=95"], "pollinate.cone_deg: must be 0 or more, below 90"),
])
def test_a_key_a_command_does_not_read_or_a_bad_value_is_one_line_naming_the_full_key(
        argv, words, tmp_path, capsys):
    assert main([a.replace("{tmp}", str(tmp_path)) for a in argv]) == 2
    err = capsys.readouterr().err
    assert words in err and len(err.strip().splitlines()) == 1
    assert not any(tmp_path.iterdir())


def test_sweep_grids_tune_sets_and_tune_spaces_take_renamed_keys_too(tmp_path, capsys):
    from flowerpose.cli.options import setting_layers
    from flowerpose.eval.jobs.config import EvalConfig
    from flowerpose.eval.studies.sweep import parse_grid
    from flowerpose.eval.studies.tune_space import read_space

    assert parse_grid(["scan.frames=40,50"], EvalConfig()) == [("scan.frames.count",
                                                                 ["40", "50"])]
    given = argparse.Namespace(profile=None, config=None, set=["scan.frames=50"])
    assert setting_layers(EvalConfig(), given) == ({"scan.frames.count": "50"},)
    space = tmp_path / "space.toml"
    space.write_text("[scan.frames]\nlow = 40\nhigh = 60\nint = true\n")
    assert [p.key for p in read_space(space, EvalConfig())] == ["scan.frames.count"]
    assert capsys.readouterr().err.count("the setting scan.frames is now scan.frames.count") == 3
