"""
Packet likelihood of a clipped window: a chip at the sensor's ceiling says only "at least this bright".

A disc's row means keep clipped pixels at the ceiling (``row_profile``), so a chip whose rows are
mostly clipped is a lower bound on its light, not a measurement of it: the light of a lamp 2x over
the ceiling reads the same in a bright run and in a bright chip between dark ones, and blur can lift
an isolated dark chip to the ceiling too. The Gaussian fit of ``packet.py`` then misfits (it predicts
the bright run brighter) and is refused. Here such a chip is *censored* (a Tobit likelihood): its
term is P(level >= observed) = Phi((mu - x) / sd) instead of a Gaussian around x, and every
hypothesis (ID, where in the packet the window starts, blur's mix) is fitted by Newton's method on
that concave log-likelihood. The chips below the ceiling (dark chips, the falloff's dimmer rows near
the rim) decide; the clipped ones only rule out hypotheses that put a dark chip there that blur
could not have lifted above the ceiling.
"""
from __future__ import annotations

from functools import lru_cache
import math

import numpy as np

from vlp_ros.beacon.chips import ChipLevels, interior_bounds
from vlp_ros.beacon.encoding import packet_chips
from vlp_ros.compiled import kernel
from vlp_ros.compiled.linalg import lu_solve, OPENCV_PIVOT_FLOOR

# A chip whose interior rows have more than this share of their pixels clipped is censored.
CENSORED_SHARE = 0.5
# Newton steps per hypothesis (the log-likelihood is concave: a few from the least-squares start suffice),
# and step halvings before a step is given up.
_NEWTON_STEPS = 12
_HALVINGS = 6
_LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)
# Envelope (3, quadratic in the chip index) and contrast-times-envelope (2, linear: kept positive at
# both ends of the window, so positive all along it).
_PARAMETERS = 5
# Relative step of the periods the run middles are tried on (a 50-chip window drifts 0.025 chips a step).
_PERIOD_STEP = 5e-4


@lru_cache(maxsize=4)
def _signs(id_bits: int) -> np.ndarray:
    """Every ID's packet as chip signs (+1 bright, -1 dark), (2^id_bits, L)."""
    return np.array([packet_chips(i, id_bits) for i in range(2 ** id_bits)], dtype=float) * 2.0 - 1.0


def clipped_run_grids(share: np.ndarray, period: float, tolerance: float) -> list[tuple[float, float]]:
    """
    Chip grids (period, where a chip begins, in rows) from where the rows cross half clipped.

    Blur erodes a dark run and widens a bright one by the same rows at both ends, so the middles of the runs
    between crossings lie on chip edges (runs of even length) or chip middles (odd): on a lattice of half
    chips. The period within +-``tolerance`` (relative) that puts them best on such a lattice, and its two
    readings (chips beginning on the lattice, or half a chip off it); none with fewer than three runs.
    """
    above = share > 0.5
    edges = np.flatnonzero(above[1:] != above[:-1])
    # Sub-row crossing positions (row r covers [r, r + 1)): where the share passes 0.5 between row middles.
    crossings = edges + 0.5 + (0.5 - share[edges]) / (share[edges + 1] - share[edges])
    middles = 0.5 * (crossings[1:] + crossings[:-1])
    if len(middles) < 3:
        return []
    steps = max(int(math.ceil(tolerance / _PERIOD_STEP)), 1)
    periods = period * (1.0 + _PERIOD_STEP * np.arange(-steps, steps + 1))
    phasors = np.exp(4j * np.pi * middles[None, :] / periods[:, None]).sum(axis=1)
    best = int(np.argmax(np.abs(phasors)))
    found = periods[best]
    lattice = (np.angle(phasors[best]) / (4.0 * np.pi) * found) % (0.5 * found)
    return [(found, lattice), (found, lattice + 0.5 * found)]


def raw_chips(z: np.ndarray, w: np.ndarray, share: np.ndarray, levels: ChipLevels,
              margin: float | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """
    Return each chip of ``levels`` as the rows it averages show it, before normalisation.

    That is before the local extremes normalise it (they squeeze a clipped neighbourhood's contrast to
    the ceiling's): its relative brightness, the weight of its rows, and the weighted share of its pixels
    that are clipped.
    """
    sums = [np.concatenate([[0.0], np.cumsum(values)]) for values in (w, w * z, w * share)]
    low, high = interior_bounds(levels, margin, len(w))

    def between(cumulative: np.ndarray) -> np.ndarray:
        def at(u: np.ndarray) -> np.ndarray:
            i = np.minimum(u.astype(int), len(w) - 1)
            return cumulative[i] + (u - i) * (cumulative[i + 1] - cumulative[i])
        return at(high) - at(low)

    weight = np.maximum(between(sums[0]), 1e-12)
    return between(sums[1]) / weight, weight, between(sums[2]) / weight


def censored_log_likelihoods(x: np.ndarray, v: np.ndarray, k: np.ndarray, censored: np.ndarray, id_bits: int,
                             mixes: tuple[float, ...]) -> tuple[np.ndarray, float]:
    """
    Return the log-likelihood of each ID of chip levels ``x``, and the best hypothesis's deviance.

    Shift and mix are marginalised, the IDs equally likely a priori; ``v`` are the weights, ``k`` the
    chip indices, and ``censored`` ones are lower bounds. The deviance is the weighted squared residuals
    of the measured chips plus -2 log P of the censored ones.
    """
    fits = _censored_fits(np.asarray(x, dtype=float), np.asarray(v, dtype=float), np.asarray(k, dtype=np.int64),
                          np.asarray(censored, dtype=np.bool_), _signs(id_bits), np.asarray(mixes, dtype=float))
    top = fits.max()
    # Mean over mixes and shifts, per ID.
    per_id = top + np.log(np.exp(fits - top).mean(axis=(0, 1)))
    return per_id, -2.0 * float(top)


@kernel
def _censored_fits(x: np.ndarray, v: np.ndarray, k: np.ndarray, censored: np.ndarray, signs: np.ndarray,
                   mixes: np.ndarray) -> np.ndarray:
    """
    Return the maximised censored log-likelihood of every (mix, shift, ID), (mixes, L, ids).

    Chip j's light is an envelope times (1 + contrast x its template s_p + mix (s_p-1 + s_p+1)), p = (k_j
    + shift) % L: the lamp's light (falloff, chords, glare) scales bright and dark chips alike, which is
    what decides where blur lifts a dark chip over the ceiling. Linear in its parameters: the envelope
    quadratic in the chip index, contrast-times-envelope linear in it and positive over the window (a
    bright chip is brighter).
    """
    n, ids, length = len(x), signs.shape[0], signs.shape[1]
    out = np.empty((len(mixes), length, ids))
    design = np.empty((n, _PARAMETERS))
    middle, half = 0.5 * (k[0] + k[-1]), max(0.5 * float(k[-1] - k[0]), 1.0)
    for j in range(n):
        t = (k[j] - middle) / half
        design[j, 0], design[j, 1], design[j, 2] = 1.0, t, t * t
    root = np.sqrt(v)
    for m in range(len(mixes)):
        mix = mixes[m]
        for shift in range(length):
            for i in range(ids):
                for j in range(n):
                    p = (k[j] + shift) % length
                    template = signs[i, p] + mix * (signs[i, (p - 1) % length] + signs[i, (p + 1) % length])
                    design[j, 3], design[j, 4] = template, template * design[j, 1]
                out[m, shift, i] = _fit(design, x, v, root, censored)
    return out


@kernel
def _fit(design: np.ndarray, x: np.ndarray, v: np.ndarray, root: np.ndarray, censored: np.ndarray) -> float:
    """
    Return the log-likelihood that Newton's method maximises.

    Newton's method starts from the least-squares fit of every chip (censored ones at their bounds), halving steps
    that do not raise the log-likelihood; the contrast is kept positive (``_positive_contrast``).
    """
    n, size = len(x), _PARAMETERS
    gradient, hessian = np.zeros(size), np.zeros((size, size))
    for j in range(n):
        for a in range(size):
            gradient[a] += v[j] * design[j, a] * x[j]
            for b in range(size):
                hessian[a, b] += v[j] * design[j, a] * design[j, b]
    theta = _solve(hessian, gradient)
    _positive_contrast(theta)
    best = _log_likelihood(design, x, v, root, censored, theta)
    trial = np.empty(size)
    for _ in range(_NEWTON_STEPS):
        gradient[:] = 0.0
        hessian[:, :] = 0.0
        for j in range(n):
            mu = 0.0
            for a in range(size):
                mu += design[j, a] * theta[a]
            if censored[j]:
                u = root[j] * (mu - x[j])
                ratio = _mills(u)
                slope, curvature = ratio * root[j], ratio * (u + ratio) * v[j]
            else:
                slope, curvature = v[j] * (x[j] - mu), v[j]
            for a in range(size):
                gradient[a] += slope * design[j, a]
                for b in range(size):
                    hessian[a, b] += curvature * design[j, a] * design[j, b]
        step = _solve(hessian, gradient)
        scale, value, gained = 1.0, best, False
        for _ in range(_HALVINGS):
            for a in range(size):
                trial[a] = theta[a] + scale * step[a]
            _positive_contrast(trial)
            value = _log_likelihood(design, x, v, root, censored, trial)
            if value > best:
                gained = True
                break
            scale *= 0.5
        if not gained:
            break
        improvement = value - best
        theta[:] = trial
        best = value
        if improvement < 1e-6:
            break
    return best


@kernel
def _positive_contrast(theta: np.ndarray) -> None:
    """Projects the contrast's middle value and slope (theta[3], theta[4]) onto middle >= |slope|."""
    middle, slope = theta[3], theta[4]
    if middle >= abs(slope):
        return
    edge = max(0.5 * (middle + abs(slope)), 0.0)
    theta[3], theta[4] = edge, edge if slope > 0.0 else -edge


@kernel
def _log_likelihood(design: np.ndarray, x: np.ndarray, v: np.ndarray, root: np.ndarray, censored: np.ndarray,
                    theta: np.ndarray) -> float:
    total = 0.0
    for j in range(len(x)):
        mu = 0.0
        for a in range(len(theta)):
            mu += design[j, a] * theta[a]
        if censored[j]:
            total += _log_normal_cdf(root[j] * (mu - x[j]))
        else:
            total -= 0.5 * v[j] * (x[j] - mu) ** 2
    return total


@kernel
def _log_normal_cdf(u: float) -> float:
    """Log Phi(u), with its asymptote far in the lower tail (where erfc underflows)."""
    if u > -30.0:
        return math.log(0.5 * math.erfc(-u / math.sqrt(2.0)))
    return -0.5 * u * u - math.log(-u) - _LOG_SQRT_2PI


@kernel
def _mills(u: float) -> float:
    """phi(u) / Phi(u): the censored term's slope in u."""
    return math.exp(-0.5 * u * u - _LOG_SQRT_2PI - _log_normal_cdf(u))


@kernel
def _solve(matrix: np.ndarray, vector: np.ndarray) -> np.ndarray:
    """
    Return matrix^-1 vector for a small symmetric positive semi-definite matrix.

    A tiny ridge guards against a singular one (a hypothesis whose template the envelope explains).
    """
    ridged = matrix.copy()
    for a in range(len(vector)):
        ridged[a, a] += 1e-9 * matrix[a, a] + 1e-12
    solved = lu_solve(ridged, vector, OPENCV_PIVOT_FLOOR)
    return solved.solution if solved.ok else np.zeros(len(vector))
