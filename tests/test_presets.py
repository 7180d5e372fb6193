"""Presets are data: assets/presets/NAME.toml over the settings' keys, offered by --preset,
named by suites, and hashed into the reports made with them, so that two reports of one
suite version that ran other preset files are refused side by side."""

import json

import pytest

from flowerpose.cli import main
from flowerpose.config import load_preset, preset_hash, preset_names, profile_hash
from flowerpose.errors import InputError
from flowerpose.eval.jobs.config import eval_config
from flowerpose.sim.world_config import SimConfig, preset, sim_preset


def test_every_shipped_preset_applies_to_the_settings_and_names_its_plants():
    assert {"easy", "realistic", "hard", "field"} <= set(preset_names())
    for name in preset_names():
        settings, description = load_preset(name)
        assert description and set(settings) <= {"sim", "score", "scan", "pipeline"}
        config = eval_config(name)
        assert config.sim == sim_preset(name) and preset(name).name == name
    # The realistic preset is the defaults; the field preset changes every part it says.
    assert sim_preset("realistic") == SimConfig()
    field = eval_config("field")
    assert field.sim.degrade.points_per_flower == (100.0, 1000.0)
    assert field.score.label_error_deg == 5.0 and field.sim.oracle.points == 100_000


def test_an_unknown_preset_is_refused_in_one_line_naming_the_known(tmp_path, capsys):
    with pytest.raises(InputError, match="known: easy, field, hard, realistic"):
        sim_preset("medium")
    with pytest.raises(SystemExit) as exit_:
        main(["plant", "--preset", "medium", "--out", str(tmp_path / "p")])
    assert exit_.value.code == 2
    assert "medium" in capsys.readouterr().err
    assert not (tmp_path / "p").exists()


def test_a_hash_is_of_the_files_content():
    hashes = {name: preset_hash(name) for name in preset_names()}
    assert len(set(hashes.values())) == len(hashes)
    assert all(len(h) == 64 and int(h, 16) >= 0 for h in hashes.values())
    assert preset_hash("field") == preset_hash("field") != profile_hash("upstream")


def _suite_report(path, preset_sha):
    """A minimal eval report of suite field-10 v2 made with a preset file of this hash."""
    report = {"run": {"flowerpose": "0", "commit": None, "date": "d", "command": "flowerpose eval",
                      "assets": {"preset": {"name": "field", "sha256": preset_sha}}},
              "suite": {"name": "field-10", "version": 2, "description": "d"},
              "config": {}, "plants": [],
              "summary": {"found_visible": 1, "visible": 1, "fp": 0,
                          "error_deg": {m: {"mean": 1.0, "median": 1.0} for m in
                                        ("plane", "superellipsoid", "paraboloid")}}}
    path.write_text(json.dumps(report))
    return path


def test_results_refuse_two_reports_of_one_suite_version_with_other_preset_files(tmp_path):
    from flowerpose.eval.studies.results import results_markdown

    one = _suite_report(tmp_path / "one.json", "a" * 64)
    same = _suite_report(tmp_path / "same.json", "a" * 64)
    other = _suite_report(tmp_path / "other.json", "b" * 64)
    assert results_markdown([one, same]).count("field-10 (v2)") == 2
    with pytest.raises(InputError, match="other.json.*hashes differ"):
        results_markdown([one, other])


@pytest.mark.slow
def test_an_eval_report_records_its_preset_and_profile_files(tmp_path):
    out = tmp_path / "run"
    assert main(["eval", "-q", "--source", "oracle", "--preset", "easy", "--plants", "1",
                 "--workers", "1", "--no-cache", "--profile", "upstream",
                 "--out", str(out)]) == 0
    assets = json.loads((out / "report.json").read_text())["run"]["assets"]
    assert assets == {"preset": {"name": "easy", "sha256": preset_hash("easy")},
                      "profile": {"name": "upstream", "sha256": profile_hash("upstream")}}
