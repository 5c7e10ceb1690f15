"""
The start-up advice on camera settings.

Silent inside the limits the beacon benchmark reads reliably, specific (setting, value, lamps)
outside them.
"""
from vlp_ros.beacon.camera_settings import packet_setting_advice, tone_setting_advice
from vlp_ros.pipeline.config import settings_from_tree
from vlp_ros.sim.scenarios import robot_scenario

TONES = {'hall': 1000.0, 'door': 5000.0, 'desk': 8000.0}


def test_settings_inside_the_limits_give_no_advice() -> None:
    assert packet_setting_advice(8000.0, 1.5e-5, None) == []
    assert packet_setting_advice(8000.0, 1.5e-5, 1.0e-4) == []
    assert tone_setting_advice(TONES, 2.0e-5, 3.0e-5) == []


def test_the_simulated_robot_is_configured_within_the_limits() -> None:
    beacon = settings_from_tree(robot_scenario().locator_parameters(imu=True)).beacon
    assert packet_setting_advice(beacon.chip_rate, beacon.row_time, beacon.exposure) == []


def test_too_few_rows_per_chip_name_the_chip_rate() -> None:
    (advice,) = packet_setting_advice(30000.0, 1.5e-5, None)
    assert advice.startswith('beacon.chip_rate') and '2.2 rows per chip' in advice


def test_an_exposure_over_a_chip_names_the_exposure() -> None:
    (advice,) = packet_setting_advice(8000.0, 1.5e-5, 2.0e-4)
    assert advice.startswith('beacon.exposure') and '1.6 chips' in advice


def test_tone_mode_without_the_exposure_asks_for_it() -> None:
    (advice,) = tone_setting_advice(TONES, 2.0e-5, None)
    assert 'beacon.exposure is 0' in advice


def test_an_exposure_shorter_than_a_row_is_reported() -> None:
    (advice,) = tone_setting_advice(TONES, 2.0e-5, 1.0e-5)
    assert 'shorter than beacon.row_time' in advice


def test_fast_tones_at_slow_rows_name_the_lamps() -> None:
    (advice,) = tone_setting_advice(TONES, 4.0e-5, 4.0e-5)
    # 8 kHz at 40 us: 3.1 rows per period; 5 kHz: 5 rows.
    assert "'desk' (3.1 rows)" in advice and 'door' not in advice and 'hall' not in advice


def test_an_exposure_of_about_whole_periods_names_the_washed_out_lamps() -> None:
    # 200 us is one period of 5 kHz and 1.6 of 8 kHz (|sinc| 0.19); 1 kHz keeps 94 % of its contrast.
    (advice,) = tone_setting_advice(TONES, 2.0e-5, 2.0e-4)
    assert "'door' (0 %" in advice and "'desk' (19 %" in advice and 'hall' not in advice


def test_tone_lamps_closer_than_a_row_time_error_allows_are_named() -> None:
    # 2 % of the row time moves 8000 Hz by 160 Hz: lamps 250 Hz apart cannot be told apart there.
    (advice,) = tone_setting_advice({'a': 2000.0, 'b': 2300.0, 'c': 8000.0, 'd': 8250.0}, 2.0e-5, 3.0e-5)
    assert "'c' and 'd'" in advice and "'a'" not in advice
