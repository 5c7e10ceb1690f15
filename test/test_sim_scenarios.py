"""Scenarios match the seed paper's experiment and the robot setup; the IMU model reads gravity right."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vlp_ros.beacon.encoding import packet_length
from vlp_ros.pose import Pose
from vlp_ros.gravity import STANDARD_GRAVITY
from vlp_ros.sim.imu import specific_force
from vlp_ros.sim.render import render_frame
from vlp_ros.sim.scenarios import PAPER_DESIGN_DISTANCE, design_beacon, paper_scenario, robot_scenario


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
