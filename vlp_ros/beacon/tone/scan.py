"""
The frequency scan: the FFT's peak, a coarse scan of square waves around it, and the likelihood grid.

Each step narrows the one before: the zero-padded FFT finds the tone (``spectral_peak``), a scan of
frequencies, phases and (unknown) exposures around it the best square wave (``start``), and, after
the fit's Gauss-Newton step (``ToneFit.peak``), the likelihood of every frequency around that peak
(phase, envelope and amplitude at their best, the noise level marginalised) is evaluated on a grid
that is redone until it resolves the peak (``likelihood``).
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from vlp_ros.beacon.tone.model import Peak, rss, ToneFit
from vlp_ros.compiled import kernel

_PAD = 8
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


class Start(NamedTuple):
    """The best square wave of the coarse scan (``start``)."""

    # Cycles per window, phase (periods, at the window's centre), exposure (rows).
    cycles: float
    phase: float
    exposure_rows: float
    # The evidence (nats) by which it beats the envelope alone.
    evidence: float
    # The cycles tried, and the least residual sum of squares at each.
    tried: np.ndarray
    rss: np.ndarray


class Likelihood(NamedTuple):
    """Cycles per window on a grid and the log likelihood of each, relative to the best (``likelihood``)."""

    grid: np.ndarray
    log_density: np.ndarray
    # Whether a frequency beyond the grid fits nearly as well (the likelihood has other peaks).
    other_peaks: bool


class GridPass(NamedTuple):
    """One pass of the likelihood grid (``_grid_pass``)."""

    # At each grid point, the least residual sum of squares over the phases tried.
    rss: np.ndarray
    # The log likelihood (noise level marginalised, relative to the best) and the likelihood.
    log_density: np.ndarray
    density: np.ndarray
    # Their mean and spread (blurred by the edge quantum).
    mean: float
    sigma: float
    # The best grid point.
    best: int
    # Whether a best phase was an outer one (it may lie further out) where the likelihood matters.
    cornered: bool


def spectral_peak(fit: ToneFit, low: float, high: float) -> float | None:
    """
    Return the cycles per window of the strongest sinusoid between ``low`` and ``high`` cycles.

    That is the zero-padded FFT's peak; None if the range holds no frequency the FFT resolves.
    """
    n = len(fit.kept.y)
    size = _PAD * (1 << (n - 1).bit_length())
    return _spectral_peak(np.fft.rfft(fit.kept.weighted_y, size), n, size, low, high)


def start(fit: ToneFit, cycles: float, exposure_rows: float | None) -> Start:
    """
    Return the best square wave among a scan around ``cycles`` (the FFT's peak).

    The harmonics that few rows per period alias can pull the FFT's peak aside: the scan tries
    frequencies around it, phases over half a period (the other half only flips the sign) and, unknown,
    exposures; the best's phase is refined by a parabola through it and its neighbours.
    """
    return _scan(cycles, math.nan if exposure_rows is None else exposure_rows, fit.dof, *fit.model)


def likelihood(fit: ToneFit, peak: Peak, quantum: float, start: Start) -> Likelihood | None:
    """
    Return cycles per window on a grid around the ``peak``, and the log likelihood of each.

    Phase, envelope and amplitude are at their best, the noise level marginalised, the likelihood blurred
    by ``quantum`` cycles; ``other_peaks`` says whether a frequency beyond the grid that the ``start``
    scan or the grid's passes tried fits nearly as well. None if no grid resolves it.
    """
    found, grid = _likelihood_grid(peak.cycles, peak.phase, peak.slope, max(peak.scale, quantum), peak.phase_spread,
                                   peak.exposure_rows, quantum, start.tried, start.rss, fit.dof, *fit.model)
    return grid if found else None


@kernel
def _spectral_peak(spectrum: np.ndarray, n: int, size: int, low: float, high: float) -> float | None:
    """Return spectral_peak from the ``n`` rows' FFT zero-padded to ``size``."""
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


@kernel
def _scan(peak_cycles: float, given_exposure_rows: float, dof: int, rows: int, tau_around: np.ndarray, stride: int,
          products: np.ndarray, weights: np.ndarray, null_rss: float, power: float) -> Start:
    """
    Return start's scan: rss at every cycles around ``peak_cycles`` x exposure rows x phase of _PHASE_SCAN.

    The exposure rows are the given ones, or unknown (nan) _KAPPAS of the period. The best's phase is
    refined by a parabola through it and its neighbours.
    """
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
    tried = rss(flat_cycles, flat_phase, flat_exposure, rows, tau_around, stride, products, weights, null_rss, power)
    best = np.argmin(tried)
    row, k = best // phases, best % phases
    left, centre, right = tried[row * phases + (k - 1) % phases], tried[best], tried[row * phases + (k + 1) % phases]
    # The parabola through the best and its neighbours (the best is the least of the three).
    curvature = max(left + right - 2.0 * centre, 1e-300)
    place = 0.5 * (left - right) / curvature
    least = max(centre - 0.5 * curvature * place * place, 0.0)
    sigma2 = max(least / dof, 1e-15 * null_rss, 1e-300)
    least_by_cycles = np.empty(n)
    for i in range(n):
        least_by_cycles[i] = tried[i * m * phases:(i + 1) * m * phases].min()
    return Start(cycles[row // m], _PHASE_SCAN[k] + place / (2.0 * phases), exposure_rows[row % m],
                 (null_rss - least) / (2.0 * sigma2), cycles, least_by_cycles)


@kernel
def _likelihood_grid(cycles: float, phase: float, slope: float, scale: float, spread: float, exposure_rows: float,
                     quantum: float, start_tried: np.ndarray, start_rss: np.ndarray, dof: int, rows: int,
                     tau_around: np.ndarray, stride: int, products: np.ndarray, weights: np.ndarray, null_rss: float,
                     power: float) -> tuple[bool, Likelihood]:
    """
    Return whether a grid resolves the likelihood (_grid_pass's passes until one does), and the last grid.

    The last grid comes with its log likelihood (blurred by ``quantum``), and whether a frequency beyond
    it fits nearly as well: of the first scan or of an earlier pass (these with the grid's phases: a
    rugged plateau of peaks can leave the last grid on one of them, its t tails hiding the others).
    """
    n, step = len(_GRID), _GRID[1] - _GRID[0]
    centre = cycles
    tried, tried_rss = np.empty(_PASSES * n), np.empty(_PASSES * n)
    for done in range(_PASSES):
        grid = centre + scale * _GRID
        if grid[0] <= 0.0:
            return False, Likelihood(grid, grid, False)
        # Each frequency's best phase lies near the regression line through the peak.
        result = _grid_pass(grid, phase + slope * (grid - cycles), spread, exposure_rows, quantum, rows, tau_around,
                            stride, products, weights, null_rss, power)
        log_density, best, sigma = result.log_density, result.best, result.sigma
        tried[done * n:(done + 1) * n], tried_rss[done * n:(done + 1) * n] = grid, result.rss
        if result.cornered:
            # The best phase lies beyond the ones tried where the likelihood matters: try wider.
            spread *= 3.0
        elif not n // 4 <= best < n - n // 4:
            centre, scale = grid[best], 3.0 * scale
        elif sigma < _MIN_STEPS_PER_SIGMA * scale * step:
            # Narrower than the grid resolves: the spread of a sharp peak shows better in its curvature
            # (at most ten times narrower: between grid points it is not known yet).
            bend = log_density[best - 1] + log_density[best + 1] - 2.0 * log_density[best]
            sigma = min(sigma, scale * step / np.sqrt(max(-bend, 1e-12)))
            centre, scale = result.mean, max(sigma, 0.1 * scale)
        elif max(log_density[0], log_density[-1]) >= -_GRID_DROP and sigma * _MIN_SPAN > scale * _GRID[-1]:
            centre, scale = result.mean, sigma
        else:
            if quantum > 0.0:
                log_density = _blurred(grid, result.density, quantum)
            bound = result.rss.min() * np.exp(2.0 * _GRID_DROP / (dof + 1))
            other_peaks = False
            for i in range(len(start_tried)):
                other_peaks |= (start_tried[i] < grid[0] or start_tried[i] > grid[-1]) and start_rss[i] < bound
            for i in range((done + 1) * n):
                other_peaks |= (tried[i] < grid[0] or tried[i] > grid[-1]) and tried_rss[i] < bound
            return True, Likelihood(grid, log_density, other_peaks)
    return False, Likelihood(tried[:n], tried[:n], False)


@kernel
def _grid_pass(grid: np.ndarray, phase: np.ndarray, spread: float, exposure_rows: float, quantum: float, rows: int,
               tau_around: np.ndarray, stride: int, products: np.ndarray, weights: np.ndarray, null_rss: float,
               power: float) -> GridPass:
    """
    Return one pass of the likelihood grid.

    At each cycles of ``grid`` the phase is at its best among ``phase`` and ``spread`` x _PHASE_STEPS
    either side.
    """
    n, steps = len(grid), len(_PHASE_STEPS)
    cycles, tried = np.empty(n * steps), np.empty(n * steps)
    for i in range(n):
        for j in range(steps):
            cycles[i * steps + j] = grid[i]
            tried[i * steps + j] = phase[i] + spread * _PHASE_STEPS[j]
    all_rss = rss(cycles, tried, np.full(n * steps, exposure_rows), rows, tau_around, stride, products, weights,
                  null_rss, power)
    least, log_density = np.empty(n), np.empty(n)
    outer = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        best = 0
        for j in range(1, steps):
            if all_rss[i * steps + j] < all_rss[i * steps + best]:
                best = j
        least[i], outer[i] = all_rss[i * steps + best], best == 0 or best == steps - 1
        log_density[i] = -power * np.log(max(least[i], 1e-300))
    log_density -= log_density.max()
    density = np.exp(log_density)
    total = density.sum()
    mean = (density * grid).sum() / total
    # The spread after the blur by the edge quantum.
    sigma = math.hypot(math.sqrt((density * (grid - mean) ** 2).sum() / total), quantum)
    cornered = False
    for i in range(n):
        cornered |= outer[i] and log_density[i] > -_GRID_DROP
    return GridPass(least, log_density, density, mean, sigma, int(np.argmax(log_density)), cornered)


@kernel
def _blurred(grid: np.ndarray, density: np.ndarray, quantum: float) -> np.ndarray:
    """Return the log of ``density`` on ``grid`` blurred by a Gaussian of spread ``quantum`` (at least 1e-300)."""
    out = np.empty(len(grid))
    for i in range(len(grid)):
        total = 0.0
        for j in range(len(grid)):
            total += np.exp(-0.5 * ((grid[i] - grid[j]) / quantum) ** 2) * density[j]
        out[i] = np.log(max(total, 1e-300))
    return out
