"""The stage cache: keys that change when and only when a stage's inputs, settings or code
change; entries made whole or not at all; a scan capture run once for the same plant."""

import dataclasses
import json
import os

import pytest

from flowerpose import cache as cache_module
from flowerpose.cache import StageCache, stage_key
from flowerpose.eval import scan_source
from flowerpose.eval.scan_source import CAPTURE_FILES, ScanSourceConfig, capture_scan_cached
from flowerpose.scan_geometry import ScanPathConfig


def _inputs(tmp_path, text="plant"):
    path = tmp_path / f"{text}.json"
    path.write_text(text)
    return [path]


def test_a_key_changes_with_the_inputs_settings_and_code_and_nothing_else(tmp_path,
                                                                          monkeypatch):
    settings = {"scan": {"frames": 200, "width": 1280}}
    key = stage_key("scan", settings, _inputs(tmp_path))
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    # Same content under another name, the same settings in another order: the same key.
    assert stage_key("scan", {"scan": {"width": 1280, "frames": 200}},
                     _inputs(elsewhere)) == key
    assert stage_key("scan", {"scan": {"frames": 199, "width": 1280}}, _inputs(tmp_path)) != key
    assert stage_key("scan", settings, _inputs(tmp_path, "other plant")) != key
    assert stage_key("rgbd", settings, _inputs(tmp_path)) != key
    monkeypatch.setattr(cache_module, "code_version", lambda: "another version")
    assert stage_key("scan", settings, _inputs(tmp_path)) != key


def test_an_entry_is_whole_or_absent_and_the_first_of_two_fills_wins(tmp_path):
    cache = StageCache(tmp_path / "cache")
    source = tmp_path / "cloud.ply"
    source.write_text("first")
    assert cache.entry("scan", "k") is None
    # A fill killed before its rename leaves a private folder that is never read.
    (tmp_path / "cache" / "scan" / ".k.partial-1-dead").mkdir(parents=True)
    (tmp_path / "cache" / "scan" / "k").mkdir()  # and a folder without entry.json is no entry
    assert cache.entry("scan", "k") is None
    os.rmdir(tmp_path / "cache" / "scan" / "k")
    entry = cache.store("scan", "k", {"r/cloud.ply": source}, {"result": {"n": 1}})
    source.write_text("second")
    again = cache.store("scan", "k", {"r/cloud.ply": source}, {"result": {"n": 2}})
    assert again == entry and (entry / "r" / "cloud.ply").read_text() == "first"
    assert StageCache.about(entry)["result"] == {"n": 1}
    assert sorted(p.name for p in (tmp_path / "cache" / "scan").iterdir()) == [
        ".k.partial-1-dead", "k"]  # nothing of the lost fill is left
    StageCache.restore(entry, {"r/cloud.ply": tmp_path / "out" / "cloud.ply"})
    assert (tmp_path / "out" / "cloud.ply").read_text() == "first"


def test_a_scan_capture_runs_once_for_the_same_plant_and_settings(tmp_path, monkeypatch):
    plant = tmp_path / "plant"
    plant.mkdir()
    for name in ("plant.json", "plant.ply", "plant_labels.npz"):
        (plant / name).write_text(name)
    runs = []

    def capture(plant_dir, config, path):
        runs.append(config)
        names = [n for n in CAPTURE_FILES if n != "frames"] + [
            "frames/frames.json", "frames/frames/frame_000004.jpg", "scan/frames/frame_000004.jpg"]
        for name in names:
            (plant_dir / name).parent.mkdir(parents=True, exist_ok=True)
            (plant_dir / name).write_text(f"{name} of run {len(runs)}")
        return {"recorded": 10, "seconds": {"scan": 5.0, "frames": 1.0, "reconstruct": 9.0}}

    monkeypatch.setattr(scan_source, "capture_scan", capture)
    root, config = tmp_path / "cache", ScanSourceConfig()
    first = capture_scan_cached(plant, config, None, root)
    assert len(runs) == 1 and "cached" not in first
    (plant / "reconstruction" / "cloud.ply").unlink()
    (plant / "frames" / "frames" / "frame_000004.jpg").unlink()
    # Workers change no output: the entry is reused, its files put back.
    again = capture_scan_cached(plant, dataclasses.replace(config, workers=1), None, root)
    assert len(runs) == 1 and again["cached"] and again["recorded"] == 10
    assert again["seconds"] == {"scan": 0.0, "frames": 0.0, "reconstruct": 0.0}
    assert (plant / "reconstruction" / "cloud.ply").read_text() == \
        "reconstruction/cloud.ply of run 1"
    assert (plant / "frames" / "frames" / "frame_000004.jpg").is_file()  # the chosen frames
    entry = next((root / "scan").iterdir())
    assert not (entry / "scan" / "frames").exists()  # not the scan's every frame
    capture_scan_cached(plant, dataclasses.replace(config, frames=100), None, root)
    capture_scan_cached(plant, config, ScanPathConfig(azimuth_step_deg=30.0), root)
    assert len(runs) == 3  # another frame count, another path: scanned again
    (plant / "plant.json").write_text(json.dumps({"another": "plant"}))
    capture_scan_cached(plant, config, None, root)
    assert len(runs) == 4
    capture_scan_cached(plant, config, None, None)  # no cache: always run
    assert len(runs) == 5


def test_no_cache_and_a_cache_folder_contradict_before_any_work(tmp_path, capsys):
    from flowerpose.cli import main

    for command in (["eval", "--source", "oracle"], ["sweep", "--grid", "cluster.eps=0.01"]):
        assert main([*command, "--no-cache", "--cache", str(tmp_path / "cache"), "--out",
                     str(tmp_path / "out")]) == 2
        assert "contradict" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
    with pytest.raises(SystemExit):  # the sweep's sources are the generated plants'
        main(["sweep", "--source", "real", "--grid", "cluster.eps=0.01", "--out", "x"])
