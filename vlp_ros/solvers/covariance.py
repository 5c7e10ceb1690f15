"""Pose covariance by first-order propagation of the measurement noise.

The pose is perturbed as in ``Pose``'s covariance convention: ``delta`` =
(position offset in the map, rotation vector about the map axes applied on the
left). With residuals already divided by their sigmas, the covariance of
``delta`` at the least-squares solution is (J^T J)^-1, J = d residuals / d delta.
"""
from __future__ import annotations

import cv2
import numpy as np

from vlp_ros.pose import Pose

# Beyond this condition number of J^T J scaled to unit diagonal (units cancel)
# some pose direction is not observed to first order (e.g. an exactly frontal
# view of one lamp), and no first-order covariance exists.
_MAX_CONDITION = 1e12


def perturbed(pose: Pose, delta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rotation, position) of ``pose`` moved by ``delta`` = (dx, dy, dz, rotation vector)."""
    left, _ = cv2.Rodrigues(np.asarray(delta[3:], dtype=float))
    return left @ pose.rotation, pose.position + delta[:3]


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
