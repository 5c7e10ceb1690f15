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

from dataclasses import dataclass
import math

import numpy as np

from vlp_ros.compiled.small_arrays import median

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
# Largest lag-one correlation of the residuals of adjacent rows counted.
_MAX_CORRELATION = 0.8


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
              noise_factor: float, saturation_level: float) -> PointFit | None:
    """
    Return the centre of the light in ``brightness`` (one lamp's box, one channel).

    None when its core is not round enough, or too small (``min_radius`` px), to give one.

    A clipped row's maximum is not its level, and where it leaves the clip depends on how
    far its stripe overexposes it: clipped rows are used only when the unclipped ones give
    too few crossings or no round core (the dark stripes alone may span too few of its rows),
    and their scatter (stripe by stripe) then widens the centre's sigma.
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
    return fit if fit is not None or not np.any(core & clipped) else _core_fit(points, rows, core, min_radius)


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
    points, rows = [], []
    width = light.shape[1]
    clip = saturation_level - 1.0 - background
    for row in np.flatnonzero((maxima > _MIN_ROW_SHARE * peak) & (maxima > floor)):
        profile = light[row]
        # A clipped row's maximum is not its level: where it leaves the clip is a level crossing
        # of its own (half of the clip would lie out in the glow).
        half = clip if maxima[row] >= clip else 0.5 * maxima[row]
        top = int(np.argmax(profile))
        left = top
        while left > 0 and profile[left - 1] >= half:
            left -= 1
        right = top
        while right < width - 1 and profile[right + 1] >= half:
            right += 1
        if left == 0 or right == width - 1:
            continue
        # Linear interpolation between the last pixel below half and the first above it.
        x_left = left - (profile[left] - half) / (profile[left] - profile[left - 1])
        x_right = right + (profile[right] - half) / (profile[right] - profile[right + 1])
        points += [(x_left, row), (x_right, row)]
        rows.append(row)
    rows = np.asarray(rows, dtype=int)
    return np.asarray(points, dtype=float).reshape(-1, 2), rows, maxima[rows] >= clip


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
