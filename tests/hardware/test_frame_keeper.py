"""Choosing frames while recording: the same frames as the frame stage, written once."""

import csv
import functools

import cv2
import numpy as np
import pytest

from flowerpose.errors import InputError
from flowerpose.hardware.backends.frame_keeper import FrameKeeper
from flowerpose.jsonio import write_json
from flowerpose.pipeline.frames import FrameSelectConfig, frame_score, select_frames
from flowerpose.scanio import FRAME_PATTERN, TRAJECTORY_COLUMNS, Intrinsics, trajectory_row

FPS = 30.0


@functools.cache
def _texture() -> np.ndarray:
    rng = np.random.default_rng(0)
    return cv2.resize(rng.integers(0, 256, (60, 80, 3)).astype(np.uint8), (320, 240),
                      interpolation=cv2.INTER_NEAREST)


def _frames(count: int, seed: int = 1) -> list[tuple[np.ndarray, float]]:
    """A steady 30 fps stream from 10 s (mid-frame times: none on a bin edge), each frame
    blurred by a random amount."""
    blur = np.random.default_rng(seed).uniform(0.0, 4.0, count)
    return [(cv2.GaussianBlur(_texture(), (0, 0), b) if b > 0.3 else _texture(),
             10 + (k + 0.5) / FPS)
            for k, b in enumerate(blur)]


def _record(folder, frames) -> None:
    """A scan folder holding `frames` as the recorder writes them."""
    (folder / "frames").mkdir(parents=True)
    rows = []
    for k, (image, t) in enumerate(frames):
        cv2.imwrite(str(folder / "frames" / FRAME_PATTERN.format(k)), image,
                    [cv2.IMWRITE_JPEG_QUALITY, 100])
        rows.append(trajectory_row(k, t, np.array([1.0, 0.5, 0.3]), 0.0, 0.1,
                                   np.array([1.0, 0.5, 0.2]), np.eye(3)))
    with open(folder / "trajectory.csv", "w", newline="") as handle:
        csv.writer(handle).writerows([TRAJECTORY_COLUMNS, *rows])
    write_json(folder / "camera.json", Intrinsics(320, 240, 300, 300, 160, 120).to_json())


def _keep(frames, bins, keep):
    keeper = FrameKeeper(10.0, len(frames) / FPS, bins, keep)
    out = [kept for image, t in frames for kept in keeper.offer(image, t)]
    return out + keeper.flush(), keeper


def test_the_sharpest_few_of_each_bin_are_handed_on_once_their_bin_has_passed():
    frames = _frames(60)
    keeper = FrameKeeper(10.0, 2.0, bins=6, keep=2)
    handed = [keeper.offer(image, t) for image, t in frames]
    # Nothing leaves while its bin is open; each bin's pair leaves with the next bin's first.
    assert [len(h) for h in handed] == [2 if k in (10, 20, 30, 40, 50) else 0 for k in range(60)]
    assert keeper.left_out == 60 - 10 - 2
    last = keeper.flush()
    scores = [frame_score(image, keeper.config)[0] for image, _ in frames]
    for b, chosen in enumerate([*[h for h in handed if h], last]):
        best = sorted(range(10 * b, 10 * b + 10), key=lambda k: -scores[k])[:2]
        assert [t for _, t in chosen] == [frames[k][1] for k in sorted(best)]  # time order
    assert keeper.kept == 12


def test_a_scan_that_overruns_its_plan_keeps_bins_of_the_same_width():
    # A field scan takes longer than planned (head settling, latency): its last part must
    # not collapse into one bin of 3 frames.
    keeper = FrameKeeper(0.0, 10.0, bins=5, keep=1)
    assert [keeper.bin_of(t) for t in (-1.0, 0.0, 1.99, 2.0, 9.99, 10.0, 13.0)] == \
        [0, 0, 0, 1, 4, 5, 6]
    frames = [(np.full((8, 8, 3), k, np.uint8), 0.5 * k) for k in range(30)]  # 15 s
    kept = [handed for image, t in frames for handed in keeper.offer(image, t)]
    kept += keeper.flush()
    assert len(kept) == 8 and keeper.kept == 8  # bins 0-7 of 2 s, one frame each


def test_the_streamed_choice_is_the_frame_stages_on_every_frame_and_on_the_kept_ones(tmp_path):
    frames = _frames(120)
    _record(tmp_path / "all", frames)
    offline = select_frames(tmp_path / "all", tmp_path / "chosen-all",
                            FrameSelectConfig(count=8), progress=False)["frames"]
    best, _ = _keep(frames, bins=8, keep=1)
    np.testing.assert_allclose([t for _, t in best], [f["t"] for f in offline], atol=1e-6)
    kept, keeper = _keep(frames, bins=8, keep=3)
    assert keeper.kept == 24 and keeper.left_out == 96
    _record(tmp_path / "kept", kept)
    streamed = select_frames(tmp_path / "kept", tmp_path / "chosen-kept",
                             FrameSelectConfig(count=8), progress=False)["frames"]
    np.testing.assert_allclose([f["t"] for f in streamed], [f["t"] for f in offline], atol=1e-6)


@pytest.mark.parametrize("args", [(0.0, 0.0, 10, 1), (0.0, 5.0, 0, 1), (0.0, 5.0, 10, 0)])
def test_a_keeper_needs_a_duration_bins_and_frames(args):
    with pytest.raises(InputError, match="frame keeper"):
        FrameKeeper(*args)
