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
_MAX_POOLED_ROWS = 64
# Ramp pixels within this (of the row's step) of background or plateau give probits
# too noisy to measure the blur with.
_PROBIT_MARGIN = 0.03
_MIN_BLUR_ROWS = 10
# Fewer row sides than this leave the edge's level at a half.
_MIN_EDGE_ROWS = 10
# The 99.9 % point of chi-square with 2 degrees of freedom, for the edge's level line against a uniform
# disc's (0.5, 0); neighbouring pixels' residuals are alike (stripes, blur, the model's misfit), which
# counts each of them as about this many.
_UNIFORM_CHI_SQUARE = 13.8
_EDGE_CORRELATION = 4.0
# Rows meeting the edge at a grazing angle (|n_x| below this) reach too far along the row for its profile.
_MIN_ACROSS = 0.3
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
    points = points[interior]
    # Evenly spread over the rim (the points come left crossings first, in row order).
    points = points[::-(-len(points) // _MAX_POOLED_ROWS)] if len(points) else points
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
# Steps the clipped edge fit may take with its blur at its bound before it gives up.
_SOFTEST_STEPS = 10
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
    each step onto them; unconverged after ``_SOFTEST_STEPS`` steps at the blur's bound. A trial step costs
    only the model's values (``_edge_cost``); its Jacobian's normal equations (``_edge_normal``) are formed
    once it is taken.
    """
    lower = np.array([clip, 0.2, -1.0])
    upper = np.array([_MAX_FITTED_OVEREXPOSURE * clip, 2.0 * max_blur, 4.0 * max_blur])
    params = np.array([2.0 * clip, 0.5 * max_blur, 0.5])
    # The model's values at the parameters last evaluated: those taken, whenever the normal equations are formed.
    below = np.empty(t.size)
    cost = _edge_cost(params, t, v, censored, below)
    normal, gradient, damped, trial = np.empty((3, 3)), np.empty(3), np.empty((3, 3)), np.empty(3)
    damping = 1e-3
    converged = False
    pinned = softest = 0
    for _ in range(_EDGE_FIT_ITERATIONS):
        _edge_normal(params, t, v, censored, below, normal, gradient)
        improved = False
        trial_cost = cost
        while damping < 1e10:
            damped[:] = normal
            for k in range(3):
                damped[k, k] += damping * max(normal[k, k], 1e-12)
            step = np.linalg.solve(damped, -gradient)
            for k in range(3):
                trial[k] = min(max(params[k] + step[k], lower[k]), upper[k])
            trial_cost = _edge_cost(trial, t, v, censored, below)
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
        params[:] = trial
        cost = trial_cost
        damping = max(damping / 10.0, 1e-12)
        pinned = pinned + 1 if params[0] >= upper[0] else 0
        # An amplitude held at its bound is a lamp too overexposed for any edge: no need to refine the rest.
        if change < 1e-8 or relative < 1e-12 or pinned >= 3:
            converged = True
            break
        softest = softest + 1 if params[1] >= upper[1] else 0
        # A blur held at its bound is a ramp softer than any edge the fit allows, which then only crawls
        # along the bound (tone foreign set: all 60 steps, unconverged); fits that converge there do so
        # within 8 steps.
        if softest >= _SOFTEST_STEPS:
            break
    return converged, params[0], params[2]


@kernel
def _edge_cost(params: np.ndarray, t: np.ndarray, v: np.ndarray, censored: np.ndarray, below: np.ndarray) -> float:
    """``_censored_edge_fit``'s half sum of squared residuals at ``params``; Phi of each sample into ``below``."""
    amplitude, blur, edge = params[0], params[1], params[2]
    spread = math.sqrt(blur * blur + _PIXEL_VARIANCE)
    cost = 0.0
    for i in range(t.size):
        z = (-edge - t[i]) / spread
        below[i] = 0.5 * math.erfc(-z / math.sqrt(2.0))
        difference = amplitude * below[i] - v[i]
        if not (censored[i] and difference > 0.0):
            cost += 0.5 * difference * difference
    return cost


@kernel
def _edge_normal(params: np.ndarray, t: np.ndarray, v: np.ndarray, censored: np.ndarray, below: np.ndarray,
                 normal: np.ndarray, gradient: np.ndarray) -> None:
    """
    Form the normal equations J^T J, J^T r (into the arrays) of ``_censored_edge_fit``'s model at ``params``.

    ``below`` holds ``_edge_cost``'s Phi at ``params``; censored samples whose model lies above them count none.
    """
    amplitude, blur, edge = params[0], params[1], params[2]
    spread = math.sqrt(blur * blur + _PIXEL_VARIANCE)
    normal[:] = 0.0
    gradient[:] = 0.0
    for i in range(t.size):
        difference = amplitude * below[i] - v[i]
        if censored[i] and difference > 0.0:
            continue
        z = (-edge - t[i]) / spread
        density = math.exp(-0.5 * z * z) / math.sqrt(2.0 * math.pi)
        j0 = below[i]
        j1 = -amplitude * density * z * blur / (spread * spread)
        j2 = -amplitude * density / spread
        normal[0, 0] += j0 * j0
        normal[0, 1] += j0 * j1
        normal[0, 2] += j0 * j2
        normal[1, 1] += j1 * j1
        normal[1, 2] += j1 * j2
        normal[2, 2] += j2 * j2
        gradient[0] += j0 * difference
        gradient[1] += j1 * difference
        gradient[2] += j2 * difference
    normal[1, 0], normal[2, 0], normal[2, 1] = normal[0, 1], normal[0, 2], normal[1, 2]


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

    The fraction per row; ``departure`` (px): how far a half-level crossing lies off the disc's edge for
    the light's departure from a uniform disc on a dark ceiling; ``misfit`` (px): the profile model's
    smooth misfit (``_smooth_misfit``) as a move of the crossings, with what clipped rows' light mixed into
    the others moves them (``clipped_mix_sigma``); ``modelled``: whether the profile
    model was fitted (too few rows leave a half).
    """

    fraction: np.ndarray
    departure: float = 0.0
    misfit: float = 0.0
    modelled: bool = False


def edge_level_fraction(brightness: np.ndarray, levels: RowLevels, background: float, ellipse: np.ndarray,
                        blur: float, marker: tuple[np.ndarray, float] | None = None,
                        saturation_level: float = np.inf) -> EdgeLevel | None:
    """
    Where between background and each row's plateau the disc's edge lies.

    The level of the disc's true edge, as a fraction of the row's rise (0.5 for a uniform disc on a dark
    ceiling), per row of ``levels``; None when the profile model does not converge to a fraction inside
    ``_FRACTION_BOUNDS`` (the light is no disc on a ceiling: a bare LED's glow). ``marker`` (centre,
    radius) keeps its pixels out; pixels at ``saturation_level`` or above are left out.

    A diffuser brighter in the middle puts the plateau (read in the chord's middle)
    above the disc's level at its edge, and a glare halo lifts the ceiling next to it:
    half of the plateau then lies inside the edge, by 0.7 px at 2 px of blur for a 30 %
    falloff with a 20 % halo. The profiles across the edge, all round the lamp (each row's
    pixels within ``_PROFILE_BLURS`` blurs of it, over the row's rise), are fitted together by
    one model of the optics (``_edge_profile_fit``): the disc's own level falling linearly toward
    its edge, the ceiling's (lifted by any halo) falling linearly away from it, joined by a
    Gaussian-blurred step at the edge. Falloff and halo are round about the lamp, so both
    levels are one value each over the row's plateau, which the falloff lowers with the squared
    normalised radius of the row's chord middle, where it was read. The model's value at its fitted
    edge is the level each row's crossing takes; its noise is a few thousandths of the rise.
    """
    ellipse = np.asarray(ellipse, dtype=float)
    has_marker = marker is not None
    centre, radius = (np.asarray(marker[0], dtype=float), float(marker[1])) if has_marker else (np.zeros(2), 0.0)
    t, value, rho, count = _edge_samples(brightness, levels.rows, np.asarray(levels.plateau, dtype=float),
                                         float(background), ellipse, float(blur), has_marker, centre, radius,
                                         float(saturation_level))
    if count < _MIN_EDGE_ROWS:
        return EdgeLevel(np.full(levels.rows.size, 0.5))
    fitted, params, rms, covariance = _edge_profile_fit(t, value, rho, float(blur))
    if not fitted:
        return None
    row_radius = _chord_middle_radius(levels.rows, conic_of(ellipse), ellipse)
    crossing_per_level = _CROSSING_PER_LEVEL * params[6]
    misfit = math.hypot(crossing_per_level * rms,
                        clipped_mix_sigma(np.count_nonzero(levels.plateau >= saturation_level) / levels.rows.size,
                                          float(params[6]), math.sqrt(ellipse[2] * ellipse[3])))
    if not _departs_from_uniform(params, covariance, median(row_radius)):
        return EdgeLevel(np.full(levels.rows.size, 0.5), 0.0, misfit, True)
    fraction = _edge_level(params, row_radius)
    if fraction.min() < _FRACTION_BOUNDS[0] or fraction.max() > _FRACTION_BOUNDS[1]:
        return None
    level = median(fraction)
    return EdgeLevel(fraction, crossing_per_level * abs(level - 0.5), misfit, True)


# The light of clipped rows, of unknown level, that blur mixes into the ends of the unclipped rows beside
# them moves those rows' crossings in patterns round the rim that no profile of the unclipped pixels shows.
# Mixed along a curved edge, light moves a crossing by kappa s^2 / 2 per unit of its level relative to the
# row's (``blur_shifts``); a clipped neighbour's excess is unknown up to a few times the row's rise: counted
# as this many times that pull, for the blur's variance beyond ``SHARP_BLUR_PX`` (as ``edge_model_sigma``),
# times the share of the rows that clip. On the simulator's robot rows, at the true pose: 28 px lamps, 55-77 %
# of their rows clipped at 1.9-2.5 px of blur, had the rim's offset and first two harmonics 0.09-0.37 px RMS
# where the profile's misfit showed 0.02-0.13 px; 37 px tone lamps 0.01-0.29 px.
CLIPPED_MIX_PULLS = 3.0


def clipped_mix_sigma(clipped_share: float, blur_px: float, radius_px: float) -> float:
    """
    Return how far (px, one sigma per rim error mode) clipped neighbours move the unclipped rows' crossings.

    ``clipped_share`` is the share of the lamp's rows whose plateau clips, ``blur_px`` the edge's blur,
    ``radius_px`` the lamp's mean radius in the image.
    """
    excess_variance = max(blur_px * blur_px - SHARP_BLUR_PX ** 2, 0.0)
    return CLIPPED_MIX_PULLS * clipped_share * 0.5 * excess_variance / max(radius_px, 1.0)


# Each row's pixels within this many blurs of the edge (on both sides) are fitted by the profile model.
_PROFILE_BLURS = 4.5
_PROFILE_PARAMETERS = 7
_PROFILE_ITERATIONS = 40
# A round has converged when its next step would move the parameters by less than this share of their
# standard errors (the step's Mahalanobis length at the residuals' variance): far below their noise. The
# first round's residuals pick the outliers; a sample near the cut flips with a change of 0.01 standard
# errors, moving the result by up to 0.2 (tone foreign set), so that round goes ten times further.
_PROFILE_STEP_SIGMAS = (0.001, 0.01)
# Samples further than this many robust sigmas off the model (a neighbouring lamp, a stripe the blur
# mixed unevenly) are left out of the second round.
_PROFILE_OUTLIER_SIGMAS = 4.0
# At most about this many rows (evenly spread) give samples: a 4K lamp's few hundred rows would cost
# milliseconds and add little (the level's noise is a few thousandths of the rise with a hundred).
_PROFILE_MAX_ROWS = 100
_INVERSE_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)
_MISFIT_NOISE_SIGMAS = 3.0


@kernel
def _edge_samples(brightness: np.ndarray, rows: np.ndarray, plateau: np.ndarray, background: float,
                  ellipse: np.ndarray, blur: float, has_marker: bool, centre: np.ndarray, radius: float,
                  saturation_level: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """
    Return ``edge_level_fraction``'s samples: distance across the edge (px, outward positive), level over the rise.

    Also each sample's row's squared normalised chord-middle radius, and how many row sides gave samples.
    Rows meeting the edge at a grazing angle (|n_x| below ``_MIN_ACROSS``) and pixels near the marker
    give none; of many rows, every k-th (``_PROFILE_MAX_ROWS``). The distance is measured along the ray
    from the ellipse's centre in its normalised frame (exact for a circle, where a first-order distance
    errs by 7 % ten pixels from a 75 px rim).
    """
    conic = conic_of(ellipse)
    middle = _chord_middle_radius(rows, conic, ellipse)
    left, right, crossed = chords(conic, rows.astype(np.float64))
    cx, cy, a, b, theta = ellipse[0], ellipse[1], ellipse[2], ellipse[3], ellipse[4]
    c, s = math.cos(theta), math.sin(theta)
    width = brightness.shape[1]
    reach = _PROFILE_BLURS * blur + 1.0
    # Each side of a row gives at most 2 reach / |n_x| + 2 pixels, |n_x| >= _MIN_ACROSS.
    capacity = 2 * rows.size * (int(2.0 * reach / _MIN_ACROSS) + 3)
    t, value, rho = np.empty(capacity), np.empty(capacity), np.empty(capacity)
    count = sides = 0
    for i in range(0, rows.size, -(-rows.size // _PROFILE_MAX_ROWS)):
        rise = plateau[i] - background
        if not (crossed[i] and rise > 0.0 and plateau[i] < saturation_level):
            continue
        y = float(rows[i])
        for side in range(2):
            edge = left[i] if side == 0 else right[i]
            gx = edge * conic[0, 0] + y * conic[1, 0] + conic[2, 0]
            gy = edge * conic[0, 1] + y * conic[1, 1] + conic[2, 1]
            across = abs(gx) / max(math.sqrt(gx * gx + gy * gy), 1e-12)
            span = reach / max(across, 1e-12)
            if across < _MIN_ACROSS or span > 0.5 * (right[i] - left[i]):
                continue
            first = int(math.floor(edge - span))
            taken = 0
            for col in range(first, first + int(2.0 * span) + 2):
                if not (0 <= col < width and count < capacity):
                    continue
                level = float(brightness[rows[i], col])
                if level >= saturation_level:
                    continue
                dx, dy = col - centre[0], y - centre[1]
                if has_marker and dx * dx + dy * dy <= radius * radius:
                    continue
                ex, ey = col - cx, y - cy
                u, v = (ex * c + ey * s) / a, (-ex * s + ey * c) / b
                normalised = math.sqrt(u * u + v * v)
                if not normalised > 0.0:
                    continue
                # The point on the ellipse along the same normalised ray, and the distance to it.
                px, py = a * u / normalised, b * v / normalised
                distance = math.sqrt((u * a - px) ** 2 + (v * b - py) ** 2) * (1.0 if normalised > 1.0 else -1.0)
                if abs(distance) > reach:
                    continue
                t[count], value[count], rho[count] = distance, (level - background) / rise, middle[i]
                count += 1
                taken += 1
            sides += 1 if taken > 0 else 0
    return t[:count], value[:count], rho[:count], sides


@kernel
def _edge_profile_fit(t: np.ndarray, value: np.ndarray, rho: np.ndarray,
                      blur: float) -> tuple[bool, np.ndarray, float, np.ndarray]:
    """
    Return the edge's profile model fitted by Levenberg-Marquardt in two rounds.

    That is (converged, parameters, smooth misfit RMS ``_smooth_misfit``, parameter covariance at the
    residuals' variance).

    The model, at distance t across the edge (outward positive) of a row whose chord middle lies at
    squared normalised radius rho: the disc's level alpha + beta t inside the edge at -e and the
    ceiling's gamma + delta t outside it, blurred by a Gaussian of sigma S. Both levels are over the
    row's plateau, which a falloff of a share f lowers to 1 - f rho: alpha = a0 / (1 + k rho),
    gamma = g0 / (1 + k rho), k = -f to first order. A blurred step between two straight lines is
    exactly (alpha + beta t) Phi(z) + (gamma + delta t) (1 - Phi(z)) + (delta - beta) S phi(z),
    z = (-e - t) / S. Parameters (a0, k, beta, g0, delta, e, S). The second round leaves out samples further
    than ``_PROFILE_OUTLIER_SIGMAS`` robust sigmas from the first.
    """
    params = np.array([0.9, 0.0, 0.0, 0.05, 0.0, 0.0, max(blur, 0.3)])
    kept = np.ones(t.size, np.bool_)
    converged = False
    covariance = np.zeros((_PROFILE_PARAMETERS, _PROFILE_PARAMETERS))
    for round_ in range(2):
        converged, params, cost, residual, jacobian = _profile_rounds(
            t, value, rho, kept, params, _PROFILE_STEP_SIGMAS[round_])
        if not converged:
            return False, params, 0.0, covariance
        if round_ == 1:
            variance = 2.0 * cost / max(np.count_nonzero(kept) - _PROFILE_PARAMETERS, 1)
            normal = jacobian.T @ jacobian
            for k in range(_PROFILE_PARAMETERS):
                normal[k, k] += 1e-12
            covariance = variance * np.linalg.inv(normal)
            return True, params, _smooth_misfit(t, rho, kept, residual, cost), covariance
        scale = _MAD_TO_SIGMA * median(np.abs(residual[kept]))
        for i in range(t.size):
            kept[i] = abs(residual[i]) <= _PROFILE_OUTLIER_SIGMAS * max(scale, 1e-6)
    return converged, params, 0.0, covariance


@kernel
def _smooth_misfit(t: np.ndarray, rho: np.ndarray, kept: np.ndarray, residual: np.ndarray, cost: float) -> float:
    """
    Return the RMS of the profile model's residuals that is smooth across the edge: the model's misfit, not noise.

    Pixel noise differs from one pixel to the next; a misfit of the model (a halo or a falloff of
    another shape, blur that is no Gaussian) is alike in neighbouring pixels of a row. Half the mean
    square difference of neighbouring residuals is the noise's variance; what the residuals' mean
    square holds beyond it is the misfit's.
    """
    count = np.count_nonzero(kept)
    total = 2.0 * cost / max(count - _PROFILE_PARAMETERS, 1)
    differences = pairs = 0.0
    for i in range(t.size - 1):
        if kept[i] and kept[i + 1] and rho[i] == rho[i + 1] and abs(t[i + 1] - t[i]) < 1.5:
            differences += (residual[i + 1] - residual[i]) ** 2
            pairs += 1.0
    if pairs < _PROFILE_PARAMETERS:
        return math.sqrt(total)
    # The noise's variance is known to a share sqrt(2 / pairs) of itself: a misfit within
    # ``_MISFIT_NOISE_SIGMAS`` of that is none (a clean disc's edge, which the model fits exactly).
    noise = 0.5 * differences / pairs
    return math.sqrt(max(total - noise - _MISFIT_NOISE_SIGMAS * noise * math.sqrt(2.0 / pairs), 0.0))


@kernel
def _profile_rounds(t: np.ndarray, value: np.ndarray, rho: np.ndarray, kept: np.ndarray, params: np.ndarray,
                    step_sigmas: float) -> tuple[bool, np.ndarray, float, np.ndarray, np.ndarray]:
    """
    One Levenberg-Marquardt fit of ``_edge_profile_fit``'s model on the ``kept`` samples, from ``params``.

    Returns (converged, parameters) and the model's cost, residuals and Jacobian at those parameters
    (``_profile_model``), so that the caller need not evaluate it again. Converged once the next step
    would move the parameters by under ``step_sigmas`` standard errors, without evaluating it.
    """
    n = t.size
    residual, jacobian = np.empty(n), np.empty((n, _PROFILE_PARAMETERS))
    cost = _profile_model(params, t, value, rho, kept, residual, jacobian)
    degrees = max(np.count_nonzero(kept) - _PROFILE_PARAMETERS, 1)
    # Trials are evaluated into a second pair of arrays, swapped with the first when one is taken.
    trial_residual, trial_jacobian = np.empty(n), np.empty((n, _PROFILE_PARAMETERS))
    damping = 1e-3
    for _ in range(_PROFILE_ITERATIONS):
        normal = jacobian.T @ jacobian
        gradient = jacobian.T @ residual
        improved = False
        trial = params.copy()
        trial_cost = cost
        while damping < 1e10:
            damped = normal.copy()
            for k in range(_PROFILE_PARAMETERS):
                damped[k, k] += damping * max(normal[k, k], 1e-12)
            step = np.linalg.solve(damped, -gradient)
            # Checked on a lightly damped step only: a heavily damped one is short for want of trust, not of gain.
            if damping <= 1e-3 and step @ (normal @ step) * degrees < 2.0 * cost * step_sigmas * step_sigmas:
                return True, params, cost, residual, jacobian
            trial = params + step
            trial[1] = max(trial[1], -0.9)
            trial[6] = max(trial[6], 0.2)
            trial_cost = _profile_model(trial, t, value, rho, kept, trial_residual, trial_jacobian)
            if trial_cost < cost:
                improved = True
                break
            damping *= 10.0
        if not improved:
            return True, params, cost, residual, jacobian
        relative = (cost - trial_cost) / max(cost, 1e-300)
        params, cost = trial, trial_cost
        residual, trial_residual = trial_residual, residual
        jacobian, trial_jacobian = trial_jacobian, jacobian
        damping = max(damping / 10.0, 1e-12)
        if relative < 1e-10:
            return True, params, cost, residual, jacobian
    return False, params, cost, residual, jacobian


@kernel
def _profile_model(params: np.ndarray, t: np.ndarray, value: np.ndarray, rho: np.ndarray, kept: np.ndarray,
                   residual: np.ndarray, jacobian: np.ndarray) -> float:
    """``_edge_profile_fit``'s residuals and Jacobian (into the arrays; 0 for samples not kept); half their squares."""
    a0, k, beta, g0, delta, edge, spread = params
    cost = 0.0
    for i in range(t.size):
        if not kept[i]:
            residual[i] = 0.0
            for column in range(_PROFILE_PARAMETERS):
                jacobian[i, column] = 0.0
            continue
        scale = 1.0 / (1.0 + k * rho[i])
        alpha, gamma = a0 * scale, g0 * scale
        z = (-edge - t[i]) / spread
        below = 0.5 * math.erfc(-z / math.sqrt(2.0))
        density = math.exp(-0.5 * z * z) * _INVERSE_SQRT_2PI
        inside, outside = alpha + beta * t[i], gamma + delta * t[i]
        difference = inside * below + outside * (1.0 - below) + (delta - beta) * spread * density - value[i]
        # d model / dz = phi ((alpha - gamma) - (beta - delta) e), as t + S z = -e.
        along = density * ((alpha - gamma) - (beta - delta) * edge)
        residual[i] = difference
        jacobian[i, 0] = scale * below
        jacobian[i, 1] = -rho[i] * scale * (alpha * below + gamma * (1.0 - below))
        jacobian[i, 2] = t[i] * below - spread * density
        jacobian[i, 3] = scale * (1.0 - below)
        jacobian[i, 4] = t[i] * (1.0 - below) + spread * density
        jacobian[i, 5] = -along / spread
        jacobian[i, 6] = -along * z / spread + (delta - beta) * density
        cost += 0.5 * difference * difference
    return cost


def _departs_from_uniform(params: np.ndarray, covariance: np.ndarray, rho: float) -> bool:
    """
    Whether the edge's level departs from a uniform disc's on a dark ceiling (a half, k = 0) beyond its noise.

    The level is taken at the rows' median ``rho``. A uniform disc has its edge at half of every row's
    rise: unless the profile tells otherwise beyond doubt, that stays exact, as the level's own noise
    would move all rim points alike (a size error of several of its standard deviations on a clean lamp).
    """
    a0, k, beta, g0, delta, edge, spread = (float(v) for v in params)
    scale, tail = 1.0 / (1.0 + k * rho), spread * _INVERSE_SQRT_2PI
    # The gradients of the level at rho (``_edge_level``) and of k.
    gradients = np.array([[0.5 * scale, -0.5 * (a0 + g0) * rho * scale * scale, -0.5 * edge - tail, 0.5 * scale,
                           -0.5 * edge + tail, -0.5 * (beta + delta), (delta - beta) * _INVERSE_SQRT_2PI],
                          [0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0]])
    offset = np.array([float(_edge_level(params, np.array([rho]))[0]) - 0.5, k])
    try:
        chi_square = float(offset @ np.linalg.solve(gradients @ covariance @ gradients.T, offset))
    except np.linalg.LinAlgError:
        return True
    return not chi_square < _UNIFORM_CHI_SQUARE * _EDGE_CORRELATION


def _edge_level(params: np.ndarray, rho: np.ndarray) -> np.ndarray:
    """
    Return the model's level at its edge for rows whose chord middles lie at ``rho``.

    At the edge (z = 0) the model is the two levels' midpoint plus (delta - beta) S phi(0).
    """
    a0, k, beta, g0, delta, edge, spread = (float(v) for v in params)
    return (0.5 * (a0 + g0) / (1.0 + k * np.asarray(rho, dtype=float)) - 0.5 * edge * (beta + delta)
            + (delta - beta) * spread * _INVERSE_SQRT_2PI)


# A share q of the row's rise added to one side of a step blurred by s moves its half-level crossing by
# s Phi^-1(1/2 + q / 2), about sqrt(2 pi) s q / 2 for small q.
_CROSSING_PER_LEVEL = math.sqrt(2.0 * math.pi)
# The share of the profile model's smooth misfit taken as the prior sigma of the rim's smooth error patterns:
# on the simulator's 4K lamp under every look (clean, blur, glare, falloff, saturated, overexposed, realistic,
# as JPEG) the misfit was 0.002-0.10 px where the patterns at the true pose were 0.01-0.18 px.
MISFIT_SHARE = 1.5


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
    two harmonics: ``measurement.rim_error_modes``), given the edge's blur variance and how far the light's
    departure from a uniform disc moves them (``EdgeLevel.departure``): the larger of the two, as a sharp
    edge's crossings, which the blur term leaves exact, still move with glare and falloff. For rims whose
    crossings were not put at the profile model's level (clipped rows needed, too few rows).

    Any departure of the light from a uniform disc with a step edge moves the crossing of a
    blurred edge by the blur variance times the light's relative change across it: a diffuser's
    falloff or a glare halo (its slope over the row's rise), the stripes of neighbouring rows
    that blur mixes into a row's ends differently than into its middle (the edge's slope times
    the stripes' relative slope), a blur that is no Gaussian: beyond a pixel of blur it grows with
    the variance.
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
