"""What detection measures of one lamp in one frame: the hand-over to beacon decoding and solvers."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class LampObservation:
    """One lamp blob, in raw (distorted) pixel coordinates of the full frame.

    ``ellipse`` is (cx, cy, a, b, theta): centre, semi-axes a >= b, and the angle (rad)
    of the a axis from image +x toward +y, from a direct least-squares fit of
    ``rim_points``. ``rim_sigma`` is the measured standard deviation (px) of rim
    points across the edge; ``marker_sigma`` that of the marker centroid per axis.
    ``bbox`` = (x0, y0, x1, y1), x1 and y1 exclusive; ``disc_mask`` and
    ``marker_mask`` are boolean arrays over that box. ``center_sigma`` is the standard
    deviation (px, per axis) of ``center`` when the detector measures the centre itself
    (the light of a bare LED, whose rim is no ellipse); None: the rim points carry it.
    """

    ellipse: np.ndarray
    rim_points: np.ndarray
    rim_sigma: float
    marker: np.ndarray | None
    marker_sigma: float
    bbox: tuple[int, int, int, int]
    disc_mask: np.ndarray
    marker_mask: np.ndarray | None = None
    center_sigma: float | None = None

    @property
    def center(self) -> np.ndarray:
        return np.asarray(self.ellipse[:2], dtype=float)
