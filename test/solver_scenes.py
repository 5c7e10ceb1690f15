"""Synthetic cameras, lamps and observations for the pose solver tests."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from vlp_ros.camera import CameraModel
from vlp_ros.ellipse import fit_ellipse
from vlp_ros.lamp_map import Lamp
from vlp_ros.observation import LampObservation
from vlp_ros.pose import Pose


def camera_4k() -> CameraModel:
    """Nokia Lumia 1020 field of view (f = 7.25 mm, 1.12 um pixels at 7712 px) scaled to 3840x2160."""
    f = 7.25e-3 / 1.12e-6 * 3840 / 7712
    return CameraModel(3840, 2160, [[f, 0, 1919.5], [0, f, 1079.5], [0, 0, 1]])


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
    """The lamp's exactly projected rim points and marker, plus Gaussian noise of the stated sigmas if ``rng``."""
    rim = camera.project(pose.map_to_camera(lamp.rim_points(rim_count)))
    marker = camera.project(pose.map_to_camera(lamp.marker_position()))[0]
    if rng is not None:
        rim = rim + rng.normal(0.0, rim_sigma, rim.shape)
        marker = marker + rng.normal(0.0, marker_sigma, 2)
    assert np.all((rim >= 0) & (rim < [camera.width, camera.height])), 'lamp leaves the image'
    x0, y0 = np.floor(rim.min(axis=0)).astype(int)
    x1, y1 = np.ceil(rim.max(axis=0)).astype(int) + 1
    return LampObservation(ellipse=fit_ellipse(rim), rim_points=rim, rim_sigma=rim_sigma,
                           marker=marker if with_marker else None, marker_sigma=marker_sigma,
                           bbox=(int(x0), int(y0), int(x1), int(y1)),
                           disc_mask=np.ones((y1 - y0, x1 - x0), dtype=bool))
