"""Real photographs: the ROMI scanner's 60 photos of a potted Arabidopsis (../shared/real-photos,
or the folder FLOWERPOSE_SHARED names) reconstructed three ways by `flowerpose bench
--photos`: with its calibrated COLMAP model, with only the scanner's rough logged poses, and
from the images alone; each checked against the calibrated camera centres, and the three
clouds against each other. Full size (1440 x 1080): the one slow test of real images, about
two and a half minutes on 2 cores.
"""

import os
from pathlib import Path

import pytest

from flowerpose.eval.studies.photo_bench import run_photo_bench

SHARED = Path(os.environ.get("FLOWERPOSE_SHARED",
                             Path(__file__).resolve().parents[2].parent / "shared"))
SET = SHARED / "real-photos" / "romi-arabidopsis"

pytestmark = [pytest.mark.slow, pytest.mark.skipif(
    not SET.is_dir(), reason="the real photographs are in ../shared/real-photos; "
    "flowerpose data fetch romi-arabidopsis gets them")]


@pytest.fixture(scope="module")
def bench(tmp_path_factory) -> dict:
    """photo_bench.json of the set, three ways."""
    return run_photo_bench(SET, tmp_path_factory.mktemp("photo-bench"))


def test_the_calibrated_model_registers_the_photos_where_they_were(bench):
    way = bench["ways"]["calibrated"]
    assert way["mode"] == "poses" and way["metric"]
    assert way["registered"] >= 58
    assert way["centres_rms_mm"] < 2.0


def test_rough_logged_poses_give_a_metric_model_where_the_photos_were(bench):
    way = bench["ways"]["rough"]
    assert way["mode"] == "incremental"  # degrees off: not for guiding the matching
    assert way["registered"] >= 58 and way["metric"]
    assert way["centres_rms_mm"] < 3.0  # as placed: no alignment to the calibrated ones
    assert way["similarity_scale"] == pytest.approx(1.0, abs=0.01)


def test_the_images_alone_give_every_view_and_an_upright_cloud(bench):
    way = bench["ways"]["none"]
    assert way["registered"] == 60 and not way["metric"]
    assert way["centres_rms_after_similarity_mm"] < 3.0
    # The scanner's frame is z up; the levelled model must be so already.
    assert way["up_error_deg"] < 2.0


def test_the_three_clouds_agree(bench):
    for pair, scores in bench["agreement"].items():
        assert scores["after ICP 2mm"] >= 0.9, pair
        assert scores["placed 5mm"] >= 0.95, pair
