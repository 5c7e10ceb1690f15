"""The beacon contract: packets as chips, read back by the packet decoder, and the light they make."""
from beacon_scenes import flat_profile
import numpy as np
import pytest

from vlp_ros.beacon.encoding import (packet_bits, packet_chips, packet_length, packet_waveform, PREAMBLE,
                                     tone_waveform, Waveform)
from vlp_ros.beacon.packet import decode_packet

ROW_TIME = 2e-5
CHIP_RATE = 1.0 / (5 * ROW_TIME)  # five rows a chip
EXPOSURE = 3e-5


def read_back(waveform: Waveform, id_bits: int = 8, start: float = 0.0) -> int | None:
    """Return the ID the packet decoder reads from two packets' clean rows of ``waveform``."""
    profile = flat_profile(waveform, 2 * 5 * packet_length(id_bits), ROW_TIME, EXPOSURE, start)
    return decode_packet(profile, CHIP_RATE, ROW_TIME, id_bits).lamp_id


@pytest.mark.parametrize('id_bits', [1, 4, 8, 12])
def test_every_id_round_trips(id_bits):
    ids = range(2 ** id_bits) if id_bits <= 8 else range(0, 2 ** id_bits, 97)
    for lamp_id in ids:
        chips = packet_chips(lamp_id, id_bits)
        assert len(chips) == packet_length(id_bits)
        assert read_back(packet_waveform(lamp_id, CHIP_RATE, 0.7, id_bits), id_bits) == lamp_id


def test_packet_layout_is_preamble_then_manchester_msb_first_with_even_parity():
    chips = packet_chips(0b10110000)
    assert packet_length(8) == 24
    assert tuple(chips[:6]) == PREAMBLE
    # 1 -> 10, 0 -> 01; data 10110000 has three ones: parity 1.
    assert chips[6:].tolist() == [1, 0, 0, 1, 1, 0, 1, 0, 0, 1, 0, 1, 0, 1, 0, 1, 1, 0]
    assert packet_bits(0b10110000) == [1, 0, 1, 1, 0, 0, 0, 0, 1]
    assert packet_bits(0b11)[-1] == 0


def test_back_to_back_packets_decode_from_any_start():
    wave = packet_waveform(201, CHIP_RATE, 0.7)
    assert {read_back(wave, start=k / CHIP_RATE) for k in range(24)} == {201}


@pytest.mark.parametrize('spoilt', ['manchester', 'parity', 'two ids'])
def test_chips_that_no_packet_makes_give_no_id(spoilt):
    chips = packet_chips(77)
    if spoilt == 'manchester':
        chips[9] = chips[8]
    elif spoilt == 'parity':
        chips[8:10] = 1 - chips[8:10]  # a valid Manchester pair, but the other bit
    else:
        chips = np.concatenate([packet_chips(5), packet_chips(6)])
    assert read_back(Waveform(chips, CHIP_RATE, 0.7)) is None


def test_ids_beyond_the_bits_are_rejected():
    with pytest.raises(ValueError, match='does not fit'):
        packet_chips(256)


def test_light_levels_and_exposure_averaging():
    wave = packet_waveform(77, chip_rate=10_000.0, depth=0.6, offset=3e-5)
    chip = 1e-4
    starts = 3e-5 + chip * np.arange(24) + 0.25 * chip
    # A window inside one chip sees that chip's level exactly.
    np.testing.assert_allclose(wave.mean_brightness(starts, 0.5 * chip), 1.0 - 0.6 * (1 - packet_chips(77)))
    # A whole packet averages to the middle level: half the chips are bright.
    assert wave.mean_brightness(np.array([0.123]), 24 * chip)[0] == pytest.approx(0.7)
    tone = tone_waveform(2_000.0, depth=1.0)
    np.testing.assert_allclose(tone.mean_brightness(np.array([0.0, 2.5e-4]), 0.0), [1.0, 0.0], atol=1e-9)
