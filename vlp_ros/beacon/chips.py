"""From a row profile to chip levels: find the chip grid, then average each chip's rows.

Positions are in rows: row r of the profile covers [r, r + 1). The chip period in
rows is known only to a few percent (``row_time`` and ``chip_rate`` are both
nominal), and the phase not at all, so both are searched: the right grid is the
one whose chip-wise constant fit of the profile captures the most energy (least
squares with one free level per chip). Sums over chips come from cumulative sums,
so a candidate grid costs one look-up per chip, not per row.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from vlp_ros.small_arrays import median

_COARSE_PHASES = 6
# Chips of the window the coarse grid looks at, and the largest drift of its period steps across them.
_FIRST_CHIPS = 24
_COARSE_DRIFT = 0.3
# The fine grid: 5 x 5 points a quarter of the coarse steps apart, around the coarse best.
_FINE_STEPS = np.arange(-2, 3) / 4.0
_MIN_DOF = 4
# Least share of a row a chip must hold to count.
_MIN_CHIP_ROWS = 0.25
# Chips on each side whose extremes give a chip's midline and contrast, and the least share of
# the lamp's whole contrast such a neighbourhood must show to be trusted.
_EXTREMES_HALF_WIDTH = 3
_MIN_LOCAL_CONTRAST = 0.25
_EXTREMES_KERNEL = np.ones((1, 2 * _EXTREMES_HALF_WIDTH + 1), dtype=np.uint8)
# Median of a chi-square variable with one degree of freedom.
_CHI2_1_MEDIAN = 0.4549


@dataclass(frozen=True)
class ChipLevels:
    """Chip-wise averages of a modulation profile on the found grid.

    Chip k spans rows [phase + k period, phase + (k + 1) period); ``index`` lists the
    chips that hold enough rows to be measured (increasing), ``levels`` their
    averages normalised to about +1 (bright) and -1 (dark) and ``variances`` their
    noise variances on that scale.
    """

    index: np.ndarray
    levels: np.ndarray
    variances: np.ndarray
    period: float
    phase: float


class _Cumulative:
    """Sums of w, w z, w z^2 and of used rows over any row interval, rows split pro rata."""

    def __init__(self, z: np.ndarray, w: np.ndarray) -> None:
        self.size = len(z)
        # sums[0]: cumulative sums up to each row, sums[1]: each row's own terms (0 past the end).
        self.sums = np.zeros((2, 4, self.size + 1))
        self.rows = self.sums[1]
        self.rows[:, :-1] = w, w * z, w * z * z, w > 0
        np.cumsum(self.rows[:, :-1], axis=1, out=self.sums[0, :, 1:])

    def at(self, u: np.ndarray, fields: int) -> np.ndarray:
        """The first ``fields`` cumulative sums up to positions ``u`` (within [0, size]), shape
        (fields,) + u.shape."""
        i = u.astype(np.intp)
        # take: several times faster than fancy indexing for these sizes.
        totals, rows = self.sums[:, :fields].take(i, axis=2)
        return totals + (u - i) * rows


def _noise_variance(z: np.ndarray, w: np.ndarray) -> float:
    """Per-pixel noise variance of a profile from row-to-row differences (robust to stripe edges).

    Pairs with an empty row count as noiseless; the median shrugs them off."""
    if np.count_nonzero(w) < 4:
        return float('inf')
    d = z[1:] - z[:-1]
    inverse = 1.0 / np.maximum(w, 1e-12)
    return median(d * d / (inverse[:-1] + inverse[1:])) / _CHI2_1_MEDIAN


def chip_levels(z: np.ndarray, w: np.ndarray, period: float, tolerance: float,
                margin: float | None) -> ChipLevels | None:
    """Chip levels of modulation ``z`` (weights ``w``) with a nominal chip ``period`` in rows.

    The period is searched within +-``tolerance`` (relative). Each chip averages only
    the rows more than ``margin`` rows from its edges, where a row's exposure lies in
    one chip (None: the middle half of the chip). None when the window holds too few
    rows to fit a grid.
    """
    if not period > 1.0:
        raise ValueError(f'a chip must span more than one row, got {period:.3g} rows')
    cum = _Cumulative(z, w)
    sigma2 = _noise_variance(z, w)
    if not np.isfinite(sigma2) or cum.size < 3 * period:
        return None
    sigma2 = max(sigma2, 1e-12)
    period, phase = _search_grid(cum, period, tolerance, sigma2)
    interior = period / 4.0 if margin is None else min(margin, 0.5 * (period - 1.0))
    return _levels(cum, period, phase, interior, sigma2)


def _levels(cum: _Cumulative, period: float, phase: float, margin: float, sigma2: float) -> ChipLevels | None:
    """Chip averages over each chip's interior, normalised by the local extremes; None if no chip
    holds enough rows."""
    first = int(np.floor(-phase / period))
    count = int(np.ceil((cum.size - phase) / period)) - first
    edges = phase + period * np.arange(first, first + count) + np.array([[margin], [period - margin]])
    # Chips the window's ends cut short.
    whole = (edges[0] >= 0.0) & (edges[1] <= cum.size)
    sums = cum.at(np.minimum(np.maximum(edges, 0.0), cum.size), 4)
    weight, total, square, rows = sums[:, 1] - sums[:, 0]
    # A sliver of a row at the window's ends is mostly rounding (differences of large sums). Counted
    # in rows, not pixels: the short rows near the lamp's top and bottom carry their own weights.
    filled = rows > _MIN_CHIP_ROWS
    used = filled.nonzero()[0]
    if used.size == 0:
        return None
    span = slice(used[0], used[-1] + 1)
    weight, total, square, rows, filled, whole = weight[span], total[span], square[span], rows[span], \
        filled[span], whole[span]
    mean = total / np.where(filled, weight, 1.0)
    # Within-chip scatter measures the noise where there is enough of it.
    dof = rows @ filled - used.size
    if dof >= _MIN_DOF:
        sigma2 = max(float((square - mean * total) @ filled) / dof, 1e-12)
    centre, amplitude = _baseline(mean, filled & whole)
    index = used - used[0]
    return ChipLevels(index, (mean[index] - centre[index]) / amplitude[index],
                      sigma2 / (weight[index] * amplitude[index] ** 2), period, float(edges[0, used[0]] - margin))


def _search_grid(cum: _Cumulative, period: float, tolerance: float, sigma2: float) -> tuple[float, float]:
    """A coarse grid on the window's first chips, then a fine one around its best on the whole
    window (a period error drifts the grid in proportion to the rows it spans)."""
    end = min(float(cum.size), _FIRST_CHIPS * period)
    step = _COARSE_DRIFT * period / end
    # Less a rounding error: 5 % in steps of 1.25 % is four steps, not five.
    count = math.ceil(tolerance / step - 1e-9)
    phase_step = period / _COARSE_PHASES
    best = _best_grid(cum, end, period * (1.0 + step * np.arange(-count, count + 1)),
                      phase_step * np.arange(_COARSE_PHASES), sigma2)
    return _best_grid(cum, float(cum.size), best[0] * (1.0 + step * _FINE_STEPS),
                      best[1] + phase_step * _FINE_STEPS, sigma2)


def _best_grid(cum: _Cumulative, end: float, periods: np.ndarray, phases: np.ndarray,
               sigma2: float) -> tuple[float, float]:
    """The (period, phase) pair whose chip-wise constant fit of rows [0, end) captures most energy
    beyond noise."""
    offsets = phases % periods[:, None]
    chips = np.arange(-1.0, math.ceil(end / periods.min()) + 2.0)
    bounds = np.minimum(np.maximum(offsets[:, :, None] + periods[:, None, None] * chips, 0.0), end)
    sums = cum.at(bounds, 2)
    weight, total = sums[..., 1:] - sums[..., :-1]
    # Empty chips have zero sums: the tiny offset only keeps their ratio defined.
    energy = (total * total / (weight + 1e-12) - sigma2 * (weight > 1e-9)).sum(axis=-1)
    k, j = divmod(int(energy.argmax()), energy.shape[1])
    return float(periods[k]), float(offsets[k, j])


def _baseline(mean: np.ndarray, solid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Midline and half-contrast of every chip from its neighbourhood's brightest and darkest chips.

    ID-blind: no run of equal chips is longer than four (the preamble's three and a
    neighbouring Manchester chip), so any seven consecutive chips hold both levels. Following the
    extremes rather than fitting a curve through the chips copes with any slow
    envelope, a contrast that saturation squeezes along the lamp, and the preamble's
    imbalance. Only ``solid`` chips (whole ones) set the extremes.
    """
    if np.count_nonzero(solid) < 2:
        return np.zeros(len(mean)), np.ones(len(mean))
    # Running maximum of the bright and (negated) dark extremes; dilation ignores what lies outside.
    extremes = cv2.dilate(np.where(solid, [mean, -mean], -np.inf), _EXTREMES_KERNEL,
                          borderType=cv2.BORDER_CONSTANT, borderValue=-np.inf)
    upper, lower = extremes[0], -extremes[1]
    # A neighbourhood without both levels (too few whole chips, or noise only) borrows the lamp's
    # overall extremes.
    top, bottom = upper.max(), lower.min()
    lone = ~(upper - lower > _MIN_LOCAL_CONTRAST * (top - bottom))
    upper[lone], lower[lone] = top, bottom
    contrast = np.maximum(0.5 * (upper - lower), 1e-12)
    return 0.5 * (upper + lower), contrast
