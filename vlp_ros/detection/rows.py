"""Rows of a rolling-shutter lamp: each row has one brightness across the disc.

A row's level is the median of samples over the middle half of its chord, well
away from the blurred edge and from a marker at the rim.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr

from vlp_ros.ellipse import conic_from_ellipse, geometric_distances
from vlp_ros.small_arrays import percentile

# Plateau samples per row, spread over the middle half of the row's chord.
_FRACTIONS = np.linspace(0.25, 0.75, 9)
# Once the ellipse is known, more of them (a row's two rim points share its plateau's
# error), of which at least a few must lie well inside the edge.
_CLEAR_FRACTIONS = np.linspace(0.25, 0.75, 25)
_MIN_CLEAR_SAMPLES = 5


@dataclass(frozen=True)
class RowLevels:
    """The lit rows of one lamp: row index, first and last pixel above threshold, plateau level."""

    rows: np.ndarray
    first: np.ndarray
    last: np.ndarray
    plateau: np.ndarray


def row_levels(brightness: np.ndarray, threshold: float, background: float,
               level_fraction: float) -> RowLevels:
    """Rows bright enough to carry edges: plateau above ``level_fraction`` of the typical lit row.

    ``brightness`` holds one lamp (2D); ``threshold`` separates it from the background.
    """
    above = brightness > threshold
    lit = np.flatnonzero(above.any(axis=1))
    if lit.size == 0:
        return RowLevels(*(np.zeros(0, dtype=int),) * 3, np.zeros(0))
    above = above[lit]
    first = np.argmax(above, axis=1)
    last = brightness.shape[1] - 1 - np.argmax(above[:, ::-1], axis=1)
    span = last - first
    # The middle half of the chord is well away from the blurred edge (and from a marker at the rim).
    cols = np.rint(first[:, None] + span[:, None] * _FRACTIONS[None, :]).astype(int)
    plateau = _median_of_rows(brightness[lit[:, None], cols])
    reference = percentile(plateau, 90.0)
    keep = (span >= 2) & (plateau - background >= level_fraction * (reference - background))
    return RowLevels(lit[keep], first[keep], last[keep], plateau[keep])


def clear_levels(brightness: np.ndarray, levels: RowLevels, ellipse: np.ndarray, clearance: float,
                 marker: tuple[np.ndarray, float] | None) -> RowLevels:
    """``levels`` with each row's plateau measured again where the disc is at least ``clearance`` (px)
    inside ``ellipse``, on the middle half of the row's chord, away from the ``marker`` disc
    (centre, radius) if given; rows without enough such samples are dropped.

    Blur dims the disc within a few blurs of its edge, and near the disc's top and
    bottom that reaches the middle of the chord: a plateau a few tenths of a level low
    there moves the rows' half-level crossings outward by a hundredth of a pixel in
    the rows that meet the edge obliquely. A marker of another colour does the same to
    the rows it crosses. (The median of noisy samples, some of them dimmed, is lower
    than the noise-free one, so both grow with the noise.)
    """
    left, right, crossed = ellipse_chords(ellipse, levels.rows)
    cols = left[:, None] + (right - left)[:, None] * _CLEAR_FRACTIONS[None, :]
    rows = np.broadcast_to(levels.rows[:, None], cols.shape)
    depth = -geometric_distances(ellipse, np.column_stack([cols.ravel(), rows.ravel()])).reshape(cols.shape)
    samples = brightness[rows, np.clip(np.rint(cols), 0, brightness.shape[1] - 1).astype(int)].astype(float)
    usable = depth >= clearance
    if marker is not None:
        usable &= np.hypot(cols - marker[0][0], rows - marker[0][1]) > marker[1]
    count = np.count_nonzero(usable, axis=1)
    keep = crossed & (count >= _MIN_CLEAR_SAMPLES)
    # Unusable samples sort last (np.nanmedian costs ten times as much).
    ordered = np.sort(np.where(usable, samples, np.inf)[keep], axis=1)
    plateau = np.take_along_axis(ordered, (count[keep] // 2)[:, None], axis=1)[:, 0]
    return RowLevels(levels.rows[keep], levels.first[keep], levels.last[keep], plateau)


def steady_rows(profile: np.ndarray, tolerance: float, floor: float) -> np.ndarray:
    """Rows that share their level with a neighbouring row within ``tolerance`` of it (plus ``floor``).

    Where blur has mixed a row with a neighbour of another level, its level lies between
    the two stripes' and matches neither neighbour; such a row's profile is not its own.
    Rows of unknown (NaN) level are never steady.
    """
    padded = np.pad(profile, 1, constant_values=np.nan)
    closest = np.fmin(np.abs(padded[:-2] - profile), np.abs(padded[2:] - profile))
    with np.errstate(invalid='ignore'):
        return closest <= tolerance * np.abs(profile) + floor


def ellipse_chords(ellipse: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(left, right, crossed): where each row (y = ``rows``) enters and leaves the ellipse."""
    conic = conic_from_ellipse(ellipse)
    y = np.asarray(rows, dtype=float)
    # The row's conic in x: a x^2 + b x + c = 0.
    a = conic[0, 0]
    b = 2.0 * (conic[0, 1] * y + conic[0, 2])
    c = conic[1, 1] * y * y + 2.0 * conic[1, 2] * y + conic[2, 2]
    discriminant = b * b - 4.0 * a * c
    root = np.sqrt(np.maximum(discriminant, 0.0))
    return (-b - root) / (2.0 * a), (-b + root) / (2.0 * a), discriminant > 0.0


def row_profile(brightness: np.ndarray, ellipse: np.ndarray, background: float, blur: float) -> np.ndarray:
    """Every row's level above ``background`` inside ``ellipse`` (array pixels).

    Near the disc's top and bottom the blurred edge dims the disc itself: the
    plateau is divided by the blurred disc's value at the middle of the chord
    (Gaussian ``blur``). NaN for rows that miss the ellipse or whose chord middle
    lies within two blurs of the edge, where that correction would dominate.
    """
    rows = np.arange(brightness.shape[0])
    left, right, crossed = ellipse_chords(ellipse, rows)
    clearance = -geometric_distances(ellipse, np.column_stack([0.5 * (left + right), rows]))
    crossed &= (left >= 0.0) & (right <= brightness.shape[1] - 1) & (clearance >= 2.0 * blur)
    profile = np.full(rows.size, np.nan)
    inside = np.flatnonzero(crossed)
    cols = np.rint(left[inside, None] + (right - left)[inside, None] * _FRACTIONS[None, :]).astype(int)
    plateau = _median_of_rows(brightness[inside[:, None], cols]) - background
    profile[inside] = plateau / ndtr(clearance[inside] / blur)
    return profile


def _median_of_rows(samples: np.ndarray) -> np.ndarray:
    return np.partition(samples, samples.shape[1] // 2, axis=1)[:, samples.shape[1] // 2].astype(float)
