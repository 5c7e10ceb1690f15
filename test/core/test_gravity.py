"""Up direction from accelerometer samples."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from vlp_ros.core.gravity import GravityBuffer


def test_nearest_recent_sample_gives_unit_up_in_camera_frame() -> None:
    imu_to_camera = Rotation.from_euler('x', 90, degrees=True)
    buffer = GravityBuffer(imu_to_camera.as_quat(), max_age=0.05)
    buffer.add(1_000_000_000, [0.0, 0.0, 9.81])
    buffer.add(1_040_000_000, [0.0, 9.81, 0.0])
    # Unit vectors: a nanoradian.
    np.testing.assert_allclose(buffer.up_at(1_005_000_000), imu_to_camera.apply([0, 0, 1]), atol=1e-9)
    np.testing.assert_allclose(buffer.up_at(1_038_000_000), imu_to_camera.apply([0, 1, 0]), atol=1e-9)
    assert buffer.newest_stamp_ns == 1_040_000_000


def test_stale_or_accelerating_samples_give_nothing() -> None:
    buffer = GravityBuffer(np.array([0.0, 0.0, 0.0, 1.0]), max_age=0.05)
    assert buffer.up_at(0) is None
    buffer.add(0, [0.0, 0.0, 9.81])
    assert buffer.up_at(100_000_000) is None
    buffer.add(200_000_000, [0.0, 0.1, 0.2])  # free fall
    assert buffer.up_at(200_000_000) is None
    buffer.add(300_000_000, [0.0, 3.0, 12.0])  # accelerating hard
    assert buffer.up_at(300_000_000) is None
