"""
The shared small linear algebra of the kernels equals numpy's, and reports what numpy raises on.

Tolerances: a millionth relative, far above rounding and far below anything a fit could notice.
"""
import cv2
import numpy as np
import pytest

from vlp_ros.compiled.linalg import (inverse3_into, lu_solve, OPENCV_PIVOT_FLOOR, pseudo_inverse, pseudo_inverse_form,
                                     rcond_cutoff, svd_cutoff, symmetric_eigen)


@pytest.mark.parametrize('size', [2, 3, 4, 6])
def test_lu_solve_is_numpys_for_vectors_and_columns(size: int) -> None:
    rng = np.random.default_rng(size)
    for _ in range(20):
        matrix = rng.normal(size=(size, size))
        vector, columns = rng.normal(size=size), rng.normal(size=(size, 3))
        solved = lu_solve(matrix, vector, 0.0)
        assert solved.ok
        np.testing.assert_allclose(solved.solution, np.linalg.solve(matrix, vector), rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(lu_solve(matrix, columns, OPENCV_PIVOT_FLOOR).solution,
                                   np.linalg.solve(matrix, columns), rtol=1e-6, atol=1e-9)


def test_lu_solve_reports_a_singular_matrix() -> None:
    singular = np.array([[1.0, 2.0, 3.0], [2.0, 4.0, 6.0], [0.0, 1.0, 1.0]])
    assert not lu_solve(singular, np.ones(3), 0.0).ok
    # Rounding leaves a tiny pivot where the rows are dependent: the OpenCV floor counts it as zero.
    nearly = np.array([[0.1, 0.2, 0.3], [0.3, 0.6, 0.9 + 1e-17], [0.0, 1.0, 1.0]])
    assert not lu_solve(nearly, np.ones(3), OPENCV_PIVOT_FLOOR).ok
    assert not lu_solve(np.zeros((6, 6)), np.ones(6), 0.0).ok


def test_inverse3_is_numpys() -> None:
    rng = np.random.default_rng(3)
    out = np.empty((3, 3))
    for _ in range(20):
        matrix = rng.normal(size=(3, 3))
        inverse3_into(matrix, out)
        np.testing.assert_allclose(out, np.linalg.inv(matrix), rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize('size', [2, 4])
def test_pseudo_inverse_is_numpys_also_when_rank_deficient(size: int) -> None:
    rng = np.random.default_rng(4)
    for rank in range(1, size + 1):
        root = rng.normal(size=(size, rank))
        matrix = root @ root.T
        vector = rng.normal(size=size)
        eigen = symmetric_eigen(matrix)
        expected = np.linalg.pinv(matrix, rcond=1e-9, hermitian=True)
        np.testing.assert_allclose(pseudo_inverse(eigen, rcond_cutoff(eigen, 1e-9)), expected, rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(pseudo_inverse(eigen, svd_cutoff(eigen)), np.linalg.pinv(matrix),
                                   rtol=1e-6, atol=1e-6 * np.abs(expected).max())
        assert pseudo_inverse_form(eigen, vector, rcond_cutoff(eigen, 1e-9)) == pytest.approx(
            vector @ expected @ vector, rel=1e-6)


def test_a_matrix_that_is_not_finite_gives_nan_instead_of_raising() -> None:
    eigen = symmetric_eigen(np.array([[1.0, np.nan], [np.nan, 1.0]]))
    assert np.isnan(eigen.values).all() and np.isnan(pseudo_inverse(eigen, 0.0)).all()


def test_lu_solve_gives_opencvs_decomp_lu() -> None:
    rng = np.random.default_rng(5)
    for _ in range(20):
        root = rng.normal(size=(4, 4))
        matrix, vector = root @ root.T + 0.1 * np.eye(4), rng.normal(size=4)
        _, expected = cv2.solve(matrix, vector.reshape(4, 1), flags=cv2.DECOMP_LU)
        np.testing.assert_allclose(lu_solve(matrix, vector, OPENCV_PIVOT_FLOOR).solution, expected.ravel(),
                                   rtol=1e-8, atol=1e-10)


def test_pseudo_inverse_form_of_2x2_is_numpys_pinv() -> None:
    rng = np.random.default_rng(6)
    root = rng.normal(size=(40, 2, 2))
    matrices = [*(r @ r.T for r in root), *(np.outer(r[0], r[0]) for r in root[:10]),
                np.diag([1.0, 1e-12]), np.diag([-2.0, 3.0]), np.zeros((2, 2)), np.eye(2)]
    for matrix in matrices:
        vector = rng.normal(size=2)
        expected = vector @ np.linalg.pinv(matrix, rcond=1e-9, hermitian=True) @ vector
        eigen = symmetric_eigen(matrix)
        form = pseudo_inverse_form(eigen, vector, rcond_cutoff(eigen, 1e-9))
        assert form == pytest.approx(expected, rel=1e-6, abs=1e-9)
