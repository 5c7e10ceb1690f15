"""Ellipses as parameters and as conics, and the direct least-squares fit.

The fit is Fitzgibbon, Pilu and Fisher's direct ellipse-specific least squares
(PAMI 1999) in the numerically stable form of Halir and Flusser (1998), written
here because OpenCV's fitEllipseDirect returns no conic and no residuals.
"""
from __future__ import annotations

import numpy as np


def conic_from_ellipse(ellipse: np.ndarray) -> np.ndarray:
    """Symmetric 3x3 conic C with x^T C x = 0 for homogeneous points x on the ellipse."""
    cx, cy, a, b, theta = (float(v) for v in ellipse)
    c, s = np.cos(theta), np.sin(theta)
    # Axis-aligned conic diag(1/a^2, 1/b^2, -1) moved by rotation then translation.
    to_local = np.array([[c, s, -(c * cx + s * cy)], [-s, c, s * cx - c * cy], [0.0, 0.0, 1.0]])
    return to_local.T @ np.diag([1.0 / a ** 2, 1.0 / b ** 2, -1.0]) @ to_local


def ellipse_from_conic(conic: np.ndarray) -> np.ndarray:
    """(cx, cy, a, b, theta) of a real ellipse conic; ValueError for anything else."""
    C = np.asarray(conic, dtype=float)
    C = 0.5 * (C + C.T)
    A2 = C[:2, :2]
    if np.linalg.det(A2) <= 0.0:
        raise ValueError('conic is not an ellipse')
    center = np.linalg.solve(A2, -C[:2, 2])
    k = -(C[2, 2] + C[:2, 2] @ center)
    if k * A2[0, 0] <= 0.0:
        raise ValueError('conic is an imaginary ellipse')
    evals, evecs = np.linalg.eigh(A2 / k)
    # Smallest eigenvalue <-> longest axis.
    a, b = 1.0 / np.sqrt(evals[0]), 1.0 / np.sqrt(evals[1])
    theta = float(np.arctan2(evecs[1, 0], evecs[0, 0]))
    theta = (theta + np.pi / 2) % np.pi - np.pi / 2
    return np.array([center[0], center[1], a, b, theta])


def fit_ellipse(points: np.ndarray) -> np.ndarray:
    """Direct least-squares ellipse (cx, cy, a, b, theta) through >= 5 points (N, 2).

    Points are centred and scaled first so the fit is well conditioned for pixel
    coordinates of any magnitude.
    """
    p = np.asarray(points, dtype=float).reshape(-1, 2)
    if len(p) < 5:
        raise ValueError(f'an ellipse fit needs at least 5 points, got {len(p)}')
    mean = p.mean(axis=0)
    scale = np.sqrt(np.mean(np.sum((p - mean) ** 2, axis=1)))
    if not scale > 0.0:
        raise ValueError('ellipse fit points are all identical')
    x, y = ((p - mean) / scale).T
    D1 = np.stack([x * x, x * y, y * y], axis=1)
    D2 = np.stack([x, y, np.ones_like(x)], axis=1)
    S1, S2, S3 = D1.T @ D1, D1.T @ D2, D2.T @ D2
    try:
        T = -np.linalg.solve(S3, S2.T)
    except np.linalg.LinAlgError as err:
        raise ValueError('ellipse fit points are degenerate (collinear)') from err
    M = S1 + S2 @ T
    M = np.array([M[2] / 2.0, -M[1], M[0] / 2.0])
    evals, evecs = np.linalg.eig(M)
    evecs = np.real(evecs)
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
    h = np.column_stack([p, np.ones(len(p))])
    value = np.einsum('ni,ij,nj->n', h, C, h)
    grad = 2.0 * (h @ C)[:, :2]
    return value / np.linalg.norm(grad, axis=1)
