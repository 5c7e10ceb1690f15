"""Tone mode (Luxapose style): which lamp's frequency the stripes repeat at.

Row r samples the light at ``r * row_time``, so a square wave of frequency f
shows stripes of period ``1 / (f * row_time)`` rows. A zero-padded FFT of the
profile finds the tone; a least-squares fit of the square wave as the rows see
it (averaged over the exposure, on a quadratic envelope; or, as demosaicing
a Bayer mosaic does, mixed with the neighbouring rows) finds the best
frequency; the likelihood of every frequency around it (phase, envelope and
amplitude at their best, the noise level marginalised) then gives each lamp's
band (its frequency +- the tolerance) its probability, and "some other
frequency" the rest, each band as likely per hertz as any other.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.special import stdtr

from vlp_ros.beacon.profile import RowProfile, light_profile, relative_brightness
from vlp_ros.beacon.reading import (MIN_CONFIDENCE, UNMAPPED, UNMAPPED_WEIGHT, BeaconReading, has_evidence,
                                    log_prior, no_evidence, reading)
from vlp_ros.compiled import kernel
from vlp_ros.core.observation import LampObservation

# How far off (relative) the row time may be: every frequency then reads off by as much, so each lamp's band
# widens by that share of its frequency (issue 14: nominal row times are 0.3-2 % off).
ROW_TIME_TOLERANCE = 0.02
# Beyond, the bands of a lamp and its octave meet.
MAX_ROW_TIME_TOLERANCE = 0.3
# Evidence (nats) by which the square wave must beat the envelope alone before its frequency counts.
MIN_TONE_EVIDENCE = 25.0
_PAD = 8
# Envelope terms (1, u, u^2) and the tone's amplitude (linear), frequency and phase (not).
_PARAMETERS = 6
# Longer windows are thinned to about this many rows (their frequency is pinned down many times over),
# keeping at least _MIN_ROWS_PER_PERIOD rows per stripe period.
_MAX_ROWS = 128
_MIN_ROWS_PER_PERIOD = 8.0
# Phases tried over half a period (the other half only flips the square wave's sign).
_PHASES = 16
_PHASE_SCAN = np.arange(_PHASES) / (2.0 * _PHASES)
# The first scan tries frequencies in 2 _START_STEPS + 1 steps over at least +-_START_REACH cycles per
# window around the FFT's peak.
_START_STEPS = 2
_START_REACH = 0.05
# Unknown, the exposure is tried at these shares of the tone's period. Beyond half a period longer
# exposures look the same (kappa and kappa + 1 give one shape, 1 - kappa its mirror).
_KAPPAS = np.array([0.03, 0.08, 0.15, 0.22, 0.3, 0.38, 0.46])
_MIN_EXPOSURE_ROWS = 0.05
# Phases tried at each frequency of the grid, in spreads of the phase from the fit's line (the spread
# widens where the best is an outer one). The spread is the unmixed fit's: mixed rows place the phase
# more sharply, and lie off the line, so the steps are a third of it.
_PHASE_STEPS = np.linspace(-1.0, 1.0, 7)
# The likelihood is evaluated on a grid of +-10 scales around its peak, the scale being the spread of
# the likelihood (remeasured on the grid, which is redone if needed) ...
_GRID = np.linspace(-10.0, 10.0, 31)
_PASSES = 6
# ... and must hold at least this many grid steps per standard deviation ...
_MIN_STEPS_PER_SIGMA = 1.0
# ... and fall by this many nats towards the grid's ends, or span this many standard deviations each
# side (beyond, a Student's t takes over).
_GRID_DROP = 12.0
_MIN_SPAN = 7.0
# Log densities (relative to the peak's) below these carry no mass worth counting (far below the 1e-4
# a decision leaves to the others): at the grid's ends, for the tails beyond, and on the grid.
_NEGLIGIBLE = -15.0
_FLOOR = -50.0
# How well an edge is placed (standard deviation) when all that places it is a gap of this many rows
# (uniform over it), as when the exposure is shorter than a row or (a row) unknown.
_EDGE_QUANTUM = 0.3
# Least share of the fundamental that the exposure lets through (|sinc(exposure x frequency)|): what is
# left of stripes averaged over about a whole period is shaped by the exact exposure more than by the
# frequency.
_MIN_TRANSMISSION = 0.1
# Colour sensors read through a Bayer mosaic mix each row with its neighbours when demosaicing (bilinear
# luma: about [w, 1 - 2 w, w] with w 0.13 on one row, 0.22 on the next). Unmodelled, the mix moves the
# edges' apparent places by up to a row, and short exposures the frequency by a band. Either camera is
# a hypothesis: a row's own light, or mixed (w at its best of _MIX_LEVELS on even and odd rows apart) with a
# small prior weight, so that mixing counts where it fits clearly better and leaves unmixed frames as they were.
_MIX_LEVELS = np.linspace(0.0, 0.3, 5)
_MIXED_WEIGHT = 0.01
# A lamp without a rim (a bare LED) is read out to this many core radii: on the five-LED rig's photos its
# glow still carries the stripes at 10 % of the core's level 4-8 core radii out (issue 14).
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
    """The lamp (by ID) whose ``frequencies`` entry (Hz) matches the stripes within its band: the frequency
    +- (``tolerance_hz`` + ``row_time_tolerance`` x the frequency), since a row time off by 2 % reads every
    frequency 2 % off. Where neighbouring bands overlap, a frequency in both gives neither (no ID).

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
    centres, lowest, highest, candidates, mapped, prior = _lamps(tuple(frequencies.items()), unmapped_weight)
    if not 0.0 <= row_time_tolerance < MAX_ROW_TIME_TOLERANCE:
        raise ValueError(f'row_time_tolerance must lie in [0, {MAX_ROW_TIME_TOLERANCE}), got {row_time_tolerance}')
    low, high = _bands(tuple(centres.tolist()), tolerance_hz, row_time_tolerance)
    nyquist = 0.5 / row_time
    if not np.all(high < nyquist):
        raise ValueError(f'lamp frequencies must lie in (0, Nyquist {nyquist:.0f} Hz minus their band) '
                         f'got {centres.tolist()}')

    z, w, usable = relative_brightness(profile)
    if usable < 8:
        return no_evidence(candidates, mapped, prior, 'too few rows')
    duration = len(w) * row_time
    search = (0.5 * lowest, min(1.5 * highest, 0.9 * nyquist))
    # The envelope (vignetting, the disc's falloff) is fitted with the stripes, as a quadratic.
    fit = _ToneFit(z, w)
    cycles = fit.spectral_peak(search[0] * duration, search[1] * duration)
    if cycles is None:
        return no_evidence(candidates, mapped, prior, 'no tone in the search range')
    if cycles < min_periods:
        return no_evidence(candidates, mapped, prior, f'fewer than {min_periods} stripe periods in view')
    exposure_rows = None if exposure is None else exposure / row_time
    # Unknown, the exposure may be anything from a row on: thin as if it were one.
    fit.thin(cycles, exposure_rows or 1.0)
    if fit.dof < 1:
        return no_evidence(candidates, mapped, prior, 'too few rows')
    start = fit.start(cycles, exposure_rows)
    if start.evidence < MIN_TONE_EVIDENCE:
        return no_evidence(candidates, mapped, prior, 'no tone stands out of the noise')
    if abs(_sinc(start.exposure_rows * start.cycles / fit.rows)) < _MIN_TRANSMISSION:
        return no_evidence(candidates, mapped, prior, 'the exposure spans about whole periods: stripes washed out')
    peak = fit.peak(start, exposure_rows is None)
    if peak is None:
        return no_evidence(candidates, mapped, prior, 'the stripes fit no square wave')
    # Unknown, the exposure may pass for blur across rows: edges are then known to a row, the period to a
    # row over the window. Shorter than a row, edges in the gaps between the rows' exposures move unseen
    # (the likelihood has plateaus that no grid of phases follows): the period is known to a gap.
    gap = 1.0 if exposure is None else max(1.0 - peak.exposure_rows, 0.0)
    quantum = _EDGE_QUANTUM * gap * peak.cycles / fit.rows
    likelihood = fit.likelihood(peak, quantum, start)
    if likelihood is None:
        return no_evidence(candidates, mapped, prior, 'the stripes do not pin the frequency down')
    if likelihood.other_peaks:
        return no_evidence(candidates, mapped, prior, 'the stripes fit frequencies apart about as well')
    grid, log_density = likelihood.grid, likelihood.log_density
    log_mass = _log_band_masses(grid, duration, log_density, fit.dof, low, high, search)
    return reading(candidates, mapped, log_mass, prior, min_confidence)


def point_light_profile(image: np.ndarray, observation: LampObservation) -> RowProfile:
    """Brightness per row of a lamp without a rim (a bare LED: core and glow), from every row its light
    reaches, for ``decode_tone``: the core alone spans a few stripe periods, its glow many."""
    profile = light_profile(image, observation, reach=POINT_LIGHT_REACH)
    cap = _ROW_WEIGHT_SHARE * float(profile.weights.max(initial=0.0))
    return RowProfile(profile.values, np.minimum(profile.weights, cap), profile.saturated, profile.first_row)


def agreeing(light: BeaconReading, disc: BeaconReading) -> BeaconReading:
    """One lamp's reading from its light (``point_light_profile``) checked against its disc's: the light's
    when the disc weighs no other candidate highest, the disc's when the light has no evidence, and
    none when the two favour different candidates."""
    if not has_evidence(light):
        return disc
    if has_evidence(disc) and _favourite(disc) != _favourite(light):
        return no_evidence(light.candidates, light.mapped, light.log_prior, 'its disc and its glow read different tones')
    return light


def _favourite(reading: BeaconReading) -> int:
    return int(reading.candidates[np.argmax(reading.log_likelihoods + reading.log_prior)])


@lru_cache(maxsize=16)
def _bands(centres: tuple[float, ...], tolerance_hz: float, row_time_tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """Each lamp's band (Hz): its low and high edges."""
    frequencies = np.array(centres)
    low = frequencies * (1.0 - row_time_tolerance) - tolerance_hz
    high = frequencies * (1.0 + row_time_tolerance) + tolerance_hz
    for edges in (low, high):
        edges.flags.writeable = False
    return low, high


@lru_cache(maxsize=16)
def _lamps(items: tuple[tuple[int, float], ...],
           unmapped_weight: float) -> tuple[np.ndarray, float, float, np.ndarray, np.ndarray, np.ndarray]:
    """Lamp frequencies (by ID), the lowest and highest, candidates (the lamps, then UNMAPPED), which are
    mapped, and their log prior: the same for every lamp of a frame."""
    items = sorted(items)
    ids = np.array([i for i, _ in items], dtype=int)
    centres = np.array([f for _, f in items], dtype=float)
    if np.any(ids < 0):
        raise ValueError(f'lamp ids must not be negative, got {ids[ids < 0].tolist()}')
    if not np.all(centres > 0.0):
        raise ValueError(f'lamp frequencies must be positive, got {centres.tolist()}')
    mapped = np.append(np.ones(len(ids), dtype=bool), False)
    return (centres, float(centres.min()), float(centres.max()), np.append(ids, UNMAPPED), mapped,
            log_prior(mapped, unmapped_weight))


@dataclass(frozen=True)
class _Start:
    """The best square wave of a coarse scan (cycles per window, phase, exposure rows), the evidence
    (nats) by which it beats the envelope alone, and the best residual sum of squares at each cycles
    tried."""

    cycles: float
    phase: float
    exposure_rows: float
    evidence: float
    tried: np.ndarray
    rss: np.ndarray


@dataclass(frozen=True)
class _Peak:
    """The best square wave: cycles per window, phase (periods, at the window's centre), exposure (rows);
    the spread (as the fit's curvature has it) of its cycles, how its best phase moves with them, and the
    phase's spread at fixed cycles (at least half the gap between the rows' exposures)."""

    cycles: float
    phase: float
    exposure_rows: float
    scale: float
    slope: float
    phase_spread: float


@dataclass(frozen=True)
class _Likelihood:
    """Cycles per window on a grid and the log likelihood of each (relative to the best); and whether a
    frequency beyond the grid fits nearly as well (the likelihood has other peaks)."""

    grid: np.ndarray
    log_density: np.ndarray
    other_peaks: bool


class _ToneFit:
    """Weighted least squares of a profile by an envelope (1, u, u^2) plus an exposure-smeared square wave.

    Time runs in units of the window from its centre (tau in [-0.5, 0.5)), frequency in cycles per
    window, phase in periods at the window's centre (where it hardly moves with the frequency).
    """

    def __init__(self, z: np.ndarray, w: np.ndarray) -> None:
        self.rows = len(z)
        self.z, self.w = z, w
        self._use(1)

    def _use(self, stride: int) -> None:
        # Templates are taken at every row from the one before the first kept to the one after the last, a
        # kept row's own and its neighbours' (tau_around); the envelope is orthonormal (weighted) over the
        # kept rows, and y what it leaves of the profile.
        (self.tau, self.tau_around, self.sqrt_w, self.envelope, self.y, self.null_rss, self.weighted_y,
         self.products, self.weights) = _envelope_fit(self.z, self.w, stride)
        self.dof = len(self.tau) - _PARAMETERS
        # All that _rss_kernel needs of the fit (after the cycles, phases and exposures).
        self.model = (self.rows, self.tau_around, stride, self.products, self.weights, self.null_rss,
                      0.5 * (self.dof + 1))

    def thin(self, cycles: float, exposure_rows: float) -> None:
        """Keep every k-th row of a long window, while the rows' exposures still cover the time axis (a
        gap would hide edges)."""
        stride = min(math.ceil(self.rows / _MAX_ROWS), int(self.rows / cycles / _MIN_ROWS_PER_PERIOD),
                     int(exposure_rows))
        if stride > 1:
            self._use(stride)

    def spectral_peak(self, low: float, high: float) -> float | None:
        """Cycles per window of the strongest sinusoid between ``low`` and ``high`` cycles (the zero-padded
        FFT's peak); None if the range holds no frequency the FFT resolves."""
        n = len(self.y)
        size = _PAD * (1 << (n - 1).bit_length())
        return _spectral_peak(np.fft.rfft(self.weighted_y, size), n, size, low, high)

    def start(self, cycles: float, exposure_rows: float | None) -> _Start:
        """The best square wave among a scan of frequencies around ``cycles`` (the FFT's peak, which the
        harmonics that few rows per period alias can pull aside), of phases over half a period (the other
        half only flips the sign) and, unknown, of exposures; its phase refined by a parabola through the
        best and its neighbours."""
        return _Start(*_scan(cycles, math.nan if exposure_rows is None else exposure_rows, self.dof, *self.model))

    def peak(self, start: _Start, free: bool) -> _Peak | None:
        """The best square wave near the ``start`` (the exposure ``free`` or not): one Gauss-Newton step
        (the likelihood grid around it finds the rest), with the spreads of its frequency and phase."""
        found, *fields = _gauss_newton(start.cycles, start.phase, start.exposure_rows, free, self.rows, self.tau,
                                       self.sqrt_w, self.envelope, self.y, self.null_rss, self.dof)
        return _Peak(*fields) if found else None

    def likelihood(self, peak: _Peak, quantum: float, start: _Start) -> _Likelihood | None:
        """Cycles per window on a grid around the ``peak``, the log likelihood of each (phase, envelope
        and amplitude at their best, the noise level marginalised; blurred by ``quantum`` cycles), and
        whether a frequency beyond it that the ``start`` scan or the grid's passes tried fits nearly as
        well; None if no grid resolves it."""
        found, grid, log_density, other_peaks = _likelihood_grid(
            peak.cycles, peak.phase, peak.slope, max(peak.scale, quantum), peak.phase_spread, peak.exposure_rows,
            quantum, start.tried, start.rss, self.dof, *self.model)
        return _Likelihood(grid, log_density, other_peaks) if found else None


@kernel
def _likelihood_grid(cycles: float, phase: float, slope: float, scale: float, spread: float, exposure_rows: float,
                     quantum: float, start_tried: np.ndarray, start_rss: np.ndarray, dof: int, rows: int,
                     tau_around: np.ndarray, stride: int, products: np.ndarray, weights: np.ndarray, null_rss: float,
                     power: float) -> tuple[bool, np.ndarray, np.ndarray, bool]:
    """_ToneFit.likelihood: _grid_pass's passes until the grid resolves the likelihood (whether one does),
    the last grid and its log likelihood (blurred by ``quantum``), and whether a frequency beyond it fits
    nearly as well: of the first scan or of an earlier pass (these with the grid's phases: a rugged
    plateau of peaks can leave the last grid on one of them, its t tails hiding the others)."""
    n, step = len(_GRID), _GRID[1] - _GRID[0]
    centre = cycles
    tried, tried_rss = np.empty(_PASSES * n), np.empty(_PASSES * n)
    for done in range(_PASSES):
        grid = centre + scale * _GRID
        if grid[0] <= 0.0:
            return False, grid, grid, False
        # Each frequency's best phase lies near the regression line through the peak.
        rss, log_density, density, mean, sigma, best, cornered = _grid_pass(
            grid, phase + slope * (grid - cycles), spread, exposure_rows, quantum, rows, tau_around, stride,
            products, weights, null_rss, power)
        tried[done * n:(done + 1) * n], tried_rss[done * n:(done + 1) * n] = grid, rss
        if cornered:
            # The best phase lies beyond the ones tried where the likelihood matters: try wider.
            spread *= 3.0
        elif not n // 4 <= best < n - n // 4:
            centre, scale = grid[best], 3.0 * scale
        elif sigma < _MIN_STEPS_PER_SIGMA * scale * step:
            # Narrower than the grid resolves: the spread of a sharp peak shows better in its curvature
            # (at most ten times narrower: between grid points it is not known yet).
            bend = log_density[best - 1] + log_density[best + 1] - 2.0 * log_density[best]
            sigma = min(sigma, scale * step / np.sqrt(max(-bend, 1e-12)))
            centre, scale = mean, max(sigma, 0.1 * scale)
        elif max(log_density[0], log_density[-1]) >= -_GRID_DROP and sigma * _MIN_SPAN > scale * _GRID[-1]:
            centre, scale = mean, sigma
        else:
            if quantum > 0.0:
                log_density = _blurred(grid, density, quantum)
            bound = rss.min() * np.exp(2.0 * _GRID_DROP / (dof + 1))
            other_peaks = False
            for i in range(len(start_tried)):
                other_peaks |= (start_tried[i] < grid[0] or start_tried[i] > grid[-1]) and start_rss[i] < bound
            for i in range((done + 1) * n):
                other_peaks |= (tried[i] < grid[0] or tried[i] > grid[-1]) and tried_rss[i] < bound
            return True, grid, log_density, other_peaks
    return False, tried[:n], tried[:n], False


@kernel
def _rss_kernel(cycles: np.ndarray, phase: np.ndarray, exposure_rows: np.ndarray, rows: int, tau_around: np.ndarray,
                stride: int, products: np.ndarray, weights: np.ndarray, null_rss: float, power: float) -> np.ndarray:
    """Residual sum of squares of each (cycles, phase, exposure rows) (1-d arrays of one length) with the
    best envelope and amplitude, as both cameras together have it: the rows' own light, or mixed with the
    neighbouring rows' (the best of _MIX_LEVELS on even and odd rows), with prior weight _MIXED_WEIGHT;
    that is the rss whose
    likelihood (noise level marginalised) is the sum of theirs, ``power`` being (dof + 1) / 2. The fit's
    arguments are its ``model``.

    A row sees the +-1 square wave's mean over its exposure, exactly: a difference of the wave's integral,
    a triangle wave 0.5 - |frac(x) - 0.5|, over the exposure (its length only scales the template, which
    the amplitude absorbs). Kept row i is template position stride i + 1, its neighbours stride i and
    stride i + 2. Its products with the weighted envelope and y (``products``, four columns) and with each
    other (``weights``) are summed for the row's own template and, on even and odd rows apart, for what
    mixing in the neighbours adds per unit of w; every mix m = row + w_even even + w_odd odd then has
    explained = (m . y)^2 / |m|^2, envelope projected out, |m|^2 a quadratic in w_even and w_odd.
    """
    count, kept = len(cycles), len(weights)
    template = np.empty(len(tau_around))
    out = np.empty(count)
    for c in range(count):
        shift = cycles[c] * exposure_rows[c] / rows
        # Every template position up to stride 3 (a plain loop: it vectorises), else only the kept rows' and
        # their neighbours'.
        if stride <= 3:
            for p in range(len(tau_around)):
                early = cycles[c] * tau_around[p] - phase[c]
                late = early + shift
                template[p] = abs(early - np.rint(early)) - abs(late - np.rint(late))
        else:
            for i in range(kept):
                for p in range(stride * i, stride * i + 3):
                    early = cycles[c] * tau_around[p] - phase[c]
                    late = early + shift
                    template[p] = abs(early - np.rint(early)) - abs(late - np.rint(late))
        # Scalars (registers), summed in row order.
        r0 = r1 = r2 = r3 = e0 = e1 = e2 = e3 = o0 = o1 = o2 = o3 = 0.0
        rr = rm_even = rm_odd = mm_even = mm_odd = 0.0
        for i in range(kept):
            row = template[stride * i + 1]
            mixing = template[stride * i] + template[stride * i + 2]
            mixing -= 2.0 * row
            r0 += row * products[i, 0]
            r1 += row * products[i, 1]
            r2 += row * products[i, 2]
            r3 += row * products[i, 3]
            rr += row * row * weights[i]
            if (stride * i) & 1:
                o0 += mixing * products[i, 0]
                o1 += mixing * products[i, 1]
                o2 += mixing * products[i, 2]
                o3 += mixing * products[i, 3]
                rm_odd += row * mixing * weights[i]
                mm_odd += mixing * mixing * weights[i]
            else:
                e0 += mixing * products[i, 0]
                e1 += mixing * products[i, 1]
                e2 += mixing * products[i, 2]
                e3 += mixing * products[i, 3]
                rm_even += row * mixing * weights[i]
                mm_even += mixing * mixing * weights[i]
        # |m|^2 = norm_0 + norm_even w_even + norm_odd w_odd + norm_even2 w_even^2 + norm_odd2 w_odd^2
        # + norm_cross w_even w_odd, the envelope's share of each product (its three columns) taken off.
        norm_0 = rr - (r0 * r0 + r1 * r1 + r2 * r2)
        norm_even = 2.0 * (rm_even - (r0 * e0 + r1 * e1 + r2 * e2))
        norm_odd = 2.0 * (rm_odd - (r0 * o0 + r1 * o1 + r2 * o2))
        norm_even2 = mm_even - (e0 * e0 + e1 * e1 + e2 * e2)
        norm_odd2 = mm_odd - (o0 * o0 + o1 * o1 + o2 * o2)
        norm_cross = -2.0 * (e0 * o0 + e1 * o1 + e2 * o2)
        own = max(null_rss - r3 * r3 / max(norm_0, 1e-300), 1e-300)
        best = -np.inf
        for even in _MIX_LEVELS:
            projection_even = r3 + e3 * even
            norm_even_part = norm_0 + (norm_even + norm_even2 * even) * even
            for odd in _MIX_LEVELS:
                projection = projection_even + o3 * odd
                norm = norm_even_part + (norm_odd + norm_odd2 * odd + norm_cross * even) * odd
                best = max(best, projection * projection / max(norm, 1e-300))
        mixed = max(null_rss - best, 1e-300)
        out[c] = mixed * (_MIXED_WEIGHT + (mixed / own) ** power) ** (-1.0 / power)
    return out


@kernel
def _gauss_newton(cycles: float, phase: float, exposure_rows: float, free: bool, rows: int, tau: np.ndarray,
                  sqrt_w: np.ndarray, envelope: np.ndarray, y: np.ndarray, null_rss: float,
                  dof: int) -> tuple[bool, float, float, float, float, float, float]:
    """_ToneFit.peak: whether there is one, and its cycles, phase, exposure rows, the spread of its cycles, how
    its best phase moves with them and the phase's spread at fixed cycles."""
    rss, normal, gradient = _linearised_kernel(cycles, phase, exposure_rows, free, rows, tau, sqrt_w, envelope, y,
                                               null_rss)
    invertible, inverse = _inverse(normal)
    # Edges in the gaps between the rows' exposures move unseen by up to a gap (in periods).
    gap = max(1.0 - exposure_rows, 0.0) * cycles / rows
    if not (invertible and inverse[0, 0] > 0.0 and inverse[1, 1] > 0.0):
        # No edge inside an exposure: all there is to go on is the gaps (the period moves by about a
        # gap over the window).
        return gap > 0.0, cycles, phase, exposure_rows, gap, 0.0, gap
    step = inverse @ gradient
    cycles, phase = cycles + step[0], phase + step[1]
    if free:
        exposure_rows = min(max(exposure_rows + step[2], _MIN_EXPOSURE_ROWS), 0.5 * rows / cycles)
    # The noise from the residual the step leaves (as the linearised fit predicts it).
    covariance = inverse * (max(rss - step @ gradient, 1e-3 * rss) / dof)
    slope = covariance[0, 1] / covariance[0, 0]
    return (True, cycles, phase, exposure_rows, math.sqrt(covariance[0, 0]), slope,
            max(math.sqrt(max(covariance[1, 1] - slope * covariance[0, 1], 0.0)), 0.5 * gap))


@kernel
def _linearised_kernel(cycles: float, phase: float, exposure: float, free_exposure: bool, rows: int, tau: np.ndarray,
                       sqrt_w: np.ndarray, envelope: np.ndarray, y: np.ndarray,
                       null_rss: float) -> tuple[float, np.ndarray, np.ndarray]:
    """Residual sum of squares at (cycles, phase, exposure rows), and the normal matrix and gradient (J^T J,
    J^T r) over cycles, phase (and exposure) with envelope and amplitude at their best (Kaufman's variable
    projection Jacobian J), all from products of the template (0) and its derivatives, weighted, with each
    other, the envelope and y."""
    m = 4 if free_exposure else 3
    kappa = cycles * exposure / rows
    column = np.empty(m)
    products, along, with_y = np.zeros((m, m)), np.zeros((m, 3)), np.zeros(m)
    for i in range(len(tau)):
        theta = cycles * tau[i] - phase
        early = theta - np.floor(theta)
        late = theta + kappa
        late -= np.floor(late)
        mean = (min(late, 1.0 - late) - min(early, 1.0 - early)) / kappa
        square = np.sign(0.5 - late)
        slope = (square - np.sign(0.5 - early)) / kappa
        by_kappa = (square - mean) / kappa
        column[0] = mean * sqrt_w[i]
        column[1] = (slope * tau[i] + by_kappa * (exposure / rows)) * sqrt_w[i]
        column[2] = -slope * sqrt_w[i]
        if free_exposure:
            column[3] = by_kappa * (cycles / rows) * sqrt_w[i]
        for a in range(m):
            with_y[a] += column[a] * y[i]
            for k in range(3):
                along[a, k] += column[a] * envelope[k, i]
            for b in range(m):
                products[a, b] += column[a] * column[b]
    # Products of the envelope-free template (0) and derivatives (1...).
    gram = np.empty((m, m))
    for a in range(m):
        for b in range(m):
            gram[a, b] = products[a, b] - (along[a, 0] * along[b, 0] + along[a, 1] * along[b, 1]
                                           + along[a, 2] * along[b, 2])
    norm = max(gram[0, 0], 1e-300)
    amplitude = with_y[0] / norm
    normal, gradient = np.empty((m - 1, m - 1)), np.empty(m - 1)
    for a in range(1, m):
        gradient[a - 1] = amplitude * (with_y[a] - amplitude * gram[0, a])
        for b in range(1, m):
            normal[a - 1, b - 1] = amplitude * amplitude * (gram[a, b] - gram[0, a] * gram[0, b] / norm)
    return null_rss - amplitude * with_y[0], normal, gradient


@kernel
def _scan(peak_cycles: float, given_exposure_rows: float, dof: int, rows: int, tau_around: np.ndarray, stride: int,
          products: np.ndarray, weights: np.ndarray, null_rss: float,
          power: float) -> tuple[float, float, float, float, np.ndarray, np.ndarray]:
    """_ToneFit.start's scan: _rss_kernel at every cycles around ``peak_cycles`` x exposure rows (the given
    ones, or unknown (nan) _KAPPAS of the period) x phase of _PHASE_SCAN; the best's cycles, phase (refined
    by a parabola through it and its neighbours) and exposure rows, the evidence (nats) by which it beats
    the envelope alone, the cycles tried and the least rss at each."""
    # Steps that move the window's ends by half a row, over at least +-_START_REACH cycles.
    step = max(0.5 * peak_cycles / rows, _START_REACH / _START_STEPS)
    cycles = peak_cycles + step * np.arange(-_START_STEPS, _START_STEPS + 1)
    if math.isnan(given_exposure_rows):
        exposure_rows = _KAPPAS * rows / peak_cycles
    else:
        exposure_rows = np.full(1, given_exposure_rows)
    n, m, phases = len(cycles), len(exposure_rows), len(_PHASE_SCAN)
    size = n * m * phases
    flat_cycles, flat_phase, flat_exposure = np.empty(size), np.empty(size), np.empty(size)
    for i in range(n):
        for j in range(m):
            for k in range(phases):
                at = (i * m + j) * phases + k
                flat_cycles[at], flat_phase[at], flat_exposure[at] = cycles[i], _PHASE_SCAN[k], exposure_rows[j]
    rss = _rss_kernel(flat_cycles, flat_phase, flat_exposure, rows, tau_around, stride, products, weights, null_rss,
                      power)
    best = np.argmin(rss)
    row, k = best // phases, best % phases
    left, centre, right = rss[row * phases + (k - 1) % phases], rss[best], rss[row * phases + (k + 1) % phases]
    # The parabola through the best and its neighbours (the best is the least of the three).
    curvature = max(left + right - 2.0 * centre, 1e-300)
    place = 0.5 * (left - right) / curvature
    least = max(centre - 0.5 * curvature * place * place, 0.0)
    sigma2 = max(least / dof, 1e-15 * null_rss, 1e-300)
    least_by_cycles = np.empty(n)
    for i in range(n):
        least_by_cycles[i] = rss[i * m * phases:(i + 1) * m * phases].min()
    return (cycles[row // m], _PHASE_SCAN[k] + place / (2.0 * phases), exposure_rows[row % m],
            (null_rss - least) / (2.0 * sigma2), cycles, least_by_cycles)


@kernel
def _grid_pass(grid: np.ndarray, phase: np.ndarray, spread: float, exposure_rows: float, quantum: float, rows: int,
               tau_around: np.ndarray, stride: int, products: np.ndarray, weights: np.ndarray, null_rss: float,
               power: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float, int, bool]:
    """One pass of the likelihood grid: at each cycles of ``grid``, the residual sum of squares with the
    phase at its best among ``phase`` and ``spread`` x _PHASE_STEPS either side; the log likelihood
    (noise level marginalised, relative to the best) and likelihood; their mean and spread (blurred by
    ``quantum``), the best grid point, and whether a best phase was an outer one (it may lie further
    out) where the likelihood matters."""
    n, steps = len(grid), len(_PHASE_STEPS)
    cycles, tried = np.empty(n * steps), np.empty(n * steps)
    for i in range(n):
        for j in range(steps):
            cycles[i * steps + j] = grid[i]
            tried[i * steps + j] = phase[i] + spread * _PHASE_STEPS[j]
    all_rss = _rss_kernel(cycles, tried, np.full(n * steps, exposure_rows), rows, tau_around, stride, products,
                          weights, null_rss, power)
    rss, log_density = np.empty(n), np.empty(n)
    outer = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        best = 0
        for j in range(1, steps):
            if all_rss[i * steps + j] < all_rss[i * steps + best]:
                best = j
        rss[i], outer[i] = all_rss[i * steps + best], best == 0 or best == steps - 1
        log_density[i] = -power * np.log(max(rss[i], 1e-300))
    log_density -= log_density.max()
    density = np.exp(log_density)
    total = density.sum()
    mean = (density * grid).sum() / total
    # The spread after the blur by the edge quantum.
    sigma = math.hypot(math.sqrt((density * (grid - mean) ** 2).sum() / total), quantum)
    cornered = False
    for i in range(n):
        cornered |= outer[i] and log_density[i] > -_GRID_DROP
    return rss, log_density, density, mean, sigma, int(np.argmax(log_density)), cornered


@kernel
def _spectral_peak(spectrum: np.ndarray, n: int, size: int, low: float, high: float) -> float | None:
    """_ToneFit.spectral_peak from the ``n`` rows' FFT zero-padded to ``size``."""
    first, last = math.ceil(low * size / n), min(int(high * size / n), len(spectrum) - 1)
    if last < first:
        return None
    peak, most = first, -1.0
    for i in range(first, last + 1):
        power = spectrum[i].real ** 2 + spectrum[i].imag ** 2
        if power > most:
            peak, most = i, power
    cycles = peak * n / size
    if 0 < peak < len(spectrum) - 1:
        # Parabola through the log spectrum around the peak (a Gaussian-like lobe).
        left, right = spectrum[peak - 1], spectrum[peak + 1]
        left = math.log(left.real ** 2 + left.imag ** 2 + 1e-300)
        right = math.log(right.real ** 2 + right.imag ** 2 + 1e-300)
        centre = math.log(most + 1e-300)
        curvature = left - 2.0 * centre + right
        if curvature < 0.0:
            cycles += n / size * min(max(0.5 * (left - right) / curvature, -0.5), 0.5)
    return cycles


def _sinc(x: float) -> float:
    return math.sin(math.pi * x) / (math.pi * x) if x != 0.0 else 1.0


@kernel
def _envelope_fit(z: np.ndarray, w: np.ndarray, stride: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                                                     np.ndarray, float, np.ndarray, np.ndarray,
                                                                     np.ndarray]:
    """Every ``stride``-th row of profile ``z`` (weights ``w``): its time tau (window units from the centre), tau
    at every row from the one before the first kept to the one after the last, sqrt(w), the orthonormal
    (weighted) envelope basis 1, u, u^2 (3, kept), the weighted profile with the envelope projected out
    (y) and its square sum, y sqrt(w), the rows' products with the templates (kept, 4: envelope times
    sqrt(w), y sqrt(w)) and the weights."""
    rows = len(z)
    kept = (rows - 1) // stride + 1
    tau, sqrt_w = np.empty(kept), np.empty(kept)
    tau_around = (np.arange(-1, stride * (kept - 1) + 2) - 0.5 * (rows - 1)) / rows
    basis = np.empty((3, kept))
    for i in range(kept):
        tau[i] = (stride * i - 0.5 * (rows - 1)) / rows
        sqrt_w[i] = math.sqrt(w[stride * i])
        u = 2.0 * tau[i]
        basis[0, i], basis[1, i], basis[2, i] = sqrt_w[i], u * sqrt_w[i], u * u * sqrt_w[i]
    envelope = _whitening(basis @ basis.T) @ basis
    y = np.empty(kept)
    for i in range(kept):
        y[i] = z[stride * i] * sqrt_w[i]
    y -= (envelope @ y) @ envelope
    weighted_y = y * sqrt_w
    products = np.empty((kept, 4))
    for i in range(kept):
        for k in range(3):
            products[i, k] = envelope[k, i] * sqrt_w[i]
        products[i, 3] = weighted_y[i]
    return tau, tau_around, sqrt_w, envelope, y, float(y @ y), weighted_y, products, sqrt_w * sqrt_w


@kernel
def _whitening(gram: np.ndarray) -> np.ndarray:
    """The inverse of the Cholesky factor of a 3x3 Gram matrix, in closed form."""
    a, b, c, d, e, f = gram[0, 0], gram[0, 1], gram[0, 2], gram[1, 1], gram[1, 2], gram[2, 2]
    l00 = math.sqrt(a)
    l10, l20 = b / l00, c / l00
    l11 = math.sqrt(d - l10 * l10)
    l21 = (e - l20 * l10) / l11
    l22 = math.sqrt(f - l20 * l20 - l21 * l21)
    m10 = -l10 / (l00 * l11)
    out = np.zeros((3, 3))
    out[0, 0], out[1, 0], out[1, 1] = 1.0 / l00, m10, 1.0 / l11
    out[2, 0], out[2, 1], out[2, 2] = -(l20 / l00 + l21 * m10) / l22, -l21 / (l11 * l22), 1.0 / l22
    return out


@kernel
def _inverse(m: np.ndarray) -> tuple[bool, np.ndarray]:
    """Whether a 2x2 or 3x3 matrix is invertible, and its inverse by cofactors."""
    n = len(m)
    cofactors = np.empty((n, n))
    if n == 2:
        cofactors[0, 0], cofactors[0, 1], cofactors[1, 0], cofactors[1, 1] = m[1, 1], -m[0, 1], -m[1, 0], m[0, 0]
        det = m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0]
    else:
        for r in range(3):
            for c in range(3):
                # The cofactor of m[c, r]: rows and columns other than c and r, in cyclic order.
                r1, r2, c1, c2 = (c + 1) % 3, (c + 2) % 3, (r + 1) % 3, (r + 2) % 3
                cofactors[r, c] = m[r1, c1] * m[r2, c2] - m[r1, c2] * m[r2, c1]
        det = m[0, 0] * cofactors[0, 0] + m[0, 1] * cofactors[1, 0] + m[0, 2] * cofactors[2, 0]
    scale = np.abs(m).max() ** n
    return np.isfinite(det) and abs(det) > 1e-12 * scale, cofactors / det


def _log_band_masses(grid: np.ndarray, duration: float, log_density: np.ndarray, dof: int, low: np.ndarray,
                     high: np.ndarray, search: tuple[float, float]) -> np.ndarray:
    """log P(f in each band: [``low``, ``high``], per lamp) and, last, log P(f in none), for f's density
    given on an even ``grid`` of cycles per window of ``duration`` (exponential between grid points: a
    Gaussian's tails are integrated well from a coarse grid), continued beyond it by the Student's t
    (``dof`` degrees of freedom, centred on the grid's peak) whose density meets the grid's ends, all cut
    to the ``search`` range: a frequency outside it would have shown as another peak."""
    frequency, edges, log_density, cdf, tails = _grid_cdf(grid, duration, log_density, low, high,
                                                          search[0], search[1])
    for end, tailed in zip((0, -1), tails):
        if tailed:
            _add_t_tail(frequency, log_density, dof, edges, cdf, end)
    return _band_log_masses(cdf, edges, len(low))


def _add_t_tail(frequency: np.ndarray, log_density: np.ndarray, dof: int, edges: np.ndarray, cdf: np.ndarray,
                end: int) -> None:
    """Adds to ``cdf`` at the ``edges`` beyond the grid's ``end`` (0 or -1) the mass of the Student's t whose
    density meets the grid's there."""
    beyond = edges < frequency[0] if end == 0 else edges > frequency[-1]
    # The t's scale that makes it exp(log_density[end]) at the grid's end, 1 at the centre (where the
    # t density is gamma((dof + 1) / 2) / (sqrt(dof pi) gamma(dof / 2))).
    centre = frequency[np.argmax(log_density)]
    scale = abs(frequency[end] - centre) / math.sqrt(dof * max(math.expm1(-2.0 * log_density[end] / (dof + 1)), 1e-12))
    peak = math.exp(math.lgamma(0.5 * (dof + 1)) - math.lgamma(0.5 * dof)) / math.sqrt(dof * math.pi)
    tail = stdtr(dof, (edges[beyond] - centre) / scale) - stdtr(dof, (frequency[end] - centre) / scale)
    cdf[beyond] += tail * scale / peak


@kernel
def _blurred(grid: np.ndarray, density: np.ndarray, quantum: float) -> np.ndarray:
    """log of ``density`` on ``grid`` blurred by a Gaussian of spread ``quantum`` (at least 1e-300)."""
    out = np.empty(len(grid))
    for i in range(len(grid)):
        total = 0.0
        for j in range(len(grid)):
            total += np.exp(-0.5 * ((grid[i] - grid[j]) / quantum) ** 2) * density[j]
        out[i] = np.log(max(total, 1e-300))
    return out


@kernel
def _grid_cdf(grid: np.ndarray, duration: float, log_density: np.ndarray, low: np.ndarray, high: np.ndarray,
              search_low: float, search_high: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                                              tuple[bool, bool]]:
    """The grid's frequencies (cycles per window of ``duration``); the edges (the bands' low edges, high
    edges, then the search range's ends, all cut to that range); the log density relative to its peak
    (at least _FLOOR); its integral from the grid's start to each edge (exponential between grid points;
    0 before the grid, the whole beyond it); and, for the grid's start and end, whether an edge lies
    beyond it where the density is not negligible (_add_t_tail adds mass there)."""
    frequency = grid / duration
    bands = len(low)
    edges = np.empty(2 * bands + 2)
    edges[:bands], edges[bands:2 * bands] = low, high
    edges[-2], edges[-1] = search_low, search_high
    edges = np.minimum(np.maximum(edges, search_low), search_high)
    # Below _FLOOR there is nothing to count (and the exponentials stay finite).
    log_density = np.maximum(log_density - log_density.max(), _FLOOR)
    step = frequency[1] - frequency[0]
    cumulative = np.zeros(len(frequency))
    for i in range(len(frequency) - 1):
        # The integral over [0, step] of exp(log_density[i] + rise x / step).
        rise = log_density[i + 1] - log_density[i]
        shape = np.expm1(rise) / rise if abs(rise) > 1e-6 else 1.0 + 0.5 * rise
        cumulative[i + 1] = cumulative[i] + np.exp(log_density[i]) * step * shape
    # Within a grid step the cumulative is taken as linear: where a band's edge falls in a tail, that
    # gives the band around the peak a little less and "none" a little more than the exponential would.
    before = after = False
    for edge in edges:
        before |= edge < frequency[0]
        after |= edge > frequency[-1]
    tails = (before and log_density[0] >= _NEGLIGIBLE, after and log_density[-1] >= _NEGLIGIBLE)
    return frequency, edges, log_density, np.interp(edges, frequency, cumulative), tails


@kernel
def _band_log_masses(cdf: np.ndarray, edges: np.ndarray, bands: int) -> np.ndarray:
    """log of each band's share of the search range (``cdf`` at the ``edges``: the bands' low edges, high
    edges and the range's ends) and, last, of the rest's: what lies in no band (overlapping bands share)."""
    whole = max(cdf[-1] - cdf[-2], 1e-300)
    out = np.empty(bands + 1)
    for b in range(bands):
        out[b] = np.log(max(cdf[bands + b] - cdf[b], 1e-300) / whole)
    # The bands' union, merged in the order of their low edges.
    union = 0.0
    order = np.argsort(edges[:bands])
    start, end = order[0], bands + order[0]
    for b in order[1:]:
        if edges[b] <= edges[end]:
            if edges[bands + b] > edges[end]:
                end = bands + b
        else:
            union += cdf[end] - cdf[start]
            start, end = b, bands + b
    union += cdf[end] - cdf[start]
    out[bands] = np.log(max(1.0 - union / whole, 1e-300))
    return out
