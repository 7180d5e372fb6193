"""Dense reconstruction on a GPU: COLMAP's PatchMatch stereo and fusion through pycolmap.

Runs only where pycolmap was built with CUDA (`pycolmap.has_cuda`; on PyPI the
`pycolmap-cuda12` wheel). The sparse model it starts from is already in the bed frame
(`sfm.py`), so the fused cloud is too: metres, z up.

    sparse model + frames -> work_dir/ (undistorted images, stereo/depth_maps, ...)
                          -> work_dir/fused.ply
"""

from __future__ import annotations

# cv2 before pycolmap (sfm.py says why).
import cv2  # noqa: F401  # isort: skip

import shutil
from pathlib import Path

try:
    import pycolmap
except ImportError:  # the [recon] extra is not installed: the settings still load
    pycolmap = None

from flowerpose.cloudio import Cloud, read_cloud
from flowerpose.errors import InputError
from flowerpose.processes import reclaim_sigterm
from flowerpose.stopwatch import Stopwatch

# Importing pycolmap gave SIGTERM to glog, which prints a C stack dump and kills the process.
reclaim_sigterm()


def cuda_available() -> bool:
    """Whether this pycolmap can run PatchMatch stereo (built with CUDA)."""
    return pycolmap is not None and bool(pycolmap.has_cuda)


def reconstruct_patch_match(frames_dir: Path, sparse_dir: Path, work_dir: Path,
                            max_image_size: int = 1280) -> tuple[Cloud, dict]:
    """Fused PatchMatch cloud (bed frame, metres) of the frames the sparse model in
    sparse_dir registered, and a small report; work_dir is rewritten."""
    if not cuda_available():
        raise InputError("reconstruct.dense_method", "patch_match needs pycolmap built with "
                         "CUDA (pip install pycolmap-cuda12 on a machine with an NVIDIA GPU); "
                         "use sgbm on the CPU")
    watch = Stopwatch()
    if work_dir.exists():
        shutil.rmtree(work_dir)
    pycolmap.undistort_images(work_dir, sparse_dir, frames_dir)
    watch.lap("undistort")
    options = pycolmap.PatchMatchOptions()
    options.max_image_size = max_image_size
    options.geom_consistency = True
    pycolmap.patch_match_stereo(work_dir, options=options)
    watch.lap("patch_match")
    fused = work_dir / "fused.ply"
    pycolmap.stereo_fusion(fused, work_dir, output_type="ply")
    watch.lap("fusion")
    cloud = read_cloud(fused, units="m")  # an empty fusion is refused there, by name
    return cloud, {"method": "patch_match", "points": len(cloud),
                   "seconds": watch.report(digits=3, total=None)}
