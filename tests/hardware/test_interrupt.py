"""A real simulated scan in a subprocess, stopped by SIGINT, SIGTERM and SIGKILL: the scan
folder stays consistent every time (rows once each, after their frames), no renderer
outlives it, and the scan resumes to completion."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from flowerpose.jsonio import read_json
from flowerpose.scanio import frame_files, read_trajectory
from flowerpose.sim.bundle import make_plant

#: Seconds without progress after which a run the test waits on counts as hung: not a speed
#: limit (the machine may be slow and busy), only so a hang fails instead of blocking CI.
HANG_S = 600


@pytest.fixture(scope="module")
def plant_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("plant")
    make_plant(0, "easy", points=2000, out_dir=out)
    return out


def _interruptible() -> None:
    """Ctrl-C as a terminal gives it: a shell's background job starts with SIGINT ignored,
    and Python keeps that, so the signal the test sends would never arrive."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _scan(plant_dir: Path, out: Path) -> subprocess.Popen:
    command = [sys.executable, "-m", "flowerpose", "scan", "--sim", "--plant",
               str(plant_dir), "--out", str(out), "--width", "96", "--height", "54",
               "--frame-rate", "0.2", "--workers", "1", "--no-preview"]
    return subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"},
                            preexec_fn=_interruptible)


def _rows(out: Path) -> int:
    try:
        return max(0, len((out / "trajectory.csv").read_text().splitlines()) - 1)
    except FileNotFoundError:
        return 0


def _children(pid: int) -> list[int]:
    found = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        text = (task / "children").read_text().split() if (task / "children").exists() else []
        found += [int(c) for c in text]
    return found


def _alive(pid: int) -> bool:
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except FileNotFoundError:
        return False
    return "State:\tZ" not in status


def _consistent(out: Path) -> int:
    trajectory = read_trajectory(out / "trajectory.csv")
    assert np.all(np.diff(trajectory.frame) > 0), "each frame's row once, in order"
    on_disk = {int(p.stem.split("_")[-1]) for p in frame_files(out)}
    assert set(trajectory.frame) <= on_disk, "a row only after its frame"
    manifest = read_json(out / "scan.json")
    assert manifest["completed"] <= manifest["waypoints"]
    return len(trajectory)


def _stop(process: subprocess.Popen, out: Path, how: signal.Signals,
          after_rows: int) -> tuple[int, str, list[int]]:
    rows, progress = _rows(out), time.monotonic()
    while rows < after_rows:
        assert process.poll() is None, process.communicate()
        assert time.monotonic() - progress < HANG_S, f"the scan recorded nothing in {HANG_S} s"
        time.sleep(0.2)
        if _rows(out) > rows:
            rows, progress = _rows(out), time.monotonic()
    workers = _children(process.pid)
    process.send_signal(how)
    _, err = process.communicate(timeout=HANG_S)
    return process.returncode, err, workers


def _gone(pids: list[int], what: str) -> None:
    """Wait for the processes to end (a hang after HANG_S fails, naming `what`)."""
    since = time.monotonic()
    while any(_alive(p) for p in pids):
        assert time.monotonic() - since < HANG_S, f"{what} outlived its parent"
        time.sleep(0.1)


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="needs Linux's /proc")
def test_signals_leave_a_consistent_scan_that_resumes(plant_dir, tmp_path):
    out = tmp_path / "scan"
    code, err, _ = _stop(_scan(plant_dir, out), out, signal.SIGINT, 15)
    assert code == 130 and err.strip().splitlines()[-1] == "flowerpose: interrupted"
    first = _consistent(out)
    assert read_json(out / "scan.json")["status"] == "interrupted"

    code, err, _ = _stop(_scan(plant_dir, out), out, signal.SIGTERM, first + 10)
    assert code == 143 and err.strip().splitlines()[-1] == "flowerpose: terminated"
    second = _consistent(out)
    assert second > first

    code, _, workers = _stop(_scan(plant_dir, out), out, signal.SIGKILL, second + 10)
    assert code == -signal.SIGKILL and workers
    _gone(workers, "a renderer")  # the renderers die with the scan
    third = _consistent(out)
    assert third > second

    finish = _scan(plant_dir, out)
    _, err = finish.communicate(timeout=HANG_S)
    assert finish.returncode == 0, err
    assert read_json(out / "scan.json")["status"] == "complete"
    assert _consistent(out) > third


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="needs Linux's /proc")
@pytest.mark.parametrize("how", [signal.SIGINT, signal.SIGTERM])
def test_an_eval_stopped_from_the_terminal_says_one_line_and_leaves_no_worker(tmp_path, how):
    # The whole process group gets the signal, as from a terminal's Ctrl-C. An empty stage
    # cache of its own: the plants are made, so the eval is still running when it comes.
    process = subprocess.Popen(
        [sys.executable, "-m", "flowerpose", "eval", "--source", "oracle", "--plants", "6",
         "--workers", "2", "--out", str(tmp_path / "run")], stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True, start_new_session=True, preexec_fn=_interruptible,
        env={**os.environ, "FLOWERPOSE_CACHE": str(tmp_path / "cache")})
    since = time.monotonic()
    while not list((tmp_path / "run" / "plants").glob("seed-*/cloud.ply")):
        assert process.poll() is None and time.monotonic() - since < HANG_S
        time.sleep(0.1)
    workers = _children(process.pid)
    os.killpg(process.pid, how)
    _, err = process.communicate(timeout=HANG_S)
    assert process.returncode == {signal.SIGINT: 130, signal.SIGTERM: 143}[how]
    assert err.strip().splitlines()[-1] in ("flowerpose: interrupted", "flowerpose: terminated")
    assert "Traceback" not in err
    _gone(workers, "a worker of the stopped eval")
