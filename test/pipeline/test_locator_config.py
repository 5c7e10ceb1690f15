"""Validation of the locator's parameters: every bad value names its parameter."""
from __future__ import annotations

import numpy as np
import pytest

from vlp_ros.pipeline.config import ConfigError, default_parameters, settings_from_parameters


def _values(**overrides):
    values = default_parameters()
    values.update({
        'leds.names': ['hall', 'door'],
        'leds.hall.id': 5, 'leds.hall.position': [1, 2, 3], 'leds.hall.radius': 0.055,
        'leds.door.id': 9, 'leds.door.position': [4.0, 2.0, 3.0], 'leds.door.radius': 1,
        'leds.door.marker_angle': 1.5, 'leds.door.marker_distance': 0.9,
    })
    values.update(overrides)
    return values


def test_valid_map_accepts_integers_for_doubles_and_fills_defaults() -> None:
    settings = settings_from_parameters(_values())
    hall = settings.lamps.get(5)
    np.testing.assert_array_equal(hall.position, [1.0, 2.0, 3.0])
    assert hall.marker_distance == pytest.approx(0.055) and hall.marker_angle == 0.0
    door = settings.lamps.get(9)
    assert door.radius == 1.0 and door.marker_distance == 0.9
    assert settings.prior_up is None and settings.solver == 'perspective'


@pytest.mark.parametrize('overrides, parameter', [
    ({'leds.names': []}, 'leds.names'),
    ({'leds.names': ['hall', 'hall']}, 'leds.names'),
    ({'leds.hall.id': None}, 'leds.hall.id'),
    ({'leds.hall.position': [1.0, 2.0]}, 'leds.hall.position'),
    ({'leds.hall.position': None}, 'leds.hall.position'),
    ({'leds.hall.radius': 0, 'leds.hall.marker_distance': 0.01}, 'leds.hall.marker_distance'),
    ({'leds.hall.radius': -1}, 'leds.hall.radius'),
    ({'leds.door.id': 5}, 'leds.door.id'),
    ({'leds.door.id': 300}, 'leds.door.id'),
    ({'leds.dor.radius': 0.1}, 'leds.dor.radius'),
    ({'leds.hall.raduis': 0.1}, 'leds.hall.raduis'),
    ({'beacon.mode': 'morse'}, 'beacon.mode'),
    ({'beacon.chip_rate': 0}, 'beacon.chip_rate'),
    ({'beacon.row_time': 'fast'}, 'beacon.row_time'),
    ({'solver': 'guess'}, 'solver'),
    ({'prior.up_in_camera': [0, 0]}, 'prior.up_in_camera'),
    ({'prior.up_in_camera': [0, 0, 0]}, 'prior.up_in_camera'),
    ({'imu.rotation': [0, 0, 0]}, 'imu.rotation'),
    ({'continuity.max_speed': -0.5}, 'continuity.max_speed'),
    ({'qos.reliability': 'sometimes'}, 'qos.reliability'),
    ({'qos.depth': 0}, 'qos.depth'),
    ({'map_frame': ''}, 'map_frame'),
])
def test_bad_parameter_is_named(overrides, parameter: str) -> None:
    with pytest.raises(ConfigError) as caught:
        settings_from_parameters(_values(**overrides))
    assert caught.value.parameter == parameter
    assert str(caught.value).startswith(parameter + ':')


def test_a_lamp_missing_from_names_is_not_dropped_silently() -> None:
    values = _values(**{'leds.names': ['hall']})
    with pytest.raises(ConfigError, match="lamp 'door' is not in leds.names"):
        settings_from_parameters(values)


def test_tone_mode_needs_distinct_frequencies() -> None:
    tone = {'beacon.mode': 'tone', 'leds.hall.frequency': 2000, 'leds.door.frequency': 2400}
    settings = settings_from_parameters(_values(**tone))
    assert settings.lamps.frequencies() == {5: 2000.0, 9: 2400.0}
    with pytest.raises(ConfigError, match='leds.hall.frequency: missing'):
        settings_from_parameters(_values(**{**tone, 'leds.hall.frequency': None}))
    with pytest.raises(ConfigError, match='could not be told apart'):
        settings_from_parameters(_values(**{**tone, 'leds.door.frequency': 2050}))


def test_static_prior_is_normalised() -> None:
    settings = settings_from_parameters(_values(**{'prior.up_in_camera': [0, 0, -2]}))
    np.testing.assert_allclose(settings.prior_up, [0, 0, -1])
