"""
The seed paper's single-lamp pose solver: weak perspective of one circle and its marker.

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

Candidates (Appendix B as reconstructed). ``cos(alpha) = -b / a`` would put the
camera above the lamp's lit face and is excluded; the marker settles the
half-turn ambiguity of the ellipse axis. That leaves the two signs of
``alpha``: they share M, so they predict the same weak-perspective image of
every point of the lamp plane, marker included (the reflection ambiguity of
weak perspective), and no constraint on the paper's quantities can pick one.
Both are returned, sorted by ``cost``, the chi-square of their full
perspective reprojection, so the pipeline's disambiguation (cost gap, up
direction, continuity) treats this solver like any other. Near the optical
axis the two costs differ by less than the weak-perspective misfit itself, so
the order there is a coin flip: only an up direction or continuity can decide.
The poses are exactly the paper's (unrefined); only their order uses
perspective.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from vlp_ros.core.camera import CameraModel
from vlp_ros.core.ellipse import fit_ellipse
from vlp_ros.core.lamp_map import Lamp
from vlp_ros.core.observation import LampObservation
from vlp_ros.core.pose import Pose
from vlp_ros.solvers.candidates import PoseCandidate
from vlp_ros.solvers.measurement import LampMeasurement

# Below this b / a the lamp is seen nearly edge-on and 1 / cos(alpha) amplifies
# any marker error without bound.
MIN_AXIS_RATIO = 0.05


def solve_lamp_paper(observation: LampObservation, lamp: Lamp,
                     camera: CameraModel) -> list[PoseCandidate]:
    """
    Return the paper's two weak-perspective poses of the camera, the better-fitting one first.

    ``cost`` is the chi-square of ``LampMeasurement`` (full perspective, pixels),
    as for every solver; ``covariance`` is None: the paper gives none.
    """
    if observation.marker is None:
        raise ValueError("the paper's solver needs the marker to fix the rotation about the lamp axis")
    if not lamp.marker_distance > 0.0:
        raise ValueError(f'lamp {lamp.name!r} has its marker at the centre: no azimuth to read')
    measurement = LampMeasurement.from_observation(observation, lamp, camera)
    ellipse = fit_ellipse(measurement.rim_rays[:, :2])
    marker = camera.normalize(np.asarray(observation.marker, dtype=float))[0]
    candidates = []
    for tilt_sign in (1.0, -1.0):
        pose = _weak_perspective_pose(ellipse, marker, lamp, tilt_sign)
        residuals, _ = measurement.linearize(pose.rotation, pose.position)
        candidates.append(PoseCandidate(pose, float(residuals @ residuals), measurement.residual_count))
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
