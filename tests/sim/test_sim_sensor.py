"""The camera sensor model: blur it reports is blur it applied, noise, determinism."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.stats import spearmanr

from flowerpose.errors import InputError
from flowerpose.pipeline.colour import rgb_to_hsv
from flowerpose.sim.camera import intrinsics_from_config, look_at
from flowerpose.sim.sensor import (
    SensorConfig,
    apply_sensor,
    defocus_radius,
    image_velocity,
    process_colour,
    sharpness_truth,
)

CLEAN = SensorConfig(read_noise_dn=0.0, shot_noise_dn=0.0, jpeg_quality=None)
SETTLED = 10.0
"""Seconds since the stop: long after the autofocus settled."""


@pytest.fixture(scope="module")
def texture():
    """(180, 320, 3) uint8 random texture with detail at every scale."""
    rng = np.random.default_rng(7)
    coarse = cv2.resize(rng.uniform(0, 255, (23, 40, 3)).astype(np.float32), (320, 180))
    fine = cv2.GaussianBlur(rng.uniform(0, 255, (180, 320, 3)).astype(np.float32), (0, 0), 0.7)
    return np.clip(0.5 * coarse + 0.5 * fine, 0, 255).astype(np.uint8)


def sharpness(image):
    """Variance of the Laplacian of the grey image (the paper's frame score)."""
    return cv2.Laplacian(cv2.cvtColor(image, cv2.COLOR_RGB2GRAY), cv2.CV_64F).var()


def test_at_rest_only_noise(texture):
    config = SensorConfig(jpeg_quality=None)
    out, record = apply_sensor(texture, (0.0, 0.0), SETTLED, config, np.random.default_rng(0))
    assert (record.motion_blur_px, record.defocus_px, record.blur_rms_px) == (0.0, 0.0, 0.0)
    assert sharpness_truth(record) == 1.0 and record.jpeg_quality is None
    difference = out.astype(float) - texture
    assert abs(difference.mean()) < 0.1
    assert difference.std() == pytest.approx(record.noise_sigma_dn, rel=0.05)
    level = texture.astype(float)
    expected = np.sqrt(config.read_noise_dn ** 2 + config.shot_noise_dn ** 2 * level / 255)
    assert record.noise_sigma_dn == pytest.approx(np.sqrt((expected ** 2).mean()), rel=1e-3)
    clean, record = apply_sensor(texture, (0.0, 0.0), SETTLED, CLEAN, np.random.default_rng(0))
    assert np.array_equal(clean, texture) and record.noise_sigma_dn == 0.0


def test_shot_noise_grows_with_the_signal():
    config = SensorConfig(jpeg_quality=None)
    flat = np.full((200, 200, 3), 40, np.uint8)
    flat[100:] = 220
    out, _ = apply_sensor(flat, (0.0, 0.0), SETTLED, config, np.random.default_rng(1))
    dark, bright = (out[:100].astype(float) - 40).std(), (out[100:].astype(float) - 220).std()
    assert dark == pytest.approx(np.sqrt(1.5 ** 2 + 9 * 40 / 255), rel=0.05)
    assert bright == pytest.approx(np.sqrt(1.5 ** 2 + 9 * 220 / 255), rel=0.05)


def test_faster_motion_blurs_more(texture):
    records, scores = [], []
    for speed in (0.0, 100.0, 300.0, 1000.0):
        out, record = apply_sensor(texture, (speed, 0.3 * speed), SETTLED, CLEAN,
                                   np.random.default_rng(0))
        records.append(record)
        scores.append(sharpness(out))
        assert record.motion_blur_px == pytest.approx(np.hypot(speed, 0.3 * speed) * 0.02)
        assert record.defocus_px == 0.0
    assert np.all(np.diff(scores) < 0)
    truth = [sharpness_truth(r) for r in records]
    assert truth[0] == 1.0 and np.all(np.diff(truth) < 0)
    # A line of length L has an RMS radius of L / sqrt(12).
    rms = records[-1].blur_rms_px
    assert rms == pytest.approx(records[-1].motion_blur_px / np.sqrt(12), rel=0.05)
    assert records[-1].motion_angle_rad == pytest.approx(np.arctan2(0.3, 1.0))


def test_motion_blurs_along_its_direction():
    stripes = np.zeros((120, 120, 3), np.uint8)
    stripes[:, ::8] = 255  # vertical lines: horizontal motion smears them
    lines = stripes.transpose(1, 0, 2).copy()  # horizontal lines: it leaves them
    across, _ = apply_sensor(stripes, (400.0, 0.0), SETTLED, CLEAN, np.random.default_rng(0))
    along, _ = apply_sensor(lines, (400.0, 0.0), SETTLED, CLEAN, np.random.default_rng(0))
    assert across.std() < 0.6 * stripes.std()
    assert np.array_equal(along, lines)


def test_defocus_fades_as_autofocus_settles(texture):
    config = SensorConfig()
    times = np.linspace(0.0, 3.0, 31)
    radius = np.array([defocus_radius(t, config) for t in times])
    assert radius[0] == config.defocus_px and defocus_radius(-1.0, config) == config.defocus_px
    settling = times < config.autofocus_settle_s
    assert np.all(np.diff(radius[settling]) < 0)
    assert np.all(radius[~settling] == 0.0)
    scores, truth = [], []
    for t in (0.0, 0.5, 1.0, 1.25, SETTLED):
        out, record = apply_sensor(texture, (0.0, 0.0), t, CLEAN, np.random.default_rng(0))
        assert record.defocus_px == pytest.approx(defocus_radius(t, config))
        scores.append(sharpness(out))
        truth.append(sharpness_truth(record))
    assert np.all(np.diff(scores) > 0)
    assert np.all(np.diff(truth) > 0) and truth[-1] == 1.0


def test_truth_ranks_frames_like_the_paper_score(texture):
    rng = np.random.default_rng(11)
    config = SensorConfig()
    scores, truth = [], []
    for seed in range(24):
        speed, angle = rng.choice([0.0, rng.uniform(0, 1200)]), rng.uniform(0, np.pi)
        velocity = speed * np.array([np.cos(angle), np.sin(angle)])
        since_stop = rng.choice([SETTLED, rng.uniform(0, 2)])
        out, record = apply_sensor(texture, velocity, since_stop, config,
                                   np.random.default_rng(seed))
        scores.append(sharpness(out))
        truth.append(sharpness_truth(record))
    assert spearmanr(truth, scores).statistic > 0.9
    assert truth[int(np.argmax(scores))] == 1.0, "the sharpest-looking frame is sharp"


def test_deterministic_with_the_seed(texture):
    config = SensorConfig()
    a, ra = apply_sensor(texture, (250.0, -80.0), 0.4, config, np.random.default_rng(3))
    b, rb = apply_sensor(texture, (250.0, -80.0), 0.4, config, np.random.default_rng(3))
    c, _ = apply_sensor(texture, (250.0, -80.0), 0.4, config, np.random.default_rng(4))
    assert np.array_equal(a, b) and ra == rb
    assert not np.array_equal(a, c)
    assert a.shape == texture.shape and a.dtype == np.uint8


def test_jpeg_compression_is_applied(texture):
    rough = apply_sensor(texture, (0, 0), SETTLED, SensorConfig(jpeg_quality=20),
                         np.random.default_rng(0))[0]
    fine = apply_sensor(texture, (0, 0), SETTLED, SensorConfig(jpeg_quality=95),
                        np.random.default_rng(0))[0]
    error = [np.abs(image.astype(float) - texture).mean() for image in (rough, fine)]
    assert error[0] > 1.5 * error[1]


def test_image_velocity_of_a_turning_camera():
    k = intrinsics_from_config()
    start = look_at([0.0, 0.0, 0.3], [1.0, 0.0, 0.3])
    turn = np.radians(1.0)  # counter-clockwise seen from above: the view swings left
    rotation = np.array([[np.cos(turn), -np.sin(turn), 0], [np.sin(turn), np.cos(turn), 0],
                         [0, 0, 1]])
    end = start.copy()
    end[:3, :3] = rotation @ start[:3, :3]
    velocity = image_velocity(start, end, 0.1, k, distance_m=0.5)
    # The scene moves right in the image at fx * angular speed.
    assert velocity[0] == pytest.approx(k.fx * np.tan(turn) / 0.1, rel=1e-6)
    assert abs(velocity[1]) < 1e-6
    slide = start.copy()
    slide[:3, 3] += [0.0, -0.01, 0.0]  # 1 cm to the camera's right
    velocity = image_velocity(start, slide, 0.5, k, distance_m=0.5)
    assert velocity == pytest.approx([-k.fx * 0.01 / 0.5 / 0.5, 0.0])


def test_colour_processing_changes_nothing_by_default(texture):
    image, _ = apply_sensor(texture, np.zeros(2), SETTLED, CLEAN, np.random.default_rng(0))
    assert np.array_equal(image, texture)
    assert process_colour(texture, SensorConfig()) is texture


def test_gain_brightens_and_clips_saturation_pales_about_luma():
    colours = np.array([[100, 50, 20], [200, 200, 200], [20, 150, 40]], np.uint8)
    brighter = process_colour(colours, SensorConfig(gain=1.5))
    assert brighter.tolist() == [[150, 75, 30], [255, 255, 255], [30, 225, 60]]
    grey = process_colour(colours, SensorConfig(saturation=0.0)).astype(int)
    luma = colours @ np.array([0.299, 0.587, 0.114])
    assert np.all(np.abs(grey - np.rint(luma)[:, None]) <= 1)  # every channel at the luma
    paler = rgb_to_hsv(process_colour(colours, SensorConfig(saturation=0.6)))[:, 1]
    assert np.all(paler[[0, 2]] < rgb_to_hsv(colours)[[0, 2], 1])


def test_a_warm_white_balance_moves_a_leaf_green_toward_yellow():
    leaf = np.array([[60, 110, 40]], np.uint8)
    warm = process_colour(leaf, SensorConfig(white_balance=(1.2, 1.0, 0.8)))
    assert rgb_to_hsv(warm)[0, 0] < rgb_to_hsv(leaf)[0, 0] - 5


@pytest.mark.parametrize("setting", [{"gain": 0.0}, {"saturation": -0.1},
                                     {"white_balance": (1.0, 0.0, 1.0)},
                                     {"white_balance": (1.0, 1.0)}])
def test_bad_colour_processing_is_refused(setting):
    with pytest.raises(InputError, match="sensor."):
        SensorConfig(**setting)
