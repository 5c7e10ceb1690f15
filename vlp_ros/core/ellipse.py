"""
Ellipses as parameters and as conics, and the direct least-squares fit.

The fit is Fitzgibbon, Pilu and Fisher's direct ellipse-specific least squares
(PAMI 1999) in the numerically stable form of Halir and Flusser (1998), written
here because OpenCV's fitEllipseDirect returns no conic and no residuals. The
numerics are compiled kernels (``vlp_ros.compiled``): a lamp's rim is fitted
several times per frame, and the same few dozen numpy calls on a few hundred
points cost more in call overhead than in arithmetic. Kernels report failures
as status codes, which the Python functions raise as ValueError.
"""
from __future__ import annotations

import math

import numpy as np

from vlp_ros.compiled import kernel
from vlp_ros.compiled.linalg import lu_solve, OPENCV_PIVOT_FLOOR

# Status codes of the kernels, and the errors they stand for.
OK, TOO_FEW, IDENTICAL, COLLINEAR, NO_ELLIPSE, NOT_ELLIPSE, IMAGINARY = range(7)
_ERRORS = {TOO_FEW: 'an ellipse fit needs at least 5 points, got {count}',
           IDENTICAL: 'ellipse fit points are all identical',
           COLLINEAR: 'ellipse fit points are degenerate (collinear)',
           NO_ELLIPSE: 'no ellipse fits these points',
           NOT_ELLIPSE: 'conic is not an ellipse',
           IMAGINARY: 'conic is an imaginary ellipse'}


def fit_error(status: int, count: int) -> ValueError:
    """Return the ValueError a kernel's non-OK ``status`` stands for (``count``: the points given)."""
    return ValueError(_ERRORS[status].format(count=count))


def conic_from_ellipse(ellipse: np.ndarray) -> np.ndarray:
    """Symmetric 3x3 conic C with x^T C x = 0 for homogeneous points x on the ellipse."""
    return conic_of(np.asarray(ellipse, dtype=float))


def ellipse_from_conic(conic: np.ndarray) -> np.ndarray:
    """(cx, cy, a, b, theta) of a real ellipse conic; ValueError for anything else."""
    status, ellipse = ellipse_of_conic(np.asarray(conic, dtype=float))
    if status != OK:
        raise fit_error(status, 0)
    return ellipse


def fit_ellipse(points: np.ndarray) -> np.ndarray:
    """
    Direct least-squares ellipse (cx, cy, a, b, theta) through >= 5 points (N, 2).

    Points are centred and scaled first so the fit is well conditioned for pixel
    coordinates of any magnitude.
    """
    p = np.ascontiguousarray(points, dtype=float).reshape(-1, 2)
    status, ellipse = fit_points(p)
    if status != OK:
        raise fit_error(status, len(p))
    return ellipse


def geometric_distances(ellipse: np.ndarray, points: np.ndarray) -> np.ndarray:
    """
    Approximate signed distance (N,) of points to the ellipse (Sampson, first order).

    Positive outside. Accurate to first order in distance / curvature radius,
    which is all the fit residuals here need.
    """
    return distances(np.asarray(ellipse, dtype=float), np.ascontiguousarray(points, dtype=float).reshape(-1, 2))


@kernel
def conic_of(ellipse: np.ndarray) -> np.ndarray:
    """``conic_from_ellipse`` of a float array (cx, cy, a, b, theta)."""
    cx, cy, a, b, theta = ellipse[0], ellipse[1], ellipse[2], ellipse[3], ellipse[4]
    c, s = math.cos(theta), math.sin(theta)
    # The axis-aligned conic u^2/a^2 + v^2/b^2 = 1, rotated by theta and moved to the centre.
    ia, ib = 1.0 / (a * a), 1.0 / (b * b)
    xx, yy, xy = c * c * ia + s * s * ib, s * s * ia + c * c * ib, c * s * (ia - ib)
    x1, y1 = -(xx * cx + xy * cy), -(xy * cx + yy * cy)
    conic = np.empty((3, 3))
    conic[0, 0], conic[0, 1], conic[0, 2] = xx, xy, x1
    conic[1, 0], conic[1, 1], conic[1, 2] = xy, yy, y1
    conic[2, 0], conic[2, 1] = x1, y1
    conic[2, 2] = xx * cx * cx + 2.0 * xy * cx * cy + yy * cy * cy - 1.0
    return conic


@kernel
def ellipse_of_conic(C: np.ndarray) -> tuple[int, np.ndarray]:
    """(status, ellipse) of a 3x3 float conic: ``ellipse_from_conic`` as a kernel."""
    ellipse = np.zeros(5)
    p, r = C[0, 0], C[1, 1]
    q, d, e = 0.5 * (C[0, 1] + C[1, 0]), 0.5 * (C[0, 2] + C[2, 0]), 0.5 * (C[1, 2] + C[2, 1])
    det = p * r - q * q
    if det <= 0.0:
        return NOT_ELLIPSE, ellipse
    cx, cy = (q * e - r * d) / det, (q * d - p * e) / det
    k = -(C[2, 2] + d * cx + e * cy)
    if k * p <= 0.0:
        return IMAGINARY, ellipse
    # Eigenvalues of the 2x2 block over k: the smaller one belongs to the longer axis.
    mean, radius = 0.5 * (p + r) / k, math.hypot(0.5 * (p - r), q) / abs(k)
    theta = 0.5 * math.atan2(-2.0 * q / k, (r - p) / k)
    ellipse[0], ellipse[1] = cx, cy
    ellipse[2], ellipse[3] = 1.0 / math.sqrt(mean - radius), 1.0 / math.sqrt(mean + radius)
    ellipse[4] = (theta + math.pi / 2) % math.pi - math.pi / 2
    return OK, ellipse


@kernel
def distances(ellipse: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``geometric_distances`` of a float ellipse and points (N, 2)."""
    C = conic_of(ellipse)
    out = np.empty(points.shape[0])
    for i in range(points.shape[0]):
        out[i] = conic_distance(C, points[i, 0], points[i, 1])
    return out


@kernel
def conic_distance(C: np.ndarray, x: float, y: float) -> float:
    """Return the signed Sampson distance of point (x, y) to the ellipse of conic ``C`` (3x3)."""
    # Half the conic's gradient, (C h)_xy, and its value h^T C h = (C h)_xy . p + (C h)_w.
    gx = C[0, 0] * x + C[0, 1] * y + C[0, 2]
    gy = C[0, 1] * x + C[1, 1] * y + C[1, 2]
    value = gx * x + gy * y + (C[0, 2] * x + C[1, 2] * y + C[2, 2])
    return 0.5 * value / math.sqrt(gx * gx + gy * gy)


@kernel
def fit_points(p: np.ndarray) -> tuple[int, np.ndarray]:
    """(status, ellipse) of the direct fit through points (N, 2): ``fit_ellipse`` as a kernel."""
    n = p.shape[0]
    if n < 5:
        return TOO_FEW, np.zeros(5)
    mx, my = 0.0, 0.0
    for i in range(n):
        mx += p[i, 0]
        my += p[i, 1]
    mx /= n
    my /= n
    spread = 0.0
    for i in range(n):
        spread += (p[i, 0] - mx) ** 2 + (p[i, 1] - my) ** 2
    scale = math.sqrt(spread / n)
    if not scale > 0.0:
        return IDENTICAL, np.zeros(5)
    # The scatter of the design rows [x^2, xy, y^2, x, y, 1]: it holds S1, S2 and S3 as blocks.
    scatter = np.zeros((6, 6))
    row = np.empty(6)
    row[5] = 1.0
    for i in range(n):
        x, y = (p[i, 0] - mx) / scale, (p[i, 1] - my) / scale
        row[0], row[1], row[2], row[3], row[4] = x * x, x * y, y * y, x, y
        for j in range(6):
            for k in range(j, 6):
                scatter[j, k] += row[j] * row[k]
    for j in range(6):
        for k in range(j):
            scatter[j, k] = scatter[k, j]
    # T = -S3^-1 S2^T, pivots as OpenCV's DECOMP_LU.
    solved = lu_solve(scatter[3:, 3:], scatter[:3, 3:].T.copy(), OPENCV_PIVOT_FLOOR)
    if not solved.ok:
        return COLLINEAR, np.zeros(5)
    T = -solved.solution
    reduced = scatter[:3, :3].copy()
    for i in range(3):
        for k in range(3):
            for j in range(3):
                reduced[i, k] += scatter[i, 3 + j] * T[j, k]
    M = np.empty((3, 3))
    for k in range(3):
        M[0, k] = reduced[2, k] / 2.0
        M[1, k] = -reduced[1, k]
        M[2, k] = reduced[0, k] / 2.0
    # The constrained eigenvalues are real (Halir and Flusser); of their eigenvectors, the one
    # with 4 A C - B^2 > 0 is the ellipse (the first by descending eigenvalue, as OpenCV sorts).
    values, vectors = np.linalg.eig(M)
    best = -1
    for j in range(3):
        if 4.0 * vectors[0, j] * vectors[2, j] - vectors[1, j] ** 2 > 0.0:
            if best < 0 or values[j] > values[best]:
                best = j
    if best < 0:
        return NO_ELLIPSE, np.zeros(5)
    a1 = vectors[:, best]
    rest = np.zeros(3)
    for i in range(3):
        for j in range(3):
            rest[i] += T[i, j] * a1[j]
    # (Filled element by element: numba builds a nested-list np.array through lists, at ~1 us each.)
    normalized = np.empty((3, 3))
    normalized[0, 0], normalized[0, 1], normalized[0, 2] = a1[0], a1[1] / 2, rest[0] / 2
    normalized[1, 0], normalized[1, 1], normalized[1, 2] = a1[1] / 2, a1[2], rest[1] / 2
    normalized[2, 0], normalized[2, 1], normalized[2, 2] = rest[0] / 2, rest[1] / 2, rest[2]
    # Undo the normalisation x_norm = S x, S = [[1/s, 0, -mx/s], [0, 1/s, -my/s], [0, 0, 1]]: S^T N S.
    S = np.zeros((3, 3))
    S[0, 0], S[0, 2], S[1, 1], S[1, 2], S[2, 2] = 1 / scale, -mx / scale, 1 / scale, -my / scale, 1.0
    conic = np.zeros((3, 3))
    for i in range(3):
        for k in range(3):
            for j in range(3):
                for m in range(3):
                    conic[i, k] += S[j, i] * normalized[j, m] * S[m, k]
    return ellipse_of_conic(conic)
