"""Real photographs: the ROMI scanner's 60 photos of a potted Arabidopsis (../shared/real-photos,
or the folder FLOWERPOSE_SHARED names) reconstructed three ways: with its calibrated COLMAP
model, with only the scanner's rough logged poses, and from the images alone. Each is
checked against the calibrated camera centres, and the three clouds against each other.

The photos are downscaled to 720 pixels wide so the three reconstructions take about two
minutes on 2 cores; `flowerpose bench --photos` times the full size.
"""

import os
from pathlib import Path

import cv2  # noqa: F401  # before pycolmap (pipeline/sfm.py)
import numpy as np
import pycolmap
import pytest

from flowerpose.cloudio import read_cloud
from flowerpose.data import romi_rough_poses
from flowerpose.eval.quality import cloud_agreement
from flowerpose.pipeline.align import umeyama
from flowerpose.pipeline.photos import PhotoImportConfig, import_photos
from flowerpose.pipeline.reconstruct import reconstruct

SHARED = Path(os.environ.get("FLOWERPOSE_SHARED",
                             Path(__file__).resolve().parents[2].parent / "shared"))
SET = SHARED / "real-photos" / "romi-arabidopsis"

pytestmark = [pytest.mark.slow, pytest.mark.skipif(
    not SET.is_dir(), reason="the real photographs are in ../shared/real-photos; "
    "flowerpose data fetch romi-arabidopsis gets them")]

SIZE = 720


@pytest.fixture(scope="module")
def calibrated_centres() -> dict[str, np.ndarray]:
    """The calibrated camera centres by photo name, metres (the model is in millimetres)."""
    model = pycolmap.Reconstruction(str(SET / "colmap"))
    return {image.name: image.projection_center() / 1000 for image in model.images.values()}


@pytest.fixture(scope="module")
def three_ways(tmp_path_factory) -> dict[str, Path]:
    """The set reconstructed with the calibrated model, the rough poses and no poses."""
    work = tmp_path_factory.mktemp("real-photos")
    romi_rough_poses(SET / "metadata", work / "rough.csv")
    config = PhotoImportConfig(max_size=SIZE, units="mm")
    given = {"calibrated": {"colmap": SET / "colmap"}, "rough": {"poses": work / "rough.csv"},
             "none": {}}
    out = {}
    for kind, poses in given.items():
        import_photos(SET / "images", work / f"frames-{kind}", config, **poses)
        out[kind] = reconstruct(work / f"frames-{kind}", work / f"recon-{kind}",
                                progress=False)
    return out


def _centres(result) -> dict[str, np.ndarray]:
    return {image.name.split("/")[-1]: image.projection_center()
            for image in result.sparse.reconstruction.images.values()
            if image.has_pose and image.num_points3D >= 30}


def _against_calibrated(result, calibrated) -> tuple[float, float, float]:
    """(RMS metres as placed, RMS metres after a similarity, the similarity's scale)."""
    found = _centres(result)
    names = sorted(found)
    a = np.array([found[n] for n in names])
    b = np.array([calibrated[n] for n in names])
    similarity = umeyama(a, b)
    rms = float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))))
    aligned = float(np.sqrt(np.mean(np.sum((similarity.apply(a) - b) ** 2, axis=1))))
    return rms, aligned, similarity.scale


def test_the_calibrated_model_registers_the_photos_where_they_were(three_ways,
                                                                   calibrated_centres):
    result = three_ways["calibrated"]
    assert result.report["images_registered"] >= 58
    rms, _, _ = _against_calibrated(result, calibrated_centres)
    assert rms < 0.002


def test_rough_logged_poses_give_a_metric_model_where_the_photos_were(three_ways,
                                                                      calibrated_centres):
    result = three_ways["rough"]
    assert result.report["sparse"]["mode"] == "incremental"  # degrees off: not for guiding
    assert result.report["images_registered"] >= 58
    rms, _, scale = _against_calibrated(result, calibrated_centres)
    assert rms < 0.003
    assert scale == pytest.approx(1.0, abs=0.01)


def test_the_images_alone_give_every_view_and_an_upright_cloud(three_ways, calibrated_centres):
    result = three_ways["none"]
    assert result.report["images_registered"] == 60
    assert not result.report["metric"]
    _, aligned, _ = _against_calibrated(result, calibrated_centres)
    assert aligned < 0.003
    found = _centres(result)
    names = sorted(found)
    similarity = umeyama(np.array([found[n] for n in names]),
                         np.array([calibrated_centres[n] for n in names]))
    # The scanner's frame is z up: levelling must have put the model so already.
    up = similarity.rotation @ np.array([0, 0, 1.0])
    assert np.degrees(np.arccos(np.clip(up[2], -1, 1))) < 2.0


def test_the_three_clouds_agree(three_ways, calibrated_centres):
    clouds = {}
    for kind, result in three_ways.items():
        found = _centres(result)
        names = sorted(found)
        similarity = umeyama(np.array([found[n] for n in names]),
                             np.array([calibrated_centres[n] for n in names]))
        clouds[kind] = similarity.apply(read_cloud(result.report["cloud"], units="m").points)
    kinds = sorted(clouds)
    for i, a in enumerate(kinds):
        for b in kinds[i + 1:]:
            assert cloud_agreement(clouds[a], clouds[b], 0.002)["fscore"] >= 0.9, (a, b)
