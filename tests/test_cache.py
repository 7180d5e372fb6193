"""The stage cache: keys that change when and only when a stage's inputs, settings or code
change; entries made whole or not at all; a scan capture run once for the same plant."""

import dataclasses
import hashlib
import json
import os

import pytest

from flowerpose import cache as cache_module
from flowerpose.cache import StageCache, stage_key
from flowerpose.eval.capture import photogrammetry, scan_source
from flowerpose.eval.capture.photogrammetry import RECONSTRUCTION_FILES
from flowerpose.eval.capture.scan_source import (
    SCAN_FILES,
    ScanSourceConfig,
    capture_scan_cached,
)
from flowerpose.eval.jobs.plant_set import PlantSet
from flowerpose.eval.pool import Execution
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
    monkeypatch.setattr(cache_module, "code_version", lambda roots=None: "another version")
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


def _fake_capture(monkeypatch):
    """The capture's steps as stand-ins that write their files and count their runs."""
    runs = {"scan": [], "frames": [], "reconstruct": []}

    def film(plant_dir, config, path):
        runs["scan"].append(config)
        for name in [*SCAN_FILES, "scan/frames/frame_000004.jpg"]:
            (plant_dir / name).parent.mkdir(parents=True, exist_ok=True)
            (plant_dir / name).write_text(f"{name} of scan {len(runs['scan'])}")
        return {"recorded": 10, "seconds": {"scan": 5.0}}

    def choose(folder, frames):
        runs["frames"].append(frames)
        assert (folder / "scan" / "frames" / "frame_000004.jpg").is_file()  # a recording
        for name in ("frames/frames.json", "frames/frames/frame_000004.jpg"):
            (folder / name).parent.mkdir(parents=True, exist_ok=True)
            (folder / name).write_text(f"{name} of choice {len(runs['frames'])}")
        return {"frames": 1}

    def reconstruct(folder, config):
        runs["reconstruct"].append(config)
        for name in RECONSTRUCTION_FILES:
            (folder / name).parent.mkdir(parents=True, exist_ok=True)
            (folder / name).write_text(f"{name} of reconstruction {len(runs['reconstruct'])}")
        return {"images_registered": 1, "images_used": 1, "points": 7, "alignment_rms_m": 0.0}

    monkeypatch.setattr(scan_source, "film_plant", film)
    monkeypatch.setattr(photogrammetry, "choose_frames", choose)
    monkeypatch.setattr(photogrammetry, "reconstruct_frames", reconstruct)
    monkeypatch.setattr(scan_source, "cloud_quality", lambda plant_dir, built: {})
    return runs


def _plant(tmp_path):
    plant = tmp_path / "plant"
    plant.mkdir()
    for name in ("plant.json", "plant.ply", "plant_labels.npz"):
        (plant / name).write_text(name)
    return plant


def test_a_scan_capture_runs_once_for_the_same_plant_and_settings(tmp_path, monkeypatch):
    runs = _fake_capture(monkeypatch)
    plant = _plant(tmp_path)
    root, config = tmp_path / "cache", ScanSourceConfig()
    first = capture_scan_cached(plant, config, None, root)
    assert (len(runs["scan"]), len(runs["reconstruct"])) == (1, 1) and first["cached"] == []
    (plant / "reconstruction" / "cloud.ply").unlink()
    (plant / "frames" / "frames" / "frame_000004.jpg").unlink()
    # Workers change no output: the entries are reused, their files put back.
    again = capture_scan_cached(plant, dataclasses.replace(
        config, camera=dataclasses.replace(config.camera, workers=1)), None, root)
    assert (len(runs["scan"]), len(runs["reconstruct"])) == (1, 1)
    assert again["cached"] == ["scan", "frames", "reconstruct"] and again["recorded"] == 10
    assert again["seconds"] == {"scan": 0.0, "frames": 0.0, "reconstruct": 0.0}
    assert (plant / "reconstruction" / "cloud.ply").read_text() == \
        "reconstruction/cloud.ply of reconstruction 1"
    assert (plant / "frames" / "frames" / "frame_000004.jpg").is_file()  # the chosen frames
    entry = next((root / "scan").iterdir())
    assert not (entry / "scan" / "frames").exists()  # not the scan's every frame
    capture_scan_cached(plant, dataclasses.replace(
        config, frames=dataclasses.replace(config.frames, count=100)), None, root)
    capture_scan_cached(plant, config, ScanPathConfig(azimuth_step_deg=30.0), root)
    # Another frame count: the cache keeps no recording, so the plant is filmed again to
    # choose from (the stand-in refuses to choose without one); another path: scanned again.
    assert (len(runs["scan"]), len(runs["frames"])) == (3, 3)
    (plant / "plant.json").write_text(json.dumps({"another": "plant"}))
    capture_scan_cached(plant, config, None, root)
    assert len(runs["scan"]) == 4
    capture_scan_cached(plant, config, None, None)  # no cache: always run
    assert (len(runs["scan"]), len(runs["reconstruct"])) == (5, 5)


def test_other_reconstruction_settings_reuse_the_scan_and_the_frames(tmp_path, monkeypatch):
    runs = _fake_capture(monkeypatch)
    plant = _plant(tmp_path)
    root, config = tmp_path / "cache", ScanSourceConfig()
    capture_scan_cached(plant, config, None, root)
    other = dataclasses.replace(config, reconstruct=dataclasses.replace(
        config.reconstruct, dense_poses="recorded"))
    result = capture_scan_cached(plant, other, None, root)
    assert (len(runs["scan"]), len(runs["reconstruct"])) == (1, 2)
    assert result["cached"] == ["scan", "frames"]
    assert result["seconds"]["scan"] == result["seconds"]["frames"] == 0.0
    assert result["seconds"]["reconstruct"] > 0
    # Each reconstruction keeps its own entry, tied to the scan's.
    assert len(list((root / "reconstruct").iterdir())) == 2
    assert capture_scan_cached(plant, config, None, root)["cached"] == [
        "scan", "frames", "reconstruct"]
    assert (plant / "reconstruction" / "cloud.ply").read_text() == \
        "reconstruction/cloud.ply of reconstruction 1"


def _key(name: str) -> str:
    """A stage key as the cache makes them: a SHA-256 in hex."""
    return hashlib.sha256(name.encode()).hexdigest()


def test_prune_removes_the_least_recently_used_entries_and_nothing_else(tmp_path):
    cache = StageCache(tmp_path / "cache")
    source = tmp_path / "payload"
    source.write_bytes(b"x" * 1000)
    keys = {name: _key(name) for name in ("old", "middle", "new")}
    for key in keys.values():
        cache.store("scan", key, {"cloud.ply": source}, {"result": {}})
    stamp = 946_684_800  # 2000-01-01, long ago
    for age, name in enumerate(("new", "middle", "old")):
        os.utime(tmp_path / "cache" / "scan" / keys[name] / "entry.json",
                 (stamp - age, stamp - age))
    foreign = tmp_path / "cache" / "notes.txt"  # not the cache's: never removed
    foreign.write_text("mine")
    (tmp_path / "cache" / "scan" / "nokey").mkdir()  # no entry.json: not an entry
    live = tmp_path / "cache" / "scan" / f".{keys['new']}.partial-1-0000live"  # running
    live.mkdir()
    (live / ".flowerpose-fill").write_text("")
    sizes = {e.folder.name: e.size for e in cache.entries()}
    names = {key: name for name, key in keys.items()}
    assert [names[e.folder.name] for e in cache.entries()] == ["old", "middle", "new"]
    assert cache.prune(sizes[keys["new"]] + sizes[keys["middle"]]) and \
        [names[e.folder.name] for e in cache.entries()] == ["middle", "new"]
    # A hit is a use: the restored entry is kept over one used earlier.
    os.utime(tmp_path / "cache" / "scan" / keys["middle"] / "entry.json",
             (stamp + 5, stamp + 5))
    assert [names[e.folder.name] for e in cache.prune(sizes[keys["middle"]])] == ["new"]
    assert [names[e.folder.name] for e in cache.prune(0)] == ["middle"]
    assert foreign.read_text() == "mine" and (tmp_path / "cache" / "scan" / "nokey").is_dir()
    assert live.is_dir()
    os.utime(live, (stamp, stamp))  # a day old: its fill was killed
    cache.prune(0)
    assert not live.exists()


def test_a_folder_the_cache_did_not_make_is_never_pruned(tmp_path, capsys):
    from flowerpose.cli import main

    mine = tmp_path / "mydata"
    (mine / "survey" / "plot-7").mkdir(parents=True)
    (mine / "survey" / "plot-7" / "entry.json").write_text('{"plot": 7}')
    (mine / "survey" / ".old.pruned-1").mkdir()
    (mine / "survey" / ".old.pruned-1" / "keep.txt").write_text("mine")
    before = sorted(p.relative_to(mine).as_posix() for p in mine.rglob("*"))
    assert main(["cache", "--cache", str(mine), "--clear"]) == 2
    assert "not a flowerpose stage cache" in capsys.readouterr().err
    assert sorted(p.relative_to(mine).as_posix() for p in mine.rglob("*")) == before
    # Inside the cache, a user's entry.json that names no stage and key of its own is not
    # an entry, and a pruned-looking folder not named after a key is not the cache's.
    cache = StageCache(tmp_path / "cache")
    payload = tmp_path / "payload"
    payload.write_bytes(b"x")
    cache.store("scan", _key("a"), {"cloud.ply": payload}, {"result": {}})
    assert (tmp_path / "cache" / "CACHEDIR.TAG").read_text().startswith(
        "Signature: 8a477f597d28d172789f06886806bc55")
    (tmp_path / "cache" / "scan" / "notes").mkdir()
    (tmp_path / "cache" / "scan" / "notes" / "entry.json").write_text('{"stage": "scan"}')
    (tmp_path / "cache" / "scan" / ".mine.pruned-2").mkdir()
    assert [e.folder.name for e in cache.prune(0)] == [_key("a")]
    assert (tmp_path / "cache" / "scan" / "notes" / "entry.json").is_file()
    assert (tmp_path / "cache" / "scan" / ".mine.pruned-2").is_dir()


def test_a_cache_hit_is_a_use(tmp_path):
    cache = StageCache(tmp_path / "cache")
    plant = _plant(tmp_path)
    (plant / "out.txt").write_text("made")
    cache.run("plant", {}, [plant / "plant.json"], plant, ["out.txt"], lambda: {})
    about = next((tmp_path / "cache" / "plant").iterdir()) / "entry.json"
    os.utime(about, (946_684_800, 946_684_800))  # 2000-01-01
    _, cached, _ = cache.run("plant", {}, [plant / "plant.json"], plant, ["out.txt"],
                             lambda: pytest.fail("computed again"))
    assert cached and about.stat().st_mtime > 946_684_800


def test_no_cache_and_a_cache_folder_contradict_before_any_work(tmp_path, capsys):
    from flowerpose.cli import main

    for command in (["eval", "--source", "oracle"], ["sweep", "--grid", "cluster.eps=0.01"]):
        assert main([*command, "--no-cache", "--cache", str(tmp_path / "cache"), "--out",
                     str(tmp_path / "out")]) == 2
        assert "contradict" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
    # A sweep on real plants needs their folders, said before any work.
    assert main(["sweep", "--source", "real", "--grid", "cluster.eps=0.01", "--out",
                 str(tmp_path / "out")]) == 2
    assert "needs at least one labelled plant folder" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_the_cache_command_says_what_is_held_and_prunes_only_entries(tmp_path, capsys,
                                                                    monkeypatch):
    from flowerpose.cli import main

    cache = StageCache(tmp_path / "cache")
    payload = tmp_path / "payload"
    payload.write_bytes(b"x" * 2_000_000)
    for stage, key in (("scan", "a"), ("scan", "b"), ("reconstruct", "c")):
        cache.store(stage, _key(key), {"cloud.ply": payload}, {"result": {}})
    (tmp_path / "cache" / "notes.txt").write_text("mine")
    assert main(["cache", "--cache", str(tmp_path / "cache")]) == 0
    shown = capsys.readouterr().out
    assert "| scan " in shown and "| reconstruct " in shown and "| total " in shown
    assert "6.0 MB" in shown
    assert main(["cache", "--cache", str(tmp_path / "cache"), "--max-size", "0.003"]) == 0
    assert "removed 2 entries (4.0 MB)" in capsys.readouterr().out
    assert main(["cache", "--cache", str(tmp_path / "cache"), "--clear"]) == 0
    assert cache.entries() == [] and (tmp_path / "cache" / "notes.txt").read_text() == "mine"
    monkeypatch.setenv("FLOWERPOSE_CACHE_MAX_GB", "lots")
    assert main(["eval", "--source", "oracle", "--out", str(tmp_path / "out")]) == 2
    assert "FLOWERPOSE_CACHE_MAX_GB: must be a size in GB" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_an_eval_again_takes_its_plants_detections_and_scores_from_the_cache(tmp_path):
    from flowerpose.eval.jobs.config import EvalConfig
    from flowerpose.eval.jobs.eval_run import EvalRun
    from flowerpose.eval.studies.eval_recipe import run_eval

    root, config = tmp_path / "cache", EvalConfig()

    def run(out, cfg=config):
        return run_eval(cfg, EvalRun(PlantSet("oracle", plants=1, seed=1)), tmp_path / out,
                        Execution(1, root))

    first, again = run("a"), run("b")
    assert again["summary"] == first["summary"] and first["timing_s"]["cluster"] > 0
    assert again["timing_s"]["plant"] == again["timing_s"]["cluster"] == 0.0
    assert (tmp_path / "b" / "plants" / "seed-1" / "flowers.json").read_bytes() == \
        (tmp_path / "a" / "plants" / "seed-1" / "flowers.json").read_bytes()
    # Another pipeline setting: the same plant, detected and scored afresh.
    other = run("c", dataclasses.replace(config, cluster=dataclasses.replace(
        config.cluster, eps=0.008)))
    assert other["timing_s"]["plant"] == 0.0 and other["timing_s"]["cluster"] > 0
    assert len(list((root / "detect").iterdir())) == 2
    assert len(list((root / "plant").iterdir())) == 1


def test_a_size_past_any_disk_is_no_limit_and_a_data_folder_is_no_cache(tmp_path, capsys):
    from flowerpose.cli import main

    assert main(["cache", "--cache", str(tmp_path / "cache"), "--max-size", "1e300"]) == 0
    capsys.readouterr()
    mine = tmp_path / "mydata"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine")
    assert main(["eval", "--source", "oracle", "--cache", str(mine), "--out",
                 str(tmp_path / "out")]) == 2
    assert "not a flowerpose stage cache" in capsys.readouterr().err
    assert [p.name for p in mine.iterdir()] == ["notes.txt"]
