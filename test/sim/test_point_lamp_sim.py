"""
The simulator's bare-LED look.

A core where the LED projects, a glow at the measured level, tone stripes on every row it
reaches, and the ``bare_leds`` scenario on the command line.
"""
from __future__ import annotations

import numpy as np
import pytest

from vlp_ros.pipeline.config import default_parameters, flatten_parameters, settings_from_parameters, settings_from_tree
from vlp_ros.pipeline.frame import Pipeline
from vlp_ros.sim import __main__ as cli
from vlp_ros.sim.point_lamps import bare_led_scenario, PointLampLook, RIG_FREQUENCIES

import yaml


@pytest.fixture(scope='module')
def full_resolution_photo():
    """
    Return one noise-free photo at the rig's full 7712 px with the tone unmodulated, and a second one striped.

    The unmodulated one (depth ~0) is for the profile.
    """
    flat = bare_led_scenario('full', photos=1, seed=2, depth=1e-6)
    striped = bare_led_scenario('full', photos=1, seed=2, depth=0.75)
    return flat.render(0, None), striped.render(0, None)


def test_the_core_is_where_the_led_projects_and_the_glow_is_at_the_measured_level(full_resolution_photo) -> None:
    frame, _ = full_resolution_photo
    green = frame.image[..., 1].astype(float)
    for truth in frame.lamps:
        x, y = np.rint(truth.center_pixel).astype(int)
        assert green[y, x] == 255.0, 'the bright core saturates'
        row = green[y, x - 200:x + 201] - 12.0
        lit = np.flatnonzero(row >= 0.5 * row.max())
        # Within the photos' 31-64 px at half level, centred on the LED's image.
        assert 31 <= len(lit) <= 64 and abs(lit.mean() - 200) < 1.0
        # The glow at 10 % of the core's 320 DN about 120 px out (the photos: 10 % at ~120 px).
        assert 0.07 * 320 < np.mean([row[200 - 120], row[200 + 120]]) < 0.13 * 320


def test_the_stripes_run_across_core_and_glow_at_the_tone(full_resolution_photo) -> None:
    _, frame = full_resolution_photo
    green = frame.image[..., 1].astype(float)
    truth = min(frame.lamps, key=lambda t: t.lamp_id)
    x, y = np.rint(truth.center_pixel).astype(int)
    # A column through the glow, 100 px beside the core: its rows carry the tone.
    column = green[y - 150:y + 150, x + 100] - 12.0
    spectrum = np.abs(np.fft.rfft((column - column.mean()) * np.hanning(len(column)), 4096))
    peak = np.argmax(spectrum[5:]) + 5
    rows_per_period = 4096 / peak
    assert rows_per_period == pytest.approx(1.0 / (RIG_FREQUENCIES[0] * 21.03e-6), rel=0.05)


def test_bare_leds_on_the_command_line_writes_point_lamps_in_tone_mode(tmp_path, capsys) -> None:
    out = tmp_path / 'out'
    assert cli.main(['--scenario', 'bare_leds', '--camera', '1080p', '--frames', '1', '--led-glow', '0.2',
                     '--out', str(out)]) == 0
    assert 'tone lamps' in capsys.readouterr().out
    values = default_parameters()
    values.update(flatten_parameters(
        yaml.safe_load((out / 'params.yaml').read_text())['vlp_locator']['ros__parameters']))
    settings = settings_from_parameters(values)
    assert settings.beacon.mode == 'tone' and len(settings.lamps) == 5
    assert all(lamp.is_point for lamp in settings.lamps)
    assert (out / 'bare_leds_1080p' / 'metadata.yaml').exists()


@pytest.mark.parametrize('arguments, message', [
    (['--scenario', 'bare_leds', '--led-glow', '1.5'], '--led-glow must be in [0, 1)'),
    (['--scenario', 'bare_leds', '--led-core-radius', '0'], '--led-core-radius must be positive'),
    (['--scenario', 'paper', '--photos', '3'], '--photos: only valid with --scenario bare_leds'),
    (['--scenario', 'bare_leds', '--points', '3'], '--points: only valid with --scenario paper'),
])
def test_bad_bare_led_options_are_refused_in_one_line(tmp_path, capsys, arguments, message) -> None:
    assert cli.main(arguments + ['--out', str(tmp_path / 'out')]) == 2
    error = capsys.readouterr().err
    assert message in error and len(error.strip().splitlines()) == 1


def test_a_look_refuses_impossible_values() -> None:
    with pytest.raises(ValueError):
        PointLampLook(glow_level=1.0)


@pytest.mark.simulation
@pytest.mark.parametrize('look, poses', [(PointLampLook(core_radius=0.02, glow_level=0.1), 3),
                                         (PointLampLook(), 0)])
def test_bare_led_photos_through_the_pipeline_give_right_ids_and_poses_or_none(look, poses) -> None:
    """
    The soft-glow look is read: a pose from the five LEDs on each photo.

    The rig's measured look is not (its glow hides the cores from this detector): no ID
    and no pose, and never a wrong one.
    """
    scenario = bare_led_scenario('4k', photos=3, seed=4, look=look)
    pipeline = Pipeline(settings_from_tree(scenario.locator_parameters(imu=False)))
    rng = np.random.default_rng(9)
    located = 0
    for index, truth in enumerate(scenario.poses):
        frame = scenario.render(index, rng)
        result = pipeline.process(frame.image, frame.camera, frame.start_time)
        assert set(result.decoded_ids) <= {t.lamp_id for t in frame.lamps if t.fully_inside}
        if result.pose is not None:
            assert result.pose.position_error(truth) < 0.05
            located += 1
    assert located >= poses
