"""
Bare LEDs as the five-LED rig's photos show them.

A 1 cm core in a glow at 40 % of it, stripes on every row the light reaches. Their tones are read
over core and glow, raw and as JPEG with the row time 2 % off nominal; and a map whose spacing the
row-time tolerance cannot separate is named at start.
"""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from vlp_ros.beacon.camera_settings import tone_setting_advice
from vlp_ros.beacon.reading import (BeaconReading, log_prior, MIN_CONFIDENCE, no_evidence, reading, UNMAPPED,
                                    UNMAPPED_WEIGHT)
from vlp_ros.beacon.tone import agreeing
from vlp_ros.detection import detect_lamps
from vlp_ros.pipeline.config import beacon_from_parameters, ConfigError, default_parameters, settings_from_tree
from vlp_ros.pipeline.frame import Pipeline
from vlp_ros.sim.imu import specific_force
from vlp_ros.sim.point_lamps import bare_led_scenario, PointLampLook
from vlp_ros.sim.sensor import encode_jpeg

PHOTOS = 3
# The target for photos with three or more LEDs identified.
TARGET_M = 0.05


@pytest.mark.simulation
@pytest.mark.parametrize('row_time_error, jpeg_quality', [(0.0, None), (0.02, 90), (-0.015, 90)])
def test_the_rigs_leds_are_identified_from_their_glow_and_located(row_time_error, jpeg_quality) -> None:
    scenario = bare_led_scenario('4k', photos=PHOTOS, seed=11, look=PointLampLook(),
                                 row_time_error=row_time_error, jpeg_quality=jpeg_quality)
    pipeline = Pipeline(settings_from_tree(scenario.locator_parameters(imu=True)))
    rng = np.random.default_rng(4)
    right = wrong = 0
    for index, pose in enumerate(scenario.poses):
        frame = scenario.render(index, rng)
        image = frame.image if jpeg_quality is None else cv2.imdecode(encode_jpeg(frame.image, jpeg_quality),
                                                                      cv2.IMREAD_COLOR)
        force = specific_force(pose, None, scenario.imu_noise, rng)
        result = pipeline.process(image, frame.camera, frame.start_time, force / np.linalg.norm(force))
        in_view = {t.lamp_id for t in frame.lamps if t.fully_inside}
        right += sum(i in in_view for i in result.decoded_ids)
        wrong += sum(i not in in_view for i in result.decoded_ids)
        if len(result.decoded_ids) >= 3:
            assert result.pose is not None, result.detail
            assert np.linalg.norm(result.pose.position - pose.position) < TARGET_M
    assert wrong == 0
    # Over the core alone 7 of 30 such LEDs are identified; over core and glow all but the odd one.
    assert right >= 0.9 * 5 * PHOTOS


def test_a_map_spaced_below_what_the_row_time_tolerance_separates_is_named() -> None:
    # 200 Hz apart at 4 kHz: each band reaches 60 Hz + 2 % (84 Hz) out, past the midpoint, so a lamp
    # between them that is not in the map reads as one of them.
    tight = {'a': 4000.0, 'b': 4200.0, 'c': 8000.0}
    (advice,) = tone_setting_advice(tight, 2.0e-5, 3.0e-5, frequency_tolerance=60.0, row_time_tolerance=0.02)
    assert advice.startswith('beacon.row_time_tolerance') and "'a' and 'b'" in advice and "'c'" not in advice
    # A measured row time (0.5 %) separates them.
    assert tone_setting_advice(tight, 2.0e-5, 3.0e-5, frequency_tolerance=20.0, row_time_tolerance=0.005) == []


def test_the_row_time_tolerance_is_a_parameter_checked_at_start() -> None:
    values = default_parameters()
    assert beacon_from_parameters(values).row_time_tolerance == pytest.approx(0.02)
    values['beacon.row_time_tolerance'] = 0.4
    with pytest.raises(ConfigError) as err:
        beacon_from_parameters(values)
    assert err.value.parameter == 'beacon.row_time_tolerance'


@pytest.mark.simulation
def test_every_led_of_the_rigs_photos_is_detected_at_its_centre() -> None:
    # In 4 of these 12 photos an LED's dark stripes alone span too few of the core's rows to pass for
    # round: its clipped bright rows are tried too.
    scenario = bare_led_scenario('4k', photos=12, seed=1, look=PointLampLook())
    rng = np.random.default_rng([1, 1])
    for index in range(len(scenario.poses)):
        frame = scenario.render(index, rng)
        centres = [o.center for o in detect_lamps(frame.image)]
        for truth in frame.lamps:
            assert min(np.linalg.norm(c - truth.center_pixel) for c in centres) < 3.0, (index, truth.lamp_id)


def _reading_for(lamp_id: int) -> BeaconReading:
    """Return a reading certain of ``lamp_id`` among lamps 1-3 and UNMAPPED."""
    candidates, mapped = np.array([1, 2, 3, UNMAPPED]), np.array([True, True, True, False])
    evidence = np.where(candidates == lamp_id, 30.0, 0.0)
    return reading(candidates, mapped, evidence, log_prior(mapped, UNMAPPED_WEIGHT), MIN_CONFIDENCE)


def test_a_core_taken_for_a_disc_keeps_an_id_only_where_disc_and_glow_agree() -> None:
    # On JPEG photos of the rig a clipped 3.5 kHz core taken for a disc read 2 kHz on its disc, its glow 3.5.
    assert _reading_for(2).lamp_id == 2
    assert agreeing(_reading_for(2), _reading_for(2)).lamp_id == 2
    disagreeing = agreeing(_reading_for(3), _reading_for(1))
    assert disagreeing.lamp_id is None and not disagreeing.unknown
    nothing = no_evidence(*(lambda r: (r.candidates, r.mapped, r.log_prior))(_reading_for(1)), 'no tone')
    assert agreeing(nothing, _reading_for(1)).lamp_id == 1
    assert agreeing(_reading_for(3), nothing).lamp_id == 3
