"""Tone mode (Luxapose style): which lamp's frequency the stripes repeat at.

Row r samples the light at ``r * row_time``, so a square wave of frequency f
shows stripes of period ``1 / (f * row_time)`` rows. A zero-padded FFT of the
profile finds the tone; a least-squares fit of the square wave as the rows see
it (averaged over the exposure, on a quadratic envelope) finds the best
frequency; the likelihood of every frequency around it (phase, envelope and
amplitude at their best, noise level marginalised) then gives each lamp's band
(its frequency +- the tolerance) its probability, and "some other frequency" the
rest, each band as likely per hertz as any other.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import gammaln, stdtr

from vlp_ros.beacon.profile import RowProfile, modulation
from vlp_ros.beacon.reading import (MIN_CONFIDENCE, UNMAPPED, UNMAPPED_WEIGHT, BeaconReading, log_prior,
                                    no_evidence, reading)

# Evidence (nats) by which a sinusoid must beat the envelope alone before its frequency counts.
MIN_TONE_EVIDENCE = 25.0
_PAD = 8
# Envelope terms (1, u, u^2) and the tone's amplitude: the linear parameters of every fit.
_LINEAR = 4
# Longer windows are thinned to about this many rows (their frequency is pinned down many times over),
# keeping at least _MIN_ROWS_PER_PERIOD rows per stripe period.
_MAX_ROWS = 128
_MIN_ROWS_PER_PERIOD = 8.0
# Phases tried over half a period (the other half only flips the square wave's sign).
_PHASES = 16
_REFINE_STEPS = 6
# The likelihood is evaluated at this many scales (see _Peak.scale) around its peak ...
_GRID = np.linspace(-10.0, 10.0, 81)
# ... and must have fallen by this many nats at the grid's ends, or the grid widens.
_GRID_DROP = 12.0
_MAX_WIDENINGS = 3
# Log densities below this carry no mass worth counting (exp underflows).
_NEGLIGIBLE = -700.0
# An unknown exposure as a share of the tone's period: where the fit may start. Beyond half a period
# longer exposures look the same (kappa and kappa + 1 give one shape, 1 - kappa its mirror).
_START_KAPPAS = np.array([0.05, 0.15, 0.3, 0.45])
_MIN_EXPOSURE_ROWS = 0.05
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
    start = _spectral_peak(values / np.average(values, weights=w) - 1.0, w, search[0] * duration,
                           search[1] * duration)
    if start is None:
        return no_evidence(candidates, mapped, prior, 'no tone stands out of the noise')
    if start < min_periods:
        return no_evidence(candidates, mapped, prior, f'fewer than {min_periods} stripe periods in view')
    # The envelope through the stripes leans on them; one over whole periods does not.
    exposure_rows = None if exposure is None else exposure / row_time
    # Unknown, the exposure may be anything from a row on: thin as if it were one.
    fit = _ToneFit(modulation(profile, period=len(w) / start)[window], w, start, exposure_rows or 1.0)
    peak = fit.peak(start, exposure_rows)
    if peak is None:
        return no_evidence(candidates, mapped, prior, 'the stripes fit no square wave')
    if abs(np.sinc(peak.exposure_rows * peak.cycles / fit.rows)) < _MIN_TRANSMISSION:
        return no_evidence(candidates, mapped, prior, 'the exposure spans about whole periods: stripes washed out')
    # Unknown, the exposure may pass for blur across rows: edges are then known to a row, the period to a
    # row over the window.
    quantum = _EDGE_QUANTUM * peak.cycles / fit.rows if exposure is None else 0.0
    cycles, log_density = fit.likelihood(peak, quantum)
    log_mass = _log_band_masses(cycles / duration, log_density, peak.dof, centres - tolerance_hz,
                                centres + tolerance_hz, search)
    return reading(candidates, mapped, log_mass, prior, min_confidence)


def _spectral_peak(z: np.ndarray, w: np.ndarray, low: float, high: float) -> float | None:
    """Cycles per window of the strongest sinusoid between ``low`` and ``high`` (the zero-padded
    FFT's peak), with the envelope (1, u, u^2) projected out; None unless the sinusoid beats the
    envelope alone by MIN_TONE_EVIDENCE."""
    n = len(z)
    sqrt_w = np.sqrt(w)
    envelope = _envelope_basis(n, sqrt_w)
    y = z * sqrt_w
    y -= envelope @ (envelope.T @ y)
    size = _PAD * int(2 ** np.ceil(np.log2(n)))
    spectrum = np.abs(np.fft.rfft(y * sqrt_w, size)) ** 2
    bins = np.arange(len(spectrum)) * n / size
    inside = np.flatnonzero((bins >= low) & (bins <= high))
    if inside.size == 0:
        return None
    peak = int(inside[np.argmax(spectrum[inside])])
    cycles = bins[peak]
    if 0 < peak < len(spectrum) - 1:
        # Parabola through the log spectrum around the peak (a Gaussian-like lobe).
        left, centre, right = np.log(spectrum[peak - 1:peak + 2] + 1e-300)
        curvature = left - 2.0 * centre + right
        if curvature < 0.0:
            cycles += bins[1] * float(np.clip(0.5 * (left - right) / curvature, -0.5, 0.5))
    phase = 2.0 * np.pi * cycles * np.arange(n) / n
    columns = np.stack([np.cos(phase), np.sin(phase)]) * sqrt_w
    columns -= (columns @ envelope) @ envelope.T
    amplitudes = np.linalg.lstsq(columns.T, y, rcond=None)[0]
    null_rss = float(y @ y)
    rss = max(null_rss - float(amplitudes @ (columns @ y)), 0.0)
    sigma2 = max(rss / max(n - 5, 1), 1e-15 * null_rss, 1e-300)
    return cycles if (null_rss - rss) / (2.0 * sigma2) >= MIN_TONE_EVIDENCE else None


def _envelope_basis(rows: int, sqrt_w: np.ndarray) -> np.ndarray:
    """Orthonormal (weighted) basis of 1, u, u^2 over the window: projecting it out leaves what the
    tone must explain."""
    u = np.linspace(-1.0, 1.0, rows)
    basis, _ = np.linalg.qr(np.stack([np.ones_like(u), u, u * u], axis=1) * sqrt_w[:, None])
    return basis


@dataclass(frozen=True)
class _Peak:
    """The best square wave: cycles per window, phase at the window's centre (periods), exposure in
    rows, and the frequency's scale (cycles): its standard deviation, at least the width over which
    edges that fall between rows' exposures can move unseen."""

    cycles: float
    phase: float
    exposure_rows: float
    scale: float
    dof: int


class _ToneFit:
    """Weighted least squares of a profile by an envelope (1, u, u^2) plus an exposure-smeared square wave.

    Time runs in units of the window from its centre (tau in [-0.5, 0.5)), frequency in cycles per
    window. Long windows are thinned to every k-th row.
    """

    def __init__(self, z: np.ndarray, w: np.ndarray, cycles: float, exposure_rows: float) -> None:
        self.rows = len(z)
        # Thinned rows must still cover the time axis with their exposures: a gap would hide edges.
        stride = max(1, min(int(np.ceil(self.rows / _MAX_ROWS)), int(self.rows / cycles / _MIN_ROWS_PER_PERIOD),
                            int(exposure_rows)))
        kept = np.arange(0, self.rows, stride)
        self.tau = (kept - 0.5 * (self.rows - 1)) / self.rows
        self.sqrt_w = np.sqrt(w[kept])
        self.envelope = _envelope_basis(self.rows, np.sqrt(w))[kept]
        self.envelope, _ = np.linalg.qr(self.envelope)
        self.y = self._residual(z[kept] * self.sqrt_w)
        self.null_rss = float(self.y @ self.y)
        self.dof = len(kept) - _LINEAR - 2

    def _residual(self, columns: np.ndarray) -> np.ndarray:
        """``columns`` (..., rows) less their envelope part."""
        return columns - (columns @ self.envelope) @ self.envelope.T

    def _wave(self, cycles: np.ndarray, phase: np.ndarray, exposure_rows: np.ndarray | float):
        """Each row's mean of the +-1 square wave over its exposure (exact: a difference of the wave's
        integral, a triangle wave), weighted, for every (cycles, phase) pair; with the square wave at
        the exposure's start and end, which the derivatives need."""
        kappa = np.asarray(cycles * np.asarray(exposure_rows) / self.rows)[..., None]
        theta = np.asarray(cycles)[..., None] * self.tau - np.asarray(phase)[..., None]
        late = theta + kappa
        mean = (_triangle(late) - _triangle(theta)) / kappa
        return mean, _square(theta), _square(late), kappa

    def _rss(self, mean: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Residual sum of squares with the best envelope and amplitude; the projected template, its
        amplitude and squared norm."""
        template = self._residual(mean * self.sqrt_w)
        norm = np.maximum((template * template).sum(-1), 1e-300)
        projection = template @ self.y
        return self.null_rss - projection * projection / norm, template, projection / norm, norm

    def peak(self, cycles: float, exposure_rows: float | None) -> _Peak | None:
        """The best square wave near ``cycles``: a scan of phases (and, unknown, exposures), then
        Gauss-Newton over frequency and phase (and exposure), envelope and amplitude solved exactly at
        every step (variable projection)."""
        free = exposure_rows is None
        exposures = _START_KAPPAS * self.rows / cycles if free else np.array([exposure_rows])
        phases = np.arange(_PHASES) / (2.0 * _PHASES)
        grid_phase, grid_exposure = (v.ravel() for v in np.meshgrid(phases, exposures))
        rss = self._rss(self._wave(np.full(len(grid_phase), cycles), grid_phase, grid_exposure)[0])[0]
        best = int(np.argmin(rss))
        params = np.array([cycles, grid_phase[best], grid_exposure[best]])
        rss = float(rss[best])
        for _ in range(_REFINE_STEPS):
            jacobian, residual = self._jacobian(params, free)
            normal = jacobian @ jacobian.T
            step = np.linalg.lstsq(normal, jacobian @ residual, rcond=1e-12)[0]
            for _ in range(4):
                trial = params.copy()
                trial[:len(step)] += step
                if free:
                    trial[2] = np.clip(trial[2], _MIN_EXPOSURE_ROWS, 0.5 * self.rows / trial[0])
                trial_rss = float(self._rss(self._wave(trial[0], trial[1], trial[2])[0])[0])
                if trial_rss <= rss:
                    break
                step *= 0.25
            else:
                break
            params, rss = trial, trial_rss
        jacobian, _ = self._jacobian(params, free)
        # Frequency's information with the other parameters free.
        others = jacobian[1:]
        leftover = jacobian[0] - np.linalg.lstsq(others.T, jacobian[0], rcond=1e-10)[0] @ others
        information = float(leftover @ leftover)
        # Edges in the gaps between rows' exposures move freely by up to the gap: the period by about
        # a gap over the window (when no edge falls inside an exposure, that is all there is).
        gap = max(1.0 - params[2], 0.0) * params[0] / self.rows
        sigma = np.sqrt(rss / max(self.dof, 1) / information) if information > 0.0 else 0.0 if gap > 0.0 else np.inf
        if not (np.isfinite(sigma) and self.dof >= 1):
            return None
        return _Peak(float(params[0]), float(params[1]) % 0.5, float(params[2]), float(np.hypot(sigma, 0.5 * gap)),
                     self.dof)

    def _jacobian(self, params: np.ndarray, free_exposure: bool) -> tuple[np.ndarray, np.ndarray]:
        """Rows' sensitivities to (cycles, phase[, exposure rows]) with envelope and amplitude at their
        best (Kaufman's variable projection Jacobian), and the residual."""
        cycles, phase, exposure = params
        mean, early, late, kappa = self._wave(cycles, phase, exposure)
        _, template, amplitude, norm = self._rss(mean)
        slope = (late - early) / kappa
        by_kappa = (late - mean) / kappa
        light = [slope * self.tau + by_kappa * exposure / self.rows, -slope]
        if free_exposure:
            light.append(by_kappa * cycles / self.rows)
        jacobian = amplitude * self._residual(np.stack(light) * self.sqrt_w)
        jacobian -= np.outer(jacobian @ template / norm, template)
        return jacobian, self.y - amplitude * template

    def likelihood(self, peak: _Peak, quantum: float) -> tuple[np.ndarray, np.ndarray]:
        """Cycles per window on a grid around the peak and the log likelihood of each (phase, envelope
        and amplitude at their best, the noise level marginalised), blurred by ``quantum`` (cycles)."""
        scale = np.hypot(peak.scale, quantum)
        for _ in range(_MAX_WIDENINGS + 1):
            cycles = peak.cycles + scale * _GRID
            rss = self._profile_rss(cycles, peak)
            log_density = -0.5 * (self.dof + 1) * np.log(np.maximum(rss, 1e-300))
            log_density -= log_density.max()
            if max(log_density[0], log_density[-1]) < -_GRID_DROP:
                break
            scale *= 3.0
        if quantum > 0.0:
            step = cycles[1] - cycles[0]
            kernel = np.exp(-0.5 * (np.subtract.outer(cycles, cycles) / quantum) ** 2) * step / (
                np.sqrt(2.0 * np.pi) * quantum)
            log_density = np.log(np.maximum(kernel @ np.exp(log_density), 1e-300))
        return cycles, log_density

    def _profile_rss(self, cycles: np.ndarray, peak: _Peak) -> np.ndarray:
        """Residual sum of squares at each of ``cycles`` with the phase at its best: a Gauss-Newton step
        from the peak's (the phase at the window's centre hardly moves with the frequency)."""
        phase = np.full(len(cycles), peak.phase)
        mean, early, late, kappa = self._wave(cycles, phase, peak.exposure_rows)
        rss, template, amplitude, norm = self._rss(mean)
        derivative = self._residual(-(late - early) / kappa * self.sqrt_w)
        cross = (derivative * template).sum(-1)
        curvature = amplitude * ((derivative * derivative).sum(-1) - cross * cross / norm)
        step = (derivative @ self.y - amplitude * cross) / np.where(np.abs(curvature) > 0.0, curvature, np.inf)
        stepped = self._rss(self._wave(cycles, phase + np.clip(step, -0.1, 0.1), peak.exposure_rows)[0])[0]
        return np.minimum(rss, stepped)


def _triangle(x: np.ndarray) -> np.ndarray:
    """Integral of the +-1 square wave (period 1, +1 on [0, 0.5)) from 0 to x."""
    f = x - np.floor(x)
    return np.minimum(f, 1.0 - f)


def _square(x: np.ndarray) -> np.ndarray:
    return np.where(x - np.floor(x) < 0.5, 1.0, -1.0)


def _log_band_masses(frequency: np.ndarray, log_density: np.ndarray, dof: int, low: np.ndarray, high: np.ndarray,
                     search: tuple[float, float]) -> np.ndarray:
    """log P(f in each band) and, last, log P(f in none), for f's density given on a grid of
    ``frequency`` (piecewise linear between), continued beyond it by the Student's t (``dof``
    degrees of freedom, centred on the grid's peak) whose density meets the grid's ends, all cut to
    the ``search`` range: a frequency outside it would have shown as another peak."""
    log_density = log_density - log_density.max()
    density = np.exp(log_density)
    centre = frequency[np.argmax(density)]
    cumulative = np.concatenate([[0.0], np.cumsum(0.5 * (density[1:] + density[:-1]) * np.diff(frequency))])
    lower, upper = (_t_tail(frequency[i], centre, log_density[i], dof) for i in (0, -1))

    def mass(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        a, b = (np.clip(v, search[0], search[1]) for v in (a, b))
        inside = np.interp(b, frequency, cumulative) - np.interp(a, frequency, cumulative)
        return (inside + lower(np.minimum(a, frequency[0]), np.minimum(b, frequency[0]))
                + upper(np.maximum(a, frequency[-1]), np.maximum(b, frequency[-1])))

    total = float(mass(np.array([search[0]]), np.array([search[1]]))[0])
    band = np.maximum(mass(low, high), 1e-300) / max(total, 1e-300)
    outside = max(1.0 - float(band.sum()), 1e-300)
    return np.log(np.append(band, outside))


def _t_tail(end: float, centre: float, log_density: float, dof: int):
    """Mass between a and b (beyond the grid's ``end``) of the Student's t density around ``centre``,
    1 there, whose scale makes it exp(``log_density``) at ``end``."""
    if log_density < _NEGLIGIBLE:
        return lambda a, b: np.zeros(np.shape(a))
    z = np.sqrt(dof * max(np.expm1(-2.0 * log_density / (dof + 1)), 1e-12))
    scale = max(abs(end - centre), 1e-300) / z
    # The t density is gamma((dof + 1) / 2) / (sqrt(dof pi) gamma(dof / 2)) at its centre.
    peak = np.exp(gammaln(0.5 * (dof + 1)) - gammaln(0.5 * dof)) / np.sqrt(dof * np.pi)

    def mass(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.abs(stdtr(dof, (b - centre) / scale) - stdtr(dof, (a - centre) / scale)) * scale / peak
    return mass
