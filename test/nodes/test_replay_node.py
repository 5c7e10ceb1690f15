"""The `replay` executable as a real process over DDS: what arrives, on which topic, in which order."""
from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
import time

from conftest import spin_until
import pytest
from replay_bags import (CAMERA_INFO, camera_info_data, chatter, copy_bag, IMAGE, image_data, Recorded, SHARED_BAGS,
                         sqlite3_topic_data, T0_NS, write_bag, write_split_bag)

pytestmark = pytest.mark.dds

TALKER_DB = SHARED_BAGS / 'talker_sqlite3' / 'talker.db3'
TALKER_MCAP = SHARED_BAGS / 'talker_mcap'
TALKER_START_NS = 1585866235112411371  # starting_time in its metadata.yaml


class Received(list):
    """(arrival time, message) pairs of one subscription."""

    def messages(self) -> list:
        return [message for _, message in self]

    def arrivals(self) -> list[float]:
        return [arrival for arrival, _ in self]


def subscribe(node, topic: str, msg_type, reliable: bool = True) -> Received:
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    received = Received()
    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT)
    node.create_subscription(msg_type, topic, lambda msg: received.append((time.monotonic(), msg)), qos)
    return received


def run_to_end(node, replay, done: Callable[[], bool] = lambda: True, timeout: float = 60.0) -> int:
    """Spin until the replay exits and ``done()`` holds; the replay's exit status."""
    assert spin_until(node, lambda: replay.popen.poll() is not None and done(), timeout), replay.output()
    assert 'Traceback' not in replay.output()
    return replay.popen.returncode


def play_until(node, replay, done: Callable[[], bool], timeout: float = 60.0) -> None:
    """Spin until ``done()``, then stop the replay: its final wait for acknowledgements would only cost time."""
    assert spin_until(node, done, timeout), replay.output()
    assert replay.interrupt() == 0
    assert 'Traceback' not in replay.output()


def deserialized(data: list[bytes], msg_type) -> list:
    from rclpy.serialization import deserialize_message
    return [deserialize_message(raw, msg_type) for raw in data]


@pytest.mark.parametrize('name', ['talker_sqlite3', 'talker_mcap'])
def test_real_recordings_arrive_complete_in_order_and_byte_exact(start_process, test_node, name: str) -> None:
    from rcl_interfaces.msg import Log
    from std_msgs.msg import String
    expected = {'/topic': deserialized(sqlite3_topic_data(TALKER_DB, '/topic'), String),
                '/recorded_rosout': deserialized(sqlite3_topic_data(TALKER_DB, '/rosout'), Log)}
    # The recorded /rosout goes elsewhere: the live one carries the logs of the nodes running now.
    received = {'/topic': subscribe(test_node, '/topic', String),
                '/recorded_rosout': subscribe(test_node, '/recorded_rosout', Log)}
    replay = start_process('replay', SHARED_BAGS / name, '--rate', '5', '--remap', '/rosout:=/recorded_rosout')
    assert run_to_end(test_node, replay,
                      lambda: all(len(received[t]) >= len(expected[t]) for t in expected)) == 0
    assert {topic: messages.messages() for topic, messages in received.items()} == expected
    assert all(len(messages) == 10 for messages in expected.values())
    assert 'replay: done: published 20 messages' in replay.stderr()
    # Its stderr is a file: no progress bar, whose carriage returns would garble the log.
    assert b'\r' not in replay.stderr_path.read_bytes()


def test_topic_selection_remapping_and_start_offset_by_options_or_parameters(start_process, test_node) -> None:
    from std_msgs.msg import String
    bag = SHARED_BAGS / 'talker_sqlite3'
    expected = deserialized(sqlite3_topic_data(TALKER_DB, '/topic', TALKER_START_NS + 2 * 10**9), String)
    assert 0 < len(expected) < 10
    by_options = subscribe(test_node, '/by_options', String)
    by_parameters = subscribe(test_node, '/by_parameters', String)
    original = subscribe(test_node, '/topic', String)
    replays = [
        start_process('replay', bag, '--topics', '/topic', '/nope', '--remap', '/topic:=/by_options',
                      '--start-offset', '2', '--rate', '5'),
        start_process('replay', '--ros-args', '-p', f'bag:={bag}', '-p', "topics:=['/topic', '/nope']",
                      '-p', "remap:=['/topic:=/by_parameters']", '-p', 'start_offset:=2', '-p', 'rate:=5.0')]
    for replay, received in zip(replays, [by_options, by_parameters]):
        play_until(test_node, replay, lambda: len(received) >= len(expected))
        assert received.messages() == expected
        assert 'topic /nope is not in the bag' in replay.stderr()
    assert original == []


def test_rate_scales_playback_time(start_process, test_node, tmp_path: Path) -> None:
    """
    A message never arrives before the replay's schedule allows, whatever the machine's speed.

    Message k no earlier than (its bag time - the first's) / rate after the replay was started.
    (How late it comes depends on the machine, so no upper bound is asserted.)
    """
    bag = write_bag(tmp_path / 'bag', chatter(10, 0.1))  # 0.9 s of messages
    from std_msgs.msg import String
    fast = subscribe(test_node, '/fast', String)
    slow = subscribe(test_node, '/slow', String)
    launched = time.monotonic()  # the system-wide monotonic clock, which the replay's schedule runs on too
    fast_replay = start_process('replay', bag, '--rate', '2', '--remap', '/chatter:=/fast')
    slow_replay = start_process('replay', bag, '--rate', '0.25', '--remap', '/chatter:=/slow')
    play_until(test_node, slow_replay, lambda: len(slow) >= 10)
    play_until(test_node, fast_replay, lambda: len(fast) >= 10)
    expected = [f'hello {k}' for k in range(10)]
    assert [m.data for m in fast.messages()] == expected and [m.data for m in slow.messages()] == expected
    for received, rate in ((fast, 2.0), (slow, 0.25)):
        for k, arrival in enumerate(received.arrivals()):
            assert arrival - launched >= k * 0.1 / rate, (rate, k)


def test_clock_follows_bag_time(start_process, test_node, tmp_path: Path) -> None:
    from rosgraph_msgs.msg import Clock
    from std_msgs.msg import String
    bag = write_bag(tmp_path / 'bag', chatter(10, 0.1))
    clock = subscribe(test_node, '/clock', Clock, reliable=False)
    played = subscribe(test_node, '/chatter', String)
    replay = start_process('replay', bag, '--clock', '20')
    play_until(test_node, replay, lambda: len(played) >= 10 and len(clock) >= 2)
    times = [m.clock.sec * 10**9 + m.clock.nanosec for m in clock.messages()]
    assert times == sorted(times)
    # Within the bag's time however late the replay runs: 0.9 s of messages.
    assert T0_NS <= times[0] and times[-1] <= T0_NS + 900_000_000


def test_loop_plays_the_bag_again_after_each_delay_until_interrupted(start_process, test_node,
                                                                     tmp_path: Path) -> None:
    from std_msgs.msg import String
    bag = write_bag(tmp_path / 'bag', chatter(3, 0.05))
    received = subscribe(test_node, '/chatter', String)
    launched = time.monotonic()
    replay = start_process('replay', bag, '--loop', '--delay', '1.0')
    play_until(test_node, replay, lambda: len(received) >= 7)
    assert [m.data for m in received.messages()[:7]] == [f'hello {k % 3}' for k in range(7)]
    # Each pass waits its delay first, then plays 0.1 s: pass k's first message is no earlier than
    # (k + 1) delays and k passes after the start, however fast the machine is.
    arrivals = received.arrivals()
    for first_of_pass, passes in ((0, 0), (3, 1), (6, 2)):
        assert arrivals[first_of_pass] - launched >= (passes + 1) * 1.0 + passes * 0.1, first_of_pass


def test_split_and_compressed_bags_play_every_message(start_process, test_node, tmp_path: Path) -> None:
    from std_msgs.msg import String
    messages = chatter(6, 0.02)
    bags = {
        'split_sqlite3_v9': write_split_bag(tmp_path / 'split', messages, parts=3),
        'zstd_file_mcap_v8': write_bag(tmp_path / 'file', messages, storage='mcap', version=8, compression='file'),
        'zstd_message_sqlite3_v9': write_bag(tmp_path / 'message', messages, compression='message'),
    }
    received = {layout: subscribe(test_node, f'/{layout}', String) for layout in bags}
    replays = {layout: start_process('replay', bag, '--remap', f'/chatter:=/{layout}') for layout, bag in bags.items()}
    for layout, replay in replays.items():
        play_until(test_node, replay, lambda: len(received[layout]) >= len(messages))
        assert received[layout].messages() == deserialized([m.data for m in messages], String), layout


def test_types_without_installed_module_are_skipped_with_one_warning(start_process, test_node,
                                                                     tmp_path: Path) -> None:
    from std_msgs.msg import String
    exotic = [Recorded('/exotic', 'foo_msgs/msg/Bar', m.timestamp_ns + 1, m.data) for m in chatter(3, 0.05)]
    bag = write_bag(tmp_path / 'bag', sorted(chatter(3, 0.05) + exotic, key=lambda m: m.timestamp_ns))
    received = subscribe(test_node, '/chatter', String)
    replay = start_process('replay', bag)
    play_until(test_node, replay, lambda: len(received) >= 3)
    assert len(received) == 3
    assert replay.stderr().count('foo_msgs/msg/Bar is not installed') == 1


def _corrupt(path: Path, at: int) -> Path:
    data = bytearray(path.read_bytes())
    data[at: at + 64] = b'\xff' * 64
    path.write_bytes(bytes(data))
    return path


UNPLAYABLE = {
    'missing path': (lambda d: d / 'missing', 'does not exist'),
    'directory without metadata.yaml': (lambda d: d, 'has no metadata.yaml'),
    'empty bag': (lambda d: write_bag(d / 'b', []), 'is empty'),
    'corrupt db3': (lambda d: _corrupt(copy_bag(SHARED_BAGS / 'talker_sqlite3', d / 'b') / 'talker.db3', 0).parent,
                    'cannot be opened'),
    'corrupt mcap': (lambda d: _corrupt(copy_bag(SHARED_BAGS / 'talker_mcap', d / 'b') / 'talker.mcap', 4000).parent,
                     'cannot be opened'),
    'unknown storage': (lambda d: _replace_in(copy_bag(SHARED_BAGS / 'talker_mcap', d / 'b') / 'metadata.yaml',
                                              'storage_identifier: mcap', 'storage_identifier: rosbag_v1'),
                        "'rosbag_v1' not supported"),
    'no installed type': (lambda d: write_bag(d / 'b', [Recorded('/x', 'foo_msgs/msg/Bar', T0_NS, b'')]),
                          'no selected topic has an installed message type'),
}


def _replace_in(path: Path, old: str, new: str) -> Path:
    path.write_text(path.read_text().replace(old, new))
    return path.parent


def test_unplayable_bags_end_with_one_clear_line_and_status_1(start_process, tmp_path: Path) -> None:
    replays = {}
    for index, (case, (make, _)) in enumerate(UNPLAYABLE.items()):
        (tmp_path / str(index)).mkdir()
        replays[case] = start_process('replay', make(tmp_path / str(index)))
    for case, replay in replays.items():
        assert replay.wait(timeout=60.0) == 1, case
        errors = [line for line in replay.stderr().splitlines() if line.startswith('replay: error:')]
        assert len(errors) == 1 and UNPLAYABLE[case][1] in errors[0], (case, replay.stderr())
        assert 'Traceback' not in replay.output(), case


BAD_OPTIONS = [
    ([TALKER_MCAP, '--rate', 'fast'], 'invalid float value'), ([TALKER_MCAP, '--rate', '0'], 'rate must be positive'),
    ([TALKER_MCAP, '--remap', '/a'], 'FROM:=TO'), ([], 'no bag given'),
    ([TALKER_MCAP, '--ros-args', '-p', 'rate:=fast'], "parameter 'rate' must be a number")]


def test_bad_options_are_usage_errors_with_status_2(start_process) -> None:
    replays = [start_process('replay', *args) for args, _ in BAD_OPTIONS]
    for replay, (args, message) in zip(replays, BAD_OPTIONS):
        assert replay.wait(timeout=60.0) == 2, args
        assert message in replay.stderr() and 'usage: replay' in replay.stderr(), (args, replay.stderr())
        assert 'Traceback' not in replay.output(), args


def test_deterministic_mode_publishes_each_frame_after_the_previous_answer(start_process, test_node,
                                                                           tmp_path: Path) -> None:
    """Frames 100 s apart play in seconds, each after the answer to the previous one (or the timeout)."""
    from geometry_msgs.msg import PoseStamped
    from sensor_msgs.msg import CameraInfo, Image
    from std_msgs.msg import Header
    stamps = [T0_NS + k * 100 * 10**9 for k in range(6)]
    recorded = []
    for stamp in stamps:
        recorded += [Recorded('/camera/camera_info', CAMERA_INFO, stamp, camera_info_data(stamp)),
                     Recorded('/camera/image_raw', IMAGE, stamp + 1, image_data(stamp))]
    bag = write_bag(tmp_path / 'bag', recorded)
    # Answers come 0.2 s after a frame; the timeout leaves a slow machine 2.8 s more to send them.
    silent_frame, answer_delay, timeout = 3, 0.2, 3.0
    replay = start_process('replay', bag, '--deterministic', '--answer-timeout', str(timeout))
    processed = test_node.create_publisher(Header, 'vlp/processed', 10)
    poses = test_node.create_publisher(PoseStamped, 'vlp/pose', 10)
    time.sleep(1.5)  # the replay is up and must wait for the frame subscriber not to lose frame 0
    infos = subscribe(test_node, '/camera/camera_info', CameraInfo)
    frames = subscribe(test_node, '/camera/image_raw', Image)
    answered_at: dict[int, float] = {}

    def echo() -> bool:
        """Answer each frame ``answer_delay`` after it arrived, alternating the two answer topics."""
        for index, (arrival, image) in enumerate(frames):
            if index in answered_at or index == silent_frame or time.monotonic() < arrival + answer_delay:
                continue
            answered_at[index] = time.monotonic()
            if index % 2:
                poses.publish(PoseStamped(header=image.header))
            else:
                processed.publish(Header(stamp=image.header.stamp, frame_id='ok'))
        return replay.popen.poll() is not None

    assert spin_until(test_node, echo, 40.0), replay.output()
    assert replay.popen.returncode == 0 and 'Traceback' not in replay.output()
    assert [(f.header.stamp.sec, f.header.stamp.nanosec) for f in frames.messages()] == [
        (s // 10**9, s % 10**9) for s in stamps]
    assert len(infos) == len(stamps)
    arrivals = frames.arrivals()
    for index in range(1, len(stamps)):
        if index - 1 == silent_frame:
            # The silent frame went out after the answer before it, and waited the whole timeout.
            assert arrivals[index] >= answered_at[index - 2] + timeout
        else:
            assert arrivals[index] >= answered_at[index - 1]
    assert 'frames answered: 5, unanswered: 1' in replay.stderr()


def test_own_arguments_keep_bare_remap_rules_and_ros_sections_go_to_rclpy() -> None:
    from vlp_ros.nodes.replay import split_ros_arguments
    own, ros = split_ros_arguments(['replay', 'bag', '--remap', '/a:=/b', '--ros-args', '-r', '__node:=n',
                                    '-p', 'rate:=2.0', '--', '--loop', '--ros-args', '--log-level', 'warn'])
    assert own == ['replay', 'bag', '--remap', '/a:=/b', '--loop']
    assert ros == ['--ros-args', '-r', '__node:=n', '-p', 'rate:=2.0', '--ros-args', '--log-level', 'warn']


def test_message_classes_are_found_for_installed_types_only() -> None:
    from sensor_msgs.msg import Image
    from std_msgs.msg import String
    from vlp_ros.nodes.replay import message_class
    assert message_class('sensor_msgs/msg/Image') is Image
    assert message_class('std_msgs/String') is String
    for missing in ['foo_msgs/msg/Bar', 'std_msgs/msg/Nope', 'std_msgs/msg/rclpy', 'garbage']:
        assert message_class(missing) is None, missing
