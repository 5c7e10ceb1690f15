"""Timing for the benchmark scripts: medians over repeats, after one warm-up run."""
from __future__ import annotations

from collections.abc import Callable
import time

import numpy as np


def median_seconds(run: Callable[[], object], repeats: int) -> float:
    run()
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        run()
        times.append(time.perf_counter() - started)
    return float(np.median(times))
