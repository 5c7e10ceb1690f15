"""What detection measures of one lamp in one frame: the hand-over to beacon decoding and solvers."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class LampObservation:
    """
    One lamp blob, in raw (distorted) pixel coordinates of the full frame.

    ``ellipse`` is (cx, cy, a, b, theta): centre, semi-axes a >= b, and the angle (rad)
    of the a axis from image +x toward +y, from a direct least-squares fit of
    ``rim_points``. ``rim_sigma`` is the measured standard deviation (px) of rim
    points across the edge; ``marker_sigma`` that of the marker centroid per axis (the root
    mean variance), and ``marker_covariance`` (2x2, px^2; None: ``marker_sigma`` on either
    axis) its covariance, which is not round: the marker fit pins it along the rim better
    than across it, where blur, glare and clipping move it.
    ``bbox`` = (x0, y0, x1, y1), x1 and y1 exclusive; ``disc_mask`` and
    ``marker_mask`` are boolean arrays over that box. ``rim_model_sigma`` is the prior sigma
    (px) of the smooth patterns (offset, first and second harmonic round the rim) by which a
    soft edge's rim points may depart from the disc's edge (``detection.rim.edge_model_sigma``),
    0 where the detector could not tell the edge's blur.

    ``rim_usable`` is False for a lamp whose light has no elliptic rim (a bare LED with
    its glow, a lamp too small, soft or overexposed for an ellipse): then ``center`` is
    the centre of its light (found robustly against stripes and glow: ``detection.point``),
    ``center_sigma`` its standard deviation per axis (px), ``ellipse`` the circle through
    the core's half-maximum crossings (a = b, theta 0; for masks and boxes only),
    ``rim_points`` is empty, ``rim_sigma`` infinite and ``marker`` None. Such an
    observation is a point for the solver, never a disc. For lamps with a usable rim
    ``center_sigma`` is None: the rim points carry the centre.
    """

    ellipse: np.ndarray
    rim_points: np.ndarray
    rim_sigma: float
    marker: np.ndarray | None
    marker_sigma: float
    bbox: tuple[int, int, int, int]
    disc_mask: np.ndarray
    marker_mask: np.ndarray | None = None
    rim_usable: bool = True
    center_sigma: float | None = None
    rim_model_sigma: float = 0.0
    marker_covariance: np.ndarray | None = None

    @property
    def center(self) -> np.ndarray:
        return np.asarray(self.ellipse[:2], dtype=float)
