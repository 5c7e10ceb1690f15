"""Tone mode (Luxapose style): which lamp's frequency the stripes repeat at.

Row r samples the light at ``r * row_time``, so a square wave of frequency f
shows stripes of period ``1 / (f * row_time)`` rows. A zero-padded FFT of the
profile finds the tone; a least-squares fit of the square wave as the rows see
it (averaged over the exposure, on a quadratic envelope) finds the best
frequency; the likelihood of every frequency around it (phase, envelope and
amplitude at their best, the noise level marginalised) then gives each lamp's
band (its frequency +- the tolerance) its probability, and "some other
frequency" the rest, each band as likely per hertz as any other.
"""
from __future__ import annotations

import numpy as np
from scipy.special import gammaln, stdtr

from vlp_ros.beacon.profile import RowProfile
from vlp_ros.beacon.reading import (MIN_CONFIDENCE, UNMAPPED, UNMAPPED_WEIGHT, BeaconReading, log_prior,
                                    no_evidence, reading)

# Evidence (nats) by which a sinusoid must beat the envelope alone before its frequency counts.
MIN_TONE_EVIDENCE = 25.0
_PAD = 8
# Envelope terms (1, u, u^2) and the tone's amplitude (linear), frequency and phase (not).
_PARAMETERS = 6
# Longer windows are thinned to about this many rows (their frequency is pinned down many times over),
# keeping at least _MIN_ROWS_PER_PERIOD rows per stripe period.
_MAX_ROWS = 128
_MIN_ROWS_PER_PERIOD = 8.0
# Phases tried around the sinusoid's (periods): the square wave's edges are sharper than its fundamental.
_PHASE_OFFSETS = np.arange(-3, 4) / 48.0
# Unknown, the exposure is tried at these shares of the tone's period. Beyond half a period longer
# exposures look the same (kappa and kappa + 1 give one shape, 1 - kappa its mirror).
_KAPPAS = np.array([0.03, 0.08, 0.15, 0.22, 0.3, 0.38, 0.46])
_MIN_EXPOSURE_ROWS = 0.05
_GAUSS_NEWTON_STEPS = 4
# The likelihood is evaluated on a grid of +-10 scales around its peak, the scale being the spread of
# the likelihood (remeasured on the grid, which is redone if needed) ...
_GRID = np.linspace(-10.0, 10.0, 61)
_PASSES = 4
# ... and must hold at least this many grid steps per standard deviation ...
_MIN_STEPS_PER_SIGMA = 2.0
# ... and fall by this many nats towards the grid's ends, or span this many standard deviations each
# side (beyond, a Student's t takes over).
_GRID_DROP = 12.0
_MIN_SPAN = 7.0
# Log densities below this carry no mass worth counting (exp underflows).
_NEGLIGIBLE = -700.0
# How well an edge is placed when the exposure is unknown, in rows (blur may pass for a longer exposure).
_EDGE_QUANTUM = 0.3
# Least share of the fundamental that the exposure lets through (|sinc(exposure x frequency)|): what is
# left of stripes averaged over about a whole period is shaped by the exact exposure more than by the
# frequency.
_MIN_TRANSMISSION = 0.1


def decode_tone(profile: RowProfile, row_time: float, frequencies: dict[int, float], tolerance_hz: float, *,
                unmapped_weight: float = UNMAPPED_WEIGHT, min_confidence: float = MIN_CONFIDENCE,
                min_periods: float = 2.8, exposure: float | None = None) -> BeaconReading:
    """The lamp (by ID) whose ``frequencies`` entry (Hz) matches the stripes within ``tolerance_hz``.

    A frequency outside every band counts for the candidate ``UNMAPPED`` (prior
    ``unmapped_weight`` per hertz relative to the bands). Fewer than
    ``min_periods`` stripe periods in view give no evidence: the envelope cannot be
    told from the stripes over less. ``exposure`` (s), when known, is fitted with
    exactly; unknown, it cannot be told from blur across rows, and edges are then
    only trusted to the nearest row (a much wider frequency uncertainty).
    """
    if not row_time > 0.0:
        raise ValueError(f'row_time must be positive, got {row_time}')
    if not tolerance_hz > 0.0:
        raise ValueError(f'tolerance_hz must be positive, got {tolerance_hz}')
    if exposure is not None and not exposure > 0.0:
        raise ValueError(f'exposure must be positive, got {exposure}')
    if not frequencies:
        raise ValueError('tone decoding needs at least one lamp frequency')
    ids = np.array(sorted(frequencies), dtype=int)
    if np.any(ids < 0):
        raise ValueError(f'lamp ids must not be negative, got {ids[ids < 0].tolist()}')
    centres = np.array([frequencies[i] for i in ids], dtype=float)
    nyquist = 0.5 / row_time
    if not (np.all(centres > 0.0) and np.all(centres + tolerance_hz < nyquist)):
        raise ValueError(f'lamp frequencies must lie in (0, {nyquist - tolerance_hz:.0f}) Hz '
                         f'(row Nyquist minus tolerance), got {centres.tolist()}')
    candidates = np.append(ids, UNMAPPED)
    mapped = np.append(np.ones(len(ids), dtype=bool), False)
    prior = log_prior(mapped, unmapped_weight)

    w = np.asarray(profile.weights, dtype=float)
    used = np.flatnonzero(w > 0)
    if used.size < 8:
        return no_evidence(candidates, mapped, prior, 'too few rows')
    window = slice(used[0], used[-1] + 1)
    w = w[window]
    values = np.asarray(profile.values, dtype=float)[window]
    duration = len(w) * row_time
    search = (0.5 * centres.min(), min(1.5 * centres.max(), 0.9 * nyquist))
    # The envelope (vignetting, the disc's falloff) is fitted with the stripes, as a quadratic.
    fit = _ToneFit(values / (values @ w / w.sum()) - 1.0, w)
    start = fit.spectral_peak(search[0] * duration, search[1] * duration)
    if start is None:
        return no_evidence(candidates, mapped, prior, 'no tone stands out of the noise')
    cycles, phase = start
    if cycles < min_periods:
        return no_evidence(candidates, mapped, prior, f'fewer than {min_periods} stripe periods in view')
    exposure_rows = None if exposure is None else exposure / row_time
    # Unknown, the exposure may be anything from a row on: thin as if it were one.
    fit.thin(cycles, exposure_rows or 1.0)
    if fit.dof < 1:
        return no_evidence(candidates, mapped, prior, 'too few rows')
    peak = fit.peak(cycles, phase, exposure_rows)
    if peak is None:
        return no_evidence(candidates, mapped, prior, 'the stripes fit no square wave')
    cycles, phase, exposure_rows, scale = peak
    if abs(np.sinc(exposure_rows * cycles / fit.rows)) < _MIN_TRANSMISSION:
        return no_evidence(candidates, mapped, prior, 'the exposure spans about whole periods: stripes washed out')
    # Unknown, the exposure may pass for blur across rows: edges are then known to a row, the period to a
    # row over the window.
    quantum = _EDGE_QUANTUM * cycles / fit.rows if exposure is None else 0.0
    likelihood = fit.likelihood(cycles, phase, exposure_rows, scale, quantum)
    if likelihood is None:
        return no_evidence(candidates, mapped, prior, 'the stripes do not pin the frequency down')
    grid, log_density = likelihood
    log_mass = _log_band_masses(grid / duration, log_density, fit.dof, centres - tolerance_hz,
                                centres + tolerance_hz, search)
    return reading(candidates, mapped, log_mass, prior, min_confidence)


class _ToneFit:
    """Weighted least squares of a profile by an envelope (1, u, u^2) plus an exposure-smeared square wave.

    Time runs in units of the window from its centre (tau in [-0.5, 0.5)), frequency in cycles per
    window, phase in periods at the window's centre (where it hardly moves with the frequency).
    """

    def __init__(self, z: np.ndarray, w: np.ndarray) -> None:
        self.rows = len(z)
        self.z, self.w = z, w
        self._use(np.arange(self.rows))

    def _use(self, kept: np.ndarray) -> None:
        self.tau = (kept - 0.5 * (self.rows - 1)) / self.rows
        self.sqrt_w = np.sqrt(self.w[kept])
        u = 2.0 * self.tau
        # Orthonormal (weighted) envelope basis: projecting it out leaves what the tone must explain.
        self.envelope, _ = np.linalg.qr(np.stack([np.ones_like(u), u, u * u], axis=1) * self.sqrt_w[:, None])
        self.y = self._residual(self.z[kept] * self.sqrt_w)
        self.null_rss = float(self.y @ self.y)
        self.dof = len(kept) - _PARAMETERS

    def thin(self, cycles: float, exposure_rows: float) -> None:
        """Keep every k-th row of a long window, while the rows' exposures still cover the time axis (a
        gap would hide edges)."""
        stride = min(int(np.ceil(self.rows / _MAX_ROWS)), int(self.rows / cycles / _MIN_ROWS_PER_PERIOD),
                     int(exposure_rows))
        if stride > 1:
            self._use(np.arange(0, self.rows, stride))

    def _residual(self, columns: np.ndarray) -> np.ndarray:
        """``columns`` (..., rows) less their envelope part."""
        return columns - (columns @ self.envelope) @ self.envelope.T

    def spectral_peak(self, low: float, high: float) -> tuple[float, float] | None:
        """(cycles per window, phase) of the strongest sinusoid between ``low`` and ``high`` cycles (the
        zero-padded FFT's peak); None unless it beats the envelope alone by MIN_TONE_EVIDENCE. The
        phase is that of a square wave whose fundamental it is, seen over a vanishing exposure."""
        n = len(self.y)
        size = _PAD * int(2 ** np.ceil(np.log2(n)))
        spectrum = np.abs(np.fft.rfft(self.y * self.sqrt_w, size)) ** 2
        first, last = int(np.ceil(low * size / n)), int(high * size / n)
        if last < first:
            return None
        peak = first + int(np.argmax(spectrum[first:last + 1]))
        cycles = peak * n / size
        if 0 < peak < len(spectrum) - 1:
            # Parabola through the log spectrum around the peak (a Gaussian-like lobe).
            left, centre, right = np.log(spectrum[peak - 1:peak + 2] + 1e-300)
            curvature = left - 2.0 * centre + right
            if curvature < 0.0:
                cycles += n / size * float(np.clip(0.5 * (left - right) / curvature, -0.5, 0.5))
        angle = 2.0 * np.pi * cycles * self.tau
        columns = self._residual(np.stack([np.cos(angle), np.sin(angle)]) * self.sqrt_w)
        gram = columns @ columns.T
        projection = columns @ self.y
        amplitudes = np.linalg.solve(gram + 1e-12 * np.trace(gram) * np.eye(2), projection)
        explained = float(amplitudes @ projection)
        sigma2 = max((self.null_rss - explained) / max(n - 5, 1), 1e-15 * self.null_rss, 1e-300)
        if explained / (2.0 * sigma2) < MIN_TONE_EVIDENCE:
            return None
        # a cos + b sin = R sin(angle + psi); the square wave's fundamental is sin(2 pi (theta)), theta =
        # cycles tau - phase.
        return cycles, float(-np.arctan2(amplitudes[0], amplitudes[1]) / (2.0 * np.pi))

    def _rss(self, cycles: np.ndarray, phase: np.ndarray, exposure_rows: np.ndarray | float,
             with_step: bool = False) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """Residual sum of squares of each (cycles, phase) with the best envelope and amplitude, and (if
        ``with_step``) the Gauss-Newton step of its phase.

        A row sees the +-1 square wave's mean over its exposure, exactly: a difference of the wave's
        integral, a triangle wave (0.5 - |frac(x) - 0.5|).
        """
        kappa = (cycles * exposure_rows / self.rows)[:, None]
        theta = cycles[:, None] * self.tau - phase[:, None]
        early = theta - np.floor(theta) - 0.5
        late = theta + kappa
        late -= np.floor(late) + 0.5
        raw = (np.abs(early) - np.abs(late)) * (self.sqrt_w / kappa)
        # Products with the envelope-free template from the raw one: y has no envelope part.
        along = raw @ self.envelope
        norm = np.maximum(np.einsum('ij,ij->i', raw, raw) - np.einsum('ij,ij->i', along, along), 1e-300)
        projection = raw @ self.y
        amplitude = projection / norm
        rss = self.null_rss - projection * amplitude
        if not with_step:
            return rss
        # The template's derivative by phase: the square wave's values at the exposure's ends.
        derivative = (np.sign(late) - np.sign(early)) * (self.sqrt_w / kappa)
        derivative_along = derivative @ self.envelope
        cross = np.einsum('ij,ij->i', derivative, raw) - np.einsum('ij,ij->i', derivative_along, along)
        curvature = amplitude * (np.einsum('ij,ij->i', derivative, derivative)
                                 - np.einsum('ij,ij->i', derivative_along, derivative_along) - cross * cross / norm)
        step = (derivative @ self.y - amplitude * cross) / np.where(curvature != 0.0, curvature, np.inf)
        return rss, np.clip(step, -0.05, 0.05)

    def _linearised(self, params: np.ndarray, free_exposure: bool) -> tuple[float, np.ndarray, np.ndarray]:
        """Residual sum of squares at (cycles, phase, exposure rows), the rows' sensitivities to cycles,
        phase (and exposure) with envelope and amplitude at their best (Kaufman's variable projection
        Jacobian) and the residual."""
        cycles, phase, exposure = params
        kappa = cycles * exposure / self.rows
        theta = cycles * self.tau - phase
        early = theta - np.floor(theta)
        late = theta + kappa
        late -= np.floor(late)
        mean = (np.minimum(late, 1.0 - late) - np.minimum(early, 1.0 - early)) / kappa
        square = np.sign(0.5 - late)
        slope = (square - np.sign(0.5 - early)) / kappa
        by_kappa = (square - mean) / kappa
        light = [slope * self.tau + by_kappa * (exposure / self.rows), -slope]
        if free_exposure:
            light.append(by_kappa * (cycles / self.rows))
        template, *derivatives = self._residual(np.stack([mean, *light]) * self.sqrt_w)
        norm = max(float(template @ template), 1e-300)
        amplitude = float(template @ self.y) / norm
        residual = self.y - amplitude * template
        jacobian = amplitude * np.stack(derivatives)
        jacobian -= np.outer(jacobian @ template / norm, template)
        return float(residual @ residual), jacobian, residual

    def peak(self, cycles: float, phase: float,
             exposure_rows: float | None) -> tuple[float, float, float, float] | None:
        """(cycles, phase, exposure rows, scale in cycles) of the best square wave near the sinusoid
        (``cycles``, ``phase``): phases (and, unknown, exposures) tried around it, then Gauss-Newton. The
        scale is the frequency's standard deviation, and at least the width over which edges in the gaps
        between the rows' exposures move unseen."""
        free = exposure_rows is None
        exposures = _KAPPAS * self.rows / cycles if free else np.array([exposure_rows])
        # The fundamental of a wave averaged over an exposure kappa lags by kappa / 2.
        offsets, tried = (v.ravel() for v in np.meshgrid(_PHASE_OFFSETS, exposures))
        phases = phase + 0.5 * tried * cycles / self.rows + offsets
        best = int(np.argmin(self._rss(np.full(len(phases), cycles), phases, tried)))
        params = np.array([cycles, phases[best], tried[best]])
        rss, jacobian, residual = self._linearised(params, free)
        for _ in range(_GAUSS_NEWTON_STEPS):
            normal = jacobian @ jacobian.T
            step = np.linalg.lstsq(normal, jacobian @ residual, rcond=1e-12)[0]
            for _ in range(3):
                trial = params.copy()
                trial[:len(step)] += step
                if free:
                    trial[2] = np.clip(trial[2], _MIN_EXPOSURE_ROWS, 0.5 * self.rows / trial[0])
                trial_fit = self._linearised(trial, free)
                if trial_fit[0] <= rss:
                    break
                step *= 0.25
            else:
                break
            params, (rss, jacobian, residual) = trial, trial_fit
            if step[0] ** 2 * (normal[0, 0] + 1e-300) < 1e-4 * rss / self.dof:
                break
        # Frequency's information with the other parameters free.
        others = jacobian[1:]
        leftover = jacobian[0] - np.linalg.lstsq(others.T, jacobian[0], rcond=1e-10)[0] @ others
        information = float(leftover @ leftover)
        gap = max(1.0 - params[2], 0.0) * params[0] / self.rows
        sigma = np.sqrt(rss / self.dof / information) if information > 0.0 else 0.0 if gap > 0.0 else np.inf
        if not np.isfinite(sigma):
            return None
        return float(params[0]), float(params[1]), float(params[2]), float(np.hypot(sigma, 0.5 * gap))

    def likelihood(self, cycles: float, phase: float, exposure_rows: float, scale: float,
                   quantum: float) -> tuple[np.ndarray, np.ndarray] | None:
        """Cycles per window on a grid around ``cycles`` and the log likelihood of each (phase, envelope
        and amplitude at their best, the noise level marginalised), blurred by ``quantum`` (cycles);
        None if no grid resolves it. ``scale`` is a first guess of its spread."""
        centre, scale = cycles, max(scale, quantum)
        for _ in range(_PASSES):
            grid = centre + scale * _GRID
            if grid[0] <= 0.0:
                return None
            # The phase at its best: a Gauss-Newton step, kept where it helps.
            rss, step = self._rss(grid, np.full(len(grid), phase), exposure_rows, with_step=True)
            stepped = self._rss(grid, phase + step, exposure_rows)
            step = np.where(stepped < rss, step, 0.0)
            rss = np.minimum(rss, stepped)
            log_density = -0.5 * (self.dof + 1) * np.log(np.maximum(rss, 1e-300))
            log_density -= log_density.max()
            density = np.exp(log_density)
            mean = float(density @ grid / density.sum())
            # The spread after the blur by the edge quantum.
            sigma = float(np.hypot(np.sqrt(density @ (grid - mean) ** 2 / density.sum()), quantum))
            best = int(np.argmax(log_density))
            step_size = scale * (_GRID[1] - _GRID[0])
            if not len(grid) // 4 <= best < len(grid) - len(grid) // 4:
                centre, scale = grid[best], 3.0 * scale
            elif sigma < _MIN_STEPS_PER_SIGMA * step_size:
                # Narrower than the grid resolves (at most ten times: the spread of a sharp peak between
                # grid points is not known yet).
                centre, scale = mean, max(sigma, 0.1 * scale)
            elif max(log_density[0], log_density[-1]) >= -_GRID_DROP and sigma * _MIN_SPAN > scale * _GRID[-1]:
                centre, scale = mean, sigma
            else:
                break
            phase += float(step[best])
        else:
            return None
        if quantum > 0.0:
            kernel = np.exp(-0.5 * (np.subtract.outer(grid, grid) / quantum) ** 2)
            log_density = np.log(np.maximum(kernel @ density, 1e-300))
        return grid, log_density


def _log_band_masses(frequency: np.ndarray, log_density: np.ndarray, dof: int, low: np.ndarray, high: np.ndarray,
                     search: tuple[float, float]) -> np.ndarray:
    """log P(f in each band) and, last, log P(f in none), for f's density given on a grid of
    ``frequency`` (piecewise linear between), continued beyond it by the Student's t (``dof``
    degrees of freedom, centred on the grid's peak) whose density meets the grid's ends, all cut to
    the ``search`` range: a frequency outside it would have shown as another peak."""
    log_density = log_density - log_density.max()
    density = np.exp(log_density)
    cumulative = np.concatenate([[0.0], np.cumsum(0.5 * (density[1:] + density[:-1]) * np.diff(frequency))])
    edges = np.clip(np.concatenate([low, high, search]), search[0], search[1])
    cdf = np.interp(edges, frequency, cumulative)
    centre = frequency[np.argmax(density)]
    # The t density is gamma((dof + 1) / 2) / (sqrt(dof pi) gamma(dof / 2)) at its centre.
    peak = np.exp(gammaln(0.5 * (dof + 1)) - gammaln(0.5 * dof)) / np.sqrt(dof * np.pi)
    for end, beyond in ((0, edges < frequency[0]), (-1, edges > frequency[-1])):
        if log_density[end] < _NEGLIGIBLE or not beyond.any():
            continue
        # The t's scale that makes it exp(log_density[end]) at the grid's end, 1 at the centre.
        z = np.sqrt(dof * max(np.expm1(-2.0 * log_density[end] / (dof + 1)), 1e-12))
        scale = max(abs(frequency[end] - centre), 1e-300) / z
        tail = (stdtr(dof, (edges[beyond] - centre) / scale) - stdtr(dof, (frequency[end] - centre) / scale))
        cdf[beyond] += tail * scale / peak
    masses = cdf[len(low):-2] - cdf[:len(low)]
    band = np.maximum(masses, 1e-300) / max(cdf[-1] - cdf[-2], 1e-300)
    outside = max(1.0 - float(band.sum()), 1e-300)
    return np.log(np.append(band, outside))
