"""
Packet likelihood of a clipped window: a chip at the sensor's ceiling says only "at least this bright".

A disc's row means keep clipped pixels at the ceiling (``row_profile``), so a chip whose rows are
mostly clipped is a lower bound on its light, not a measurement of it: the light of a lamp 2x over
the ceiling reads the same in a bright run and in a bright chip between dark ones, and blur can lift
an isolated dark chip to the ceiling too. The Gaussian fit of ``packet.py`` then misfits (it predicts
the bright run brighter) and is refused. Here such a chip is *censored* (a Tobit likelihood): its
term is P(level >= observed) = Phi((mu - x) / sd) instead of a Gaussian around x. Every hypothesis (ID,
where in the packet the window starts, blur's mix) gets a closed-form upper bound of its maximised
log-likelihood, all of them at once; Newton's method fits that concave log-likelihood only for the
hypotheses whose bound comes within PRUNE_MARGIN of the best fit (at the median 127 of the 18432 of 8-bit
IDs, clipped drive and hand-held discs). The chips below the ceiling (dark chips, the falloff's dimmer rows near
the rim) decide; the clipped ones only rule out hypotheses that put a dark chip there that blur
could not have lifted above the ceiling.
"""
from __future__ import annotations

from functools import lru_cache
import math

import numpy as np

from vlp_ros.beacon.chips import ChipLevels, interior_bounds
from vlp_ros.beacon.encoding import packet_chips, packet_length
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
# Hypotheses whose bound lies this far (nats) below the best fit are not fitted: even all of them together
# weigh less than 1e-4 of it (18432 of them at 8 bits: e^-20 x 18432 = 4e-5).
PRUNE_MARGIN = 20.0


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
    x, v = np.asarray(x, dtype=float), np.asarray(v, dtype=float)
    k, censored = np.asarray(k, dtype=np.int64), np.asarray(censored, dtype=np.bool_)
    mixes = tuple(float(mix) for mix in mixes)
    bounds = _closed_form_bounds(x, v, k, censored, id_bits, mixes)
    fits = _fits_that_can_win(bounds, x, v, k, censored, _signs(id_bits), np.asarray(mixes, dtype=float),
                              PRUNE_MARGIN)
    top = fits.max()
    # Mean over mixes and shifts, per ID.
    per_id = top + np.log(np.exp(fits - top).mean(axis=(0, 1)))
    return per_id, -2.0 * float(top)


@lru_cache(maxsize=16)
def _template_tables(id_bits: int, mixes: tuple[float, ...]) -> tuple[np.ndarray, ...]:
    """
    Every (mix, ID)'s template at each packet position, and what the closed-form bound weighs with it.

    The template T_p = s_p + mix (s_p-1 + s_p+1) and its square; the chip's own darkness d_p = (1 - s_p) / 2 and
    d_p T_p, d_p T_p^2 (a censored chip counts in the bound's least squares only where the hypothesis makes it
    dark); and T again. Each (L, mixes x ids), the mixes side by side, but the darkness (L, ids): the mix leaves it.
    """
    signs = np.ascontiguousarray(_signs(id_bits).T)
    neighbours = np.roll(signs, 1, axis=0) + np.roll(signs, -1, axis=0)
    template = np.hstack([signs + mix * neighbours for mix in mixes])
    dark = 0.5 * (1.0 - signs)
    dark_of_each = np.hstack([dark] * len(mixes))
    tables = (template, template * template, dark, dark_of_each * template, dark_of_each * template * template,
              template)
    for table in tables:
        table.flags.writeable = False
    return tables


def _closed_form_bounds(x: np.ndarray, v: np.ndarray, k: np.ndarray, censored: np.ndarray, id_bits: int,
                        mixes: tuple[float, ...]) -> np.ndarray:
    """
    Return an upper bound of every (mix, shift, ID)'s maximised censored log-likelihood, (mixes, L, ids).

    log Phi(u) <= -u^2 / 2 for u <= 0 (Chernoff) and <= 0: a censored chip costs at most its shortfall below
    its bound squared. The bound is the least-squares fit of the measured chips and of the censored chips
    the hypothesis makes dark (at their bound), with the censored chips it makes bright taken together: their
    summed squared shortfalls are at least the square of their summed shortfall over their summed weight
    (Jensen), one term that the fit can take in closed form (``_bounds_from_sums``). The contrast is left
    unconstrained. Tight for the hypotheses that can win (their dark chips are not lifted over the ceiling),
    loose for the others, which is all that pruning needs.

    All hypotheses at once: every sum over the chips is a fold of the chips by packet position for each shift
    (``_folded``) times a table of every ID's template (``_template_tables``).
    """
    length = packet_length(id_bits)
    middle, half = 0.5 * (k[0] + k[-1]), max(0.5 * float(k[-1] - k[0]), 1.0)
    t = (k - middle) / half
    powers = t[None, :] ** np.arange(5)[:, None]
    measured = ~censored
    vm, vc = v * measured, v * censored
    # Hypothesis-free sums: over the measured chips sum v t^i (i < 5), sum v x t^i (i < 3), sum v x^2; over the
    # censored ones sum v t^i (i < 3) and sum v x.
    fixed = np.concatenate([powers @ vm, powers[:3] @ (vm * x), [vm @ (x * x)], powers[:3] @ vc, [vc @ x]])
    # Per table, the chip weights folded with it: measured chips with the template T and its square, the censored
    # ones with their darkness (d, d T, d T^2) and with T.
    weights = (np.vstack([powers[:4] * vm, powers[:2] * (vm * x)]), powers[:3] * vm,
               np.vstack([powers * vc, powers[:3] * (vc * x), (vc * x * x)[None, :]]),
               np.vstack([powers[:4] * vc, powers[:2] * (vc * x)]), powers[:3] * vc, powers[:2] * vc)
    folds = [_folded(w, k, length) for w in weights]
    sums = [(fold.reshape(-1, length) @ table).reshape(fold.shape[0], length, -1)
            for fold, table in zip(folds, _template_tables(id_bits, mixes))]
    bounds = _bounds_from_sums(fixed, *sums)
    return np.ascontiguousarray(bounds.reshape(length, len(mixes), -1).transpose(1, 0, 2))


@kernel
def _folded(weights: np.ndarray, k: np.ndarray, length: int) -> np.ndarray:
    """Each row of ``weights`` (one value per chip) summed by packet position for each shift, (rows, L, L)."""
    rows = weights.shape[0]
    out = np.zeros((rows, length, length))
    for shift in range(length):
        for j in range(len(k)):
            position = (k[j] + shift) % length
            for r in range(rows):
                out[r, shift, position] += weights[r, j]
    return out


@kernel
def _bounds_from_sums(fixed: np.ndarray, measured_t: np.ndarray, measured_t2: np.ndarray, censored_d: np.ndarray,
                      censored_dt: np.ndarray, censored_dt2: np.ndarray, censored_t: np.ndarray) -> np.ndarray:
    """
    Return every (shift, hypothesis)'s bound from its weighted sums (``_closed_form_bounds``), (L, mixes x ids).

    Columns 1, t, t^2 (envelope), T, t T (contrast) in the chip index t and the template T. The least-squares
    fit of the measured and dark censored chips (Gram matrix G = L L^T, right-hand side b), then the bright
    censored chips' summed shortfall h = c - a'theta (a, c: their summed weighted columns and bounds over the
    root of their summed weight), where positive, taken in: the fit with the term -h^2 / 2 loses
    h^2 / (2 (1 + a'G^-1 a)) (Sherman-Morrison), and its h stays positive, so the term is its own. A tiny ridge
    as in ``_solve``; a singular system bounds nothing (0). Written out without branches or inner loops, so
    that the loop over the hypotheses runs several at once (SIMD).
    """
    length, count, ids = measured_t.shape[1], measured_t.shape[2], censored_d.shape[2]
    out = np.empty((length, count))
    ridge = 1.0 + 1e-9
    for shift in range(length):
        # ``censored_d`` is the same for every mix: hypothesis i is its d of a block of ``ids``.
        for block in range(count // ids):
            for d in range(ids):
                i = block * ids + d
                cd0, cd1, cd2 = censored_d[0, shift, d], censored_d[1, shift, d], censored_d[2, shift, d]
                g00 = (fixed[0] + cd0) * ridge + 1e-12
                g01 = fixed[1] + cd1
                g02 = fixed[2] + cd2
                g11 = (fixed[2] + cd2) * ridge + 1e-12
                g12 = fixed[3] + censored_d[3, shift, d]
                g22 = (fixed[4] + censored_d[4, shift, d]) * ridge + 1e-12
                g03 = measured_t[0, shift, i] + censored_dt[0, shift, i]
                g13 = measured_t[1, shift, i] + censored_dt[1, shift, i]
                g23 = measured_t[2, shift, i] + censored_dt[2, shift, i]
                g04, g14 = g13, g23
                g24 = measured_t[3, shift, i] + censored_dt[3, shift, i]
                g33 = (measured_t2[0, shift, i] + censored_dt2[0, shift, i]) * ridge + 1e-12
                g34 = measured_t2[1, shift, i] + censored_dt2[1, shift, i]
                g44 = (measured_t2[2, shift, i] + censored_dt2[2, shift, i]) * ridge + 1e-12
                b0 = fixed[5] + censored_d[5, shift, d]
                b1 = fixed[6] + censored_d[6, shift, d]
                b2 = fixed[7] + censored_d[7, shift, d]
                b3 = measured_t[4, shift, i] + censored_dt[4, shift, i]
                b4 = measured_t[5, shift, i] + censored_dt[5, shift, i]
                a0, a1, a2 = fixed[9] - cd0, fixed[10] - cd1, fixed[11] - cd2
                a3 = censored_t[0, shift, i] - censored_dt[0, shift, i]
                a4 = censored_t[1, shift, i] - censored_dt[1, shift, i]
                squares = fixed[8] + censored_d[8, shift, d]
                # Cholesky's factor L, then y = L^-1 b and z = L^-1 a.
                l00 = math.sqrt(g00)
                l10, l20, l30, l40 = g01 / l00, g02 / l00, g03 / l00, g04 / l00
                l11 = math.sqrt(g11 - l10 * l10)
                l21, l31, l41 = (g12 - l20 * l10) / l11, (g13 - l30 * l10) / l11, (g14 - l40 * l10) / l11
                l22 = math.sqrt(g22 - l20 * l20 - l21 * l21)
                l32, l42 = (g23 - l30 * l20 - l31 * l21) / l22, (g24 - l40 * l20 - l41 * l21) / l22
                l33 = math.sqrt(g33 - l30 * l30 - l31 * l31 - l32 * l32)
                l43 = (g34 - l40 * l30 - l41 * l31 - l42 * l32) / l33
                l44 = math.sqrt(g44 - l40 * l40 - l41 * l41 - l42 * l42 - l43 * l43)
                y0 = b0 / l00
                y1 = (b1 - l10 * y0) / l11
                y2 = (b2 - l20 * y0 - l21 * y1) / l22
                y3 = (b3 - l30 * y0 - l31 * y1 - l32 * y2) / l33
                y4 = (b4 - l40 * y0 - l41 * y1 - l42 * y2 - l43 * y3) / l44
                z0 = a0 / l00
                z1 = (a1 - l10 * z0) / l11
                z2 = (a2 - l20 * z0 - l21 * z1) / l22
                z3 = (a3 - l30 * z0 - l31 * z1 - l32 * z2) / l33
                z4 = (a4 - l40 * z0 - l41 * z1 - l42 * z2 - l43 * z3) / l44
                explained = y0 * y0 + y1 * y1 + y2 * y2 + y3 * y3 + y4 * y4
                along = z0 * y0 + z1 * y1 + z2 * y2 + z3 * y3 + z4 * y4
                spread = z0 * z0 + z1 * z1 + z2 * z2 + z3 * z3 + z4 * z4
                # Without bright censored chips (their weight down to the rounding of the censored chips' total), the
                # shortfall is rounding too, and no term.
                weight = fixed[9] - cd0
                bright = weight > 1e-9 * fixed[9]
                shortfall = max(fixed[12] - censored_d[5, shift, d] - along, 0.0) if bright else 0.0
                value = -0.5 * max(squares - explained, 0.0) \
                    - 0.5 * shortfall * shortfall / max(weight + spread, 1e-300)
                # A singular system (a NaN from a negative pivot) bounds nothing.
                out[shift, i] = value if value <= 0.0 else 0.0
    return out


@kernel
def _fits_that_can_win(bounds: np.ndarray, x: np.ndarray, v: np.ndarray, k: np.ndarray, censored: np.ndarray,
                       signs: np.ndarray, mixes: np.ndarray, margin: float) -> np.ndarray:
    """
    Return every (mix, shift, ID)'s maximised censored log-likelihood, (mixes, L, ids), where it can matter.

    Chip j's light is an envelope times (1 + contrast x its template s_p + mix (s_p-1 + s_p+1)), p = (k_j
    + shift) % L: the lamp's light (falloff, chords, glare) scales bright and dark chips alike, which is
    what decides where blur lifts a dark chip over the ceiling. Linear in its parameters: the envelope
    quadratic in the chip index, contrast-times-envelope linear in it and positive over the window (a
    bright chip is brighter).

    Newton's method (``_fit``) runs on the hypotheses in the order of their ``bounds``, until a bound falls
    ``margin`` below the best fit found: every later hypothesis is then that far below the best, and keeps its
    bound (its share of the likelihood is below e^-margin of the best's).
    """
    n = len(x)
    out = bounds.copy()
    design = np.empty((n, _PARAMETERS))
    middle, half = 0.5 * (k[0] + k[-1]), max(0.5 * float(k[-1] - k[0]), 1.0)
    for j in range(n):
        t = (k[j] - middle) / half
        design[j, 0], design[j, 1], design[j, 2] = 1.0, t, t * t
    root = np.sqrt(v)
    flat, fitted = bounds.ravel(), out.ravel()
    # The best bound's fit first: only the hypotheses whose bounds come within the margin of it can be fitted, so
    # only those are sorted (a sort of all 18432 of 8 bits took longer than their fits).
    first = int(np.argmax(flat))
    best = _fit_hypothesis(first, design, x, v, root, k, censored, signs, mixes)
    fitted[first] = best
    reach = np.flatnonzero(flat >= best - margin)
    for h in reach[np.argsort(-flat[reach])]:
        if flat[h] < best - margin:
            break
        if h == first:
            continue
        value = _fit_hypothesis(h, design, x, v, root, k, censored, signs, mixes)
        fitted[h] = value
        best = max(best, value)
    return out


@kernel
def _fit_hypothesis(h: int, design: np.ndarray, x: np.ndarray, v: np.ndarray, root: np.ndarray, k: np.ndarray,
                    censored: np.ndarray, signs: np.ndarray, mixes: np.ndarray) -> float:
    """Return hypothesis ``h``'s (its flat index over (mixes, L, ids)) maximised log-likelihood, by ``_fit``."""
    ids, length = signs.shape[0], signs.shape[1]
    m, rest = h // (length * ids), h % (length * ids)
    shift, i = rest // ids, rest % ids
    mix = mixes[m]
    for j in range(len(x)):
        p = (k[j] + shift) % length
        template = signs[i, p] + mix * (signs[i, (p - 1) % length] + signs[i, (p + 1) % length])
        design[j, 3], design[j, 4] = template, template * design[j, 1]
    return _fit(design, x, v, root, censored)


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
