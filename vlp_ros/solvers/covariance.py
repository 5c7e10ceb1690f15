"""Pose covariance by first-order propagation of the measurement noise.

The pose is perturbed as in ``Pose``'s covariance convention: ``delta`` =
(position offset in the map, rotation vector about the map axes applied on the
left). With residuals already divided by their sigmas, the covariance of
``delta`` at the least-squares solution is (J^T J)^-1, J = d residuals / d delta.
"""
from __future__ import annotations

import math

import numpy as np

from vlp_ros.compiled import kernel
from vlp_ros.pose import Pose
from vlp_ros.solvers.fit_kernels import information_matrix, perturb

# Beyond this condition number of J^T J scaled to unit diagonal (units cancel)
# some pose direction is not observed to first order (e.g. an exactly frontal
# view of one lamp), and no first-order covariance exists.
_MAX_CONDITION = 1e12


def perturbed(pose: Pose, delta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rotation, position) of ``pose`` moved by ``delta`` = (dx, dy, dz, rotation vector)."""
    rotation, position = np.empty((3, 3)), np.empty(3)
    perturb(np.ascontiguousarray(pose.rotation), np.ascontiguousarray(pose.position),
            np.ascontiguousarray(delta, dtype=float), rotation, position)
    return rotation, position


def covariance_from_jacobian(jacobian: np.ndarray) -> np.ndarray:
    """(J^T J)^-1 of a whitened residual Jacobian; ValueError if the pose is not fully observed."""
    covariance = _covariance(np.ascontiguousarray(jacobian, dtype=float), _MAX_CONDITION)
    if covariance is None:
        raise ValueError('the measurements do not determine all six pose degrees of freedom')
    return covariance


@kernel
def _covariance(jacobian, max_condition):
    """Symmetrised (J^T J)^-1, or None if J^T J is not finite, has an unobserved direction or a
    condition number (scaled to unit diagonal) over ``max_condition``."""
    information = np.empty((6, 6))
    information_matrix(jacobian, information)
    if not np.all(np.isfinite(information)):
        return None
    scaled = np.empty((6, 6))
    for i in range(6):
        if not information[i, i] > 0.0:
            return None
    for i in range(6):
        for j in range(6):
            scaled[i, j] = information[i, j] / math.sqrt(information[i, i] * information[j, j])
    if np.linalg.cond(scaled) > max_condition:
        return None
    covariance = np.linalg.inv(information)
    return 0.5 * (covariance + covariance.T)


def nees(estimate: Pose, truth: Pose) -> float:
    """Normalised estimation error squared of ``estimate`` under its own covariance (mean 6 if honest)."""
    if estimate.covariance is None:
        raise ValueError('the estimate has no covariance')
    error = estimate.error_vector(truth)
    return float(error @ np.linalg.solve(estimate.covariance, error))


def with_rotation_curvature(covariance: np.ndarray, lever: np.ndarray) -> np.ndarray:
    """``covariance`` widened by the second-order position error of a pose that turns about a
    point whose bearing it sees sharply: the lamp centre, at map offset ``lever`` from the camera.

    With the bearing pinned, a rotation error d moves the camera by
    -(exp([d]x) - I) lever = -d x lever + q / 2, q = d x (d x lever). Along the lever
    the fitted range absorbs q; across it, q_i = (d . lever)(p_i . d), p_i the i-th row
    of the projector across the lever (the twist about the line of sight times the tilt
    across it): quadratic in d, so outside any first-order covariance. With d ~ N(0, P),
    q_i = d^T B_i d, B_i = sym(p_i lever^T): E q_i = tr(B_i P), Cov(q_i, q_j) =
    2 tr(B_i P B_j P); the second moment of q / 2 is added to the position block. It
    matters only when rotations are uncertain by degrees (one lamp seen near-frontally,
    its tilt from gravity), and is then many sigma of the bearing.
    """
    widened = np.array(covariance, dtype=float)
    _add_rotation_curvature(widened, np.ascontiguousarray(lever, dtype=float))
    return widened


@kernel
def _add_rotation_curvature(covariance, lever):
    """``with_rotation_curvature`` in place: B_i = sym(p_i lever^T) against the rotation block P."""
    length = math.sqrt(lever[0] * lever[0] + lever[1] * lever[1] + lever[2] * lever[2])
    b = np.empty((3, 3, 3))
    for i in range(3):
        for j in range(3):
            for k in range(3):
                across_ij = (1.0 if i == j else 0.0) - lever[i] * lever[j] / (length * length)
                across_ik = (1.0 if i == k else 0.0) - lever[i] * lever[k] / (length * length)
                b[i, j, k] = 0.5 * (across_ij * lever[k] + lever[j] * across_ik)
    b_p = np.zeros((3, 3, 3))
    for i in range(3):
        for j in range(3):
            for k in range(3):
                for m in range(3):
                    b_p[i, j, k] += b[i, j, m] * covariance[3 + m, 3 + k]
    mean = np.empty(3)
    for i in range(3):
        mean[i] = 0.5 * (b_p[i, 0, 0] + b_p[i, 1, 1] + b_p[i, 2, 2])
    for i in range(3):
        for m in range(3):
            total = 0.0
            for j in range(3):
                for k in range(3):
                    total += b_p[i, j, k] * b_p[m, k, j]
            covariance[i, m] += 0.5 * total + mean[i] * mean[m]
