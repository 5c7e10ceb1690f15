"""
From a row profile to chip levels: find the chip grid, then average each chip's rows.

Positions are in rows: row r of the profile covers [r, r + 1). The chip period in
rows is known only to a few percent (``row_time`` and ``chip_rate`` are both
nominal), and the phase not at all, so both are searched: the right grid is the
one whose chip-wise constant fit of the profile captures the most energy (least
squares with one free level per chip). Sums over chips come from cumulative sums,
so a candidate grid costs one look-up per chip, not per row.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from typing import NamedTuple

import numpy as np

from vlp_ros.compiled import kernel
from vlp_ros.compiled.small_arrays import median

_COARSE_PHASES = 6
_THOROUGH_PHASES = 24
# Chips of the window the quick coarse grid looks at, and the largest drift of its period steps across them.
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
# Median of a chi-square variable with one degree of freedom.
_CHI2_1_MEDIAN = 0.4549


@dataclass(frozen=True)
class ChipLevels:
    """
    Chip-wise averages of a modulation profile on the found grid.

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


@kernel
def _cumulative(z: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """
    Return cumulative sums of w, w z, w z^2 and of used rows up to each row boundary, and each row's own terms.

    The sums are (4, n + 1); each row's own terms (4, n + 1; 0 past the end): a sum to position u (rows
    split pro rata) is ``_at(sums, rows, field, u)``.
    """
    n = len(z)
    sums = np.zeros((4, n + 1))
    rows = np.zeros((4, n + 1))
    for i in range(n):
        rows[0, i] = w[i]
        rows[1, i] = w[i] * z[i]
        rows[2, i] = w[i] * z[i] * z[i]
        rows[3, i] = 1.0 if w[i] > 0.0 else 0.0
        for field in range(4):
            sums[field, i + 1] = sums[field, i] + rows[field, i]
    return sums, rows


@kernel
def _at(sums: np.ndarray, rows: np.ndarray, field: int, u: float) -> float:
    """Cumulative sum ``field`` up to position u (within [0, n])."""
    i = int(u)
    return sums[field, i] + (u - i) * rows[field, i]


@kernel
def _noise_variance(z: np.ndarray, w: np.ndarray) -> float:
    """
    Per-pixel noise variance of a profile from row-to-row differences (robust to stripe edges).

    Pairs with an empty row count as noiseless; the median shrugs them off.
    """
    if np.count_nonzero(w) < 4:
        return np.inf
    d = z[1:] - z[:-1]
    inverse = 1.0 / np.maximum(w, 1e-12)
    return median(d * d / (inverse[:-1] + inverse[1:])) / _CHI2_1_MEDIAN


def chip_levels(z: np.ndarray, w: np.ndarray, period: float, tolerance: float,
                margin: float | None, thorough: bool = False) -> ChipLevels | None:
    """
    Chip levels of modulation ``z`` (weights ``w``) with a nominal chip ``period`` in rows.

    The period is searched within +-``tolerance`` (relative). Each chip averages only
    the rows more than ``margin`` rows from its edges, where a row's exposure lies in
    one chip (None: the middle half of the chip). None when the window holds too few
    rows to fit a grid. ``thorough`` searches the grid on the whole window (``_search_grid``), at about
    eight times the cost.
    """
    if not period > 1.0:
        raise ValueError(f'a chip must span more than one row, got {period:.3g} rows')
    sigma2 = _noise_variance(z, w)
    if not math.isfinite(sigma2) or len(z) < 3 * period:
        return None
    sigma2 = max(sigma2, 1e-12)
    sums, rows = _cumulative(z, w)
    period, phase = _search_grid(sums, rows, period, tolerance, sigma2, thorough)
    return _on_grid(sums, rows, period, phase, margin, sigma2)


def levels_on_grid(z: np.ndarray, w: np.ndarray, period: float, phase: float,
                   margin: float | None) -> ChipLevels | None:
    """
    Return the chip levels of modulation ``z`` (weights ``w``) on a grid of chips.

    The grid's chips begin at ``phase`` + k ``period`` rows. None: no chip holds enough rows.
    """
    sums, rows = _cumulative(z, w)
    return _on_grid(sums, rows, period, phase, margin, max(_noise_variance(z, w), 1e-12))


def nearby_grids(z: np.ndarray, w: np.ndarray, found: ChipLevels, margin: float | None,
                 offsets: tuple[float, ...], scales: tuple[float, ...]) -> list[ChipLevels]:
    """
    Chip levels on the grids around ``found``'s.

    Its chip edges moved by each of ``offsets`` (in chips) and its period scaled by each of ``scales``,
    anchored at the window's weighted middle (grids with no chip left out).
    """
    sigma2 = max(_noise_variance(z, w), 1e-12)
    sums, rows = _cumulative(z, w)
    anchor = _weighted_middle(rows)
    # The found grid's chip edge nearest the anchor: scaling the period about it keeps the middle in place.
    edge = found.phase + found.period * round((anchor - found.phase) / found.period)
    periods = [found.period * scale for scale in scales for _ in offsets]
    phases = [(edge + offset * found.period) % period for period in periods[::len(offsets)] for offset in offsets]
    chips = _levels_on_grids(sums, rows, np.array(periods), np.array(phases),
                             np.array([_interior(period, margin) for period in periods]), sigma2)
    grids = []
    for period, start, begin, end in zip(periods, chips.starts, chips.ends[:-1], chips.ends[1:]):
        if end > begin:
            grids.append(ChipLevels(chips.index[begin:end], chips.levels[begin:end], chips.variances[begin:end],
                                    period, start))
    return grids


def _on_grid(sums: np.ndarray, rows: np.ndarray, period: float, phase: float, margin: float | None,
             sigma2: float) -> ChipLevels | None:
    chips = _levels(sums, rows, period, phase % period, _interior(period, margin), sigma2)
    if chips.index.size == 0:
        return None
    return ChipLevels(chips.index, chips.levels, chips.variances, period, chips.start)


def _interior(period: float, margin: float | None) -> float:
    """Rows left out at each end of a chip: ``margin``, at most what leaves a row (None: a quarter chip)."""
    return period / 4.0 if margin is None else min(margin, 0.5 * (period - 1.0))


def interior_bounds(levels: ChipLevels, margin: float | None, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Where each chip of ``levels`` begins and ends the rows it averages (within the window's ``size`` rows)."""
    interior = _interior(levels.period, margin)
    start = levels.phase + levels.period * levels.index
    return (np.clip(start + interior, 0.0, size), np.clip(start + levels.period - interior, 0.0, size))


class _Chips(NamedTuple):
    """``_levels``' result: ``ChipLevels`` short of the period."""

    index: np.ndarray
    levels: np.ndarray
    variances: np.ndarray
    start: float


class _GridsChips(NamedTuple):
    """``_levels_on_grids``' result: every grid's ``_Chips`` one after another (grid g's at ``ends[g]:ends[g + 1]``)."""

    index: np.ndarray
    levels: np.ndarray
    variances: np.ndarray
    starts: np.ndarray
    ends: np.ndarray


@kernel
def _levels_on_grids(sums: np.ndarray, rows: np.ndarray, periods: np.ndarray, phases: np.ndarray,
                     margins: np.ndarray, sigma2: float) -> _GridsChips:
    """``_levels`` on each grid (its period, phase within it and margin), all in one call."""
    count = len(periods)
    parts = []
    starts, ends = np.zeros(count), np.zeros(count + 1, dtype=np.int64)
    for g in range(count):
        chips = _levels(sums, rows, periods[g], phases[g], margins[g], sigma2)
        parts.append(chips)
        starts[g], ends[g + 1] = chips.start, ends[g] + chips.index.size
    index, levels, variances = np.empty(ends[-1], np.int64), np.empty(ends[-1]), np.empty(ends[-1])
    for g in range(count):
        index[ends[g]:ends[g + 1]] = parts[g].index
        levels[ends[g]:ends[g + 1]] = parts[g].levels
        variances[ends[g]:ends[g + 1]] = parts[g].variances
    return _GridsChips(index, levels, variances, starts, ends)


@kernel
def _levels(sums: np.ndarray, rows: np.ndarray, period: float, phase: float, margin: float,
            sigma2: float) -> _Chips:
    """
    Chip averages over each chip's interior, normalised by the local extremes.

    The chips that hold enough rows (indices from the first of them), their levels and variances,
    and where the first begins (no chips if none holds enough rows).
    """
    size = sums.shape[1] - 1
    first = int(np.floor(-phase / period))
    count = int(np.ceil((size - phase) / period)) - first
    weight, total, square, filled_rows = np.empty(count), np.empty(count), np.empty(count), np.empty(count)
    # Chips the window's ends cut short.
    whole = np.empty(count, dtype=np.bool_)
    used_first, used_last = -1, -1
    for c in range(count):
        start = phase + period * (first + c)
        low, high = start + margin, start + (period - margin)
        whole[c] = low >= 0.0 and high <= size
        low, high = min(max(low, 0.0), size), min(max(high, 0.0), size)
        weight[c] = _at(sums, rows, 0, high) - _at(sums, rows, 0, low)
        total[c] = _at(sums, rows, 1, high) - _at(sums, rows, 1, low)
        square[c] = _at(sums, rows, 2, high) - _at(sums, rows, 2, low)
        filled_rows[c] = _at(sums, rows, 3, high) - _at(sums, rows, 3, low)
        # A sliver of a row at the window's ends is mostly rounding (differences of large sums). Counted
        # in rows, not pixels: the short rows near the lamp's top and bottom carry their own weights.
        if filled_rows[c] > _MIN_CHIP_ROWS:
            used_last = c
            if used_first < 0:
                used_first = c
    if used_first < 0:
        return _Chips(np.empty(0, dtype=np.int64), np.empty(0), np.empty(0), 0.0)
    span = used_last + 1 - used_first
    mean = np.empty(span)
    solid = np.empty(span, dtype=np.bool_)
    used, row_sum, scatter = 0, 0.0, 0.0
    for c in range(span):
        chip = used_first + c
        filled = filled_rows[chip] > _MIN_CHIP_ROWS
        mean[c] = total[chip] / (weight[chip] if filled else 1.0)
        solid[c] = filled and whole[chip]
        if filled:
            used += 1
            row_sum += filled_rows[chip]
            scatter += square[chip] - mean[c] * total[chip]
    # Within-chip scatter measures the noise where there is enough of it.
    dof = row_sum - used
    if dof >= _MIN_DOF:
        sigma2 = max(scatter / dof, 1e-12)
    centre, amplitude = _baseline(mean, solid)
    index = np.empty(used, dtype=np.int64)
    levels, variances = np.empty(used), np.empty(used)
    k = 0
    for c in range(span):
        chip = used_first + c
        if filled_rows[chip] > _MIN_CHIP_ROWS:
            index[k] = c
            levels[k] = (mean[c] - centre[c]) / amplitude[c]
            variances[k] = sigma2 / (weight[chip] * amplitude[c] ** 2)
            k += 1
    return _Chips(index, levels, variances, phase + period * (first + used_first))


@kernel
def _search_grid(sums: np.ndarray, rows: np.ndarray, period: float, tolerance: float,
                 sigma2: float, thorough: bool) -> tuple[float, float]:
    """
    Search a coarse grid, then a fine one around its best on the whole window.

    The fine one spans the whole window because a period error drifts the grid in proportion to the rows
    it spans from where it is anchored.

    Quick: the coarse grid on the window's first 24 chips, 6 phases. ``thorough``: on the whole window, its
    period steps as fine as the window's length needs, 24 phases, anchored at the window's weighted middle. A
    light profile's window begins in the glow's faint rows, and a blurred window's isolated chips are faint
    too: there the quick grid misplaced the period by 1-2 % on foreign 4K frames, enough to drift a 50-chip
    window by a chip; and the chip-wise energy is sharp in phase (a tenth of a row moves it by a third).
    """
    size = float(sums.shape[1] - 1)
    if thorough:
        end, anchor, phases = size, _weighted_middle(rows), _THOROUGH_PHASES
    else:
        end, anchor, phases = min(size, _FIRST_CHIPS * period), 0.0, _COARSE_PHASES
    step = _COARSE_DRIFT * period / end
    # Less a rounding error: 5 % in steps of 1.25 % is four steps, not five.
    count = math.ceil(tolerance / step - 1e-9)
    phase_step = period / phases
    best_period, best_phase = _best_grid(sums, rows, 0.0, end, anchor,
                                         period * (1.0 + step * np.arange(-count, count + 1)),
                                         phase_step * np.arange(phases), sigma2)
    fine_period, fine_phase = _best_grid(sums, rows, 0.0, size, anchor, best_period * (1.0 + step * _FINE_STEPS),
                                         best_phase + phase_step * _FINE_STEPS, sigma2)
    return fine_period, (anchor + fine_phase) % fine_period


@kernel
def _weighted_middle(rows: np.ndarray) -> float:
    """Return the rows' centre of weight (row r covers [r, r + 1)), from their own terms."""
    weight, moment = 0.0, 0.0
    for r in range(rows.shape[1]):
        weight += rows[0, r]
        moment += rows[0, r] * (r + 0.5)
    return moment / weight if weight > 0.0 else 0.5 * (rows.shape[1] - 1)


@kernel
def _best_grid(sums: np.ndarray, rows: np.ndarray, begin: float, end: float, anchor: float, periods: np.ndarray,
               phases: np.ndarray, sigma2: float) -> tuple[float, float]:
    """
    Return the (period, phase) pair whose chip-wise constant fit of rows [begin, end) captures most energy beyond noise.

    Chip edges lie at anchor + phase + k period.
    """
    chips = math.ceil((end - begin) / periods.min()) + 3
    best, best_period, best_phase = -np.inf, 0.0, 0.0
    for period in periods:
        for phase in phases:
            # The last chip edge at or before ``begin``.
            offset = anchor + phase - period * math.ceil((anchor + phase - begin) / period)
            energy = 0.0
            weight_before, total_before = _at(sums, rows, 0, begin), _at(sums, rows, 1, begin)
            for chip in range(1, chips):
                bound = min(max(offset + period * chip, begin), end)
                weight_after, total_after = _at(sums, rows, 0, bound), _at(sums, rows, 1, bound)
                weight, total = weight_after - weight_before, total_after - total_before
                # Empty chips have zero sums: the tiny offset only keeps their ratio defined.
                energy += total * total / (weight + 1e-12) - (sigma2 if weight > 1e-9 else 0.0)
                weight_before, total_before = weight_after, total_after
            if energy > best:
                best, best_period, best_phase = energy, period, phase
    return best_period, best_phase


@kernel
def _baseline(mean: np.ndarray, solid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """
    Midline and half-contrast of every chip from its neighbourhood's brightest and darkest chips.

    ID-blind: no run of equal chips is longer than four (the preamble's three and a
    neighbouring Manchester chip), so any seven consecutive chips hold both levels. Following the
    extremes rather than fitting a curve through the chips copes with any slow
    envelope, a contrast that saturation squeezes along the lamp, and the preamble's
    imbalance. Only ``solid`` chips (whole ones) set the extremes.
    """
    n = len(mean)
    centre, contrast = np.zeros(n), np.ones(n)
    if np.count_nonzero(solid) < 2:
        return centre, contrast
    # Running extremes of the solid chips within _EXTREMES_HALF_WIDTH on either side.
    upper, lower = np.full(n, -np.inf), np.full(n, np.inf)
    for c in range(n):
        for d in range(max(c - _EXTREMES_HALF_WIDTH, 0), min(c + _EXTREMES_HALF_WIDTH + 1, n)):
            if solid[d]:
                upper[c] = max(upper[c], mean[d])
                lower[c] = min(lower[c], mean[d])
    top, bottom = upper.max(), lower.min()
    for c in range(n):
        # A neighbourhood without both levels (too few whole chips, or noise only) borrows the lamp's
        # overall extremes.
        if not upper[c] - lower[c] > _MIN_LOCAL_CONTRAST * (top - bottom):
            upper[c], lower[c] = top, bottom
        centre[c] = 0.5 * (upper[c] + lower[c])
        contrast[c] = max(0.5 * (upper[c] - lower[c]), 1e-12)
    return centre, contrast
