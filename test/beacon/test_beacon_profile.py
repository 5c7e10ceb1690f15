"""Row profiles: which pixels a lamp's brightness per row is read from, and its envelope."""
import dataclasses

from beacon_scenes import lamp_image
import cv2
import numpy as np
import pytest

from vlp_ros.beacon.decoding import decode_packet, decode_tone
from vlp_ros.beacon.encoding import packet_waveform
from vlp_ros.beacon.profile import relative_brightness, row_profile, RowProfile

ROW_TIME = 2e-5
EXPOSURE = 3e-5


def striped_lamp(**kwargs):
    wave = packet_waveform(77, chip_rate=1.0 / (5 * ROW_TIME), depth=0.6)
    return wave, lamp_image(wave, ROW_TIME, EXPOSURE, (60.0, 45.0), angle=0.4, **kwargs)


def test_profile_follows_the_light_row_by_row():
    wave, (image, observation) = striped_lamp(noise=1.0, falloff=0.0)
    profile = row_profile(image, observation)
    x0, y0, x1, y1 = observation.bbox
    assert profile.first_row == y0 and len(profile.values) == y1 - y0
    level = wave.mean_brightness(ROW_TIME * np.arange(y0, y1), EXPOSURE)
    used = profile.weights > 0
    # Background 12 DN plus 180 DN x level: the lamp's pixels only, nothing of the background.
    np.testing.assert_allclose(profile.values[used], 12.0 + 180.0 * level[used], atol=1.5)


def test_curved_edge_and_marker_are_left_out_and_short_rows_weigh_less():
    _, (image, observation) = striped_lamp()
    profile = row_profile(image, observation, edge_margin=2, marker_margin=2)
    disc_rows = observation.disc_mask.sum(axis=1)
    assert np.all(profile.weights <= disc_rows - 4 * (disc_rows > 0) + 1e-9)
    middle = len(profile.weights) // 2
    assert profile.weights[middle] > 5 * profile.weights[np.flatnonzero(profile.weights)[0]]
    plain = row_profile(image, dataclasses.replace(observation, marker_mask=None))
    # The marker is a third as bright as the disc: keeping it darkens its rows.
    marker_rows = np.flatnonzero(observation.marker_mask.any(axis=1))
    assert np.all(plain.values[marker_rows] < profile.values[marker_rows] - 1.0)


def test_bgr_and_mono_frames_give_the_same_profile():
    _, (mono, observation) = striped_lamp(rng=np.random.default_rng(3))
    _, (bgr, _) = striped_lamp(rng=np.random.default_rng(3), bgr=True)
    a, b = row_profile(mono, observation), row_profile(bgr, observation)
    np.testing.assert_allclose(a.values, b.values, atol=0.01)
    np.testing.assert_array_equal(a.weights, b.weights)


def test_saturated_pixels_are_counted_and_kept_at_the_ceiling():
    wave = packet_waveform(77, chip_rate=1.0 / (5 * ROW_TIME), depth=0.5)
    image, observation = lamp_image(wave, ROW_TIME, 1e-6, (60.0, 45.0), peak=400.0, falloff=0.0)
    profile = row_profile(image, observation)
    level = wave.level_at(ROW_TIME * np.arange(observation.bbox[1], observation.bbox[3]))
    used = profile.weights > 0
    bright, dark = used & (level == 1.0), used & (level == 0.5)
    assert np.all(profile.saturated[bright] > 0.9) and np.all(profile.saturated[dark] == 0.0)
    assert np.all(profile.values[bright] == 255.0)
    assert np.all(profile.values[dark] < 230.0)


def opencv_profile(image, observation, margin, ceiling):
    """Return the profile written with OpenCV's morphology on whole masks: eroded disc, minus dilated marker."""
    x0, y0, x1, y1 = observation.bbox
    square = np.ones((2 * margin + 1, 2 * margin + 1), np.uint8)
    mask = cv2.erode(observation.disc_mask.astype(np.uint8), square, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    if observation.marker_mask is not None:
        mask &= 1 - cv2.dilate(observation.marker_mask.astype(np.uint8), square)
    roi = image[y0:y1, x0:x1].astype(np.int64)
    luma = cv2.cvtColor(image[y0:y1, x0:x1], cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image[y0:y1, x0:x1]
    peak = roi.max(axis=2) if roi.ndim == 3 else roi
    counts = mask.sum(axis=1).astype(float)
    valid = np.maximum(counts, 1.0)
    return (luma * mask).sum(axis=1) / valid, counts, ((peak >= ceiling) & (mask > 0)).sum(axis=1) / valid


@pytest.mark.parametrize('seed', range(6))
def test_profile_equals_whole_mask_morphology(seed):
    rng = np.random.default_rng(seed)
    wave = packet_waveform(77, chip_rate=1.0 / (5 * ROW_TIME), depth=0.6)
    image, observation = lamp_image(wave, ROW_TIME, EXPOSURE, tuple(rng.uniform(8.0, 60.0, 2)),
                                    angle=rng.uniform(0.0, np.pi), peak=rng.uniform(150.0, 400.0),
                                    bgr=bool(seed % 2), marker=seed != 4, rng=rng)
    for margin in (0, 1, 2):
        profile = row_profile(image, observation, edge_margin=margin, marker_margin=margin)
        values, counts, saturated = opencv_profile(image, observation, margin, 255)
        np.testing.assert_array_equal(profile.weights, counts)
        np.testing.assert_allclose(profile.values, values, rtol=0.0, atol=1e-6)  # grey levels
        np.testing.assert_array_equal(profile.saturated, saturated)


def test_disc_of_several_runs_per_row_is_rejected():
    _, (image, observation) = striped_lamp()
    ring = observation.disc_mask.copy()
    ring[len(ring) // 2, ring.shape[1] // 2] = False
    with pytest.raises(ValueError, match='several runs'):
        row_profile(image, dataclasses.replace(observation, disc_mask=ring))


def test_relative_brightness_spans_the_usable_rows_around_their_weighted_mean():
    values = np.array([0.0, 0.0, 90.0, 110.0, 0.0, 120.0, 80.0, 0.0])
    weights = np.array([0.0, 0.0, 10.0, 30.0, 0.0, 20.0, 40.0, 0.0])
    z, w, usable = relative_brightness(RowProfile(values, weights, np.zeros(8), 0))
    assert usable == 4
    np.testing.assert_array_equal(w, weights[2:7])
    mean = (values @ weights) / weights.sum()
    used = w > 0
    np.testing.assert_allclose(z[used], values[2:7][used] / mean - 1.0)
    assert abs(z[used] @ w[used]) / w[used].sum() < 1e-9  # a weighted mean of relative brightness


def test_a_profile_without_usable_rows_is_empty():
    z, w, usable = relative_brightness(RowProfile(np.ones(5), np.zeros(5), np.zeros(5), 0))
    assert (len(z), len(w), usable) == (0, 0, 0)


def test_negative_weights_are_refused_by_both_decoders():
    weights = np.full(60, 20.0)
    weights[30] = -1.0
    profile = RowProfile(np.full(60, 100.0), weights, np.zeros(60), 0)
    with pytest.raises(ValueError, match='must not be negative'):
        decode_packet(profile, 1.0 / (5 * ROW_TIME), ROW_TIME)
    with pytest.raises(ValueError, match='must not be negative'):
        decode_tone(profile, ROW_TIME, {1: 2000.0}, 60.0)


def test_bad_inputs_are_rejected():
    _, (image, observation) = striped_lamp()
    with pytest.raises(ValueError, match='bbox'):
        row_profile(image[:50], observation)
    with pytest.raises(ValueError, match='disc_mask'):
        row_profile(image, dataclasses.replace(observation, disc_mask=observation.disc_mask[1:]))
    with pytest.raises(ValueError, match='mono'):
        row_profile(image[..., None], observation)
    with pytest.raises(ValueError, match='same length'):
        RowProfile(np.zeros(3), np.zeros(2), np.zeros(3), 0)
