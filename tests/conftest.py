"""Fixtures shared across the test packages."""

from __future__ import annotations

from pathlib import Path

import pytest

from flowerpose.sim.bundle import PlantBundle, make_plant


@pytest.fixture(scope="session")
def plant0(tmp_path_factory) -> tuple[PlantBundle, Path]:
    """Realistic seed 0 (6 open flowers, one touching pair), its files written to a folder."""
    out = tmp_path_factory.mktemp("plant0")
    return make_plant(0, out_dir=out), out


@pytest.fixture(autouse=True)
def private_stage_cache(tmp_path_factory, monkeypatch):
    """Every test's stage cache is its own (`flowerpose.cache`): none reads the user's."""
    monkeypatch.setenv("FLOWERPOSE_CACHE", str(tmp_path_factory.mktemp("stage-cache")))
