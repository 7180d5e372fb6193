"""What `flowerpose frames` and `flowerpose reconstruct` read: their sections of an eval's
`scan` settings, under the same keys (`scan.frames.*`, `scan.reconstruct.*`), without the
simulator an eval's settings bring."""

from __future__ import annotations

from dataclasses import dataclass, field

from flowerpose.pipeline.frames import FrameSelectConfig
from flowerpose.pipeline.reconstruct import ReconstructConfig


@dataclass(frozen=True)
class ScanStagesSection:
    """The photogrammetry stages of a scan."""

    frames: FrameSelectConfig = field(default_factory=FrameSelectConfig)
    """How frames are chosen (`frames`)."""
    reconstruct: ReconstructConfig = field(default_factory=ReconstructConfig)
    """Photogrammetry (`reconstruct`)."""


@dataclass(frozen=True)
class ScanStagesConfig:
    """The settings tree of `frames` and `reconstruct`: `scan.frames`, `scan.reconstruct`."""

    scan: ScanStagesSection = field(default_factory=ScanStagesSection)
    """The scan's photogrammetry stages."""
