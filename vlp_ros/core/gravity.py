"""Where "up" points in the camera frame, from accelerometer samples near an image's stamp."""
from __future__ import annotations

from collections import deque

import numpy as np
from scipy.spatial.transform import Rotation

STANDARD_GRAVITY = 9.80665
# A specific force this far (m/s^2) from g means the camera is accelerating (or the IMU is
# broken): the sample no longer points up well enough to be trusted as a measurement.
MAX_GRAVITY_DEVIATION = 1.0


class GravityBuffer:
    """
    Recent accelerometer samples turned into the camera optical frame.

    An accelerometer at rest measures the specific force, +g along map up, so the
    normalised sample is the up direction. ``imu_to_camera`` is the quaternion
    (x, y, z, w) turning IMU-frame vectors into the camera optical frame.
    """

    def __init__(self, imu_to_camera: np.ndarray, max_age: float, capacity: int = 400) -> None:
        self._rotation = Rotation.from_quat(imu_to_camera).as_matrix()
        self._max_age_ns = max_age * 1e9
        self._samples: deque[tuple[int, np.ndarray]] = deque(maxlen=capacity)

    def add(self, stamp_ns: int, specific_force_imu: np.ndarray) -> None:
        self._samples.append((stamp_ns, self._rotation @ np.asarray(specific_force_imu, dtype=float)))

    @property
    def newest_stamp_ns(self) -> int | None:
        return self._samples[-1][0] if self._samples else None

    def up_at(self, stamp_ns: int) -> np.ndarray | None:
        """Return unit up vector (camera frame) from the sample nearest ``stamp_ns``; None if none is recent enough."""
        samples = list(self._samples)  # a snapshot: another thread may be adding samples
        if not samples:
            return None
        sample_stamp, force = min(samples, key=lambda sample: abs(sample[0] - stamp_ns))
        norm = np.linalg.norm(force)
        if abs(sample_stamp - stamp_ns) > self._max_age_ns or abs(norm - STANDARD_GRAVITY) > MAX_GRAVITY_DEVIATION:
            return None
        return force / norm
