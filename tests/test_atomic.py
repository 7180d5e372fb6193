"""Result files are written whole or not at all: a failed write leaves the previous file,
no temporary, and one error naming the file."""

import errno
import os

import numpy as np
import pytest

from flowerpose import atomic
from flowerpose.cloudio import Cloud, read_cloud, write_cloud
from flowerpose.errors import InputError
from flowerpose.jsonio import write_json


def _full_disk(monkeypatch):
    def replace(src, dst):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(atomic.os, "replace", replace)


@pytest.mark.parametrize("name, write", [
    ("report.json", lambda p: write_json(p, {"new": 1})),
    ("report.md", lambda p: atomic.write_text(p, "new")),
    ("views.png", lambda p: atomic.write_image(p, np.zeros((4, 4, 3), np.uint8))),
    ("crop.ply", lambda p: write_cloud(p, Cloud(np.zeros((3, 3)), np.zeros((3, 3), np.uint8)))),
])
def test_a_full_disk_keeps_the_previous_file_and_names_it(tmp_path, monkeypatch, name, write):
    target = tmp_path / name
    target.write_bytes(b"the previous result")
    _full_disk(monkeypatch)
    with pytest.raises(InputError) as caught:
        write(target)
    assert str(target) in str(caught.value) and "cannot write" in str(caught.value)
    assert target.read_bytes() == b"the previous result"
    assert [p.name for p in tmp_path.iterdir()] == [name]


def test_a_writer_that_reports_failure_fails_and_leaves_nothing(tmp_path):
    with pytest.raises(InputError, match="the writer failed"):
        atomic.write_file(tmp_path / "cloud.ply", lambda tmp: False)
    assert list(tmp_path.iterdir()) == []


def test_an_image_opencv_cannot_encode_is_refused_before_writing(tmp_path):
    with pytest.raises(InputError, match="cannot encode"):
        atomic.write_image(tmp_path / "view.nope", np.zeros((4, 4, 3), np.uint8))
    assert list(tmp_path.iterdir()) == []


def test_writers_that_go_by_the_suffix_get_the_right_one(tmp_path):
    cloud = Cloud(np.random.default_rng(0).normal(size=(50, 3)), np.full((50, 3), 200, np.uint8))
    path = write_cloud(tmp_path / "crop.ply", cloud)
    np.testing.assert_allclose(read_cloud(path, units="m").points, cloud.points)
    image = np.dstack([np.full((8, 8), v, np.uint8) for v in (10, 120, 250)])
    import cv2

    atomic.write_image(tmp_path / "view.png", image)
    np.testing.assert_array_equal(cv2.imread(str(tmp_path / "view.png"))[..., ::-1], image)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["crop.ply", "view.png"]


@pytest.fixture
def small_disk(tmp_path):
    """A 1 MB file system, where this machine lets the test make one (root, tmpfs)."""
    import shutil
    import subprocess

    mount = tmp_path / "disk"
    mount.mkdir()
    made = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(mount)],
                          capture_output=True) if shutil.which("mount") else None
    if made is None or made.returncode != 0:
        pytest.skip("cannot make a small file system here (the injected failures cover it)")
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], capture_output=True)


@pytest.mark.slow
def test_a_full_disk_is_one_line_and_keeps_what_was_there(small_disk, tmp_path, capsys):
    from flowerpose.cli import main

    rng = np.random.default_rng(1)
    cloud = write_cloud(tmp_path / "cloud.ply", Cloud(
        rng.uniform(-0.15, 0.15, (20000, 3)) + [1.5, 0.75, 0.2],
        rng.integers(0, 256, (20000, 3)).astype(np.uint8)))
    out = small_disk / "detect"
    assert main(["detect", str(cloud), "--out", str(out), "--set", "grid.pixel_size_m=0.0005"]) \
        == 2
    # One error line (this random cloud's "flowers" also draw envelope warnings).
    err = [line for line in capsys.readouterr().err.strip().splitlines()
           if "outside the operating envelope" not in line]
    assert len(err) == 1 and str(out) in err[0] and "cannot write" in err[0]
    assert not list(out.rglob("*.tmp*"))  # no half-written file left to trust
    report = small_disk / "report.json"
    write_json(report, {"kept": True})
    try:  # fill what is left (the detection may have left nothing)
        with open(small_disk / "fill", "wb") as handle:
            while True:
                handle.write(b"\0" * 65536)
                handle.flush()
    except OSError:
        pass
    with pytest.raises(InputError, match="cannot write"):
        write_json(report, {"kept": False, "padding": "x" * 200_000})
    assert report.read_text() == '{\n "kept": true\n}'
