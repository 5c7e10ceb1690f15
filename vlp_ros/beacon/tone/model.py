"""
The stripe model: a profile as an envelope (1, u, u^2) plus an exposure-smeared square wave, and its fit.

Time runs in units of the window from its centre (tau in [-0.5, 0.5)), frequency in cycles per
window, phase in periods at the window's centre (where it hardly moves with the frequency). A row
sees the +-1 square wave's mean over its exposure; as demosaicing a Bayer mosaic does, it may also
be mixed with its neighbouring rows. ``rss`` is the model's residual at given (cycles, phase,
exposure), the envelope and amplitude at their best; ``ToneFit.peak`` refines one by Gauss-Newton.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from vlp_ros.compiled import kernel
from vlp_ros.compiled.linalg import inverse_2x2_or_3x3, inverse_cholesky_3x3

# Envelope terms (1, u, u^2) and the tone's amplitude (linear), frequency and phase (not).
_PARAMETERS = 6
# Longer windows are thinned to about this many rows (their frequency is pinned down many times over),
# keeping at least _MIN_ROWS_PER_PERIOD rows per stripe period.
_MAX_ROWS = 128
_MIN_ROWS_PER_PERIOD = 8.0
_MIN_EXPOSURE_ROWS = 0.05
# Colour sensors read through a Bayer mosaic mix each row with its neighbours when demosaicing (bilinear
# luma: about [w, 1 - 2 w, w] with w 0.13 on one row, 0.22 on the next). Unmodelled, the mix moves the
# edges' apparent places by up to a row, and short exposures the frequency by a band. Either camera is
# a hypothesis: a row's own light, or mixed (w at its best of MIX_LEVELS on even and odd rows apart) with a
# small prior weight, so that mixing counts where it fits clearly better and leaves unmixed frames as they were.
MIX_LEVELS = np.linspace(0.0, 0.3, 5)
MIXED_WEIGHT = 0.01


class EnvelopeFit(NamedTuple):
    """The kept rows of a profile with the envelope projected out (``envelope_fit``)."""

    # Every kept row's time (window units from the centre).
    tau: np.ndarray
    # Time at every row from the one before the first kept to the one after the last.
    tau_around: np.ndarray
    sqrt_w: np.ndarray
    # The orthonormal (weighted) envelope basis 1, u, u^2 (3, kept).
    envelope: np.ndarray
    # The weighted profile with the envelope projected out, and its square sum.
    y: np.ndarray
    null_rss: float
    # y sqrt(w).
    weighted_y: np.ndarray
    # The rows' products with the templates (kept, 4: envelope times sqrt(w), y sqrt(w)).
    products: np.ndarray
    weights: np.ndarray


class StripeModel(NamedTuple):
    """All that ``rss`` needs of a fit, after the cycles, phases and exposures."""

    rows: int
    tau_around: np.ndarray
    stride: int
    products: np.ndarray
    weights: np.ndarray
    null_rss: float
    # (dof + 1) / 2: the likelihood, noise level marginalised, is rss^-power.
    power: float


class Peak(NamedTuple):
    """The best square wave, one Gauss-Newton step from a start (``ToneFit.peak``)."""

    # Cycles per window, phase (periods, at the window's centre), exposure (rows).
    cycles: float
    phase: float
    exposure_rows: float
    # The spread (as the fit's curvature has it) of its cycles, and how its best phase moves with them.
    scale: float
    slope: float
    # The phase's spread at fixed cycles (at least half the gap between the rows' exposures).
    phase_spread: float


class ToneFit:
    """Weighted least squares of a profile by the stripe model, on every row or every k-th of a long window."""

    def __init__(self, z: np.ndarray, w: np.ndarray) -> None:
        self.rows = len(z)
        self.z, self.w = z, w
        self.use(1)

    def use(self, stride: int) -> None:
        """
        Fit every ``stride``-th row.

        Templates are taken at every row from the one before the first kept to the one after the last, a
        kept row's own and its neighbours' (tau_around); the envelope is orthonormal (weighted) over the
        kept rows, and y what it leaves of the profile.
        """
        self.kept = envelope_fit(self.z, self.w, stride)
        self.dof = len(self.kept.tau) - _PARAMETERS
        self.model = StripeModel(self.rows, self.kept.tau_around, stride, self.kept.products, self.kept.weights,
                                 self.kept.null_rss, 0.5 * (self.dof + 1))

    def thin(self, cycles: float, exposure_rows: float) -> None:
        """
        Keep every k-th row of a long window, while the rows' exposures still cover the time axis.

        A gap between them would hide edges.
        """
        stride = min(math.ceil(self.rows / _MAX_ROWS), int(self.rows / cycles / _MIN_ROWS_PER_PERIOD),
                     int(exposure_rows))
        if stride > 1:
            self.use(stride)

    def peak(self, cycles: float, phase: float, exposure_rows: float, free: bool) -> Peak | None:
        """
        Return the best square wave near (``cycles``, ``phase``, ``exposure_rows``), the exposure ``free`` or not.

        One Gauss-Newton step (the likelihood grid around it finds the rest), with the spreads of its
        frequency and phase; None where neither edges nor gaps place it.
        """
        kept = self.kept
        found, peak = gauss_newton(cycles, phase, exposure_rows, free, self.rows, kept.tau, kept.sqrt_w,
                                   kept.envelope, kept.y, kept.null_rss, self.dof)
        return peak if found else None


@kernel
def envelope_fit(z: np.ndarray, w: np.ndarray, stride: int) -> EnvelopeFit:
    """Return every ``stride``-th row of profile ``z`` (weights ``w``) with the envelope projected out."""
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
    # Orthonormal rows: the basis whitened by the inverse of its Gram matrix's Cholesky factor.
    envelope = inverse_cholesky_3x3(basis @ basis.T) @ basis
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
    return EnvelopeFit(tau, tau_around, sqrt_w, envelope, y, float(y @ y), weighted_y, products, sqrt_w * sqrt_w)


@kernel
def rss(cycles: np.ndarray, phase: np.ndarray, exposure_rows: np.ndarray, rows: int, tau_around: np.ndarray,
        stride: int, products: np.ndarray, weights: np.ndarray, null_rss: float, power: float) -> np.ndarray:
    """
    Return the residual sum of squares of each (cycles, phase, exposure rows), as both cameras together have it.

    The arguments after the three 1-d arrays (of one length) are a fit's ``StripeModel``. The envelope
    and amplitude are at their best; the cameras are the rows' own light, or mixed with the neighbouring
    rows' (the best of MIX_LEVELS on even and odd rows), with prior weight MIXED_WEIGHT; that is the rss
    whose likelihood (noise level marginalised) is the sum of theirs, ``power`` being (dof + 1) / 2.

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
        for even in MIX_LEVELS:
            projection_even = r3 + e3 * even
            norm_even_part = norm_0 + (norm_even + norm_even2 * even) * even
            for odd in MIX_LEVELS:
                projection = projection_even + o3 * odd
                norm = norm_even_part + (norm_odd + norm_odd2 * odd + norm_cross * even) * odd
                best = max(best, projection * projection / max(norm, 1e-300))
        mixed = max(null_rss - best, 1e-300)
        out[c] = mixed * (MIXED_WEIGHT + (mixed / own) ** power) ** (-1.0 / power)
    return out


@kernel
def gauss_newton(cycles: float, phase: float, exposure_rows: float, free: bool, rows: int, tau: np.ndarray,
                 sqrt_w: np.ndarray, envelope: np.ndarray, y: np.ndarray, null_rss: float,
                 dof: int) -> tuple[bool, Peak]:
    """Return whether ``ToneFit.peak`` finds one, and the peak."""
    residual, normal, gradient = _linearised(cycles, phase, exposure_rows, free, rows, tau, sqrt_w, envelope, y,
                                             null_rss)
    # Edges in the gaps between the rows' exposures move unseen by up to a gap (in periods).
    gap = max(1.0 - exposure_rows, 0.0) * cycles / rows
    invertible, inverse = inverse_2x2_or_3x3(normal)
    if not (invertible and inverse[0, 0] > 0.0 and inverse[1, 1] > 0.0):
        # No edge inside an exposure: all there is to go on is the gaps (the period moves by about a
        # gap over the window).
        return gap > 0.0, Peak(cycles, phase, exposure_rows, gap, 0.0, gap)
    step = inverse @ gradient
    cycles, phase = cycles + step[0], phase + step[1]
    if free:
        exposure_rows = min(max(exposure_rows + step[2], _MIN_EXPOSURE_ROWS), 0.5 * rows / cycles)
    # The noise from the residual the step leaves (as the linearised fit predicts it).
    covariance = inverse * (max(residual - step @ gradient, 1e-3 * residual) / dof)
    slope = covariance[0, 1] / covariance[0, 0]
    return True, Peak(cycles, phase, exposure_rows, math.sqrt(covariance[0, 0]), slope,
                      max(math.sqrt(max(covariance[1, 1] - slope * covariance[0, 1], 0.0)), 0.5 * gap))


@kernel
def _linearised(cycles: float, phase: float, exposure: float, free_exposure: bool, rows: int, tau: np.ndarray,
                sqrt_w: np.ndarray, envelope: np.ndarray, y: np.ndarray,
                null_rss: float) -> tuple[float, np.ndarray, np.ndarray]:
    """
    Return the residual sum of squares at (cycles, phase, exposure rows), and the normal matrix and gradient.

    The normal matrix and gradient (J^T J, J^T r) are over cycles, phase (and exposure) with envelope and
    amplitude at their best (Kaufman's variable projection Jacobian J), all from products of the template
    (0) and its derivatives, weighted, with each other, the envelope and y.
    """
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
