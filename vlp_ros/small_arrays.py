"""Median and percentile of the few hundred values a lamp yields, without numpy's overhead.

np.median and np.percentile spend 10-40 us on argument handling before touching the
data, several times what a partition of a few hundred values costs; the per-frame
pipeline calls them for every lamp. The results equal numpy's (default 'linear' method).
"""
from __future__ import annotations

import numpy as np


def median(values: np.ndarray) -> float:
    """np.median of a non-empty 1D array."""
    n = len(values)
    middle = np.partition(values, ((n - 1) // 2, n // 2))
    return 0.5 * (float(middle[(n - 1) // 2]) + float(middle[n // 2]))


def percentile(values: np.ndarray, q: float) -> float:
    """np.percentile(values, q) of a non-empty 1D array, linearly interpolated as numpy does."""
    n = len(values)
    position = q / 100.0 * (n - 1)
    below = int(np.floor(position))
    above = min(below + 1, n - 1)
    ordered = np.partition(values, (below, above))
    low, high = float(ordered[below]), float(ordered[above])
    return low + (position - below) * (high - low)
