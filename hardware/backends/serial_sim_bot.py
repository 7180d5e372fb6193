"""The simulated scan through the serial code path: the `FarmduinoBot` client on a
`VirtualFarmduino`, with one clock for the device, the bot and the camera that stands still
while frames render, so its trajectories match the direct simulated backend's."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterator
from dataclasses import asdict
from pathlib import Path

import numpy as np

from flowerpose.hardware.backends import SERIAL_SIM_TIME_SCALE
from flowerpose.hardware.backends.farmduino import FarmduinoBot
from flowerpose.hardware.backends.virtual_farmduino import FEEDBACK_PARAMETERS, VirtualFarmduino


class PausableClock:
    """Monotonic seconds of a simulated world that stand still while frames render
    (`paused()`) and while the board waits for the host (`host_turn(True)`); the host's
    own waits on the bot's time (a dwell, the head settling) move it on at once (`skip`).
    So neither rendering nor the host's latency between commands, which the time scale
    would multiply, takes any of the bot's time, as with the direct backend's clock."""

    def __init__(self):
        self._lock = threading.Lock()
        self._paused_for = 0.0
        self._since: float | None = None
        self._rendering = 0
        self._host_turn = False

    def __call__(self) -> float:
        with self._lock:
            now = time.monotonic() if self._since is None else self._since
            return now - self._paused_for

    def _update(self) -> None:
        """Stop or restart the clock for the state just changed (lock held)."""
        stopped = self._rendering > 0 or self._host_turn
        if stopped and self._since is None:
            self._since = time.monotonic()
        elif not stopped and self._since is not None:
            self._paused_for += time.monotonic() - self._since
            self._since = None

    @contextlib.contextmanager
    def paused(self) -> Iterator[None]:
        """Frames render inside: the clock stands still."""
        with self._lock:
            self._rendering += 1
            self._update()
        try:
            yield
        finally:
            with self._lock:
                self._rendering -= 1
                self._update()

    def skip(self, seconds: float) -> None:
        """Move the clock on by `seconds` at once."""
        with self._lock:
            self._paused_for -= max(0.0, float(seconds))

    def host_turn(self, waiting: bool, since: float | None = None) -> None:
        """The board has answered and waits for the host's next command (True), or has
        work of its own again (False). since: the reading the answer was due at, when it
        came late (the board's loop wakes after it): the clock stops there."""
        with self._lock:
            self._host_turn = bool(waiting)
            self._update()
            if waiting and since is not None and self._since is not None:
                self._paused_for += max(0.0, self._since - self._paused_for - since)


class SimulatedSerialBot(FarmduinoBot):
    """The simulated scan through the serial code path: a `FarmduinoBot` on its own
    `VirtualFarmduino`, filming generated plants with `SimCamera` as `SimBot` does.

    plant_dirs: folders from `flowerpose plant`. config: the simulated camera and head.
    time_scale: simulated seconds per wall second of the device and the bot's clock.
    The bot is homed at once, as any Farmduino must be after its port opens.
    """

    def __init__(self, plant_dirs: list[Path], config=None,
                 time_scale: float = SERIAL_SIM_TIME_SCALE):
        from flowerpose.hardware.backends.sim_bot import SimBotConfig, sim_camera

        self.sim_config = config or SimBotConfig()
        # The device, the bot's clock and the camera share one time that stops while frames
        # render, so the trajectory's times are the direct backend's.
        clock = PausableClock()
        camera = sim_camera(plant_dirs, self.sim_config, self._current, pause=clock.paused)
        self.device = VirtualFarmduino(time_scale=time_scale, params=FEEDBACK_PARAMETERS,
                                       wall_clock=clock, on_idle=clock.host_turn).start()
        try:
            super().__init__(self.device.path, camera=camera,
                             observer=lambda activity: self.camera.observe(activity),
                             clock_scale=time_scale, wall_clock=clock,
                             skip_time=clock.skip)
            self.home()
        except BaseException:
            self.device.close()
            raise

    def _current(self) -> tuple[np.ndarray, float, float]:
        yaw, pitch = self.head()
        return self.position(), yaw, pitch

    def describe(self) -> dict:
        return {**super().describe(), "backend": "sim via virtual Farmduino",
                "virtual": self.device.describe(), **asdict(self.sim_config)}

    def close(self) -> None:
        super().close()
        self.device.close()
