"""Packet mode: which ID explains a lamp's chip levels, weighed against every ID the bits can carry.

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

import numpy as np
from scipy.stats import chi2

from vlp_ros.beacon.chips import chip_levels
from vlp_ros.beacon.encoding import packet_chips, packet_length
from vlp_ros.beacon.profile import RowProfile, modulation
from vlp_ros.beacon.reading import (MIN_CONFIDENCE, UNMAPPED_WEIGHT, BeaconReading, log_prior, no_evidence,
                                    reading)

MIN_CHIPS = 6
# A best fit worse than this tail probability of its chi-square means the lamp is not sending packets.
MISFIT_PROBABILITY = 1e-6


@lru_cache(maxsize=4)
def _codebook(id_bits: int) -> tuple[np.ndarray, np.ndarray]:
    """Signs (+1 bright, -1 dark) of every ID's packet (2^id_bits, L), and the index matrix
    ``(p - shift) % L`` that folds window chips onto packet positions for every shift."""
    signs = np.array([packet_chips(i, id_bits) for i in range(2 ** id_bits)], dtype=float) * 2.0 - 1.0
    length = packet_length(id_bits)
    p = np.arange(length)
    return signs, (p[:, None] - p[None, :]) % length


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
    candidates = np.arange(2 ** id_bits)
    mapped = _mapped(candidates, known_ids)
    prior = log_prior(mapped, unmapped_weight)
    period = 1.0 / (chip_rate * row_time)
    margin = None if exposure is None else 0.5 * exposure / row_time + 0.25
    levels = chip_levels(modulation(profile), np.asarray(profile.weights, dtype=float), period,
                         timing_tolerance, margin)
    if levels is None:
        return no_evidence(candidates, mapped, prior, 'too few rows for a chip grid')
    filled = np.isfinite(levels.variances)
    if np.count_nonzero(filled) < MIN_CHIPS:
        return no_evidence(candidates, mapped, prior, f'only {np.count_nonzero(filled)} chips visible')
    index = np.flatnonzero(filled)
    log_likelihoods, misfit = _id_log_likelihoods(
        levels.levels[index], 1.0 / (levels.variances[index] + model_error ** 2), index, id_bits)
    if misfit > _misfit_limit(index.size - 4):
        return no_evidence(candidates, mapped, prior, 'the chips fit no packet')
    return reading(candidates, mapped, log_likelihoods, prior, min_confidence)


@lru_cache(maxsize=256)
def _misfit_limit(dof: int) -> float:
    return float(chi2.isf(MISFIT_PROBABILITY, dof))


def _mapped(candidates: np.ndarray, known_ids: Iterable[int] | None) -> np.ndarray:
    if known_ids is None:
        return np.ones(len(candidates), dtype=bool)
    known = np.fromiter(known_ids, dtype=int)
    outside = known[(known < 0) | (known >= len(candidates))]
    if outside.size:
        raise ValueError(f'known ids {outside.tolist()} do not fit in {len(candidates).bit_length() - 1} bits')
    return np.isin(candidates, known)


def _id_log_likelihoods(x: np.ndarray, v: np.ndarray, k: np.ndarray, id_bits: int) -> tuple[np.ndarray, float]:
    """Log-likelihood of each ID (the window's start in the packet marginalised), and the best fit's
    weighted squared residual.

    Chip k of the window is packet position (k + shift) % L; its level is a
    quadratic baseline in k plus beta * sign, Gaussian with weights ``v``, fitted per
    hypothesis with beta > 0. The baseline takes up what the ID-blind envelope left:
    a preamble's run of bright chips leans any envelope fitted through the stripes.
    """
    signs, fold = _codebook(id_bits)
    length = signs.shape[1]
    t = (k - k.mean()) / max(0.5 * float(np.ptp(k)), 1.0)
    powers = np.stack([v, v * t, v * t * t, v * t ** 3])
    # Baseline-only normal equations (the same for every hypothesis).
    inverse = np.linalg.inv(np.array([[powers[i + j].sum() if i + j < 4 else (powers[2] * t * t).sum()
                                       for j in range(3)] for i in range(3)]))
    moments = powers[:3] @ x
    weights = inverse @ moments
    baseline_rss = v @ (x * x) - moments @ weights
    phase = k % length
    folded = np.concatenate([np.bincount(phase, weights=w, minlength=length)[fold]
                             for w in (*powers[:3], v * x)], axis=1)
    sums = (signs @ folded).reshape(len(signs), 4, length).transpose(1, 0, 2)
    cross, xs = sums[:3], sums[3]
    # Schur complement of the baseline block: what the signs add beyond the baseline.
    schur = v.sum() - np.einsum('ihl,ij,jhl->hl', cross, inverse, cross)
    target = xs - np.tensordot(weights, cross, axes=1)
    gain = np.where((target > 0.0) & (schur > 1e-9 * v.sum()), target * target / np.maximum(schur, 1e-300), 0.0)
    rss = baseline_rss - gain
    best = rss.min(axis=1)
    log_likelihoods = -0.5 * best + np.log(np.exp(-0.5 * (rss - best[:, None])).sum(axis=1) / length)
    return log_likelihoods, float(best.min())
