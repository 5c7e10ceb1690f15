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
def _template_tables(id_bits: int, mix: float) -> tuple[np.ndarray, ...]:
    """
    Every ID's template at each packet position, and what the closed-form bound weighs with it, (L, ids) each.

    The template t_p = s_p + mix (s_p-1 + s_p+1) and its square; the chip's own darkness d_p = (1 - s_p) / 2 and
    d_p t_p, d_p t_p^2 (a censored chip counts in the bound's least squares only where the hypothesis makes it dark).
    """
    signs = np.ascontiguousarray(_signs(id_bits).T)
    template = signs + mix * (np.roll(signs, 1, axis=0) + np.roll(signs, -1, axis=0))
    dark = 0.5 * (1.0 - signs)
    tables = (template, template * template, dark, dark * template, dark * template * template, template)
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
    bounds = np.empty((len(mixes), length, 2 ** id_bits))
    for m, mix in enumerate(mixes):
        sums = [(fold.reshape(-1, length) @ table).reshape(fold.shape[0], length, -1)
                for fold, table in zip(folds, _template_tables(id_bits, mix))]
        bounds[m] = _bounds_from_sums(fixed, *sums)
    return bounds


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
    Return every (shift, ID)'s bound from its weighted sums (``_closed_form_bounds``), (L, ids).

    Columns 1, t, t^2 (envelope), T, t T (contrast) in the chip index t and the template T. The least-squares
    fit of the measured and dark censored chips (Gram matrix G, right-hand side b), then the bright censored
    chips' summed shortfall h = c - a'theta (a, c: their summed weighted columns and bounds over the root of
    their summed weight), where positive, taken in: the fit with the term -h^2 / 2 loses h^2 / (2 (1 + a'G^-1 a))
    (Sherman-Morrison), and its h stays positive, so the term is its own. A tiny ridge as in ``_solve``; a
    singular system bounds nothing (0).
    """
    length, ids = measured_t.shape[1], measured_t.shape[2]
    out = np.empty((length, ids))
    gram, target, bright = np.empty((_PARAMETERS, _PARAMETERS)), np.empty(_PARAMETERS), np.empty(_PARAMETERS)
    for shift in range(length):
        for i in range(ids):
            for a in range(3):
                for b in range(3):
                    gram[a, b] = fixed[a + b] + censored_d[a + b, shift, i]
                target[a] = fixed[5 + a] + censored_d[5 + a, shift, i]
                gram[a, 3] = gram[3, a] = measured_t[a, shift, i] + censored_dt[a, shift, i]
                gram[a, 4] = gram[4, a] = measured_t[a + 1, shift, i] + censored_dt[a + 1, shift, i]
                bright[a] = fixed[9 + a] - censored_d[a, shift, i]
            gram[3, 3] = measured_t2[0, shift, i] + censored_dt2[0, shift, i]
            gram[3, 4] = gram[4, 3] = measured_t2[1, shift, i] + censored_dt2[1, shift, i]
            gram[4, 4] = measured_t2[2, shift, i] + censored_dt2[2, shift, i]
            target[3] = measured_t[4, shift, i] + censored_dt[4, shift, i]
            target[4] = measured_t[5, shift, i] + censored_dt[5, shift, i]
            bright[3] = censored_t[0, shift, i] - censored_dt[0, shift, i]
            bright[4] = censored_t[1, shift, i] - censored_dt[1, shift, i]
            squares = fixed[8] + censored_d[8, shift, i]
            if not _cholesky(gram):
                out[shift, i] = 0.0
                continue
            # y = L^-1 b (its squared norm is b'G^-1 b), z = L^-1 a.
            _forward(gram, target)
            _forward(gram, bright)
            explained, along, spread = 0.0, 0.0, 0.0
            for a in range(_PARAMETERS):
                explained += target[a] * target[a]
                along += bright[a] * target[a]
                spread += bright[a] * bright[a]
            value = -0.5 * max(squares - explained, 0.0)
            weight = fixed[9] - censored_d[0, shift, i]
            if weight > 0.0:
                shortfall = (fixed[12] - censored_d[5, shift, i] - along) / math.sqrt(weight)
                if shortfall > 0.0:
                    value -= 0.5 * shortfall * shortfall / (1.0 + spread / weight)
            out[shift, i] = value
    return out


@kernel
def _cholesky(gram: np.ndarray) -> bool:
    """
    Factor a small symmetric positive semi-definite ``gram`` into its lower triangle, in place.

    With the tiny ridge of ``_solve``; False where it is singular even so.
    """
    size = gram.shape[0]
    for a in range(size):
        gram[a, a] += 1e-9 * gram[a, a] + 1e-12
    for a in range(size):
        pivot = gram[a, a]
        for c in range(a):
            pivot -= gram[a, c] * gram[a, c]
        if not pivot > 1e-300:
            return False
        pivot = math.sqrt(pivot)
        gram[a, a] = pivot
        for b in range(a + 1, size):
            value = gram[b, a]
            for c in range(a):
                value -= gram[b, c] * gram[a, c]
            gram[b, a] = value / pivot
    return True


@kernel
def _forward(factor: np.ndarray, vector: np.ndarray) -> None:
    """Replace ``vector`` by L^-1 ``vector``, L the lower triangle of ``factor``."""
    for a in range(len(vector)):
        value = vector[a]
        for c in range(a):
            value -= factor[a, c] * vector[c]
        vector[a] = value / factor[a, a]


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
    n, ids, length = len(x), signs.shape[0], signs.shape[1]
    out = bounds.copy()
    design = np.empty((n, _PARAMETERS))
    middle, half = 0.5 * (k[0] + k[-1]), max(0.5 * float(k[-1] - k[0]), 1.0)
    for j in range(n):
        t = (k[j] - middle) / half
        design[j, 0], design[j, 1], design[j, 2] = 1.0, t, t * t
    root = np.sqrt(v)
    flat = bounds.ravel()
    order = np.argsort(-flat)
    best = -np.inf
    for h in order:
        if flat[h] < best - margin:
            break
        m, rest = h // (length * ids), h % (length * ids)
        shift, i = rest // ids, rest % ids
        mix = mixes[m]
        for j in range(n):
            p = (k[j] + shift) % length
            template = signs[i, p] + mix * (signs[i, (p - 1) % length] + signs[i, (p + 1) % length])
            design[j, 3], design[j, 4] = template, template * design[j, 1]
        value = _fit(design, x, v, root, censored)
        out[m, shift, i] = value
        best = max(best, value)
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
