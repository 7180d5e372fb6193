"""`flowerpose data`: the authors' real plant fetched from a local mirror (never the network),
checked by SHA-256, whole or not at all."""

import hashlib
import shutil
from pathlib import Path

import pytest

from flowerpose import data
from flowerpose.cli import main

SHARED_REAL = Path(__file__).resolve().parents[1].parent / "shared" / "real"
SHARED_PHOTOS = SHARED_REAL.parent / "real-photos" / "romi-arabidopsis"


def _mirror(root: Path, published: data.PublishedPlant, sources: dict[str, Path]) -> Path:
    """A copy of the authors' repository holding the plant's files at their paths there."""
    for item in published.files:
        target = root / item.upstream
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(sources[item.local], target)
    return root


@pytest.fixture
def tiny(tmp_path, monkeypatch):
    """A published plant of two small files, and its mirror."""
    files = {"labels.json": b'{"flowers": []}', "candidates/pcd_0.ply": b"ply\n"}
    made = {}
    for local, content in files.items():
        made[local] = tmp_path / "src" / local
        made[local].parent.mkdir(parents=True, exist_ok=True)
        made[local].write_bytes(content)
    published = data.PublishedPlant("tiny", "two files", tuple(
        data.PublishedFile(f"repo/{local}", local, hashlib.sha256(content).hexdigest())
        for local, content in files.items()), {"truth_scale": 1})
    monkeypatch.setitem(data.PLANTS, "tiny", published)
    return published, _mirror(tmp_path / "mirror", published, made)


def test_a_fetch_from_a_mirror_is_whole_checked_and_kept(tmp_path, tiny):
    published, mirror = tiny
    folder, files = data.fetch("tiny", tmp_path / "plant", str(mirror))
    assert {p.relative_to(folder).as_posix() for p, _, _ in files} == {
        "labels.json", "candidates/pcd_0.ply"}
    assert (folder / "source.json").is_file()
    # Fetched again: checked and kept, nothing downloaded.
    assert data.fetch("tiny", folder, str(tmp_path / "nowhere"))[0] == folder


def test_a_corrupted_or_interrupted_fetch_leaves_nothing(tmp_path, tiny, monkeypatch, capsys):
    published, mirror = tiny
    (mirror / published.files[1].upstream).write_bytes(b"ply\nchanged\n")
    assert main(["data", "fetch", "tiny", "--to", str(tmp_path / "plant"), "--mirror",
                 str(mirror)]) == 2
    assert "does not match its published checksum" in capsys.readouterr().err
    assert list(tmp_path.glob("plant*")) == [] and list(tmp_path.glob(".plant*")) == []

    def cut(*args):
        raise KeyboardInterrupt

    monkeypatch.setattr(data, "_download", cut)
    with pytest.raises(KeyboardInterrupt):
        data.fetch("tiny", tmp_path / "plant", str(mirror))
    assert list(tmp_path.glob("*plant*")) == []


@pytest.mark.skipif(not SHARED_REAL.is_dir(), reason="the authors' plant is in ../shared/real, "
                    "beside the repository (CI has it); not here")
@pytest.mark.slow
def test_the_papers_plant_from_a_mirror_is_a_real_plant_folder_eval_reads(tmp_path, capsys):
    published = data.PLANTS["paper-plant-3"]
    sources = {item.local: SHARED_REAL / "paper-plant-3" / item.local for item in published.files}
    sources["LICENSE-flowerPose.txt"] = SHARED_REAL / "LICENSE-flowerPose.txt"
    mirror = _mirror(tmp_path / "mirror", published, sources)
    assert main(["data", "fetch", "paper-plant-3", "--to", str(tmp_path / "p3"), "--mirror",
                 str(mirror)]) == 0
    printed = capsys.readouterr().out.splitlines()
    assert printed[-1] == str(tmp_path / "p3") and len(printed) == len(published.files) + 1
    assert main(["eval", "--source", "real", str(tmp_path / "p3"), "--out",
                 str(tmp_path / "eval")]) == 0
    assert "recall" in capsys.readouterr().out


@pytest.mark.skipif(not SHARED_PHOTOS.is_dir(), reason="the real photographs are in "
                    "../shared/real-photos, beside the repository; not here")
def test_the_photo_set_from_a_mirror_gets_its_poses_and_calibrated_model(tmp_path, capsys):
    import cv2  # noqa: F401  # before pycolmap (pipeline/sfm.py)
    import numpy as np
    import pycolmap

    published = data.PLANTS["romi-arabidopsis"]
    sources = {item.local: SHARED_PHOTOS / item.local for item in published.files}
    mirror = _mirror(tmp_path / "mirror", published, sources)
    assert main(["data", "fetch", "romi-arabidopsis", "--to", str(tmp_path / "romi"),
                 "--mirror", str(mirror)]) == 0
    folder = tmp_path / "romi"
    assert len(list((folder / "images").glob("*.jpg"))) == 60
    # The calibrated model written from the metadata is the shared copy's, pose for pose.
    ours = pycolmap.Reconstruction(str(folder / "colmap"))
    theirs = pycolmap.Reconstruction(str(SHARED_PHOTOS / "colmap"))
    by_name = {image.name: image for image in theirs.images.values()}
    assert len(ours.images) == 60
    for image in ours.images.values():
        assert np.allclose(image.projection_center(),
                           by_name[image.name].projection_center(), atol=1e-6)
    assert np.allclose(ours.cameras[1].params, theirs.cameras[1].params)
    rows = (folder / "poses.csv").read_text().splitlines()
    assert rows[0] == "file,x,y,z,pan,tilt" and len(rows) == 61
    assert rows[1].startswith("00000_rgb.jpg,75.0,375.0,80.0,0.0,")  # pan 270: along +x
