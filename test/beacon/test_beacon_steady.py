"""Steady lamps are told from beacons by whether their rows vary beyond their shape and pixel noise."""
from beacon_scenes import glaring_lamp, lamp_image
import numpy as np
import pytest

from vlp_ros.beacon.encoding import packet_waveform, tone_waveform
from vlp_ros.beacon.steady import box_shows_no_modulation, STEADY_MISS

ROW_TIME = 1.5e-5


def steady():
    return packet_waveform(0, chip_rate=1.0 / (3 * ROW_TIME), depth=0.0)


def shows_no_modulation(image, observation) -> bool:
    return box_shows_no_modulation(image, observation.bbox, observation.ellipse)


@pytest.mark.parametrize('peak, blur, radius', [(200.0, 0.8, 25.0), (400.0, 1.6, 40.0), (900.0, 2.0, 60.0),
                                                (250.0, 1.6, 15.0)])
def test_steady_lamps_of_any_look_show_no_modulation(peak, blur, radius):
    # Clipped or not, blurred, with glare and falloff: noise alone lifts the ratio over the threshold in about
    # STEADY_MISS of lamps, so none of 20 should be.
    shown = [shows_no_modulation(*glaring_lamp(steady(), ROW_TIME, 2e-5, radius, peak=peak, blur=blur,
                                               rng=np.random.default_rng(seed)))
             for seed in range(20)]
    assert all(shown), f'{shown.count(False)} of 20 steady lamps read as modulated (expected {20 * STEADY_MISS:.2f})'


@pytest.mark.parametrize('wave', [
    packet_waveform(77, chip_rate=1.0 / (2.5 * ROW_TIME), depth=0.6),  # 2.5 rows per chip
    packet_waveform(200, chip_rate=1.0 / (5 * ROW_TIME), depth=0.3),   # shallow
    tone_waveform(2000.0, depth=0.5),                                  # 33 rows a period: few across the lamp
])
@pytest.mark.parametrize('peak, blur, radius', [(200.0, 1.6, 25.0), (900.0, 2.0, 40.0), (300.0, 1.6, 12.0)])
def test_beacons_clipped_blurred_or_small_show_modulation(wave, peak, blur, radius):
    for seed in range(5):
        image, observation = glaring_lamp(wave, ROW_TIME, 2e-5, radius, peak=peak, blur=blur,
                                          rng=np.random.default_rng(seed))
        assert not shows_no_modulation(image, observation)


def test_sharp_colour_lamp_with_its_marker():
    wave = packet_waveform(77, chip_rate=1.0 / (3 * ROW_TIME), depth=0.5)
    image, observation = lamp_image(wave, ROW_TIME, 2e-5, (50.0, 35.0), angle=0.4, bgr=True)
    assert not shows_no_modulation(image, observation)
    image, observation = lamp_image(steady(), ROW_TIME, 2e-5, (50.0, 35.0), angle=0.4, bgr=True)
    assert shows_no_modulation(image, observation)


def test_a_lamp_of_too_few_rows_or_wholly_clipped_is_left_to_the_decoder():
    image, observation = glaring_lamp(steady(), ROW_TIME, 2e-5, 6.0, peak=200.0)
    assert not shows_no_modulation(image, observation)
    image, observation = glaring_lamp(steady(), ROW_TIME, 2e-5, 30.0, peak=200.0)
    assert not shows_no_modulation(np.full_like(image, 255), observation)
