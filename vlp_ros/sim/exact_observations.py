"""Exact lamp observations from a known pose, for solver tests and benchmarks (no image)."""
from __future__ import annotations

import numpy as np

from vlp_ros.core.camera import CameraModel
from vlp_ros.core.ellipse import fit_ellipse
from vlp_ros.core.lamp_map import Lamp
from vlp_ros.core.observation import LampObservation
from vlp_ros.core.pose import Pose


def synthetic_observation(lamp: Lamp, pose: Pose, camera: CameraModel, rim_count: int = 120,
                          rim_sigma: float = 0.3, marker_sigma: float = 0.2,
                          rng: np.random.Generator | None = None, with_marker: bool = True) -> LampObservation:
    """
    Return an observation of ``lamp`` from ``pose`` computed by projection, not from an image.

    ``rim_count`` projected rim points and the projected marker (lens distortion included),
    plus Gaussian noise of the stated sigmas per axis when ``rng`` is given.
    """
    if not np.all(pose.map_to_camera(lamp.rim_points(8))[:, 2] > 0.0):
        raise ValueError(f'lamp {lamp.name!r} is not in front of the camera')
    rim = camera.project(pose.map_to_camera(lamp.rim_points(rim_count)))
    marker = camera.project(pose.map_to_camera(lamp.marker_position()))[0]
    if rng is not None:
        rim = rim + rng.normal(0.0, rim_sigma, rim.shape)
        marker = marker + rng.normal(0.0, marker_sigma, 2)
    if not np.all((rim >= 0.0) & (rim < [camera.width, camera.height])):
        raise ValueError(f'lamp {lamp.name!r} is not entirely inside the image')
    x0, y0 = np.floor(rim.min(axis=0)).astype(int)
    x1, y1 = np.ceil(rim.max(axis=0)).astype(int) + 1
    return LampObservation(ellipse=fit_ellipse(rim), rim_points=rim, rim_sigma=rim_sigma,
                           marker=marker if with_marker else None, marker_sigma=marker_sigma,
                           bbox=(int(x0), int(y0), int(x1), int(y1)),
                           disc_mask=np.ones((y1 - y0, x1 - x0), dtype=bool))
