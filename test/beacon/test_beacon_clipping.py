"""
Clipped, blurred stripes and complement-closed codebooks: a lamp is read as itself or as nothing.

A lamp bright enough to clip at the ceiling, seen through an ordinary blur, lifts its isolated dark chips to
the ceiling too: the chips then look like a packet that was never sent, and with odd ``id_bits`` the
complement of a packet passes parity. Read as measured levels, such profiles fit other IDs with certainty
(3-bit lamp 5 as its complement 2 at 0.99998, lamp 4 as 2 at 1.0).
"""
import cv2
import numpy as np
import pytest

from vlp_ros.beacon.camera_settings import packet_setting_advice
from vlp_ros.beacon.encoding import complement_closed, packet_bits, packet_waveform
from vlp_ros.beacon.packet import BLUR_MIXES, decode_packet
from vlp_ros.beacon.profile import RowProfile

# The simulator's robot row: 3-bit IDs at 3.09 rows per chip, 1.3 packets in view, 20 us exposure.
ID_BITS = 3
CHIP_RATE = 10492.0
ROW_TIME = 1.0 / (CHIP_RATE * 3.09)
ROWS = 56
MAP = list(range(1, 8))


def clipped_profile(lamp_id: int, seed: int, blur_rows: float, gain: float = 1.64, depth: float = 0.6) -> RowProfile:
    """
    Return the row profile of a lamp ``gain`` times the ceiling at full brightness, blurred, then clipped.

    ``gain`` is the realistic look's overexposure; the lamp's rows are blurred by a Gaussian of
    ``blur_rows`` before the sensor clips them, as a lens does.
    """
    rng = np.random.default_rng([lamp_id, seed])
    wave = packet_waveform(lamp_id, CHIP_RATE, depth, ID_BITS, offset=rng.uniform(0.0, 14.0 / CHIP_RATE))
    pad = 10
    light = gain * wave.mean_brightness(np.arange(-pad, ROWS + pad) * ROW_TIME, 20e-6)
    if blur_rows > 0.0:
        light = cv2.GaussianBlur(light[:, None], (1, 0), sigmaX=0, sigmaY=blur_rows)[:, 0]
    value = np.minimum(light[pad:-pad] + 0.004 * rng.standard_normal(ROWS), 1.0)
    return RowProfile(255.0 * value, np.full(ROWS, 40.0), (value >= 1.0).astype(float), 0)


@pytest.mark.parametrize('mixes', [(0.0,), BLUR_MIXES])
def test_clipped_blurred_stripes_are_never_read_as_another_id(mixes):
    for lamp_id in MAP:
        for seed in range(40):
            reading = decode_packet(clipped_profile(lamp_id, seed, 1.6), CHIP_RATE, ROW_TIME, ID_BITS, MAP,
                                    blur_mixes=mixes)
            assert reading.lamp_id in (None, lamp_id), (lamp_id, seed, reading.detail)


def test_clipped_sharp_stripes_are_still_read():
    """Clipping alone hides nothing: the dark chips stay below the ceiling, and the bright ones at it differ."""
    readings = [decode_packet(clipped_profile(lamp_id, seed, 0.5), CHIP_RATE, ROW_TIME, ID_BITS, MAP).lamp_id
                for lamp_id in MAP for seed in range(20)]
    assert sum(r is not None for r in readings) >= 0.95 * len(readings)
    assert all(r in (None, lamp_id) for r, lamp_id in zip(readings, np.repeat(MAP, 20)))


@pytest.mark.parametrize('lamp_id', MAP)
def test_inverted_stripes_give_no_id(lamp_id):
    """
    Polarity is evidence.

    A 1 chip is the brighter level, so a lamp whose light is inverted (every chip's complement, which with
    odd id_bits is the complement ID's packet with an inverted preamble) is no lamp.
    """
    for seed in range(5):
        profile = clipped_profile(lamp_id, seed, 0.0, gain=0.9)
        inverted = RowProfile(255.0 - profile.values, profile.weights, profile.saturated, 0)
        reading = decode_packet(inverted, CHIP_RATE, ROW_TIME, ID_BITS, MAP)
        assert reading.lamp_id is None


def test_odd_id_bits_make_the_codebook_complement_closed():
    for bits in (1, 3, 5, 7, 9):
        assert complement_closed(bits)
        word = packet_bits(1, bits)
        complement = [1 - b for b in word]
        assert sum(complement) % 2 == 0
    assert not any(complement_closed(bits) for bits in (2, 4, 8, 16))


def test_odd_id_bits_are_named_at_start():
    (advice,) = packet_setting_advice(CHIP_RATE, ROW_TIME, None, ID_BITS)
    assert 'beacon.id_bits 3' in advice and 'complement' in advice
    assert packet_setting_advice(CHIP_RATE, ROW_TIME, None, 8) == []
