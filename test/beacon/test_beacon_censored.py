"""
A clipped, blurred disc read with its clipped chips censored: "at least this bright", not "this bright".

The simulator's realistic look puts the paper's lamp 2.2 times over the sensor's ceiling behind a 1.6 px
blur and a diffuser 30 % dimmer at its rim: the bright chips all read the ceiling, whether a run or one chip
between dark ones, and in the disc's middle blur lifts isolated dark chips over it too. The Gaussian reading
misfits such a disc and refuses it;
``decode_clipped_packet`` reads it, and never as another ID.
"""
import numpy as np
import pytest

from vlp_ros.beacon.censored import (_bounds_from_sums, _fits_that_can_win, _folded, _hypothesis_sums, _packet_masks,
                                     _signs, _sound_bounds_from_sums, _template_tables, censored_log_likelihoods)
from vlp_ros.beacon.encoding import packet_chips, packet_length, packet_waveform
from vlp_ros.beacon.evidence import EvidenceTracker
from vlp_ros.beacon.packet import BLUR_MIXES, decode_clipped_packet, decode_packet
from vlp_ros.beacon.profile import RowProfile
from vlp_ros.core.observation import LampObservation
from vlp_ros.pipeline.config import settings_from_tree
from vlp_ros.pipeline.frame import Pipeline
from vlp_ros.sim.looks import apply_look, LOOKS, transported
from vlp_ros.sim.scenarios import paper_scenario, with_rim_markers

# The paper scenario's 4K beacon: 8-bit IDs at 5.68 rows per chip, 50 us exposure (3.2 rows).
ROW_TIME = 1.0 / (30.0 * 2160)
CHIP_RATE = 11405.0
EXPOSURE = 50e-6
MAP = [11, 90, 200]


def clipped_disc(lamp_id: int, seed: int, packets: float = 1.5, gain: float = 2.2, blur_rows: float = 1.6,
                 falloff: float = 0.3, depth: float = 0.6, steady: bool = False) -> RowProfile:
    """
    Return a disc's row profile.

    Each row's pixels lit by the diffuser's 1 - falloff (r/R)^2, blurred across rows with the stripes,
    clipped pixel by pixel at the ceiling (1.0), averaged with the clipped ones at it.
    """
    rng = np.random.default_rng([lamp_id, seed])
    rows = int(packets * packet_length(8) / (CHIP_RATE * ROW_TIME))
    wave = packet_waveform(lamp_id, CHIP_RATE, 0.0 if steady else depth, 8,
                           offset=rng.uniform(0.0, packet_length(8) / CHIP_RATE))
    pad = 12
    times = (np.arange(-pad, rows + pad) + rng.uniform(0.0, 1.0)) * ROW_TIME
    offsets = np.arange(-pad, pad + 1)
    kernel = np.exp(-0.5 * (offsets / blur_rows) ** 2)
    stripes = np.convolve(wave.mean_brightness(times, EXPOSURE), kernel / kernel.sum(), mode='same')[pad:-pad]
    height = (np.arange(rows) + 0.5) / rows * 2.0 - 1.0
    across = np.linspace(-1.0, 1.0, 41)
    r2 = height[:, None] ** 2 + (across[None, :] * np.sqrt(1.0 - height[:, None] ** 2)) ** 2
    light = gain * (1.0 - falloff * r2) * stripes[:, None] + 0.01 * rng.standard_normal(r2.shape)
    clipped = light >= 1.0
    return RowProfile(255.0 * np.minimum(light, 1.0).mean(axis=1), np.full(rows, 41.0), clipped.mean(axis=1), 0)


def test_a_clipped_blurred_disc_is_read():
    readings = [decode_clipped_packet(clipped_disc(lamp_id, seed), CHIP_RATE, ROW_TIME, 8, MAP).lamp_id
                for lamp_id in MAP for seed in range(10)]
    assert sum(r == lamp_id for r, lamp_id in zip(readings, np.repeat(MAP, 10))) >= 0.8 * len(readings)


def test_the_gaussian_reading_refuses_what_the_censored_one_reads():
    """The same discs fit no packet as measured levels."""
    for seed in range(5):
        profile = clipped_disc(90, seed)
        assert decode_packet(profile, CHIP_RATE, ROW_TIME, 8, MAP, blur_mixes=BLUR_MIXES).lamp_id is None


@pytest.mark.parametrize('packets, gain, blur_rows', [(0.8, 2.2, 1.6), (1.5, 3.0, 2.0), (1.2, 2.2, 2.5),
                                                      (1.5, 1.5, 1.6)])
def test_a_clipped_disc_is_never_read_as_another_id(packets, gain, blur_rows):
    """Less than a packet, brighter, more blur than the model's mixes: read right or not at all, every ID."""
    for lamp_id in range(0, 256, 17):
        for seed in range(2):
            profile = clipped_disc(lamp_id, seed, packets, gain, blur_rows)
            reading = decode_clipped_packet(profile, CHIP_RATE, ROW_TIME, 8, None)
            assert reading.lamp_id in (None, lamp_id), (lamp_id, seed, reading.confidence)


def test_censored_readings_below_a_packet_add_up_across_frames():
    """
    The simulator's realistic drive.

    A clipped, blurred disc showing 0.7 of a packet reads its ID at 0.97-0.999 in each frame, never certain alone.
    ``read_lamp`` passes those readings on, and the tracker sums them: certain within six frames, and never of
    another ID (every 34th ID, new packet phase each frame).
    """
    first_certain = []
    for lamp_id in range(0, 256, 34):
        tracker = EvidenceTracker(MAP + [lamp_id])
        ids = []
        for frame in range(6):
            reading = decode_clipped_packet(clipped_disc(lamp_id, frame, packets=0.7), CHIP_RATE, ROW_TIME, 8,
                                            MAP + [lamp_id])
            ids += tracker.update([LampObservation(np.array([100.0 + 20.0 * frame, 50.0, 40.0, 40.0, 0.0]),
                                                   np.zeros((0, 2)), 0.1, None, 0.1, (0, 0, 1, 1),
                                                   np.ones((1, 1), dtype=bool))], [reading], 0.1 * frame)
        assert set(ids) <= {None, lamp_id}, lamp_id
        first_certain.append(lamp_id in ids)
    assert all(first_certain)


def test_a_steady_clipped_lamp_gives_no_id():
    for seed in range(10):
        reading = decode_clipped_packet(clipped_disc(0, seed, steady=True), CHIP_RATE, ROW_TIME, 8, MAP)
        assert reading.lamp_id is None and not reading.unknown


def test_an_unclipped_window_is_left_to_the_gaussian_reading():
    reading = decode_clipped_packet(clipped_disc(90, 0, gain=0.9), CHIP_RATE, ROW_TIME, 8, MAP)
    assert reading.lamp_id is None and reading.detail == 'not clipped'


@pytest.mark.simulation
def test_the_simulators_realistic_stills_are_identified():
    """
    The accuracy benchmark's hand-held realistic stills (paper's 4K lamp at 2 m, rim marker, clutter).

    The locator's reading of each mapped lamp, and never of a clutter lamp.
    """
    scenario = apply_look(with_rim_markers(paper_scenario('4k', height=2.0, points=3, postures=1, seed=0), 0.9, 0.1),
                          LOOKS['realistic'], 0)
    pipeline = Pipeline(settings_from_tree(scenario.locator_parameters(imu=True)))
    identified = 0
    for index in range(len(scenario.poses)):
        frame = scenario.render(index, np.random.default_rng([0, 99, index]))
        image = transported(scenario, frame.image)
        result = pipeline.process(image, scenario.camera, float(index), None)
        assert set(result.decoded_ids) <= {11}
        identified += 11 in result.decoded_ids
    assert identified >= 7


def clipped_chips(lamp_id: int, seed: int, gain: float, mix: float = 0.3, chips: int = 17,
                  steady: bool = False) -> tuple[np.ndarray, ...]:
    """
    Return a window's chip levels, weights, indices and which are censored, as ``censored_log_likelihoods`` takes.

    The chips of ``lamp_id`` from a random packet position, blurred (``mix`` of each neighbour) at a depth of 0.6,
    under an envelope that falls off 30 % to the window's ends; the brightest chip ``gain`` times the ceiling (1.0)
    at the middle, with 2 % noise.
    """
    rng = np.random.default_rng([lamp_id, seed])
    length = packet_length(8)
    signs = packet_chips(lamp_id, 8) * 2.0 - 1.0
    positions = (np.arange(chips) + rng.integers(length)) % length
    template = 0.0 if steady else signs[positions] + mix * (signs[positions - 1] + signs[(positions + 1) % length])
    t = np.linspace(-1.0, 1.0, chips)
    depth = 0.6
    light = gain * (1.0 - 0.3 * t * t) * (1.0 + depth * template) / (1.0 + depth * (1.0 + 2.0 * mix)) \
        + 0.02 * rng.standard_normal(chips)
    censored = light >= 1.0
    x = np.minimum(light, 1.0)
    weights = np.full(chips, 1.0 / (0.02 ** 2 + (0.2 * 0.5 * (x.max() - x.min())) ** 2))
    return x, weights, np.arange(chips), censored


def every_fit(x: np.ndarray, v: np.ndarray, k: np.ndarray, censored: np.ndarray) -> tuple[np.ndarray, tuple]:
    """Return every (mix, shift, ID) hypothesis fitted by Newton's method (no pruning), and the bounds' sums."""
    sums = _hypothesis_sums(x, v, k, censored, 8, BLUR_MIXES)
    bounds = np.ascontiguousarray(_bounds_from_sums(*sums).reshape(-1, len(BLUR_MIXES), 256).transpose(1, 0, 2))
    fits, _ = _fits_that_can_win(bounds, sums, x, v, k, censored, _signs(8), _packet_masks(8),
                                 np.asarray(BLUR_MIXES), np.inf, -np.inf)
    return fits, sums


WINDOWS = [(lamp_id, seed, gain) for lamp_id, seed, gain in [(90, 0, 1.6), (11, 1, 2.2), (200, 2, 3.0), (37, 3, 2.6)]]


@pytest.mark.parametrize('lamp_id, seed, gain', WINDOWS)
def test_the_sound_bounds_bound_every_hypothesis(lamp_id, seed, gain):
    """Blur lifts dark chips over the ceiling here: no hypothesis fits above its sound bound."""
    x, v, k, censored = clipped_chips(lamp_id, seed, gain)
    fits, sums = every_fit(x, v, k, censored)
    sound = _sound_bounds_from_sums(*sums).reshape(-1, len(BLUR_MIXES), 256).transpose(1, 0, 2)
    assert censored.sum() >= 3
    assert np.all(fits <= sound + 1e-3)


@pytest.mark.parametrize('lamp_id, seed, gain, scrambled', [window + (False,) for window in WINDOWS]
                         + [(0, 4, 2.2, False), (90, 5, 2.2, True), (11, 6, 1.6, True)])
def test_a_window_is_refused_exactly_when_no_hypothesis_fits_within_the_limit(lamp_id, seed, gain, scrambled):
    """
    Limits a hair below and above the best of all fits: refused, then read at that deviance.

    A steady lamp, lamps' chips, and their chips in a random order (which fit no packet).
    """
    x, v, k, censored = clipped_chips(lamp_id, seed, gain, steady=lamp_id == 0)
    if scrambled:
        order = np.random.default_rng(seed).permutation(len(x))
        x, censored = x[order], censored[order]
    best = -2.0 * every_fit(x, v, k, censored)[0].max()
    below, above = best * (1.0 - 1e-6) - 1e-9, best * (1.0 + 1e-6) + 1e-9
    refused, deviance = censored_log_likelihoods(x, v, k, censored, 8, BLUR_MIXES, below)
    assert refused is None and deviance > below
    read, deviance = censored_log_likelihoods(x, v, k, censored, 8, BLUR_MIXES, above)
    assert read is not None and deviance == best


@pytest.mark.parametrize('id_bits', [1, 3, 8, 12])
def test_the_hypothesis_sums_are_every_ids_table_sums(id_bits):
    """The sums through the tables' factors are the chips' folds times every ID's tables, to rounding."""
    rng = np.random.default_rng(id_bits)
    length = packet_length(id_bits)
    k = np.sort(rng.choice(2 * length, size=length + 3, replace=False))
    x, v, censored = rng.uniform(0.2, 1.0, len(k)), rng.uniform(0.5, 2.0, len(k)), rng.uniform(size=len(k)) < 0.5
    sums = _hypothesis_sums(x, v, k, censored, id_bits, BLUR_MIXES)
    t = (k - 0.5 * (k[0] + k[-1])) / (0.5 * (k[-1] - k[0]))
    powers = t[None, :] ** np.arange(5)[:, None]
    vm, vc = v * ~censored, v * censored
    measured = _folded(np.vstack([powers[:4] * vm, powers[:2] * (vm * x)]), k, length)
    clipped = _folded(np.vstack([powers * vc, powers[:3] * (vc * x), (vc * x * x)[None, :]]), k, length)
    signs, squares, dark, dark_neighbours, dark_squares = _template_tables(id_bits)
    expected = [measured @ signs, measured[:3] @ squares, clipped @ dark, clipped[[0, 1, 2, 3, 5, 6]] @ dark_neighbours,
                clipped[:3] @ dark_squares, clipped[:2] @ signs]
    for got, want in zip(sums[2:], expected):
        np.testing.assert_allclose(got, want, rtol=0.0, atol=1e-12 * np.abs(want).max())
