"""Simulated recordings read back through rosbags, the project's bag reader, and the locator's settings."""
import fcntl
import os
from pathlib import Path
import pty
import struct
import subprocess
import sys
import termios

import numpy as np
import pytest
from rosbags.rosbag2 import Reader

from vlp_ros.bags.reader import Bag
from vlp_ros.beacon.encoding import packet_waveform
from vlp_ros.core.camera import CameraModel
from vlp_ros.core.gravity import STANDARD_GRAVITY
from vlp_ros.core.lamp_map import Lamp
from vlp_ros.core.pose import Pose
from vlp_ros.pipeline.config import default_parameters, flatten_parameters, settings_from_parameters
from vlp_ros.sim import __main__ as cli
from vlp_ros.sim.bag_writer import TYPESTORE
from vlp_ros.sim.recording import EPOCH_NS, record, write_params
from vlp_ros.sim.render import SimLamp
from vlp_ros.sim.scenarios import BeaconDesign, Scenario
from vlp_ros.sim.sensor import SensorModel

import yaml

TOPICS = {'/image_raw': 'sensor_msgs/msg/Image', '/camera_info': 'sensor_msgs/msg/CameraInfo',
          '/imu': 'sensor_msgs/msg/Imu', '/ground_truth/pose': 'geometry_msgs/msg/PoseStamped'}


def tiny_scenario(bayer=None) -> Scenario:
    camera = CameraModel(96, 64, [[120.0, 0.0, 47.5], [0.0, 120.0, 31.5], [0.0, 0.0, 1.0]], [-0.05, 0.01, 0, 0, 0])
    sensor = SensorModel(row_time=1.0 / (30 * 64), exposure=1e-4, bayer=bayer)
    beacon = BeaconDesign(chip_rate=2000.0, id_bits=4, depth=0.6)
    lamp = Lamp('lamp_a', 6, [0.0, 0.0, 1.0], 0.1, marker_angle=0.5, marker_distance=0.08)
    sim = SimLamp(lamp, packet_waveform(6, 2000.0, 0.6, 4))
    poses = [Pose(np.eye(3), [0.01 * k, 0.0, 0.0]) for k in range(3)]
    accelerations = [np.array([0.1 * k, 0.0, 0.0]) for k in range(3)]
    return Scenario('tiny', camera, sensor, [sim], poses, accelerations, beacon,
                    prior_up=np.array([0.0, 0.0, 1.0]), imu_noise=0.0)


@pytest.mark.parametrize('storage', ['sqlite3', 'mcap'])
def test_bag_round_trip_has_every_topic_with_matching_stamps(tmp_path, storage):
    scenario = tiny_scenario()
    frames = record(scenario, tmp_path / 'bag', storage, True, np.random.default_rng(0))
    assert frames == 3
    expected_stamps = [EPOCH_NS + int(round(t * 1e9)) for t in scenario.frame_times()]
    with Reader(tmp_path / 'bag') as reader:
        assert {c.topic: c.msgtype for c in reader.connections} == TOPICS
        seen = {topic: [] for topic in TOPICS}
        for connection, timestamp, raw in reader.messages():
            message = TYPESTORE.deserialize_cdr(raw, connection.msgtype)
            stamp = message.header.stamp.sec * 1_000_000_000 + message.header.stamp.nanosec
            assert stamp == timestamp
            seen[connection.topic].append((timestamp, message))
    for topic, messages in seen.items():
        assert [t for t, _ in messages] == expected_stamps, topic
    image = seen['/image_raw'][1][1]
    assert (image.width, image.height, image.encoding, image.step) == (96, 64, 'bgr8', 96 * 3)
    assert image.header.frame_id == 'camera_optical_frame'
    info = seen['/camera_info'][0][1]
    np.testing.assert_allclose(info.k.reshape(3, 3), scenario.camera.K)
    np.testing.assert_allclose(info.d, scenario.camera.D)
    np.testing.assert_allclose(info.p.reshape(3, 4)[:, :3], scenario.camera.K)
    assert info.distortion_model == 'plumb_bob' and info.header.frame_id == 'camera_optical_frame'
    truth = seen['/ground_truth/pose'][2][1]
    assert truth.header.frame_id == 'map'
    assert (truth.pose.position.x, truth.pose.orientation.w) == pytest.approx((0.02, 1.0))
    accel = seen['/imu'][1][1].linear_acceleration
    assert (accel.x, accel.y, accel.z) == pytest.approx((0.1, 0.0, STANDARD_GRAVITY))


def test_bag_offers_sensor_qos_for_images_and_reliable_camera_info(tmp_path):
    record(tiny_scenario(bayer='grbg'), tmp_path / 'bag', 'mcap', False, np.random.default_rng(0))
    with Bag(tmp_path / 'bag') as bag:
        topics = bag.topics
        assert set(topics) == set(TOPICS) - {'/imu'}
        assert topics['/image_raw'].qos.reliability == 'BEST_EFFORT'
        assert topics['/camera_info'].qos.reliability == 'RELIABLE'
        assert topics['/image_raw'].message_count == 3
    with Reader(tmp_path / 'bag') as reader:
        connection = next(c for c in reader.connections if c.topic == '/image_raw')
        _, _, raw = next(reader.messages(connections=[connection]))
        image = TYPESTORE.deserialize_cdr(raw, connection.msgtype)
        assert (image.encoding, image.step, image.data.size) == ('bayer_grbg8', 96, 96 * 64)


def test_params_file_configures_the_locator(tmp_path):
    scenario = tiny_scenario()
    write_params(tmp_path / 'params.yaml', scenario, imu=True)
    document = yaml.safe_load((tmp_path / 'params.yaml').read_text())
    values = default_parameters()
    values.update(flatten_parameters(document['vlp_locator']['ros__parameters']))
    settings = settings_from_parameters(values)
    lamp = settings.lamps.get(6)
    np.testing.assert_allclose(lamp.marker_position(), scenario.lamps[0].lamp.marker_position())
    assert lamp.radius == 0.1 and settings.beacon.chip_rate == 2000.0 and settings.beacon.id_bits == 4
    assert settings.beacon.row_time == pytest.approx(scenario.sensor.row_time)
    np.testing.assert_allclose(settings.prior_up, [0.0, 0.0, 1.0])
    assert settings.imu_enabled


def test_command_line_writes_bag_and_params(tmp_path, capsys):
    out = tmp_path / 'out'
    status = cli.main(['--scenario', 'paper', '--camera', '1080p', '--points', '2', '--postures', '1',
                       '--out', str(out), '--storage', 'mcap', '--imu', '--bayer', 'rggb', '--seed', '3'])
    assert status == 0
    assert 'wrote' in capsys.readouterr().out
    with Reader(out / 'paper_1080p') as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
    assert counts == dict.fromkeys(TOPICS, 4)
    values = default_parameters()
    values.update(flatten_parameters(
        yaml.safe_load((out / 'params.yaml').read_text())['vlp_locator']['ros__parameters']))
    settings = settings_from_parameters(values)
    assert settings.imu_enabled and settings.prior_up is None and settings.continuity_max_age == 0.0
    assert settings.lamps.ids == [11] and settings.beacon.id_bits == 4
    assert cli.main(['--scenario', 'paper', '--out', str(out)]) == 2
    assert 'exists already' in capsys.readouterr().err


@pytest.mark.parametrize('arguments, message', [
    (['--scenario', 'robot', '--camera', '4k'], '--camera: only valid with --scenario paper'),
    (['--scenario', 'paper', '--frames', '0'], '--frames must be at least 1'),
    (['--scenario', 'paper', '--depth', '1.5'], '--depth must be in (0, 1]'),
    (['--scenario', 'paper', '--height', '-2'], '--height must be positive'),
])
def test_command_line_rejects_bad_options_in_one_line(tmp_path, capsys, arguments, message):
    assert cli.main(arguments + ['--out', str(tmp_path / 'out')]) == 2
    error = capsys.readouterr().err
    assert message in error and len(error.strip().splitlines()) == 1
    assert not (tmp_path / 'out').exists()


def test_command_line_usage_error_has_no_traceback(tmp_path):
    result = subprocess.run([sys.executable, '-m', 'vlp_ros.sim', '--scenario', 'office', '--out', str(tmp_path)],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2
    assert 'invalid choice' in result.stderr and 'Traceback' not in result.stderr


def _command_line_stderr(out: Path, terminal: bool) -> bytes:
    """Run the command line on a small scenario; what it wrote to stderr, a pipe or a pseudo-terminal."""
    command = [sys.executable, '-m', 'vlp_ros.sim', '--scenario', 'paper', '--camera', '1080p', '--points', '2',
               '--postures', '1', '--out', str(out)]
    if not terminal:
        return subprocess.run(command, capture_output=True, timeout=300, check=True).stderr
    controller, terminal_end = pty.openpty()
    # A terminal 80 columns wide: tqdm draws nothing in a 0-column one.
    fcntl.ioctl(terminal_end, termios.TIOCSWINSZ, struct.pack('HHHH', 24, 80, 0, 0))
    with subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=terminal_end) as process:
        os.close(terminal_end)
        chunks = []
        while True:
            try:
                chunk = os.read(controller, 4096)
            except OSError:  # EIO: the process closed its end
                break
            if not chunk:
                break
            chunks.append(chunk)
    os.close(controller)
    assert process.returncode == 0
    return b''.join(chunks)


def test_command_line_shows_progress_on_a_terminal_and_none_in_a_log(tmp_path):
    assert b'4/4' in _command_line_stderr(tmp_path / 'terminal', terminal=True)
    logged = _command_line_stderr(tmp_path / 'log', terminal=False)
    assert b'\r' not in logged and b'4/4' not in logged
