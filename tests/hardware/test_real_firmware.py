"""The serial client against FarmBot's own Farmduino firmware (6.6.26, as FarmBot OS 15.4.11
flashes it), run in simavr with its UART on a pseudo-terminal (the firmware folder,
FLOWERPOSE_SHARED's `firmware`, by default ../shared beside the repository). The
firmware runs in real time, so these are few and short; the protocol's every path is tested
against the virtual Farmduino (test_farmduino.py)."""

from __future__ import annotations

import functools
import os
import signal
import subprocess
import threading
from pathlib import Path

import numpy as np
import pytest

from flowerpose.hardware.backends.farmduino import FarmduinoBot
from flowerpose.hardware.bot import SolidCamera
from flowerpose.hardware.bot_errors import EmergencyStopError, HomingError, LockedError

#: The firmware and its runner: FLOWERPOSE_SHARED's `firmware` folder, by default
#: ../shared/firmware beside the repository (CI has it).
FIRMWARE = Path(os.environ.get("FLOWERPOSE_SHARED",
                               Path(__file__).resolve().parents[2].parent / "shared")) / "firmware"
CAMERA = functools.partial(SolidCamera, width=32, height=24, fps=2)

#: Every test runs under the 20 s watchdog (conftest.py).
pytestmark = pytest.mark.usefixtures("watchdog")


@pytest.fixture(scope="module")
def runner(tmp_path_factory) -> Path:
    """The built runner's folder (build.sh installs simavr where it is missing)."""
    if not (FIRMWARE / "build.sh").is_file():
        pytest.skip(f"the real Farmduino firmware is not here ({FIRMWARE}; FLOWERPOSE_SHARED "
                    "names the folder that holds it)")
    out = tmp_path_factory.mktemp("farmduino-sim")
    built = subprocess.run(["bash", str(FIRMWARE / "build.sh"), str(out)], capture_output=True,
                           text=True, timeout=600)
    if built.returncode != 0:
        pytest.skip(f"the firmware runner does not build here: {built.stderr.strip()[-300:]}")
    return out


@pytest.fixture
def board(runner, tmp_path):
    """A freshly booted board: the path of its serial port."""
    link = tmp_path / "farmduino"
    started = subprocess.run(["bash", str(FIRMWARE / "run.sh"), str(link)], capture_output=True,
                             text=True, timeout=30, env={**os.environ, "FIRMWARE_SIM": str(runner)})
    assert started.returncode == 0, started.stderr
    pid = int(started.stdout.split()[1])
    try:
        yield link
    finally:
        os.kill(pid, signal.SIGTERM)


def test_connect_writes_the_bots_settings_and_refuses_a_homing_it_cannot_finish(board):
    settings = {71: 300.0, 72: 300.0}
    with FarmduinoBot(board, camera=CAMERA, clock_scale=1.0, settings=settings) as bot:
        assert bot.info.firmware.startswith("6.6.26")
        assert bot.info.motion.x.max_speed == 300  # written at connect and read back
        # No endstops and no encoders on the firmware's defaults: refused before any move,
        # where the firmware would search for home for ever.
        before = bot.position().copy()
        with pytest.raises(HomingError, match="neither its endstops"):
            bot.home()
        np.testing.assert_array_equal(bot.position(), before)


@pytest.mark.slow
def test_moves_and_servos_then_an_emergency_stop_mid_move_and_an_unlock(board):
    with FarmduinoBot(board, camera=CAMERA, clock_scale=1.0) as bot:
        bot.home_here()
        start = bot.position().copy()
        bot.move_to(start + [0.02, 0.01, 0.0])
        np.testing.assert_allclose(bot.position(), start + [0.02, 0.01, 0.0], atol=2e-4)
        bot.set_head(0.3, 0.8)
        assert bot.head() == pytest.approx((0.3, 0.8), abs=np.radians(2.0))
        threading.Timer(0.5, bot.emergency_stop).start()
        with pytest.raises(EmergencyStopError):
            bot.move_to(bot.position() + [0.3, 0.0, 0.0])  # about 4 s: stopped in the first
        stopped = bot.position().copy()
        assert stopped[0] < start[0] + 0.02 + 0.3 - 0.05
        with pytest.raises(LockedError):
            bot.move_to(stopped + [0.01, 0.0, 0.0])
        bot.unlock()
        bot.move_to(stopped + [0.01, 0.0, 0.0])
        np.testing.assert_allclose(bot.position(), stopped + [0.01, 0.0, 0.0], atol=2e-4)
