"""The survey's params files: the partial map it reads, the surveyed one it writes, and the locator loading that."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from vlp_ros.pipeline.config import ConfigError, default_parameters, settings_from_parameters, settings_from_params_file
from vlp_ros.survey.partial_map import load_partial_map, SurveyedLamp, write_surveyed

import yaml


def partial_file(tmp_path: Path, anchors: int = 2) -> Path:
    leds = {'names': ['a', 'b', 'c']}
    for k, name in enumerate(leds['names']):
        leds[name] = {'id': 10 + k, 'radius': 0.075, 'marker_distance': 0.0675}
        if k < anchors:
            leds[name].update(position=[1.2 * k, 0.0, 2.6], marker_angle=0.5 * k)
    params = {'beacon': {'chip_rate': 16000.0}, 'base_frame': 'base_link',
              'camera_in_base': {'translation': [0.0, 0.0, 0.45], 'rotation': [0.0, 0.0, 0.0, 1.0]}, 'leds': leds}
    path = tmp_path / 'partial.yaml'
    path.write_text(yaml.safe_dump({'vlp_locator': {'ros__parameters': params}}))
    return path


def test_lamps_without_a_position_are_surveyed_the_others_are_anchors(tmp_path: Path) -> None:
    partial = load_partial_map(partial_file(tmp_path))
    assert partial.surveyed == ['c'] and sorted(partial.anchors) == ['a', 'b']
    np.testing.assert_array_equal(partial.anchors['b'].position, [1.2, 0.0, 2.6])
    assert partial.anchors['b'].marker_angle == 0.5
    assert partial.settings.mounting is not None


def test_a_survey_needs_two_anchors(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as caught:
        load_partial_map(partial_file(tmp_path, anchors=1))
    assert caught.value.parameter == 'leds'


def test_the_surveyed_file_is_the_partial_one_filled_in_and_the_locator_loads_it(tmp_path: Path) -> None:
    path = partial_file(tmp_path)
    partial = load_partial_map(path)
    surveyed = SurveyedLamp(np.array([2.4012345, 0.01, 2.61]), 1.25, np.diag([1e-6, 4e-6, 9e-6]), 0.001)
    out = tmp_path / 'surveyed.yaml'
    write_surveyed(partial, {'c': surveyed}, out)
    settings = settings_from_params_file(out)
    lamp = settings.lamps.get(12)
    np.testing.assert_allclose(lamp.position, [2.40123, 0.01, 2.61])
    np.testing.assert_allclose(lamp.position_sigma, [0.001, 0.002, 0.003])
    assert lamp.marker_angle == pytest.approx(1.25)
    # Everything else as it was: the anchors exact, the mounting and the beacon kept.
    np.testing.assert_array_equal(settings.lamps.get(11).position_sigma, [0.0, 0.0, 0.0])
    np.testing.assert_array_equal(settings.lamps.get(11).position, [1.2, 0.0, 2.6])
    assert settings.beacon.chip_rate == 16000.0
    assert settings.base_frame == 'base_link'


def _values(**overrides):
    values = default_parameters()
    values.update({'leds.names': ['hall'], 'leds.hall.id': 5, 'leds.hall.position': [1, 2, 3],
                   'leds.hall.radius': 0.075})
    values.update(overrides)
    return values


def test_position_sigma_is_three_standard_deviations_absent_meaning_exact() -> None:
    assert settings_from_parameters(_values()).lamps.get(5).position_sigma is None
    lamp = settings_from_parameters(_values(**{'leds.hall.position_sigma': [0.001, 0, 2e-3]})).lamps.get(5)
    np.testing.assert_array_equal(lamp.position_sigma, [0.001, 0.0, 0.002])


@pytest.mark.parametrize('value', [[0.001, 0.002], [0.001, -0.002, 0.001], [0.001, float('nan'), 0.0], 'small'])
def test_a_bad_position_sigma_is_named(value) -> None:
    with pytest.raises(ConfigError) as caught:
        settings_from_parameters(_values(**{'leds.hall.position_sigma': value}))
    assert caught.value.parameter == 'leds.hall.position_sigma'
