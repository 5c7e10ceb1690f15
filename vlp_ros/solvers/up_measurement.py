"""
A measured up direction (IMU gravity, or a mount prior with a known spread) as pose residuals.

The residual is where the pose puts map +z in the camera frame, ``u = R^T e_z``,
seen from the measured direction g: its stereographic projection onto g's
tangent plane, ``2 T u / (1 + g.u)`` with T the two tangent axes, divided by
sigma. That is 2 tan(angle / 2) along the direction of the error, so ~ the
angle near g and growing without bound only at -g (a pose upside down is
never a minimum). It leaves the yaw and the position free: they come from the
lamps. Near a frontal view of one lamp, where the rim barely fixes the tilt
from the line of sight, these two residuals fix it.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
import math

import numpy as np

from vlp_ros.compiled import kernel
from vlp_ros.compiled.linalg import pseudo_inverse_form, rcond_cutoff, symmetric_eigen
from vlp_ros.core.pose import Pose
from vlp_ros.solvers.candidates import PoseCandidate
from vlp_ros.solvers.fit_kernels import linearize, Terms
# Largest innovation chi-square (2 dof) of a measured up direction that agrees with the
# lamps: exceeded by chance with probability 1e-4 (exp(-18.42 / 2)).
UP_INNOVATION_GATE = 18.42
# Relative size below which an eigenvalue of I - J P J^T is a direction the lamps do not observe.
_PSEUDO_INVERSE_RCOND = 1e-9


def unit_direction(vector: np.ndarray) -> np.ndarray:
    """``vector`` (3,) scaled to unit length; ValueError unless finite and non-zero."""
    vector = np.asarray(vector, dtype=float).reshape(3)
    # As np.linalg.norm (sqrt of the same BLAS dot), without its ~3 us of argument handling.
    norm = math.sqrt(vector @ vector)
    if not (math.isfinite(norm) and norm > 0.0):
        raise ValueError(f'up direction {vector} is not a finite non-zero vector')
    return vector / norm


@dataclass(frozen=True, eq=False)
class UpMeasurement:
    """
    Map +z measured in the camera optical frame as ``direction`` (any non-zero length), with its ``sigma``.

    ``sigma`` (rad) is the standard deviation of its error about each of the two axes perpendicular
    to it.
    """

    direction: np.ndarray
    sigma: float
    terms: Terms = field(init=False, repr=False)

    residual_count = 2

    def __post_init__(self) -> None:
        if not (math.isfinite(self.sigma) and self.sigma > 0.0):
            raise ValueError(f'up sigma must be positive and finite, got {self.sigma}')
        direction = unit_direction(self.direction)
        object.__setattr__(self, 'direction', direction)
        object.__setattr__(self, 'sigma', float(self.sigma))
        object.__setattr__(self, 'terms', Terms(up_directions=direction.reshape(1, 3),
                                                up_tangents=_tangent_axes(direction),
                                                up_sigma=np.array([self.sigma])))

    def linearize(self, rotation: np.ndarray, position: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """
        Return the residuals over sigma (2,) for the camera pose and their Jacobian (2, 6).

        The Jacobian is with respect to the pose perturbation of ``covariance.perturbed`` (the position
        columns are zero).
        """
        return linearize(self.terms, rotation, position)

    def innovation(self, pose: Pose, covariance: np.ndarray | None = None) -> float:
        """
        Return the chi-square (2 dof) of this measurement against the rest of a fit that included it.

        It is taken at that fit's ``pose`` with the fit's ``covariance`` (None: the pose's):
        r^T (I - J P J^T)^-1 r, the residual over its own variance after the fit has absorbed
        part of it. It is the measurement's disagreement with what the lamps alone say about
        the up direction, in sigmas squared; 0 along directions the lamps do not observe at all
        (nothing to disagree with). P must be the fit's own posterior (a covariance widened
        for model error is not: ``PoseCandidate.separating_covariance``).
        """
        covariance = pose.covariance if covariance is None else covariance
        if covariance is None:
            raise ValueError('the pose has no covariance')
        residual, jacobian = self.linearize(pose.rotation, pose.position)
        return _innovation(jacobian, np.ascontiguousarray(covariance, dtype=float), residual, _PSEUDO_INVERSE_RCOND)


@kernel
def _innovation(jacobian, covariance, residual, rcond):
    """``UpMeasurement.innovation`` from the measurement's Jacobian (2, 6) and residual (2,)."""
    left = np.empty((2, 2))
    for a in range(2):
        for b in range(2):
            total = 0.0
            for i in range(6):
                row = 0.0
                for j in range(6):
                    row += covariance[i, j] * jacobian[b, j]
                total += jacobian[a, i] * row
            left[a, b] = (1.0 if a == b else 0.0) - total
    # v^T M^+ v with M^+ as np.linalg.pinv(M, rcond, hermitian=True) forms it.
    eigen = symmetric_eigen(left)
    return pseudo_inverse_form(eigen, residual, rcond_cutoff(eigen, rcond))


@kernel
def _tangent_axes(direction):
    """
    Tangent axes (1, 2, 3) of a unit ``direction`` g.

    G x e for the axis e least aligned with g, normalised, then g x that.
    """
    least = 0
    for i in range(1, 3):
        if abs(direction[i]) < abs(direction[least]):
            least = i
    axis = np.zeros(3)
    axis[least] = 1.0
    tangents = np.empty((1, 2, 3))
    first, second = tangents[0, 0], tangents[0, 1]
    _cross(direction, axis, first)
    norm = math.sqrt(first[0] * first[0] + first[1] * first[1] + first[2] * first[2])
    for i in range(3):
        first[i] /= norm
    _cross(direction, first, second)
    return tangents


@kernel
def _cross(a, b, out):
    out[0] = a[1] * b[2] - a[2] * b[1]
    out[1] = a[2] * b[0] - a[0] * b[2]
    out[2] = a[0] * b[1] - a[1] * b[0]


def with_agreeing_up(solve: Callable[[Sequence[UpMeasurement]], list[PoseCandidate]],
                     up: Sequence[UpMeasurement]) -> list[PoseCandidate]:
    """
    Return ``solve(up)``, solved again without every up measurement that no candidate agrees with.

    An up measurement is disagreed with at an innovation over ``UP_INNOVATION_GATE``: an accelerating
    IMU's "gravity" would otherwise pull the pose away from what the lamps show.
    """
    candidates = solve(up)
    agreeing = [m for m in up if any(m.innovation(c.pose, c.separating_covariance) <= UP_INNOVATION_GATE
                                     for c in candidates)]
    return candidates if len(agreeing) == len(up) else solve(agreeing)
