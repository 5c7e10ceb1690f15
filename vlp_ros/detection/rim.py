"""Sub-pixel points on a lamp's true disc edge, and the ellipse through them.

A rolling shutter gives every row of the lamp one brightness, so the left and
right ends of each lit row are true disc edges while the tops and bottoms of the
stripes are not. Each row is normalised on its own: the edge is where the row
crosses half-way between the background and that row's plateau inside the
disc, which neither the modulation nor a straight edge's symmetric blur can
move. A curved edge's can: blur pulls the half level of a convex disc inward
by kappa s^2 / 2 (``blur_shifts``). A clipped row's plateau is not its
brightness, so its crossing lies outside the edge: ``clipped_edge_offset``
measures by how much.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.special import ndtr, ndtri

from vlp_ros.detection.rows import RowLevels
from vlp_ros.ellipse import conic_from_ellipse, fit_ellipse, geometric_distances
from vlp_ros.small_arrays import median

# Robust (MAD) standard deviation of a normal distribution.
_MAD_TO_SIGMA = 1.4826
_ELLIPSE_PARAMETERS = 5
# Clipped rows pooled to measure how far their crossings lie outside the edge.
_MAX_POOLED_ROWS = 200
# Ramp pixels within this (of the row's step) of background or plateau give probits
# too noisy to measure the blur with.
_PROBIT_MARGIN = 0.03
_MIN_BLUR_ROWS = 10


@dataclass(frozen=True)
class RimFit:
    """The ellipse through the kept rim points, their RMS distance across the edge (px), and
    how many points were left after grazing rows were dropped (before outlier rejection)."""

    ellipse: np.ndarray
    points: np.ndarray
    sigma: float
    candidates: int


def row_crossings(brightness: np.ndarray, levels: RowLevels, background: float,
                  reach: int) -> tuple[np.ndarray, np.ndarray]:
    """Left and right half-level crossings of every row, as points (N, 2) in the array's pixels.

    Returns the points and each one's row plateau. ``reach`` bounds how far inside
    the first pixel above threshold the crossing may lie. Rows whose edge leaves the
    array give no point.
    """
    if levels.rows.size == 0:
        return np.zeros((0, 2)), np.zeros(0)
    half = 0.5 * (levels.plateau + background)
    width = brightness.shape[1]
    steps = np.arange(-1, reach + 1)
    points, plateaus = [], []
    for start, direction in ((levels.first, 1), (levels.last, -1)):
        cols = start[:, None] + direction * steps[None, :]
        inside = (cols >= 0) & (cols < width)
        values = brightness[levels.rows[:, None], np.clip(cols, 0, width - 1)].astype(float)
        # Outside the array counts as bright, so a clipped edge yields no crossing.
        values[~inside] = np.inf
        reached = values >= half[:, None]
        k = np.argmax(reached, axis=1)
        ok = (k > 0) & reached[np.arange(k.size), k]
        rows = np.flatnonzero(ok)
        k = k[ok]
        outer, inner = values[rows, k - 1], values[rows, k]
        fraction = (half[rows] - outer) / (inner - outer)
        x = cols[rows, k - 1] + direction * fraction
        points.append(np.column_stack([x, levels.rows[rows].astype(float)]))
        plateaus.append(levels.plateau[rows])
    return np.concatenate(points), np.concatenate(plateaus)


def outward_normals(ellipse: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Unit normals (N, 2) of the ellipse's level curves at ``points``, pointing outward."""
    C = conic_from_ellipse(ellipse)
    gradient = (np.column_stack([points, np.ones(len(points))]) @ C)[:, :2]
    return gradient / np.maximum(np.linalg.norm(gradient, axis=1, keepdims=True), 1e-12)


def clipped_edge_offset(brightness: np.ndarray, points: np.ndarray, ellipse: np.ndarray, background: float,
                        saturation_level: float, max_blur: float) -> tuple[float, float] | None:
    """(edge, overexposure): how far (px) inside ``ellipse``, fitted to half-clip crossings of
    clipped rows, the true edge lies, and the rows' level over the clip level.

    A clipped row's plateau is not its brightness A, so its half level sits low on
    the blurred edge, outside the true edge. The rows' ramps, pooled in distance t
    across the ellipse, show the unclipped foot of B + A Phi((-edge - t) / sigma)
    averaged over the pixel's square; fitting A, sigma and the edge to it (clipped
    pixels as censored: the model must reach the clip) places the edge. Only rows
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
    v = values - background
    # The pixel square seen across the edge: offsets of a 3 x 3 grid of its points along each normal.
    grid = (np.arange(3) - 1.0) / 3.0
    qx, qy = (g.ravel() for g in np.meshgrid(grid, grid))
    normal = np.abs(np.broadcast_to(normals[:, None, :], cols.shape + (2,))[keep])
    spread = normal[:, :1] * qx[None, :] + normal[:, 1:] * qy[None, :]

    def residual(params: np.ndarray) -> np.ndarray:
        amplitude, sigma, edge = params
        difference = amplitude * ndtr((-edge - t[:, None] - spread) / sigma).mean(axis=1) - v
        return np.where(censored, np.minimum(difference, 0.0), difference)

    clip = saturation_level - background
    result = least_squares(residual, np.array([2.0 * clip, 0.5 * max_blur, 0.5]),
                           bounds=([clip, 0.2, -1.0], [np.inf, 2.0 * max_blur, 4.0 * max_blur]))
    if not result.success:
        return None
    amplitude, _, edge = result.x
    return float(edge), float(amplitude / clip)


def blur_variance(brightness: np.ndarray, points: np.ndarray, plateaus: np.ndarray, background: float,
                  ellipse: np.ndarray) -> float | None:
    """Variance (px^2) across the edge of the blur it went through (optics and pixel area together),
    from the ramps of unclipped rows at their crossings ``points``; None if too few rows tell.

    A Gaussian-blurred edge with unit normal n reads Phi(+-(edge - x) |n_x| / s) along
    a row, so the probits of the two pixels around the crossing differ by |n_x| / s.
    The pixel's square adds its variance 1/12 along every direction, as a Gaussian
    of that variance would.
    """
    cols = np.floor(points[:, 0]).astype(int)
    rows = points[:, 1].astype(int)
    inside = (cols >= 0) & (cols + 1 < brightness.shape[1]) & (plateaus > background)
    cols, rows = cols[inside], rows[inside]
    step = plateaus[inside] - background
    left = (brightness[rows, cols] - background) / step
    right = (brightness[rows, cols + 1] - background) / step
    usable = (np.minimum(left, right) > _PROBIT_MARGIN) & (np.maximum(left, right) < 1.0 - _PROBIT_MARGIN)
    if np.count_nonzero(usable) < _MIN_BLUR_ROWS:
        return None
    across = np.abs(outward_normals(ellipse, points[inside][usable])[:, 0])
    sigma = across / np.abs(ndtri(right[usable]) - ndtri(left[usable]))
    return median(sigma) ** 2


def blur_shifts(ellipse: np.ndarray, points: np.ndarray, variance: float) -> np.ndarray:
    """Moves (N, 2) that put half-level crossings of a blurred disc back on its edge.

    Blur of variance s^2 along the edge's tangent bends it by kappa t^2 / 2 over the
    kernel's reach (kappa the curvature), so less than half the kernel lies inside a
    convex edge at the edge itself: the half level lies kappa s^2 / 2 inside it (0.3 px
    over the radius in px for a 0.7 px optics blur). It has the same sign at every rim
    point, so it shrinks the fitted ellipse: by twice the size's own standard deviation
    (0.0045 px against 0.0023 px) for a 4K lamp 2 m away.
    """
    cx, cy, a, b, theta = (float(v) for v in ellipse)
    c, s = np.cos(theta), np.sin(theta)
    local = (points - [cx, cy]) @ np.array([[c, -s], [s, c]])
    # The curvature of the ellipse at the parameter angle t of each point.
    t = np.arctan2(local[:, 1] / b, local[:, 0] / a)
    curvature = a * b / (a * a * np.sin(t) ** 2 + b * b * np.cos(t) ** 2) ** 1.5
    return (0.5 * variance * curvature)[:, None] * outward_normals(ellipse, points)


def edge_slopes(ellipse: np.ndarray, points: np.ndarray) -> np.ndarray:
    """|dx/dy| of the ellipse's edge near each point: large where a row meets the edge at a grazing angle."""
    C = conic_from_ellipse(ellipse)
    h = np.column_stack([points, np.ones(len(points))])
    gradient = (h @ C)[:, :2]
    return np.abs(gradient[:, 1]) / np.maximum(np.abs(gradient[:, 0]), 1e-12)


def fit_rim(points: np.ndarray, max_slope: float, outlier_sigmas: float,
            min_sigma: float, near: np.ndarray | None = None) -> RimFit:
    """Ellipse through row crossings: grazing rows dropped, then outliers beyond ``outlier_sigmas``.

    ``near``: an ellipse already close to the points, to tell the grazing rows by.
    Raises ValueError when too few points remain for a fit.
    """
    # A rough ellipse through a quarter of the points is enough to tell the grazing rows.
    ellipse = near if near is not None else fit_ellipse(points[::4] if len(points) >= 40 else points)
    kept = points[edge_slopes(ellipse, points) <= max_slope]
    ellipse = fit_ellipse(kept)
    candidates = len(kept)
    distances = geometric_distances(ellipse, kept)
    scale = max(_MAD_TO_SIGMA * median(np.abs(distances)), min_sigma)
    inliers = np.abs(distances) <= outlier_sigmas * scale
    if not inliers.all():
        kept = kept[inliers]
        ellipse = fit_ellipse(kept)
        distances = geometric_distances(ellipse, kept)
    # The pose fit weighs every point alike, so its covariance scales with their mean square
    # distance (over the degrees of freedom the ellipse leaves), not with their median spread:
    # rows differ in brightness, hence in noise, and the points' spread is heavier-tailed than
    # a normal's (MAD-based sigma 3-7 % short of the RMS).
    sigma = max(float(np.sqrt(distances @ distances / max(len(distances) - _ELLIPSE_PARAMETERS, 1))), min_sigma)
    return RimFit(ellipse, kept, sigma, candidates)
