"""Tone-mode decoding: the lamp whose frequency band holds the stripes' frequency, or None."""
import numpy as np
import pytest
from beacon_scenes import flat_profile, lamp_image

from vlp_ros.beacon.decoding import UNMAPPED, decode_tone, row_profile
from vlp_ros.beacon.encoding import Waveform, tone_waveform

ROW_TIME = 2e-5
# Lamps 200 Hz apart from 1 to 5 kHz, ids 10, 11, ...
FREQUENCIES = {10 + k: 1000.0 + 200.0 * k for k in range(21)}
TOLERANCE = 60.0


def tone_profile(frequency, periods=4.0, exposure=4e-5, depth=0.7, noise=0.3, seed=0):
    rows = int(np.ceil(periods / (frequency * ROW_TIME)))
    return flat_profile(tone_waveform(frequency, depth, offset=1.7e-4), rows, ROW_TIME, exposure, noise=noise,
                        rng=np.random.default_rng(seed))


@pytest.mark.parametrize('lamp_id', [10, 17, 23, 30])
def test_lamp_found_by_its_frequency(lamp_id):
    frequency = FREQUENCIES[lamp_id] * 1.004
    reading = decode_tone(tone_profile(frequency), ROW_TIME, FREQUENCIES, TOLERANCE, exposure=4e-5)
    assert reading.lamp_id == lamp_id and reading.confidence > 0.9999
    assert reading.candidates[np.argmax(reading.log_likelihoods)] == lamp_id


@pytest.mark.parametrize('exposure', [3e-5, 6e-5, 1.2e-4])
def test_three_periods_suffice_at_any_known_exposure(exposure):
    reading = decode_tone(tone_profile(2600.0, periods=3.2, exposure=exposure), ROW_TIME, FREQUENCIES, TOLERANCE,
                          exposure=exposure)
    assert reading.lamp_id == 18


def test_exposure_of_about_a_period_gives_no_id():
    # 8.4 kHz over 125 us: 1.05 periods per exposure, the stripes all but average away.
    profile = tone_profile(8400.0, periods=8.0, exposure=1.25e-4, noise=0.05)
    reading = decode_tone(profile, ROW_TIME, {**FREQUENCIES, 99: 8400.0}, TOLERANCE, exposure=1.25e-4)
    assert reading.lamp_id is None and 'washed out' in reading.detail


def test_unknown_exposure_needs_more_periods():
    # Blur across rows can pass for a longer exposure: edges count only to the nearest row.
    short = decode_tone(tone_profile(4600.0, periods=3.2), ROW_TIME, FREQUENCIES, TOLERANCE)
    assert short.lamp_id is None and not short.unknown
    assert decode_tone(tone_profile(4600.0, periods=12.0), ROW_TIME, FREQUENCIES, TOLERANCE).lamp_id == 28


@pytest.mark.parametrize('frequency', [2100.0, 5800.0])
def test_frequency_between_or_beyond_the_lamps_is_rejected(frequency):
    reading = decode_tone(tone_profile(frequency, periods=6.0), ROW_TIME, FREQUENCIES, TOLERANCE, exposure=4e-5)
    assert reading.lamp_id is None and reading.unknown
    assert reading.candidates[np.argmax(reading.log_likelihoods)] == UNMAPPED


def test_too_few_periods_or_no_stripes_give_no_id():
    assert decode_tone(tone_profile(2000.0, periods=1.0), ROW_TIME, FREQUENCIES, TOLERANCE).lamp_id is None
    steady = flat_profile(Waveform(np.array([1], dtype=np.uint8), 1.0, 0.0), 120, ROW_TIME, 4e-5, noise=1.0,
                          rng=np.random.default_rng(2))
    reading = decode_tone(steady, ROW_TIME, FREQUENCIES, TOLERANCE)
    assert reading.lamp_id is None and not reading.unknown


def test_from_an_image_of_a_tilted_lamp():
    image, observation = lamp_image(tone_waveform(3400.0, 0.6, offset=2e-5), ROW_TIME, 5e-5, (90.0, 60.0),
                                    angle=1.1, falloff=0.3, rng=np.random.default_rng(4))
    reading = decode_tone(row_profile(image, observation), ROW_TIME, FREQUENCIES, TOLERANCE, exposure=5e-5)
    assert reading.lamp_id == 22


def test_bad_inputs_are_rejected():
    profile = tone_profile(2000.0)
    with pytest.raises(ValueError, match='at least one'):
        decode_tone(profile, ROW_TIME, {}, TOLERANCE)
    with pytest.raises(ValueError, match='Nyquist'):
        decode_tone(profile, ROW_TIME, {1: 30_000.0}, TOLERANCE)
    with pytest.raises(ValueError, match='tolerance'):
        decode_tone(profile, ROW_TIME, FREQUENCIES, 0.0)
    with pytest.raises(ValueError, match='exposure'):
        decode_tone(profile, ROW_TIME, FREQUENCIES, TOLERANCE, exposure=0.0)
