"""Pose covariance by first-order propagation of the measurement noise.

The pose is perturbed as in ``Pose``'s covariance convention: ``delta`` =
(position offset in the map, rotation vector about the map axes applied on the
left). With residuals already divided by their sigmas, the covariance of
``delta`` at the least-squares solution is (J^T J)^-1, J = d residuals / d delta.
"""
from __future__ import annotations

import numpy as np

from vlp_ros.pose import Pose
from vlp_ros.solvers.fit_kernels import perturb

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
    information = jacobian.T @ jacobian
    if not np.all(np.isfinite(information)) or not np.all(np.diag(information) > 0.0):
        raise ValueError('the measurements do not determine all six pose degrees of freedom')
    scale = 1.0 / np.sqrt(np.diag(information))
    if np.linalg.cond(information * np.outer(scale, scale)) > _MAX_CONDITION:
        raise ValueError('the measurements do not determine all six pose degrees of freedom')
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
    unit = lever / np.linalg.norm(lever)
    across = np.eye(3) - np.outer(unit, unit)
    b = 0.5 * (across[:, :, None] * lever[None, None, :] + lever[None, :, None] * across[:, None, :])
    b_p = b @ covariance[3:, 3:]
    mean = 0.5 * np.trace(b_p, axis1=1, axis2=2)
    widened = covariance.copy()
    widened[:3, :3] += 0.5 * np.einsum('ijk,lkj->il', b_p, b_p) + np.outer(mean, mean)
    return widened
