"""Scenarios match the seed paper's experiment and the robot setup; the IMU model reads gravity right."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vlp_ros.beacon.encoding import packet_length
from vlp_ros.core.gravity import STANDARD_GRAVITY
from vlp_ros.core.pose import Pose
from vlp_ros.sim.imu import specific_force
from vlp_ros.sim.render import render_frame
from vlp_ros.sim.scenarios import (as_stills, design_beacon, PAPER_DESIGN_DISTANCE, paper_scenario,
                                   robot_drive_scenario, robot_scenario, robot_tone_scenario, with_rim_markers)


@pytest.mark.parametrize('kind, focal', [('4k', 3223.0), ('1080p', 1612.0)])
def test_paper_beacon_spans_enough_packets_at_enough_rows_per_chip(kind, focal):
    scenario = paper_scenario(kind, points=1, postures=1)
    assert scenario.camera.focal == pytest.approx(focal, abs=1.0)
    rows_per_chip = 1.0 / (scenario.beacon.chip_rate * scenario.sensor.row_time)
    span = scenario.camera.focal * 2 * scenario.lamps[0].lamp.radius / PAPER_DESIGN_DISTANCE
    assert rows_per_chip >= 4.0 - 1e-3
    assert span / (rows_per_chip * packet_length(scenario.beacon.id_bits)) >= 1.3 - 1e-3
    assert scenario.lamps[0].lamp.id < 2 ** scenario.beacon.id_bits


def test_beacon_design_refuses_a_lamp_too_small_for_its_ids():
    with pytest.raises(ValueError, match='cannot hold'):
        design_beacon(30.0, 3e-5, 200, 0.5)


def test_paper_grid_postures_all_see_the_whole_lamp():
    scenario = paper_scenario('1080p', height=1.5, points=7, postures=2, seed=4)
    assert len(scenario.poses) == 7 * 7 * 2
    positions = np.array([p.position for p in scenario.poses])
    assert np.ptp(positions[:, 0]) == pytest.approx(3.0) and np.ptp(positions[:, 1]) == pytest.approx(3.0)
    assert np.allclose(positions[:, 2], 0.0)
    assert scenario.lamps[0].lamp.position[2] == 1.5
    for pose in scenario.poses[::9]:
        frame = render_frame(scenario.camera, pose, scenario.lamps, scenario.sensor, 0.0, None)
        assert frame.lamps[0].fully_inside
    tilts = np.degrees([np.arccos(p.rotation[2, 2]) for p in scenario.poses])
    centre = np.linalg.norm(positions[:, :2], axis=1) < 1e-9
    assert tilts[centre].max() <= 30.0 and tilts.max() > 10.0
    assert scenario.prior_up is None and scenario.independent_frames


def test_robot_keeps_the_static_prior_and_sees_one_to_four_lamps():
    scenario = robot_scenario(seed=2)
    ids = [s.lamp.id for s in scenario.lamps]
    assert len(set(ids)) == len(ids) and max(ids) < 2 ** scenario.beacon.id_bits
    for pose in scenario.poses:
        angle = np.arccos(np.clip(pose.up_in_camera() @ scenario.prior_up, -1.0, 1.0))
        assert angle < 0.5 * scenario.prior_tolerance
    assert np.allclose([p.position[2] for p in scenario.poses], 0.45)
    in_view = []
    for pose in scenario.poses[::40]:
        frame = render_frame(scenario.camera, pose, scenario.lamps, scenario.sensor, 0.0, None)
        in_view.append(sum(t.fully_inside for t in frame.lamps))
    assert min(in_view) >= 1 and max(in_view) <= 4 and len(set(in_view)) > 1


def test_truncated_scenario_keeps_the_first_frames():
    scenario = robot_scenario()
    short = scenario.truncated(5)
    assert len(short.poses) == 5 and short.poses[4] is scenario.poses[4]
    np.testing.assert_allclose(short.frame_times(), np.arange(5) / 30.0)


def test_accelerometer_at_rest_reads_gravity_along_map_up():
    looking_up = Pose(np.eye(3), [0.0, 0.0, 0.0])
    np.testing.assert_allclose(specific_force(looking_up), [0.0, 0.0, STANDARD_GRAVITY])
    tilted = Pose(Rotation.from_euler('xz', [30.0, 40.0], degrees=True).as_matrix(), [1.0, 2.0, 0.0])
    force = specific_force(tilted)
    np.testing.assert_allclose(force / np.linalg.norm(force), tilted.up_in_camera())


def test_accelerometer_adds_motion_and_noise():
    pose = Pose(np.eye(3), [0.0, 0.0, 0.0])
    np.testing.assert_allclose(specific_force(pose, np.array([0.5, 0.0, 0.0])), [0.5, 0.0, STANDARD_GRAVITY])
    rng = np.random.default_rng(0)
    samples = np.array([specific_force(pose, noise_std=0.05, rng=rng) for _ in range(2000)])
    assert samples.std(axis=0) == pytest.approx([0.05] * 3, rel=0.1)
    with pytest.raises(ValueError, match='random generator'):
        specific_force(pose, noise_std=0.05)


def lamps_fully_in_view(scenario, index):
    frame = render_frame(scenario.camera, scenario.poses[index], scenario.lamps, scenario.sensor, 0.0, None)
    return [t for t in frame.lamps if t.fully_inside]


@pytest.mark.simulation
def test_robot_drive_is_a_moving_robot_with_gaps():
    scenario = robot_drive_scenario()
    assert scenario.frame_rate == 10.0 and scenario.sensor.row_time == 15e-6
    assert (scenario.beacon.chip_rate, scenario.beacon.id_bits) == (16000.0, 8)
    steps = np.diff([pose.position[:2] for pose in scenario.poses], axis=0)
    np.testing.assert_allclose(np.linalg.norm(steps, axis=1) * scenario.frame_rate, 0.8, rtol=0.02)
    headings = [np.arctan2(pose.rotation[1, 1], pose.rotation[0, 1]) for pose in scenario.poses]
    turn = np.abs(np.diff(np.unwrap(headings))) * scenario.frame_rate
    assert 0.25 < turn.max() < 0.35
    spacing = {round(abs(a.lamp.position[0] - b.lamp.position[0]), 6) for a in scenario.lamps for b in scenario.lamps}
    assert 2.4 in spacing and 1.2 not in spacing
    in_view = [lamps_fully_in_view(scenario, k) for k in range(len(scenario.poses))]
    gaps = sum(1 for seen in in_view if not seen)
    assert 0.03 * len(in_view) < gaps < 0.25 * len(in_view)
    # ~77 px across at 4 rows per chip: 0.8 of a 24-chip packet per frame.
    diameters = [2 * np.sqrt(t.ellipse[2] * t.ellipse[3]) for seen in in_view for t in seen]
    assert 70.0 < np.median(diameters) < 85.0
    rows_per_chip = 1.0 / (scenario.beacon.chip_rate * scenario.sensor.row_time)
    assert np.median(diameters) / (rows_per_chip * packet_length(8)) == pytest.approx(0.8, abs=0.05)


def test_robot_tone_lamps_span_two_to_six_periods_and_are_300_hz_apart():
    scenario = robot_tone_scenario(frames=6)
    frequencies = sorted(s.lamp.frequency for s in scenario.lamps)
    assert frequencies[0] == 2000.0 and frequencies[-1] == 5300.0 and set(np.diff(frequencies)) == {300.0}
    params = scenario.locator_parameters(False)
    assert params['beacon'] == {'mode': 'tone', 'row_time': 15e-6, 'exposure': 20e-6}
    assert params['leds']['lamp_1']['frequency'] == 2000.0
    # A frontal lamp spans its image diameter in rows.
    span_rows = np.median([2 * np.sqrt(t.ellipse[2] * t.ellipse[3]) for k in range(6)
                           for t in lamps_fully_in_view(scenario, k)])
    periods = span_rows * scenario.sensor.row_time * np.array([2000.0, 5300.0])
    assert 2.0 < periods[0] < 2.6 and 5.6 < periods[1] < 6.6


def test_rim_markers_and_stills_keep_everything_else():
    scenario = paper_scenario('1080p', points=2, postures=1)
    rim = with_rim_markers(scenario)
    lamp = rim.lamps[0]
    assert lamp.lamp.marker_distance == pytest.approx(0.9 * lamp.lamp.radius)
    assert lamp.marker_radius == pytest.approx(0.1 * lamp.lamp.radius)
    assert lamp.lamp.marker_angle == scenario.lamps[0].lamp.marker_angle and lamp.waveform == scenario.lamps[0].waveform
    stills = as_stills(rim, 0.1)
    np.testing.assert_allclose(np.diff(stills.frame_times()), 0.1)
    assert 'continuity' not in stills.locator_parameters(True)
    assert scenario.locator_parameters(True)['continuity'] == {'max_age': 0.0}
    with pytest.raises(ValueError, match='marker distance'):
        with_rim_markers(scenario, 1.2)
