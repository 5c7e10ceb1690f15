"""
The locator's settings, validated from flat ROS-style parameter values.

ROS-free: the node reads its parameters into a ``dict`` and this module turns it
into typed settings, raising ``ConfigError`` whose message names the parameter.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from vlp_ros.beacon.tone import MAX_ROW_TIME_TOLERANCE, ROW_TIME_TOLERANCE
from vlp_ros.core.lamp_map import Lamp, LampMap
from vlp_ros.core.mounting import Mounting, unit_quaternion_problem
from vlp_ros.solvers.floor import Floor

import yaml

BEACON_MODES = ('packet', 'tone')
SOLVERS = ('perspective', 'paper')
RELIABILITIES = ('best_effort', 'reliable')
# A base that tilts this much (rad) about a horizontal axis is on no floor the planar model describes.
MAX_SIGMA_TILT = 0.5
IMAGE_TRANSPORTS = ('raw', 'compressed')


@dataclass(frozen=True)
class ParameterSpec:
    """
    One parameter: ``kind`` is string, string_array, number, number_array, integer or bool.

    Numbers accept integers too (a params file may say ``radius: 1``).
    """

    name: str
    kind: str
    default: Any
    description: str


PARAMETERS = (
    ParameterSpec('map_frame', 'string', 'map', 'frame_id of the published poses'),
    ParameterSpec('leds.names', 'string_array', [], 'names of the lamps in the map; each has leds.<name>.* fields'),
    ParameterSpec('beacon.mode', 'string', 'packet', 'how lamps identify themselves: packet or tone'),
    ParameterSpec('beacon.chip_rate', 'number', 8000.0, 'packet mode chip rate (Hz)'),
    ParameterSpec('beacon.id_bits', 'integer', 8, 'packet mode data bits per ID'),
    ParameterSpec('beacon.row_time', 'number', 1.5e-5, "camera's time between consecutive row exposure starts (s)"),
    ParameterSpec('beacon.exposure', 'number', 0.0,
                  "camera's exposure time (s); 0 = unknown. Tone mode needs it for short exposures"),
    ParameterSpec('beacon.frequency_tolerance', 'number', 60.0, 'tone mode: largest accepted frequency error (Hz)'),
    ParameterSpec('beacon.row_time_tolerance', 'number', ROW_TIME_TOLERANCE,
                  "tone mode: how far (relative) beacon.row_time may be off; each lamp's band widens by that share "
                  'of its frequency'),
    ParameterSpec('solver', 'string', 'perspective', 'pose solver: perspective (exact) or paper (weak perspective)'),
    ParameterSpec('prior.up_in_camera', 'number_array', [],
                  'fixed mount: where map +z points in the camera optical frame (3 numbers); empty = no prior'),
    ParameterSpec('prior.tolerance', 'number', 0.35, 'largest angle (rad) between a pose and the static prior'),
    ParameterSpec('prior.sigma', 'number', 0.0,
                  'standard deviation (rad) of the mount prior; > 0 makes it a measurement in the pose fit, '
                  '0 only a gate'),
    ParameterSpec('imu.enabled', 'bool', False,
                  'use gravity from the imu topic to tell pose candidates apart'),
    ParameterSpec('imu.rotation', 'number_array', [0.0, 0.0, 0.0, 1.0],
                  'quaternion (x, y, z, w) turning IMU-frame vectors into the camera optical frame'),
    ParameterSpec('imu.max_age', 'number', 0.1,
                  'an IMU message older than this (s) at the image stamp is not used'),
    ParameterSpec('imu.tolerance', 'number', 0.35, 'largest angle (rad) between a pose and measured gravity'),
    ParameterSpec('imu.sigma', 'number', 0.005,
                  "standard deviation (rad) of the IMU's up direction; > 0 makes gravity a measurement in the pose "
                  'fit, 0 only a gate'),
    ParameterSpec('continuity.gate', 'number', 0.3,
                  'a candidate within this distance (m) of a recent pose continues it'),
    ParameterSpec('continuity.max_age', 'number', 1.0, 'how long (s) a pose may vouch for the next; 0 disables'),
    ParameterSpec('continuity.max_speed', 'number', 2.0,
                  'fastest the camera is expected to move (m/s): the gate grows by this times the time since the '
                  'recent pose'),
    ParameterSpec('image_transport', 'string', 'raw', 'raw (image_raw) or compressed (image_raw/compressed)'),
    ParameterSpec('qos.reliability', 'string', 'best_effort',
                  'image subscription reliability: best_effort or reliable'),
    ParameterSpec('qos.depth', 'integer', 1, 'image subscription queue depth'),
    ParameterSpec('base_frame', 'string', '',
                  "the robot's frame whose pose is published; empty = publish the camera optical frame"),
    ParameterSpec('camera_in_base.translation', 'number_array', [0.0, 0.0, 0.0],
                  "the camera optical frame's origin in base_frame (x, y, z) (m)"),
    ParameterSpec('camera_in_base.rotation', 'number_array', [0.0, 0.0, 0.0, 1.0],
                  'unit quaternion (x, y, z, w) of the camera optical frame (z forward, x right, y down) '
                  'in base_frame'),
    ParameterSpec('planar.enabled', 'bool', False,
                  'base_frame moves on a horizontal floor, a measurement of every pose (needs base_frame)'),
    ParameterSpec('planar.height', 'number', 0.0, "the z of base_frame's origin in map_frame (m)"),
    ParameterSpec('planar.sigma_height', 'number', 0.01,
                  "how far bumps, suspension and an uneven floor move base_frame's origin off that height (m)"),
    ParameterSpec('planar.sigma_tilt', 'number', 0.01,
                  "how far they tilt base_frame's +z off vertical, about each horizontal axis (rad)"),
)
LAMP_PARAMETERS = (
    ParameterSpec('id', 'integer', None, 'beacon ID of the lamp'),
    ParameterSpec('position', 'number_array', None, 'centre of the luminous disc in the map (x, y, z) (m)'),
    ParameterSpec('radius', 'number', None, 'radius of the luminous disc (m); 0 = a point lamp (bare LED)'),
    ParameterSpec('marker_angle', 'number', 0.0, 'map direction of the red marker from the centre (rad, +x toward +y)'),
    ParameterSpec('marker_distance', 'number', None,
                  "marker centroid's distance from the centre (m); default the radius"),
    ParameterSpec('frequency', 'number', None, "tone mode: the lamp's square-wave frequency (Hz)"),
    ParameterSpec('position_sigma', 'number_array', None,
                  'standard deviation (m) of the position along map x, y and z (a surveyed map); absent = exact'),
)
LAMP_FIELDS = tuple(spec.name for spec in LAMP_PARAMETERS)


def default_parameters() -> dict[str, Any]:
    return {spec.name: spec.default for spec in PARAMETERS}


class ConfigError(ValueError):
    """A parameter that cannot be used; the message starts with the parameter's name."""

    def __init__(self, parameter: str, problem: str) -> None:
        super().__init__(f'{parameter}: {problem}')
        self.parameter = parameter


@dataclass(frozen=True)
class BeaconSettings:
    mode: str
    chip_rate: float
    id_bits: int
    row_time: float
    exposure: float | None
    frequency_tolerance: float
    row_time_tolerance: float = ROW_TIME_TOLERANCE


@dataclass(frozen=True)
class LocatorSettings:
    map_frame: str
    lamps: LampMap
    beacon: BeaconSettings
    solver: str
    prior_up: np.ndarray | None
    prior_tolerance: float
    prior_sigma: float | None
    imu_enabled: bool
    imu_rotation: np.ndarray
    imu_max_age: float
    imu_tolerance: float
    imu_sigma: float | None
    continuity_gate: float
    continuity_max_age: float
    continuity_max_speed: float
    image_transport: str
    qos_reliability: str
    qos_depth: int
    # None when base_frame is empty: the camera optical frame is published.
    base_frame: str | None = None
    mounting: Mounting | None = None
    # None unless planar.enabled: the floor base_frame moves on.
    floor: Floor | None = None


def _number(values: Mapping[str, Any], name: str, *, positive: bool = False,
            minimum: float | None = None) -> float:
    value = values.get(name)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(name, f'expected a number, got {value!r}')
    value = float(value)
    if not np.isfinite(value):
        raise ConfigError(name, f'must be finite, got {value}')
    if positive and value <= 0.0:
        raise ConfigError(name, f'must be positive, got {value}')
    if minimum is not None and value < minimum:
        raise ConfigError(name, f'must be at least {minimum}, got {value}')
    return value


def _integer(values: Mapping[str, Any], name: str, low: int, high: int) -> int:
    value = values.get(name)
    if isinstance(value, bool) or not isinstance(value, int):
        raise ConfigError(name, f'expected an integer, got {value!r}')
    if not low <= value <= high:
        raise ConfigError(name, f'must be in [{low}, {high}], got {value}')
    return value


def _vector(values: Mapping[str, Any], name: str, length: int, *, allow_empty: bool = False) -> np.ndarray | None:
    value = values.get(name)
    if value is None or isinstance(value, (str, bytes)) or not hasattr(value, '__len__'):
        raise ConfigError(name, f'expected a list of {length} numbers, got {value!r}')
    if allow_empty and len(value) == 0:
        return None
    if len(value) != length or any(isinstance(v, bool) or not isinstance(v, (int, float)) for v in value):
        raise ConfigError(name, f'expected {length} numbers, got {list(value)!r}')
    vector = np.asarray(value, dtype=float)
    if not np.all(np.isfinite(vector)):
        raise ConfigError(name, f'must be finite, got {list(value)!r}')
    return vector


def _choice(values: Mapping[str, Any], name: str, options: tuple[str, ...]) -> str:
    value = values.get(name)
    if value not in options:
        raise ConfigError(name, f'must be one of {", ".join(options)}; got {value!r}')
    return value


def _unit(vector: np.ndarray, name: str) -> np.ndarray:
    norm = np.linalg.norm(vector)
    if norm < 1e-9:
        raise ConfigError(name, 'must not be the zero vector')
    return vector / norm


def lamp_from_parameters(values: Mapping[str, Any], name: str, tone_mode: bool) -> Lamp:
    prefix = f'leds.{name}.'
    for field in ('id', 'position', 'radius'):
        if values.get(prefix + field) is None:
            raise ConfigError(prefix + field, f'missing: every lamp in leds.names needs {field}')
    radius = _number(values, prefix + 'radius', minimum=0.0)
    marker_distance = None
    if radius == 0.0 and values.get(prefix + 'marker_distance') is not None:
        raise ConfigError(prefix + 'marker_distance', 'a point lamp (radius 0) has no marker')
    if values.get(prefix + 'marker_distance') is not None:
        marker_distance = _number(values, prefix + 'marker_distance', positive=True)
    frequency = None
    if values.get(prefix + 'frequency') is not None:
        frequency = _number(values, prefix + 'frequency', positive=True)
    elif tone_mode:
        raise ConfigError(prefix + 'frequency', 'missing: beacon.mode is tone, so every lamp needs a frequency')
    angle = _number(values, prefix + 'marker_angle') if values.get(prefix + 'marker_angle') is not None else 0.0
    return Lamp(name=name, id=_integer(values, prefix + 'id', 0, 2 ** 31 - 1),
                position=_vector(values, prefix + 'position', 3), radius=radius,
                marker_angle=angle, marker_distance=marker_distance, frequency=frequency,
                position_sigma=_position_sigma(values, prefix + 'position_sigma'))


def _position_sigma(values: Mapping[str, Any], name: str) -> np.ndarray | None:
    """Three standard deviations (m) not below zero, or None where the parameter is absent (exact)."""
    if values.get(name) is None:
        return None
    sigma = _vector(values, name, 3)
    if np.any(sigma < 0.0):
        raise ConfigError(name, f'standard deviations must not be negative, got {sigma.tolist()}')
    return sigma


def lamp_map_from_parameters(values: Mapping[str, Any], beacon: BeaconSettings) -> LampMap:
    names = values.get('leds.names')
    if not names:
        raise ConfigError('leds.names', 'the lamp map is empty: list the lamp names')
    if len(set(names)) != len(names):
        duplicate = next(n for n in names if names.count(n) > 1)
        raise ConfigError('leds.names', f'lamp name {duplicate!r} appears twice')
    _reject_unlisted_lamps(values, names)
    lamps = [lamp_from_parameters(values, name, beacon.mode == 'tone') for name in names]
    seen: dict[int, str] = {}
    for lamp in lamps:
        if lamp.id in seen:
            raise ConfigError(f'leds.{lamp.name}.id', f'id {lamp.id} is also the id of lamp {seen[lamp.id]!r}')
        if beacon.mode == 'packet' and lamp.id >= 2 ** beacon.id_bits:
            raise ConfigError(f'leds.{lamp.name}.id',
                              f'id {lamp.id} does not fit in beacon.id_bits = {beacon.id_bits}')
        seen[lamp.id] = lamp.name
    _reject_indistinct_frequencies(lamps, beacon)
    return LampMap(lamps)


def _reject_unlisted_lamps(values: Mapping[str, Any], names: list[str]) -> None:
    """
    Raise ConfigError for a lamp key whose lamp is not in leds.names or whose field is unknown.

    A lamp whose name is misspelt in leds.names or in its own keys must not vanish silently.
    """
    for key in values:
        parts = key.split('.')
        if parts[0] != 'leds' or key == 'leds.names':
            continue
        if len(parts) != 3 or parts[1] not in names:
            raise ConfigError(key, f'lamp {parts[1]!r} is not in leds.names {list(names)} (a typo?)')
        if parts[2] not in LAMP_FIELDS:
            raise ConfigError(key, f'unknown lamp field {parts[2]!r} (known: {", ".join(LAMP_FIELDS)})')


def _reject_indistinct_frequencies(lamps: list[Lamp], beacon: BeaconSettings) -> None:
    if beacon.mode != 'tone':
        return
    ordered = sorted(lamps, key=lambda lamp: lamp.frequency)
    for low, high in zip(ordered, ordered[1:]):
        if high.frequency - low.frequency <= 2.0 * beacon.frequency_tolerance:
            raise ConfigError(f'leds.{high.name}.frequency',
                              f'{high.frequency} Hz is within 2 x beacon.frequency_tolerance of lamp '
                              f'{low.name!r} ({low.frequency} Hz): the two could not be told apart')


def beacon_from_parameters(values: Mapping[str, Any]) -> BeaconSettings:
    return BeaconSettings(
        mode=_choice(values, 'beacon.mode', BEACON_MODES),
        chip_rate=_number(values, 'beacon.chip_rate', positive=True),
        id_bits=_integer(values, 'beacon.id_bits', 1, 16),
        row_time=_number(values, 'beacon.row_time', positive=True),
        exposure=_number(values, 'beacon.exposure', minimum=0.0) or None,
        frequency_tolerance=_number(values, 'beacon.frequency_tolerance', positive=True),
        row_time_tolerance=_row_time_tolerance(values))


def _row_time_tolerance(values: Mapping[str, Any]) -> float:
    value = _number(values, 'beacon.row_time_tolerance', minimum=0.0)
    if not value < MAX_ROW_TIME_TOLERANCE:
        raise ConfigError('beacon.row_time_tolerance', f'must be below {MAX_ROW_TIME_TOLERANCE}, got {value}')
    return value


def mounting_from_parameters(values: Mapping[str, Any], map_frame: str) -> tuple[str | None, Mounting]:
    """(base_frame or None, the camera's mounting in it); the mounting is validated even when unused."""
    base_frame = values.get('base_frame')
    if not isinstance(base_frame, str):
        raise ConfigError('base_frame', f'must be a frame name or empty, got {base_frame!r}')
    if base_frame == map_frame:
        raise ConfigError('base_frame', f'must differ from map_frame ({map_frame!r})')
    translation = _vector(values, 'camera_in_base.translation', 3)
    rotation = _vector(values, 'camera_in_base.rotation', 4)
    problem = unit_quaternion_problem(rotation)
    if problem:
        raise ConfigError('camera_in_base.rotation', problem)
    return base_frame or None, Mounting.from_quaternion(rotation / np.linalg.norm(rotation), translation)


def floor_from_parameters(values: Mapping[str, Any], base_frame: str | None, mounting: Mounting,
                          solver: str) -> Floor | None:
    """Return the floor of ``planar.*`` (None unless ``planar.enabled``), its values validated even when unused."""
    enabled = values.get('planar.enabled')
    if not isinstance(enabled, bool):
        raise ConfigError('planar.enabled', f'expected true or false, got {enabled!r}')
    height = _number(values, 'planar.height')
    sigma_height = _number(values, 'planar.sigma_height', positive=True)
    sigma_tilt = _number(values, 'planar.sigma_tilt', positive=True)
    if not sigma_tilt < MAX_SIGMA_TILT:
        raise ConfigError('planar.sigma_tilt', f'must be below {MAX_SIGMA_TILT} rad (a floor, in radians), '
                                               f'got {sigma_tilt}')
    if not enabled:
        return None
    if base_frame is None:
        raise ConfigError('planar.enabled', 'needs base_frame (and camera_in_base): the floor holds the robot '
                                            'base, not the camera')
    if solver != 'perspective':
        raise ConfigError('planar.enabled', f'needs solver perspective, got {solver!r}')
    return Floor(mounting, height, sigma_height, sigma_tilt)


def settings_from_parameters(values: Mapping[str, Any]) -> LocatorSettings:
    """Typed, validated settings; raises ConfigError naming the first bad parameter."""
    map_frame = values.get('map_frame')
    if not isinstance(map_frame, str) or not map_frame:
        raise ConfigError('map_frame', f'must be a non-empty frame name, got {map_frame!r}')
    beacon = beacon_from_parameters(values)
    prior_up = _vector(values, 'prior.up_in_camera', 3, allow_empty=True)
    rotation = _unit(_vector(values, 'imu.rotation', 4), 'imu.rotation')
    base_frame, mounting = mounting_from_parameters(values, map_frame)
    solver = _choice(values, 'solver', SOLVERS)
    floor = floor_from_parameters(values, base_frame, mounting, solver)
    return LocatorSettings(
        map_frame=map_frame,
        lamps=lamp_map_from_parameters(values, beacon),
        beacon=beacon,
        solver=solver,
        prior_up=None if prior_up is None else _unit(prior_up, 'prior.up_in_camera'),
        prior_tolerance=_number(values, 'prior.tolerance', positive=True),
        prior_sigma=_number(values, 'prior.sigma', minimum=0.0) or None,
        imu_enabled=bool(values.get('imu.enabled')),
        imu_rotation=rotation,
        imu_max_age=_number(values, 'imu.max_age', positive=True),
        imu_tolerance=_number(values, 'imu.tolerance', positive=True),
        imu_sigma=_number(values, 'imu.sigma', minimum=0.0) or None,
        continuity_gate=_number(values, 'continuity.gate', positive=True),
        continuity_max_age=_number(values, 'continuity.max_age', minimum=0.0),
        continuity_max_speed=_number(values, 'continuity.max_speed', minimum=0.0),
        image_transport=_choice(values, 'image_transport', IMAGE_TRANSPORTS),
        qos_reliability=_choice(values, 'qos.reliability', RELIABILITIES),
        qos_depth=_integer(values, 'qos.depth', 1, 1000),
        base_frame=base_frame,
        mounting=mounting if base_frame else None,
        floor=floor)


def flatten_parameters(tree: Mapping[str, Any], prefix: str = '') -> dict[str, Any]:
    """Nested ``ros__parameters`` as in a params file -> dotted parameter names."""
    flat: dict[str, Any] = {}
    for key, value in tree.items():
        if isinstance(value, Mapping):
            flat.update(flatten_parameters(value, f'{prefix}{key}.'))
        else:
            flat[prefix + key] = value
    return flat


def settings_from_params_file(path: Path | str, node: str = 'vlp_locator') -> LocatorSettings:
    """Return settings from a ``--params-file`` YAML, reading the section of ``node`` (or ``/**``)."""
    document = yaml.safe_load(Path(path).read_text()) or {}
    return settings_from_tree(parameters_tree(document, node, path))


def parameters_tree(document: Mapping[str, Any], node: str, path: Path | str) -> dict[str, Any]:
    """Return the nested ``ros__parameters`` of ``node`` (or ``/**``) in a params file's ``document`` at ``path``."""
    section = next((document[key] for key in (node, f'/{node}', '/**') if key in document), None)
    if not isinstance(section, Mapping) or 'ros__parameters' not in section:
        raise ConfigError('params file', f'{path} has no {node}: ros__parameters section')
    return section['ros__parameters']


def settings_from_tree(tree: Mapping[str, Any]) -> LocatorSettings:
    """Return the settings that nested ``ros__parameters`` (as in a params file) give over the defaults."""
    values = default_parameters()
    values.update(flatten_parameters(tree))
    return settings_from_parameters(values)
