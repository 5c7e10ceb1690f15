"""
Each lamp's band of frequencies, and the share of the frequency's likelihood that falls in it.

The likelihood comes on an even grid of cycles per window (``scan.likelihood``); between grid
points it is taken as exponential (a Gaussian's tails are integrated well from a coarse grid),
and beyond the grid a Student's t continues it, whose density meets the grid's ends.
"""
from __future__ import annotations

from functools import lru_cache
import math
from typing import NamedTuple

import numpy as np
from scipy.special import stdtr

from vlp_ros.compiled import kernel

# Log densities (relative to the peak's) below these carry no mass worth counting (far below the 1e-4
# a decision leaves to the others): at the grid's ends, for the tails beyond, and on the grid.
_NEGLIGIBLE = -15.0
_FLOOR = -50.0


class GridCdf(NamedTuple):
    """The likelihood grid integrated up to each band's edges (``_grid_cdf``)."""

    # The grid's frequencies (Hz).
    frequency: np.ndarray
    # The bands' low edges, high edges, then the search range's ends, all cut to that range.
    edges: np.ndarray
    # The log density relative to its peak, at least _FLOOR.
    log_density: np.ndarray
    # Its integral from the grid's start to each edge.
    cdf: np.ndarray
    # For the grid's start and end: whether an edge lies beyond it where the density is not negligible.
    tails: tuple[bool, bool]


@lru_cache(maxsize=16)
def band_edges(centres: tuple[float, ...], tolerance_hz: float,
               row_time_tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """Return each lamp's band (Hz): its low and high edges."""
    frequencies = np.array(centres)
    low = frequencies * (1.0 - row_time_tolerance) - tolerance_hz
    high = frequencies * (1.0 + row_time_tolerance) + tolerance_hz
    for edges in (low, high):
        edges.flags.writeable = False
    return low, high


def log_band_masses(grid: np.ndarray, duration: float, log_density: np.ndarray, dof: int, low: np.ndarray,
                    high: np.ndarray, search: tuple[float, float]) -> np.ndarray:
    """
    Return log P(f in each band: [``low``, ``high``], per lamp) and, last, log P(f in none).

    f's density is given on an even ``grid`` of cycles per window of ``duration`` (exponential between
    grid points), continued beyond it by the Student's t (``dof`` degrees of freedom, centred on the
    grid's peak) whose density meets the grid's ends, all cut to the ``search`` range: a frequency
    outside it would have shown as another peak.
    """
    integrated = _grid_cdf(grid, duration, log_density, low, high, search[0], search[1])
    for end, tailed in zip((0, -1), integrated.tails):
        if tailed:
            _add_t_tail(integrated, dof, end)
    return _band_log_masses(integrated.cdf, integrated.edges, len(low))


def _add_t_tail(integrated: GridCdf, dof: int, end: int) -> None:
    """
    Add to the cdf at the edges beyond the grid's ``end`` (0 or -1) the mass of the Student's t there.

    The t is the one whose density meets the grid's at that end.
    """
    frequency, log_density, edges, cdf = integrated.frequency, integrated.log_density, integrated.edges, integrated.cdf
    beyond = edges < frequency[0] if end == 0 else edges > frequency[-1]
    # The t's scale that makes it exp(log_density[end]) at the grid's end, 1 at the centre (where the
    # t density is gamma((dof + 1) / 2) / (sqrt(dof pi) gamma(dof / 2))).
    centre = frequency[np.argmax(log_density)]
    scale = abs(frequency[end] - centre) / math.sqrt(dof * max(math.expm1(-2.0 * log_density[end] / (dof + 1)), 1e-12))
    peak = math.exp(math.lgamma(0.5 * (dof + 1)) - math.lgamma(0.5 * dof)) / math.sqrt(dof * math.pi)
    tail = stdtr(dof, (edges[beyond] - centre) / scale) - stdtr(dof, (frequency[end] - centre) / scale)
    cdf[beyond] += tail * scale / peak


@kernel
def _grid_cdf(grid: np.ndarray, duration: float, log_density: np.ndarray, low: np.ndarray, high: np.ndarray,
              search_low: float, search_high: float) -> GridCdf:
    """
    Return the grid's frequencies (cycles per window of ``duration``), the bands' edges and the cdf there.

    The edges are the bands' low edges, high edges, then the search range's ends, all cut to that range;
    the log density is taken relative to its peak (at least _FLOOR); its integral runs from the grid's
    start to each edge (exponential between grid points; 0 before the grid, the whole beyond it); and,
    for the grid's start and end, ``tails`` says whether an edge lies beyond it where the density is not
    negligible (_add_t_tail adds mass there).
    """
    frequency = grid / duration
    bands = len(low)
    edges = np.empty(2 * bands + 2)
    edges[:bands], edges[bands:2 * bands] = low, high
    edges[-2], edges[-1] = search_low, search_high
    edges = np.minimum(np.maximum(edges, search_low), search_high)
    # Below _FLOOR there is nothing to count (and the exponentials stay finite).
    log_density = np.maximum(log_density - log_density.max(), _FLOOR)
    step = frequency[1] - frequency[0]
    cumulative = np.zeros(len(frequency))
    for i in range(len(frequency) - 1):
        # The integral over [0, step] of exp(log_density[i] + rise x / step).
        rise = log_density[i + 1] - log_density[i]
        shape = np.expm1(rise) / rise if abs(rise) > 1e-6 else 1.0 + 0.5 * rise
        cumulative[i + 1] = cumulative[i] + np.exp(log_density[i]) * step * shape
    # Within a grid step the cumulative is taken as linear: where a band's edge falls in a tail, that
    # gives the band around the peak a little less and "none" a little more than the exponential would.
    before = after = False
    for edge in edges:
        before |= edge < frequency[0]
        after |= edge > frequency[-1]
    tails = (before and log_density[0] >= _NEGLIGIBLE, after and log_density[-1] >= _NEGLIGIBLE)
    return GridCdf(frequency, edges, log_density, np.interp(edges, frequency, cumulative), tails)


@kernel
def _band_log_masses(cdf: np.ndarray, edges: np.ndarray, bands: int) -> np.ndarray:
    """
    Return the log of each band's share of the search range and, last, of what lies in no band.

    ``cdf`` is given at the ``edges``: the bands' low edges, high edges and the range's ends. Overlapping
    bands share.
    """
    whole = max(cdf[-1] - cdf[-2], 1e-300)
    out = np.empty(bands + 1)
    for b in range(bands):
        out[b] = np.log(max(cdf[bands + b] - cdf[b], 1e-300) / whole)
    # The bands' union, merged in the order of their low edges.
    union = 0.0
    order = np.argsort(edges[:bands])
    start, end = order[0], bands + order[0]
    for b in order[1:]:
        if edges[b] <= edges[end]:
            if edges[bands + b] > edges[end]:
                end = bands + b
        else:
            union += cdf[end] - cdf[start]
            start, end = b, bands + b
    union += cdf[end] - cdf[start]
    out[bands] = np.log(max(1.0 - union / whole, 1e-300))
    return out
