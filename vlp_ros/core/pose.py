"""Camera pose in the map frame and the conventions of its covariance."""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation


@dataclass
class Pose:
    """
    The camera optical frame (REP 103: z forward, x right, y down) in the map frame.

    ``rotation`` maps camera-frame vectors to map-frame vectors (its columns are
    the camera axes in the map); ``position`` is the camera centre in the map.
    ``covariance`` is 6x6 over (x, y, z, rotation about map x, y, z) as in
    geometry_msgs/PoseWithCovariance; the rotation part is the covariance of the
    small rotation vector ``d`` in ``rotation = expm([d]x) @ rotation_true``.
    """

    rotation: np.ndarray
    position: np.ndarray
    covariance: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.rotation = np.asarray(self.rotation, dtype=float).reshape(3, 3)
        self.position = np.asarray(self.position, dtype=float).reshape(3)

    @classmethod
    def from_quaternion(cls, xyzw: np.ndarray, position: np.ndarray) -> Pose:
        return cls(Rotation.from_quat(xyzw).as_matrix(), position)

    def quaternion_xyzw(self) -> np.ndarray:
        return Rotation.from_matrix(self.rotation).as_quat()

    def map_to_camera(self, points_map: np.ndarray) -> np.ndarray:
        """Map-frame points (N, 3) expressed in the camera optical frame."""
        return (np.asarray(points_map, dtype=float).reshape(-1, 3) - self.position) @ self.rotation

    def up_in_camera(self) -> np.ndarray:
        """Where map +z points, as a unit vector in the camera optical frame."""
        return self.rotation[2, :].copy()

    def position_error(self, other: Pose) -> float:
        return float(np.linalg.norm(self.position - other.position))

    # OpenCV's Rodrigues below: scipy's Rotation costs ~25x more per call, and the solvers
    # compare every start and candidate this way.
    def rotation_error(self, other: Pose) -> float:
        """Angle (rad) of the rotation between the two orientations."""
        rotation_vector, _ = cv2.Rodrigues(self.rotation.T @ other.rotation)
        return float(np.linalg.norm(rotation_vector))

    def error_vector(self, truth: Pose) -> np.ndarray:
        """6-vector (position error, map-frame rotation vector) in the covariance's convention."""
        drot, _ = cv2.Rodrigues(self.rotation @ truth.rotation.T)
        return np.concatenate([self.position - truth.position, drot.ravel()])
