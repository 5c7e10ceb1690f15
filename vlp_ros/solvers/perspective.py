"""Exact perspective single-lamp solver: circle pose, marker yaw, then least-squares refinement.

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
but ~10 cm a few degrees off it, where the pair is really two poses.

A measured up direction (``UpMeasurement``: IMU gravity, or a mount prior with a
sigma) joins the fit and fixes the tilt the rim leaves loose: near-frontal views
then have one well-posed candidate and no merging is done; an oblique view's twin
keeps its minimum but pays for disagreeing with the measurement. A measurement no
candidate agrees with (an accelerating IMU) is left out (``with_agreeing_up``).
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from vlp_ros.camera import CameraModel
from vlp_ros.lamp_map import Lamp
from vlp_ros.observation import LampObservation
from vlp_ros.pose import Pose
from vlp_ros.solvers.ambiguity import COST_GAP
from vlp_ros.solvers.candidates import PoseCandidate, distinct
from vlp_ros.solvers.circle_pose import CirclePose, circle_poses, normalized_conic
from vlp_ros.solvers.covariance import perturbed, with_rotation_curvature
from vlp_ros.solvers.measurement import LampMeasurement
from vlp_ros.solvers.refinement import Measurement, linearize, refine_pose
from vlp_ros.solvers.up_measurement import UpMeasurement, with_agreeing_up

_MAP_UP = np.array([0.0, 0.0, 1.0])
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


def pose_from_circle(circle: CirclePose, lamp: Lamp, ray: np.ndarray, target: np.ndarray) -> Pose | None:
    """Camera pose from the lamp's circle in the camera frame and the ray (normalised,
    homogeneous) towards a map point ``target`` off the lamp's vertical axis: its marker,
    or another lamp's centre. None if the ray cannot reach the target's height."""
    up = circle.normal
    height = up @ circle.center + (target[2] - lamp.position[2])
    along_ray = up @ ray
    if not (along_ray > 0.0 and height > 0.0):
        return None
    offset = ray * (height / along_ray) - circle.center
    offset -= (offset @ up) * up
    heading_map = np.array([target[0] - lamp.position[0], target[1] - lamp.position[1], 0.0])
    if not (np.linalg.norm(offset) > 0.0 and np.linalg.norm(heading_map) > 0.0):
        return None
    heading_camera = offset / np.linalg.norm(offset)
    heading_map /= np.linalg.norm(heading_map)
    camera_basis = np.column_stack([heading_camera, np.cross(up, heading_camera), up])
    map_basis = np.column_stack([heading_map, np.cross(_MAP_UP, heading_map), _MAP_UP])
    rotation = map_basis @ camera_basis.T
    return Pose(rotation, lamp.position - rotation @ circle.center)


def closed_form_poses(measurement: LampMeasurement) -> list[Pose]:
    """The unrefined pose of each circle candidate (one or two)."""
    lamp = measurement.lamp
    if measurement.marker_ray is None:
        raise ValueError(f'lamp {lamp.name!r}: a single lamp needs its marker to fix the yaw')
    if not lamp.marker_distance > 0.0:
        raise ValueError(f'lamp {lamp.name!r}: marker at the centre cannot fix the yaw')
    circles = circle_poses(normalized_conic(measurement.rim_rays[:, :2]), lamp.radius)
    poses = (pose_from_circle(circle, lamp, measurement.marker_ray, lamp.marker_position()) for circle in circles)
    return [pose for pose in poses if pose is not None]


def solve_lamp(observation: LampObservation, lamp: Lamp, camera: CameraModel,
               up: Sequence[UpMeasurement] = ()) -> list[PoseCandidate]:
    """Refined candidate poses (one or two, cheapest first, covariance set) from one lamp and
    any measured up directions."""
    measurement = LampMeasurement.from_observation(observation, lamp, camera)
    starts = closed_form_poses(measurement)

    def refined(agreeing_up: Sequence[UpMeasurement]) -> list[PoseCandidate]:
        found: list[PoseCandidate] = []
        # The start that agrees best with the measured up first: it sets the bar for the other.
        for start in sorted(starts, key=lambda pose: _chi_square(agreeing_up, pose)):
            best = min((c.cost for c in found), default=np.inf)
            candidate = refine_pose(start, [measurement], agreeing_up,
                                    give_up=lambda pose, cost, best=best: cost > best + HOPELESS_GAP)
            if candidate is not None:
                found.append(_turning_about(candidate, lamp))
        candidates = distinct(found)
        if not agreeing_up and len(candidates) == 2 and _straddle_frontal(*candidates):
            return [_midpoint(*candidates, measurement)]
        return candidates

    return with_agreeing_up(refined, up)


def _chi_square(measurements: Sequence[Measurement], pose: Pose) -> float:
    if not measurements:
        return 0.0
    residuals, _ = linearize(measurements, pose)
    return float(residuals @ residuals)


def _turning_about(candidate: PoseCandidate, lamp: Lamp) -> PoseCandidate:
    pose = candidate.pose
    pose.covariance = with_rotation_curvature(pose.covariance, lamp.position - pose.position)
    return candidate


def _straddle_frontal(better: PoseCandidate, other: PoseCandidate) -> bool:
    separation = other.pose.error_vector(better.pose)
    return float(separation @ np.linalg.solve(better.pose.covariance, separation)) < FRONTAL_SEPARATION_M2


def _midpoint(a: PoseCandidate, b: PoseCandidate, measurement: LampMeasurement) -> PoseCandidate:
    separation = b.pose.error_vector(a.pose)
    pose = Pose(*perturbed(a.pose, 0.5 * separation))
    pose.covariance = 0.5 * (a.pose.covariance + b.pose.covariance) + 0.25 * np.outer(separation, separation)
    residuals, _ = linearize([measurement], pose)
    return PoseCandidate(pose=pose, cost=float(residuals @ residuals), residual_count=len(residuals))

