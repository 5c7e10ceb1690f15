"""
What a lamp deployment gives over the floor: expected pose error and where lamp IDs can be read.

At every point of a floor grid the camera is placed (lamps ``ceiling`` m above it,
one fixed orientation everywhere), and the lamps it sees whole and large enough
for detection give exact synthetic observations with the stated measurement
noise. The pose engine then solves them as it would a frame, and its reported
covariance is the expected error; the lamps' heights in image rows tell whether
their beacons can be read.

Assumptions (each settable): the detector measures a rim point per edge crossing of
every lamp row, i.e. about two per row the lamp spans (spread evenly round the rim
here), each ``rim_sigma`` px across the edge, and the marker to ``marker_sigma`` px;
an IMU gives the up direction to ``imu_sigma`` rad (None: no IMU, then one lamp alone
is ambiguous and gives no fix); a lamp counts when its image stays ``border_px`` inside
the frame and spans at least ``min_diameter_px`` (the detector's defaults).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum
from functools import cached_property

import numpy as np

from vlp_ros.beacon.encoding import packet_length
from vlp_ros.core.camera import CameraModel
from vlp_ros.core.lamp_map import Lamp
from vlp_ros.core.observation import LampObservation
from vlp_ros.core.pose import Pose
from vlp_ros.detection.detector import DetectionOptions
from vlp_ros.pipeline.config import default_parameters
from vlp_ros.sim.exact_observations import synthetic_observation
from vlp_ros.sim.render import MARKER_RADIUS_FRACTION
from vlp_ros.sim.scenarios import MARKER_RIM_GAP_FRACTION
from vlp_ros.solvers.ambiguity import DisambiguationHints, UpHint
from vlp_ros.solvers.fusion import solve_lamps
from vlp_ros.solvers.measurement import LampMeasurement
from vlp_ros.solvers.refinement import refine_pose

_LOCATOR_DEFAULTS = default_parameters()
_DETECTION_DEFAULTS = DetectionOptions()
# Rim samples for deciding whether a lamp is whole in the frame and how many rows it spans.
_OUTLINE_POINTS = 32
# Fewest rim points the detector accepts for a lamp.
_MIN_RIM_POINTS = _DETECTION_DEFAULTS.min_rim_points


class Decodability(IntEnum):
    """Whether the best-placed lamp in view carries enough of its beacon for an ID."""

    NONE = 0
    FEW_FRAMES = 1
    ONE_FRAME = 2


@dataclass(frozen=True)
class MeasurementNoise:
    """The detector's and the IMU's accuracy, and what the detector needs to see a lamp."""

    rim_sigma: float = 0.1
    marker_sigma: float = 0.15
    imu_sigma: float | None = _LOCATOR_DEFAULTS['imu.sigma']
    imu_tolerance: float = _LOCATOR_DEFAULTS['imu.tolerance']
    min_diameter_px: float = _DETECTION_DEFAULTS.min_diameter
    border_px: float = float(_DETECTION_DEFAULTS.blur_margin)

    def __post_init__(self) -> None:
        for name in ('rim_sigma', 'marker_sigma', 'min_diameter_px'):
            if not getattr(self, name) > 0.0:
                raise ValueError(f'{name} must be positive, got {getattr(self, name)}')
        if self.imu_sigma is not None and not self.imu_sigma > 0.0:
            raise ValueError(f'imu_sigma must be positive (or None for no IMU), got {self.imu_sigma}')
        if not self.border_px >= 0.0:
            raise ValueError(f'border_px must not be negative, got {self.border_px}')


@dataclass(frozen=True)
class BeaconPlan:
    """
    Beacon settings and the spans decoding needs (docs/beacon.md).

    Packet mode: one frame reads the ID when a lamp spans ``min_packets`` packets, a few
    frames together (the evidence tracker) when it spans ``partial_packets``; either way
    a chip must last ``min_rows_per_chip`` rows. Tone mode: one frame needs
    ``min_periods`` stripe periods of the lowest lamp frequency ``tone_frequency``; frames
    with fewer give no evidence at all, so there is no few-frames case.
    """

    mode: str = _LOCATOR_DEFAULTS['beacon.mode']
    chip_rate: float = _LOCATOR_DEFAULTS['beacon.chip_rate']
    id_bits: int = _LOCATOR_DEFAULTS['beacon.id_bits']
    row_time: float = _LOCATOR_DEFAULTS['beacon.row_time']
    tone_frequency: float = 1000.0
    min_packets: float = 1.3
    partial_packets: float = 0.5
    min_rows_per_chip: float = 4.0
    min_periods: float = 3.0

    def __post_init__(self) -> None:
        if self.mode not in ('packet', 'tone'):
            raise ValueError(f"beacon mode must be 'packet' or 'tone', got {self.mode!r}")
        for name in ('chip_rate', 'row_time', 'tone_frequency', 'min_packets', 'partial_packets',
                     'min_rows_per_chip', 'min_periods'):
            if not getattr(self, name) > 0.0:
                raise ValueError(f'beacon {name} must be positive, got {getattr(self, name)}')
        if not 1 <= self.id_bits <= 16:
            raise ValueError(f'beacon id_bits must be in [1, 16], got {self.id_bits}')

    @property
    def rows_per_chip(self) -> float:
        return 1.0 / (self.chip_rate * self.row_time)

    def classify(self, span_rows: np.ndarray) -> np.ndarray:
        """Return the ``Decodability`` codes for lamps spanning ``span_rows`` image rows (0 for no lamp)."""
        span_rows = np.asarray(span_rows, dtype=float)
        codes = np.full(span_rows.shape, int(Decodability.NONE))
        if self.mode == 'tone':
            period_rows = 1.0 / (self.tone_frequency * self.row_time)
            codes[span_rows >= self.min_periods * period_rows] = Decodability.ONE_FRAME
            return codes
        if self.rows_per_chip < self.min_rows_per_chip:
            return codes
        packet_rows = packet_length(self.id_bits) * self.rows_per_chip
        codes[span_rows >= self.partial_packets * packet_rows] = Decodability.FEW_FRAMES
        codes[span_rows >= self.min_packets * packet_rows] = Decodability.ONE_FRAME
        return codes


@dataclass(frozen=True)
class Deployment:
    """
    A room, its lamps and the camera that moves over its floor.

    ``room``: width along x, depth along y (m, from the origin); ``lamps``: their centres
    ``lamp.position[2]`` m above the camera, which moves in the plane z = 0; ``camera`` with
    its orientation (``camera_rotation``, camera to map) at every floor point.
    """

    room: tuple[float, float]
    lamps: tuple[Lamp, ...]
    camera: CameraModel
    camera_rotation: np.ndarray = field(default_factory=lambda: np.eye(3))

    def __post_init__(self) -> None:
        width, depth = self.room
        if not (width > 0.0 and depth > 0.0):
            raise ValueError(f'room width and depth must be positive, got {width} x {depth}')
        if not self.lamps:
            raise ValueError('a deployment needs at least one lamp')
        for lamp in self.lamps:
            if not lamp.position[2] > 0.0:
                raise ValueError(f'lamp {lamp.name!r} must hang above the camera, got height {lamp.position[2]}')
        rotation = np.asarray(self.camera_rotation, dtype=float)
        if rotation.shape != (3, 3) or not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-9):
            raise ValueError('camera_rotation must be a 3x3 rotation matrix')
        object.__setattr__(self, 'camera_rotation', rotation)

    @cached_property
    def outlines(self) -> np.ndarray:
        """Rim samples (lamps, points, 3) in the map, for visibility and image size."""
        return np.stack([lamp.rim_points(_OUTLINE_POINTS) for lamp in self.lamps])


@dataclass
class FloorPlan:
    """
    What a deployment gives per floor cell (rows along y, columns along x).

    Expected 3D position error (cm, NaN where there is no fix), lamps in view, and
    ``Decodability`` codes.
    """

    xs: np.ndarray
    ys: np.ndarray
    error_cm: np.ndarray
    lamps_in_view: np.ndarray
    decodability: np.ndarray

    @property
    def coverage(self) -> float:
        """Fraction of the floor with a fix."""
        return float(np.mean(np.isfinite(self.error_cm)))

    def error_percentile(self, q: float) -> float:
        """Percentile ``q`` of the expected error over the covered floor (NaN if none)."""
        covered = self.error_cm[np.isfinite(self.error_cm)]
        return float(np.percentile(covered, q)) if covered.size else float('nan')

    def decodable_fraction(self, level: Decodability) -> float:
        """Fraction of the floor where an ID is read at ``level`` or better."""
        return float(np.mean(self.decodability >= level))


def ceiling_lamp(name: str, lamp_id: int, x: float, y: float, ceiling: float, radius: float) -> Lamp:
    """Return a lamp as the simulator builds them: marker just inside the rim, toward +x."""
    if not radius > 0.0:
        raise ValueError(f'lamp radius must be positive, got {radius}')
    marker_distance = radius * (1.0 - MARKER_RADIUS_FRACTION - MARKER_RIM_GAP_FRACTION)
    return Lamp(name, lamp_id, [x, y, ceiling], radius, marker_angle=0.0, marker_distance=marker_distance)


def grid_positions(room: tuple[float, float], spacing: float) -> np.ndarray:
    """
    Return lamp (x, y) (N, 2) on a square grid of ``spacing``, centred in the room.

    As many per side as fit the room at that spacing (at least one).
    """
    if not spacing > 0.0:
        raise ValueError(f'lamp spacing must be positive, got {spacing}')
    axes = []
    for size in room:
        count = max(1, int(round(size / spacing)))
        axes.append(0.5 * size + (np.arange(count) - 0.5 * (count - 1)) * spacing)
    gx, gy = np.meshgrid(*axes)
    return np.column_stack([gx.ravel(), gy.ravel()])


def looking_up(tilt: float = 0.0, tilt_azimuth: float = 0.0, yaw: float = 0.0) -> np.ndarray:
    """
    Return the camera-to-map rotation of a camera looking up, optionally tilted.

    The camera looks straight up (image x along map direction ``yaw``), then is tilted by
    ``tilt`` toward map direction ``tilt_azimuth`` (all rad).
    """
    c, s = np.cos(yaw), np.sin(yaw)
    turned = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    axis = np.array([-np.sin(tilt_azimuth), np.cos(tilt_azimuth), 0.0])
    skew = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    tilted = np.eye(3) + np.sin(tilt) * skew + (1.0 - np.cos(tilt)) * skew @ skew
    return tilted @ turned


def visible_spans(deployment: Deployment, pose: Pose, noise: MeasurementNoise) -> dict[int, float]:
    """Image height in rows of every lamp the detector would see whole, by index in the deployment."""
    camera = deployment.camera
    shape = deployment.outlines.shape
    outlines = pose.map_to_camera(deployment.outlines.reshape(-1, 3)).reshape(shape)
    in_front = np.flatnonzero(np.all(outlines[:, :, 2] > 0.0, axis=1))
    if in_front.size == 0:
        return {}
    pixels = camera.project(outlines[in_front].reshape(-1, 3)).reshape(in_front.size, -1, 2)
    diameters = np.linalg.norm(pixels[:, :, None, :] - pixels[:, None, :, :], axis=-1).max(axis=(1, 2))
    # The rim bulges past the outline's chords by up to ~this (doubled for perspective).
    bulge = diameters * (1.0 - np.cos(np.pi / _OUTLINE_POINTS))
    low = noise.border_px + bulge[:, None, None]
    high = np.array([camera.width, camera.height]) - 1.0 - low
    whole = np.all((pixels >= low) & (pixels <= high), axis=(1, 2)) & (diameters >= noise.min_diameter_px)
    spans = np.ptp(pixels[:, :, 1], axis=1)
    return {int(i): float(span) for i, span in zip(in_front[whole], spans[whole])}


def lamp_observations(deployment: Deployment, pose: Pose, spans: dict[int, float],
                      noise: MeasurementNoise) -> list[tuple[LampObservation, Lamp]]:
    """
    Return exact observations of the lamps in ``spans`` (from ``visible_spans``) with the noise's sigmas.

    Two rim points per row each lamp spans.
    """
    pairs = []
    for index, span in spans.items():
        lamp = deployment.lamps[index]
        rim_count = max(_MIN_RIM_POINTS, 2 * int(round(span)))
        observation = synthetic_observation(lamp, pose, deployment.camera, rim_count=rim_count,
                                            rim_sigma=noise.rim_sigma, marker_sigma=noise.marker_sigma)
        pairs.append((observation, lamp))
    return pairs


def expected_position_error(deployment: Deployment, pose: Pose, spans: dict[int, float],
                            noise: MeasurementNoise) -> float:
    """
    Return the expected position error (m): sqrt(trace) of the position covariance the solver reports.

    The covariance is for exact observations of the lamps in ``spans`` from ``pose``; NaN when the
    solver gives no pose.
    """
    pairs = lamp_observations(deployment, pose, spans, noise)
    up = [] if noise.imu_sigma is None else [UpHint(pose.up_in_camera(), noise.imu_tolerance, noise.imu_sigma)]
    hints = DisambiguationHints(up_in_camera=up)
    if len(pairs) == 1:
        solved = solve_lamps(pairs, deployment.camera, hints).pose
    else:
        # Exact data put the joint fit's minimum at the true pose, where solve_lamps's search
        # for starts (most of its time) ends too: refining there gives its covariance.
        measurements = [LampMeasurement.from_observation(obs, lamp, deployment.camera) for obs, lamp in pairs]
        fit = refine_pose(pose, measurements, hints.up_measurements())
        solved = None if fit is None else fit.pose
    if solved is None:
        return float('nan')
    return float(np.sqrt(np.trace(solved.covariance[:3, :3])))


def plan_floor(deployment: Deployment, beacon: BeaconPlan, noise: MeasurementNoise, points: int = 40) -> FloorPlan:
    """Return the expected error and decodability at the centres of a ``points`` x ``points`` floor grid."""
    if points < 1:
        raise ValueError(f'points must be at least 1, got {points}')
    if beacon.mode == 'packet' and len(deployment.lamps) > 2 ** beacon.id_bits:
        raise ValueError(f'{len(deployment.lamps)} lamps need more than {beacon.id_bits} ID bits')
    width, depth = deployment.room
    xs = (np.arange(points) + 0.5) * width / points
    ys = (np.arange(points) + 0.5) * depth / points
    error = np.full((points, points), np.nan)
    in_view = np.zeros((points, points), dtype=int)
    best_span = np.zeros((points, points))
    for row, y in enumerate(ys):
        for col, x in enumerate(xs):
            pose = Pose(deployment.camera_rotation, [x, y, 0.0])
            spans = visible_spans(deployment, pose, noise)
            if not spans:
                continue
            in_view[row, col] = len(spans)
            best_span[row, col] = max(spans.values())
            error[row, col] = 100.0 * expected_position_error(deployment, pose, spans, noise)
    return FloorPlan(xs, ys, error, in_view, beacon.classify(best_span))
