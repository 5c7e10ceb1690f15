"""
Exact perspective single-lamp solver: circle pose, marker yaw, then least-squares refinement.

Each of the two circle poses of the rim fixes where map up points in the camera
(the disc is horizontal) and where the lamp centre is; the marker, intersected
with that plane, fixes the yaw about the vertical. Both candidates are refined
on all rim points and the marker and returned with their costs: one circle and
its marker generally cannot tell them apart (see ``ambiguity``).

Near a frontal view (the disc's normal along the line of sight) the two
candidates merge: the image conic depends on the tilt from the line of sight
only to second order, so noise splits one pose into two that straddle it,
each off by ~ distance * sqrt(noise / size) (9 cm for a 5.5 cm lamp at 2 m
with 0.3 px rim noise) with a first-order covariance that is far too small
(mean NEES ~ 80). Such a pair is replaced by its midpoint with the covariance
of the equal two-component mixture: mean NEES 3-6, 6 mm error when exactly frontal,
but ~10 cm a few degrees off it, where the pair is really two poses. A pair whose
members each explain the image while their merge does not is two poses too, however
close under the first-order covariance: the rim's cost rises between them (a 15 cm lamp
near the image centre 1.7 m above a robot's camera: the pair 20-40 cm apart, each at a
chi-square of ~50 for 50 rim points, the merge at 150-590). It is solved as two.

A measured up direction (``UpMeasurement``: IMU gravity, or a mount prior with a
sigma) fixes the tilt the rim leaves loose. Where the rim's pair is two distinct
poses, or the measurement singles one out of a frontal-straddling pair, the poses
are refined with it as two more residuals: the twin keeps its minimum but pays for
disagreeing (or, hopeless, is dropped). Where the pair is one blurred pose, the
merge is updated with it linearly: a fit there would land on one of the pair,
i.e. on the rim's noise, ~2 degrees off at 2 m (mean NEES ~ 20 with a 1 degree
sigma). A measurement no candidate agrees with (an accelerating IMU) is left out
(``with_agreeing_up``).
"""
from __future__ import annotations

from collections.abc import Sequence
from functools import cache
import math

import numpy as np

from vlp_ros.compiled import kernel
from vlp_ros.core.camera import CameraModel
from vlp_ros.core.lamp_map import Lamp
from vlp_ros.core.observation import LampObservation
from vlp_ros.core.pose import Pose
from vlp_ros.solvers.ambiguity import COST_GAP
from vlp_ros.solvers.candidates import distinct, explains_the_image, PoseCandidate
from vlp_ros.solvers.circle_pose import circle_poses, CirclePose, normalized_conic
from vlp_ros.solvers.covariance import perturbed, widened_toward_up, with_rotation_curvature
from vlp_ros.solvers.fit_kernels import inverse_form
from vlp_ros.solvers.measurement import LampMeasurement
from vlp_ros.solvers.refinement import FORECAST_MARGIN, forecast_minimum, linearize, Measurement, refine_pose
from vlp_ros.solvers.up_measurement import UpMeasurement, with_agreeing_up

# Squared Mahalanobis separation (under the cheaper candidate's covariance) below
# which two candidates straddle a frontal view. For a truly frontal view it is
# distributed as ~450 chi-square(2) (measured: 4K and wide cameras, 0.1-0.3 px
# noise), so a frontal view stays unmerged with probability exp(-25000 / 900) < 1e-12;
# above it the first-order covariance is at most ~1.5x optimistic (mean NEES <= 9).
FRONTAL_SEPARATION_M2 = 25000.0
# A start still this much costlier than a candidate already found after
# ``refinement.PATIENCE`` iterations is dropped: one lamp's rim has two minima, so
# such a start either creeps on to that candidate (10-20 more iterations against a
# gravity measurement) or stops at its own minimum, far over ``COST_GAP`` above it.
HOPELESS_GAP = 25.0 * COST_GAP
# Innovation chi-square gap between the two poses of a frontal-straddling pair beyond
# which the up measurements single one out (the other's posterior weight < 1e-3).
PAIR_RESOLVED_GAP = 2.0 * np.log(1000.0)
# Innovation chi-square (2 dof) of an up measurement beyond which the pose is widened toward it
# (its 95 % point: a lamp whose shape departs from the model tilts the pose by tenths of a
# degree to degrees while claiming hundredths, and only gravity shows it), by the share of
# the disagreement that noise does not explain. Measured (covariance_honesty, 30 frames):
# a trigger at the mean (2) took clean 4K NEES to 3.9-4.1.
UP_DOUBT = 5.99


def pose_from_circle(circle: CirclePose, lamp: Lamp, ray: np.ndarray, target: np.ndarray) -> Pose | None:
    """
    Return the camera pose from the lamp's circle in the camera frame and the ray towards a map point.

    The ray (normalised, homogeneous) points towards a map point ``target`` off the lamp's vertical
    axis: its marker, or another lamp's centre. None if the ray cannot reach the target's height.
    """
    rotation, position = np.empty((3, 3)), np.empty(3)
    if not _pose_from_circle(np.ascontiguousarray(circle.normal, dtype=float),
                             np.ascontiguousarray(circle.center, dtype=float),
                             np.ascontiguousarray(lamp.position, dtype=float), np.ascontiguousarray(ray, dtype=float),
                             np.ascontiguousarray(target, dtype=float), rotation, position):
        return None
    return Pose(rotation, position)


@kernel
def _pose_from_circle(up, center, lamp_position, ray, target, rotation, position):
    """
    ``pose_from_circle`` into ``rotation`` and ``position``; False if there is none.

    The ray meets the target's height on the lamp's plane (``up`` its normal); the heading
    from the lamp centre to that point, in the camera and in the map, fixes the yaw.
    """
    height = up[0] * center[0] + up[1] * center[1] + up[2] * center[2] + (target[2] - lamp_position[2])
    along_ray = up[0] * ray[0] + up[1] * ray[1] + up[2] * ray[2]
    if not (along_ray > 0.0 and height > 0.0):
        return False
    offset = np.empty(3)
    for i in range(3):
        offset[i] = ray[i] * (height / along_ray) - center[i]
    along_up = offset[0] * up[0] + offset[1] * up[1] + offset[2] * up[2]
    for i in range(3):
        offset[i] -= along_up * up[i]
    heading_x, heading_y = target[0] - lamp_position[0], target[1] - lamp_position[1]
    offset_norm = math.sqrt(offset[0] * offset[0] + offset[1] * offset[1] + offset[2] * offset[2])
    heading_norm = math.sqrt(heading_x * heading_x + heading_y * heading_y)
    if not (offset_norm > 0.0 and heading_norm > 0.0):
        return False
    # Camera basis: the heading, up x heading, up; map basis: the heading, its left turn, +z.
    camera = np.empty((3, 3))
    for i in range(3):
        camera[i, 0] = offset[i] / offset_norm
        camera[i, 2] = up[i]
    camera[0, 1] = up[1] * camera[2, 0] - up[2] * camera[1, 0]
    camera[1, 1] = up[2] * camera[0, 0] - up[0] * camera[2, 0]
    camera[2, 1] = up[0] * camera[1, 0] - up[1] * camera[0, 0]
    cos_yaw, sin_yaw = heading_x / heading_norm, heading_y / heading_norm
    for j in range(3):
        rotation[0, j] = cos_yaw * camera[j, 0] - sin_yaw * camera[j, 1]
        rotation[1, j] = sin_yaw * camera[j, 0] + cos_yaw * camera[j, 1]
        rotation[2, j] = camera[j, 2]
    for i in range(3):
        position[i] = lamp_position[i] - (rotation[i, 0] * center[0] + rotation[i, 1] * center[1]
                                          + rotation[i, 2] * center[2])
    return True


def closed_form_poses(measurement: LampMeasurement) -> list[Pose]:
    """Return the unrefined pose of each circle candidate (one or two)."""
    lamp = measurement.lamp
    if measurement.marker_ray is None:
        raise ValueError(f'lamp {lamp.name!r}: a single lamp needs its marker to fix the yaw')
    if not lamp.marker_distance > 0.0:
        raise ValueError(f'lamp {lamp.name!r}: marker at the centre cannot fix the yaw')
    circles = circle_poses(normalized_conic(measurement.rim_rays[:, :2]), lamp.radius)
    marker = lamp.marker_position()
    poses = (pose_from_circle(circle, lamp, measurement.marker_ray, marker) for circle in circles)
    return [pose for pose in poses if pose is not None]


def solve_lamp(observation: LampObservation, lamp: Lamp, camera: CameraModel,
               up: Sequence[UpMeasurement] = ()) -> list[PoseCandidate]:
    """
    Return refined candidate poses from one lamp and any measured up directions.

    They are one or two, cheapest first, covariance set.
    """
    measurement = LampMeasurement.from_observation(observation, lamp, camera)
    starts = closed_form_poses(measurement)

    @cache
    def rim_only() -> tuple[list[Pose], list[PoseCandidate]]:
        """Each start's own minimum (or the start, where the rim leaves a direction free), and the candidates."""
        fits = [(start, refine_pose(start, [measurement])) for start in starts]
        return ([start if fit is None else fit.pose for start, fit in fits],
                distinct([_turning_about(fit, lamp) for _, fit in fits if fit is not None]))

    def solve(agreeing: Sequence[UpMeasurement]) -> list[PoseCandidate]:
        if agreeing and _clearly_apart(starts, measurement):
            return _refined_with_up(starts, measurement, agreeing)
        minima, candidates = rim_only()
        if len(candidates) == 2 and _straddle_frontal(*candidates) and not _one_of_pair(candidates, agreeing):
            merged = _updated(_midpoint(*candidates, measurement), measurement, agreeing)
            if explains_the_image(merged) or not all(explains_the_image(c) for c in candidates):
                return [merged]
            # Each of the pair explains the image and their merge does not: the rim's cost rises
            # between them, so they are two poses after all (a lamp near the image centre seen from
            # 2 m, 40 cm apart), not one that noise split.
        return _refined_with_up(minima, measurement, agreeing) if agreeing else candidates

    return widened_where_up_disagrees(with_agreeing_up(solve, up), up, lamp.position)


def widened_where_up_disagrees(candidates: list[PoseCandidate], up: Sequence[UpMeasurement],
                               pivot: np.ndarray) -> list[PoseCandidate]:
    """
    Return ``candidates`` with each covariance widened toward every up measurement it disagrees with.

    It is widened beyond ``UP_DOUBT`` (``covariance.widened_toward_up``; ``pivot`` the map point the
    image pins).
    """
    for candidate in candidates:
        pose = candidate.pose
        for measurement in up:
            innovation = measurement.innovation(pose, candidate.separating_covariance)
            if innovation > UP_DOUBT:
                # Only the disagreement beyond what noise explains (2, its mean) is in doubt.
                excess = 1.0 - 2.0 / innovation
                pose.covariance = widened_toward_up(pose, measurement.direction, pivot, excess)
    return candidates


def _clearly_apart(starts: list[Pose], measurement: LampMeasurement) -> bool:
    """
    Whether the closed-form pair is too far apart to straddle a frontal view, without refining it.

    Its separation under the rim's information at one start tracks the refined pair's
    within ~30% (measured, 0-11 degree views, 4K and 1080p).
    """
    if len(starts) != 2:
        return False
    _, jacobian = linearize([measurement], starts[0])
    change = jacobian @ starts[1].error_vector(starts[0])
    return float(change @ change) > 2.0 * FRONTAL_SEPARATION_M2


def _one_of_pair(pair: list[PoseCandidate], up: Sequence[UpMeasurement]) -> bool:
    """
    Whether the up measurements single out one of a pair that straddles a frontal view.

    Then the pair was two poses after all and the one they favour is refined with them; else
    it is one blurred pose, and its merge is updated with them.
    """
    if not up:
        return False
    first, second = (_up_update(candidate.pose, up)[2] for candidate in pair)
    return abs(first - second) > PAIR_RESOLVED_GAP


def _refined_with_up(starts: list[Pose], measurement: LampMeasurement,
                     up: Sequence[UpMeasurement]) -> list[PoseCandidate]:
    found: list[PoseCandidate] = []
    # The start that agrees best with the measured up first: it sets the bar for the other.
    for start in sorted(starts, key=lambda pose: _chi_square(up, pose)):
        best = min((c.cost for c in found), default=np.inf)
        if found and forecast_minimum(start, [measurement, *up]) > FORECAST_MARGIN * (best + HOPELESS_GAP):
            continue
        fit = refine_pose(start, [measurement], up, give_up=lambda pose, cost, best=best: cost > best + HOPELESS_GAP)
        if fit is not None:
            found.append(_turning_about(fit, measurement.lamp))
    return distinct(found)


def _updated(merged: PoseCandidate, measurement: LampMeasurement, up: Sequence[UpMeasurement]) -> PoseCandidate:
    """
    Return the merged frontal pose corrected by the up measurements.

    It is one linear update: the up residuals are nearly linear over the pair's few degrees of spread.
    """
    if not up:
        return merged
    step, covariance, _ = _up_update(merged.pose, up)
    pose = Pose(*perturbed(merged.pose, step), covariance)
    residuals, _ = linearize([measurement, *up], pose)
    return PoseCandidate(pose=pose, cost=float(residuals @ residuals), residual_count=len(residuals))


def _up_update(pose: Pose, up: Sequence[UpMeasurement]) -> tuple[np.ndarray, np.ndarray, float]:
    """
    Return the linear (Kalman) update of ``pose`` and its covariance by the up measurements.

    (pose step, covariance after, innovation chi-square).
    """
    residuals, jacobian = linearize(up, pose)
    step, covariance = np.empty(6), np.empty((6, 6))
    chi_square = _kalman_update(residuals, jacobian, np.ascontiguousarray(pose.covariance, dtype=float),
                                step, covariance)
    return step, covariance, chi_square


@kernel
def _kalman_update(residuals, jacobian, covariance, step, covariance_after):
    """
    ``_up_update`` into ``step`` and ``covariance_after``, returning the innovation chi-square.

    S = J P J^T + I, gain K = P J^T S^-1, step -K r, P - K J P, r^T S^-1 r.
    """
    count = residuals.shape[0]
    projected = np.zeros((count, 6))
    for a in range(count):
        for i in range(6):
            for j in range(6):
                projected[a, i] += jacobian[a, j] * covariance[j, i]
    innovation = np.eye(count)
    for a in range(count):
        for b in range(count):
            for i in range(6):
                innovation[a, b] += projected[a, i] * jacobian[b, i]
    # S^-1 [J P, r], as one solve.
    right = np.empty((count, 7))
    right[:, :6] = projected
    right[:, 6] = residuals
    solved = np.linalg.solve(innovation, right)
    chi_square = 0.0
    for a in range(count):
        chi_square += residuals[a] * solved[a, 6]
    for i in range(6):
        total = 0.0
        for a in range(count):
            total += solved[a, i] * residuals[a]
        step[i] = -total
        for j in range(6):
            total = 0.0
            for a in range(count):
                total += solved[a, i] * projected[a, j]
            covariance_after[i, j] = covariance[i, j] - total
    return chi_square


def _chi_square(measurements: Sequence[Measurement], pose: Pose) -> float:
    residuals, _ = linearize(measurements, pose)
    return float(residuals @ residuals)


def _turning_about(candidate: PoseCandidate, lamp: Lamp) -> PoseCandidate:
    pose = candidate.pose
    lever = lamp.position - pose.position
    pose.covariance = with_rotation_curvature(pose.covariance, lever)
    if candidate.fit_covariance is not None:
        candidate.fit_covariance = with_rotation_curvature(candidate.fit_covariance, lever)
    return candidate


def _straddle_frontal(better: PoseCandidate, other: PoseCandidate) -> bool:
    separation = other.pose.error_vector(better.pose)
    return inverse_form(better.separating_covariance, separation) < FRONTAL_SEPARATION_M2


def _midpoint(a: PoseCandidate, b: PoseCandidate, measurement: LampMeasurement) -> PoseCandidate:
    separation = b.pose.error_vector(a.pose)
    pose = Pose(*perturbed(a.pose, 0.5 * separation))
    pose.covariance = 0.5 * (a.pose.covariance + b.pose.covariance) + 0.25 * np.outer(separation, separation)
    residuals, _ = linearize([measurement], pose)
    return PoseCandidate(pose=pose, cost=float(residuals @ residuals), residual_count=len(residuals))
