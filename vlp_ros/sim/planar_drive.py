"""
A ground robot driving under sparse lamps: its camera's height and tilt held by the floor.

The base (base_link) drives at 0.8 m/s, weaving, on a floor at height 0; the camera sits
on it 20 cm ahead and 45 cm up, looking straight up with the top of its image toward the
front (``MOUNTING``): 1080p, 100 deg field of view. Lamps of 10-20 cm hang 2-3 m above
the floor on a jittered grid 4 m apart, so most frames show one lamp and some none. The
floor rocks the base about both horizontal axes (incommensurate sinusoids whose combined
tilt stays within ``max_tilt``) and bumps its height: a flat floor (0.3 deg, 2 mm) or a
rough one (1.5 deg, 7 mm). ``planar_parameters`` are the ``planar.*`` settings that describe
it: the standard deviations of that tilt and height.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from vlp_ros.core.camera import CameraModel
from vlp_ros.core.mounting import Mounting
from vlp_ros.core.pose import Pose
from vlp_ros.sim.scenarios import (BeaconDesign, DRIVE_SPEED, DRIVE_TURN_RATE, make_lamp, ROBOT_CAMERA_MOUNT,
                                   ROBOT_EXPOSURE, ROBOT_ROW_TIME, Scenario)
from vlp_ros.sim.sensor import SensorModel

MOUNTING = Mounting(ROBOT_CAMERA_MOUNT, np.array([0.2, 0.0, 0.45]))
LAMP_SPACING = 4.0
FRAME_RATE = 10.0


@dataclass(frozen=True)
class FloorKind:
    """How far a floor tilts (deg, the base's +z from vertical) and bumps the base's height (m), at most."""

    name: str
    max_tilt_deg: float
    max_bump: float

    @property
    def sigma_tilt(self) -> float:
        """Return the standard deviation (rad) of the tilt about each horizontal axis (sinusoids of max / sqrt 2)."""
        return float(np.radians(self.max_tilt_deg) / 2.0)

    @property
    def sigma_height(self) -> float:
        return float(self.max_bump / np.sqrt(2.0))


FLOORS = {'flat': FloorKind('flat', 0.3, 0.002), 'rough': FloorKind('rough', 1.5, 0.007)}


def planar_drive_scenario(floor: FloorKind, seed: int = 0, duration: float = 15.0, speed: float = DRIVE_SPEED,
                          turn_rate: float = DRIVE_TURN_RATE) -> tuple[Scenario, list[Pose]]:
    """Return the drive (the camera's poses) and the true base poses, frame by frame."""
    rng = np.random.default_rng(seed)
    camera = CameraModel.from_horizontal_fov(1920, 1080, np.radians(100.0), D=np.array([-0.05, 0.004, 0.0, 0.0, 0.0]))
    sensor = SensorModel(row_time=ROBOT_ROW_TIME, exposure=ROBOT_EXPOSURE, blur_sigma=0.8)
    beacon = BeaconDesign(16000.0, 8, 0.75)
    times = np.arange(0.0, duration, 1.0 / FRAME_RATE)
    path, heading = _weave(times, speed, turn_rate, rng)
    lamps = _sparse_lamps(path, beacon, rng)
    amplitude = np.radians(floor.max_tilt_deg) / np.sqrt(2.0)
    rates = rng.uniform(1.5, 3.5, 3)
    phases = rng.uniform(0.0, 2.0 * np.pi, 3)
    bases, cameras = [], []
    for t, position, psi in zip(times, path, heading):
        roll, pitch = amplitude * np.sin(rates[:2] * t + phases[:2])
        bump = floor.max_bump * np.sin(rates[2] * 1.7 * t + phases[2])
        # Tilted about the base's own axes after its heading: the floor under its wheels.
        rotation = Rotation.from_euler('ZYX', [psi, pitch, roll]).as_matrix()
        base = Pose(rotation, [position[0], position[1], bump])
        bases.append(base)
        cameras.append(MOUNTING.camera_pose(base))
    scenario = Scenario(f'planar_{floor.name}', camera, sensor, lamps, cameras,
                        [np.zeros(3) for _ in cameras], beacon, frame_rate=FRAME_RATE)
    return scenario, bases


def _weave(times: np.ndarray, speed: float, turn_rate: float,
           rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Return positions (N, 2) and headings of a base weaving with a heading rate up to ``turn_rate``."""
    omega = 2.0 * np.pi / 10.0
    amplitude = turn_rate / omega
    start_heading = rng.uniform(-0.3, 0.3)
    fine = np.linspace(0.0, times[-1], int(times[-1] * 200) + 1)
    heading = start_heading + amplitude * np.sin(omega * fine)
    step = fine[1] - fine[0]
    path = np.cumsum(speed * np.stack([np.cos(heading), np.sin(heading)], axis=1), axis=0) * step
    indices = np.round(times / step).astype(int)
    return path[indices] - path[0], heading[indices]


def _sparse_lamps(path: np.ndarray, beacon: BeaconDesign, rng: np.random.Generator) -> list:
    """Lamps on a grid ``LAMP_SPACING`` apart over the path, jittered 0.3 m; 5-10 cm radius, 2-3 m up."""
    low, high = path.min(axis=0) - LAMP_SPACING, path.max(axis=0) + LAMP_SPACING
    xs = np.arange(low[0], high[0], LAMP_SPACING)
    ys = np.arange(low[1], high[1], LAMP_SPACING)
    spots = [(x, y) for x in xs for y in ys]
    ids = rng.choice(np.arange(1, 256), len(spots), replace=False)
    lamps = []
    for k, ((x, y), lamp_id) in enumerate(zip(spots, ids)):
        position = [x + rng.uniform(-0.3, 0.3), y + rng.uniform(-0.3, 0.3), rng.uniform(2.0, 3.0)]
        lamps.append(make_lamp(f'lamp_{k}', int(lamp_id), position, float(rng.uniform(0.05, 0.10)),
                               float(rng.uniform(-np.pi, np.pi)), beacon, rng, peak_dn=190.0))
    return lamps


def mounting_parameters() -> dict[str, Any]:
    """``base_frame`` and ``camera_in_base`` of ``MOUNTING`` as nested ``ros__parameters``."""
    return {'base_frame': 'base_link',
            'camera_in_base': {'translation': [float(v) for v in MOUNTING.translation],
                               'rotation': [float(v) for v in Rotation.from_matrix(MOUNTING.rotation).as_quat()]}}


def planar_parameters(floor: FloorKind, sigma_tilt: float | None = None) -> dict[str, Any]:
    """``planar.*`` for ``floor`` (``sigma_tilt`` in rad, None: the floor's own) as nested ``ros__parameters``."""
    return {'planar': {'enabled': True, 'height': 0.0, 'sigma_height': floor.sigma_height,
                       'sigma_tilt': floor.sigma_tilt if sigma_tilt is None else float(sigma_tilt)}}
