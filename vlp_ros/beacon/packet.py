"""Packet mode: which ID explains a lamp's chip levels, weighed against every ID the bits can carry.

Soft maximum-likelihood decoding: each hypothesis (ID, where in the packet the
window starts) predicts every chip of the window; the preamble search, Manchester
decoding and parity check of a hard decoder are all inside that comparison, which
also uses partial packets and repeated packets at full strength. Every ID of
``id_bits`` is a hypothesis, so an unmapped ID is recognised as such instead of
being matched to the nearest mapped one.
"""
from __future__ import annotations

import math
from collections.abc import Iterable
from functools import lru_cache

import numpy as np
from scipy.stats import chi2

from vlp_ros.beacon.chips import chip_levels
from vlp_ros.beacon.encoding import packet_bits, packet_chips, packet_length
from vlp_ros.beacon.profile import RowProfile, modulation
from vlp_ros.beacon.reading import (MIN_CONFIDENCE, UNMAPPED_WEIGHT, BeaconReading, log_prior, no_evidence,
                                    reading)

MIN_CHIPS = 6
# Beyond this many packets more rows add little but time: the central ones are used.
MAX_PACKETS = 2.3
# A best fit worse than this tail probability of its chi-square means the lamp is not sending packets.
MISFIT_PROBABILITY = 1e-6


@lru_cache(maxsize=4)
def _codebook(id_bits: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every ID's packet, factored: its chip signs (+1 bright, -1 dark) are ``chip_weights @ design``.

    ``design`` (2 + id_bits, 2^id_bits) is a row of ones over the +-1 of each ID's bits and parity;
    ``chip_weights`` (L, 2 + id_bits) say what the constant (the preamble) and each bit put on
    every packet position (Manchester: +-1 on the bit's two chips). ``fold`` (shift, position) is
    ``(position - shift) % L``: it folds window chips onto packet positions for every shift.
    """
    ids, length = 2 ** id_bits, packet_length(id_bits)
    signs = np.array([packet_chips(i, id_bits) for i in range(ids)], dtype=float) * 2 - 1
    bit_signs = np.array([packet_bits(i, id_bits) for i in range(ids)], dtype=float).T * 2 - 1
    design = np.vstack([np.ones(ids), bit_signs])
    # The contract is linear in the bit signs, so least squares factors it exactly.
    chip_weights = np.linalg.lstsq(design.T, signs, rcond=None)[0]
    if not np.allclose(design.T @ chip_weights, signs):
        raise AssertionError('packet chips are not linear in the bit signs')
    p = np.arange(length)
    # float32: the hypotheses' sums need ~1e-3 nats, and halve the time of the largest arrays.
    return design.astype(np.float32), chip_weights.T.copy(), (p[None, :] - p[:, None]) % length


def decode_packet(profile: RowProfile, chip_rate: float, row_time: float, id_bits: int = 8,
                  known_ids: Iterable[int] | None = None, *, exposure: float | None = None,
                  timing_tolerance: float = 0.05, unmapped_weight: float = UNMAPPED_WEIGHT,
                  min_confidence: float = MIN_CONFIDENCE, model_error: float = 0.2) -> BeaconReading:
    """The ID a packet-mode lamp sends, from its row profile.

    ``chip_rate`` (Hz) and ``row_time`` (s) are nominal: the chip period is searched
    within +-``timing_tolerance``. ``exposure`` (s), when known, tells how many rows
    at each chip edge see both neighbours. ``known_ids`` are the map's IDs (None:
    all); every other ID has ``unmapped_weight`` times their prior. ``model_error``
    is the spread (in half-contrasts) that any chip level may have beyond pixel
    noise: it keeps single chips from deciding alone.
    """
    if not (chip_rate > 0.0 and row_time > 0.0):
        raise ValueError(f'chip_rate and row_time must be positive, got {chip_rate} and {row_time}')
    if not 1 <= id_bits <= 16:
        raise ValueError(f'id_bits must lie in 1..16, got {id_bits}')
    if exposure is not None and not exposure >= 0.0:
        raise ValueError(f'exposure must not be negative, got {exposure}')
    candidates, mapped, prior = _hypotheses(id_bits, None if known_ids is None else tuple(known_ids),
                                            unmapped_weight)
    period = 1.0 / (chip_rate * row_time)
    margin = None if exposure is None else 0.5 * exposure / row_time + 0.25
    # Only the mean level: a curve fitted through few chips bends with them, and the chip levels
    # follow the envelope locally anyway.
    z, w = _central_rows(modulation(profile, degree=0), np.asarray(profile.weights, dtype=float),
                         MAX_PACKETS * packet_length(id_bits) * period)
    levels = chip_levels(z, w, period, timing_tolerance, margin)
    if levels is None:
        return no_evidence(candidates, mapped, prior, 'too few rows for a chip grid')
    if levels.index.size < MIN_CHIPS:
        return no_evidence(candidates, mapped, prior, f'only {levels.index.size} chips visible')
    log_likelihoods, misfit = _id_log_likelihoods(
        levels.levels, 1.0 / (levels.variances + model_error ** 2), levels.index, id_bits)
    if misfit > _misfit_limit(levels.index.size - 4):
        return no_evidence(candidates, mapped, prior, 'the chips fit no packet')
    return reading(candidates, mapped, log_likelihoods, prior, min_confidence)


def _central_rows(z: np.ndarray, w: np.ndarray, rows: float) -> tuple[np.ndarray, np.ndarray]:
    """The lamp's rows (those with weight), cut to the central ``rows`` when there are more."""
    used = (w > 0).nonzero()[0]
    if used.size == 0:
        return z[:0], w[:0]
    first, last = int(used[0]), int(used[-1]) + 1
    excess = last - first - math.ceil(rows)
    if excess > 0:
        first, last = first + excess // 2, last - (excess - excess // 2)
    return z[first:last], w[first:last]


@lru_cache(maxsize=256)
def _misfit_limit(dof: int) -> float:
    return float(chi2.isf(MISFIT_PROBABILITY, dof))


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


def _id_log_likelihoods(x: np.ndarray, v: np.ndarray, k: np.ndarray, id_bits: int) -> tuple[np.ndarray, float]:
    """Log-likelihood of each ID (the window's start in the packet marginalised), and the best fit's
    weighted squared residual.

    Chip k of the window is packet position (k + shift) % L; its level is a
    quadratic baseline in k plus beta * sign, Gaussian with weights ``v``, fitted per
    hypothesis with beta > 0. The baseline takes up what the ID-blind envelope left:
    a preamble's run of bright chips leans any envelope fitted through the stripes.
    """
    design, chip_weights, fold = _codebook(id_bits)
    ids, length = design.shape[1], len(fold)
    basis = _orthonormal_baseline(k, v)
    vx = v * x
    baseline = basis @ vx
    baseline_rss = float(vx @ x - baseline @ baseline)
    # Per packet position: sums of v times each baseline column over the chips that land there, and
    # of v times what the baseline leaves of x (every ID's fit is linear in it). Folded for every
    # shift and factored by bit, then for every (ID, shift): the sums over its bright minus its dark
    # chips, (4, L, ids), each hypothesis along the last axis.
    vbasis = basis * v
    # The residual's row scaled by sqrt(1/2): its squares then come out as half gains (log-likelihoods).
    columns = np.concatenate([vbasis, ((vx - baseline @ vbasis) * np.sqrt(0.5))[None]])
    folded = (columns @ (k[:, None] % length == np.arange(length))).take(fold, axis=1)
    per_bit = (folded @ chip_weights).reshape(4 * length, len(design)).astype(np.float32)
    sums = (per_bit @ design).reshape(4, length, ids)
    # With an orthonormal baseline, what the signs add beyond it is their part orthogonal to it.
    total = np.float32(v.sum())
    schur = np.maximum(total - np.square(sums[:3]).sum(axis=0), np.float32(1e-6) * total)
    target = np.maximum(sums[3], np.float32(0))
    half_gain = target * target / schur
    best = half_gain.max(axis=0)
    spread = np.log(np.exp(half_gain - best, out=half_gain).sum(axis=0) / length)
    return best.astype(float) + spread - 0.5 * baseline_rss, baseline_rss - 2.0 * float(best.max())


def _orthonormal_baseline(k: np.ndarray, v: np.ndarray) -> np.ndarray:
    """1, t, t^2 in the (increasing) chip index, made orthonormal under the weights ``v`` (Gram-Schmidt,
    written out through the weighted moments of t), (3, n)."""
    t = (k - 0.5 * (k[0] + k[-1])) / max(0.5 * float(k[-1] - k[0]), 1.0)
    vt, t2 = v * t, t * t
    m0, m1, m2, m3, m4 = float(v.sum()), float(vt.sum()), float(vt @ t), float(vt @ t2), float((v * t2) @ t2)
    linear = t - m1 / m0
    linear_norm2 = m2 - m1 * m1 / m0
    lean = (m3 - m1 * m2 / m0) / linear_norm2
    quadratic = t2 - m2 / m0 - lean * linear
    quadratic_norm2 = m4 - m2 * m2 / m0 - lean * lean * linear_norm2
    basis = np.empty((3, len(t)))
    basis[0] = 1.0 / math.sqrt(m0)
    np.multiply(linear, 1.0 / math.sqrt(linear_norm2), out=basis[1])
    np.multiply(quadratic, 1.0 / math.sqrt(max(quadratic_norm2, 1e-300)), out=basis[2])
    return basis
