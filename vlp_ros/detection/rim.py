"""Sub-pixel points on a lamp's true disc edge, and the ellipse through them.

A rolling shutter gives every row of the lamp one brightness, so the left and
right ends of each lit row are true disc edges while the tops and bottoms of the
stripes are not. Each row is normalised on its own: the edge is where the row
crosses half-way between the background and that row's plateau inside the
disc, which neither the modulation nor a symmetric blur can move.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vlp_ros.detection.rows import RowLevels
from vlp_ros.ellipse import conic_from_ellipse, fit_ellipse, geometric_distances

# Robust (MAD) standard deviation of a normal distribution.
_MAD_TO_SIGMA = 1.4826


@dataclass(frozen=True)
class RimFit:
    """The ellipse through the kept rim points, their robust spread across the edge (px)."""

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


def edge_slopes(ellipse: np.ndarray, points: np.ndarray) -> np.ndarray:
    """|dx/dy| of the ellipse's edge near each point: large where a row meets the edge at a grazing angle."""
    C = conic_from_ellipse(ellipse)
    h = np.column_stack([points, np.ones(len(points))])
    gradient = (h @ C)[:, :2]
    return np.abs(gradient[:, 1]) / np.maximum(np.abs(gradient[:, 0]), 1e-12)


def fit_rim(points: np.ndarray, max_slope: float, outlier_sigmas: float,
            min_sigma: float) -> RimFit:
    """Ellipse through row crossings: grazing rows dropped, then outliers beyond ``outlier_sigmas``.

    Raises ValueError when too few points remain for a fit.
    """
    ellipse = fit_ellipse(points)
    kept = points[edge_slopes(ellipse, points) <= max_slope]
    ellipse = fit_ellipse(kept)
    candidates = len(kept)
    distances = geometric_distances(ellipse, kept)
    scale = max(_MAD_TO_SIGMA * np.median(np.abs(distances)), min_sigma)
    kept = kept[np.abs(distances) <= outlier_sigmas * scale]
    ellipse = fit_ellipse(kept)
    distances = geometric_distances(ellipse, kept)
    sigma = max(_MAD_TO_SIGMA * float(np.median(np.abs(distances - np.median(distances)))), min_sigma)
    return RimFit(ellipse, kept, sigma, candidates)
