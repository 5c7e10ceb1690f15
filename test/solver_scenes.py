"""Synthetic cameras, lamps and observations for the pose solver tests."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from vlp_ros.core.camera import CameraModel
from vlp_ros.core.lamp_map import Lamp
from vlp_ros.core.observation import LampObservation
from vlp_ros.core.pose import Pose
from vlp_ros.sim.exact_observations import synthetic_observation
from vlp_ros.sim.scenarios import paper_camera


def camera_4k() -> CameraModel:
    """Nokia Lumia 1020 field of view (f = 7.25 mm, 1.12 um pixels at 7712 px) scaled to 3840x2160."""
    return paper_camera('4k')


def camera_wide() -> CameraModel:
    """1080p, 100 degrees horizontal, barrel distortion."""
    return CameraModel.from_horizontal_fov(1920, 1080, np.radians(100.0), D=np.array([-0.05, 0.0, 0.0, 0.0, 0.0]))


def small_lamp(position=(0.0, 0.0, 2.0), marker_angle: float = 0.3, lamp_id: int = 1) -> Lamp:
    return Lamp(f'lamp{lamp_id}', lamp_id, np.array(position, dtype=float), 0.055, marker_angle=marker_angle,
                marker_distance=0.045)


def grid_lamps(count: int) -> list[Lamp]:
    """15 cm lamps on a 1.2 m grid at 2.6 m, markers pointing different ways."""
    spots = [(0.0, 0.0), (1.2, 0.0), (0.0, 1.2), (1.2, 1.2), (-1.2, 0.0), (0.0, -1.2)]
    return [Lamp(f'grid{i}', 10 + i, np.array([x, y, 2.6]), 0.075, marker_angle=0.7 * i + 0.2,
                 marker_distance=0.065) for i, (x, y) in enumerate(spots[:count])]


def looking_up(position, tilt=(0.0, 0.0, 0.0)) -> Pose:
    """Camera at ``position`` looking up (optical axis = map +z), then rotated by ``tilt`` (map rotation vector)."""
    return Pose(Rotation.from_rotvec(tilt).as_matrix(), np.array(position, dtype=float))


def observe(lamp: Lamp, pose: Pose, camera: CameraModel, rim_count: int = 120, rim_sigma: float = 0.3,
            marker_sigma: float = 0.2, rng: np.random.Generator | None = None,
            with_marker: bool = True) -> LampObservation:
    """
    Return the lamp's exactly projected rim points and marker.

    Gaussian noise of the stated sigmas is added if ``rng`` is given.
    """
    return synthetic_observation(lamp, pose, camera, rim_count, rim_sigma, marker_sigma, rng, with_marker)


def measured_up(pose: Pose, sigma: float = 0.0, rng: np.random.Generator | None = None,
                error: np.ndarray = np.zeros(2)) -> np.ndarray:
    """
    Return ``pose``'s up direction in the camera, turned by ``error`` plus noise if ``rng``.

    ``error`` is in rad, about two fixed axes perpendicular to the up direction; the noise is
    N(0, sigma) about each of them.
    """
    up = pose.up_in_camera()
    first = np.cross(up, [1.0, 0.0, 0.0])
    first /= np.linalg.norm(first)
    turn = np.asarray(error, dtype=float) + (rng.normal(0.0, sigma, 2) if rng is not None else 0.0)
    return Rotation.from_rotvec(turn[0] * first + turn[1] * np.cross(up, first)).apply(up)
