"""
Small dense linear algebra that kernels share: 2x2 to 6x6 solves, inverses and pseudo-inverses.

Anything a kernel calls must be a kernel too, so the small systems of the fits (the
ellipse fit's 3x3 block, the marker's 4x4 and the pose's 6x6 normal equations, the
consider covariances' pseudo-inverses) are solved here, once, instead of by a
hand-written solver in each module. numba's own ``np.linalg`` works inside kernels
too, and is the choice wherever a call is rare; the routines here stay only where
``python -m vlp_ros.benchmarks.linalg_speed`` (each routine in a kernel loop) shows
that they pay in the per-frame loops: on matrices this small LAPACK's argument
checks, Fortran-order copies and allocations cost 3-10 times the arithmetic.

Functions:

- ``lu_solve(matrix, rhs, pivot_floor)``: ``Solved(ok, solution)`` of ``matrix x = rhs``
  (rhs a vector or columns) by LU with partial pivoting; not ok when a pivot is zero
  or below ``pivot_floor`` (``OPENCV_PIVOT_FLOOR``: as OpenCV's DECOMP_LU; 0: as
  LAPACK's gesv). 3-4x faster than ``np.linalg.solve``, which also raises instead of
  reporting a singular matrix.
- ``inverse3_into(matrix, out)``: the inverse of a 3x3 matrix by cofactors, inf/nan if
  it is singular (as the residuals that use it then are). ~30x faster than ``np.linalg.inv``.
- ``symmetric_eigen(matrix)``: ``Eigen(values, vectors)`` of a symmetric matrix: numba's
  ``np.linalg.eigh`` (a hand-written Jacobi saved ~6 us of a 4x4, under 1 % of a frame
  in the pipeline benchmark), nan for a matrix that is not finite instead of raising.
- ``pseudo_inverse(eigen, cutoff)``: the pseudo-inverse from an ``Eigen``, eigenvalues of
  magnitude at most ``cutoff`` dropped (``svd_cutoff`` and ``rcond_cutoff`` give OpenCV's
  DECOMP_SVD and numpy's ``pinv(..., hermitian=True)`` cut-offs).
- ``pseudo_inverse_form(eigen, vector, cutoff)``: ``v^T M^+ v`` from M's ``Eigen``.
- ``inverse_cholesky_3x3(gram)``: the inverse of a 3x3 Gram matrix's Cholesky factor, in
  closed form (the tone model's whitening); nan where the matrix is not positive definite.
- ``inverse_2x2_or_3x3(m)``: whether a 2x2 or 3x3 matrix is invertible, and its inverse by
  cofactors (the tone fit's normal equations). Against numba's ``np.linalg`` (``inv(cholesky())``,
  ``det`` and ``inv``) these two take 0.2 us per tone decode instead of 2 us, and give nan
  where LAPACK raises.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from vlp_ros.compiled import kernel

# OpenCV's DECOMP_LU treats pivots below this as zero.
OPENCV_PIVOT_FLOOR = 100.0 * float(np.finfo(np.float64).eps)
_DBL_EPSILON = float(np.finfo(np.float64).eps)


class Solved(NamedTuple):
    """The outcome of ``lu_solve``: ``ok`` False if the matrix was singular (``solution`` then undefined)."""

    ok: bool
    solution: np.ndarray


class Eigen(NamedTuple):
    """Eigenvalues (m,) and unit eigenvectors (m, m; as columns) of a symmetric matrix."""

    values: np.ndarray
    vectors: np.ndarray


@kernel
def lu_solve(matrix: np.ndarray, rhs: np.ndarray, pivot_floor: float) -> Solved:
    """Solve ``matrix`` (m, m) x = ``rhs`` ((m,) or (m, k)) by LU with partial pivoting."""
    m = matrix.shape[0]
    a = matrix.copy()
    solution = rhs.copy()
    b = solution.reshape((m, -1))
    columns = b.shape[1]
    for i in range(m):
        pivot = i
        for j in range(i + 1, m):
            if abs(a[j, i]) > abs(a[pivot, i]):
                pivot = j
        if a[pivot, i] == 0.0 or abs(a[pivot, i]) < pivot_floor:
            return Solved(False, solution)
        if pivot != i:
            for k in range(m):
                a[i, k], a[pivot, k] = a[pivot, k], a[i, k]
            for k in range(columns):
                b[i, k], b[pivot, k] = b[pivot, k], b[i, k]
        # Multipliers by the pivot's reciprocal, as OpenCV and LAPACK's dgetf2 form them.
        reciprocal = 1.0 / a[i, i]
        for j in range(i + 1, m):
            factor = a[j, i] * reciprocal
            for k in range(i + 1, m):
                a[j, k] -= factor * a[i, k]
            for k in range(columns):
                b[j, k] -= factor * b[i, k]
    for i in range(m - 1, -1, -1):
        for k in range(columns):
            total = b[i, k]
            for j in range(i + 1, m):
                total -= a[i, j] * b[j, k]
            b[i, k] = total / a[i, i]
    return Solved(True, solution)


@kernel
def inverse3_into(matrix: np.ndarray, out: np.ndarray) -> None:
    """Write the inverse of a 3x3 ``matrix`` into ``out`` (cofactors; inf/nan if singular)."""
    m = matrix
    c00 = m[1, 1] * m[2, 2] - m[1, 2] * m[2, 1]
    c01 = m[1, 2] * m[2, 0] - m[1, 0] * m[2, 2]
    c02 = m[1, 0] * m[2, 1] - m[1, 1] * m[2, 0]
    inverse_det = 1.0 / (m[0, 0] * c00 + m[0, 1] * c01 + m[0, 2] * c02)
    out[0, 0] = c00 * inverse_det
    out[1, 0] = c01 * inverse_det
    out[2, 0] = c02 * inverse_det
    out[0, 1] = (m[0, 2] * m[2, 1] - m[0, 1] * m[2, 2]) * inverse_det
    out[1, 1] = (m[0, 0] * m[2, 2] - m[0, 2] * m[2, 0]) * inverse_det
    out[2, 1] = (m[0, 1] * m[2, 0] - m[0, 0] * m[2, 1]) * inverse_det
    out[0, 2] = (m[0, 1] * m[1, 2] - m[0, 2] * m[1, 1]) * inverse_det
    out[1, 2] = (m[0, 2] * m[1, 0] - m[0, 0] * m[1, 2]) * inverse_det
    out[2, 2] = (m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0]) * inverse_det


@kernel
def symmetric_eigen(matrix: np.ndarray) -> Eigen:
    """Return the ``Eigen`` of a symmetric ``matrix`` (its lower triangle), all nan unless it is finite."""
    # np.linalg.eigh raises on inf or nan; a fit gone wrong should yield nan, as the other routines do.
    if not np.all(np.isfinite(matrix)):
        m = matrix.shape[0]
        # (Transposed: eigh's vectors are in Fortran order, and both results must have one type.)
        return Eigen(np.full(m, np.nan), np.full((m, m), np.nan).T)
    values, vectors = np.linalg.eigh(matrix)
    return Eigen(values, vectors)


@kernel
def svd_cutoff(eigen: Eigen) -> float:
    """Return OpenCV's DECOMP_SVD cut-off: 2 eps times the sum of the singular values."""
    total = 0.0
    for value in eigen.values:
        total += abs(value)
    return 2.0 * _DBL_EPSILON * total


@kernel
def rcond_cutoff(eigen: Eigen, rcond: float) -> float:
    """Return ``np.linalg.pinv(..., rcond, hermitian=True)``'s cut-off: rcond times the largest magnitude."""
    largest = 0.0
    for value in eigen.values:
        largest = max(largest, abs(value))
    return rcond * largest


@kernel
def pseudo_inverse(eigen: Eigen, cutoff: float) -> np.ndarray:
    """Return the pseudo-inverse of the matrix of ``eigen``, eigenvalues of magnitude <= ``cutoff`` dropped."""
    values, vectors = eigen.values, eigen.vectors
    m = values.size
    inverse = np.zeros((m, m))
    for i in range(m):
        if abs(values[i]) <= cutoff:
            continue
        weight = 1.0 / values[i]
        for r in range(m):
            for c in range(m):
                inverse[r, c] += vectors[r, i] * weight * vectors[c, i]
    return inverse


@kernel
def pseudo_inverse_form(eigen: Eigen, vector: np.ndarray, cutoff: float) -> float:
    """Return v^T M^+ v for ``vector`` v and the matrix M of ``eigen`` (eigenvalues <= ``cutoff`` dropped)."""
    values, vectors = eigen.values, eigen.vectors
    total = 0.0
    for i in range(values.size):
        if abs(values[i]) <= cutoff:
            continue
        projection = 0.0
        for r in range(values.size):
            projection += vectors[r, i] * vector[r]
        total += projection * projection / values[i]
    return total


@kernel
def inverse_cholesky_3x3(gram: np.ndarray) -> np.ndarray:
    """Return the inverse of the Cholesky factor of a 3x3 Gram matrix, in closed form."""
    a, b, c, d, e, f = gram[0, 0], gram[0, 1], gram[0, 2], gram[1, 1], gram[1, 2], gram[2, 2]
    l00 = math.sqrt(a)
    l10, l20 = b / l00, c / l00
    l11 = math.sqrt(d - l10 * l10)
    l21 = (e - l20 * l10) / l11
    l22 = math.sqrt(f - l20 * l20 - l21 * l21)
    m10 = -l10 / (l00 * l11)
    out = np.zeros((3, 3))
    out[0, 0], out[1, 0], out[1, 1] = 1.0 / l00, m10, 1.0 / l11
    out[2, 0], out[2, 1], out[2, 2] = -(l20 / l00 + l21 * m10) / l22, -l21 / (l11 * l22), 1.0 / l22
    return out


@kernel
def inverse_2x2_or_3x3(m: np.ndarray) -> tuple[bool, np.ndarray]:
    """Return whether a 2x2 or 3x3 matrix is invertible, and its inverse by cofactors."""
    n = len(m)
    cofactors = np.empty((n, n))
    if n == 2:
        cofactors[0, 0], cofactors[0, 1], cofactors[1, 0], cofactors[1, 1] = m[1, 1], -m[0, 1], -m[1, 0], m[0, 0]
        det = m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0]
    else:
        for r in range(3):
            for c in range(3):
                # The cofactor of m[c, r]: rows and columns other than c and r, in cyclic order.
                r1, r2, c1, c2 = (c + 1) % 3, (c + 2) % 3, (r + 1) % 3, (r + 2) % 3
                cofactors[r, c] = m[r1, c1] * m[r2, c2] - m[r1, c2] * m[r2, c1]
        det = m[0, 0] * cofactors[0, 0] + m[0, 1] * cofactors[1, 0] + m[0, 2] * cofactors[2, 0]
    scale = np.abs(m).max() ** n
    return np.isfinite(det) and abs(det) > 1e-12 * scale, cofactors / det
