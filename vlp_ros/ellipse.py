"""Ellipses as parameters and as conics, and the direct least-squares fit.

The fit is Fitzgibbon, Pilu and Fisher's direct ellipse-specific least squares
(PAMI 1999) in the numerically stable form of Halir and Flusser (1998), written
here because OpenCV's fitEllipseDirect returns no conic and no residuals.
"""
from __future__ import annotations

import math

import cv2
import numpy as np


def conic_from_ellipse(ellipse: np.ndarray) -> np.ndarray:
    """Symmetric 3x3 conic C with x^T C x = 0 for homogeneous points x on the ellipse."""
    cx, cy, a, b, theta = (float(v) for v in ellipse)
    c, s = math.cos(theta), math.sin(theta)
    # The axis-aligned conic u^2/a^2 + v^2/b^2 = 1, rotated by theta and moved to the centre,
    # written out: tiny matrix products cost more in call overhead than in arithmetic.
    ia, ib = 1.0 / (a * a), 1.0 / (b * b)
    xx, yy, xy = c * c * ia + s * s * ib, s * s * ia + c * c * ib, c * s * (ia - ib)
    x1, y1 = -(xx * cx + xy * cy), -(xy * cx + yy * cy)
    return np.array([[xx, xy, x1], [xy, yy, y1], [x1, y1, xx * cx * cx + 2.0 * xy * cx * cy + yy * cy * cy - 1.0]])


def ellipse_from_conic(conic: np.ndarray) -> np.ndarray:
    """(cx, cy, a, b, theta) of a real ellipse conic; ValueError for anything else."""
    C = np.asarray(conic, dtype=float)
    p, r = float(C[0, 0]), float(C[1, 1])
    q, d, e = 0.5 * float(C[0, 1] + C[1, 0]), 0.5 * float(C[0, 2] + C[2, 0]), 0.5 * float(C[1, 2] + C[2, 1])
    det = p * r - q * q
    if det <= 0.0:
        raise ValueError('conic is not an ellipse')
    cx, cy = (q * e - r * d) / det, (q * d - p * e) / det
    k = -(float(C[2, 2]) + d * cx + e * cy)
    if k * p <= 0.0:
        raise ValueError('conic is an imaginary ellipse')
    # Eigenvalues of the 2x2 block over k: the smaller one belongs to the longer axis.
    mean, radius = 0.5 * (p + r) / k, math.hypot(0.5 * (p - r), q) / abs(k)
    a, b = 1.0 / math.sqrt(mean - radius), 1.0 / math.sqrt(mean + radius)
    theta = 0.5 * math.atan2(-2.0 * q / k, (r - p) / k)
    theta = (theta + math.pi / 2) % math.pi - math.pi / 2
    return np.array([cx, cy, a, b, theta])


def fit_ellipse(points: np.ndarray) -> np.ndarray:
    """Direct least-squares ellipse (cx, cy, a, b, theta) through >= 5 points (N, 2).

    Points are centred and scaled first so the fit is well conditioned for pixel
    coordinates of any magnitude.
    """
    p = np.asarray(points, dtype=float).reshape(-1, 2)
    if len(p) < 5:
        raise ValueError(f'an ellipse fit needs at least 5 points, got {len(p)}')
    mean = p.mean(axis=0)
    centred = p - mean
    scale = math.sqrt(float(np.einsum('ij,ij->', centred, centred)) / len(p))
    if not scale > 0.0:
        raise ValueError('ellipse fit points are all identical')
    # One design matrix [x^2, xy, y^2 | x, y, 1]: its scatter holds S1, S2 and S3 as blocks.
    design = np.empty((len(p), 6))
    design[:, 3:5] = centred / scale
    x, y = design[:, 3], design[:, 4]
    design[:, 0] = x * x
    design[:, 1] = x * y
    design[:, 2] = y * y
    design[:, 5] = 1.0
    scatter = design.T @ design
    S1, S2, S3 = scatter[:3, :3], scatter[:3, 3:], scatter[3:, 3:]
    # OpenCV's 3x3 solve and eigen decomposition: numpy's cost ~5x more in call overhead.
    solved, T = cv2.solve(S3, S2.T, flags=cv2.DECOMP_LU)
    if not solved:
        raise ValueError('ellipse fit points are degenerate (collinear)')
    T = -T
    M = S1 + S2 @ T
    M = np.array([M[2] / 2.0, -M[1], M[0] / 2.0])
    # The constrained eigenvalues are real (Halir and Flusser): OpenCV's solver assumes as much.
    _, evecs = cv2.eigenNonSymmetric(M)
    evecs = evecs.T
    cond = 4.0 * evecs[0] * evecs[2] - evecs[1] ** 2
    valid = np.flatnonzero(cond > 0.0)
    if valid.size == 0:
        raise ValueError('no ellipse fits these points')
    a1 = evecs[:, valid[0]]
    A, B, Cc = a1
    Dd, Ee, F = T @ a1
    normalized = np.array([[A, B / 2, Dd / 2], [B / 2, Cc, Ee / 2], [Dd / 2, Ee / 2, F]])
    # Undo the normalisation: x_norm = S x with S = [[1/s, 0, -mx/s], [0, 1/s, -my/s], [0, 0, 1]].
    S = np.array([[1 / scale, 0.0, -mean[0] / scale], [0.0, 1 / scale, -mean[1] / scale], [0.0, 0.0, 1.0]])
    return ellipse_from_conic(S.T @ normalized @ S)


def ellipse_points(ellipse: np.ndarray, count: int) -> np.ndarray:
    """``count`` points (N, 2) evenly spaced in parameter on the ellipse."""
    cx, cy, a, b, theta = (float(v) for v in ellipse)
    t = np.linspace(0.0, 2.0 * np.pi, count, endpoint=False)
    c, s = np.cos(theta), np.sin(theta)
    x, y = a * np.cos(t), b * np.sin(t)
    return np.stack([cx + c * x - s * y, cy + s * x + c * y], axis=1)


def geometric_distances(ellipse: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Approximate signed distance (N,) of points to the ellipse (Sampson, first order).

    Positive outside. Accurate to first order in distance / curvature radius,
    which is all the fit residuals here need.
    """
    C = conic_from_ellipse(ellipse)
    p = np.asarray(points, dtype=float).reshape(-1, 2)
    x, y = p[:, 0], p[:, 1]
    # Half the conic's gradient, (C h)_xy, and its value h^T C h = (C h)_xy . p + (C h)_w.
    gx = C[0, 0] * x + C[0, 1] * y + C[0, 2]
    gy = C[0, 1] * x + C[1, 1] * y + C[1, 2]
    value = gx * x + gy * y + (C[0, 2] * x + C[1, 2] * y + C[2, 2])
    return 0.5 * value / np.sqrt(gx * gx + gy * gy)
