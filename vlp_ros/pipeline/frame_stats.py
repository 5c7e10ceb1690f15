"""Running counts and rates of what the locator did with its frames, for diagnostics."""
from __future__ import annotations

from collections import Counter, deque
from dataclasses import dataclass, field
import time

import numpy as np


@dataclass
class FrameStats:
    """Counters over the node's life and rates over the last ``window`` seconds."""

    window: float = 5.0
    received: int = 0
    processed: int = 0
    poses: int = 0
    superseded: int = 0
    dropped: Counter = field(default_factory=Counter)
    no_pose: Counter = field(default_factory=Counter)
    decoded_ids: Counter = field(default_factory=Counter)
    unknown_ids: int = 0
    _arrivals: deque = field(default_factory=deque)
    _completions: deque = field(default_factory=deque)
    _latencies: deque = field(default_factory=lambda: deque(maxlen=200))

    def frame_received(self, now: float | None = None) -> None:
        self.received += 1
        self._arrivals.append(time.monotonic() if now is None else now)

    def frame_dropped(self, reason: str) -> None:
        self.dropped[reason] += 1

    def frame_processed(self, outcome: str, latency: float, now: float | None = None) -> None:
        """``outcome`` is 'pose' or the reason there is no pose; ``latency`` in seconds."""
        self.processed += 1
        if outcome == 'pose':
            self.poses += 1
        else:
            self.no_pose[outcome] += 1
        self._completions.append(time.monotonic() if now is None else now)
        self._latencies.append(latency)

    def ids_seen(self, decoded: list[int], unknown: int) -> None:
        self.decoded_ids.update(decoded)
        self.unknown_ids += unknown

    def rates(self, now: float | None = None) -> tuple[float, float]:
        """(input, processed) frames per second over the window."""
        now = time.monotonic() if now is None else now
        for times in (self._arrivals, self._completions):
            while times and times[0] < now - self.window:
                times.popleft()
        return len(self._arrivals) / self.window, len(self._completions) / self.window

    def latency_ms(self) -> tuple[float, float]:
        """(median, max) processing latency in ms over recent frames; NaN before any."""
        if not self._latencies:
            return float('nan'), float('nan')
        values = np.asarray(self._latencies) * 1e3
        return float(np.median(values)), float(values.max())
