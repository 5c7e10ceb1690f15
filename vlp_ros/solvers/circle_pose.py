"""A circle of known radius from its perspective image: the cone method.

Safaee-Rad, Tchoukanov, Smith and Benhabib, "Three-dimensional location
estimation of circular features for machine vision", IEEE T-RA 8(5), 1992.
The image conic in normalised coordinates is the cone X^T C X = 0 through the
camera centre. In C's eigenframe (l1 >= l2 > 0 > l3) the cone minus l2 times
the unit sphere factorises into two planes, so every plane parallel to one of
them cuts the cone in a circle: two plane orientations, each with one distance
for the known radius.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vlp_ros.ellipse import conic_from_ellipse, ellipse_from_conic, fit_ellipse

# Below this (~ the tilt from the line of sight, rad) the two circles are one:
# roundoff alone makes it ~1e-8 for a circular image.
_COINCIDENT_TILT = 1e-6


@dataclass(frozen=True)
class CirclePose:
    """A circle in the camera frame: ``normal`` is the unit normal of its plane
    pointing away from the camera (``normal @ center`` is the plane's distance)."""

    normal: np.ndarray
    center: np.ndarray


def normalized_conic(normalized_rim: np.ndarray) -> np.ndarray:
    """Conic (3x3) fitted to rim points (N, 2) in undistorted normalised coordinates: the cone's matrix."""
    return conic_from_ellipse(fit_ellipse(normalized_rim))


def circle_poses(conic: np.ndarray, radius: float) -> list[CirclePose]:
    """Both circles of ``radius`` whose image is ``conic``; one when they coincide (frontal view)."""
    if not radius > 0.0:
        raise ValueError(f'circle radius must be positive, got {radius}')
    C = 0.5 * (np.asarray(conic, dtype=float) + np.asarray(conic, dtype=float).T)
    ellipse_from_conic(C)  # ValueError unless the image is a real ellipse
    evals, evecs = np.linalg.eigh(C)
    if np.count_nonzero(evals > 0.0) < 2:
        evals, evecs = -evals[::-1], evecs[:, ::-1]
    l3, l2, l1 = evals
    if not (l3 < 0.0 < l2):
        raise ValueError('conic is not the image of a circle (eigenvalue signs)')
    e1, e3 = evecs[:, 2], evecs[:, 0]
    span = l1 - l3
    # Clipped: l1 - l2 is a tiny negative number for a circular image.
    alpha = np.sqrt(max(l1 - l2, 0.0) / span)
    beta = np.sqrt((l2 - l3) / span)
    distance = radius * l2 / np.sqrt(-l1 * l3)
    signs = (1.0,) if alpha < _COINCIDENT_TILT else (1.0, -1.0)
    poses = []
    for sign in signs:
        normal = alpha * e1 + sign * beta * e3
        other = alpha * e1 - sign * beta * e3
        # Centre of the sphere l2 |X|^2 + (a.X)(b.X) = 0 on the plane, projected onto it.
        sphere_center = -distance * span / (2.0 * l2) * other
        center = sphere_center + (distance - normal @ sphere_center) * normal
        if center[2] < 0.0:
            # The cone is symmetric through the camera centre: take the nappe in front.
            normal, center = -normal, -center
        poses.append(CirclePose(normal=normal, center=center))
    return poses
