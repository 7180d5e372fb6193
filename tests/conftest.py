"""Fixtures shared across the test packages, and the markers: `slow` (a test of a second
or more: `make test-fast` leaves them out) and `hardware` (every test of tests/hardware)."""

from __future__ import annotations

from pathlib import Path

import pytest

from flowerpose.sim.bundle import PlantBundle, make_plant

HARDWARE = Path(__file__).parent / "hardware"


#: The test files that take longest (seconds of a 2-core run alone, 2026-12-07: the bed runs
#: 217, the real photographs 128; in a full run, pollination 90, the README 85, the board
#: 100, ...), run first: `make test` hands whole files to its workers in collection order,
#: and the longest first makes them end together.
LONGEST_FIRST = ("eval/test_bed_run.py", "pipeline/test_real_photos.py",
                 "eval/test_pollination.py", "test_readme.py", "pipeline/test_board.py",
                 "eval/test_scan_source.py", "eval/test_ray.py", "eval/test_bed_serial.py",
                 "eval/test_html_report.py", "hardware/test_cloud_broker.py",
                 "hardware/test_interrupt.py", "hardware/test_sim_bot.py")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if HARDWARE in Path(item.fspath).parents:
            item.add_marker(pytest.mark.hardware)
    root = Path(__file__).parent
    rank = {name: k for k, name in enumerate(LONGEST_FIRST)}

    def position(item: pytest.Item) -> int:
        return rank.get(Path(item.fspath).relative_to(root).as_posix(), len(rank))

    items.sort(key=position)  # stable: the rest keep their order


@pytest.fixture(scope="session")
def plant0(tmp_path_factory) -> tuple[PlantBundle, Path]:
    """Realistic seed 0 (6 open flowers, one touching pair), its files written to a folder."""
    out = tmp_path_factory.mktemp("plant0")
    return make_plant(0, out_dir=out), out


@pytest.fixture(scope="session")
def session_stage_cache(tmp_path_factory) -> Path:
    """The stage cache the session's tests share, never the user's."""
    return tmp_path_factory.mktemp("stage-cache")


@pytest.fixture(autouse=True)
def stage_cache(session_stage_cache, monkeypatch):
    """Every test reads and fills the session's stage cache (`flowerpose.cache`): a plant,
    scan or detection one test made is taken by the next that asks for the same, as a user's
    second run takes it (an entry's key holds its inputs, settings and code). The tests of
    the cache itself pass a root of their own."""
    monkeypatch.setenv("FLOWERPOSE_CACHE", str(session_stage_cache))
