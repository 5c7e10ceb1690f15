"""
Simulated recordings: lamps, camera, sensor, the camera's path, and the matching locator parameters.

``paper_scenario`` is the seed paper's experiment (one lamp above a 3 m x 3 m
grid, hand-held phone postures); ``robot_scenario`` a robot with an upward
wide-angle camera driving under a row of ceiling lamps.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from vlp_ros.beacon.encoding import packet_length, packet_waveform, tone_waveform
from vlp_ros.core.camera import CameraModel
from vlp_ros.core.gravity import STANDARD_GRAVITY
from vlp_ros.core.lamp_map import Lamp
from vlp_ros.core.pose import Pose
from vlp_ros.sim.render import MARKER_RADIUS_FRACTION, render_frame, RenderedFrame, SimLamp
from vlp_ros.sim.sensor import SensorModel

# Nokia Lumia 1020: f = 7.25 mm, 1.12 um pixels, 7712 px wide; scaled to the output width.
LUMIA_FOCAL_PX_FULL = 7.25e-3 / 1.12e-6
LUMIA_FULL_WIDTH = 7712
PAPER_CAMERAS = {'4k': (3840, 2160), '1080p': (1920, 1080)}
FRAME_RATE = 30.0
# The paper scenario's beacon is sized for the lamp at this distance.
PAPER_DESIGN_DISTANCE = 2.0
# The marker disc sits just inside the rim: this much of the radius stays between them.
MARKER_RIM_GAP_FRACTION = 0.03
# Aimed postures (the paper's photos): how far the optical axis strays from the lamp, and
# how far the hand turns the phone about it.
AIMED_OFF_AXIS_DEG = 5.5
AIMED_TWIST_DEG = 30.0
# Camera axes in the robot base frame (x forward, y left, z up): image x to the left, looking up.
ROBOT_CAMERA_MOUNT = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class BeaconDesign:
    """Beacon settings shared by all lamps of a scenario (tone mode: chip rate and ID bits unused)."""

    chip_rate: float
    id_bits: int
    depth: float
    mode: str = 'packet'


@dataclass
class Scenario:
    """
    Everything needed to render a recording and to configure the locator for it.

    ``accelerations`` (map frame, m/s^2) are the camera's own, per frame, for the
    IMU. ``prior_up`` is where map up points in the camera when the mount makes
    that a valid static prior (None otherwise). ``independent_frames``: frames are
    separate photos, so no pose vouches for the next.

    Looks (``vlp_ros.sim.looks``): ``clutter`` are unmodulated lamps that are not in the
    map; ``jpeg_quality`` sends the images as JPEG (``image_transport: compressed``);
    the locator is given the row time ``sensor.row_time / (1 + row_time_error)``
    (the nominal one) while the sensor's true row time is ``sensor.row_time``.
    """

    name: str
    camera: CameraModel
    sensor: SensorModel
    lamps: list[SimLamp]
    poses: list[Pose]
    accelerations: list[np.ndarray]
    beacon: BeaconDesign
    frame_rate: float = FRAME_RATE
    prior_up: np.ndarray | None = None
    prior_tolerance: float = 0.35
    prior_sigma: float = 0.0
    imu_noise: float = 0.02
    independent_frames: bool = False
    clutter: list[SimLamp] = field(default_factory=list)
    jpeg_quality: int | None = None
    row_time_error: float = 0.0

    def frame_times(self) -> np.ndarray:
        """When each frame's row 0 starts exposing (s since the recording start)."""
        return np.arange(len(self.poses)) / self.frame_rate

    def truncated(self, frames: int) -> Scenario:
        if frames < 1:
            raise ValueError(f'frames must be at least 1, got {frames}')
        return replace(self, poses=self.poses[:frames], accelerations=self.accelerations[:frames])

    @property
    def nominal_row_time(self) -> float:
        """Return the row time the locator is told (the sensor's true one differs by ``row_time_error``)."""
        return self.sensor.row_time / (1.0 + self.row_time_error)

    def render(self, index: int, rng: np.random.Generator | None) -> RenderedFrame:
        """Frame ``index`` as the camera records it: the map's lamps and the clutter lamps."""
        return render_frame(self.camera, self.poses[index], self.lamps + self.clutter, self.sensor,
                            float(self.frame_times()[index]), rng)

    def mapped_truths(self, frame: RenderedFrame) -> list:
        """Return the ground truth of the map's lamps in ``frame`` (without the clutter lamps)."""
        ids = {sim.lamp.id for sim in self.lamps}
        return [t for t in frame.lamps if t.lamp_id in ids]

    def locator_parameters(self, imu: bool) -> dict[str, Any]:
        """Return the locator's ``ros__parameters`` (nested as in a params file) for this scenario."""
        leds: dict[str, Any] = {'names': [s.lamp.name for s in self.lamps]}
        for sim in self.lamps:
            lamp = sim.lamp
            leds[lamp.name] = {'id': int(lamp.id), 'position': [round(float(v), 9) for v in lamp.position],
                               'radius': float(lamp.radius), 'marker_angle': float(lamp.marker_angle),
                               'marker_distance': float(lamp.marker_distance)}
            if lamp.frequency is not None:
                leds[lamp.name]['frequency'] = float(lamp.frequency)
        beacon: dict[str, Any] = {'mode': self.beacon.mode}
        if self.beacon.mode == 'packet':
            beacon.update(chip_rate=float(self.beacon.chip_rate), id_bits=int(self.beacon.id_bits))
        beacon.update(row_time=float(self.nominal_row_time), exposure=float(self.sensor.exposure))
        params: dict[str, Any] = {'map_frame': 'map', 'leds': leds, 'beacon': beacon}
        if self.jpeg_quality is not None:
            params['image_transport'] = 'compressed'
        if self.prior_up is not None:
            params['prior'] = {'up_in_camera': [float(v) for v in self.prior_up],
                               'tolerance': float(self.prior_tolerance), 'sigma': float(self.prior_sigma)}
        if imu:
            # The simulated IMU samples once per frame at the image's stamp.
            # Its noise and the camera's own acceleration (RMS magnitude, conservatively all of it
            # across the up direction), over g, are how far the up direction it gives may stray.
            rms_acceleration = np.sqrt(np.mean(np.sum(np.square(self.accelerations), axis=1)))
            sigma = np.hypot(self.imu_noise, rms_acceleration) / STANDARD_GRAVITY
            params['imu'] = {'enabled': True, 'rotation': [0.0, 0.0, 0.0, 1.0], 'max_age': 0.5 / self.frame_rate,
                             'sigma': float(sigma)}
        if self.independent_frames:
            params['continuity'] = {'max_age': 0.0}
        return params


def design_beacon(span_rows: float, row_time: float, max_id: int, depth: float,
                  min_packets: float = 1.3, min_rows_per_chip: float = 4.0, max_bits: int = 8) -> BeaconDesign:
    """
    Return the beacon design with the most ID bits that a lamp spanning ``span_rows`` rows can carry.

    Most ID bits (<= ``max_bits``, enough for ``max_id``) and the chip rate at which a lamp spanning
    ``span_rows`` rows holds ``min_packets`` packets, each chip at least ``min_rows_per_chip`` rows;
    ValueError when no number of bits allows that.
    """
    for bits in range(max_bits, max(int(max_id).bit_length(), 1) - 1, -1):
        rows_per_chip = span_rows / (min_packets * packet_length(bits))
        if rows_per_chip >= min_rows_per_chip:
            return BeaconDesign(float(round(1.0 / (rows_per_chip * row_time))), bits, depth)
    raise ValueError(f'a lamp spanning {span_rows:.0f} rows cannot hold {min_packets} packets of id {max_id} '
                     f'at {min_rows_per_chip} rows per chip')


def paper_camera(kind: str) -> CameraModel:
    """Return the Lumia 1020's field of view at 4K or 1080p output, principal point at the centre."""
    if kind not in PAPER_CAMERAS:
        raise ValueError(f'camera must be one of {", ".join(PAPER_CAMERAS)}, got {kind!r}')
    width, height = PAPER_CAMERAS[kind]
    f = LUMIA_FOCAL_PX_FULL * width / LUMIA_FULL_WIDTH
    return CameraModel(width, height, [[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])


def make_lamp(name: str, lamp_id: int, position: np.ndarray, radius: float, marker_angle: float,
              beacon: BeaconDesign, rng: np.random.Generator, peak_dn: float) -> SimLamp:
    """Return a lamp with its marker just inside the rim and an unsynchronised beacon clock."""
    marker_distance = radius * (1.0 - MARKER_RADIUS_FRACTION - MARKER_RIM_GAP_FRACTION)
    lamp = Lamp(name, lamp_id, position, radius, marker_angle=marker_angle, marker_distance=marker_distance)
    period = packet_length(beacon.id_bits) / beacon.chip_rate
    waveform = packet_waveform(lamp_id, beacon.chip_rate, beacon.depth, beacon.id_bits,
                               offset=float(rng.uniform(0.0, period)))
    return SimLamp(lamp, waveform, peak_dn=peak_dn)


def paper_scenario(camera_kind: str = '4k', height: float = 2.0, points: int = 7, postures: int = 3,
                   seed: int = 0, depth: float = 0.75, max_tilt_deg: float = 30.0,
                   area: float = 3.0, bayer: str | None = None, posture: str = 'anywhere') -> Scenario:
    """
    One 11 cm lamp ``height`` m above a ``points`` x ``points`` grid over ``area`` x ``area`` m.

    At each grid point the phone takes ``postures`` photos. ``posture='anywhere'``:
    optical axis uniformly random within ``max_tilt_deg`` of straight up (widened to
    reach the lamp at grid points from where it is farther off), random roll about
    the axis, kept only if the whole lamp is at least 20 px inside the image.
    ``posture='aimed'`` (the paper's photos): the phone points at the lamp
    (``_aimed_pose``). The beacon is designed for >= 1.3 packets at >= 4 rows per
    chip with the lamp 2 m away.
    """
    if not height > 0.0:
        raise ValueError(f'height must be positive, got {height}')
    if points < 1 or postures < 1:
        raise ValueError('points and postures must be at least 1')
    if posture not in ('anywhere', 'aimed'):
        raise ValueError(f"posture must be 'anywhere' or 'aimed', got {posture!r}")
    rng = np.random.default_rng(seed)
    camera = paper_camera(camera_kind)
    sensor = SensorModel(row_time=1.0 / (FRAME_RATE * camera.height), exposure=50e-6, bayer=bayer)
    radius, lamp_id = 0.055, 11
    beacon = design_beacon(camera.focal * 2.0 * radius / PAPER_DESIGN_DISTANCE, sensor.row_time, lamp_id, depth)
    sim = make_lamp('lamp', lamp_id, [0.0, 0.0, height], radius, 0.6, beacon, rng, peak_dn=210.0)
    grid = np.linspace(-area / 2, area / 2, points) if points > 1 else np.zeros(1)
    poses = []
    for x in grid:
        for y in grid:
            position = np.array([x, y, 0.0])
            poses.extend(_aimed_pose(position, sim.lamp, rng) if posture == 'aimed'
                         else _hand_held_pose(camera, position, sim.lamp, max_tilt_deg, rng) for _ in range(postures))
    return Scenario(f'paper_{camera_kind}', camera, sensor, [sim], poses, [np.zeros(3)] * len(poses), beacon,
                    independent_frames=True)


def _hand_held_pose(camera: CameraModel, position: np.ndarray, lamp: Lamp, max_tilt_deg: float,
                    rng: np.random.Generator, margin: float = 20.0) -> Pose:
    to_lamp = lamp.position - position
    lamp_zenith = np.degrees(np.arccos(to_lamp[2] / np.linalg.norm(to_lamp)))
    half_fov = np.degrees(np.arctan(0.5 * min(camera.width, camera.height) / camera.focal))
    limit = np.radians(max(max_tilt_deg, lamp_zenith + half_fov))
    for _ in range(10000):
        tilt = np.arccos(rng.uniform(np.cos(limit), 1.0))
        rotation = Rotation.from_euler('zyz', [rng.uniform(0, 2 * np.pi), tilt, rng.uniform(0, 2 * np.pi)])
        pose = Pose(rotation.as_matrix(), position)
        rim = pose.map_to_camera(lamp.rim_points(32))
        if np.all(rim[:, 2] > 0.0):
            pixels = camera.project(rim)
            if (np.all(pixels >= margin) and np.all(pixels[:, 0] <= camera.width - 1 - margin)
                    and np.all(pixels[:, 1] <= camera.height - 1 - margin)):
                return pose
    raise ValueError(f'no posture at {position[:2]} sees the whole lamp')


def _aimed_pose(position: np.ndarray, lamp: Lamp, rng: np.random.Generator,
                off_axis_deg: float = AIMED_OFF_AXIS_DEG, twist_deg: float = AIMED_TWIST_DEG) -> Pose:
    """
    Return the phone pointed at the lamp by hand.

    Its optical axis uniformly within ``off_axis_deg`` of the lamp's centre, the
    phone held upright (portrait: the sensor's long side, image x, along the phone)
    with its top, the image's left edge, toward the lamp (any way round below it),
    twisted about the axis by up to ``twist_deg``. The lamp stays near the image
    centre, so the whole of it is in view with any camera of the paper's field of
    view.
    """
    to_lamp = lamp.position - position
    axis = to_lamp / np.linalg.norm(to_lamp)
    horizontal = np.hypot(to_lamp[0], to_lamp[1])
    heading = np.arctan2(to_lamp[1], to_lamp[0]) if horizontal > 1e-3 else rng.uniform(-np.pi, np.pi)
    toward = np.array([np.cos(heading), np.sin(heading), 0.0])
    left = toward - (toward @ axis) * axis
    right = -left / np.linalg.norm(left)
    aimed = np.column_stack([right, np.cross(axis, right), axis])
    off_axis = np.arccos(rng.uniform(np.cos(np.radians(off_axis_deg)), 1.0))
    off_direction = rng.uniform(-np.pi, np.pi)
    hand = Rotation.from_euler('z', rng.uniform(-1.0, 1.0) * np.radians(twist_deg)) * Rotation.from_rotvec(
        off_axis * np.array([np.cos(off_direction), np.sin(off_direction), 0.0]))
    return Pose(aimed @ hand.as_matrix(), position)


def robot_scenario(lamp_count: int = 7, spacing: float = 1.2, height: float = 2.15, camera_height: float = 0.45,
                   speed: float = 0.4, seed: int = 0, depth: float = 0.75, bayer: str | None = None) -> Scenario:
    """
    Return a robot driving under a row of ``lamp_count`` 15 cm lamps ``spacing`` m apart.

    Its 100 deg HFOV 1080p camera is ``camera_height`` m up, looking up; the lamps hang ``height``
    m above the camera.

    The robot sways sideways along the row and its chassis rocks by < 1 deg, so the
    static prior (map up along camera +z) holds within a small tolerance.
    """
    if lamp_count < 1 or not spacing > 0.0 or not height > 0.0 or not speed > 0.0:
        raise ValueError('lamp_count, spacing, height and speed must be positive')
    rng = np.random.default_rng(seed)
    camera = CameraModel.from_horizontal_fov(1920, 1080, np.radians(100.0), D=np.array([-0.05, 0.004, 0.0, 0.0, 0.0]))
    sensor = SensorModel(row_time=1.0 / (FRAME_RATE * camera.height), exposure=20e-6, blur_sigma=0.8, bayer=bayer)
    radius = 0.075
    beacon = design_beacon(camera.focal * 2.0 * radius / height, sensor.row_time, lamp_count, depth,
                           min_rows_per_chip=3.0)
    lamps = [make_lamp(f'lamp_{k}', k, [(k - 1) * spacing, 0.0, camera_height + height], radius,
                       float(rng.uniform(-np.pi, np.pi)), beacon, rng, peak_dn=190.0)
             for k in range(1, lamp_count + 1)]
    start, end = -spacing, lamp_count * spacing
    times = np.arange(0.0, (end - start) / speed, 1.0 / FRAME_RATE)
    sway, sway_period = 0.25, 8.0
    omega = 2.0 * np.pi / sway_period
    phases = rng.uniform(0.0, 2.0 * np.pi, 2)
    poses, accelerations = [], []
    for t in times:
        position = np.array([start + speed * t, sway * np.sin(omega * t), camera_height])
        heading = np.arctan2(sway * omega * np.cos(omega * t), speed)
        rock = np.radians(0.7) * np.sin(np.array([2.1, 2.9]) * t + phases)
        rotation = Rotation.from_euler('zyx', [heading, rock[0], rock[1]]).as_matrix() @ ROBOT_CAMERA_MOUNT
        poses.append(Pose(rotation, position))
        accelerations.append(np.array([0.0, -sway * omega ** 2 * np.sin(omega * t), 0.0]))
    return Scenario('robot', camera, sensor, lamps, poses, accelerations, beacon,
                    prior_up=np.array([0.0, 0.0, 1.0]), prior_tolerance=0.1, prior_sigma=np.radians(0.7))


# The moving robot and the tone lamps' robot: a 1080p camera whose lamps
# are ~77 px across (the independent renderer's f 1100 px and lens), rows 15 us apart.
ROBOT_1080P_FOCAL = 1100.0
ROBOT_1080P_DISTORTION = (-0.08, 0.03, 0.0005, -0.0003, 0.0)
ROBOT_ROW_TIME = 15e-6
ROBOT_EXPOSURE = 20e-6
# The drive: 0.8 m/s, weaving with a heading rate up to 0.3 rad/s.
DRIVE_SPEED = 0.8
DRIVE_TURN_RATE = 0.3
ROBOT_LAMP_RADIUS = 0.075
ROBOT_CAMERA_HEIGHT = 0.45


def robot_1080p_camera() -> CameraModel:
    K = [[ROBOT_1080P_FOCAL, 0.0, 964.0], [0.0, ROBOT_1080P_FOCAL, 537.0], [0.0, 0.0, 1.0]]
    return CameraModel(1920, 1080, K, np.array(ROBOT_1080P_DISTORTION))


def robot_drive_scenario(seed: int = 0, duration: float = 12.0, speed: float = DRIVE_SPEED,
                         turn_rate: float = DRIVE_TURN_RATE,
                         spacing: float = 2.4, height: float = 2.15, depth: float = 0.75,
                         bayer: str | None = None) -> Scenario:
    """
    Return a robot driving ``speed`` m/s and weaving under two rows of four packet lamps ``spacing`` m apart.

    Its heading rate goes up to ``turn_rate`` rad/s; 10 frames/s.

    Packet IDs at 16 kchip/s, 8 bits: with 15 us rows a chip is 4 rows and a 15 cm lamp
    (~77 px across at 2.15 m) holds 0.8 of a packet. Between the rows of lamps the
    image often holds no lamp fully: the tracker must pick the lamps up again.
    """
    if not duration > 0.0 or not speed > 0.0 or not spacing > 0.0 or not height > 0.0:
        raise ValueError('duration, speed, spacing and height must be positive')
    rng = np.random.default_rng(seed)
    camera = robot_1080p_camera()
    sensor = SensorModel(row_time=ROBOT_ROW_TIME, exposure=ROBOT_EXPOSURE, blur_sigma=0.8, bayer=bayer)
    beacon = BeaconDesign(16000.0, 8, depth)
    ids = rng.choice(np.arange(1, 256), 8, replace=False)
    lamps = [make_lamp(f'lamp_{k}', int(lamp_id), [spacing * (k // 2 - 1), spacing * ((k % 2) - 0.5),
                                                   ROBOT_CAMERA_HEIGHT + height],
                       ROBOT_LAMP_RADIUS, float(rng.uniform(-np.pi, np.pi)), beacon, rng, peak_dn=190.0)
             for k, lamp_id in enumerate(ids)]
    frame_rate = 10.0
    times = np.arange(0.0, duration, 1.0 / frame_rate)
    # Heading psi(t) = A sin(w t) with A w = turn_rate: the robot weaves across the gap between the rows.
    omega = 2.0 * np.pi / 12.0
    amplitude = turn_rate / omega
    fine = np.linspace(0.0, duration, int(duration * 200) + 1)
    heading = amplitude * np.sin(omega * fine)
    step = fine[1] - fine[0]
    path = np.cumsum(speed * np.stack([np.cos(heading), np.sin(heading)], axis=1), axis=0) * step
    path += np.array([-1.5 * spacing, -0.4]) - path[0]
    phases = rng.uniform(0.0, 2.0 * np.pi, 2)
    poses, accelerations = [], []
    for t in times:
        k = int(round(t / step))
        psi, rate = heading[k], amplitude * omega * np.cos(omega * t)
        rock = np.radians(0.7) * np.sin(np.array([2.1, 2.9]) * t + phases)
        rotation = Rotation.from_euler('zyx', [psi, rock[0], rock[1]]).as_matrix() @ ROBOT_CAMERA_MOUNT
        poses.append(Pose(rotation, [path[k, 0], path[k, 1], ROBOT_CAMERA_HEIGHT]))
        # Centripetal: speed x heading rate, to the left of the heading.
        accelerations.append(speed * rate * np.array([-np.sin(psi), np.cos(psi), 0.0]))
    return Scenario('robot_drive', camera, sensor, lamps, poses, accelerations, beacon, frame_rate=frame_rate,
                    prior_up=np.array([0.0, 0.0, 1.0]), prior_tolerance=0.1, prior_sigma=np.radians(0.7))


TONE_FREQUENCIES = tuple(2000.0 + 300.0 * k for k in range(12))


def robot_tone_scenario(seed: int = 0, frames: int = 24, interval: float = 2.0, spacing: float = 1.2,
                        height: float = 2.15, depth: float = 0.75, bayer: str | None = None) -> Scenario:
    """
    Robot stills ``interval`` s apart under a 4 x 3 grid of tone lamps 2000-5300 Hz (300 Hz apart).

    15 cm lamps 2.15 m above the 1080p camera span ~77 rows: 2.3 periods of the 2000 Hz
    lamp and 6 of the 5300 Hz one at 15 us a row. The camera is anywhere under the grid,
    any heading, its chassis rocking by < 1 deg (static prior).
    """
    if frames < 1 or not interval > 0.0 or not spacing > 0.0 or not height > 0.0:
        raise ValueError('frames, interval, spacing and height must be positive')
    rng = np.random.default_rng(seed)
    camera = robot_1080p_camera()
    sensor = SensorModel(row_time=ROBOT_ROW_TIME, exposure=ROBOT_EXPOSURE, blur_sigma=0.8, bayer=bayer)
    beacon = BeaconDesign(0.0, 0, depth, mode='tone')
    lamps = []
    for k, frequency in enumerate(TONE_FREQUENCIES):
        position = [spacing * (k // 3 - 1), spacing * (k % 3 - 1), ROBOT_CAMERA_HEIGHT + height]
        lamp = Lamp(f'lamp_{k + 1}', k + 1, position, ROBOT_LAMP_RADIUS,
                    marker_angle=float(rng.uniform(-np.pi, np.pi)),
                    marker_distance=ROBOT_LAMP_RADIUS * (1.0 - MARKER_RADIUS_FRACTION - MARKER_RIM_GAP_FRACTION),
                    frequency=frequency)
        waveform = tone_waveform(frequency, depth, offset=float(rng.uniform(0.0, 1.0 / frequency)))
        lamps.append(SimLamp(lamp, waveform, peak_dn=190.0))
    poses = []
    for _ in range(frames):
        xy = rng.uniform([-1.5 * spacing, -1.3 * spacing], [2.5 * spacing, 1.3 * spacing])
        rock = np.radians(0.7) * rng.uniform(-1.0, 1.0, 2)
        rotation = Rotation.from_euler('zyx', [rng.uniform(-np.pi, np.pi), *rock]).as_matrix() @ ROBOT_CAMERA_MOUNT
        poses.append(Pose(rotation, [xy[0], xy[1], ROBOT_CAMERA_HEIGHT]))
    return Scenario('robot_tone', camera, sensor, lamps, poses, [np.zeros(3)] * frames, beacon,
                    frame_rate=1.0 / interval, prior_up=np.array([0.0, 0.0, 1.0]), prior_tolerance=0.1,
                    prior_sigma=np.radians(0.7))


def with_rim_markers(scenario: Scenario, distance: float = 0.9, radius: float = 0.1) -> Scenario:
    """
    Return the scenario with every marker moved and resized (in fractions of the lamp radius r).

    Each marker is centred at ``distance`` x r from the lamp centre, with radius ``radius`` x r.

    The defaults are the paper's "marginal point" (a dot of 0.1 r at 0.9 r, touching the
    rim); ``distance`` from 0.5 out to 1.0 puts it inside, touching or straddling the rim.
    """
    if not 0.0 <= distance <= 1.0 or not radius > 0.0:
        raise ValueError(f'marker distance must be in [0, 1] and radius positive (fractions of r), '
                         f'got {distance}, {radius}')
    lamps = [replace(sim, lamp=replace(sim.lamp, marker_distance=distance * sim.lamp.radius),
                     marker_radius=radius * sim.lamp.radius) for sim in scenario.lamps]
    return replace(scenario, lamps=lamps)


def as_stills(scenario: Scenario, interval: float) -> Scenario:
    """
    Return the scenario's photos taken ``interval`` s apart, stamped so, with the locator's continuity on.

    Hand-held stills 0.1 s apart let the last pose meet the next photo (which may be
    from anywhere on the grid); 2 s apart, the default ``continuity.max_age`` expires.
    """
    if not interval > 0.0:
        raise ValueError(f'interval must be positive, got {interval}')
    return replace(scenario, frame_rate=1.0 / interval, independent_frames=False)
