"""Pose covariance by first-order propagation of the measurement noise.

The pose is perturbed as in ``Pose``'s covariance convention: ``delta`` =
(position offset in the map, rotation vector about the map axes applied on the
left). With residuals already divided by their sigmas, the covariance of
``delta`` at the least-squares solution is (J^T J)^-1, J = d residuals / d delta.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

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


# Model error. A lamp that is not the model's uniform disc with a sharp edge (a diffuser
# brighter in the middle, glare, soft edges) moves its half-level crossings in or out all
# round the rim together: measured on an independent renderer's frames with blur 1.6 px,
# 30 % falloff and glare, 0.4-0.6 px inward with 0.3-0.4 px scatter about that, and on
# the simulator's falloff look 0.31 px, where clean frames are within 0.03 px. One lamp's
# rim cannot tell that offset from range (a larger disc farther away has the same image),
# so it is a parameter of the fit (``measurement.rim_offset_shape`` says how it varies
# round the rim). With several lamps, which fix the scale, it is estimated with a prior of
# ``RIM_OFFSET_FLOOR_PX`` (or ``RIM_OFFSET_PRIOR`` times the rim's scatter, if more), and
# the pose moves with it where the data determine it (its variance below
# ``OFFSET_DETERMINED`` of the prior's). One lamp's marker would fix the scale too, but
# too noisily and with a bias near frontal views (measured: 2 mm at 0.3 m, 5 standard
# errors): there it only widens the covariance along range by ``RIM_OFFSET_PRIOR`` times
# the rim's scatter. The rim points' scatter beyond their stated sigma, and a marker that
# the pose cannot place within ``MARKER_CONSISTENT`` sigmas, widen their own information
# by what their residuals show.
RIM_OFFSET_PRIOR = 1.5
RIM_OFFSET_FLOOR_PX = 0.5
OFFSET_DETERMINED = 0.25
MARKER_CONSISTENT = 2.0
_REWEIGHTINGS = 2


@dataclass(frozen=True)
class ModelErrorFit:
    """The pose fit allowing for model error: the pose ``step`` (as ``perturbed``'s delta),
    its ``covariance``, the chi-square ``cost`` with the rim offset fitted (its prior included),
    and the common rim offset ``rim_offset`` (px, outward positive; 0 where not determined)."""

    step: np.ndarray
    covariance: np.ndarray
    cost: float
    rim_offset: float


def allow_for_model_error(residuals: np.ndarray, jacobian: np.ndarray, rim_sigma: np.ndarray,
                          offset_shape: np.ndarray, lamp_count: int, marker_count: int) -> ModelErrorFit:
    """The linear update of a converged fit (whitened ``residuals`` and ``jacobian`` laid out as
    ``fit_kernels.Terms``: rim points, then 2 per marker, then 2 per up direction) by a common
    rim offset, each rim point moved by it times its ``offset_shape`` (``measurement.rim_offset_shape``),
    and by the residuals' own scatter; ValueError if the pose is not fully observed."""
    covariance_from_jacobian(jacobian)  # raises where no first-order covariance exists
    rim_count = len(rim_sigma)
    rims, markers = slice(0, rim_count), slice(rim_count, rim_count + 2 * marker_count)
    # d residual / d offset: an outward offset moves every rim point out by it.
    design = np.column_stack([jacobian, np.zeros(len(residuals))])
    design[rims, 6] = -offset_shape / rim_sigma
    offset_sigma = _rim_offset_sigma(residuals[rims], rim_sigma)
    estimated = lamp_count >= 2
    if estimated:
        offset_sigma = max(offset_sigma, RIM_OFFSET_FLOOR_PX)
    weights = np.ones(len(residuals))
    rim_dof = max(rim_count - 5 * lamp_count - 1, 1)
    for _ in range(_REWEIGHTINGS):
        step, covariance = _weighted_fit(residuals, design, weights, offset_sigma, estimated)
        predicted = residuals + design @ step
        weights[rims] = 1.0 / max(1.0, float(predicted[rims] @ predicted[rims]) / rim_dof)
        marker_chi2 = np.square(predicted[markers]).reshape(-1, 2).sum(axis=1)
        weights[markers] = np.repeat(1.0 / np.where(marker_chi2 > MARKER_CONSISTENT ** 2, marker_chi2, 1.0), 2)
    step, covariance = _weighted_fit(residuals, design, weights, offset_sigma, estimated)
    predicted = residuals + design @ step
    return ModelErrorFit(step=step[:6], covariance=0.5 * (covariance + covariance.T),
                         cost=float(predicted @ predicted + (step[6] / offset_sigma) ** 2), rim_offset=float(step[6]))


def _rim_offset_sigma(rim_residuals: np.ndarray, rim_sigma: np.ndarray) -> float:
    """The rim offset's prior sigma (px) from the rims' scatter; point lamps alone have no rim,
    and then the offset, which moves nothing, keeps the floor's prior."""
    if not len(rim_sigma):
        return RIM_OFFSET_FLOOR_PX
    scatter_px = float(np.sqrt(np.mean(np.square(rim_residuals * rim_sigma))))
    return RIM_OFFSET_PRIOR * max(scatter_px, float(np.mean(rim_sigma)))


def _weighted_fit(residuals: np.ndarray, design: np.ndarray, weights: np.ndarray, offset_sigma: float,
                  estimated: bool) -> tuple[np.ndarray, np.ndarray]:
    """The Gauss-Newton step (pose, offset) of the weighted residuals with the offset's prior,
    the offset left at 0 unless ``estimated`` and the data determine it, and the pose's covariance."""
    information = design.T @ (design * weights[:, None])
    information[6, 6] += 1.0 / offset_sigma ** 2
    covariance = np.linalg.inv(information)
    gradient = design.T @ (weights * residuals)
    if estimated and covariance[6, 6] < OFFSET_DETERMINED * offset_sigma ** 2:
        return -covariance @ gradient, covariance[:6, :6]
    step = np.zeros(7)
    step[:6] = -np.linalg.solve(information[:6, :6], gradient[:6])
    return step, covariance[:6, :6]


def widened_toward_up(pose: Pose, up_in_camera: np.ndarray, pivot: np.ndarray, share: float = 1.0) -> np.ndarray:
    """``pose``'s covariance plus ``share`` of the outer product of the pose change that would make it agree
    with a measured up direction (unit, camera frame): the rotation turning its up onto it, the
    camera turning about the map point ``pivot`` whose bearing the image pins. Whether the up
    measurement (an accelerating IMU) or the lamps (a shape off the model) are wrong, the frame
    cannot tell: the covariance then spans both."""
    measured_in_map = pose.rotation @ up_in_camera
    axis = np.cross(measured_in_map, np.array([0.0, 0.0, 1.0]))
    rotation = math.atan2(float(np.linalg.norm(axis)), float(measured_in_map[2])) * axis / max(
        float(np.linalg.norm(axis)), 1e-300)
    widened = np.array(pose.covariance, dtype=float)
    # The tilt is in doubt by that angle about either horizontal axis, not only the one measured,
    # and the position by what it moves the camera; uncorrelated, as the true tilt error is neither
    # exactly the measured angle nor exactly pivoting about ``pivot``.
    for tilt in (rotation, np.array([-rotation[1], rotation[0], 0.0])):
        moved = -np.cross(tilt, pivot - pose.position)
        widened[:3, :3] += share * np.outer(moved, moved)
        widened[3:, 3:] += share * np.outer(tilt, tilt)
    return widened
