"""A cloud's flowers found without truth, through the stage cache: the detect stage as
eval's synthetic plants, the simulated bed and the physical bot's bed all run it.
"""

from __future__ import annotations

from pathlib import Path

from flowerpose.cloudio import read_cloud
from flowerpose.config import to_dict
from flowerpose.log import noted
from flowerpose.pipeline.detect import ONNX_PREFIX
from flowerpose.pipeline.flowers import (
    PipelineConfig,
    find_flowers,
    write_flowers,
    write_normals_ply,
)

#: What the detect stage writes of a cloud, and the stage cache keeps.
DETECT_FILES = ("flowers.json", "flowers.ply", "normals.ply")


def _cacheable(pipeline: PipelineConfig) -> bool:
    """Whether a detection with these settings may come from the stage cache: the built-in
    detectors' code is in the cache's code version (an ONNX model's file in the key); a
    plug-in class's code is not, so its detections are always run."""
    detector = pipeline.detect.detector
    return detector == "colour" or detector.startswith(ONNX_PREFIX)


def _detector_files(pipeline: PipelineConfig) -> list[Path]:
    """The files a detection reads besides the cloud: an ONNX model."""
    detector = pipeline.detect.detector
    return [Path(detector.removeprefix(ONNX_PREFIX))] if detector.startswith(ONNX_PREFIX) else []


def detect_cloud(cloud: Path, pipeline: PipelineConfig, folder: Path,
                 cache: Path | None = None) -> tuple[dict[str, float], str | None]:
    """The pipeline on a cloud, its flowers written into `folder` (`DETECT_FILES`, with the
    warnings said on the way as flowers.json's notes). With `cache` (the stage cache's
    folder), a detection made before from the same files, settings and code is taken from
    it. Returns the stage timings, seconds (0 where taken from the cache), and the stage
    cache's key of the detection (None where it did not go through the cache)."""

    def detect() -> dict:
        with noted() as notes:
            result = find_flowers(read_cloud(cloud), pipeline)
        write_flowers(folder / "flowers.json", result, cloud, notes=notes)
        write_normals_ply(folder, result.flowers)
        return {"timing_s": result.timing_s}

    if cache is None or not _cacheable(pipeline):
        return detect()["timing_s"], None
    from flowerpose.cache import StageCache

    detected, cached, key = StageCache(cache).run(
        "detect", to_dict(pipeline), [cloud, *_detector_files(pipeline)], folder,
        DETECT_FILES, detect)
    return {stage: 0.0 if cached else t for stage, t in detected["timing_s"].items()}, key
