"""
Packet mode: which ID explains a lamp's chip levels, weighed against every ID the bits can carry.

Soft maximum-likelihood decoding: each hypothesis (ID, where in the packet the
window starts) predicts every chip of the window; the preamble search, Manchester
decoding and parity check of a hard decoder are all inside that comparison, which
also uses partial packets and repeated packets at full strength. Every ID of
``id_bits`` is a hypothesis, so an unmapped ID is recognised as such instead of
being matched to the nearest mapped one.
"""
from __future__ import annotations

from collections.abc import Iterable
from functools import lru_cache
import math

import numpy as np
# scipy.special, not scipy.stats: the same chi-square tail without scipy.stats' import time at start.
from scipy.special import chdtri

from vlp_ros.beacon.censored import censored_log_likelihoods, CENSORED_SHARE, clipped_run_grids, raw_chips
from vlp_ros.beacon.chips import _noise_variance, chip_levels, ChipLevels, levels_on_grid, nearby_grids
from vlp_ros.beacon.encoding import packet_bits, packet_chips, packet_length
from vlp_ros.beacon.profile import relative_brightness, RowProfile
from vlp_ros.beacon.reading import BeaconReading, log_prior, MIN_CONFIDENCE, no_evidence, reading, UNMAPPED_WEIGHT
from vlp_ros.compiled import kernel

MIN_CHIPS = 6
# Beyond this many packets more rows add little but time: the central ones are used.
MAX_PACKETS = 2.3
# Shares of each neighbouring chip that blur across rows may mix into a chip: sharp, and a Gaussian blur of
# about a third and a half of the chip (a 2 px blur of 5-row chips leaves an isolated chip 40 % of its
# contrast, mix 0.2).
BLUR_MIXES = (0.0, 0.15, 0.3)
# Where blur is weighed in, the chip grid is too: the grid search's best (the chip-wise constant fit's) sat a
# quarter chip off the likelihood's on foreign 4K frames, where blur and the rows' exposure round the chips.
# Grids with the chip edges moved by these shares of a chip, and the period scaled by these factors.
GRID_OFFSETS = (-0.3, -0.15, 0.0, 0.15, 0.3)
GRID_SCALES = (0.99, 1.0, 1.01)
# The largest misfit per degree of freedom of a grid around the found one that counts: on the foreign frames
# the best of them fitted to 0.07-0.55, the found grid to 0.73-1.78.
NEARBY_MISFIT = 1.0
# The default: sharp chips only. With BLUR_MIXES the benchmark's tracker rows have not been run yet.
SHARP = (0.0,)
# A best fit worse than this tail probability of its chi-square means the lamp is not sending packets.
MISFIT_PROBABILITY = 1e-6
# A window whose rows have more than this share of their pixels clipped is read as clipped: a clipped chip
# only says its light reached the ceiling, which blur can lift an isolated dark chip to (docs/beacon.md).
CLIPPED_SHARE = 0.1
# The largest misfit (weighted squared residual per degree of freedom) of a clipped window's best fit that
# still counts as evidence: clipped discs that read right fitted to 0.46 at most, clipped and blurred ones
# that hid their dark chips under the ceiling (and leaned to wrong IDs) to 1.17 at least.
CLIPPED_MISFIT = 0.7
# The fewest chips below the ceiling that a clipped window's censored reading needs (the others only bound).
MIN_CENSORED_MEASURED = 8


@lru_cache(maxsize=4)
def _neighbour_products(id_bits: int) -> tuple[np.ndarray, np.ndarray]:
    """
    Every ID's products of chip signs one and two positions apart around the packet, (L, 2^id_bits) each.

    S[p] s[p + 1] and s[p] s[p + 2].
    """
    signs = np.array([packet_chips(i, id_bits) for i in range(2 ** id_bits)], dtype=float) * 2 - 1
    return ((signs * np.roll(signs, -1, axis=1)).T.copy(), (signs * np.roll(signs, -2, axis=1)).T.copy())


@lru_cache(maxsize=4)
def _codebook(id_bits: int) -> tuple[np.ndarray, np.ndarray]:
    """
    Every ID's packet, factored: its chip signs (+1 bright, -1 dark) are ``chip_weights @ design``.

    ``design`` (2 + id_bits, 2^id_bits) is a row of ones over the +-1 of each ID's bits and parity;
    ``chip_weights`` (L, 2 + id_bits) say what the constant (the preamble) and each bit put on
    every packet position (Manchester: +-1 on the bit's two chips).
    """
    ids = 2 ** id_bits
    signs = np.array([packet_chips(i, id_bits) for i in range(ids)], dtype=float) * 2 - 1
    bit_signs = np.array([packet_bits(i, id_bits) for i in range(ids)], dtype=float).T * 2 - 1
    design = np.vstack([np.ones(ids), bit_signs])
    # The contract is linear in the bit signs, so least squares factors it exactly: in whole numbers (0 and +-1,
    # least squares' ~1e-17 for the zeros rounded away) where the bits determine it.
    chip_weights = np.linalg.lstsq(design.T, signs, rcond=None)[0]
    whole = np.round(chip_weights)
    if np.array_equal(design.T @ whole, signs):
        chip_weights = whole
    if not np.allclose(design.T @ chip_weights, signs):
        raise AssertionError('packet chips are not linear in the bit signs')
    # float32: the hypotheses' sums need ~1e-3 nats, and halve the time of the largest arrays.
    return design.astype(np.float32), chip_weights.T.copy()


@lru_cache(maxsize=4)
def _chip_weight_entries(id_bits: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """
    Return ``_codebook``'s nonzero chip weights by packet position: (starts (L + 1,), bits, weights).

    Position p's entries are ``starts[p]:starts[p + 1]``: a bit or the constant puts its weight on a few
    positions only (Manchester: two), so the per-bit sums skip the zeros.
    """
    chip_weights = _codebook(id_bits)[1]
    positions, bits = np.nonzero(chip_weights)
    starts = np.searchsorted(positions, np.arange(len(chip_weights) + 1))
    entries = (starts.astype(np.int64), bits.astype(np.int64), chip_weights[positions, bits])
    for array in entries:
        array.flags.writeable = False
    return entries


def decode_packet(profile: RowProfile, chip_rate: float, row_time: float, id_bits: int = 8,
                  known_ids: Iterable[int] | None = None, *, exposure: float | None = None,
                  timing_tolerance: float = 0.05, unmapped_weight: float = UNMAPPED_WEIGHT,
                  min_confidence: float = MIN_CONFIDENCE, model_error: float = 0.2,
                  blur_mixes: tuple[float, ...] = SHARP) -> BeaconReading:
    """
    Return the ID a packet-mode lamp sends, from its row profile.

    ``chip_rate`` (Hz) and ``row_time`` (s) are nominal: the chip period is searched
    within +-``timing_tolerance``. ``exposure`` (s), when known, tells how many rows
    at each chip edge see both neighbours. ``known_ids`` are the map's IDs (None:
    all); every other ID has ``unmapped_weight`` times their prior. ``model_error``
    is the spread (in half-contrasts) that any chip level may have beyond pixel
    noise: it keeps single chips from deciding alone. ``blur_mixes`` are the shares of each
    neighbouring chip that optical blur across rows may mix into a chip, equally likely a priori; they
    are weighed in only when sharp chips leave the ID open.
    """
    period, margin = _chip_timing(chip_rate, row_time, id_bits, exposure)
    candidates, mapped, prior = _hypotheses(id_bits, None if known_ids is None else tuple(known_ids),
                                            unmapped_weight)
    z, w, clipped_share = _window(profile, period, id_bits)
    clipped = bool(clipped_share @ w > CLIPPED_SHARE * w.sum())
    levels = chip_levels(z, w, period, timing_tolerance, margin)
    if levels is None:
        return no_evidence(candidates, mapped, prior, 'too few rows for a chip grid')
    if levels.index.size < MIN_CHIPS:
        return no_evidence(candidates, mapped, prior, f'only {levels.index.size} chips visible')
    # Sharp chips first (quick, and all a sharp lamp needs); blurred ones weighed in when that leaves the ID open,
    # on a grid searched thoroughly and on the grids around it.
    sharp = _packet_reading([levels], model_error, id_bits, (0.0,), candidates, mapped, prior, min_confidence, clipped)
    if sharp.lamp_id is not None or sharp.unknown or blur_mixes == (0.0,):
        return sharp
    # Where blur rounds the chips, the quick grid search misplaces the grid (docs/beacon.md): searched thoroughly.
    levels = chip_levels(z, w, period, timing_tolerance, margin, thorough=True) or levels
    grids = [levels] + nearby_grids(z, w, levels, margin, GRID_OFFSETS, GRID_SCALES)
    return _packet_reading(grids, model_error, id_bits, blur_mixes, candidates, mapped, prior, min_confidence,
                           clipped)


def no_packet(id_bits: int, known_ids: Iterable[int] | None, detail: str,
              unmapped_weight: float = UNMAPPED_WEIGHT) -> BeaconReading:
    """Return the reading that ``decode_packet`` gives a lamp without chips: no evidence, with why."""
    candidates, mapped, prior = _hypotheses(id_bits, None if known_ids is None else tuple(known_ids),
                                            unmapped_weight)
    return no_evidence(candidates, mapped, prior, detail)


def decode_clipped_packet(profile: RowProfile, chip_rate: float, row_time: float, id_bits: int = 8,
                          known_ids: Iterable[int] | None = None, *, exposure: float | None = None,
                          timing_tolerance: float = 0.05, unmapped_weight: float = UNMAPPED_WEIGHT,
                          min_confidence: float = MIN_CONFIDENCE, model_error: float = 0.2,
                          blur_mixes: tuple[float, ...] = BLUR_MIXES) -> BeaconReading:
    """
    Decode a clipped window of a disc's ``row_profile`` as ``decode_packet`` does, its clipped chips censored.

    Clipped pixels are kept at the ceiling; the window's mostly clipped chips are read as censored, "at
    least this bright" (vlp_ros.beacon.censored), blur weighed in (``blur_mixes``) on the thoroughly
    searched grid. No evidence for a window that is not clipped (the Gaussian reading holds there), and
    for one whose best fit misfits even so.
    """
    period, margin = _chip_timing(chip_rate, row_time, id_bits, exposure)
    candidates, mapped, prior = _hypotheses(id_bits, None if known_ids is None else tuple(known_ids),
                                            unmapped_weight)
    z, w, clipped_share = _window(profile, period, id_bits)
    if not clipped_share @ w > CLIPPED_SHARE * w.sum():
        return no_evidence(candidates, mapped, prior, 'not clipped')
    # The grid comes from where rows cross half clipped (censored.clipped_run_grids): where the ceiling flattens
    # the light, that is what shows the chips. Searched on the light, or on the clipped shares by chip energy, the
    # period was 3-6 % off on the simulator's realistic stills and on synthesised clipped discs (a chip over a
    # packet). Its two readings half a chip apart are weighed like nearby grids: those that fit, equally likely.
    grids = [levels_on_grid(z, w, grid_period, phase, margin)
             for grid_period, phase in clipped_run_grids(clipped_share, period, timing_tolerance)]
    grids = [levels for levels in grids if levels is not None and levels.index.size >= MIN_CHIPS]
    if not grids:
        return no_evidence(candidates, mapped, prior, 'too few chips for a clipped window')
    fitting = [fit for fit in (_censored_fit(z, w, clipped_share, levels, margin, model_error, id_bits, blur_mixes)
                               for levels in grids) if fit is not None]
    if not fitting:
        return no_evidence(candidates, mapped, prior, 'the clipped chips fit no packet')
    stacked = np.array(fitting)
    top = stacked.max(axis=0)
    log_likelihoods = top + np.log(np.exp(stacked - top).mean(axis=0))
    return reading(candidates, mapped, log_likelihoods, prior, min_confidence)


def _censored_fit(z: np.ndarray, w: np.ndarray, clipped_share: np.ndarray, levels: ChipLevels, margin: float | None,
                  model_error: float, id_bits: int, mixes: tuple[float, ...]) -> np.ndarray | None:
    """
    Every ID's censored log-likelihood on the grid of ``levels``.

    None when too few chips lie below the ceiling or the best hypothesis misfits.
    """
    means, chip_weights, shares = raw_chips(z, w, clipped_share, levels, margin)
    censored = shares > CENSORED_SHARE
    measured = int(np.count_nonzero(~censored))
    if measured < MIN_CENSORED_MEASURED:
        return None
    # The model error in half-contrasts, as the Gaussian reading's, on the raw chips' scale.
    half_contrast = 0.5 * float(means.max() - means.min())
    weights = 1.0 / (_noise_variance(z, w) / chip_weights + (model_error * half_contrast) ** 2)
    log_likelihoods, _ = censored_log_likelihoods(means, weights, levels.index, censored, id_bits, mixes,
                                                  _misfit_limit(max(measured - 5, 1)))
    return log_likelihoods


def _chip_timing(chip_rate: float, row_time: float, id_bits: int,
                 exposure: float | None) -> tuple[float, float | None]:
    """
    Return the nominal chip period in rows, and the rows at each chip edge whose exposure sees both neighbours.

    The latter is None for an unknown exposure.
    """
    if not (chip_rate > 0.0 and row_time > 0.0):
        raise ValueError(f'chip_rate and row_time must be positive, got {chip_rate} and {row_time}')
    if not 1 <= id_bits <= 16:
        raise ValueError(f'id_bits must lie in 1..16, got {id_bits}')
    if exposure is not None and not exposure >= 0.0:
        raise ValueError(f'exposure must not be negative, got {exposure}')
    return 1.0 / (chip_rate * row_time), None if exposure is None else 0.5 * exposure / row_time + 0.25


def _window(profile: RowProfile, period: float, id_bits: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """
    Return the rows decoded.

    Brightness relative to their mean, weights and clipped shares, the central MAX_PACKETS
    packets at most.
    """
    # Only the mean level: a curve fitted through few chips bends with them, and the chip levels
    # follow the envelope locally anyway.
    z, w, _ = relative_brightness(profile)
    first = int(np.argmax(np.asarray(profile.weights) > 0))
    clipped_share = np.asarray(profile.saturated, dtype=float)[first:first + len(z)]
    return _central_rows(MAX_PACKETS * packet_length(id_bits) * period, z, w, clipped_share)


def _packet_reading(grids: list[ChipLevels], model_error: float, id_bits: int, mixes: tuple[float, ...],
                    candidates: np.ndarray, mapped: np.ndarray, prior: np.ndarray,
                    min_confidence: float, clipped: bool) -> BeaconReading:
    """
    Return the reading of the chips on ``grids`` under ``mixes``.

    The grid search's own (the first) and the ones around it that fit well, equally likely a priori
    (their likelihoods are averaged).

    The first grid must fit (more strictly where the window is ``clipped``: there the chips' levels are not
    linear in the light, so a misfit means the ceiling hid dark chips, and the fit then leans to IDs whose
    chips were never seen); otherwise there is no evidence. A grid around it counts only if it fits within
    NEARBY_MISFIT per degree of freedom: trying grids must not let a lamp the model does not describe find
    one where a wrong ID fits (an exposure of two chips read 126 as 66 so, at 2.2 per degree of freedom).
    """
    first, *nearby = grids
    weights = 1.0 / (first.variances + model_error ** 2)
    dof = first.index.size - 4
    limit = min(_misfit_limit(dof), CLIPPED_MISFIT * dof) if clipped else _misfit_limit(dof)
    log_likelihoods, misfit = _id_log_likelihoods(first.levels, weights, first.index, id_bits, mixes, limit)
    if misfit > _misfit_limit(dof):
        return no_evidence(candidates, mapped, prior, 'the chips fit no packet')
    if log_likelihoods is None:
        return no_evidence(candidates, mapped, prior, 'clipped chips misfit: blur may have lifted dark chips to '
                                                      'the ceiling')
    fitting = [log_likelihoods]
    good_fit = min(NEARBY_MISFIT, CLIPPED_MISFIT) if clipped else NEARBY_MISFIT
    for levels in nearby:
        weights = 1.0 / (levels.variances + model_error ** 2)
        log_likelihoods, _ = _id_log_likelihoods(levels.levels, weights, levels.index, id_bits, mixes,
                                                 good_fit * (levels.index.size - 4))
        if log_likelihoods is not None:
            fitting.append(log_likelihoods)
    stacked = np.array(fitting)
    top = stacked.max(axis=0)
    return reading(candidates, mapped, top + np.log(np.exp(stacked - top).mean(axis=0)), prior, min_confidence)


def _central_rows(rows: float, *arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    """Return the window's ``arrays`` (one value per row) cut to their central ``rows`` when they hold more."""
    excess = len(arrays[0]) - math.ceil(rows)
    if excess <= 0:
        return arrays
    first, last = excess // 2, len(arrays[0]) - (excess - excess // 2)
    return tuple(array[first:last] for array in arrays)


@lru_cache(maxsize=256)
def _misfit_limit(dof: int) -> float:
    return float(chdtri(dof, MISFIT_PROBABILITY))


@lru_cache(maxsize=16)
def _hypotheses(id_bits: int, known_ids: tuple[int, ...] | None,
                unmapped_weight: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every ID, which of them the map holds, and their log prior (read-only, shared between calls)."""
    candidates = np.arange(2 ** id_bits)
    if known_ids is None:
        mapped = np.ones(len(candidates), dtype=bool)
    else:
        known = np.array(known_ids, dtype=int)
        outside = known[(known < 0) | (known >= len(candidates))]
        if outside.size:
            raise ValueError(f'known ids {outside.tolist()} do not fit in {id_bits} bits')
        mapped = np.isin(candidates, known)
    prior = log_prior(mapped, unmapped_weight)
    for array in (candidates, mapped, prior):
        array.flags.writeable = False
    return candidates, mapped, prior


def _id_log_likelihoods(x: np.ndarray, v: np.ndarray, k: np.ndarray, id_bits: int,
                        mixes: tuple[float, ...] = (0.0,),
                        misfit_limit: float = np.inf) -> tuple[np.ndarray | None, float]:
    """
    Return the log-likelihood of each ID, and the best fit's weighted squared residual.

    The window's start in the packet and the blur's mix are marginalised. The log-likelihoods are None (not
    taken) when that residual exceeds ``misfit_limit``.

    Chip k of the window is packet position (k + shift) % L; its level is a
    quadratic baseline in k plus beta * (sign_k + mix (sign_k-1 + sign_k+1)), Gaussian with weights ``v``,
    fitted per hypothesis with beta > 0: optical blur across rows mixes each chip with its neighbours
    (``mixes``, equally likely a priori; 0: sharp). The baseline takes up what the ID-blind envelope left:
    a preamble's run of bright chips leans any envelope fitted through the stripes.
    """
    design, chip_weights = _codebook(id_bits)
    length = len(chip_weights)
    mixes = np.array(mixes, dtype=float)
    per_bit, baseline_rss, by_weight, before = _per_bit_sums(x, v, k, *_chip_weight_entries(id_bits),
                                                             chip_weights.shape[1], mixes)
    # Every (mix, shift, ID): the sums over its bright minus its dark chips, each hypothesis along the last axis.
    sums = (per_bit.reshape(-1, per_bit.shape[2]) @ design).reshape(len(mixes), 4 * length, -1)
    if mixes.any():
        # The neighbours' products summed by weight do not depend on the mix: taken once for all mixes.
        next_products, second_products = _neighbour_products(id_bits)
        neighbours, seconds = (by_weight + before) @ next_products, before @ second_products
    else:
        neighbours = seconds = np.zeros((0, 0))
    half_gains, best, misfit = _half_gains(sums, mixes, float(v.sum()), neighbours, seconds, baseline_rss)
    if misfit > misfit_limit:
        return None, misfit
    # numpy's float32 exp and log, as the likelihoods have always been taken (numba's differ in the last bit).
    np.subtract(half_gains, best[:, None, :], out=half_gains)
    spread = np.log(np.exp(half_gains, out=half_gains).sum(axis=1) / length)
    per_mix = best.astype(float) + spread - 0.5 * baseline_rss
    if len(per_mix) == 1:
        return per_mix[0], misfit
    top = per_mix.max(axis=0)
    return top + np.log(np.exp(per_mix - top).mean(axis=0)), misfit


@kernel
def _per_bit_sums(x: np.ndarray, v: np.ndarray, k: np.ndarray, starts: np.ndarray, weighted_bits: np.ndarray,
                  weights: np.ndarray, bits: int,
                  mixes: np.ndarray) -> tuple[np.ndarray, float, np.ndarray, np.ndarray]:
    """
    Return what each hypothesis's fit needs, factored by bit: (mixes, 4 L, 2 + id_bits) float32, row f L + shift.

    The baseline's weighted squared residual; the weights v summed by packet position for each
    shift (L, L); and the same one position on (each row rolled back by one).

    With a mix, chip j's template also holds mix times its neighbours' signs: what it puts on its own
    position goes on the neighbouring positions too, times mix.

    Per packet position: sums of v times each orthonormal baseline column over the chips that land
    there, and of v times what the baseline leaves of x (every ID's fit is linear in it), the latter
    scaled by sqrt(1/2) so that its squares come out as half gains (log-likelihoods). Folded for every
    shift (the window's chip j at packet position (j + shift) % L) and multiplied by what each bit puts
    on each position (the nonzero chip weights of ``_chip_weight_entries``: ``bits`` is 2 + id_bits).
    """
    n, length = len(x), len(starts) - 1
    basis = _orthonormal_baseline(k, v)
    baseline = np.zeros(3)
    vx_x = 0.0
    for j in range(n):
        vx = v[j] * x[j]
        vx_x += vx * x[j]
        for f in range(3):
            baseline[f] += basis[f, j] * vx
    baseline_rss = vx_x - (baseline[0] * baseline[0] + baseline[1] * baseline[1] + baseline[2] * baseline[2])
    half = math.sqrt(0.5)
    weight_at = np.zeros(2 * length)
    for j in range(n):
        weight_at[k[j] % length] += v[j]
    weight_at[length:] = weight_at[:length]
    by_weight, before = np.empty((length, length)), np.empty((length, length))
    for shift in range(length):
        for position in range(length):
            by_weight[shift, position] = weight_at[position - shift + length]
            before[shift, position] = weight_at[(position + 1) % length - shift + length]
    per_bit = np.empty((len(mixes), 4 * length, bits), dtype=np.float32)
    totals = np.empty(bits)
    for m in range(len(mixes)):
        mix = mixes[m]
        # Twice over, so that position - shift + L indexes (position - shift) % L.
        by_position = np.zeros((4, 2 * length))
        for j in range(n):
            position = k[j] % length
            earlier, later = (position - 1) % length, (position + 1) % length
            explained = 0.0
            for f in range(3):
                vbasis = basis[f, j] * v[j]
                explained += baseline[f] * vbasis
                by_position[f, position] += vbasis
                by_position[f, earlier] += mix * vbasis
                by_position[f, later] += mix * vbasis
            residual = (v[j] * x[j] - explained) * half
            by_position[3, position] += residual
            by_position[3, earlier] += mix * residual
            by_position[3, later] += mix * residual
        by_position[:, length:] = by_position[:, :length]
        for f in range(4):
            for shift in range(length):
                totals[:] = 0.0
                for position in range(length):
                    folded = by_position[f, position - shift + length]
                    for entry in range(starts[position], starts[position + 1]):
                        totals[weighted_bits[entry]] += folded * weights[entry]
                per_bit[m, f * length + shift] = totals
    return per_bit, baseline_rss, by_weight, before


@kernel
def _half_gains(sums: np.ndarray, mixes: np.ndarray, total: float, neighbours: np.ndarray, seconds: np.ndarray,
                baseline_rss: float) -> tuple[np.ndarray, np.ndarray, float]:
    """
    Return half the gain of each (mix, shift, ID)'s best-fitting contrast, each (mix, ID)'s best, and the best misfit.

    The gains are (mixes, L, ids), from ``sums`` (mixes, 4 L, ids), in float32 arithmetic like the sums. The
    misfit is the least weighted squared residual of any hypothesis, ``baseline_rss`` less twice the best gain.

    A template t_k = s_k + mix (s_k-1 + s_k+1) has the energy sum(v t^2) (1 + 2 mix^2) ``total`` (sum(v)) +
    2 mix ``neighbours`` + 2 mix^2 ``seconds`` (the weighted sums of the signs' products, ``_neighbour_products``:
    (L, ids) each, not needed without a mix), taken in float64 and rounded to float32. With an orthonormal
    baseline, what the signs add beyond it is their part orthogonal to it; the contrast must be positive.
    """
    count, length, ids = sums.shape[0], sums.shape[1] // 4, sums.shape[2]
    gains = np.empty((count, length, ids), dtype=np.float32)
    best = np.full((count, ids), -np.inf, dtype=np.float32)
    misfit = np.inf
    for m in range(count):
        mix = mixes[m]
        scale, twice, square = 1.0 + 2.0 * mix * mix, 2.0 * mix, 2.0 * mix * mix
        for shift in range(length):
            for i in range(ids):
                a, b, c = sums[m, shift, i], sums[m, length + shift, i], sums[m, 2 * length + shift, i]
                if mix == 0.0:
                    energy = np.float32(total)
                else:
                    energy = np.float32(scale * total + twice * neighbours[shift, i] + square * seconds[shift, i])
                schur = max(energy - (a * a + b * b + c * c), np.float32(1e-6) * energy)
                target = max(sums[m, 3 * length + shift, i], np.float32(0.0))
                gains[m, shift, i] = target * target / schur
                best[m, i] = max(best[m, i], gains[m, shift, i])
        fit = baseline_rss - 2.0 * float(best[m].max())
        if fit < misfit:
            misfit = fit
    return gains, best, misfit


@kernel
def _orthonormal_baseline(k: np.ndarray, v: np.ndarray) -> np.ndarray:
    """
    Return 1, t, t^2 in the (increasing) chip index, made orthonormal under the weights ``v``, (3, n).

    Gram-Schmidt, written out through the weighted moments of t.
    """
    n = len(k)
    middle, half = 0.5 * (k[0] + k[-1]), max(0.5 * float(k[-1] - k[0]), 1.0)
    t = np.empty(n)
    m0 = m1 = m2 = m3 = m4 = 0.0
    for j in range(n):
        t[j] = (k[j] - middle) / half
        vt, t2 = v[j] * t[j], t[j] * t[j]
        m0 += v[j]
        m1 += vt
        m2 += vt * t[j]
        m3 += vt * t2
        m4 += v[j] * t2 * t2
    linear_norm2 = m2 - m1 * m1 / m0
    lean = (m3 - m1 * m2 / m0) / linear_norm2
    quadratic_norm2 = m4 - m2 * m2 / m0 - lean * lean * linear_norm2
    basis = np.empty((3, n))
    constant, linear_scale = 1.0 / math.sqrt(m0), 1.0 / math.sqrt(linear_norm2)
    quadratic_scale = 1.0 / math.sqrt(max(quadratic_norm2, 1e-300))
    for j in range(n):
        linear = t[j] - m1 / m0
        basis[0, j] = constant
        basis[1, j] = linear * linear_scale
        basis[2, j] = (t[j] * t[j] - m2 / m0 - lean * linear) * quadratic_scale
    return basis
