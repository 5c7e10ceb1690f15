"""
A circle of known radius from its perspective image: the cone method.

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
import math

import numpy as np

from vlp_ros.compiled import kernel
from vlp_ros.core.ellipse import conic_from_ellipse, ellipse_from_conic, fit_ellipse

# Below this (~ the tilt from the line of sight, rad) the two circles are one:
# roundoff alone makes it ~1e-8 for a circular image.
_COINCIDENT_TILT = 1e-6


@dataclass(frozen=True)
class CirclePose:
    """
    A circle in the camera frame.

    ``normal`` is the unit normal of its plane pointing away from the camera
    (``normal @ center`` is the plane's distance).
    """

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
    normals, centers = np.empty((2, 3)), np.empty((2, 3))
    count = _circles(evals, evecs, float(radius), _COINCIDENT_TILT, normals, centers)
    if count == 0:
        raise ValueError('conic is not the image of a circle (eigenvalue signs)')
    return [CirclePose(normal=normals[k], center=centers[k]) for k in range(count)]


@kernel
def _circles(evals, evecs, radius, coincident_tilt, normals, centers):
    """
    ``circle_poses`` from C's ascending eigenvalues and eigenvectors (columns).

    The number of circles (0 if C is not the image of a circle), their normals and centres
    into the rows.
    """
    flip = 1.0
    if (evals[0] > 0.0) + (evals[1] > 0.0) + (evals[2] > 0.0) < 2:
        # -C: its eigenvalues are -evals reversed, the vectors reversed with them.
        flip = -1.0
    l3, l2, l1 = evals[0], evals[1], evals[2]
    first, last = 2, 0
    if flip < 0.0:
        l3, l2, l1 = -evals[2], -evals[1], -evals[0]
        first, last = 0, 2
    if not (l3 < 0.0 < l2):
        return 0
    span = l1 - l3
    # Clipped: l1 - l2 is a tiny negative number for a circular image.
    alpha = math.sqrt(max(l1 - l2, 0.0) / span)
    beta = math.sqrt((l2 - l3) / span)
    distance = radius * l2 / math.sqrt(-l1 * l3)
    count = 1 if alpha < coincident_tilt else 2
    scale = -distance * span / (2.0 * l2)
    for k in range(count):
        signed_beta = (1.0 if k == 0 else -1.0) * beta
        along = 0.0
        for i in range(3):
            normals[k, i] = alpha * evecs[i, first] + signed_beta * evecs[i, last]
            # Centre of the sphere l2 |X|^2 + (a.X)(b.X) = 0 on the plane (b the other plane's
            # normal), projected onto it.
            centers[k, i] = scale * (alpha * evecs[i, first] - signed_beta * evecs[i, last])
            along += normals[k, i] * centers[k, i]
        for i in range(3):
            centers[k, i] += (distance - along) * normals[k, i]
        if centers[k, 2] < 0.0:
            # The cone is symmetric through the camera centre: take the nappe in front.
            for i in range(3):
                normals[k, i], centers[k, i] = -normals[k, i], -centers[k, i]
    return count
