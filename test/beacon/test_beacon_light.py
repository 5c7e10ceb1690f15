"""The light profile: every row a lamp's light reaches, its glow included, and clipped discs read on it."""
from beacon_scenes import glaring_lamp
import numpy as np
import pytest

from vlp_ros.beacon.decoding import decode_packet, decode_tone, light_profile, read_lamp
from vlp_ros.beacon.encoding import packet_waveform, Waveform

ROW_TIME = 1.5e-5
CHIP_RATE = 1.0 / (5 * ROW_TIME)
MAP = [3, 17, 77, 130, 201, 254]


def test_a_clipped_disc_is_read_on_its_glow_and_dark_rows():
    wave = packet_waveform(77, CHIP_RATE, depth=0.6)
    image, observation = glaring_lamp(wave, ROW_TIME, 1e-5, 60.0, peak=500.0)
    assert (image == 255).mean() > 0.02
    profile = light_profile(image, observation)
    rows = profile.first_row + np.arange(len(profile.values))
    truth = wave.mean_brightness(ROW_TIME * rows, 1e-5)
    used = profile.weights > 0
    disc_rows = (rows >= observation.bbox[1]) & (rows < observation.bbox[3])
    # The glow reaches rows above and below the disc, and they count.
    assert used[~disc_rows].sum() > 20
    # Bright rows are clipped on the disc: the glow says how bright they were.
    assert np.corrcoef(profile.values[used], truth[used])[0, 1] > 0.9


def test_a_clipped_glaring_lamp_with_a_packet_and_a_half_is_read():
    wave = packet_waveform(201, CHIP_RATE, depth=0.6, offset=3e-4)
    image, observation = glaring_lamp(wave, ROW_TIME, 1e-5, 95.0, peak=450.0, blur=0.8)
    reading = decode_packet(light_profile(image, observation), CHIP_RATE, ROW_TIME, 8, MAP)
    assert reading.lamp_id == 201


def test_an_unmodulated_glaring_lamp_is_never_identified():
    steady = Waveform(np.array([1, 1]), chip_rate=1000.0, depth=0.5)
    for seed in range(3):
        image, observation = glaring_lamp(steady, ROW_TIME, 1e-5, 60.0, peak=400.0, rng=np.random.default_rng(seed))
        profile = light_profile(image, observation)
        assert decode_packet(profile, CHIP_RATE, ROW_TIME, 8, MAP).lamp_id is None
        tone = decode_tone(profile, ROW_TIME, {1: 2000.0, 2: 2300.0, 3: 2600.0}, 60.0, exposure=2e-5)
        assert tone.lamp_id is None and not tone.unknown


@pytest.mark.parametrize('offset', [1e-4, 4e-4, 7e-4])
def test_a_packet_blurred_by_2_px_with_glare_is_read(offset):
    # 5 rows per chip under a 2 px blur: an isolated chip keeps about half its contrast.
    wave = packet_waveform(130, CHIP_RATE, depth=0.6, offset=offset)
    image, observation = glaring_lamp(wave, ROW_TIME, 1e-5, 95.0, peak=200.0, blur=2.0, rng=np.random.default_rng(1))
    reading = read_lamp(image, observation, lambda profile: decode_packet(profile, CHIP_RATE, ROW_TIME, 8, MAP))
    assert reading.lamp_id == 130
    sharp_only = read_lamp(image, observation, lambda profile: decode_packet(profile, CHIP_RATE, ROW_TIME, 8, MAP,
                                                                             blur_mixes=(0.0,)))
    assert sharp_only.lamp_id in (None, 130)
