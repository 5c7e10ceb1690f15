"""The seed paper's single-lamp pose solver: weak perspective of one circle and its marker.

Zhang, Zhong, Kemao and Zhang, "A Single LED Positioning System Based on Circle
Projection", IEEE Photonics Journal 9(4), 2017. Only the paper's abstract could
be retrieved while writing this; the solver is reconstructed from the published
description of its method (weak perspective, scale s = a / r, two rotation
angles from the marker, one from the ellipse shape with cos(tilt) = b / a and the
ellipse orientation as in its Appendix B, position from the lamp's known
position, the scale and the focal length). Equation numbers refer to the paper;
the algebra and the angle convention below are ours.

Model. Under weak perspective a lamp-plane point at map offset (x, y) from the
lamp centre images at ``u = u_c + s * M @ (x, y)``, where ``u_c`` is the ellipse
centre (taken as the image of the lamp centre), ``s = f / Z`` with Z the lamp's
depth, and M the top-left 2x2 block of the map-to-camera rotation. Writing that
rotation as ``Rz(gamma) Rx(alpha) Rz(beta)`` gives
``M = R2(gamma) diag(1, cos alpha) R2(beta)``, hence:

- semi-axes ``a = s r`` and ``b = s r cos(alpha)``: the scale ``s = a / r`` (eq. 1)
  and the tilt ``cos(alpha) = b / a`` (eq. 12-13, Appendix B);
- the major axis lies at image angle ``gamma``: the ellipse orientation;
- the marker offset ``s d M (cos phi, sin phi)`` then fixes ``beta`` (the role of
  eq. 7-8), whatever the tilt, as it also pins ``gamma + beta`` when the tilt is 0.

Units (eq. 1 and 14 as printed mix millimetres and pixels): we read them as
``Z = f r / a`` with f and a in the same unit. We work in undistorted normalised
image coordinates (pixels of an ideal camera with f = 1, from
``CameraModel.normalize``, the same points as ``undistort_pixels`` divided by f),
so ``Z = r / a`` and the lamp centre in the camera frame is ``(u_c, 1) * Z``
(eq. 14); lens distortion is removed before the ellipse is refitted, so it is
not counted against the method.

Candidates. ``cos(alpha) < 0`` would put the camera above the lamp's lit face and
is excluded. The two signs of ``alpha`` leave M unchanged, so they predict the
same weak-perspective image of every point of the lamp plane, marker included:
this is the reflection ambiguity of weak perspective, and none of the paper's
quantities separates the two. Both are returned, sorted by the chi-square of
the full perspective reprojection of the rim and the marker, so that the first
is the one the image favours and the caller's disambiguation (cost gap, gravity,
continuity) treats this solver like any other. Neither pose is refined: the
poses are exactly the paper's; only their ranking uses perspective.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from vlp_ros.camera import CameraModel
from vlp_ros.ellipse import ellipse_from_conic, fit_ellipse, geometric_distances
from vlp_ros.lamp_map import Lamp
from vlp_ros.observation import LampObservation
from vlp_ros.pose import Pose
from vlp_ros.solvers.candidates import PoseCandidate

# Below this b / a the lamp is seen nearly edge-on and 1 / cos(alpha) amplifies
# any marker error without bound.
MIN_AXIS_RATIO = 0.05


def solve_lamp_paper(observation: LampObservation, lamp: Lamp,
                     camera: CameraModel) -> list[PoseCandidate]:
    """The paper's two weak-perspective poses of the camera, the better-fitting one first."""
    if observation.marker is None:
        raise ValueError("the paper's solver needs the marker to fix the rotation about the lamp axis")
    if not (observation.rim_sigma > 0.0 and observation.marker_sigma > 0.0):
        raise ValueError(f'rim_sigma ({observation.rim_sigma}) and marker_sigma '
                         f'({observation.marker_sigma}) must be positive')
    if not lamp.marker_distance > 0.0:
        raise ValueError(f'lamp {lamp.name!r} has its marker at the centre: no azimuth to read')
    rim = camera.normalize(observation.rim_points)
    marker = camera.normalize(observation.marker)[0]
    ellipse = fit_ellipse(rim)
    poses = [_weak_perspective_pose(ellipse, marker, lamp, sign) for sign in (1.0, -1.0)]
    candidates = [_scored(pose, rim, marker, observation, lamp, camera) for pose in poses]
    return sorted(candidates, key=lambda candidate: candidate.cost)


def _weak_perspective_pose(ellipse: np.ndarray, marker: np.ndarray, lamp: Lamp,
                           tilt_sign: float) -> Pose:
    """Camera pose from the normalised ellipse and marker, for one sign of the tilt."""
    cx, cy, a, b, theta = (float(v) for v in ellipse)
    axis_ratio = b / a
    if axis_ratio < MIN_AXIS_RATIO:
        raise ValueError(f'lamp seen nearly edge-on (b / a = {axis_ratio:.3g}): tilt is unusable')
    scale = a / lamp.radius
    alpha = tilt_sign * np.arccos(axis_ratio)
    c, s = np.cos(theta), np.sin(theta)
    # Undo R2(gamma) then diag(1, cos alpha): what is left is R2(beta) applied to the marker's map direction.
    offset = (marker - (cx, cy)) / (scale * lamp.marker_distance)
    unrotated = np.array([c * offset[0] + s * offset[1], (-s * offset[0] + c * offset[1]) / axis_ratio])
    beta = np.arctan2(unrotated[1], unrotated[0]) - lamp.marker_angle
    map_to_camera = Rotation.from_euler('ZXZ', [theta, alpha, beta]).as_matrix()
    lamp_in_camera = np.array([cx, cy, 1.0]) / scale
    rotation = map_to_camera.T
    return Pose(rotation, lamp.position - rotation @ lamp_in_camera)


def _scored(pose: Pose, rim: np.ndarray, marker: np.ndarray, observation: LampObservation,
            lamp: Lamp, camera: CameraModel) -> PoseCandidate:
    """The pose with the chi-square of its full perspective reprojection of rim and marker.

    Residuals are computed in normalised coordinates and scaled by the focal
    length to pixels, where the sigmas are stated.
    """
    map_to_camera = pose.rotation.T
    centre = pose.map_to_camera(lamp.position)[0]
    # Lamp-plane coordinates (x, y, 1) -> homogeneous normalised image point.
    homography_inv = np.linalg.inv(np.column_stack([map_to_camera[:, 0], map_to_camera[:, 1], centre]))
    conic = homography_inv.T @ np.diag([1.0, 1.0, -lamp.radius ** 2]) @ homography_inv
    rim_residuals = geometric_distances(ellipse_from_conic(conic), rim) * camera.focal / observation.rim_sigma
    marker_camera = pose.map_to_camera(lamp.marker_position())[0]
    marker_residual = (marker_camera[:2] / marker_camera[2] - marker) * camera.focal / observation.marker_sigma
    cost = float(np.sum(rim_residuals ** 2) + np.sum(marker_residual ** 2))
    return PoseCandidate(pose, cost, residual_count=len(rim) + 2)
