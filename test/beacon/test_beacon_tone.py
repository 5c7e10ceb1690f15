"""Tone-mode decoding: the lamp whose frequency band holds the stripes' frequency, or None."""
import itertools

from beacon_scenes import flat_profile, lamp_image
import cv2
import numpy as np
import pytest

from vlp_ros.beacon.decoding import decode_tone, row_profile, UNMAPPED
from vlp_ros.beacon.encoding import tone_waveform, Waveform
from vlp_ros.beacon.profile import RowProfile
from vlp_ros.beacon.tone import model, scan

ROW_TIME = 2e-5
# Lamps 200 Hz apart from 1 to 5 kHz, ids 10, 11, ...
FREQUENCIES = {10 + k: 1000.0 + 200.0 * k for k in range(21)}
TOLERANCE = 60.0


def tone_profile(frequency, periods=4.0, exposure=4e-5, depth=0.7, noise=0.3, seed=0, row_time=ROW_TIME,
                 offset=1.7e-4):
    rows = int(np.ceil(periods / (frequency * row_time)))
    return flat_profile(tone_waveform(frequency, depth, offset=offset), rows, row_time, exposure, noise=noise,
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


@pytest.mark.parametrize('lamp_id', [28, 29, 30])
def test_neighbouring_frequencies_told_apart_over_three_periods(lamp_id):
    # 4.6-5 kHz at 20 us rows: about 11 rows per period, 34 rows; 200 Hz apart drift by 0.13 period.
    reading = decode_tone(tone_profile(FREQUENCIES[lamp_id], periods=3.2, exposure=3e-5), ROW_TIME, FREQUENCIES,
                          TOLERANCE, exposure=3e-5)
    assert reading.lamp_id == lamp_id
    others = reading.log_likelihoods[reading.candidates != lamp_id]
    assert np.all(others < reading.log_likelihoods[reading.candidates == lamp_id] - 20.0)


@pytest.mark.parametrize('frequency', [3300.0, 4900.0])
@pytest.mark.parametrize('seed', [0, 1, 2])
def test_frequency_between_lamps_over_a_short_window_is_never_a_lamp(frequency, seed):
    profile = tone_profile(frequency, periods=3.2, exposure=3e-5, seed=seed)
    # With the row time known to 0.1 %, the lamp is recognised as not in the map; known only to 2 %, 3300 Hz
    # lies in the bands of both 3200 and 3400 Hz: still never a lamp.
    reading = decode_tone(profile, ROW_TIME, FREQUENCIES, TOLERANCE, exposure=3e-5, row_time_tolerance=0.001)
    assert reading.lamp_id is None and reading.unknown
    assert decode_tone(profile, ROW_TIME, FREQUENCIES, TOLERANCE, exposure=3e-5).lamp_id is None


def test_frequency_on_a_band_edge_gives_no_id():
    # Lamp 20's band is 3000 +- (60 Hz + 2 % of it): at its edge the frequency is as likely in as out.
    reading = decode_tone(tone_profile(3120.0, periods=3.2, exposure=3e-5), ROW_TIME, FREQUENCIES, TOLERANCE,
                          exposure=3e-5)
    assert reading.lamp_id is None and not reading.unknown


def test_exposure_shorter_than_a_row_places_edges_only_to_a_gap():
    # Exposed for 0.4 of each 50 us row, edges between the rows' exposures move unseen. Over 40 rows of 2 kHz
    # (10 rows per period) that still pins the lamp; over 15 rows of 4.6 kHz it leaves a plateau of
    # frequencies that fit equally well, which must give no ID (not the plateau's best point).
    row_time = 5e-5

    def read(frequency, periods, seed):
        profile = tone_profile(frequency, periods=periods, exposure=0.4 * row_time, noise=0.5, seed=seed,
                               row_time=row_time, offset=1e-4 * seed)
        return decode_tone(profile, row_time, FREQUENCIES, TOLERANCE, exposure=0.4 * row_time).lamp_id

    assert [read(2000.0, 4.0, seed) for seed in range(6)] == [15] * 6
    assert [read(4600.0, 3.5, seed) for seed in range(6)] == [None] * 6


def test_noisy_fast_tone_over_few_rows_gives_no_id():
    # 4.8 kHz at 50 us rows over 3 periods: 13 rows, too noisy to place the period within 60 Hz.
    row_time = 5e-5
    for seed in range(5):
        reading = decode_tone(tone_profile(4800.0, periods=3.0, exposure=2 * row_time, noise=3.0, seed=seed,
                                           row_time=row_time), row_time, FREQUENCIES, TOLERANCE, exposure=2 * row_time)
        assert reading.lamp_id is None and not reading.unknown


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
    reading = decode_tone(tone_profile(frequency, periods=6.0), ROW_TIME, FREQUENCIES, TOLERANCE, exposure=4e-5,
                          row_time_tolerance=0.001)
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


def demosaiced_profile(frequency, row_time, exposure, rows, seed):
    """
    Return a white lamp's rows through an RGGB mosaic, demosaiced as the locator reads bayer_rggb8.

    Each row's luma mixes in its neighbours (w about 0.13 and 0.22 on alternate rows).
    """
    rng = np.random.default_rng(seed)
    profile = flat_profile(tone_waveform(frequency, 0.7, offset=rng.uniform(0.0, 1e-3)), rows + 2, row_time,
                           exposure, noise=0.3, rng=rng)
    mosaic = np.repeat(np.rint(100.0 * profile.values)[:, None], 8, axis=1).astype(np.uint16)
    luma = cv2.cvtColor(cv2.cvtColor(mosaic, cv2.COLOR_BayerBG2BGR), cv2.COLOR_BGR2GRAY)[1:-1, 2:-2]
    return RowProfile(luma.mean(axis=1), np.full(rows, 100.0), np.zeros(rows), 0)


def test_demosaiced_rows_give_the_lamp_or_no_id_never_a_wrong_one():
    # Exposed for half of each 34.6 us row, 8 rows per period: the mix fills the gaps between the rows'
    # exposures, which a model of unmixed rows reads as edges moved (towards a neighbouring band).
    row_time, exposure = 3.46e-5, 0.53 * 3.46e-5
    read = []
    for seed in range(8):
        reading = decode_tone(demosaiced_profile(3600.0, row_time, exposure, 47, seed), row_time, FREQUENCIES,
                              TOLERANCE, exposure=exposure)
        assert reading.lamp_id in (23, None)
        read.append(reading.lamp_id)
        midway = decode_tone(demosaiced_profile(3700.0, row_time, exposure, 47, seed), row_time, FREQUENCIES,
                             TOLERANCE, exposure=exposure)
        assert midway.lamp_id is None
    assert read.count(23) >= 4


@pytest.mark.parametrize('stride', [1, 2, 5])
def test_each_mix_is_fitted_exactly(stride):
    # The fit takes each mix's |m|^2 and m . y from products of a few templates; here every mix is built
    # row by row and fitted by least squares with the envelope.
    rng = np.random.default_rng(stride)
    rows, exposure_rows = 90, 1.3
    z, w = rng.normal(size=rows), rng.uniform(0.5, 1.0, rows)
    fit = model.ToneFit(z, w)
    fit.use(stride)
    cycles, phase = rng.uniform(3.0, 9.0, (4, 2)), rng.uniform(0.0, 1.0, (4, 2))
    kept = np.arange(0, rows, stride)
    u = 2.0 * (kept - 0.5 * (rows - 1)) / rows
    sqrt_w = np.sqrt(w[kept])
    envelope = np.stack([np.ones_like(u), u, u * u], axis=1)
    expected = np.empty(cycles.shape)
    for index in np.ndindex(cycles.shape):
        start = cycles[index] * ((np.arange(-1, rows + 1) - 0.5 * (rows - 1)) / rows) - phase[index]
        # A row's mean of the square wave over its exposure, up to scale.
        mean = np.abs(start - np.rint(start)) - np.abs(start + cycles[index] * exposure_rows / rows
                                                       - np.rint(start + cycles[index] * exposure_rows / rows))
        residuals = []
        for even, odd in itertools.product(model.MIX_LEVELS, repeat=2):
            mix = np.where(np.arange(rows) % 2 == 0, even, odd)
            seen = (1.0 - 2.0 * mix) * mean[1:-1] + mix * (mean[:-2] + mean[2:])
            design = np.column_stack([envelope, seen[kept]]) * sqrt_w[:, None]
            residual = z[kept] * sqrt_w - design @ np.linalg.lstsq(design, z[kept] * sqrt_w, rcond=None)[0]
            residuals.append(residual @ residual)
        own, mixed = residuals[0], min(residuals)
        power = 0.5 * (fit.dof + 1)
        expected[index] = mixed * (model.MIXED_WEIGHT + (mixed / own) ** power) ** (-1.0 / power)
    rss = model.rss(cycles.ravel(), phase.ravel(), np.full(cycles.size, exposure_rows), *fit.model)
    np.testing.assert_allclose(rss.reshape(cycles.shape), expected, rtol=1e-6)  # sums of squares to six digits


def test_a_plateau_of_peaks_gives_no_id():
    # A demosaiced lamp at an unmapped 6.9 kHz over 16 rows (4.2 rows per period, exposed 1.09 rows): the
    # mixed rows fit everything from 6.8 to 7.1 kHz about as well, and the grid, narrowed onto the peak
    # near 7 kHz, sees none of the others (alone it reads lamp 30 at 7 kHz, 0.99999); its wider passes do.
    sums = [1064, 1094, 1002, 1847, 2496, 2101, 1429, 2077, 2839, 2284, 1437, 1669, 2314, 1071, 536, 432]
    pixels = np.array([6, 9, 11, 13, 14, 16, 16, 16, 16, 16, 16, 14, 13, 7, 6, 4], dtype=float)
    profile = RowProfile(np.array(sums) / pixels, pixels, np.zeros(len(pixels)), 0)
    row_time = 3.4585e-5
    lamps = {k: 1000.0 + 200.0 * k for k in range(46)}
    assert decode_tone(profile, row_time, lamps, TOLERANCE, exposure=3.7857e-5).lamp_id is None


@pytest.mark.parametrize('seed', range(4))
def test_spectral_peak_is_the_zero_padded_ffts(seed):
    # The strongest bin of the zero-padded FFT in the range, moved by the parabola through its log power
    # and its neighbours'.
    rng = np.random.default_rng(seed)
    rows = int(rng.integers(40, 300))
    fit = model.ToneFit(np.sin(2 * np.pi * rng.uniform(3, 20) * np.arange(rows) / rows) + rng.normal(size=rows),
                        rng.uniform(0.5, 1.0, rows))
    low, high = rng.uniform(1.0, 4.0), rng.uniform(15.0, 40.0)
    size = scan._PAD * (1 << (rows - 1).bit_length())
    power = np.abs(np.fft.rfft(fit.kept.weighted_y, size)) ** 2
    first, last = int(np.ceil(low * size / rows)), min(int(high * size / rows), len(power) - 1)
    peak = first + int(np.argmax(power[first:last + 1]))
    left, centre, right = np.log(power[peak - 1:peak + 2])
    shift = min(max(0.5 * (left - right) / (left - 2 * centre + right), -0.5), 0.5)
    # One part per million of the frequency: lamps are told apart at parts per hundred.
    assert scan.spectral_peak(fit, low, high) == pytest.approx((peak + shift) * rows / size, rel=1e-6)
    assert scan.spectral_peak(fit, 30.0 * rows, 31.0 * rows) is None


# A robot's tone lamps: 12 from 2000 to 5300 Hz, 300 Hz apart, 15 us rows, 20 us exposure.
SPARSE = {1 + k: 2000.0 + 300.0 * k for k in range(12)}


@pytest.mark.parametrize('lamp_id, periods', [(1, 2.2), (5, 2.5), (9, 2.8), (12, 2.3)])
@pytest.mark.parametrize('row_time_error', [-0.02, 0.0, 0.02])
def test_two_to_three_periods_of_lamps_300_hz_apart_are_read_with_the_row_time_2_percent_off(
        lamp_id, periods, row_time_error):
    # The true row time is (1 + error) x the nominal one: every frequency reads (1 + error) x its own.
    profile = tone_profile(SPARSE[lamp_id], periods=periods, exposure=2e-5, row_time=1.5e-5 * (1 + row_time_error),
                           seed=lamp_id)
    reading = decode_tone(profile, 1.5e-5, SPARSE, 60.0, exposure=2e-5)
    assert reading.lamp_id == lamp_id


@pytest.mark.parametrize('seed', range(4))
def test_a_lamp_half_way_between_lamps_300_hz_apart_is_never_one_of_them(seed):
    profile = tone_profile(3650.0, periods=3.5, exposure=2e-5, row_time=1.5e-5, seed=seed)
    reading = decode_tone(profile, 1.5e-5, SPARSE, 60.0, exposure=2e-5)
    assert reading.lamp_id is None
