"""Session fixtures of the sim tests."""

from __future__ import annotations

import pytest

from flowerpose.sim.bundle import PlantBundle, make_plant


@pytest.fixture(scope="session")
def bundle0() -> PlantBundle:
    """Seed 0, realistic preset, default 60,000-point oracle cloud."""
    return make_plant(0)
