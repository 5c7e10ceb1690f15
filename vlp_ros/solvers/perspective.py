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
of the equal two-component mixture: mean NEES 3-6, 6 mm error when exactly frontal.
"""
from __future__ import annotations

import numpy as np

from vlp_ros.camera import CameraModel
from vlp_ros.lamp_map import Lamp
from vlp_ros.observation import LampObservation
from vlp_ros.pose import Pose
from vlp_ros.solvers.candidates import PoseCandidate, distinct
from vlp_ros.solvers.circle_pose import CirclePose, circle_poses, normalized_conic
from vlp_ros.solvers.covariance import perturbed
from vlp_ros.solvers.measurement import LampMeasurement
from vlp_ros.solvers.refinement import linearize, refine_pose

_MAP_UP = np.array([0.0, 0.0, 1.0])
# Squared Mahalanobis separation (under the cheaper candidate's covariance) below
# which two candidates straddle a frontal view. For a truly frontal view it is
# distributed as ~450 chi-square(2) (measured: 4K and wide cameras, 0.1-0.3 px
# noise), so a frontal view stays unmerged with probability exp(-25000 / 900) < 1e-12;
# above it the first-order covariance is at most ~1.5x optimistic (mean NEES <= 9).
FRONTAL_SEPARATION_M2 = 25000.0


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


def solve_lamp(observation: LampObservation, lamp: Lamp, camera: CameraModel) -> list[PoseCandidate]:
    """Refined candidate poses (one or two, cheapest first, covariance set) from one lamp."""
    measurement = LampMeasurement.from_observation(observation, lamp, camera)
    refined = (refine_pose(pose, [measurement]) for pose in closed_form_poses(measurement))
    candidates = distinct([candidate for candidate in refined if candidate is not None])
    if len(candidates) == 2 and _straddle_frontal(*candidates):
        return [_midpoint(*candidates, measurement)]
    return candidates


def _straddle_frontal(better: PoseCandidate, other: PoseCandidate) -> bool:
    separation = other.pose.error_vector(better.pose)
    return float(separation @ np.linalg.solve(better.pose.covariance, separation)) < FRONTAL_SEPARATION_M2


def _midpoint(a: PoseCandidate, b: PoseCandidate, measurement: LampMeasurement) -> PoseCandidate:
    separation = b.pose.error_vector(a.pose)
    pose = Pose(*perturbed(a.pose, 0.5 * separation))
    pose.covariance = 0.5 * (a.pose.covariance + b.pose.covariance) + 0.25 * np.outer(separation, separation)
    residuals, _ = linearize([measurement], pose)
    return PoseCandidate(pose=pose, cost=float(residuals @ residuals), residual_count=len(residuals))

