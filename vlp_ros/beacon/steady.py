"""
Whether a lamp's rows show any modulation: a steady lamp (one not in the map) has no beacon to read.

A rolling shutter turns a beacon's light into brightness that changes from row to row and is the same
along each row. A steady lamp's row sums change only as its shape, falloff and glare do, smoothly: their
second differences, less their straight line, hold little but pixel noise. The noise is measured on the
same pixels: the sum over the box's even columns minus that over its odd ones cancels the smooth shape
and any modulation alike (both are the same on neighbouring columns), and pixel noise, independent from
pixel to pixel, gives its differences the same variance as the row sums'. For a steady lamp the ratio of
the two energies then follows Fisher's F, and a lamp is steady when the ratio lies below that
distribution's ``1 - STEADY_MISS`` quantile. On the simulator's looks (blur, clipping, glare, falloff,
JPEG, tone lamps and 2.5-row chips) beacons reached 6 to thousands of times that quantile, steady lamps
at most 0.8 of it. Every error of the noise model that understates the noise (JPEG, demosaicing) makes
lamps look modulated: they are then read as any lamp.
"""
from __future__ import annotations

from functools import lru_cache
import math

import numpy as np
# scipy.special, not scipy.stats: the same F quantile without scipy.stats' import time at start.
from scipy.special import fdtri

from vlp_ros.compiled import kernel

# Rows within this share of the lamp's half height from its centre are tested: beyond it, a disc's chord
# bends too fast for the differences to leave only noise.
BAND = 0.6
# The share of steady lamps whose ratio the noise lifts above the threshold (they are then read as any lamp).
STEADY_MISS = 1e-3
# The fewest differences that test anything: a smaller lamp is read as any lamp.
MIN_TERMS = 8
# Second differences along the rows, less their straight line over the band: nothing is left of a shape whose
# curvature changes steadily (a small bright disc's falloff and glare), and little of a beacon is lost (higher
# differences lost most of a blurred beacon's chips).
ORDER = 2


def box_shows_no_modulation(image: np.ndarray, bbox: tuple[int, int, int, int], ellipse: np.ndarray) -> bool:
    """
    Whether the rows of the lamp in ``bbox`` around ``ellipse`` vary no more than its shape and noise explain.

    ``bbox`` is (x0, y0, x1, y1), ``ellipse`` (cx, cy, a, b, theta), in frame pixels. ``image`` is the
    full bgr8 or mono8 frame; colour frames are tested on the channel that is brightest on the lamp's
    middle row. False where the test cannot tell (too few rows, no noise: every pixel clipped).
    """
    x0, y0, x1, y1 = (int(v) for v in bbox)
    cx, cy, a, b, theta = (float(v) for v in ellipse)
    half_height = math.hypot(a * math.sin(theta), b * math.cos(theta))
    top = max(math.ceil(cy - BAND * half_height), y0)
    bottom = min(math.floor(cy + BAND * half_height) + 1, y1)
    if bottom - top < MIN_TERMS + ORDER or x1 - x0 < 2:
        return False
    # An even number of columns: the even and odd ones then cover the lamp alike.
    band = image[top:bottom, x0:x0 + (x1 - x0) // 2 * 2]
    if band.ndim == 3:
        band = band[..., int(np.argmax(band[len(band) // 2].max(axis=0)))]
    signal, noise = _row_energies(band)
    if not noise > 0.0:
        return False
    return signal / noise < _steady_quantile(bottom - top - ORDER - 2)


@kernel
def _row_energies(band: np.ndarray) -> tuple[float, float]:
    """
    Return the curvature energies (``_curvature_energy``) of the band's row sums and of its even less odd columns.

    ``band`` (rows, an even number of columns) is one channel.
    """
    rows, columns = band.shape
    sums, parities = np.empty(rows), np.empty(rows)
    for row in range(rows):
        even = odd = 0.0
        for column in range(0, columns, 2):
            even += band[row, column]
            odd += band[row, column + 1]
        sums[row], parities[row] = even + odd, even - odd
    return _curvature_energy(sums), _curvature_energy(parities)


@kernel
def _curvature_energy(values: np.ndarray) -> float:
    """Sum of the squared ``ORDER``-th differences of ``values`` off their least-squares line."""
    differences = values.copy()
    for _ in range(ORDER):
        differences = differences[1:] - differences[:-1]
    count = differences.size
    mean = differences.mean()
    moment = spread = 0.0
    for i in range(count):
        along = i - 0.5 * (count - 1)
        moment += along * differences[i]
        spread += along * along
    slope = moment / spread
    energy = 0.0
    for i in range(count):
        left = differences[i] - mean - (i - 0.5 * (count - 1)) * slope
        energy += left * left
    return energy


@lru_cache(maxsize=512)
def _steady_quantile(terms: int) -> float:
    """
    Return the ``1 - STEADY_MISS`` quantile of a steady lamp's energy ratio over ``terms`` differences (beyond a line).

    Differences of a white noise overlap: the sum of ``terms`` of their squares is as spread as a chi-square
    of ``terms`` over the sum of their squared correlations degrees of freedom.
    """
    weights = np.diff(np.eye(2 * ORDER + 1)[ORDER], ORDER)
    correlations = np.correlate(weights, weights, 'full') / (weights @ weights)
    dof = terms / float(correlations @ correlations)
    return float(fdtri(dof, dof, 1.0 - STEADY_MISS))
