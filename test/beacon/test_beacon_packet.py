"""Packet-mode decoding: the right ID or None, never another one."""
from beacon_scenes import flat_profile, lamp_image
import numpy as np
import pytest

from vlp_ros.beacon import packet
from vlp_ros.beacon.chips import chip_levels
from vlp_ros.beacon.decoding import decode_packet, row_profile
from vlp_ros.beacon.encoding import packet_chips, packet_waveform, Waveform

ROW_TIME = 2e-5
ROWS_PER_CHIP = 5.0
CHIP_RATE = 1.0 / (ROWS_PER_CHIP * ROW_TIME)
MAP = [3, 17, 77, 130, 201, 254]


def profile_of(lamp_id, packets=1.5, depth=0.7, chip_rate=CHIP_RATE, noise=0.5, seed=0, start=3.3e-4):
    wave = packet_waveform(lamp_id, chip_rate, depth, offset=start)
    rows = int(round(packets * 24 * ROWS_PER_CHIP))
    return flat_profile(wave, rows, ROW_TIME, 3e-5, noise=noise, rng=np.random.default_rng(seed))


@pytest.mark.parametrize('lamp_id', [0, 1, 85, 170, 254, 255])
def test_every_kind_of_id_decodes_from_one_and_a_half_packets(lamp_id):
    for start in (0.0, 7.7e-4, 1.9e-3):
        reading = decode_packet(profile_of(lamp_id, start=start), CHIP_RATE, ROW_TIME, 8, None)
        assert reading.lamp_id == lamp_id and reading.confidence > 0.9999
        assert np.argmax(reading.log_likelihoods) == lamp_id


@pytest.mark.parametrize('depth', [0.3, 0.5, 1.0])
def test_depth_from_thirty_to_hundred_percent(depth):
    assert decode_packet(profile_of(130, depth=depth), CHIP_RATE, ROW_TIME, 8, MAP).lamp_id == 130


@pytest.mark.parametrize('error', [-0.04, -0.02, 0.02, 0.04])
def test_chip_rate_known_to_a_few_percent(error):
    profile = profile_of(201, packets=2.0, chip_rate=CHIP_RATE * (1.0 + error))
    assert decode_packet(profile, CHIP_RATE, ROW_TIME, 8, MAP).lamp_id == 201


def test_far_wrong_chip_rate_gives_no_id():
    for error in (-0.2, 0.25):
        profile = profile_of(201, packets=2.0, chip_rate=CHIP_RATE * (1.0 + error))
        assert decode_packet(profile, CHIP_RATE, ROW_TIME, 8, MAP).lamp_id is None


def test_id_outside_the_map_is_recognised_and_rejected():
    reading = decode_packet(profile_of(100), CHIP_RATE, ROW_TIME, 8, MAP)
    assert reading.lamp_id is None and reading.unknown
    assert 'not in the map' in reading.detail


def test_partial_packet_matches_only_among_the_map_when_the_map_is_trusted():
    profile = profile_of(77, packets=0.7, seed=4, start=1.0e-3)
    trusting = decode_packet(profile, CHIP_RATE, ROW_TIME, 8, MAP, unmapped_weight=0.0)
    assert trusting.lamp_id == 77
    # Unseen bits leave unmapped IDs as likely as 77: no decision.
    assert decode_packet(profile, CHIP_RATE, ROW_TIME, 8, MAP).lamp_id is None


def test_window_too_short_gives_no_evidence():
    reading = decode_packet(profile_of(77, packets=0.1), CHIP_RATE, ROW_TIME, 8, MAP)
    assert reading.lamp_id is None and not np.any(reading.log_likelihoods)


def test_noise_or_steady_light_gives_no_id():
    rng = np.random.default_rng(1)
    noise = flat_profile(Waveform(np.array([1], dtype=np.uint8), 1.0, 0.0), 180, ROW_TIME, 3e-5, noise=2.0, rng=rng)
    assert decode_packet(noise, CHIP_RATE, ROW_TIME, 8, None).lamp_id is None
    steady = flat_profile(Waveform(np.array([1], dtype=np.uint8), 1.0, 0.0), 180, ROW_TIME, 3e-5)
    assert decode_packet(steady, CHIP_RATE, ROW_TIME, 8, None).lamp_id is None


def test_broken_parity_is_never_read_as_a_neighbour():
    chips = packet_chips(77)
    chips[8:10] = 1 - chips[8:10]  # valid Manchester, parity now odd: one bit from two valid packets
    wave = Waveform(chips, CHIP_RATE, 0.7, 2e-4)
    profile = flat_profile(wave, 240, ROW_TIME, 3e-5, noise=0.5)
    assert decode_packet(profile, CHIP_RATE, ROW_TIME, 8, None).lamp_id is None


def test_manchester_violation_is_never_read_as_an_id():
    chips = packet_chips(77)
    chips[11] = chips[10]
    wave = Waveform(chips, CHIP_RATE, 0.7, 2e-4)
    profile = flat_profile(wave, 240, ROW_TIME, 3e-5, noise=0.5)
    assert decode_packet(profile, CHIP_RATE, ROW_TIME, 8, None).lamp_id is None


@pytest.mark.parametrize('bgr', [False, True])
def test_from_an_image_of_a_tilted_dimming_lamp(bgr):
    wave = packet_waveform(17, CHIP_RATE * 1.02, 0.6, offset=1.1e-4)
    image, observation = lamp_image(wave, ROW_TIME, 3e-5, (110.0, 80.0), angle=0.7, falloff=0.3, bgr=bgr,
                                    rng=np.random.default_rng(5))
    reading = decode_packet(row_profile(image, observation), CHIP_RATE, ROW_TIME, 8, MAP, exposure=3e-5)
    assert reading.lamp_id == 17


def test_saturated_lamp_still_decodes():
    wave = packet_waveform(254, CHIP_RATE, 0.6, offset=1.1e-4)
    image, observation = lamp_image(wave, ROW_TIME, 3e-5, (100.0, 80.0), peak=380.0, rng=np.random.default_rng(6))
    profile = row_profile(image, observation)
    assert profile.saturated.max() > 0.5
    assert decode_packet(profile, CHIP_RATE, ROW_TIME, 8, MAP).lamp_id == 254


def test_bad_inputs_are_rejected():
    profile = profile_of(77)
    with pytest.raises(ValueError, match='positive'):
        decode_packet(profile, 0.0, ROW_TIME, 8, MAP)
    with pytest.raises(ValueError, match='id_bits'):
        decode_packet(profile, CHIP_RATE, ROW_TIME, 0, MAP)
    with pytest.raises(ValueError, match='do not fit'):
        decode_packet(profile, CHIP_RATE, ROW_TIME, 4, MAP)
    with pytest.raises(ValueError, match='more than one row'):
        decode_packet(profile, 1.0 / (0.5 * ROW_TIME), ROW_TIME, 8, MAP)


def test_short_rows_at_the_lamps_ends_still_give_chips():
    # A disc's rows near its top and bottom hold few pixels: the chips they show are noisier, not missing.
    chips = packet_chips(77)[:13] * 2.0 - 1.0
    z = np.repeat(chips, 5)[:62]  # the last chip shows two rows, its middle half three quarters of one
    w = np.full(62, 100.0)
    w[-3:] = w[:3] = 8.0
    levels = chip_levels(z, w, 5.0, 0.05, None)
    assert levels.index.tolist() == list(range(13))
    np.testing.assert_allclose(levels.levels, chips, atol=0.05)


@pytest.mark.parametrize('id_bits, lamp_id', [(1, 1), (4, 9), (12, 2741)])
def test_other_id_widths_decode(id_bits, lamp_id):
    wave = packet_waveform(lamp_id, CHIP_RATE, 0.7, id_bits, offset=3.3e-4)
    rows = int(1.5 * (6 + 2 * (id_bits + 1)) * ROWS_PER_CHIP)
    profile = flat_profile(wave, rows, ROW_TIME, 3e-5, noise=0.5, rng=np.random.default_rng(2))
    reading = decode_packet(profile, CHIP_RATE, ROW_TIME, id_bits, None)
    assert reading.lamp_id == lamp_id and np.argmax(reading.log_likelihoods) == lamp_id


@pytest.mark.parametrize('mix', [0.0, 0.2])
def test_id_likelihoods_equal_a_least_squares_fit_of_every_id_and_shift(mix):
    # Each (ID, shift) fitted directly: a weighted quadratic baseline in the chip index plus a positive
    # contrast times the chip signs, each mixed with its neighbours' by ``mix`` (blur across rows); its half
    # gain over the baseline alone, marginalised over shifts.
    rng = np.random.default_rng(5)
    id_bits, length = 4, 16

    def template(lamp_id, k, shift):
        chips = packet_chips(lamp_id, id_bits) * 2.0 - 1.0
        return chips[(k + shift) % length] + mix * (chips[(k + shift - 1) % length] + chips[(k + shift + 1) % length])

    k = np.sort(rng.choice(40, 30, replace=False))
    x = template(9, k, 5) * 0.8 + rng.normal(0.0, 0.5, len(k))
    v = rng.uniform(0.5, 3.0, len(k))
    log_likelihoods, misfit = packet._id_log_likelihoods(x, v, k, id_bits, (mix,))
    sqrt_v = np.sqrt(v)
    baseline = np.column_stack([np.ones(len(k)), k, k * k]) * sqrt_v[:, None]

    def rss(design):
        coef = np.linalg.lstsq(design, x * sqrt_v, rcond=None)[0]
        residual = x * sqrt_v - design @ coef
        return residual @ residual, coef[-1]

    rss0 = rss(baseline)[0]
    gains = np.zeros((2 ** id_bits, length))
    for lamp_id in range(2 ** id_bits):
        for shift in range(length):
            rss1, contrast = rss(np.column_stack([baseline, template(lamp_id, k, shift) * sqrt_v]))
            gains[lamp_id, shift] = 0.5 * (rss0 - rss1) if contrast > 0.0 else 0.0
    expected = np.log(np.exp(gains).mean(axis=1)) - 0.5 * rss0
    np.testing.assert_allclose(log_likelihoods, expected, rtol=1e-4, atol=1e-4)
    assert misfit == pytest.approx(rss0 - 2.0 * gains.max(), rel=1e-4)
    assert np.argmax(log_likelihoods) == 9


@pytest.mark.parametrize('id_bits', [4, 8])
def test_id_likelihoods_of_several_mixes_are_their_mean_likelihood_and_their_best_fit(id_bits):
    # The mixes are taken in one pass: each must weigh the IDs as it does alone, the blur's mix equally likely.
    rng = np.random.default_rng(id_bits)
    length = len(packet_chips(0, id_bits))
    k = np.sort(rng.choice(2 * length, length + 6, replace=False))
    chips = packet_chips(3, id_bits) * 2.0 - 1.0
    x = 0.7 * chips[(k + 2) % length] + rng.normal(0.0, 0.3, len(k))
    v = rng.uniform(0.5, 3.0, len(k))
    mixes = (0.0, 0.15, 0.3)
    together, misfit = packet._id_log_likelihoods(x, v, k, id_bits, mixes)
    alone = [packet._id_log_likelihoods(x, v, k, id_bits, (mix,)) for mix in mixes]
    each = np.array([log_likelihoods for log_likelihoods, _ in alone])
    top = each.max(axis=0)
    np.testing.assert_allclose(together, top + np.log(np.exp(each - top).mean(axis=0)), rtol=0.0, atol=1e-9)
    assert misfit == pytest.approx(min(fit for _, fit in alone), abs=1e-9)
    assert np.argmax(together) == 3
    # Above the misfit limit no likelihoods are taken, whichever the mixes.
    assert packet._id_log_likelihoods(x, v, k, id_bits, mixes, misfit_limit=0.5 * misfit) == (None, misfit)


def test_trying_grids_around_the_found_one_never_finds_a_wrong_id_in_chips_it_does_not_model():
    """
    An exposure of two chips smears each chip over three (beyond the blur mixes).

    The found grid misfits, and trying grids around it must not find one where another ID fits: the found
    grid has to fit, and the others to fit well.
    """
    row_time = 1.5e-5
    for rows_per_chip in (4.0, 7.7):
        rate = 1.0 / (rows_per_chip * row_time)
        for lamp_id in MAP + [66, 126]:
            for seed in range(3):
                rng = np.random.default_rng([lamp_id, seed])
                wave = packet_waveform(lamp_id, rate, 0.7, offset=rng.uniform(0.0, 24.0 / rate))
                profile = flat_profile(wave, int(1.6 * 24 * rows_per_chip), row_time, 2.0 / rate, noise=0.5, rng=rng)
                reading = decode_packet(profile, rate * 1.01, row_time, 8, MAP + [66], blur_mixes=packet.BLUR_MIXES)
                assert reading.lamp_id in (None, lamp_id), (rows_per_chip, lamp_id, seed)
