"""Tone mode (Luxapose style): which lamp's frequency the stripes repeat at.

Row r samples the light at ``r * row_time``, so a square wave of frequency f
shows stripes of period ``1 / (f * row_time)`` rows. A zero-padded FFT of the
profile gives a start; a least-squares fit of the square wave as the rows see it
(averaged over the exposure, mixed with neighbouring rows, on a quadratic
envelope) gives the frequency and, from the curvature of its likelihood, its
uncertainty. The estimate is then weighed against every lamp's band (its
frequency +- the tolerance) and against "some other frequency", each band as
likely per hertz as any other.
"""
from __future__ import annotations

import numpy as np
from scipy.special import stdtr

from vlp_ros.beacon.profile import RowProfile, modulation
from vlp_ros.beacon.reading import (MIN_CONFIDENCE, UNMAPPED, UNMAPPED_WEIGHT, BeaconReading, log_prior,
                                    no_evidence, reading)

# Evidence (nats) by which a sinusoid must beat the envelope alone before its frequency counts.
MIN_TONE_EVIDENCE = 25.0
_PAD = 8
_MAX_ITERATIONS = 8
# The fit stops when a step with damping below _UNDAMPED moves the frequency by less than this
# share of its standard deviation.
_CONVERGED = 0.05
_UNDAMPED = 0.01
# An unknown exposure as a fraction of the tone's period: where the fit may start. Beyond half a
# period longer exposures look the same (kappa and kappa + 1 give one shape, 1 - kappa its mirror).
_START_KAPPAS = np.array([0.05, 0.15, 0.3, 0.45])
_MIN_EXPOSURE_ROWS = 0.05
# Rows on each side that a row's value may borrow from (demosaicing, blur after read-out).
_MIX_ROWS = 2
# How well an edge that no row straddles is placed, in rows (a uniform error over one row).
_EDGE_QUANTUM = 0.3
# Least share of the fundamental that the exposure lets through (|sinc(exposure x frequency)|):
# near a whole number of periods per exposure the stripes average away.
_MIN_TRANSMISSION = 0.3


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
    # A first look needs no envelope beyond the fit's own (quadratic) one.
    fit = _ToneFit(values / np.average(values, weights=w) - 1.0, w, row_time)
    search = (0.5 * centres.min(), min(1.5 * centres.max(), 0.9 * nyquist))
    start = fit.start(search[0] * fit.duration, search[1] * fit.duration)
    if start is None:
        return no_evidence(candidates, mapped, prior, 'no tone stands out of the noise')
    if start[0] < min_periods:
        return no_evidence(candidates, mapped, prior, f'fewer than {min_periods} stripe periods in view')
    # The envelope through the stripes leans on them; one over whole periods does not.
    fit.set_profile(modulation(profile, period=len(w) / start[0])[window])
    estimate = fit.square_wave(*start, None if exposure is None else exposure / row_time)
    if estimate is None:
        return no_evidence(candidates, mapped, prior, 'the stripes fit no square wave')
    cycles, sigma, dof, _ = estimate
    if exposure is not None and abs(np.sinc(exposure * cycles / fit.duration)) < _MIN_TRANSMISSION:
        # What is left of the stripes is shaped by the exposure more than by the frequency.
        return no_evidence(candidates, mapped, prior, 'the exposure spans about whole periods: stripes washed out')
    if exposure is None or exposure < row_time:
        # No row straddles most edges, or (exposure unknown) blur may pass for a longer exposure:
        # the edges are known to a row, and the period to a row over the window.
        sigma = np.hypot(sigma, _EDGE_QUANTUM * cycles / len(w))
    if sigma / fit.duration > search[1] - search[0]:
        return no_evidence(candidates, mapped, prior, 'the stripes do not pin the frequency down')
    log_mass = _log_band_masses(cycles / fit.duration, sigma / fit.duration, dof,
                                centres - tolerance_hz, centres + tolerance_hz, search)
    return reading(candidates, mapped, log_mass, prior, min_confidence)


class _ToneFit:
    """Weighted least squares of a profile by an envelope (1, u, u^2) plus a tone.

    Time runs in units of the window (tau in [0, 1)), frequency in cycles per window.
    """

    def __init__(self, z: np.ndarray, w: np.ndarray, row_time: float) -> None:
        self.duration = len(z) * row_time
        self.tau = np.arange(len(z)) / len(z)
        u = np.linspace(-1.0, 1.0, len(z))
        self.sqrt_w = np.sqrt(w)
        basis = np.stack([np.ones_like(u), u, u * u], axis=1) * self.sqrt_w[:, None]
        # Orthonormal envelope basis: projecting it out leaves what the tone must explain.
        self.envelope, _ = np.linalg.qr(basis)
        self.set_profile(z)

    def set_profile(self, z: np.ndarray) -> None:
        """Fit another profile over the same rows and weights."""
        self.y = self._residual(z * self.sqrt_w)
        self.null_rss = float(self.y @ self.y)

    def _residual(self, columns: np.ndarray) -> np.ndarray:
        return columns - self.envelope @ (self.envelope.T @ columns)

    def sinusoid(self, cycles: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Residual sum of squares and the cosine and sine amplitudes of the best sinusoid at each frequency."""
        phase = 2.0 * np.pi * np.outer(self.tau, cycles)
        c = self._residual(np.cos(phase) * self.sqrt_w[:, None])
        s = self._residual(np.sin(phase) * self.sqrt_w[:, None])
        cc, ss, cs = (c * c).sum(0), (s * s).sum(0), (c * s).sum(0)
        cy, sy = self.y @ c, self.y @ s
        det = np.maximum(cc * ss - cs * cs, 1e-300)
        a, b = (ss * cy - cs * sy) / det, (cc * sy - cs * cy) / det
        return self.null_rss - a * cy - b * sy, a, b

    def start(self, low: float, high: float) -> tuple[float, float] | None:
        """(cycles, phase) of the best sinusoid between ``low`` and ``high`` cycles per window.

        None unless it beats the envelope alone by MIN_TONE_EVIDENCE. The FFT's peak is
        only a start: the square-wave fit refines it.
        """
        n = len(self.y)
        size = _PAD * int(2 ** np.ceil(np.log2(n)))
        spectrum = np.abs(np.fft.rfft(self.y * self.sqrt_w, size)) ** 2
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
        rss, a, b = (float(v[0]) for v in self.sinusoid(np.array([cycles])))
        sigma2 = max(rss / max(n - 5, 1), 1e-15 * self.null_rss, 1e-300)
        if (self.null_rss - rss) / (2.0 * sigma2) < MIN_TONE_EVIDENCE:
            return None
        return cycles, float(np.arctan2(-a, b) / (2.0 * np.pi))

    def square_wave(self, cycles: float, phase: float,
                    exposure_rows: float | None) -> tuple[float, float, int, float] | None:
        """(cycles, standard deviation, residual degrees of freedom, exposure in rows) of the
        exposure-smeared square wave, fitted from a sinusoid's start.

        A row sees the square wave averaged over its exposure, exactly: the difference
        of the wave's integral, a triangle wave. Demosaicing, blur applied after
        read-out and the like mix each row with its neighbours, so the template is any
        symmetric mix of a row and the next ones (linear amplitudes). Levenberg-
        Marquardt over frequency, phase and (unless given) the exposure, with envelope
        and amplitudes solved exactly at every step (variable projection).
        """
        rows = len(self.y)
        free = exposure_rows is None
        # Without the exposure, start from several (as a share of the period, up to the half
        # period beyond which longer exposures only mirror shorter ones).
        kappas = _START_KAPPAS if free else np.array([exposure_rows * cycles / rows])
        starts = np.column_stack([np.full(len(kappas), cycles), phase + 0.5 * kappas, kappas * rows / cycles])
        params = starts[int(np.argmin(self._fit(starts)[0]))]
        rss, residual, jacobian = self._projected(params, free)
        damping = 1e-3
        dof = rows - 3 - (_MIX_ROWS + 1) - jacobian.shape[1]
        for _ in range(_MAX_ITERATIONS):
            normal = jacobian.T @ jacobian
            inverse = _inverse(normal + damping * np.diag(np.diag(normal) + 1e-300))
            step = inverse @ (jacobian.T @ residual)
            trial = params.copy()
            trial[:len(step)] += step
            if free:
                trial[2] = np.clip(trial[2], _MIN_EXPOSURE_ROWS, 0.5 * rows / trial[0])
            trial_rss, trial_residual, trial_jacobian = self._projected(trial, free)
            if trial_rss < rss:
                # Done once an (almost) undamped step moves the frequency by a small part of its
                # own uncertainty; a heavily damped step is small for want of trust, not of need.
                converged = (damping < _UNDAMPED
                             and step[0] ** 2 < _CONVERGED ** 2 * inverse[0, 0] * trial_rss / max(dof, 1))
                params, rss, residual, jacobian = trial, trial_rss, trial_residual, trial_jacobian
                damping = max(damping / 4.0, 1e-9)
                if converged:
                    break
            else:
                damping *= 8.0
        # Frequency's information with the other parameters free (they may be degenerate with each
        # other, e.g. when a period spans a whole number of rows).
        others = jacobian[:, 1:]
        leftover = jacobian[:, 0] - others @ np.linalg.lstsq(others, jacobian[:, 0], rcond=1e-10)[0]
        information = float(leftover @ leftover)
        variance = rss / max(dof, 1) / information if information > 0.0 else np.inf
        if not (np.isfinite(variance) and dof >= 1):
            return None
        return float(params[0]), float(np.sqrt(variance)), dof, float(params[2])

    def _fit(self, params: np.ndarray) -> tuple[np.ndarray, ...]:
        """Best envelope and row mix for each parameter set (S, 3) of (cycles, phase, exposure rows):
        residual sums of squares (S,), and the pieces the Jacobian needs."""
        cycles, phase, exposure = (params[:, i, None] for i in range(3))
        rows = len(self.y)
        kappa = exposure * cycles / rows
        # The light of rows -MIX .. rows + MIX - 1: a row's value borrows from its neighbours'.
        tau = np.arange(-_MIX_ROWS, rows + _MIX_ROWS) / rows
        theta = cycles * tau - phase
        mean = (_triangle(theta + kappa) - _triangle(theta)) / kappa
        templates = np.stack([_ring(mean, j, rows) for j in range(_MIX_ROWS + 1)], axis=2)
        templates = self._residual(templates * self.sqrt_w[:, None])
        gram = templates.transpose(0, 2, 1) @ templates
        inverse = np.array([_inverse(g + 1e-12 * np.eye(_MIX_ROWS + 1)) for g in gram])
        mix = (inverse @ (self.y @ templates)[..., None])[..., 0]
        residual = self.y - (templates @ mix[..., None])[..., 0]
        return (residual * residual).sum(axis=1), residual, templates, inverse, mix, theta, mean, kappa

    def _projected(self, params: np.ndarray, free_exposure: bool) -> tuple[float, np.ndarray, np.ndarray]:
        """Residual sum of squares, residual and (Kaufman) Jacobian over (cycles, phase[, exposure])
        with the best envelope and row mix."""
        rss, residual, templates, inverse, mix, theta, mean, kappa = (v[0] for v in self._fit(params[None]))
        cycles, _, exposure = params
        rows = len(self.y)
        tau = np.arange(-_MIX_ROWS, rows + _MIX_ROWS) / rows
        late = _square(theta + kappa)
        slope = (late - _square(theta)) / kappa
        by_kappa = (late - mean) / kappa
        light = [slope * tau + by_kappa * exposure / rows, -slope]
        if free_exposure:
            light.append(by_kappa * cycles / rows)
        # What each parameter does to the rows, through the same row mix as the light.
        derivatives = np.stack([sum(m * _ring(d, j, rows) for j, m in enumerate(mix)) for d in light], axis=1)
        jacobian = self._residual(derivatives * self.sqrt_w[:, None])
        jacobian -= templates @ (inverse @ (templates.T @ jacobian))
        return float(rss), residual, jacobian


def _ring(extended: np.ndarray, distance: int, rows: int) -> np.ndarray:
    """Sum over the neighbours ``distance`` rows away (the row itself for 0) of a quantity given on
    rows -MIX .. rows + MIX - 1 (last axis), for rows 0 .. rows - 1."""
    centre = _MIX_ROWS
    if distance == 0:
        return extended[..., centre:centre + rows]
    return (extended[..., centre - distance:centre - distance + rows]
            + extended[..., centre + distance:centre + distance + rows])


def _inverse(m: np.ndarray) -> np.ndarray:
    """Inverse of a 2x2 or 3x3 matrix by cofactors (numpy's general solvers cost more than the fit);
    the pseudo-inverse when it is singular."""
    if m.shape == (2, 2):
        (a, b), (c, d) = m.tolist()
        cofactors, det = [[d, -b], [-c, a]], a * d - b * c
    elif m.shape == (3, 3):
        (a, b, c), (d, e, f), (g, h, i) = m.tolist()
        cofactors = [[e * i - f * h, c * h - b * i, b * f - c * e],
                     [f * g - d * i, a * i - c * g, c * d - a * f],
                     [d * h - e * g, b * g - a * h, a * e - b * d]]
        det = a * cofactors[0][0] + b * cofactors[1][0] + c * cofactors[2][0]
    else:
        return np.linalg.pinv(m)
    scale = float(np.abs(m).max()) ** len(m)
    if not (np.isfinite(det) and abs(det) > 1e-12 * scale):
        return np.linalg.pinv(m)
    return np.array(cofactors) / det


def _triangle(x: np.ndarray) -> np.ndarray:
    """Integral of the +-1 square wave (period 1, +1 on [0, 0.5)) from 0 to x."""
    f = x - np.floor(x)
    return np.minimum(f, 1.0 - f)


def _square(x: np.ndarray) -> np.ndarray:
    return np.where(x - np.floor(x) < 0.5, 1.0, -1.0)


def _log_band_masses(frequency: float, scale: float, dof: int, low: np.ndarray, high: np.ndarray,
                     search: tuple[float, float]) -> np.ndarray:
    """log P(f in each band) and, last, log P(f in none), for f following Student's t (the noise
    level is itself estimated, from ``dof`` residual degrees of freedom) around ``frequency``, cut
    to the ``search`` range: a frequency outside it would have shown as another peak."""
    def mass(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        # From whichever tail is smaller, so that far bands keep their (tiny) mass.
        a, b = (np.clip(v, search[0], search[1]) for v in (a, b))
        za, zb = (a - frequency) / scale, (b - frequency) / scale
        return np.where(za > 0.0, stdtr(dof, -za) - stdtr(dof, -zb), stdtr(dof, zb) - stdtr(dof, za))

    total = float(mass(np.array([search[0]]), np.array([search[1]]))[0])
    band = np.maximum(mass(low, high), 1e-300) / max(total, 1e-300)
    outside = max(1.0 - float(band.sum()), 1e-300)
    return np.log(np.append(band, outside))
