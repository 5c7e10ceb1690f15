"""
Where the camera sits on the robot: the camera's pose turned into the robot base's pose.

ROS-free. The pipeline solves the camera optical frame (REP 103: z forward, x right,
y down) in the map; a localization stack such as robot_localization wants the pose
of the robot's ``base_frame``. With the camera's optical frame at (``rotation``,
``translation``) in the base frame, the base sits at

    R_base = R_camera @ rotation.T,   p_base = p_camera - R_base @ translation.

Both covariances follow ``Pose``'s convention (x, y, z in the map, then the rotation
vector about the fixed map X, Y, Z axes applied on the left; m^2, rad^2; row-major
when flattened). A rotation error d of the camera is the same rotation error of the
base (it is applied on the left, in the map), and it swings the base about the camera:
p_base moves by -(exp([d]x) - I) lever ~ lever x d, lever = R_base @ translation the
base-to-camera offset in the map. So the covariance goes through

    J = [[I, [lever]x], [0, I]],   C_base = J C_camera J^T,

the lever arm coupling rotation into position. J is exact to first order; the
second-order term |d|^2 |lever| / 2 is below 0.01 mm for a 1 m lever while rotations
are known to a few mrad, as they are whenever the position is known to a centimetre.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from vlp_ros.core.pose import Pose

# A quaternion parameter whose norm is further than this from 1 is refused rather than
# normalised: 1e-3 accepts values rounded to 3 decimals (0.707 for sqrt(1/2): norm 0.99985)
# and refuses a typo or a non-quaternion (an Euler triple with a 0 appended).
UNIT_QUATERNION_TOLERANCE = 1e-3
# Floors of the published variances (m^2 and rad^2): 0.1 mm and 0.01 mrad, far below what
# any fix achieves, so they only ever replace a zero or rounding-level variance, never an
# honest one. robot_localization would clamp a zero to 1e-9 and then trust it absolutely.
MIN_POSITION_VARIANCE = 1e-8
MIN_ROTATION_VARIANCE = 1e-10


@dataclass(frozen=True)
class Mounting:
    """
    The camera optical frame in the robot's base frame.

    ``rotation`` maps camera-frame vectors to base-frame vectors (its columns are the
    camera axes in the base); ``translation`` is the camera's optical centre in the base (m).
    """

    rotation: np.ndarray
    translation: np.ndarray

    @classmethod
    def from_quaternion(cls, xyzw: np.ndarray, translation: np.ndarray) -> Mounting:
        return cls(Rotation.from_quat(xyzw).as_matrix(), np.asarray(translation, dtype=float).reshape(3))

    def base_pose(self, camera: Pose) -> Pose:
        """Return the base frame's pose in the map, with the camera's covariance carried over (None stays None)."""
        rotation = camera.rotation @ self.rotation.T
        lever = rotation @ self.translation
        covariance = None
        if camera.covariance is not None:
            jacobian = lever_arm_jacobian(lever)
            covariance = jacobian @ np.asarray(camera.covariance, dtype=float) @ jacobian.T
            covariance = 0.5 * (covariance + covariance.T)
        return Pose(rotation, camera.position - lever, covariance)

    def camera_pose(self, base: Pose) -> Pose:
        """
        Return the camera optical frame's pose in the map for a base pose (no covariance).

        It is the inverse of base_pose.
        """
        return Pose(base.rotation @ self.rotation, base.position + base.rotation @ self.translation)

    def up_in_camera(self) -> np.ndarray:
        """Where base +z points in the camera optical frame: ``prior.up_in_camera`` for a level robot."""
        return self.rotation[2, :].copy()


def lever_arm_jacobian(lever: np.ndarray) -> np.ndarray:
    """d(base pose error) / d(camera pose error) for the base at map offset -``lever`` from the camera."""
    x, y, z = np.asarray(lever, dtype=float).reshape(3)
    jacobian = np.eye(6)
    jacobian[:3, 3:] = [[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]]
    return jacobian


def unit_quaternion_problem(xyzw: np.ndarray) -> str | None:
    """Why ``xyzw`` (x, y, z, w) is not a usable rotation, or None if it is one."""
    norm = float(np.linalg.norm(xyzw))
    if norm == 0.0:
        return 'the zero quaternion is no rotation'
    if abs(norm - 1.0) > UNIT_QUATERNION_TOLERANCE:
        return (f'must be a unit quaternion (x, y, z, w): its norm {norm:.6g} is further than '
                f'{UNIT_QUATERNION_TOLERANCE:g} from 1')
    return None


def publishable_covariance(covariance: np.ndarray | None) -> np.ndarray | None:
    """
    Return the symmetric 6x6 covariance with every variance at least its floor.

    None when there is none to publish (no covariance, or one that is not finite or has a
    variance below minus its floor: more negative than rounding makes it, so broken).
    """
    if covariance is None:
        return None
    covariance = np.asarray(covariance, dtype=float).reshape(6, 6)
    floors = np.array([MIN_POSITION_VARIANCE] * 3 + [MIN_ROTATION_VARIANCE] * 3)
    if not np.all(np.isfinite(covariance)) or np.any(np.diag(covariance) < -floors):
        return None
    # Raising diagonal entries keeps a positive semi-definite matrix positive semi-definite.
    raised = 0.5 * (covariance + covariance.T)
    raised[np.diag_indices(6)] = np.maximum(np.diag(raised), floors)
    return raised
