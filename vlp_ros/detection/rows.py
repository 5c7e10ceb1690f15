"""
Rows of a rolling-shutter lamp: each row has one brightness across the disc.

A row's level is the median of samples over the middle half of its chord, well
away from the blurred edge and from a marker at the rim. The per-row loops are
compiled kernels (``vlp_ros.compiled``): numpy's per-call cost on a lamp's few
hundred rows exceeds the arithmetic.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from typing import NamedTuple

import numpy as np
from scipy.special import ndtr

from vlp_ros.compiled import kernel
from vlp_ros.compiled.small_arrays import percentile, ranked
from vlp_ros.core.ellipse import conic_distance, conic_of

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
    """
    Rows bright enough to carry edges: plateau above ``level_fraction`` of the typical lit row.

    ``brightness`` holds one lamp (2D); ``threshold`` separates it from the background.
    """
    lit = _lit_rows(brightness, float(threshold))
    if lit.rows.size == 0:
        return RowLevels(*(np.zeros(0, dtype=int),) * 3, np.zeros(0))
    # Wide enough, and bright enough against the 90th percentile (a kernel, as np.percentile costs ~20 us).
    reference = percentile(lit.plateau, 90.0)
    keep = (lit.last - lit.first >= 2) & (lit.plateau - background >= level_fraction * (reference - background))
    return RowLevels(lit.rows[keep], lit.first[keep], lit.last[keep], lit.plateau[keep])


class _LitRows(NamedTuple):
    """``_lit_rows``' result: ``RowLevels``' fields before the rows too dim or narrow are dropped."""

    rows: np.ndarray
    first: np.ndarray
    last: np.ndarray
    plateau: np.ndarray


@kernel
def _lit_rows(brightness: np.ndarray, threshold: float) -> _LitRows:
    """Rows with a pixel above ``threshold``: index, first and last such pixel, plateau level."""
    height, width = brightness.shape
    rows, first, last = np.empty(height, np.int64), np.empty(height, np.int64), np.empty(height, np.int64)
    plateau = np.empty(height)
    samples = np.empty(_FRACTIONS.size)
    count = 0
    for row in range(height):
        start = -1
        for col in range(width):
            if brightness[row, col] > threshold:
                start = col
                break
        if start < 0:
            continue
        end = width - 1
        while not brightness[row, end] > threshold:
            end -= 1
        # The middle half of the chord is well away from the blurred edge (and from a marker at the rim).
        for k in range(_FRACTIONS.size):
            samples[k] = brightness[row, int(np.rint(start + (end - start) * _FRACTIONS[k]))]
        rows[count], first[count], last[count] = row, start, end
        plateau[count] = ranked(samples, samples.size, samples.size // 2)
        count += 1
    return _LitRows(rows[:count], first[:count], last[:count], plateau[:count])


def clear_levels(brightness: np.ndarray, levels: RowLevels, ellipse: np.ndarray, clearance: float,
                 marker: tuple[np.ndarray, float] | None) -> RowLevels:
    """
    Return ``levels`` with each row's plateau measured again well inside ``ellipse``.

    The plateau is measured where the disc is at least ``clearance`` (px) inside ``ellipse``, on the
    middle half of the row's chord, away from the ``marker`` disc (centre, radius) if given; rows
    without enough such samples are dropped.

    Blur dims the disc within a few blurs of its edge, and near the disc's top and
    bottom that reaches the middle of the chord: a plateau a few tenths of a level low
    there moves the rows' half-level crossings outward by a hundredth of a pixel in
    the rows that meet the edge obliquely. A marker of another colour does the same to
    the rows it crosses. (The median of noisy samples, some of them dimmed, is lower
    than the noise-free one, so both grow with the noise.)
    """
    has_marker = marker is not None
    centre, radius = (np.asarray(marker[0], dtype=float), float(marker[1])) if has_marker else (np.zeros(2), 0.0)
    keep, plateau = _clear_plateaus(brightness, levels.rows, np.asarray(ellipse, dtype=float), float(clearance),
                                    has_marker, centre, radius)
    return RowLevels(levels.rows[keep], levels.first[keep], levels.last[keep], plateau[keep])


@kernel
def _clear_plateaus(brightness: np.ndarray, rows: np.ndarray, ellipse: np.ndarray, clearance: float,
                    has_marker: bool, centre: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """``clear_levels``: which rows keep a plateau, and the plateaus (the upper median of the usable samples)."""
    conic = conic_of(ellipse)
    left, right, crossed = chords(conic, rows.astype(np.float64))
    keep = np.zeros(rows.size, np.bool_)
    plateau = np.zeros(rows.size)
    usable = np.empty(_CLEAR_FRACTIONS.size)
    # Squared distances: math.hypot costs half the kernel's time.
    square_radius = radius * radius
    for i in range(rows.size):
        if not crossed[i]:
            continue
        count = 0
        for k in range(_CLEAR_FRACTIONS.size):
            col = left[i] + (right[i] - left[i]) * _CLEAR_FRACTIONS[k]
            if -conic_distance(conic, col, float(rows[i])) < clearance:
                continue
            dx, dy = col - centre[0], rows[i] - centre[1]
            if has_marker and not dx * dx + dy * dy > square_radius:
                continue
            usable[count] = brightness[rows[i], min(max(int(np.rint(col)), 0), brightness.shape[1] - 1)]
            count += 1
        if count >= _MIN_CLEAR_SAMPLES:
            keep[i] = True
            plateau[i] = ranked(usable, count, count // 2)
    return keep, plateau


@kernel
def chords(conic: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(left, right, crossed): where each row (y = ``rows``, float) enters and leaves the ellipse ``conic`` (3x3)."""
    left, right, crossed = np.empty(rows.size), np.empty(rows.size), np.empty(rows.size, np.bool_)
    a = conic[0, 0]
    for i in range(rows.size):
        y = rows[i]
        # The row's conic in x: a x^2 + b x + c = 0.
        b = 2.0 * (conic[0, 1] * y + conic[0, 2])
        c = conic[1, 1] * y * y + 2.0 * conic[1, 2] * y + conic[2, 2]
        discriminant = b * b - 4.0 * a * c
        root = math.sqrt(max(discriminant, 0.0))
        left[i], right[i], crossed[i] = (-b - root) / (2.0 * a), (-b + root) / (2.0 * a), discriminant > 0.0
    return left, right, crossed


def row_profile(brightness: np.ndarray, ellipse: np.ndarray, background: float, blur: float) -> np.ndarray:
    """
    Every row's level above ``background`` inside ``ellipse`` (array pixels).

    Near the disc's top and bottom the blurred edge dims the disc itself: the
    plateau is divided by the blurred disc's value at the middle of the chord
    (Gaussian ``blur``). NaN for rows that miss the ellipse or whose chord middle
    lies within two blurs of the edge, where that correction would dominate.
    """
    inside, plateau, clearance = _chord_plateaus(brightness, np.asarray(ellipse, dtype=float), float(background),
                                                 float(blur))
    profile = np.full(brightness.shape[0], np.nan)
    profile[inside] = plateau / ndtr(clearance / blur)
    return profile


@kernel
def _chord_plateaus(brightness: np.ndarray, ellipse: np.ndarray, background: float,
                    blur: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """
    Return the rows whose chord lies in the array with its middle two blurs inside the edge.

    Also return their plateaus above ``background`` and the clearance of their chord's middle.
    """
    height, width = brightness.shape
    conic = conic_of(ellipse)
    left, right, crossed = chords(conic, np.arange(height).astype(np.float64))
    rows, plateau, clearance = np.empty(height, np.int64), np.empty(height), np.empty(height)
    samples = np.empty(_FRACTIONS.size)
    count = 0
    for row in range(height):
        depth = -conic_distance(conic, 0.5 * (left[row] + right[row]), float(row))
        if not (crossed[row] and left[row] >= 0.0 and right[row] <= width - 1 and depth >= 2.0 * blur):
            continue
        for k in range(_FRACTIONS.size):
            samples[k] = brightness[row, int(np.rint(left[row] + (right[row] - left[row]) * _FRACTIONS[k]))]
        rows[count], clearance[count] = row, depth
        plateau[count] = ranked(samples, samples.size, samples.size // 2) - background
        count += 1
    return rows[:count], plateau[:count], clearance[:count]
