"""A run's config.toml, written beside its report, runs it again: the report's config
(source, folders, plants, seed and every section) is taken as it is by eval --config."""

import json

import pytest
from realplants import write_real_plant

from flowerpose.cli import main
from flowerpose.config import load_toml, settings_toml


def _report(folder):
    return json.loads((folder / "report.json").read_text())


def test_a_runs_config_toml_runs_it_again(tmp_path):
    plant = write_real_plant(tmp_path / "plant", "candidates")
    first, again = tmp_path / "first", tmp_path / "again"
    assert main(["eval", "-q", "--source", "real", str(plant), "--out", str(first),
                 "--set", "pose.offset_clip=0.2", "--set", "cluster.min_coverage=0.3"]) == 0
    written = load_toml(first / "config.toml")
    assert written["source"] == "real" and written["pose"]["offset_clip"] == 0.2
    assert main(["eval", "-q", "--config", str(first / "config.toml"), "--out",
                 str(again)]) == 0
    assert _report(again)["config"] == _report(first)["config"]
    assert _report(again)["summary"] == _report(first)["summary"]


def test_the_command_line_wins_over_a_configs_run_keys(tmp_path, capsys):
    config = tmp_path / "run.toml"
    config.write_text('source = "oracle"\nplants = 0\n')
    assert main(["eval", "--config", str(config), "--out", str(tmp_path / "e")]) == 2
    assert "run.toml: plants: must be a whole number, at least 1, got 0" in (
        capsys.readouterr().err)
    config.write_text('source = "oracle"\nplants = 1\n')
    plant = write_real_plant(tmp_path / "plant", "candidates")
    assert main(["eval", "-q", "--source", "real", str(plant), "--config", str(config),
                 "--out", str(tmp_path / "e")]) == 0
    assert _report(tmp_path / "e")["config"]["source"] == "real"


@pytest.mark.parametrize("value", [None, True, 3, 0.25, "a \"quoted\" word", [1.0, 2.0],
                                   [{"folder": "x", "files": 2}]])
def test_settings_toml_reads_back_what_it_wrote(tmp_path, value):
    path = tmp_path / "c.toml"
    path.write_text(settings_toml({"top": value, "a": {"b": {"c": value}}}, "a\nheader"))
    read = load_toml(path)
    expected = "none" if value is None else value
    assert read["top"] == expected and read["a"]["b"]["c"] == expected
