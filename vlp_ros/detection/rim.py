"""
Sub-pixel points on a lamp's true disc edge, and the ellipse through them.

A rolling shutter gives every row of the lamp one brightness, so the left and
right ends of each lit row are true disc edges while the tops and bottoms of the
stripes are not. Each row is normalised on its own: the edge is where the row
crosses half-way between the background and that row's plateau inside the
disc, which neither the modulation nor a straight edge's symmetric blur can
move. A curved edge's can: blur pulls the half level of a convex disc inward
by kappa s^2 / 2 (``blur_shifts``). A clipped row's plateau is not its
brightness, so its crossing lies outside the edge: ``clipped_edge_offset``
measures by how much.

The per-row loops (crossings, normals, the fit's outlier rounds) are compiled
kernels (``vlp_ros.compiled``): a lamp has a few hundred rim points, on which
numpy's per-call cost exceeds the arithmetic.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from typing import NamedTuple

import numpy as np
from scipy.special import ndtri

from vlp_ros.compiled import kernel
from vlp_ros.compiled.small_arrays import median
from vlp_ros.core.ellipse import conic_of, distances, fit_error, fit_points, geometric_distances, OK
from vlp_ros.detection.rows import chords, RowLevels

# Robust (MAD) standard deviation of a normal distribution.
_MAD_TO_SIGMA = 1.4826
_ELLIPSE_PARAMETERS = 5
# Clipped rows pooled to measure how far their crossings lie outside the edge.
_MAX_POOLED_ROWS = 200
# Ramp pixels within this (of the row's step) of background or plateau give probits
# too noisy to measure the blur with.
_PROBIT_MARGIN = 0.03
_MIN_BLUR_ROWS = 10
# The bands (in blurs from the edge) whose levels are followed back to it; from 3 blurs on, blur
# mixes in under 0.2 % of the other side.
_EDGE_BANDS = (3.0, 4.0)
_MIN_EDGE_ROWS = 10
# Rows meeting the edge at a grazing angle (|n_x| below this) reach too far along the row for the bands.
_MIN_ACROSS = 0.3
# The 99.9 % point of chi-square with 2 degrees of freedom, for the line against a uniform disc's
# (0.5, 0); the per-side values of neighbouring rows are alike (stripes, blur), which counts each
# of them as about this many.
_UNIFORM_CHI_SQUARE = 13.8
_EDGE_CORRELATION = 4.0
# A fraction outside these says the ramps are not an edge between two levels (discs under the
# simulator's looks, glare and falloff included: 0.33-0.55; bare LEDs with glow reach 0.25 and 0.75).
_FRACTION_BOUNDS = (0.25, 0.75)


@dataclass(frozen=True)
class RimFit:
    """
    The ellipse through the kept rim points, and how well and how blurred the rim was seen.

    It holds their RMS distance across the edge (px), how many points were left after grazing rows were
    dropped (before outlier rejection), and the prior sigma (px) of the smooth patterns round the rim by
    which the edge may depart from the model's (``edge_model_sigma``; 0 where the ramps do not tell the
    blur), and the edge's blur sigma (px) that the ramps measured (None where they do not tell).
    """

    ellipse: np.ndarray
    points: np.ndarray
    sigma: float
    candidates: int
    model_sigma: float = 0.0
    blur: float | None = None


def row_crossings(brightness: np.ndarray, levels: RowLevels, background: float,
                  reach: int, fraction: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """
    Return the left and right crossings of every row at ``fraction`` of the way from background to its plateau.

    There is one ``fraction`` per row of ``levels`` (None: a half); the crossings are points (N, 2) in
    the array's pixels.

    Returns the points and each one's row plateau. ``reach`` bounds how far inside
    the first pixel above threshold the crossing may lie. Rows whose edge leaves the
    array give no point.
    """
    return _crossings(brightness, levels.rows, levels.first, levels.last, levels.plateau, float(background),
                      int(reach), np.full(levels.rows.size, 0.5) if fraction is None
                      else np.asarray(fraction, dtype=float))


@kernel
def _crossings(brightness: np.ndarray, rows: np.ndarray, first: np.ndarray, last: np.ndarray,
               plateau: np.ndarray, background: float, reach: int,
               fraction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``row_crossings``: left crossings in row order, then right ones."""
    width = brightness.shape[1]
    points = np.empty((2 * rows.size, 2))
    plateaus = np.empty(2 * rows.size)
    count = 0
    for side in range(2):
        direction = 1 if side == 0 else -1
        for i in range(rows.size):
            half = background + fraction[i] * (plateau[i] - background)
            start = first[i] if side == 0 else last[i]
            # Steps -1 .. reach from the first pixel above threshold; outside the array counts as
            # bright, so a clipped edge yields no crossing.
            outer = 0.0
            for k in range(reach + 2):
                col = start + direction * (k - 1)
                value = float(brightness[rows[i], col]) if 0 <= col < width else np.inf
                if value >= half:
                    if k > 0:
                        points[count, 0] = start + direction * (k - 2) + direction * ((half - outer) / (value - outer))
                        points[count, 1] = float(rows[i])
                        plateaus[count] = plateau[i]
                        count += 1
                    break
                outer = value
    return points[:count], plateaus[:count]


def outward_normals(ellipse: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Return unit normals (N, 2) of the ellipse's level curves at ``points``, pointing outward."""
    return _normals(conic_of(np.asarray(ellipse, dtype=float)), np.ascontiguousarray(points, dtype=float))


@kernel
def _normals(conic: np.ndarray, points: np.ndarray) -> np.ndarray:
    normals = np.empty((points.shape[0], 2))
    for i in range(points.shape[0]):
        gx = points[i, 0] * conic[0, 0] + points[i, 1] * conic[1, 0] + conic[2, 0]
        gy = points[i, 0] * conic[0, 1] + points[i, 1] * conic[1, 1] + conic[2, 1]
        norm = max(math.sqrt(gx * gx + gy * gy), 1e-12)
        normals[i, 0], normals[i, 1] = gx / norm, gy / norm
    return normals


def clipped_edge_offset(brightness: np.ndarray, points: np.ndarray, ellipse: np.ndarray, background: float,
                        saturation_level: float, max_blur: float) -> tuple[float, float] | None:
    """
    (edge, overexposure).

    How far (px) inside ``ellipse``, fitted to half-clip crossings of clipped rows, the
    true edge lies, and the rows' level over the clip level.

    A clipped row's plateau is not its brightness A, so its half level sits low on
    the blurred edge, outside the true edge. The rows' ramps, pooled in distance t
    across the ellipse, show the unclipped foot of B + A Phi((-edge - t) / sigma), the
    pixel's square folded into sigma; fitting A, sigma and the edge to it (clipped
    pixels as censored: the model must reach the clip; ``_censored_edge_fit``) places the edge. Only rows
    inside clipped stripes (clipped two rows up and down) are pooled, so that they
    share one A. None if the ramps do not tell.
    """
    height, width = brightness.shape
    rows = points[:, 1].astype(int)
    centre_col = int(np.clip(np.rint(ellipse[0]), 0, width - 1))
    interior = ((brightness[np.clip(rows + 2, 0, height - 1), centre_col] >= saturation_level)
                & (brightness[np.clip(rows - 2, 0, height - 1), centre_col] >= saturation_level))
    points = points[interior][:_MAX_POOLED_ROWS]
    if len(points) < 3:
        return None
    normals = outward_normals(ellipse, points)
    reach = int(np.ceil(4.0 * max_blur / max(np.abs(normals[:, 0]).min(), 0.3))) + 1
    cols = np.rint(points[:, 0])[:, None] + np.sign(normals[:, 0])[:, None] * np.arange(-3, reach + 1)[None, :]
    rows = np.broadcast_to(points[:, 1:2], cols.shape)
    keep = (cols >= 0) & (cols < width)
    pixels = np.column_stack([cols[keep], rows[keep]])
    values = brightness[pixels[:, 1].astype(int), pixels[:, 0].astype(int)].astype(float)
    # Clipped pixels only say the light reached the clip level (a censored observation).
    censored = values >= saturation_level - 1
    if np.count_nonzero(~censored) < 10:
        return None
    t = geometric_distances(ellipse, pixels)
    clip = saturation_level - background
    fitted, amplitude, edge = _censored_edge_fit(np.ascontiguousarray(t), values - background, censored, clip,
                                                 float(max_blur))
    if not fitted:
        return None
    return float(edge), float(amplitude / clip)


# The pixel's square seen across an edge of any direction has the variance 1/12 (px^2) of a unit uniform
# spread; the fit folds it into the blur as a Gaussian of that variance.
_PIXEL_VARIANCE = 1.0 / 12.0
_EDGE_FIT_ITERATIONS = 60
# A lamp brighter than this over the clip level is too overexposed for any edge (the detector refuses 2.5):
# the fit stops there instead of following the amplitude out.
_MAX_FITTED_OVEREXPOSURE = 4.0


@kernel
def _censored_edge_fit(t: np.ndarray, v: np.ndarray, censored: np.ndarray, clip: float,
                       max_blur: float) -> tuple[bool, float, float]:
    """
    Return (converged, amplitude, edge) of ``clipped_edge_offset``'s ramp model, fitted by Levenberg-Marquardt.

    The model is v = A Phi((-edge - t) / S), S^2 = s^2 + ``_PIXEL_VARIANCE``, with its analytic
    Jacobian; censored values count only where the model stays below them. Bounds: A in ``clip`` to
    ``_MAX_FITTED_OVEREXPOSURE`` clips, s in [0.2, 2 max_blur], edge in [-1, 4 max_blur], kept by projecting
    each step onto them.
    """
    lower = np.array([clip, 0.2, -1.0])
    upper = np.array([_MAX_FITTED_OVEREXPOSURE * clip, 2.0 * max_blur, 4.0 * max_blur])
    params = np.array([2.0 * clip, 0.5 * max_blur, 0.5])
    n = t.size
    residual, jacobian = np.empty(n), np.empty((n, 3))
    cost = _edge_model(params, t, v, censored, residual, jacobian)
    damping = 1e-3
    converged = False
    for _ in range(_EDGE_FIT_ITERATIONS):
        normal = jacobian.T @ jacobian
        gradient = jacobian.T @ residual
        trial = np.empty(3)
        improved = False
        while damping < 1e10:
            damped = normal.copy()
            for k in range(3):
                damped[k, k] += damping * max(normal[k, k], 1e-12)
            step = np.linalg.solve(damped, -gradient)
            for k in range(3):
                trial[k] = min(max(params[k] + step[k], lower[k]), upper[k])
            trial_residual, trial_jacobian = np.empty(n), np.empty((n, 3))
            trial_cost = _edge_model(trial, t, v, censored, trial_residual, trial_jacobian)
            if trial_cost <= cost:
                improved = True
                break
            damping *= 10.0
        if not improved:
            converged = True
            break
        change = 0.0
        for k in range(3):
            change = max(change, abs(trial[k] - params[k]) / (abs(params[k]) + 1e-3))
        relative = (cost - trial_cost) / max(cost, 1e-300)
        params, cost, residual, jacobian = trial, trial_cost, trial_residual, trial_jacobian
        damping = max(damping / 10.0, 1e-12)
        if change < 1e-8 or relative < 1e-12:
            converged = True
            break
    return converged, params[0], params[2]


@kernel
def _edge_model(params: np.ndarray, t: np.ndarray, v: np.ndarray, censored: np.ndarray, residual: np.ndarray,
                jacobian: np.ndarray) -> float:
    """``_censored_edge_fit``'s residuals and Jacobian (into the arrays) at ``params``; returns half their squares."""
    amplitude, blur, edge = params[0], params[1], params[2]
    spread = math.sqrt(blur * blur + _PIXEL_VARIANCE)
    cost = 0.0
    for i in range(t.size):
        z = (-edge - t[i]) / spread
        below = 0.5 * math.erfc(-z / math.sqrt(2.0))
        density = math.exp(-0.5 * z * z) / math.sqrt(2.0 * math.pi)
        difference = amplitude * below - v[i]
        if censored[i] and difference > 0.0:
            residual[i] = 0.0
            jacobian[i, 0] = jacobian[i, 1] = jacobian[i, 2] = 0.0
            continue
        residual[i] = difference
        jacobian[i, 0] = below
        jacobian[i, 1] = -amplitude * density * z * blur / (spread * spread)
        jacobian[i, 2] = -amplitude * density / spread
        cost += 0.5 * difference * difference
    return cost


def blur_variance(brightness: np.ndarray, points: np.ndarray, plateaus: np.ndarray, background: float,
                  ellipse: np.ndarray) -> float | None:
    """
    Return the variance (px^2) across the edge of the blur it went through; None if too few rows tell.

    The blur is optics and pixel area together, measured from the ramps of unclipped rows at their
    crossings ``points``.

    A Gaussian-blurred edge with unit normal n reads Phi(+-(edge - x) |n_x| / s) along
    a row, so the probits of the two pixels around the crossing differ by |n_x| / s.
    The pixel's square adds its variance 1/12 along every direction, as a Gaussian
    of that variance would.
    """
    left, right, across = _ramps(brightness, points, plateaus, float(background),
                                 conic_of(np.asarray(ellipse, dtype=float)))
    if len(left) < _MIN_BLUR_ROWS:
        return None
    # Two pixels at the same level show no slope: that row's blur is unbounded (inf), which
    # the median weighs as a very soft edge instead of dividing by zero.
    gap = np.abs(ndtri(right) - ndtri(left))
    sigma = np.divide(across, gap, out=np.full_like(gap, np.inf), where=gap > 0.0)
    return median(sigma) ** 2


@kernel
def _ramps(brightness: np.ndarray, points: np.ndarray, plateaus: np.ndarray, background: float,
           conic: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """
    Of the crossings whose two pixels both lie on the ramp.

    Their levels (0 background, 1 plateau) and |n_x| of the edge's normal.
    """
    n = points.shape[0]
    left, right, across = np.empty(n), np.empty(n), np.empty(n)
    count = 0
    normals = _normals(conic, points)
    for i in range(n):
        col, row = int(math.floor(points[i, 0])), int(points[i, 1])
        if not (col >= 0 and col + 1 < brightness.shape[1] and plateaus[i] > background):
            continue
        step = plateaus[i] - background
        low = (brightness[row, col] - background) / step
        high = (brightness[row, col + 1] - background) / step
        if min(low, high) > _PROBIT_MARGIN and max(low, high) < 1.0 - _PROBIT_MARGIN:
            left[count], right[count], across[count] = low, high, abs(normals[i, 0])
            count += 1
    return left[:count], right[:count], across[:count]


@dataclass(frozen=True)
class EdgeLevel:
    """
    ``edge_level_fraction``'s answer.

    The fraction per row, and ``departure`` (px): how far the rows' crossings may still lie off the
    disc's edge for the light's departure from a uniform disc on a dark ceiling
    (``edge_departure``).
    """

    fraction: np.ndarray
    departure: float = 0.0


def edge_level_fraction(brightness: np.ndarray, levels: RowLevels, background: float, ellipse: np.ndarray,
                        blur: float) -> EdgeLevel | None:
    """
    Where between background and each row's plateau the disc's edge lies.

    The step's midpoint, as a fraction of the row's rise (0.5 for a uniform disc on a dark ceiling),
    per row of ``levels``; None when it leaves ``_FRACTION_BOUNDS`` (the light is no disc on a
    ceiling: a bare LED's glow).

    A diffuser brighter in the middle puts the plateau (read in the chord's middle)
    above the disc's level at its edge, and a glare halo lifts the ceiling next to it:
    half of the plateau then lies inside the edge, by 0.7 px at 2 px of blur for a 30 %
    falloff with a 20 % halo. On each side of every row the levels inside and outside
    the edge are read in two bands (``_EDGE_BANDS`` blurs from it, where blur no longer
    mixes them) and followed in a straight line back to the edge; their midpoint over
    the row's rise is that side's fraction. Falloff and halo are round about the lamp,
    so the fraction depends on where the row's plateau was read: it is fitted (robustly)
    as a straight line in the squared normalised radius of the chord's middle, which
    averages the bands' noise over all rows instead of adding it to each rim point.
    """
    ellipse = np.asarray(ellipse, dtype=float)
    plateau_of = np.full(brightness.shape[0], np.nan)
    plateau_of[levels.rows] = levels.plateau
    radius, fractions, lifts = _edge_fractions(brightness, levels.rows, plateau_of, float(background),
                                               conic_of(ellipse), ellipse, float(blur))
    if fractions.size < _MIN_EDGE_ROWS:
        return EdgeLevel(np.full(levels.rows.size, 0.5))
    departs, intercept, slope = _fraction_line(radius, fractions)
    departure = edge_departure(blur, median(fractions), median(lifts), departs)
    if not departs:
        return EdgeLevel(np.full(levels.rows.size, 0.5), departure)
    row_radius = _chord_middle_radius(levels.rows, conic_of(ellipse), ellipse)
    fraction = intercept + slope * row_radius
    if fraction.min() < _FRACTION_BOUNDS[0] or fraction.max() > _FRACTION_BOUNDS[1]:
        return None
    return EdgeLevel(fraction, departure)


# A share q of the row's rise added to one side of a step blurred by s moves its half-level crossing by
# s Phi^-1(1/2 + q / 2), about sqrt(2 pi) s q / 2 for small q.
_CROSSING_PER_LEVEL = math.sqrt(2.0 * math.pi)
# Of a departure that ``edge_level_fraction`` corrects, the share left in smooth patterns round the rim:
# on the simulator's sharp 4K discs under 30 % falloff (fraction 0.37-0.40, 0.25-0.38 px corrected),
# 0.01-0.03 px of offset and 0.01-0.045 px of second harmonic at the true pose.
CORRECTED_DEPARTURE_SHARE = 0.08
UNCORRECTED_LIFT_SHARE = 0.35


def edge_departure(blur: float, level: float, lift: float, corrected: bool) -> float:
    """
    Return how far a lamp's crossings may lie off its edge for what the light shows of its departure.

    The distance is in px, one sigma per smooth pattern round the rim, for what the light shows of its
    departure from a uniform disc on a dark ceiling, given the edge's ``blur`` (px), the median ``level``
    of the edge's midpoint over the row's rise (0.5 uniform), the median ``lift`` of the ceiling next to
    the edge over the rise (0 dark), and whether the crossings were ``corrected`` to the measured level.

    A glare halo lifts the ceiling beside the edge and the disc inside it alike, which moves the step's
    midpoint little but its level on either side, and the halo's slope and its stripes move each row's
    crossing differently: on the simulator's sharp 4K discs under a 20 % halo (lift 0.04-0.08), 0.02-0.06 px
    of offset and up to 0.06 px of second harmonic, with the level indistinguishable from a half (0.51-0.53
    against 0.49-0.51 clean) and so left uncorrected. Uncorrected, half the lift counts whole; a
    level the crossings were corrected to leaves ``CORRECTED_DEPARTURE_SHARE`` of its move. A uniform disc on
    a dark ceiling (lift 0, the level not told from a half) gives 0.
    """
    moved = CORRECTED_DEPARTURE_SHARE * abs(level - 0.5) if corrected else 0.0
    return _CROSSING_PER_LEVEL * blur * max(UNCORRECTED_LIFT_SHARE * max(lift, 0.0), moved)


@kernel
def _fraction_line(radius: np.ndarray, fractions: np.ndarray) -> tuple[bool, float, float]:
    """
    ``edge_level_fraction``'s robust line of the fractions in the radius.

    (whether it departs from a uniform disc's (0.5, 0), intercept, slope), three rounds of least squares
    each dropping the values over 3 robust sigmas off; no departure when fewer than ``_MIN_EDGE_ROWS``
    values remain.

    A uniform disc on a dark ceiling has its edge at half of every row's rise; unless the rows tell
    otherwise beyond doubt, that stays exact: the line's own noise would move all rim points alike.
    (Compiled: in numpy, np.linalg.lstsq and the rounds' small array calls cost 0.1-0.4 ms a lamp.)
    """
    n = fractions.size
    kept = np.ones(n, np.bool_)
    deviation = np.empty(n)
    intercept = slope = 0.0
    count = n
    for _ in range(3):
        intercept, slope = _least_squares_line(radius, fractions, kept)
        for i in range(n):
            deviation[i] = abs(fractions[i] - (intercept + slope * radius[i]))
        scale = max(_MAD_TO_SIGMA * median(deviation[kept]), 1e-3)
        count = 0
        for i in range(n):
            kept[i] = deviation[i] <= 3.0 * scale
            count += kept[i]
        if count < _MIN_EDGE_ROWS:
            return False, 0.5, 0.0
    # The line's deviation from (0.5, 0) weighed by the normal matrix [[n, sum x], [sum x, sum x^2]],
    # against the residuals' variance.
    squares = total_x = total_xx = 0.0
    for i in range(n):
        if kept[i]:
            residual = fractions[i] - (intercept + slope * radius[i])
            squares += residual * residual
            total_x += radius[i]
            total_xx += radius[i] * radius[i]
    variance = squares / max(count - 2, 1)
    offset = intercept - 0.5
    chi_square = offset * offset * count + 2.0 * offset * slope * total_x + slope * slope * total_xx
    return not chi_square < _UNIFORM_CHI_SQUARE * _EDGE_CORRELATION * variance, intercept, slope


@kernel
def _least_squares_line(x: np.ndarray, y: np.ndarray, kept: np.ndarray) -> tuple[float, float]:
    """
    Return (intercept, slope) of the least-squares line through the ``kept`` points (x, y).

    It is np.linalg.lstsq's: when all their x are equal, as for a shape that is no disc, the smallest
    such line.
    """
    count = centre_x = centre_y = 0.0
    for i in range(x.size):
        if kept[i]:
            count += 1.0
            centre_x += x[i]
            centre_y += y[i]
    centre_x, centre_y = centre_x / count, centre_y / count
    spread = covariance = 0.0
    for i in range(x.size):
        if kept[i]:
            spread += (x[i] - centre_x) * (x[i] - centre_x)
            covariance += (x[i] - centre_x) * (y[i] - centre_y)
    if not spread > 0.0:
        scale = centre_y / (1.0 + centre_x * centre_x)
        return scale, scale * centre_x
    slope = covariance / spread
    return centre_y - slope * centre_x, slope


@kernel
def _chord_middle_radius(rows: np.ndarray, conic: np.ndarray, ellipse: np.ndarray) -> np.ndarray:
    """(r / R)^2 in the ellipse's own frame at the middle of each row's chord (1 where it misses)."""
    left, right, crossed = chords(conic, rows.astype(np.float64))
    cx, cy, a, b, theta = ellipse[0], ellipse[1], ellipse[2], ellipse[3], ellipse[4]
    c, s = math.cos(theta), math.sin(theta)
    radius = np.ones(rows.size)
    for i in range(rows.size):
        if crossed[i]:
            dx, dy = 0.5 * (left[i] + right[i]) - cx, rows[i] - cy
            u, v = (dx * c + dy * s) / a, (-dx * s + dy * c) / b
            radius[i] = u * u + v * v
    return radius


@kernel
def _edge_fractions(brightness: np.ndarray, rows: np.ndarray, plateau_of: np.ndarray, background: float,
                    conic: np.ndarray, ellipse: np.ndarray, blur: float) -> tuple[np.ndarray, np.ndarray]:
    """
    Return ``edge_level_fraction``'s per-side values, with their rows' ``_chord_middle_radius`` and the ceiling's level.

    The ceiling's level is that next to the edge (its outer band traced back to it) over the row's rise.
    """
    middle = _chord_middle_radius(rows, conic, ellipse)
    width = brightness.shape[1]
    left, right, crossed = chords(conic, rows.astype(np.float64))
    near, far = _EDGE_BANDS[0] * blur, _EDGE_BANDS[1] * blur
    values, radius, lifts = np.empty(2 * rows.size), np.empty(2 * rows.size), np.empty(2 * rows.size)
    count = 0
    for i in range(rows.size):
        rise = plateau_of[rows[i]] - background
        if not (crossed[i] and rise > 0.0):
            continue
        for side in range(2):
            edge = left[i] if side == 0 else right[i]
            inward = 1.0 if side == 0 else -1.0
            gx = edge * conic[0, 0] + rows[i] * conic[1, 0] + conic[2, 0]
            gy = edge * conic[0, 1] + rows[i] * conic[1, 1] + conic[2, 1]
            across = abs(gx) / max(math.sqrt(gx * gx + gy * gy), 1e-12)
            # Both bands inside must lie in the near half of the chord.
            if across < _MIN_ACROSS or (2.0 * far - near) / across > 0.5 * (right[i] - left[i]):
                continue
            found_1, inside_1, outside_1 = _band_levels(brightness, rows[i], edge, inward, near / across,
                                                        far / across, width)
            found_2, inside_2, outside_2 = _band_levels(brightness, rows[i], edge, inward, far / across,
                                                        (2.0 * far - near) / across, width)
            if not (found_1 and found_2):
                continue
            # Band centres at c and c + (far - near) blurs: a straight line back to the edge.
            back = 0.5 * (near + far) / (far - near)
            inside = inside_1 - (inside_2 - inside_1) * back
            outside = outside_1 - (outside_2 - outside_1) * back
            values[count] = (0.5 * (inside + outside) - background) / rise
            lifts[count] = (outside - background) / rise
            radius[count] = middle[i]
            count += 1
    return radius[:count], values[:count], lifts[:count]


@kernel
def _band_levels(brightness: np.ndarray, row: int, edge: float, inward: float, lo: float, hi: float,
                 width: int) -> tuple[bool, float, float]:
    """
    Return (in the array, mean inside, mean outside) of the pixels ``lo`` to ``hi`` px along the row from ``edge``.

    The pixels are taken inward and outward (at least one pixel each).
    """
    start, end = math.ceil(lo), max(math.floor(hi), math.ceil(lo))
    inside = outside = 0.0
    for k in range(start, end + 1):
        inner, outer = int(round(edge + inward * k)), int(round(edge - inward * k))
        if not (0 <= inner < width and 0 <= outer < width):
            return False, 0.0, 0.0
        inside += brightness[row, inner]
        outside += brightness[row, outer]
    count = end - start + 1
    return True, inside / count, outside / count


# A rim's smooth error patterns: none below a blur of ``SHARP_BLUR_PX`` (the simulator's clean 4K look
# and the independent renderer's clean drive, 0.72-0.86 px with the pixel, fit within 0.01 px and
# 0.13 px), then ``EDGE_MODEL_PER_BLUR_VARIANCE`` px per px^2 of blur variance beyond it (0.4-0.75 px for
# the 2.1-2.5 px of that renderer's soft hand-held rims, measured there at 0.1-0.45 px offset and
# 0.2-0.9 px second harmonic).
SHARP_BLUR_PX = 1.0
EDGE_MODEL_PER_BLUR_VARIANCE = 0.15


def edge_model_sigma(blur_variance_px2: float, departure_px: float = 0.0) -> float:
    """
    Return how far the half-level crossings of a blurred edge may depart from the disc's edge.

    The distance is in px, one sigma per mode, in smooth patterns round the rim (an offset and the first
    two harmonics: ``measurement.rim_error_modes``), given the edge's blur variance and what the light
    shows of its departure from a uniform disc (``edge_departure``): the larger of the two, as a sharp
    edge's crossings, which the blur term leaves exact, still move with glare and falloff.

    Any departure of the light from a uniform disc with a step edge moves the crossing of a
    blurred edge by the blur variance times the light's relative change across it: a diffuser's
    falloff or a glare halo (its slope over the row's rise), the stripes of neighbouring rows
    that blur mixes into a row's ends differently than into its middle (the edge's slope times
    the stripes' relative slope), a blur that is no Gaussian. The detector's corrections for
    these (``blur_shifts``, ``edge_level_fraction``) hold while the blur stays within a pixel;
    beyond it what they leave grows with the variance.
    """
    return max(EDGE_MODEL_PER_BLUR_VARIANCE * max(blur_variance_px2 - SHARP_BLUR_PX ** 2, 0.0), departure_px)


def blur_shifts(ellipse: np.ndarray, points: np.ndarray, variance: float) -> np.ndarray:
    """
    Return moves (N, 2) that put half-level crossings of a blurred disc back on its edge.

    Blur of variance s^2 along the edge's tangent bends it by kappa t^2 / 2 over the
    kernel's reach (kappa the curvature), so less than half the kernel lies inside a
    convex edge at the edge itself: the half level lies kappa s^2 / 2 inside it (0.3 px
    over the radius in px for a 0.7 px optics blur). It has the same sign at every rim
    point, so it shrinks the fitted ellipse: by twice the size's own standard deviation
    (0.0045 px against 0.0023 px) for a 4K lamp 2 m away.
    """
    return _shifts(np.asarray(ellipse, dtype=float), np.ascontiguousarray(points, dtype=float), float(variance))


@kernel
def _shifts(ellipse: np.ndarray, points: np.ndarray, variance: float) -> np.ndarray:
    cx, cy, a, b, theta = ellipse[0], ellipse[1], ellipse[2], ellipse[3], ellipse[4]
    c, s = math.cos(theta), math.sin(theta)
    shifts = _normals(conic_of(ellipse), points)
    for i in range(points.shape[0]):
        dx, dy = points[i, 0] - cx, points[i, 1] - cy
        # The curvature of the ellipse at the parameter angle t of the point.
        t = math.atan2((dx * -s + dy * c) / b, (dx * c + dy * s) / a)
        curvature = a * b / (a * a * math.sin(t) ** 2 + b * b * math.cos(t) ** 2) ** 1.5
        shifts[i, 0] *= 0.5 * variance * curvature
        shifts[i, 1] *= 0.5 * variance * curvature
    return shifts


@kernel
def edge_slopes(conic: np.ndarray, points: np.ndarray) -> np.ndarray:
    """
    Return |dx/dy| of the edge of the ellipse ``conic`` (3x3) near each point.

    It is large where a row meets the edge at a grazing angle.
    """
    slopes = np.empty(points.shape[0])
    for i in range(points.shape[0]):
        gx = points[i, 0] * conic[0, 0] + points[i, 1] * conic[1, 0] + conic[2, 0]
        gy = points[i, 0] * conic[0, 1] + points[i, 1] * conic[1, 1] + conic[2, 1]
        slopes[i] = abs(gy) / max(abs(gx), 1e-12)
    return slopes


def fit_rim(points: np.ndarray, max_slope: float, outlier_sigmas: float,
            min_sigma: float, near: np.ndarray | None = None) -> RimFit:
    """
    Ellipse through row crossings: grazing rows dropped, then outliers beyond ``outlier_sigmas``.

    ``near``: an ellipse already close to the points, to tell the grazing rows by.
    Raises ValueError when too few points remain for a fit.
    """
    fitted = _fit_rim(
        np.ascontiguousarray(points, dtype=float), float(max_slope), float(outlier_sigmas), float(min_sigma),
        np.zeros(5) if near is None else np.asarray(near, dtype=float), near is not None)
    if fitted.status != OK:
        raise fit_error(fitted.status, fitted.count)
    return RimFit(fitted.ellipse, fitted.kept, fitted.sigma, fitted.candidates)


class _FittedRim(NamedTuple):
    """``_fit_rim``'s result: ``RimFit``'s fields, the status of the fit, and (if it failed) the points it was given."""

    status: int
    count: int
    ellipse: np.ndarray
    kept: np.ndarray
    sigma: float
    candidates: int


@kernel
def _fit_rim(points: np.ndarray, max_slope: float, outlier_sigmas: float, min_sigma: float,
             near: np.ndarray, use_near: bool) -> _FittedRim:
    """``fit_rim``'s work."""
    failed = np.zeros((0, 2))
    ellipse = near
    if not use_near:
        # A rough ellipse through a quarter of the points is enough to tell the grazing rows.
        rough = np.ascontiguousarray(points[::4]) if points.shape[0] >= 40 else points
        status, ellipse = fit_points(rough)
        if status != OK:
            return _FittedRim(status, rough.shape[0], ellipse, failed, 0.0, 0)
    kept = points[edge_slopes(conic_of(ellipse), points) <= max_slope]
    candidates = kept.shape[0]
    status, ellipse = fit_points(kept)
    if status != OK:
        return _FittedRim(status, candidates, ellipse, failed, 0.0, 0)
    residuals = distances(ellipse, kept)
    scale = max(_MAD_TO_SIGMA * np.median(np.abs(residuals)), min_sigma)
    inliers = np.abs(residuals) <= outlier_sigmas * scale
    if not inliers.all():
        kept = kept[inliers]
        status, ellipse = fit_points(kept)
        if status != OK:
            return _FittedRim(status, kept.shape[0], ellipse, failed, 0.0, 0)
        residuals = distances(ellipse, kept)
    # The pose fit weighs every point alike, so its covariance scales with their mean square
    # distance (over the degrees of freedom the ellipse leaves), not with their median spread:
    # rows differ in brightness, hence in noise, and the points' spread is heavier-tailed than
    # a normal's (MAD-based sigma 3-7 % short of the RMS).
    square = 0.0
    for residual in residuals:
        square += residual * residual
    sigma = max(math.sqrt(square / max(residuals.size - _ELLIPSE_PARAMETERS, 1)), min_sigma)
    return _FittedRim(OK, 0, ellipse, kept, sigma, candidates)
