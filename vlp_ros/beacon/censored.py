"""
Packet likelihood of a clipped window: a chip at the sensor's ceiling says only "at least this bright".

A disc's row means keep clipped pixels at the ceiling (``row_profile``), so a chip whose rows are
mostly clipped is a lower bound on its light, not a measurement of it: the light of a lamp 2x over
the ceiling reads the same in a bright run and in a bright chip between dark ones, and blur can lift
an isolated dark chip to the ceiling too. The Gaussian fit of ``packet.py`` then misfits (it predicts
the bright run brighter) and is refused. Here such a chip is *censored* (a Tobit likelihood): its
term is P(level >= observed) = Phi((mu - x) / sd) instead of a Gaussian around x. Every hypothesis (ID,
where in the packet the window starts, blur's mix) gets a closed-form guide to its maximised log-likelihood,
all of them at once; Newton's method fits that concave log-likelihood only for the hypotheses whose guide comes
within PRUNE_MARGIN of the best fit. A window whose best fit misfits is refused; whether it does is decided on
closed-form upper bounds, sound for every hypothesis, so that a refused window fits only the few hypotheses
whose bounds reach the limit (about 80 of the 18432 of 8-bit IDs per refused window of the foreign clipped
frames). The chips below the ceiling (dark chips, the falloff's dimmer rows near the rim) decide; the clipped
ones only rule out hypotheses that put a dark chip there that blur could not have lifted above the ceiling.
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
# Nats the sound bounds are taken as loose by, for their rounding (a ridge of 1e-9 of the fit's Gram matrix).
_SOUND_SLACK = 1e-3


@lru_cache(maxsize=4)
def _signs(id_bits: int) -> np.ndarray:
    """Every ID's packet as chip signs (+1 bright, -1 dark), (2^id_bits, L)."""
    return np.array([packet_chips(i, id_bits) for i in range(2 ** id_bits)], dtype=float) * 2.0 - 1.0


@lru_cache(maxsize=4)
def _packet_masks(id_bits: int) -> np.ndarray:
    """Every ID's packet as a bit mask of its bright chips (bit p: position p), (2^id_bits,) int64."""
    powers = np.int64(1) << np.arange(packet_length(id_bits), dtype=np.int64)
    masks = (_signs(id_bits) > 0.0).astype(np.int64) @ powers
    masks.flags.writeable = False
    return masks


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
                             mixes: tuple[float, ...],
                             deviance_limit: float = math.inf) -> tuple[np.ndarray | None, float]:
    """
    Return the log-likelihood of each ID of chip levels ``x``, and the best hypothesis's deviance.

    Shift and mix are marginalised, the IDs equally likely a priori; ``v`` are the weights, ``k`` the
    chip indices, and ``censored`` ones are lower bounds. The deviance is the weighted squared residuals
    of the measured chips plus -2 log P of the censored ones. Where it exceeds ``deviance_limit``, the
    log-likelihoods are None (not taken) and the deviance returned is a lower bound of it, above the limit:
    the fits stop once no hypothesis left can come within the limit (``_fits_that_can_win``).
    """
    x, v = np.asarray(x, dtype=float), np.asarray(v, dtype=float)
    k, censored = np.asarray(k, dtype=np.int64), np.asarray(censored, dtype=np.bool_)
    mixes = tuple(float(mix) for mix in mixes)
    sums = _hypothesis_sums(x, v, k, censored, id_bits, mixes)
    bounds = np.ascontiguousarray(_bounds_from_sums(*sums).reshape(-1, len(mixes), 2 ** id_bits).transpose(1, 0, 2))
    floor = -0.5 * deviance_limit
    fits, refused_top = _fits_that_can_win(bounds, sums, x, v, k, censored, _signs(id_bits), _packet_masks(id_bits),
                                           np.asarray(mixes, dtype=float), PRUNE_MARGIN, floor)
    top = refused_top if refused_top < floor else float(fits.max())
    if -2.0 * top > deviance_limit:
        return None, -2.0 * top
    # Mean over mixes and shifts, per ID.
    per_id = top + np.log(np.exp(fits - top).mean(axis=(0, 1)))
    return per_id, -2.0 * top


@lru_cache(maxsize=4)
def _template_tables(id_bits: int) -> tuple[np.ndarray, ...]:
    """
    Every ID's chip signs and what the closed-form bounds weigh with them, at each packet position.

    The template T_p = s_p + mix n_p (n_p = s_p-1 + s_p+1) is linear in the mix, so every sum with it is taken
    from sums with s and n: with T, T^2 = 1 + 2 mix s n + mix^2 n^2 (s^2 = 1), and with the chip's own darkness
    d_p = (1 - s_p) / 2 (a censored chip counts in the guide's least squares only where the hypothesis makes it
    dark), d T = -d + mix d n and d T^2 = d - 2 mix d n + mix^2 d n^2 (d s = -d). The tables [s | n], [s n | n^2],
    d, d n and d n^2, (L, 2 ids) or (L, ids).
    """
    signs = np.ascontiguousarray(_signs(id_bits).T)
    neighbours = np.roll(signs, 1, axis=0) + np.roll(signs, -1, axis=0)
    dark = 0.5 * (1.0 - signs)
    tables = (np.hstack([signs, neighbours]), np.hstack([signs * neighbours, neighbours * neighbours]), dark,
              dark * neighbours, dark * neighbours * neighbours)
    for table in tables:
        table.flags.writeable = False
    return tables


@lru_cache(maxsize=4)
def _factored_tables(id_bits: int) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
    """
    Return the tables of ``_template_tables`` factored exactly as coefficients (L, blocks x r) times a basis (r, ids).

    A packet's chips are its preamble's and its bits' (Manchester), so each table holds a few independent rows
    (10 to 18 of the 24 positions of 8-bit IDs): the basis is such rows, the coefficients small integers, so
    a fold times a table is taken in fewer products. One basis for the two blocks of [s | n] and [s n | n^2].
    """
    factored = []
    for table in _template_tables(id_bits):
        blocks = table.shape[1] // 2 ** id_bits
        parts = np.hsplit(table, blocks)
        basis = _independent_rows(np.vstack(parts))
        coefficients = [np.round(np.linalg.lstsq(basis.T, part.T, rcond=None)[0].T) for part in parts]
        if not all(np.array_equal(c @ basis, part) for c, part in zip(coefficients, parts)):
            raise AssertionError('a template table is not a small-integer combination of its rows')
        pair = (np.hstack(coefficients), basis)
        for array in pair:
            array.flags.writeable = False
        factored.append(pair)
    return tuple(factored)


def _independent_rows(rows: np.ndarray) -> np.ndarray:
    """
    Return the rows that each add a direction to the ones before them.

    Written out (Gram-Schmidt) to keep the first such rows: a pivoted QR's choice left fractional coefficients.
    """
    kept, directions = [], []
    for row in rows:
        residual = row - sum((direction @ row) * direction for direction in directions)
        norm = float(np.linalg.norm(residual))
        if norm > 1e-6 * max(float(np.linalg.norm(row)), 1.0):
            kept.append(row)
            directions.append(residual / norm)
    return np.ascontiguousarray(np.array(kept))


def _hypothesis_sums(x: np.ndarray, v: np.ndarray, k: np.ndarray, censored: np.ndarray, id_bits: int,
                     mixes: tuple[float, ...]) -> tuple[np.ndarray, ...]:
    """
    Return the weighted sums from which every (mix, shift, ID)'s bound is taken in closed form.

    The arguments of ``_bounds_from_sums`` and ``_sound_bounds_from_sums``: the chips' sums that no hypothesis
    changes, the mixes, and per (shift, ID) the sums (``_template_tables``) over the measured chips with s and n
    (weights t^i, i < 4, and x t^i, i < 2) and with s n and n^2 (t^i, i < 3), over the censored ones with their
    darkness d (every weight below), d n (those with s) and d n^2 (t^i, i < 3), and with s and n (t^i, i < 2),
    (rows, L, [s | n] of ids each) or (rows, L, ids).

    All hypotheses at once: every sum over the chips is a fold of the chips by packet position for each shift
    (``_folded``) times a table of every ID's signs (``_factored_tables``); the mixes are combined per hypothesis
    by the bounds.
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
    # The chip weights folded: measured chips' t^i (i < 4), x t^i (i < 2); censored ones' t^i (i < 5), x t^i
    # (i < 3), x^2.
    measured_fold = _folded(np.vstack([powers[:4] * vm, powers[:2] * (vm * x)]), k, length)
    censored_fold = _folded(np.vstack([powers * vc, powers[:3] * (vc * x), (vc * x * x)[None, :]]), k, length)
    signs, squares, dark, dark_neighbours, dark_squares = _factored_tables(id_bits)

    def times(fold: np.ndarray, table: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        coefficients, basis = table
        combined = (fold.reshape(-1, length) @ coefficients).reshape(-1, len(basis))
        return (combined @ basis).reshape(fold.shape[0], length, -1)

    return (fixed, np.asarray(mixes, dtype=float), times(measured_fold, signs), times(measured_fold[:3], squares),
            times(censored_fold, dark), times(censored_fold[[0, 1, 2, 3, 5, 6]], dark_neighbours),
            times(censored_fold[:3], dark_squares), times(censored_fold[:2], signs))


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
def _bounds_from_sums(fixed: np.ndarray, mixes: np.ndarray, measured_s: np.ndarray, measured_sn: np.ndarray,
                      censored_d: np.ndarray, censored_dn: np.ndarray, censored_dnn: np.ndarray,
                      censored_s: np.ndarray) -> np.ndarray:
    """
    Return every (shift, hypothesis)'s guide bound from its weighted sums (``_hypothesis_sums``), (L, mixes x ids).

    log Phi(u) <= -u^2 / 2 for u <= 0 (Chernoff) and <= 0: a censored chip costs at most its shortfall below
    its bound squared. The guide is the least-squares fit of the measured chips and of the censored chips
    the hypothesis makes dark (at their bound), with the censored chips it makes bright taken together: their
    summed squared shortfalls are at least the square of their summed shortfall over their summed weight
    (Jensen), one term that the fit can take in closed form. The contrast is left unconstrained. It bounds the
    hypotheses whose dark chips are not lifted over the ceiling, tightly; where blur lifts a dark censored chip
    over it, the fit lies above the guide (by up to 26 nats on the foreign drive frames), so the guide orders
    the fits and prunes the likelihood's far tail, and ``_sound_bounds_from_sums`` decides refusals.

    Columns 1, t, t^2 (envelope), T, t T (contrast) in the chip index t and the template T. The least-squares
    fit of the measured and dark censored chips (Gram matrix G = L L^T, right-hand side b), then the bright
    censored chips' summed shortfall h = c - a'theta (a, c: their summed weighted columns and bounds over the
    root of their summed weight), where positive, taken in: the fit with the term -h^2 / 2 loses
    h^2 / (2 (1 + a'G^-1 a)) (Sherman-Morrison), and its h stays positive, so the term is its own. A tiny ridge
    as in ``_solve``; a singular system bounds nothing (0). Written out without branches or inner loops, so
    that the loop over the hypotheses runs several at once (SIMD).
    """
    length, ids = censored_d.shape[1], censored_d.shape[2]
    out = np.empty((length, len(mixes) * ids))
    ridge = 1.0 + 1e-9
    for shift in range(length):
        # Hypothesis i is ID d of the mix's block of ``ids``; its sums with T, T^2, d T and d T^2
        # (``_template_tables``).
        for block in range(len(mixes)):
            mix = mixes[block]
            for d in range(ids):
                i = block * ids + d
                cd0, cd1, cd2 = censored_d[0, shift, d], censored_d[1, shift, d], censored_d[2, shift, d]
                g00 = (fixed[0] + cd0) * ridge + 1e-12
                g01 = fixed[1] + cd1
                g02 = fixed[2] + cd2
                g11 = (fixed[2] + cd2) * ridge + 1e-12
                g12 = fixed[3] + censored_d[3, shift, d]
                g22 = (fixed[4] + censored_d[4, shift, d]) * ridge + 1e-12
                # The dark censored chips' sums with T (rows t^0, t^1).
                dt0 = mix * censored_dn[0, shift, d] - cd0
                dt1 = mix * censored_dn[1, shift, d] - cd1
                g03 = measured_s[0, shift, d] + mix * measured_s[0, shift, ids + d] + dt0
                g13 = measured_s[1, shift, d] + mix * measured_s[1, shift, ids + d] + dt1
                g23 = measured_s[2, shift, d] + mix * measured_s[2, shift, ids + d] \
                    + mix * censored_dn[2, shift, d] - cd2
                g04, g14 = g13, g23
                g24 = measured_s[3, shift, d] + mix * measured_s[3, shift, ids + d] \
                    + mix * censored_dn[3, shift, d] - censored_d[3, shift, d]
                g33 = (fixed[0] + mix * (2.0 * measured_sn[0, shift, d] + mix * measured_sn[0, shift, ids + d])
                       + cd0 - mix * (2.0 * censored_dn[0, shift, d] - mix * censored_dnn[0, shift, d])) * ridge + 1e-12
                g34 = fixed[1] + mix * (2.0 * measured_sn[1, shift, d] + mix * measured_sn[1, shift, ids + d]) \
                    + cd1 - mix * (2.0 * censored_dn[1, shift, d] - mix * censored_dnn[1, shift, d])
                g44 = (fixed[2] + mix * (2.0 * measured_sn[2, shift, d] + mix * measured_sn[2, shift, ids + d])
                       + cd2 - mix * (2.0 * censored_dn[2, shift, d] - mix * censored_dnn[2, shift, d])) * ridge + 1e-12
                b0 = fixed[5] + censored_d[5, shift, d]
                b1 = fixed[6] + censored_d[6, shift, d]
                b2 = fixed[7] + censored_d[7, shift, d]
                b3 = measured_s[4, shift, d] + mix * measured_s[4, shift, ids + d] \
                    + mix * censored_dn[4, shift, d] - censored_d[5, shift, d]
                b4 = measured_s[5, shift, d] + mix * measured_s[5, shift, ids + d] \
                    + mix * censored_dn[5, shift, d] - censored_d[6, shift, d]
                a0, a1, a2 = fixed[9] - cd0, fixed[10] - cd1, fixed[11] - cd2
                a3 = censored_s[0, shift, d] + mix * censored_s[0, shift, ids + d] - dt0
                a4 = censored_s[1, shift, d] + mix * censored_s[1, shift, ids + d] - dt1
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
def _sound_bounds_from_sums(fixed: np.ndarray, mixes: np.ndarray, measured_s: np.ndarray,
                            measured_sn: np.ndarray, censored_d: np.ndarray, censored_dn: np.ndarray,
                            censored_dnn: np.ndarray, censored_s: np.ndarray) -> np.ndarray:
    """
    Return an upper bound of every (shift, hypothesis)'s maximised log-likelihood, (L, mixes x ids).

    log Phi(u) <= -max(-u, 0)^2 / 2 for every censored chip, bright or dark in the hypothesis. The censored chips
    it makes dark and those it makes bright form two groups, each of whose summed squared shortfalls is at least
    its summed shortfall, where positive, squared over its summed weight (Jensen, the shortfall being convex):
    the bound is the exact maximum of the measured chips' least squares minus those two one-sided terms. Its
    maximiser has one of four sets of active terms; the set whose solution is consistent (an active group's
    shortfall positive at it, an inactive one's not) gives the maximum (the problem is concave). Where rounding
    leaves none consistent, the measured chips' fit alone bounds. Columns, ridge and Cholesky as
    ``_bounds_from_sums``; the contrast unconstrained.
    """
    length, ids = censored_d.shape[1], censored_d.shape[2]
    out = np.empty((length, len(mixes) * ids))
    ridge = 1.0 + 1e-9
    g00, g01, g02 = fixed[0] * ridge + 1e-12, fixed[1], fixed[2]
    g11, g12, g22 = fixed[2] * ridge + 1e-12, fixed[3], fixed[4] * ridge + 1e-12
    all_weight = fixed[9]
    # The envelope's part of the factor is the same for every hypothesis.
    l00 = math.sqrt(g00)
    l10, l20 = g01 / l00, g02 / l00
    l11 = math.sqrt(g11 - l10 * l10)
    l21 = (g12 - l20 * l10) / l11
    l22 = math.sqrt(g22 - l20 * l20 - l21 * l21)
    y0 = fixed[5] / l00
    y1 = (fixed[6] - l10 * y0) / l11
    y2 = (fixed[7] - l20 * y0 - l21 * y1) / l22
    for shift in range(length):
        # Hypothesis i is ID d of the mix's block of ``ids``; its sums with T and T^2 as ``_bounds_from_sums``.
        for block in range(len(mixes)):
            mix = mixes[block]
            for d in range(ids):
                i = block * ids + d
                g03 = measured_s[0, shift, d] + mix * measured_s[0, shift, ids + d]
                g13 = measured_s[1, shift, d] + mix * measured_s[1, shift, ids + d]
                g23 = measured_s[2, shift, d] + mix * measured_s[2, shift, ids + d]
                g04, g14 = g13, g23
                g24 = measured_s[3, shift, d] + mix * measured_s[3, shift, ids + d]
                square0 = fixed[0] + mix * (2.0 * measured_sn[0, shift, d] + mix * measured_sn[0, shift, ids + d])
                square2 = fixed[2] + mix * (2.0 * measured_sn[2, shift, d] + mix * measured_sn[2, shift, ids + d])
                g33 = square0 * ridge + 1e-12
                g34 = fixed[1] + mix * (2.0 * measured_sn[1, shift, d] + mix * measured_sn[1, shift, ids + d])
                g44 = square2 * ridge + 1e-12
                b3 = measured_s[4, shift, d] + mix * measured_s[4, shift, ids + d]
                b4 = measured_s[5, shift, d] + mix * measured_s[5, shift, ids + d]
                l30, l40 = g03 / l00, g04 / l00
                l31, l41 = (g13 - l30 * l10) / l11, (g14 - l40 * l10) / l11
                l32, l42 = (g23 - l30 * l20 - l31 * l21) / l22, (g24 - l40 * l20 - l41 * l21) / l22
                l33 = math.sqrt(g33 - l30 * l30 - l31 * l31 - l32 * l32)
                l43 = (g34 - l40 * l30 - l41 * l31 - l42 * l32) / l33
                l44 = math.sqrt(g44 - l40 * l40 - l41 * l41 - l42 * l42 - l43 * l43)
                y3 = (b3 - l30 * y0 - l31 * y1 - l32 * y2) / l33
                y4 = (b4 - l40 * y0 - l41 * y1 - l42 * y2 - l43 * y3) / l44
                value = -0.5 * max(fixed[8] - (y0 * y0 + y1 * y1 + y2 * y2 + y3 * y3 + y4 * y4), 0.0)
                # The dark group's summed columns and bounds, then the bright one's (all censored chips less dark),
                # each over the root of its weight (none for a group of next to no weight: no term).
                dark_weight = censored_d[0, shift, d]
                bright_weight = all_weight - dark_weight
                dark_scale = 1.0 / math.sqrt(dark_weight) if dark_weight > 1e-9 * all_weight else 0.0
                bright_scale = 1.0 / math.sqrt(bright_weight) if bright_weight > 1e-9 * all_weight else 0.0
                a0, a1, a2 = dark_weight, censored_d[1, shift, d], censored_d[2, shift, d]
                a3 = mix * censored_dn[0, shift, d] - a0
                a4 = mix * censored_dn[1, shift, d] - a1
                c = censored_d[5, shift, d]
                # All censored chips' sums with T: the bright group's are these less the dark one's.
                censored_t0 = censored_s[0, shift, d] + mix * censored_s[0, shift, ids + d]
                censored_t1 = censored_s[1, shift, d] + mix * censored_s[1, shift, ids + d]
                # z = L^-1 a, and the shortfall at the measured chips' fit, h = c - a'theta = c - z'y.
                z0 = a0 * dark_scale / l00
                z1 = (a1 * dark_scale - l10 * z0) / l11
                z2 = (a2 * dark_scale - l20 * z0 - l21 * z1) / l22
                z3 = (a3 * dark_scale - l30 * z0 - l31 * z1 - l32 * z2) / l33
                z4 = (a4 * dark_scale - l40 * z0 - l41 * z1 - l42 * z2 - l43 * z3) / l44
                h0 = c * dark_scale - (z0 * y0 + z1 * y1 + z2 * y2 + z3 * y3 + z4 * y4)
                w0 = bright_weight * bright_scale / l00
                w1 = ((fixed[10] - a1) * bright_scale - l10 * w0) / l11
                w2 = ((fixed[11] - a2) * bright_scale - l20 * w0 - l21 * w1) / l22
                w3 = ((censored_t0 - a3) * bright_scale - l30 * w0 - l31 * w1 - l32 * w2) / l33
                w4 = ((censored_t1 - a4) * bright_scale - l40 * w0 - l41 * w1 - l42 * w2 - l43 * w3) / l44
                h1 = (fixed[12] - c) * bright_scale - (w0 * y0 + w1 * y1 + w2 * y2 + w3 * y3 + w4 * y4)
                bound = _with_one_sided_terms(value, z0 * z0 + z1 * z1 + z2 * z2 + z3 * z3 + z4 * z4,
                                              w0 * w0 + w1 * w1 + w2 * w2 + w3 * w3 + w4 * w4,
                                              z0 * w0 + z1 * w1 + z2 * w2 + z3 * w3 + z4 * w4, h0, h1)
                # A singular system (a NaN from a negative pivot) bounds nothing.
                out[shift, i] = bound if bound <= 0.0 else 0.0
    return out


@kernel
def _with_one_sided_terms(value: float, z00: float, z11: float, z01: float, h0: float, h1: float) -> float:
    """
    Return the maximum of a least squares (maximum ``value``) less two one-sided terms max(h_g, 0)^2 / 2.

    ``h0``, ``h1`` are the terms' arguments at the least squares' maximiser, ``z00``, ``z11``, ``z01`` the products
    of their gradients whitened by its factor (Z): with the terms in A active, the arguments at the maximiser are
    (I + Z_A)^-1 h_A and the value falls by h_A^T (I + Z_A)^-1 h_A / 2. The consistent active set's value; else
    ``value``.
    """
    if h0 <= 0.0 and h1 <= 0.0:
        return value
    # One term active: its argument shrinks by 1 + z'z, the other's moves by z0'z1 times the active one's.
    if h0 > 0.0:
        active = h0 / (1.0 + z00)
        if h1 - z01 * active <= 0.0:
            return value - 0.5 * h0 * active
    if h1 > 0.0:
        active = h1 / (1.0 + z11)
        if h0 - z01 * active <= 0.0:
            return value - 0.5 * h1 * active
    a, b, c = 1.0 + z00, z01, 1.0 + z11
    det = a * c - b * b
    if det > 0.0:
        lambda0, lambda1 = (c * h0 - b * h1) / det, (a * h1 - b * h0) / det
        if lambda0 > 0.0 and lambda1 > 0.0:
            return value - 0.5 * (h0 * lambda0 + h1 * lambda1)
    return value


@kernel
def _envelope_design(k: np.ndarray, n: int) -> np.ndarray:
    """Return the fit's design (n, 5) with its envelope columns 1, t, t^2 filled in (t: chip index to +-1)."""
    design = np.empty((n, _PARAMETERS))
    middle, half = 0.5 * (k[0] + k[-1]), max(0.5 * float(k[-1] - k[0]), 1.0)
    for j in range(n):
        t = (k[j] - middle) / half
        design[j, 0], design[j, 1], design[j, 2] = 1.0, t, t * t
    return design


@kernel
def _fits_that_can_win(bounds: np.ndarray, sums: tuple, x: np.ndarray, v: np.ndarray, k: np.ndarray,
                       censored: np.ndarray, signs: np.ndarray, packets: np.ndarray, mixes: np.ndarray, margin: float,
                       floor: float) -> tuple[np.ndarray, float]:
    """
    Return every (mix, shift, ID)'s maximised censored log-likelihood, (mixes, L, ids), where it can matter.

    And, for a window refused, an upper bound of the best (below ``floor``); else inf.

    Chip j's light is an envelope times (1 + contrast x its template s_p + mix (s_p-1 + s_p+1)), p = (k_j
    + shift) % L: the lamp's light (falloff, chords, glare) scales bright and dark chips alike, which is
    what decides where blur lifts a dark chip over the ceiling. Linear in its parameters: the envelope
    quadratic in the chip index, contrast-times-envelope linear in it and positive over the window (a
    bright chip is brighter).

    Newton's method (``_fit``) runs on the hypotheses in the order of their guide ``bounds``, until a bound falls
    ``margin`` below the best fit found: every later hypothesis keeps its bound. A window is refused when its best
    fit lies below ``floor``: when the first fit does, the hypotheses whose sound bounds (``_sound_bounds_from_sums``
    of ``sums``, ``_hypothesis_sums``) reach the floor are fitted first, in their order, until one fits over it;
    when none does, the window is refused without the rest (every other one lies below the floor).
    """
    n = len(x)
    out = bounds.copy()
    design = _envelope_design(k, n)
    root = np.sqrt(v)
    flat, fitted = bounds.ravel(), out.ravel()
    done = np.zeros(len(flat), dtype=np.bool_)
    first = int(np.argmax(flat))
    first_fit = _fit_hypothesis(first, design, x, v, root, k, censored, signs, mixes)
    fitted[first], done[first] = first_fit, True
    # Hypotheses of one mix and shift whose IDs agree on every packet position the window's templates read are
    # the same fit (IDs that differ only outside a window shorter than the packet): fitted once (``_fit_or_twin``).
    touched = _positions_read(k, signs.shape[1])
    if first_fit < floor:
        # As (mixes, L, ids), the order of the hypotheses' flat index.
        sound = _sound_bounds_from_sums(sums[0], sums[1], sums[2], sums[3], sums[4], sums[5], sums[6], sums[7])
        lifting = sound.reshape(bounds.shape[1], bounds.shape[0], bounds.shape[2]).transpose(1, 0, 2).copy().ravel()
        # The sound bounds' rounding (the ridge) is far below the slack.
        best = first_fit
        lift = np.flatnonzero(lifting >= floor - _SOUND_SLACK)
        keys, values = _twin_table(len(lift))
        for h in lift[np.argsort(-lifting[lift])]:
            if not done[h]:
                fitted[h], done[h] = _fit_or_twin(h, touched, packets, keys, values, design, x, v, root, k,
                                                  censored, signs, mixes), True
                best = max(best, fitted[h])
                if best >= floor:
                    break
        if best < floor:
            for h in range(len(flat)):
                if not done[h]:
                    best = max(best, lifting[h] + _SOUND_SLACK)
            return out, best
    # Only the hypotheses whose bounds come within the margin of the first fit can be fitted, so only those are
    # sorted (a sort of all 18432 of 8 bits took longer than their fits).
    best = first_fit
    reach = np.flatnonzero(flat >= best - margin)
    keys, values = _twin_table(len(reach))
    for h in reach[np.argsort(-flat[reach])]:
        if flat[h] < best - margin:
            break
        if not done[h]:
            fitted[h], done[h] = _fit_or_twin(h, touched, packets, keys, values, design, x, v, root, k, censored,
                                              signs, mixes), True
        best = max(best, fitted[h])
    return out, math.inf


@kernel
def _twin_table(hypotheses: int) -> tuple[np.ndarray, np.ndarray]:
    """Return an empty open-addressing table (keys -1, values) for ``hypotheses`` fits: at least twice the slots."""
    slots = 1 << int(math.ceil(math.log2(2 * hypotheses + 2)))
    return np.full(slots, -1, dtype=np.int64), np.empty(slots)


@kernel
def _positions_read(k: np.ndarray, length: int) -> np.ndarray:
    """
    Return, per shift, the packet positions the window's templates read as a bit mask, (2, L) int64.

    Row 0 without blur's mix (the chips' own positions), row 1 with it (their neighbours too).
    """
    touched = np.zeros((2, length), dtype=np.int64)
    for shift in range(length):
        for j in range(len(k)):
            p = (k[j] + shift) % length
            touched[0, shift] |= np.int64(1) << p
            touched[1, shift] |= (np.int64(1) << p) | (np.int64(1) << ((p - 1) % length)) \
                | (np.int64(1) << ((p + 1) % length))
    return touched


@kernel
def _fit_or_twin(h: int, touched: np.ndarray, packets: np.ndarray, keys: np.ndarray, values: np.ndarray,
                 design: np.ndarray, x: np.ndarray, v: np.ndarray, root: np.ndarray, k: np.ndarray,
                 censored: np.ndarray, signs: np.ndarray, mixes: np.ndarray) -> float:
    """
    Return hypothesis ``h``'s fit (``_fit_hypothesis``), or its twin's from the table ``keys``, ``values``.

    ``packets`` are the IDs' chips as bit masks, ``touched`` the positions read (``_positions_read``): the table
    is keyed by (mix, shift, the ID's chips there).
    """
    ids, length = signs.shape[0], signs.shape[1]
    m, rest = h // (length * ids), h % (length * ids)
    shift, i = rest // ids, rest % ids
    chips = packets[i] & touched[0 if mixes[m] == 0.0 else 1, shift]
    key = (chips * length + shift) * len(mixes) + m
    slot = (key * np.int64(0x2545F4914F6CDD1D)) >> np.int64(17) & (len(keys) - 1)
    while keys[slot] >= 0:
        if keys[slot] == key:
            return values[slot]
        slot = (slot + 1) & (len(keys) - 1)
    value = _fit_hypothesis(h, design, x, v, root, k, censored, signs, mixes)
    keys[slot], values[slot] = key, value
    return value


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
    that do not raise the log-likelihood; the contrast is kept positive (``_positive_contrast``). The chips' means
    and censored terms at the accepted parameters are kept from their log-likelihood for the next step's slopes
    (erfc and its log are most of a fit's time).
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
    # Rows: the means and the censored chips' log Phi at theta, then at the trial.
    kept, tried = np.empty((2, n)), np.empty((2, n))
    best = _log_likelihood(design, x, v, root, censored, theta, kept)
    trial = np.empty(size)
    for _ in range(_NEWTON_STEPS):
        gradient[:] = 0.0
        hessian[:, :] = 0.0
        for j in range(n):
            mu = kept[0, j]
            if censored[j]:
                u = root[j] * (mu - x[j])
                ratio = math.exp(-0.5 * u * u - _LOG_SQRT_2PI - kept[1, j])
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
            value = _log_likelihood(design, x, v, root, censored, trial, tried)
            if value > best:
                gained = True
                break
            scale *= 0.5
        if not gained:
            break
        improvement = value - best
        theta[:] = trial
        kept[:, :] = tried
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
                    theta: np.ndarray, terms: np.ndarray) -> float:
    """Return the censored log-likelihood at ``theta``; ``terms`` gets each chip's mean and censored log Phi."""
    total = 0.0
    for j in range(len(x)):
        mu = 0.0
        for a in range(len(theta)):
            mu += design[j, a] * theta[a]
        terms[0, j] = mu
        if censored[j]:
            terms[1, j] = _log_normal_cdf(root[j] * (mu - x[j]))
            total += terms[1, j]
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
