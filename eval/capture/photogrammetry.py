"""A filmed plant's frames chosen and reconstructed through the stage cache: the one route
from a scan folder to a cloud for every filmed plant, eval's and sweep's simulated scans
and both beds' plants.

Per plant folder: scan/ (the recording: a simulated scan's or the bot's), frames/
(`flowerpose frames`), reconstruction/ (`flowerpose reconstruct`). Two stages of the
cache, "frames" (keyed by the recording, or by the stage that filmed it) and
"reconstruct" (keyed by the frames), each run by the pipeline's frame choice and
photogrammetry alone (`CODE`).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from flowerpose.cache import StageCache
from flowerpose.config import to_dict
from flowerpose.pipeline.frames import FrameSelectConfig
from flowerpose.pipeline.reconstruct import ReconstructConfig
from flowerpose.stopwatch import Stopwatch

#: What the stage cache keeps of a frame choice: the frames as `flowerpose frames` wrote
#: them (a reconstruction can be run again from them).
FRAMES_FILES = ("frames",)
#: What it keeps of a reconstruction of those frames: the cloud and its report.
RECONSTRUCTION_FILES = ("reconstruction/cloud.ply", "reconstruction/reconstruction.json")
#: The code the two stages run (the stage cache's code version): frame choice and
#: photogrammetry, not the simulator or the detection.
CODE = ("flowerpose.pipeline.frames", "flowerpose.pipeline.reconstruct")
#: What a simulated plant's scan folder holds besides the recording: its truth.
TRUTH_FILES = ("plant.json", "visibility.json")
#: What the reconstruction stage returns of reconstruction.json.
RECONSTRUCTION_COUNTS = ("images_registered", "images_used", "points", "alignment_rms_m")


def frames_and_cloud(folder: Path, frames: FrameSelectConfig, reconstruct: ReconstructConfig,
                     cache: Path | None, watch: Stopwatch, filmed_by: str | None = None,
                     film_again: Callable[[], None] | None = None) -> tuple[dict, list[str]]:
    """folder/frames chosen from folder/scan and reconstructed into folder/reconstruction,
    each from the stage cache at `cache` where it can be (None: no cache), `watch` lapped
    after each ("frames", "reconstruct"). The frame choice is keyed by the recording's
    files (a simulated scan's truth left out) or, where a cached stage filmed it, by that
    stage's key `filmed_by`: the cache keeps no recording, so `film_again` films it anew
    before frames are chosen from it. Returns the frames chosen, the reconstruction's
    counts (`RECONSTRUCTION_COUNTS`) and the steps taken from the cache."""

    def choose() -> dict:
        if film_again is not None:
            film_again()
        return choose_frames(folder, frames)

    def build() -> dict:
        return reconstruct_frames(folder, reconstruct)

    if cache is None:
        chosen = choose()
        watch.lap("frames")
        built = build()
        watch.lap("reconstruct")
        return {**chosen, **built}, []
    stages = StageCache(cache)
    recording = [] if filmed_by else sorted(
        p for p in (folder / "scan").rglob("*") if p.is_file() and p.name not in TRUTH_FILES)
    chosen, frames_cached, key = stages.run(
        "frames", to_dict(frames), recording, folder, FRAMES_FILES, choose,
        parents=[filmed_by] if filmed_by else [], code=CODE)
    watch.lap("frames")
    built, built_cached, _ = stages.run(
        "reconstruct", to_dict(reconstruct), [], folder, RECONSTRUCTION_FILES, build,
        parents=[key], code=CODE)
    watch.lap("reconstruct")
    return {**chosen, **built}, [step for step, hit in (("frames", frames_cached),
                                                        ("reconstruct", built_cached)) if hit]


def choose_frames(folder: Path, frames: FrameSelectConfig) -> dict:
    """folder/frames chosen from the recording in folder/scan (`flowerpose frames`); how
    many were chosen."""
    from flowerpose.pipeline.frames import select_frames

    chosen = select_frames(folder / "scan", folder / "frames", frames, progress=False,
                           overwrite=True)
    return {"frames": len(chosen["frames"])}


def reconstruct_frames(folder: Path, reconstruct: ReconstructConfig) -> dict:
    """folder/frames reconstructed into folder/reconstruction (`flowerpose reconstruct`);
    the reconstruction's counts (`RECONSTRUCTION_COUNTS`)."""
    from flowerpose.pipeline.reconstruct import reconstruct as run_reconstruction

    built = run_reconstruction(folder / "frames", folder / "reconstruction", reconstruct,
                               progress=False, overwrite=True)
    return {k: built.report[k] for k in RECONSTRUCTION_COUNTS}
