"""
Tone mode (Luxapose style): which lamp's frequency the stripes repeat at.

Row r samples the light at ``r * row_time``, so a square wave of frequency f
shows stripes of period ``1 / (f * row_time)`` rows. A zero-padded FFT of the
profile finds the tone; a least-squares fit of the square wave as the rows see
it (averaged over the exposure, on a quadratic envelope; or, as demosaicing
a Bayer mosaic does, mixed with the neighbouring rows) finds the best
frequency; the likelihood of every frequency around it (phase, envelope and
amplitude at their best, the noise level marginalised) then gives each lamp's
band (its frequency +- the tolerance) its probability, and "some other
frequency" the rest, each band as likely per hertz as any other.

One concern per module: this one is the API (``decode_tone``, and the bare
LEDs' ``point_light_profile`` and ``agreeing``) and the decisions between its
steps; ``model`` the stripe model and its fit (``ToneFit``); ``scan`` the FFT's
peak, the coarse scan and the likelihood grid; ``bands`` the lamps' bands and
the likelihood's mass in each, with Student's t tails. The model's closed-form
3x3 whitening and small inverse are in ``vlp_ros.compiled.linalg``. Each module's tuning
constants open it, beside the kernels that read them: numba freezes a kernel's
globals when it compiles, and its cache notices changes in the kernel's own
file only.
"""
from __future__ import annotations

from functools import lru_cache
import math
from typing import NamedTuple

import numpy as np

from vlp_ros.beacon.profile import light_profile, relative_brightness, RowProfile
from vlp_ros.beacon.reading import (BeaconReading, has_evidence, log_prior, MIN_CONFIDENCE, no_evidence, reading,
                                    UNMAPPED, UNMAPPED_WEIGHT)
from vlp_ros.beacon.tone import scan
from vlp_ros.beacon.tone.bands import band_edges, log_band_masses
from vlp_ros.beacon.tone.model import ToneFit
from vlp_ros.core.observation import LampObservation

# How far off (relative) the row time may be: every frequency then reads off by as much, so each lamp's band
# widens by that share of its frequency (real cameras' nominal row times are 0.3-2 % off).
ROW_TIME_TOLERANCE = 0.02
# Beyond, the bands of a lamp and its octave meet.
MAX_ROW_TIME_TOLERANCE = 0.3
# Evidence (nats) by which the square wave must beat the envelope alone before its frequency counts.
MIN_TONE_EVIDENCE = 25.0
# How well an edge is placed (standard deviation) when all that places it is a gap of this many rows
# (uniform over it), as when the exposure is shorter than a row or (a row) unknown.
_EDGE_QUANTUM = 0.3
# Least share of the fundamental that the exposure lets through (|sinc(exposure x frequency)|): what is
# left of stripes averaged over about a whole period is shaped by the exact exposure more than by the
# frequency.
_MIN_TRANSMISSION = 0.1
# A lamp without a rim (a bare LED) is read out to this many core radii: on the five-LED rig's photos its
# glow still carries the stripes at 10 % of the core's level 4-8 core radii out.
POINT_LIGHT_REACH = 10.0
# A row's brightness is known no better than the light's model (one radial shape times the row's level)
# holds: rows worth at least this share of the best row's weight count alike. Where a bare LED's core clips
# in its bright rows, only their glow measures them, with weights hundreds of times below the dark rows'
# core; left so, the dark rows and the core's edges dominate the fit, and a 10 % glow under a clipped 2 cm
# core read 12 of 30 LEDs off the map and one at its harmonic (none with the cap, nor at 1 % of it).
_ROW_WEIGHT_SHARE = 0.1


def decode_tone(profile: RowProfile, row_time: float, frequencies: dict[int, float], tolerance_hz: float, *,
                unmapped_weight: float = UNMAPPED_WEIGHT, min_confidence: float = MIN_CONFIDENCE,
                min_periods: float = 2.0, exposure: float | None = None,
                row_time_tolerance: float = ROW_TIME_TOLERANCE) -> BeaconReading:
    """
    Return the lamp (by ID) whose ``frequencies`` entry (Hz) matches the stripes within its band.

    The frequency +- (``tolerance_hz`` + ``row_time_tolerance`` x the frequency), since a row time off by 2
    % reads every frequency 2 % off. Where neighbouring bands overlap, a frequency in both gives neither
    (no ID).

    A frequency outside every band counts for the candidate ``UNMAPPED`` (prior
    ``unmapped_weight`` per hertz relative to the bands). Fewer than
    ``min_periods`` stripe periods in view give no evidence: the envelope cannot be
    told from the stripes over less. ``exposure`` (s), when known, is fitted with
    exactly; unknown, it cannot be told from blur across rows, and edges are then
    only trusted to the nearest row (a much wider frequency uncertainty); shorter
    than a row, edges between the rows' exposures are trusted to that gap.
    """
    if not row_time > 0.0:
        raise ValueError(f'row_time must be positive, got {row_time}')
    if not tolerance_hz > 0.0:
        raise ValueError(f'tolerance_hz must be positive, got {tolerance_hz}')
    if exposure is not None and not exposure > 0.0:
        raise ValueError(f'exposure must be positive, got {exposure}')
    if not frequencies:
        raise ValueError('tone decoding needs at least one lamp frequency')
    lamps = _lamps(tuple(frequencies.items()), unmapped_weight)
    candidates, mapped, prior = lamps.candidates, lamps.mapped, lamps.log_prior
    if not 0.0 <= row_time_tolerance < MAX_ROW_TIME_TOLERANCE:
        raise ValueError(f'row_time_tolerance must lie in [0, {MAX_ROW_TIME_TOLERANCE}), got {row_time_tolerance}')
    low, high = band_edges(tuple(lamps.centres.tolist()), tolerance_hz, row_time_tolerance)
    nyquist = 0.5 / row_time
    if not np.all(high < nyquist):
        raise ValueError(f'lamp frequencies must lie in (0, Nyquist {nyquist:.0f} Hz minus their band) '
                         f'got {lamps.centres.tolist()}')

    z, w, usable = relative_brightness(profile)
    if usable < 8:
        return no_evidence(candidates, mapped, prior, 'too few rows')
    duration = len(w) * row_time
    search = (0.5 * lamps.lowest, min(1.5 * lamps.highest, 0.9 * nyquist))
    # The envelope (vignetting, the disc's falloff) is fitted with the stripes, as a quadratic.
    fit = ToneFit(z, w)
    cycles = scan.spectral_peak(fit, search[0] * duration, search[1] * duration)
    if cycles is None:
        return no_evidence(candidates, mapped, prior, 'no tone in the search range')
    if cycles < min_periods:
        return no_evidence(candidates, mapped, prior, f'fewer than {min_periods} stripe periods in view')
    exposure_rows = None if exposure is None else exposure / row_time
    # Unknown, the exposure may be anything from a row on: thin as if it were one.
    fit.thin(cycles, exposure_rows or 1.0)
    if fit.dof < 1:
        return no_evidence(candidates, mapped, prior, 'too few rows')
    start = scan.start(fit, cycles, exposure_rows)
    if start.evidence < MIN_TONE_EVIDENCE:
        return no_evidence(candidates, mapped, prior, 'no tone stands out of the noise')
    if abs(_sinc(start.exposure_rows * start.cycles / fit.rows)) < _MIN_TRANSMISSION:
        return no_evidence(candidates, mapped, prior, 'the exposure spans about whole periods: stripes washed out')
    peak = fit.peak(start.cycles, start.phase, start.exposure_rows, exposure_rows is None)
    if peak is None:
        return no_evidence(candidates, mapped, prior, 'the stripes fit no square wave')
    # Unknown, the exposure may pass for blur across rows: edges are then known to a row, the period to a
    # row over the window. Shorter than a row, edges in the gaps between the rows' exposures move unseen
    # (the likelihood has plateaus that no grid of phases follows): the period is known to a gap.
    gap = 1.0 if exposure is None else max(1.0 - peak.exposure_rows, 0.0)
    quantum = _EDGE_QUANTUM * gap * peak.cycles / fit.rows
    likelihood = scan.likelihood(fit, peak, quantum, start)
    if likelihood is None:
        return no_evidence(candidates, mapped, prior, 'the stripes do not pin the frequency down')
    if likelihood.other_peaks:
        return no_evidence(candidates, mapped, prior, 'the stripes fit frequencies apart about as well')
    log_mass = log_band_masses(likelihood.grid, duration, likelihood.log_density, fit.dof, low, high, search)
    return reading(candidates, mapped, log_mass, prior, min_confidence)


def no_tone(frequencies: dict[int, float], detail: str, unmapped_weight: float = UNMAPPED_WEIGHT) -> BeaconReading:
    """Return the reading that ``decode_tone`` gives a lamp without stripes: no evidence, with why."""
    lamps = _lamps(tuple(frequencies.items()), unmapped_weight)
    return no_evidence(lamps.candidates, lamps.mapped, lamps.log_prior, detail)


def point_light_profile(image: np.ndarray, observation: LampObservation) -> RowProfile:
    """
    Return the brightness per row of a lamp without a rim (a bare LED: core and glow), for ``decode_tone``.

    It uses every row the lamp's light reaches: the core alone spans a few stripe periods, its glow many.
    """
    profile = light_profile(image, observation, reach=POINT_LIGHT_REACH)
    cap = _ROW_WEIGHT_SHARE * float(profile.weights.max(initial=0.0))
    return RowProfile(profile.values, np.minimum(profile.weights, cap), profile.saturated, profile.first_row)


def agreeing(light: BeaconReading, disc: BeaconReading) -> BeaconReading:
    """
    One lamp's reading from its light (``point_light_profile``) checked against its disc's.

    The light's when the disc weighs no other candidate highest, the disc's when the light has no
    evidence, and none when the two favour different candidates.
    """
    if not has_evidence(light):
        return disc
    if has_evidence(disc) and _favourite(disc) != _favourite(light):
        return no_evidence(light.candidates, light.mapped, light.log_prior,
                           'its disc and its glow read different tones')
    return light


def _favourite(reading: BeaconReading) -> int:
    return int(reading.candidates[np.argmax(reading.log_likelihoods + reading.log_prior)])


class _Lamps(NamedTuple):
    """A map's tone lamps as decode_tone weighs them: the same for every lamp of a frame."""

    # Frequencies (Hz, by ID), the lowest and highest.
    centres: np.ndarray
    lowest: float
    highest: float
    # The lamps' IDs, then UNMAPPED; which are mapped; their log prior.
    candidates: np.ndarray
    mapped: np.ndarray
    log_prior: np.ndarray


@lru_cache(maxsize=16)
def _lamps(items: tuple[tuple[int, float], ...], unmapped_weight: float) -> _Lamps:
    """Return the lamps of (ID, frequency) ``items``, with the candidate UNMAPPED (prior ``unmapped_weight``)."""
    items = sorted(items)
    ids = np.array([i for i, _ in items], dtype=int)
    centres = np.array([f for _, f in items], dtype=float)
    if np.any(ids < 0):
        raise ValueError(f'lamp ids must not be negative, got {ids[ids < 0].tolist()}')
    if not np.all(centres > 0.0):
        raise ValueError(f'lamp frequencies must be positive, got {centres.tolist()}')
    mapped = np.append(np.ones(len(ids), dtype=bool), False)
    return _Lamps(centres, float(centres.min()), float(centres.max()), np.append(ids, UNMAPPED), mapped,
                  log_prior(mapped, unmapped_weight))


def _sinc(x: float) -> float:
    return math.sin(math.pi * x) / (math.pi * x) if x != 0.0 else 1.0
