"""Accelerometer readings of a camera-mounted IMU, in the camera optical frame."""
from __future__ import annotations

import numpy as np

from vlp_ros.core.gravity import STANDARD_GRAVITY
from vlp_ros.core.pose import Pose


def specific_force(pose: Pose, acceleration: np.ndarray | None = None, noise_std: float = 0.0,
                   rng: np.random.Generator | None = None) -> np.ndarray:
    """
    Return what an accelerometer in the camera optical frame reads (m/s^2).

    Specific force is acceleration minus gravity, so at rest it is +g along map up.
    ``acceleration`` (map frame) is the camera's own; ``noise_std`` adds white
    noise per axis (needs ``rng``).
    """
    accel = np.zeros(3) if acceleration is None else np.asarray(acceleration, dtype=float).reshape(3)
    force = pose.rotation.T @ (accel + np.array([0.0, 0.0, STANDARD_GRAVITY]))
    if noise_std < 0.0:
        raise ValueError(f'noise_std must not be negative, got {noise_std}')
    if noise_std > 0.0:
        if rng is None:
            raise ValueError('IMU noise needs a random generator')
        force = force + rng.normal(0.0, noise_std, 3)
    return force
