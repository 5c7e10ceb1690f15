"""
Maximum-likelihood camera pose: least squares over all six DoF and all lamp measurements.

A small Levenberg-Marquardt loop on the analytic Jacobians of ``measurement``
rather than scipy.optimize.least_squares: the starts are close, so a solve
takes 3-6 iterations, run whole in one kernel (``fit_kernels.iterate``), while
least_squares' per-call overhead alone is over 1 ms (python -m
vlp_ros.benchmarks.solver_speed). Measured up directions (``up_measurement``) join the
lamps' residuals: their information enters the fit and its covariance like any
other measurement's.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Protocol

import numpy as np

from vlp_ros.core.pose import Pose
from vlp_ros.solvers.candidates import PoseCandidate
from vlp_ros.solvers.covariance import allow_for_model_error, perturbed
from vlp_ros.solvers.fit_kernels import (CONVERGED, forecast, iterate, joined, Linearization, linearize_into, PAUSED,
                                         SINGULAR, Terms)
from vlp_ros.solvers.fit_kernels import linearize as linearize_terms
from vlp_ros.solvers.measurement import LampMeasurement, rim_error_modes
from vlp_ros.solvers.up_measurement import UpMeasurement

_MAX_ITERATIONS = 50
_INITIAL_DAMPING = 1e-4
# Iterations after which ``descend`` judges whether a start is still worth following.
PATIENCE = 3
# A start whose Gauss-Newton forecast of its minimum exceeds a hopeless bar by this factor
# is dropped before it is followed at all (one linearisation instead of ``PATIENCE`` + 1).
# Measured on the accuracy benchmark: for 270 single-lamp second starts the forecast
# tracked the minimum reached within 1 %, and the same starts were dropped as after
# ``PATIENCE`` iterations; of 769 multi-lamp probes it drops 533, none of which reached
# a pose when followed.
FORECAST_MARGIN = 2.0


class Measurement(Protocol):
    """Whitened residuals of a pose: a lamp's (``LampMeasurement``) or an up direction's."""

    residual_count: int
    terms: Terms

    def linearize(self, rotation: np.ndarray, position: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...


def linearize(measurements: Sequence[Measurement], pose: Pose) -> tuple[np.ndarray, np.ndarray]:
    """Stacked whitened residuals (M,) and their Jacobian (M, 6) of all measurements at ``pose``."""
    return linearize_terms(joined([m.terms for m in measurements]), pose.rotation, pose.position)


def refine_pose(initial: Pose, measurements: Sequence[LampMeasurement], up: Sequence[UpMeasurement] = (),
                give_up: Callable[[Pose, float], bool] | None = None) -> PoseCandidate | None:
    """
    Return the least-squares pose nearest ``initial``, with its covariance, given the lamps and any up directions.

    The up directions are measured. None if the fit breaks down (the optical centre in a lamp's plane,
    a lamp behind the camera, a pose direction the measurements leave free, or no convergence), or if
    ``give_up(pose, chi-square)`` holds after ``PATIENCE`` iterations.
    """
    terms = [*measurements, *up]
    count = sum(m.residual_count for m in terms)
    if count < 6:
        raise ValueError(f'{count} residuals cannot determine a 6-DoF pose')
    try:
        joint = joined([m.terms for m in terms])
        pose, residuals, jacobian, converged = _levenberg_marquardt(initial, joint, _MAX_ITERATIONS, give_up)
        if not converged:
            return None
        fit = allow_for_model_error(residuals, jacobian, joint.rim_sigma,
                                    rim_error_modes(joint, pose.rotation, pose.position), joint.lamp_of_point,
                                    len(joint.centres), len(joint.marker_maps),
                                    np.array([m.rim_model_sigma for m in measurements if len(m.terms.centres)]))
    except (np.linalg.LinAlgError, ValueError):
        return None
    pose = Pose(*perturbed(pose, fit.step), fit.covariance)
    if not all(m.lamp_center_in_camera(pose.rotation, pose.position)[2] > 0.0 for m in measurements):
        return None
    return PoseCandidate(pose=pose, cost=fit.cost, residual_count=count, fit_covariance=fit.fit_covariance)


def forecast_minimum(initial: Pose, measurements: Sequence[Measurement]) -> float:
    """
    Return the chi-square that the Gauss-Newton model at ``initial`` forecasts for the nearest minimum.

    One linearisation, against the several iterations of reaching it.
    """
    return forecast_from(*linearize(measurements, initial))


def forecast_from(residuals: np.ndarray, jacobian: np.ndarray) -> float:
    """``forecast_minimum`` from a linearisation already at hand."""
    return float(forecast(np.ascontiguousarray(residuals, dtype=float), np.ascontiguousarray(jacobian, dtype=float)))


def descend(initial: Pose, measurements: Sequence[Measurement], max_iterations: int,
            give_up: Callable[[Pose, float], bool] | None = None) -> tuple[Pose, float] | None:
    """
    Return the least-squares pose and its chi-square reached from ``initial`` within ``max_iterations``.

    It is a cheap probe of where a start leads; None if not reached, or if
    ``give_up(pose, chi-square)`` holds after ``PATIENCE`` iterations.
    """
    try:
        pose, residuals, _, converged = _levenberg_marquardt(initial, joined([m.terms for m in measurements]),
                                                             max_iterations, give_up)
    except np.linalg.LinAlgError:
        return None
    return (pose, float(residuals @ residuals)) if converged else None


def _levenberg_marquardt(pose: Pose, terms: Terms, max_iterations: int,
                         give_up: Callable[[Pose, float], bool] | None = None
                         ) -> tuple[Pose, np.ndarray, np.ndarray, bool]:
    fit = Linearization(np.array(pose.rotation, dtype=float), np.array(pose.position, dtype=float),
                        np.empty(terms.residual_count), np.empty((terms.residual_count, 6)))
    rotation, position, residuals, jacobian = fit
    cost = linearize_into(fit, terms)
    pause = PATIENCE if give_up is not None and max_iterations > PATIENCE else max_iterations
    outcome, cost, damping = iterate(fit, terms, cost, _INITIAL_DAMPING, pause)
    if outcome == PAUSED and pause < max_iterations:
        if give_up(Pose(rotation.copy(), position.copy()), cost):
            return Pose(rotation, position), residuals, jacobian, False
        outcome, cost, damping = iterate(fit, terms, cost, damping, max_iterations - pause)
    if outcome == SINGULAR:
        raise np.linalg.LinAlgError('singular normal equations')
    return Pose(rotation, position), residuals, jacobian, outcome == CONVERGED
