"""
A robot on a horizontal floor: the floor as a measurement of the camera pose.

The robot's base frame moves on a horizontal floor at a known height (``planar.*``), and
the camera sits on it at a known mounting. Bumps, suspension and an uneven floor move the
base off that plane by ``sigma_height`` (m, its origin's height) and ``sigma_tilt`` (rad,
its +z axis about each horizontal axis). Through the mounting that is three residuals of
the camera pose: the base +z axis in the map, ``b = R_camera m`` with m where base +z
points in the camera, whose x and y should be 0; and the base origin's height,
``p_camera_z - (R_base t)_z``, which should be the floor's.

The image's candidate poses are fused with them by an iterated linear update (a
Gauss-Newton fit of the floor residuals against the candidate's pose and covariance),
weighted both ways. The image counts with the fit's own covariance (what its rim points
show) while the floor agrees with that within its 95 % point, so where several lamps or a
sharp rim fix the tilt better than the floor, the image does. Where they disagree beyond
it, the rim is off the model (glare, falloff and blur bias one small ellipse's shape and
size) and the image counts with the covariance that allows for that
(``covariance.allow_for_model_error``): the floor then decides the tilt and the range.
Neither overrides the other. The floor's residuals ride the rotation and height only, so
x, y and the yaw stay what the image says, moved only through their correlation with the
tilt and the height. The published covariance is the update's error under the model-error
allowance (Joseph form). Measured (``benchmarks.planar``): weighed by the allowance alone,
an independent renderer's clean robot frames, whose rims were right while their covariance
was ~3x too wide, lost a true 1.4 deg tilt to the floor (0.94 cm against 6-DoF's 0.76);
weighed by the fit alone, the simulator's realistic look kept its rims' bias (1.9 cm
against 1.4).

A candidate whose floor residuals the image plainly contradicts (the innovation's
chi-square, 3 dof, beyond a tail of 1e-6: a ramp, a lifted robot) is not one the robot
can be at, and is dropped; when every candidate goes, the frame has no pose
(``Reason.OFF_THE_FLOOR``). A disagreement beyond the 95 % point under the allowance too
widens it by the disagreement before the update: the image claims more than it knows, and
the floor then counts for correspondingly more.
The floor thereby also tells the two poses of one circle apart: the mirror pose's
tilt is off by twice the lamp's angle from the optical axis.

Where the image leaves a direction loose, the floor joins the fit itself. Several lamps'
fit takes the floor's tilt as an up measurement (two small lamps a metre apart leave the turn
about the line through them so loose that the fit slid 5 m from the truth to their mirror
pose; two point lamps leave it free), their model error estimated from their disagreement;
the height is fused after it. One disc lamp without its marker is fitted with the floor and
the recent pose's yaw, widened by how far the robot may have turned since (``TURN_RATE``).
"""
from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np
# scipy.special, not scipy.stats: the same chi-square tail without scipy.stats' import time at start.
from scipy.special import chdtri

from vlp_ros.core.camera import CameraModel
from vlp_ros.core.lamp_map import Lamp
from vlp_ros.core.mounting import Mounting
from vlp_ros.core.observation import LampObservation
from vlp_ros.core.pose import Pose
from vlp_ros.solvers.candidates import distinct, PoseCandidate
from vlp_ros.solvers.circle_pose import circle_poses, CirclePose, normalized_conic
from vlp_ros.solvers.covariance import allow_for_model_error, perturbed
from vlp_ros.solvers.fit_kernels import inverse_form
from vlp_ros.solvers.measurement import LampMeasurement, rim_error_modes
from vlp_ros.solvers.up_measurement import UpMeasurement

# Chi-square (3 dof) of the floor against the image beyond which the frame plainly contradicts it
# (tail 1e-6), and beyond which (its 95 % point) the covariance is widened by the disagreement.
OFF_THE_FLOOR_CHI2 = float(chdtri(3, 1e-6))
FLOOR_DOUBT_CHI2 = float(chdtri(3, 0.05))
# Squared Mahalanobis distance (6 dof, tail 1e-4) within which candidates fused with the floor are one pose.
SAME_POSE_CHI2 = float(chdtri(6, 1e-4))
# Fastest a ground robot is taken to turn (rad/s): a recent pose's yaw vouches for a later frame's
# within this rate times the time since.
TURN_RATE = 1.0
# Iterations of the linear update (the floor residuals are nearly linear: two reach 1e-6 of the minimum).
_UPDATE_ITERATIONS = 3
_FIT_ITERATIONS = 15
_FIT_STEP_TOLERANCE = 1e-9


@dataclass(frozen=True)
class Floor:
    """
    The horizontal floor the base frame moves on, and the camera's mounting on the base.

    ``height`` (m) is the base origin's z in the map; ``sigma_height`` (m) and ``sigma_tilt`` (rad)
    how far the base strays off the plane in height and in tilt about each horizontal axis.
    """

    mounting: Mounting
    height: float
    sigma_height: float
    sigma_tilt: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.sigma_height) and self.sigma_height > 0.0):
            raise ValueError(f'sigma_height must be positive and finite, got {self.sigma_height}')
        if not (math.isfinite(self.sigma_tilt) and self.sigma_tilt > 0.0):
            raise ValueError(f'sigma_tilt must be positive and finite, got {self.sigma_tilt}')

    def up_measurement(self) -> UpMeasurement:
        """Return the floor's tilt as a measured up direction in the camera frame (base +z is map +z)."""
        return UpMeasurement(self.mounting.up_in_camera(), self.sigma_tilt)

    def linearize(self, pose: Pose, tilt: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """
        Return the floor's whitened residuals at the camera ``pose`` and their Jacobian.

        Residuals (3,): base +z's map x and y over ``sigma_tilt``, the base origin's height off the floor
        over ``sigma_height`` (only the height, (1,), without ``tilt``); the Jacobian (3, 6) is in the pose
        perturbation of ``covariance.perturbed``. A rotation d (on the left, map axes) moves base +z
        b by d x b, and the base origin's height by d . (e_z x lever), lever = R_base t.
        """
        rotation = pose.rotation
        base_up = rotation @ self.mounting.up_in_camera()
        lever = rotation @ (self.mounting.rotation.T @ self.mounting.translation)
        height = (pose.position[2] - lever[2] - self.height) / self.sigma_height
        height_row = np.array([0.0, 0.0, 1.0, -lever[1], lever[0], 0.0]) / self.sigma_height
        if not tilt:
            return np.array([height]), height_row.reshape(1, 6)
        bx, by, bz = base_up
        tilt_rows = np.array([[0.0, 0.0, 0.0, 0.0, bz, -by],
                              [0.0, 0.0, 0.0, -bz, 0.0, bx]]) / self.sigma_tilt
        residuals = np.array([bx / self.sigma_tilt, by / self.sigma_tilt, height])
        return residuals, np.vstack([tilt_rows, height_row])


def on_floor(candidates: list[PoseCandidate], floor: Floor, tilt: bool = True) -> tuple[list[PoseCandidate], int]:
    """
    Return the candidates fused with the floor, cheapest first, and how many contradicted it.

    Without ``tilt`` only the height is fused: the tilt is already in the fit, and a fit that
    the image pulled off the floor's tilt by that chi-square contradicts it. A candidate whose
    floor chi-square exceeds ``OFF_THE_FLOOR_CHI2`` is left out; the chi-square is added to each
    kept candidate's cost, so the fit's cost rule weighs the floor too. Candidates the floor has
    brought within ``SAME_POSE_CHI2`` of the cheapest are one pose (``_merged``).
    """
    kept, contradicting = [], 0
    for candidate in candidates:
        fused, chi_square = _fused(candidate, floor, tilt)
        if chi_square > OFF_THE_FLOOR_CHI2 or (not tilt and tilted_off_the_floor(candidate, floor)):
            contradicting += 1
        else:
            kept.append(fused)
    kept = distinct(kept)
    if len(kept) < 2:
        return kept, contradicting
    same = [c for c in kept[1:] if inverse_form(kept[0].pose.covariance, c.pose.error_vector(kept[0].pose))
            <= SAME_POSE_CHI2]
    rest = [c for c in kept[1:] if not any(c is s for s in same)]
    return ([_merged([kept[0], *same]), *rest] if same else kept), contradicting


def _merged(candidates: list[PoseCandidate]) -> PoseCandidate:
    """
    Return one candidate for several the floor made the same pose: their mixture, weighed by likelihood.

    A near-frontal lamp's two poses, each fused with the floor, end centimetres and a degree or two of
    yaw apart, within a few sigma: neither is wrong, and the mixture's covariance spans both.
    """
    best = candidates[0]
    weights = np.exp(-0.5 * np.array([c.cost - best.cost for c in candidates]))
    weights /= weights.sum()
    offsets = [c.pose.error_vector(best.pose) for c in candidates]
    mean = sum(w * d for w, d in zip(weights, offsets))
    covariance = sum(w * (np.asarray(c.pose.covariance) + np.outer(d - mean, d - mean))
                     for w, c, d in zip(weights, candidates, offsets))
    pose = Pose(*perturbed(best.pose, mean), 0.5 * (covariance + covariance.T))
    return PoseCandidate(pose=pose, cost=best.cost, residual_count=best.residual_count)


def _fused(candidate: PoseCandidate, floor: Floor, tilt: bool) -> tuple[PoseCandidate, float]:
    """
    Return the candidate updated by the floor (iterated linear update) and the innovation chi-square.

    The update weighs the image by the fit's own covariance (``PoseCandidate.fit_covariance``: what the
    rim's points show) while the floor agrees with it within its 95 % point; beyond, the rim is off the
    model (glare, falloff, blur bias its shape) and the image is weighed by the candidate's covariance,
    which allows for that. The published covariance is the update's error under the candidate's
    covariance (Joseph form). The chi-square is taken under the candidate's covariance; beyond
    ``FLOOR_DOUBT_CHI2`` that covariance too is taken to understate the image's error by the
    disagreement, and is scaled by the chi-square over its degrees of freedom before the update.
    """
    covariance = np.asarray(candidate.pose.covariance, dtype=float)
    weighing = covariance if candidate.fit_covariance is None else np.asarray(candidate.fit_covariance, dtype=float)
    pose, jacobian, innovation = _updated(candidate.pose, weighing, floor, tilt)
    if _chi_square(innovation, jacobian, weighing) > FLOOR_DOUBT_CHI2:
        weighing = covariance
        pose, jacobian, innovation = _updated(candidate.pose, weighing, floor, tilt)
    chi_square = _chi_square(innovation, jacobian, covariance)
    if chi_square > FLOOR_DOUBT_CHI2:
        covariance = weighing = covariance * (chi_square / len(jacobian))
        pose, jacobian, _ = _updated(candidate.pose, weighing, floor, tilt)
    gain = _gain(weighing, jacobian)
    kept = np.eye(6) - gain @ jacobian
    posterior = kept @ covariance @ kept.T + gain @ gain.T
    # Told apart by the fused covariance: a near-frontal lamp's two poses, each fused with the floor, end
    # a centimetre apart, the same pose within what the image knows, though the fit alone claims less.
    pose.covariance = 0.5 * (posterior + posterior.T)
    fused = PoseCandidate(pose=pose, cost=candidate.cost + chi_square,
                          residual_count=candidate.residual_count + len(jacobian))
    return fused, chi_square


def _updated(prior: Pose, covariance: np.ndarray, floor: Floor, tilt: bool) -> tuple[Pose, np.ndarray, np.ndarray]:
    """Return the pose the floor moves ``prior`` to, the floor's Jacobian there, and the innovation."""
    step = np.zeros(6)
    pose = prior
    for _ in range(_UPDATE_ITERATIONS):
        residuals, jacobian = floor.linearize(pose, tilt)
        innovation = jacobian @ step - residuals
        step = _gain(covariance, jacobian) @ innovation
        pose = Pose(*perturbed(prior, step))
    return pose, jacobian, innovation


def _chi_square(innovation: np.ndarray, jacobian: np.ndarray, covariance: np.ndarray) -> float:
    """Return the innovation's chi-square under the image's ``covariance`` and the floor's unit noise."""
    return float(innovation @ np.linalg.solve(jacobian @ covariance @ jacobian.T + np.eye(len(innovation)),
                                              innovation))


def _gain(covariance: np.ndarray, jacobian: np.ndarray) -> np.ndarray:
    """Kalman gain P H^T (H P H^T + I)^-1 of whitened measurements."""
    projected = jacobian @ covariance
    innovation = projected @ jacobian.T + np.eye(len(jacobian))
    return np.linalg.solve(innovation, projected).T


def tilted_off_the_floor(candidate: PoseCandidate, floor: Floor) -> bool:
    """Whether a fit with the floor's tilt among its measurements was pulled off it by ``OFF_THE_FLOOR_CHI2``."""
    tilt_residuals = floor.linearize(candidate.pose)[0][:2]
    return float(tilt_residuals @ tilt_residuals) > OFF_THE_FLOOR_CHI2


def contradicts_floor(candidate: PoseCandidate, floor: Floor) -> bool:
    """
    Whether a pose fitted with the floor among its measurements plainly contradicts it.

    Its floor residuals' chi-square beyond ``OFF_THE_FLOOR_CHI2``: the image pulled the fit that far off the
    floor. The fit has absorbed part of the disagreement, so this refuses no more than the innovation would.
    """
    residuals, _ = floor.linearize(candidate.pose)
    return float(residuals @ residuals) > OFF_THE_FLOOR_CHI2


def yaw_from_continuity(observation: LampObservation, lamp: Lamp, camera: CameraModel, floor: Floor,
                        recent: Pose, age: float) -> tuple[list[PoseCandidate], int]:
    """
    Return the candidate poses of one disc lamp without its marker, and how many contradicted the floor.

    Each circle pose is headed as ``recent``.

    The rim fixes all but the turn about the lamp's vertical axis; the recent pose (``age`` s old)
    gives the yaw, within ``TURN_RATE`` x ``age`` and its own yaw variance. Each circle pose is fitted
    to the rim, that yaw and the floor (all three as measurements), its covariance allowing for the
    rim's model error; candidates that contradict the floor are left out.
    """
    measurement = LampMeasurement.from_observation(observation, lamp, camera)
    recent_yaw_variance = 0.0 if recent.covariance is None else float(recent.covariance[5, 5])
    sigma_yaw = math.sqrt(recent_yaw_variance + (TURN_RATE * age) ** 2 + 1e-6)
    found, contradicting = [], 0
    for circle in circle_poses(normalized_conic(measurement.rim_rays[:, :2]), lamp.radius):
        candidate = _fit_headed(_headed_as(circle, lamp, recent), measurement, floor, recent, sigma_yaw)
        if candidate is None:
            continue
        if contradicts_floor(candidate, floor):
            contradicting += 1
        else:
            found.append(candidate)
    return distinct(found), contradicting


def _headed_as(circle: CirclePose, lamp: Lamp, recent: Pose) -> Pose:
    """Return the camera pose whose up is the circle's normal, turned from ``recent`` by the least rotation."""
    up_in_map = recent.rotation @ circle.normal
    axis = np.cross(up_in_map, [0.0, 0.0, 1.0])
    angle = math.atan2(float(np.linalg.norm(axis)), float(up_in_map[2]))
    tilt = angle * axis / max(float(np.linalg.norm(axis)), 1e-300)
    rotation, _ = perturbed(recent, np.concatenate([np.zeros(3), tilt]))
    return Pose(rotation, lamp.position - rotation @ circle.center)


def _fit_headed(start: Pose, measurement: LampMeasurement, floor: Floor, recent: Pose,
                sigma_yaw: float) -> PoseCandidate | None:
    """Gauss-Newton on the rim, the recent yaw and the floor from ``start``; None if it breaks down."""
    pose = start
    try:
        for _ in range(_FIT_ITERATIONS):
            residuals, jacobian = _headed_residuals(pose, measurement, floor, recent, sigma_yaw)
            step = np.linalg.lstsq(jacobian, -residuals, rcond=None)[0]
            pose = Pose(*perturbed(pose, step))
            if float(step @ step) < _FIT_STEP_TOLERANCE:
                break
        else:
            return None
        residuals, jacobian = _headed_residuals(pose, measurement, floor, recent, sigma_yaw)
        terms = measurement.terms
        fit = allow_for_model_error(residuals, jacobian, terms.rim_sigma,
                                    rim_error_modes(terms, pose.rotation, pose.position), terms.lamp_of_point,
                                    1, 0, np.array([measurement.rim_model_sigma]))
    except (np.linalg.LinAlgError, ValueError):
        return None
    pose = Pose(*perturbed(pose, fit.step), fit.covariance)
    if not measurement.lamp_center_in_camera(pose.rotation, pose.position)[2] > 0.0:
        return None
    return PoseCandidate(pose=pose, cost=fit.cost, residual_count=len(residuals), fit_covariance=fit.fit_covariance)


def _headed_residuals(pose: Pose, measurement: LampMeasurement, floor: Floor, recent: Pose,
                      sigma_yaw: float) -> tuple[np.ndarray, np.ndarray]:
    """Return the rim's residuals, then the yaw's from ``recent``, then the floor's, with their Jacobian."""
    rim, rim_jacobian = measurement.linearize(pose.rotation, pose.position)
    yaw = _yaw_of(pose.rotation @ recent.rotation.T) / sigma_yaw
    floor_residuals, floor_jacobian = floor.linearize(pose)
    yaw_row = np.array([[0.0, 0.0, 0.0, 0.0, 0.0, 1.0 / sigma_yaw]])
    return (np.concatenate([rim, [yaw], floor_residuals]),
            np.vstack([rim_jacobian, yaw_row, floor_jacobian]))


def _yaw_of(rotation: np.ndarray) -> float:
    """Return the turn about map +z of a rotation near a pure yaw: where it turns a horizontal axis."""
    return math.atan2(rotation[1, 0] - rotation[0, 1], rotation[0, 0] + rotation[1, 1])
