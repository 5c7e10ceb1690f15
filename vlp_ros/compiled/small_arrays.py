"""
Median and percentile of the few hundred values a lamp yields, without numpy's overhead.

np.median and np.percentile spend 10-40 us on argument handling before touching the
data, several times what sorting a few hundred values costs; the per-frame pipeline
calls them for every lamp. Both are compiled kernels (``vlp_ros.compiled``), so other
kernels call them too. The results equal numpy's (default 'linear' method).
``ranked`` picks from a few dozen values in a kernel's own buffer, where even
numba's np.sort costs ~0.5 us in allocation and set-up.
"""
from __future__ import annotations

import math

import numpy as np

from vlp_ros.compiled import kernel


@kernel
def median(values: np.ndarray) -> float:
    """np.median of a non-empty 1D array."""
    n = len(values)
    ordered = np.sort(values)
    return 0.5 * (float(ordered[(n - 1) // 2]) + float(ordered[n // 2]))


@kernel
def percentile(values: np.ndarray, q: float) -> float:
    """
    Return the q-th percentile of a non-empty 1D array, linearly interpolated as numpy does.

    It equals np.percentile(values, q).
    """
    n = len(values)
    position = q / 100.0 * (n - 1)
    below = int(math.floor(position))
    above = min(below + 1, n - 1)
    ordered = np.sort(values)
    low, high = float(ordered[below]), float(ordered[above])
    return low + (position - below) * (high - low)


@kernel
def ranked(values: np.ndarray, count: int, rank: int) -> float:
    """
    Return the ``rank``-th smallest (from 0) of ``values[:count]``, which it overwrites.

    It keeps the ``rank`` + 1 smallest sorted at the front (insertion: for the few dozen values it
    is meant for; a median's half of them takes half the moves of sorting all).
    """
    kept = rank + 1
    for i in range(1, count):
        value = values[i]
        if i >= kept:
            # Only values below the largest kept one enter, which then drops out.
            if not value < values[kept - 1]:
                continue
            j = kept - 2
        else:
            j = i - 1
        while j >= 0 and values[j] > value:
            values[j + 1] = values[j]
            j -= 1
        values[j + 1] = value
    return float(values[rank])
