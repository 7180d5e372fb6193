"""The one stopwatch: steps add up by name, laps follow each other, the total covers all."""

import subprocess
import sys
from pathlib import Path

import pytest

from flowerpose import stopwatch
from flowerpose.stopwatch import Stopwatch


@pytest.fixture
def clock(monkeypatch):
    """perf_counter as a hand-turned clock: each test says when time passes."""
    now = [100.0]
    monkeypatch.setattr(stopwatch.time, "perf_counter", lambda: now[0])
    return now


def test_steps_add_up_by_name_and_the_total_covers_them(clock):
    watch = Stopwatch()
    with watch.step("triangulation"):
        clock[0] += 2.0
    clock[0] += 0.5  # between steps: in the total only
    with watch.step("bundle_adjustment"):
        clock[0] += 1.0
    with watch.step("triangulation"):
        clock[0] += 0.25
    assert watch.report() == {"triangulation": 2.25, "bundle_adjustment": 1.0, "total": 3.75}
    assert watch.report(total=None) == {"triangulation": 2.25, "bundle_adjustment": 1.0}


def test_a_step_that_raises_is_still_timed(clock):
    watch = Stopwatch()
    with pytest.raises(RuntimeError), watch.step("mapping"):
        clock[0] += 3.0
        raise RuntimeError
    assert watch.seconds == {"mapping": 3.0}


def test_laps_follow_each_other_and_round_on_report(clock):
    watch = Stopwatch()
    clock[0] += 1.23456
    watch.lap("sparse")
    clock[0] += 2.0
    watch.lap("dense")
    assert watch.report(digits=3) == {"sparse": 1.235, "dense": 2.0, "total": 3.235}
    assert watch.elapsed() == pytest.approx(3.23456)


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs Linux's /proc")
def test_the_process_age_counts_from_the_launch():
    # A process that waited 0.3 s before asking is at least that old (the interpreter's
    # start and imports come on top): a command's wall time starts where the user's wait did.
    script = ("import time; time.sleep(0.3); "
              "from flowerpose.stopwatch import process_age; print(process_age())")
    age = float(subprocess.run([sys.executable, "-c", script], capture_output=True,
                               text=True, check=True).stdout)
    assert age >= 0.3
