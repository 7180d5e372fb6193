"""Choosing frames while recording: the sharpest few of each bin of the scan path.

A 20-minute scan at 30 fps is about 36,000 frames, several GB as JPEG files, of which the
frame stage keeps 200. `FrameKeeper` keeps only the `keep` sharpest frames (the frame
stage's score, `pipeline.frames.frame_score`) of each of `bins` equal bins of bot time over
the planned scan, and hands them on, in time order, as soon as their bin has passed: at most
`keep` images of the open bin wait in memory, and nothing is written that is deleted later.
Frames after the planned end fall in the last bin, so a scan that runs long still ends in
`bins` bins.

With every bin holding `keep` frames, `flowerpose frames --count bins` on the recording
bins the kept frames `keep` at a time, each of its bins one of these, and so picks the
sharpest frame of each bin of the path, as it would have from every frame.
"""

from __future__ import annotations

import math

import numpy as np

from flowerpose.errors import InputError
from flowerpose.pipeline.frames import FrameSelectConfig, frame_score


class FrameKeeper:
    """The `keep` best-scoring frames of each time bin of width duration_s / bins from
    start_t (`bins` over the planned duration, as many more as the scan overruns it).

    Images are (H, W, 3) uint8 in either channel order (the score is a grey Laplacian and a
    channel maximum); times are seconds on the bot's clock.
    """

    def __init__(self, start_t: float, duration_s: float, bins: int, keep: int,
                 config: FrameSelectConfig | None = None):
        if not (math.isfinite(duration_s) and duration_s > 0):
            raise InputError("frame keeper", f"the planned duration must be positive, got "
                             f"{duration_s!r} s")
        if bins < 1 or keep < 1:
            raise InputError("frame keeper", f"needs at least 1 bin and 1 frame a bin, got "
                             f"{bins} and {keep}")
        self.start_t, self.width_s, self.bins, self.keep = start_t, duration_s / bins, bins, keep
        self.config = config or FrameSelectConfig()
        self._bin: int | None = None
        self._best: list[tuple[float, float, np.ndarray]] = []
        self.offered = self.kept = 0

    @property
    def left_out(self) -> int:
        """Frames offered that will never be handed on (the open bin's are still candidates)."""
        return self.offered - self.kept - len(self._best)

    @property
    def open_since(self) -> float:
        """Bot-clock start of the open bin, whose frames are still candidates (inf when no
        bin is open): every frame kept from before it has been handed on."""
        return math.inf if self._bin is None else self.start_t + self._bin * self.width_s

    def bin_of(self, t: float) -> int:
        """The bin of bot time t: 0 before the start; past the planned end, more bins of
        the same width (a real scan overruns its plan: head settling, reply latency; one
        last bin would have kept 3 frames of the plan's whole last part)."""
        return max(int((t - self.start_t) // self.width_s), 0)

    def offer(self, image: np.ndarray, t: float) -> list[tuple[np.ndarray, float]]:
        """Score a frame; returns the kept frames (image, t) of the bins that have now
        passed, in time order (empty while the frame's bin is still open)."""
        self.offered += 1
        b = self.bin_of(t)
        done = self.flush() if self._bin is not None and b != self._bin else []
        self._bin = b
        score = frame_score(image, self.config)[0]
        if len(self._best) < self.keep:
            self._best.append((score, t, image))
        else:
            worst = min(range(self.keep), key=lambda k: self._best[k][0])
            if score > self._best[worst][0]:
                self._best[worst] = (score, t, image)
        return done

    def flush(self) -> list[tuple[np.ndarray, float]]:
        """The open bin's kept frames, in time order (at the end of a recording)."""
        kept = [(image, t) for _, t, image in sorted(self._best, key=lambda item: item[1])]
        self._best, self._bin = [], None
        self.kept += len(kept)
        return kept
