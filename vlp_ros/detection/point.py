"""
The centre of a lamp's light when its rim is no ellipse: bare LEDs and soft or overexposed lamps.

A bare LED in a real photo is a bright core (tens of pixels at half level) inside a glow
that still reaches 10 % of it a hundred pixels out, all of it striped row by row, and
its core's half-level crossings scatter by pixels around any ellipse. Each row is read
on its own: its profile is the light's shape times the row's level, so the crossings
at half the row's maximum do not move with the stripes, and the glow, symmetric about
the centre, moves neither. A row that meets the core crosses half of its maximum on
the core's edge; a row that meets only the glow crosses it far out, nearly as wide
as the glow. The rows narrower than most of the widest give a circle whose centre is
the centre of the light, with a covariance from the crossings' own scatter.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
import math

import cv2
import numpy as np

from vlp_ros.compiled import kernel
from vlp_ros.compiled.small_arrays import median
from vlp_ros.core.observation import LampObservation

# Robust (MAD) standard deviation of a normal distribution.
_MAD_TO_SIGMA = 1.4826
# Rows wider at half their maximum than this many times the typical narrow row (of those narrower
# than midway between the narrowest and the widest) meet the glow, not the core.
_CORE_WIDTH_FACTOR = 1.5
# Rows dimmer than this (of the brightest row) are left out: noise moves their crossings.
_MIN_ROW_SHARE = 0.15
_OUTLIER_SIGMAS = 3.0
_MIN_POINTS = 12
# Share of the core rows' crossings the circle must keep, and of them on each side of its centre row.
_MIN_INLIER_SHARE = 0.6
_MIN_SIDE_SHARE = 0.2
# Crossings may scatter this much of the radius (plus a pixel) around the circle: real LEDs scatter
# 0.65-8 px around cores of radius 15-32 px.
_MAX_SCATTER_SHARE = 0.3
# The kept crossings must span this share of the circle's height: a bar's or a box's rows, all alike,
# fit a circle too, but over a band of rows well short of its diameter.
_MIN_HEIGHT_SHARE = 0.65
# An overexposed light's clipped area may be this much taller than wide, or wider than tall (its stripes).
_MAX_CLIPPED_ASPECT = 1.6
# Largest lag-one correlation of the residuals of adjacent rows counted.
_MAX_CORRELATION = 0.8
# The light's centre is found over the glow out to this many core radii (plus a margin, px), then
# measured over the core's flank out to the second: a comatic glow shifted by 13 px (4K) moved the
# first fit by 0.4-5 px, the second by 0.1-0.4 px.
_GLOW_REACH = 3.0
_GLOW_MARGIN_PX = 10.0
_CORE_REACH = 1.3
_CORE_MARGIN_PX = 6.0
# The core's area is where the de-striped light is above this share of its plateau (or of the clip).
_CORE_LEVEL = 0.9
# Shares of the distances between the estimates taken as the centre's sigma (per axis).
_DISAGREEMENT_SHARE = 0.5
_ASYMMETRY_SHARE = 0.25
# A clipped glow's plateau hides the emitter: its centre is off it by up to ~14 % of the plateau's radius
# (simulated LEDs 2-8x over, coma 0-0.6, rough cores, tails), ~5 % per axis on average. The light in a
# ring this far (px) outside the plateau, as a share of the clip, tells a clipped glow from a clipped core.
_HIDDEN_SHARE = 0.06
_PLATEAU_OFFSET_SHARE = 0.5
_EDGE_GAP_PX = (8.0, 11.0)
_GLOW_CLIPS = (0.8, 1.0)
_MIN_LIGHT_PIXELS = 200
_KNOT_PX = 1.0
_SMOOTHNESS = 2.0
_START_STEPS = 4
_MAX_ITERATIONS = 30
_GAUGE = 1.0
_MAX_STEP_PX = 2.0
_CONVERGED_PX = 1e-3
_CONVERGED_SIGMA = 0.05
_CONVERGED_COST_SHARE = 1e-4
# The fit's sigma counts pixels as independent; neighbours share their errors (the lens, JPEG's blocks,
# the shape's asymmetry), so it is taken as this many times that.
_LIGHT_CORRELATION = 1.7
_LIGHT_SIGMA_FLOOR = 0.01


@dataclass(frozen=True)
class PointFit:
    """
    Centre (box pixels) and radius of the core, and the quality of its fit.

    That is the centre's standard deviation per axis (px, the larger of the two), the kept crossings and
    their RMS distance from the circle.
    """

    center: np.ndarray
    radius: float
    sigma: float
    points: np.ndarray
    scatter: float


def fit_point(brightness: np.ndarray, background: float, noise: float, min_radius: float,
              noise_factor: float, saturation_level: float, whole: bool = True) -> PointFit | None:
    """
    Return the centre of the light in ``brightness`` (one lamp's box, one channel).

    None when its core is not round enough, or too small (``min_radius`` px), to give one.

    A clipped row's maximum is not its level, and where it leaves the clip depends on how
    far its stripe overexposes it: clipped rows are used only when the unclipped ones give
    too few crossings or no round core (the dark stripes alone may span too few of its rows),
    and their scatter (stripe by stripe) then widens the centre's sigma.

    ``whole=False`` says that the box cuts the light (the frame's border does): a light that clips its
    glow too then gives None, since its centre (``_overexposed_fit``) is that of the whole light.
    """
    points, rows, clipped = _half_maximum_crossings(brightness, background, noise_factor * noise,
                                                    saturation_level)
    if len(points) < _MIN_POINTS:
        return None
    width = points[1::2, 0] - points[0::2, 0]
    narrow = width[width <= 0.5 * (width.min() + width.max())]
    core = width <= _CORE_WIDTH_FACTOR * median(narrow)
    unclipped = core & ~clipped
    fit = _core_fit(points, rows, unclipped, min_radius) if np.count_nonzero(unclipped) >= _MIN_POINTS // 2 else None
    if fit is None and np.any(core & clipped):
        fit = _core_fit(points, rows, core, min_radius)
    if fit is not None or not whole:
        return fit
    return _overexposed_fit(brightness, background, min_radius, saturation_level)


def _overexposed_fit(brightness: np.ndarray, background: float, min_radius: float,
                     saturation_level: float) -> PointFit | None:
    """
    ``fit_point`` for a light that clips its glow too: no row's half-maximum crossing is the core's.

    The clipped area then varies row by row with the stripes and is no circle; the centre is the
    light's (``measure_light_centre``) from the clipped area's centroid, for a clipped area about as
    tall as it is wide (a bar or a window is not a bare LED).
    """
    clipped = brightness >= saturation_level
    rows, columns = np.nonzero(clipped)
    if len(rows) < _MIN_POINTS:
        return None
    height, width = np.ptp(rows) + 1.0, np.ptp(columns) + 1.0
    radius = 0.25 * (height + width)
    if radius < min_radius or max(height, width) > _MAX_CLIPPED_ASPECT * min(height, width):
        return None
    light = measure_light_centre(brightness, np.array([columns.mean(), rows.mean()]), radius, saturation_level)
    if light is None:
        return None
    return PointFit(light.center, radius, light.sigma, np.zeros((0, 2)), 0.0)


def _core_fit(points: np.ndarray, rows: np.ndarray, core: np.ndarray, min_radius: float) -> PointFit | None:
    """``fit_point``'s circle through the crossings of the ``core`` rows, or None if they are not round."""
    pairs = np.flatnonzero(core)
    core_points = points[np.ravel(np.column_stack([2 * pairs, 2 * pairs + 1]))]
    core_rows = rows[pairs]
    if len(core_points) < _MIN_POINTS:
        return None
    fit = _robust_circle(core_points)
    if fit is None:
        return None
    centre, radius, kept = fit
    residual = np.hypot(*(core_points[kept] - centre).T) - radius
    count = int(np.count_nonzero(kept))
    scatter = float(np.sqrt(np.sum(residual ** 2) / max(count - 3, 1)))
    above = np.count_nonzero(core_points[kept, 1] < centre[1])
    if (count < _MIN_POINTS or count < _MIN_INLIER_SHARE * len(core_points) or radius < min_radius
            or min(above, count - above) < _MIN_SIDE_SHARE * count
            or scatter > _MAX_SCATTER_SHARE * radius + 1.0
            or np.ptp(core_points[kept, 1]) < _MIN_HEIGHT_SHARE * 2.0 * radius):
        return None
    sigma = _centre_sigma(core_points[kept], centre, radius, scatter, np.repeat(core_rows, 2)[kept], residual)
    return PointFit(centre, float(radius), sigma, core_points[kept], scatter)


def _half_maximum_crossings(brightness: np.ndarray, background: float, floor: float,
                            saturation_level: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """
    Return the left and right crossings of half of each bright row's maximum, the N rows and which are clipped.

    The crossings are interleaved, (2N, 2), at half the clip level in clipped rows, around the run of
    pixels above it that holds the maximum.
    """
    light = brightness.astype(np.float64) - background
    maxima = light.max(axis=1)
    peak = maxima.max()
    clip = saturation_level - 1.0 - background
    bright = np.flatnonzero((maxima > _MIN_ROW_SHARE * peak) & (maxima > floor))
    # A clipped row's maximum is not its level: where it leaves the clip is a level crossing
    # of its own (half of the clip would lie out in the glow).
    halves = np.where(maxima[bright] >= clip, clip, 0.5 * maxima[bright])
    points, crossed = _crossings_around_maxima(light, bright, halves)
    rows = bright[crossed]
    return points, rows, maxima[rows] >= clip


@kernel
def _crossings_around_maxima(light: np.ndarray, rows: np.ndarray, halves: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """
    Return the crossings of each of ``rows`` at its level in ``halves``, (2N, 2) interleaved, and which rows have them.

    Around the run of pixels at or above the level that holds the row's (first) maximum; a run that reaches
    the box's edge gives none. Each crossing is interpolated linearly between the last pixel below the level
    and the first at or above it.
    """
    width = light.shape[1]
    points = np.empty((2 * rows.size, 2))
    crossed = np.zeros(rows.size, np.bool_)
    count = 0
    for i in range(rows.size):
        row, half = rows[i], halves[i]
        top = 0
        for x in range(1, width):
            if light[row, x] > light[row, top]:
                top = x
        left = top
        while left > 0 and light[row, left - 1] >= half:
            left -= 1
        right = top
        while right < width - 1 and light[row, right + 1] >= half:
            right += 1
        if left == 0 or right == width - 1:
            continue
        points[2 * count, 0] = left - (light[row, left] - half) / (light[row, left] - light[row, left - 1])
        points[2 * count + 1, 0] = right + (light[row, right] - half) / (light[row, right] - light[row, right + 1])
        points[2 * count, 1] = points[2 * count + 1, 1] = row
        crossed[i] = True
        count += 1
    return points[:2 * count], crossed


def _robust_circle(points: np.ndarray) -> tuple[np.ndarray, float, np.ndarray] | None:
    """
    (centre, radius, kept).

    A geometric circle fit, refitted without points beyond ``_OUTLIER_SIGMAS``
    robust sigmas. None if it does not converge to a circle.
    """
    kept = np.ones(len(points), bool)
    circle = _algebraic_circle(points)
    if circle is None:
        return None
    for _ in range(3):
        circle = _geometric_circle(points[kept], *circle)
        if circle is None:
            return None
        residual = np.hypot(*(points - circle[0]).T) - circle[1]
        scale = max(_MAD_TO_SIGMA * float(np.median(np.abs(residual[kept]))), 0.05)
        now = np.abs(residual) <= _OUTLIER_SIGMAS * scale
        if np.count_nonzero(now) < _MIN_POINTS:
            return None
        if np.array_equal(now, kept):
            break
        kept = now
    return circle[0], circle[1], kept


def _algebraic_circle(points: np.ndarray) -> tuple[np.ndarray, float] | None:
    """Kasa's fit: x^2 + y^2 + D x + E y + F = 0 in least squares."""
    origin = points.mean(axis=0)
    p = points - origin
    design = np.column_stack([p, np.ones(len(p))])
    solution, *_ = np.linalg.lstsq(design, -(p ** 2).sum(axis=1), rcond=None)
    centre = -0.5 * solution[:2]
    squared = centre @ centre - solution[2]
    if not squared > 0.0:
        return None
    return centre + origin, math.sqrt(squared)


def _geometric_circle(points: np.ndarray, centre: np.ndarray, radius: float) -> tuple[np.ndarray, float] | None:
    """Gauss-Newton on the distances to the circle, from (``centre``, ``radius``)."""
    params = np.array([centre[0], centre[1], radius])
    for _ in range(20):
        offset = points - params[:2]
        distance = np.maximum(np.hypot(*offset.T), 1e-9)
        jacobian = np.column_stack([-offset / distance[:, None], -np.ones(len(points))])
        step, *_ = np.linalg.lstsq(jacobian, -(distance - params[2]), rcond=None)
        params += step
        if np.linalg.norm(step) < 1e-4:
            break
    if not (np.all(np.isfinite(params)) and params[2] > 0.0):
        return None
    return params[:2].copy(), float(params[2])


def _centre_sigma(points: np.ndarray, centre: np.ndarray, radius: float, scatter: float, rows: np.ndarray,
                  residual: np.ndarray) -> float:
    """
    Return the centre's standard deviation per axis (the larger).

    The fit's covariance at the crossings' scatter, counting a row's two crossings as one (they
    share the row's level, and so its error) and adjacent rows as alike as their residuals show
    (stripes clip, blur and bloom rows in runs).
    """
    offset = points - centre
    distance = np.maximum(np.hypot(*offset.T), 1e-9)
    jacobian = np.column_stack([-offset / distance[:, None], -np.ones(len(points))])
    covariance = scatter ** 2 * np.linalg.pinv(jacobian.T @ jacobian)
    inflation = 2.0 * _row_correlation_inflation(rows, residual, points[:, 0] < centre[0])
    return float(math.sqrt(inflation * max(covariance[0, 0], covariance[1, 1])))


def _row_correlation_inflation(rows: np.ndarray, residual: np.ndarray, left: np.ndarray) -> float:
    """(1 + rho) / (1 - rho), rho the lag-one correlation of the residuals of adjacent rows on one side."""
    total = norm = 0.0
    for side in (left, ~left):
        order = np.argsort(rows[side])
        r, y = residual[side][order], rows[side][order]
        adjacent = np.flatnonzero(np.diff(y) == 1)
        total += float(np.sum(r[adjacent] * r[adjacent + 1]))
        norm += 0.5 * float(np.sum(r[adjacent] ** 2) + np.sum(r[adjacent + 1] ** 2))
    rho = min(max(total / norm, 0.0), _MAX_CORRELATION) if norm > 0.0 else 0.0
    return (1.0 + rho) / (1.0 - rho)


@dataclass(frozen=True)
class LightCentre:
    """
    The centre of a point lamp's light (full-frame pixels) and its standard deviation per axis (px).

    ``radius`` is how far out (px) the light was measured, ``clipped`` the share of those pixels clipped.
    """

    center: np.ndarray
    sigma: float
    radius: float
    clipped: float


def measure_light_centre(image: np.ndarray, start: np.ndarray, core_radius: float,
                         saturation_level: float = 250.0) -> LightCentre | None:
    """
    Return the centre of the light around ``start`` (px) whose core is about ``core_radius`` px.

    The light is modelled as one radial shape times each row's level over the ambient level,
    I(x, y) = b + s(y) f(|p - c|): the stripes scale every row of core and glow alike, and
    the shape f is free (any lens's spread, glow and tail), so only its symmetry about c is
    assumed. Clipped pixels say only that the light is above the clip and are left out, so
    the centre comes from the unclipped flanks, weighted by how steeply each pixel changes
    with the centre. It is fitted twice: over the glow out to ``_GLOW_REACH`` core radii, which
    finds the light from a start many pixels off, then over the core's flank alone
    (``_CORE_REACH``), which gives the centre: a real glow is not symmetric (coma, flare) and
    would pull it. The two fits' distance widens the sigma. None when too little light is
    unclipped.
    """
    coarse = _fit_within(image, np.asarray(start, dtype=float), _GLOW_REACH * core_radius + _GLOW_MARGIN_PX,
                         saturation_level, core_radius + _GLOW_MARGIN_PX)
    if coarse is None:
        return None
    fine = _fit_within(image, coarse.center, _CORE_REACH * core_radius + _CORE_MARGIN_PX, saturation_level,
                       0.5 * core_radius + 2.0)
    if fine is None:
        return None
    area = level_centroids(coarse, (_CORE_LEVEL,))
    if area is None:
        return None
    # Two estimates that assume different things: the flank's radial symmetry (a comatic glow does not
    # move it; an irregular emitter does) and the core's area centroid (the reverse). Each's departure
    # from the other, and the glow's from the flank, say how far the light departs from either.
    centre = 0.5 * (fine.center + area[0])
    disagreement = float(np.linalg.norm(fine.center - area[0]))
    asymmetry = float(np.linalg.norm(fine.center - coarse.center))
    sigma = math.sqrt(fine.sigma ** 2 + (_DISAGREEMENT_SHARE * disagreement) ** 2 + (_ASYMMETRY_SHARE * asymmetry) ** 2
                      + hidden_emitter_sigma(coarse, centre) ** 2)
    return LightCentre(centre, sigma, fine.reach, fine.clipped_share)


def hidden_emitter_sigma(fit: _Fit, centre: np.ndarray) -> float:
    """
    Return the centre's sigma (px, per axis) from a clipped glow that hides the emitter.

    Where the glow clips too, the plateau is a contour of the glow, and a real glow is not symmetric
    (coma, flare): the contour's centre is off the emitter by a share of its radius that no fit of the
    flank or the plateau can see. The glow clips where the light just outside the plateau is still near
    the clip (a clipped core drops to its glow within a few pixels); the sigma grows from nothing to
    ``_HIDDEN_SHARE`` of the plateau's radius, and ``_PLATEAU_OFFSET_SHARE`` of its centroid's distance
    from ``centre`` (how lopsided the glow shows itself), as that light rises from ``_GLOW_CLIPS[0]`` to
    ``_GLOW_CLIPS[1]`` of the clip.
    """
    plateau = fit.inside & fit.clipped
    radius = math.sqrt(np.count_nonzero(plateau) / math.pi)
    if radius == 0.0:
        return 0.0
    ys, xs = np.ogrid[0:plateau.shape[0], 0:plateau.shape[1]]
    distance = np.hypot(xs + fit.origin[0] - centre[0], ys + fit.origin[1] - centre[1])
    ring = fit.inside & ~fit.clipped & (distance > radius + _EDGE_GAP_PX[0]) & (distance <= radius + _EDGE_GAP_PX[1])
    if not np.any(ring):
        return 0.0
    edge = float(np.median(fit.destriped[ring])) / fit.clip
    weight = min(max((edge - _GLOW_CLIPS[0]) / (_GLOW_CLIPS[1] - _GLOW_CLIPS[0]), 0.0), 1.0)
    rows, columns = np.nonzero(plateau)
    offset = math.hypot(columns.mean() + fit.origin[0] - centre[0], rows.mean() + fit.origin[1] - centre[1])
    return weight * math.hypot(_HIDDEN_SHARE * radius, _PLATEAU_OFFSET_SHARE * offset)


def level_centroids(fit: _Fit, shares: tuple[float, ...]) -> np.ndarray | None:
    """
    Return the centroids (K, 2) of the de-striped light's areas above ``shares`` of its top level.

    The top is the core's plateau, or the clip where the brightest row clips: a clipped pixel lies
    above the clip in its own row, so above it de-striped too (its row's level is at most 1), and
    every area below the clip is known. The area holding the fit's centre counts, its pixels whole.
    """
    light = fit.destriped
    known = fit.inside & ~fit.clipped
    if not np.any(known):
        return None
    top = min(float(np.percentile(light[known], 99.5)), fit.clip)
    centroids = []
    x0, y0 = fit.origin
    seed = np.rint(fit.center - np.array([x0, y0])).astype(int)
    for share in shares:
        above = (fit.inside & (fit.clipped | (light >= share * top))).astype(np.uint8)
        _, labels = cv2.connectedComponents(above)
        if not (0 <= seed[1] < labels.shape[0] and 0 <= seed[0] < labels.shape[1]) or labels[seed[1], seed[0]] == 0:
            return None
        ys, xs = np.nonzero(labels == labels[seed[1], seed[0]])
        centroids.append([xs.mean() + x0, ys.mean() + y0])
    return np.array(centroids)


@dataclass(frozen=True)
class _Fit:
    """A radial fit's centre, sigma, reach and clipped share, and its box de-striped (levels divided out)."""

    center: np.ndarray
    sigma: float
    reach: float
    clipped_share: float
    destriped: np.ndarray
    clipped: np.ndarray
    inside: np.ndarray
    origin: tuple[int, int]
    clip: float


def _fit_within(image: np.ndarray, start: np.ndarray, reach: float, saturation_level: float,
                max_shift: float) -> _Fit | None:
    """``measure_light_centre``'s radial fit over the pixels within ``reach`` of ``start``."""
    height, width = image.shape[:2]
    x0, y0 = max(int(start[0] - reach), 0), max(int(start[1] - reach), 0)
    x1, y1 = min(int(start[0] + reach) + 2, width), min(int(start[1] + reach) + 2, height)
    roi = image[y0:y1, x0:x1]
    if roi.size == 0:
        return None
    colour = roi.ndim == 3
    # Luma: JPEG keeps it at full resolution, the colours at half.
    light = (roi.astype(np.float64) @ np.array([0.114, 0.587, 0.299])) if colour else roi.astype(np.float64)
    clipped = (roi.max(axis=2) if colour else roi) >= saturation_level
    ys, xs = np.mgrid[y0:y1, x0:x1]
    inside = np.hypot(xs - start[0], ys - start[1]) <= reach
    use = inside & ~clipped
    if np.count_nonzero(use) < _MIN_LIGHT_PIXELS:
        return None
    # The ambient level: the box's darkest pixels.
    background = float(np.percentile(light, 2.0))
    # Rows are numbered among those with a pixel used: a row all clipped has no level to fit.
    lit_rows, row = np.unique(ys[use], return_inverse=True)
    fit = _radial_fit(xs[use].astype(float), ys[use].astype(float), row, light[use] - background, start, reach,
                      len(lit_rows))
    if fit is None or np.hypot(*(fit[0] - start)) > max_shift:
        return None
    # Each box row's level, the brightest 1 (a row with no pixel used lies where the light clips: 1).
    levels = np.ones(y1 - y0)
    levels[lit_rows - y0] = fit[2] / fit[2].max()
    return _Fit(fit[0], fit[1], reach, float(np.count_nonzero(inside & clipped) / np.count_nonzero(inside)),
                (light - background) / levels[:, None], clipped, inside, (x0, y0), float(saturation_level - background))


def _radial_fit(x: np.ndarray, y: np.ndarray, row: np.ndarray, value: np.ndarray, centre: np.ndarray, reach: float,
                rows: int) -> tuple[np.ndarray, float, np.ndarray] | None:
    """
    Centre and its sigma of s(row) f(r) fitted to the pixels (``x``, ``y``) of ``value``, ``row`` their rows' index.

    Also each row's level. f is piecewise linear on knots ``_KNOT_PX`` apart (smoothed by a penalty on its
    curvature), s one level per row. A few alternating linear steps (f, then s) start it; then
    Levenberg-Marquardt (Nielsen's damping schedule) on all of them and the centre together, since a centre
    moved up or down is nearly undone by the rows' levels alone, until a step moves the centre by a small
    share of its sigma and hardly lowers the cost. The centre's sigma is its marginal from that fit, the rows' levels
    and the shape free.
    """
    penalty = _curvature_penalty(int(np.ceil(reach / _KNOT_PX)) + 2)
    try:
        found, fitted, covariance, level = _levenberg_marquardt(x, y, row, value, float(centre[0]),
                                                                float(centre[1]), rows, penalty)
    except np.linalg.LinAlgError:
        return None
    if not found:
        return None
    sigma = _LIGHT_CORRELATION * math.sqrt(max(covariance[0], covariance[1], 0.0))
    return fitted, max(sigma, _LIGHT_SIGMA_FLOOR), level


@kernel
def _curvature_penalty(knots: int) -> np.ndarray:
    """Return ``_SMOOTHNESS`` C^T C, C the knots' second differences (rows 1 -2 1): five diagonals."""
    penalty = np.zeros((knots, knots))
    for i in range(knots - 2):
        for a, wa in ((0, 1.0), (1, -2.0), (2, 1.0)):
            for b, wb in ((0, 1.0), (1, -2.0), (2, 1.0)):
                penalty[i + a, i + b] += _SMOOTHNESS * wa * wb
    return penalty


@kernel
def _levenberg_marquardt(x: np.ndarray, y: np.ndarray, row: np.ndarray, value: np.ndarray, cx: float, cy: float,
                         rows: int, penalty: np.ndarray) -> tuple[bool, np.ndarray, np.ndarray, np.ndarray]:
    """
    ``_radial_fit``'s start and iterations: whether it converged, the centre, its variances and the levels.

    Each row's level enters the model linearly and meets only its own row's pixels, so the levels'
    block of the normal matrix is diagonal but for the gauge's rank-one term: the levels are eliminated
    in closed form (a Schur complement, Sherman-Morrison for the gauge), leaving a system the size of the
    shape. The steps and the centre's marginal are those of the whole system, to rounding.
    """
    knots = penalty.shape[0]
    level = np.ones(rows)
    shape = np.zeros(knots)
    for _ in range(_START_STEPS):
        shape = _shape(x, y, row, value, cx, cy, level, penalty)
        level = _row_levels(x, y, row, value, cx, cy, shape, rows)
    damping, growth = 1e-3, 2.0
    linearised = _linearised(x, y, row, value, cx, cy, level, shape, penalty)
    cost, diagonal, mixed, spans, block, level_gradient, gradient = linearised
    if not np.all(diagonal > 0.0):
        return False, np.zeros(2), np.zeros(2), level
    # Converged once a step moves the centre by a small share of its own sigma (as the start's linearisation
    # gives it) and the cost hardly falls: a slow valley of the shape and levels still carries the centre.
    marginal = _centre_marginal(diagonal, mixed, spans, block)
    converged = max(_CONVERGED_SIGMA * math.sqrt(max(cost / max(value.size - rows - knots - 2, 1) * marginal, 0.0)),
                    _CONVERGED_PX)
    for _ in range(_MAX_ITERATIONS):
        level_step, step = _damped_step(diagonal, mixed, spans, block, level_gradient, gradient, damping)
        tx, ty = cx + step[knots], cy + step[knots + 1]
        if not (math.isfinite(tx) and math.isfinite(ty)):
            return False, np.zeros(2), np.zeros(2), level
        trial_level, trial_shape = level + level_step, shape + step[:knots]
        trial = _cost(x, y, row, value, tx, ty, trial_level, trial_shape, penalty)
        predicted = _predicted_reduction(diagonal, block, level_gradient, gradient, level_step, step, damping)
        if not trial < cost or predicted <= 0.0:
            # Nielsen's schedule: the damping grows ever faster while steps fail.
            damping *= growth
            growth *= 2.0
            if damping > 1e6:
                break
            continue
        ratio = (cost - trial) / predicted
        damping = max(damping * max(1.0 / 3.0, 1.0 - (2.0 * ratio - 1.0) ** 3), 1e-7)
        growth = 2.0
        settled = math.hypot(step[knots], step[knots + 1]) < converged and cost - trial < _CONVERGED_COST_SHARE * trial
        cx, cy, level, shape = tx, ty, trial_level, trial_shape
        cost, diagonal, mixed, spans, block, level_gradient, gradient = _linearised(x, y, row, value, cx, cy, level,
                                                                                    shape, penalty)
        if settled:
            break
    size = rows + knots + 2
    variance = cost / max(value.size - size, 1)
    if not np.all(diagonal > 0.0):
        return False, np.zeros(2), np.zeros(2), level
    inverse = np.linalg.inv(_reduced(diagonal, mixed, spans, block, 0.0))
    return (True, np.array([cx, cy]), variance * np.array([inverse[knots, knots], inverse[knots + 1, knots + 1]]),
            level)


@kernel
def _centre_marginal(diagonal: np.ndarray, mixed: np.ndarray, spans: np.ndarray, block: np.ndarray) -> float:
    """Return the larger of the centre's two diagonal entries in the inverse normal matrix (per unit variance)."""
    m = block.shape[0]
    unit = np.zeros((m, 2))
    unit[m - 2, 0], unit[m - 1, 1] = 1.0, 1.0
    columns = np.linalg.solve(_reduced(diagonal, mixed, spans, block, 0.0), unit)
    return max(columns[m - 2, 0], columns[m - 1, 1])


@kernel
def _predicted_reduction(diagonal: np.ndarray, block: np.ndarray, level_gradient: np.ndarray, gradient: np.ndarray,
                         level_step: np.ndarray, step: np.ndarray, damping: float) -> float:
    """Return the cost's drop the linearised model predicts for a damped step: step . (damping D step + gradient)."""
    levels = level_step @ (damping * (diagonal + _GAUGE + 1e-12) * level_step + level_gradient)
    rest = 0.0
    for j in range(step.size):
        rest += step[j] * (damping * (block[j, j] + 1e-12) * step[j] + gradient[j])
    return levels + rest


@kernel
def _reduced(diagonal: np.ndarray, mixed: np.ndarray, spans: np.ndarray, block: np.ndarray, damping: float
             ) -> np.ndarray:
    """
    Return the Schur complement of the (damped) levels' block in the normal matrix.

    That block is diag(``diagonal``) + gauge 1 1^T, ``mixed`` (rows, m) the levels' rows against the
    rest, nonzero only in each row's ``spans`` of knots (rows, 2) and the centre's last two columns;
    ``block`` (m, m) the rest's own.
    """
    m = block.shape[0]
    complement = block.copy()
    for j in range(m):
        complement[j, j] += damping * (block[j, j] + 1e-12)
    u = 1.0 / (diagonal + damping * (diagonal + _GAUGE + 1e-12))
    column = np.zeros(m)
    for i in range(diagonal.size):
        columns = _span(spans[i, 0], spans[i, 1], m)
        for p in range(columns.size):
            a = columns[p]
            weighted = u[i] * mixed[i, a]
            column[a] += weighted
            for q in range(p, columns.size):
                complement[a, columns[q]] -= weighted * mixed[i, columns[q]]
    gauge = _GAUGE / (1.0 + _GAUGE * u.sum())
    for a in range(m):
        for b in range(a, m):
            complement[a, b] += gauge * column[a] * column[b]
            complement[b, a] = complement[a, b]
    return complement


@kernel
def _span(first: int, last: int, m: int) -> np.ndarray:
    """Return the columns of ``mixed`` a row touches: its knots ``first``-``last`` and the centre's two."""
    columns = np.empty(last - first + 3, np.int64)
    columns[:last - first + 1] = np.arange(first, last + 1)
    columns[-2], columns[-1] = m - 2, m - 1
    return columns


@kernel
def _levels_solve(diagonal: np.ndarray, damping: float, right: np.ndarray) -> np.ndarray:
    """Return the (damped) levels' block, diag(``diagonal``) + gauge 1 1^T, solved for ``right``."""
    u = 1.0 / (diagonal + damping * (diagonal + _GAUGE + 1e-12))
    solved = u * right
    return solved - u * (_GAUGE * solved.sum() / (1.0 + _GAUGE * u.sum()))


@kernel
def _damped_step(diagonal: np.ndarray, mixed: np.ndarray, spans: np.ndarray, block: np.ndarray,
                 level_gradient: np.ndarray, gradient: np.ndarray, damping: float) -> tuple[np.ndarray, np.ndarray]:
    """Return the Levenberg-Marquardt step of the levels and of the rest (shape, centre)."""
    complement = _reduced(diagonal, mixed, spans, block, damping)
    right = gradient - _levels_solve(diagonal, damping, level_gradient) @ mixed
    step = np.linalg.solve(complement, right)
    return _levels_solve(diagonal, damping, level_gradient - mixed @ step), step


@kernel
def _linearised(x: np.ndarray, y: np.ndarray, row: np.ndarray, value: np.ndarray, cx: float, cy: float,
                level: np.ndarray, shape: np.ndarray, penalty: np.ndarray
                ) -> tuple[float, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """
    Return the cost of ``_radial_fit``'s model and its Gauss-Newton normal equations, by blocks.

    The levels' block's diagonal (the gauge's 1 1^T left implicit), the levels against the shape's knots
    and the centre (rows, knots + 2) and the span of knots each row touches, the knots' and centre's own
    block and the gradients of both.
    """
    rows, knots = level.size, shape.size
    diagonal = np.zeros(rows)
    level_gradient = np.zeros(rows)
    mixed = np.zeros((rows, knots + 2))
    spans = np.empty((rows, 2), np.int64)
    spans[:, 0], spans[:, 1] = knots, 0
    block = np.zeros((knots + 2, knots + 2))
    gradient = np.zeros(knots + 2)
    cost = 0.0
    for i in range(value.size):
        dx, dy = x[i] - cx, y[i] - cy
        r = max(math.hypot(dx, dy), 1e-9)
        k = min(int(r / _KNOT_PX), knots - 2)
        t = r / _KNOT_PX - k
        j = row[i]
        s = level[j]
        g = (1.0 - t) * shape[k] + t * shape[k + 1]
        residual = value[i] - s * g
        # d(model)/d(centre): the shape's slope along the pixel's direction from the centre, reversed.
        slope = (shape[k + 1] - shape[k]) / _KNOT_PX
        a0, a1 = s * (1.0 - t), s * t
        ax, ay = -s * slope * dx / r, -s * slope * dy / r
        cost += residual * residual
        diagonal[j] += g * g
        level_gradient[j] += g * residual
        spans[j, 0], spans[j, 1] = min(spans[j, 0], k), max(spans[j, 1], k + 1)
        mixed[j, k] += g * a0
        mixed[j, k + 1] += g * a1
        mixed[j, knots] += g * ax
        mixed[j, knots + 1] += g * ay
        block[k, k] += a0 * a0
        block[k + 1, k + 1] += a1 * a1
        block[k, k + 1] += a0 * a1
        block[k, knots] += a0 * ax
        block[k, knots + 1] += a0 * ay
        block[k + 1, knots] += a1 * ax
        block[k + 1, knots + 1] += a1 * ay
        block[knots, knots] += ax * ax
        block[knots, knots + 1] += ax * ay
        block[knots + 1, knots + 1] += ay * ay
        gradient[k] += a0 * residual
        gradient[k + 1] += a1 * residual
        gradient[knots] += ax * residual
        gradient[knots + 1] += ay * residual
    for k in range(knots - 1):
        block[k + 1, k] = block[k, k + 1]
    for k in range(knots):
        block[knots, k] = block[k, knots]
        block[knots + 1, k] = block[k, knots + 1]
    block[knots + 1, knots] = block[knots, knots + 1]
    block[:knots, :knots] += penalty
    smoothing = penalty @ shape
    gradient[:knots] -= smoothing
    # The product s f keeps its scale free: the levels' sum is held.
    excess = level.sum() - rows
    level_gradient -= _GAUGE * excess
    cost += shape @ smoothing + _GAUGE * excess ** 2
    return cost, diagonal, mixed, spans, block, level_gradient, gradient


@kernel
def _cost(x: np.ndarray, y: np.ndarray, row: np.ndarray, value: np.ndarray, cx: float, cy: float, level: np.ndarray,
          shape: np.ndarray, penalty: np.ndarray) -> float:
    """Return the cost of ``_radial_fit``'s model alone, as ``_linearised`` sums it."""
    knots = shape.size
    cost = 0.0
    for i in range(value.size):
        r = max(math.hypot(x[i] - cx, y[i] - cy), 1e-9)
        k = min(int(r / _KNOT_PX), knots - 2)
        t = r / _KNOT_PX - k
        residual = value[i] - level[row[i]] * ((1.0 - t) * shape[k] + t * shape[k + 1])
        cost += residual * residual
    return cost + shape @ (penalty @ shape) + _GAUGE * (level.sum() - level.size) ** 2


@kernel
def _shape(x: np.ndarray, y: np.ndarray, row: np.ndarray, value: np.ndarray, cx: float, cy: float,
           level: np.ndarray, penalty: np.ndarray) -> np.ndarray:
    """Least squares of ``value`` = level (interpolated shape) about (``cx``, ``cy``): the shape's knots."""
    knots = penalty.shape[0]
    # Each pixel touches two knots: the normal equations' three diagonals, summed pixel by pixel.
    normal = penalty.copy()
    right = np.zeros(knots)
    for i in range(value.size):
        r = max(math.hypot(x[i] - cx, y[i] - cy), 1e-9)
        k = min(int(r / _KNOT_PX), knots - 2)
        t = r / _KNOT_PX - k
        s = level[row[i]]
        a0, a1 = s * (1.0 - t), s * t
        normal[k, k] += a0 * a0
        normal[k + 1, k + 1] += a1 * a1
        normal[k, k + 1] += a0 * a1
        normal[k + 1, k] += a0 * a1
        right[k] += a0 * value[i]
        right[k + 1] += a1 * value[i]
    for k in range(knots):
        normal[k, k] += 1e-9
    return np.linalg.solve(normal, right)


@kernel
def _row_levels(x: np.ndarray, y: np.ndarray, row: np.ndarray, value: np.ndarray, cx: float, cy: float,
                shape: np.ndarray, rows: int) -> np.ndarray:
    """Each row's level: the least-squares scale of the shape about (``cx``, ``cy``) to the row's light, the top 1."""
    knots = shape.size
    along = np.zeros(rows)
    power = np.zeros(rows)
    for i in range(value.size):
        r = max(math.hypot(x[i] - cx, y[i] - cy), 1e-9)
        k = min(int(r / _KNOT_PX), knots - 2)
        t = r / _KNOT_PX - k
        g = (1.0 - t) * shape[k] + t * shape[k + 1]
        along[row[i]] += g * value[i]
        power[row[i]] += g * g
    level = along / np.maximum(power, 1e-12)
    top = level.max()
    return level / top if top > 0.0 else np.ones(rows)


def measured_as_point(image: np.ndarray, observation: LampObservation, saturation_level: float = 250.0
                      ) -> LampObservation:
    """
    Return ``observation`` as a point lamp's light: its centre and sigma from ``measure_light_centre``.

    A bare LED's round core may pass for a disc, whose rim sits where the stripes and the clip put
    it; as a point it has no rim and no marker. The observation itself when its light gives no centre.
    """
    radius = float(observation.ellipse[2])
    light = measure_light_centre(image, observation.center, radius, saturation_level)
    if light is None:
        return observation
    return replace(observation, ellipse=np.array([*light.center, radius, radius, 0.0]), rim_points=np.zeros((0, 2)),
                   rim_sigma=float('inf'), marker=None, marker_sigma=float('inf'), rim_usable=False,
                   center_sigma=light.sigma, rim_model_sigma=0.0)
