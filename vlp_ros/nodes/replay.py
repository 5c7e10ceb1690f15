"""
The `replay` node: plays rosbag2 recordings into the ROS graph, like `ros2 bag play`.

    replay PATH [--topics T [T ...]] [--remap FROM:=TO] [--rate R] [--loop]
                [--start-offset S] [--delay S] [--clock [HZ]]
                [--deterministic [--answer-timeout S]] [--ros-args ...]

Every option is also a ROS parameter of the same name (underscores, `bag` for
PATH, `clock` in Hz with 0 for off); the command line wins. Messages go out as
recorded bytes with the recorded QoS. In deterministic mode each camera frame
waits for the locator's answer (same stamp on vlp/pose or vlp/processed) or
`answer_timeout`, so results do not depend on machine speed.
"""
from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
import importlib
import sys
import time

from geometry_msgs.msg import PoseStamped
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.duration import Duration
from rclpy.exceptions import ParameterException
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.publisher import Publisher
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.time import Time
from rosgraph_msgs.msg import Clock
from std_msgs.msg import Header
from tqdm import tqdm

from vlp_ros.bags.playback_plan import (DEFAULT_CLOCK_HZ, playback_origin, PlaybackOptions, PlaybackTally,
                                        seconds_played, select_topics, Timeline)
from vlp_ros.bags.reader import Bag, BagMessage, BagTopic, FRAME_TYPES, header_stamp
from vlp_ros.nodes.lifecycle import run_node

DISCOVERY_WAIT_S = 5.0  # at most, for subscribers to match first (a lost announcement costs 3 s)
DISCOVERY_SETTLE_S = 0.5  # once some matched, this long without another match ends the wait
MATCH_SETTLE_S = 0.3  # see _wait_for_subscribers
FRAME_SUBSCRIBER_WAIT_S = 10.0  # deterministic mode: for the frame topics' first subscriber
ACK_WAIT_S = 4.0  # at the end, for reliable subscribers' acknowledgements (they follow 3 s heartbeats)
PROGRESS_PERIOD_S = 0.5
PROGRESS_FORMAT = 'replay: {desc}, {n:.1f}/{total:.1f} s ({percentage:.0f}%) |{bar}|'
SPIN_SLICE_S = 0.05
# Answers only need to arrive; best effort matches publishers of either reliability.
ANSWER_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
CLOCK_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)  # rclcpp::ClockQoS
NUMBER_PARAMETERS = {'rate': 1.0, 'start_offset': 0.0, 'delay': 0.0, 'clock': 0.0, 'answer_timeout': 2.0}


def command_line_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='replay', description='Play a rosbag2 directory into the ROS graph.',
        epilog='Each option can also be set as a ROS parameter (--ros-args -p rate:=2.0); '
               'the command line wins.')
    parser.add_argument('bag', nargs='?', metavar='PATH', help='rosbag2 directory (sqlite3 or mcap)')
    parser.add_argument('--topics', nargs='+', metavar='T', help='play only these topics')
    parser.add_argument('--remap', action='append', metavar='FROM:=TO', help='publish topic FROM as TO')
    parser.add_argument('--rate', type=float, metavar='R', help='playback speed factor (default 1)')
    parser.add_argument('--loop', action='store_true', default=None, help='play again and again')
    parser.add_argument('--start-offset', type=float, metavar='S', help='start S seconds into the bag')
    parser.add_argument('--delay', type=float, metavar='S', help='wait S seconds before playing')
    parser.add_argument('--clock', type=float, nargs='?', const=DEFAULT_CLOCK_HZ, metavar='HZ',
                        help=f'publish /clock at HZ (default {DEFAULT_CLOCK_HZ:g})')
    parser.add_argument('--deterministic', action='store_true', default=None,
                        help='ignore bag timing: publish each camera frame once the previous one '
                             'was answered on vlp/pose or vlp/processed (or timed out)')
    parser.add_argument('--answer-timeout', type=float, metavar='S',
                        help='deterministic mode: give up waiting for an answer after S seconds (default 2)')
    return parser


def split_ros_arguments(argv: Sequence[str]) -> tuple[list[str], list[str]]:
    """
    Split ``argv`` into the program's own arguments and the `--ros-args ... [--]` sections for rclpy.

    rclpy.utilities.remove_ros_args would also swallow bare FROM:=TO words (the
    pre-Foxy remapping syntax), which are the values of --remap here.
    """
    own: list[str] = []
    ros: list[str] = []
    in_ros = False
    for arg in argv:
        if arg == '--ros-args':
            in_ros = True
            ros.append(arg)
        elif in_ros and arg == '--':
            in_ros = False
        else:
            (ros if in_ros else own).append(arg)
    return own, ros


def message_class(msgtype: str) -> type | None:
    """Return the installed Python class of a ROS message type name such as 'sensor_msgs/msg/Image'."""
    parts = msgtype.split('/')
    if len(parts) == 2:  # pre-Dashing spelling 'pkg/Type'
        parts.insert(1, 'msg')
    if len(parts) != 3:
        return None
    package, kind, name = parts
    try:
        module = importlib.import_module(f'{package}.{kind}')
    except ImportError:
        return None
    cls = getattr(module, name, None)
    return cls if hasattr(cls, 'get_fields_and_field_types') else None


def offered_qos_profile(topic: BagTopic) -> QoSProfile:
    return QoSProfile(depth=topic.qos.depth,
                      reliability=ReliabilityPolicy[topic.qos.reliability],
                      durability=DurabilityPolicy[topic.qos.durability])


class Replay(Node):

    def __init__(self, command_line: argparse.Namespace) -> None:
        super().__init__('vlp_replay')
        self.options = self._options(command_line)
        self._executor = SingleThreadedExecutor(context=self.context)
        self._executor.add_node(self)
        self._bag_publishers: dict[str, Publisher] = {}
        self._skip_reasons: dict[str, str] = {}  # selected topics read and counted, not published
        self._tally = PlaybackTally({})
        self._published = 0
        self._total = 0
        self._answered = 0
        self._unanswered = 0
        self._pending_stamp: tuple[int, int] | None = None
        self._last_bag_ns = 0
        self._latest_bag_ns = 0  # the bag's last message: bag time never runs past it
        self._timeline: Timeline | None = None
        self._loop_start = 0.0

    def _options(self, command_line: argparse.Namespace) -> PlaybackOptions:
        values = {
            'bag': self.declare_parameter('bag', '').value,
            'topics': self.declare_parameter('topics', Parameter.Type.STRING_ARRAY).value or (),
            'remap': self.declare_parameter('remap', Parameter.Type.STRING_ARRAY).value or (),
            'loop': self.declare_parameter('loop', False).value,
            'deterministic': self.declare_parameter('deterministic', False).value,
        }
        for name, default in NUMBER_PARAMETERS.items():
            values[name] = self._number_parameter(name, default)
        for name in values:
            given = getattr(command_line, name)
            if given is not None:
                values[name] = given
        return PlaybackOptions(**{**values, 'topics': tuple(values['topics']),
                                  'remap': tuple(values['remap'])})

    def _number_parameter(self, name: str, default: float) -> float:
        # Dynamic typing so that `-p rate:=2` (an integer) is accepted as well as 2.0.
        value = self.declare_parameter(name, default, ParameterDescriptor(dynamic_typing=True)).value
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f'parameter {name!r} must be a number, got {value!r}')
        return float(value)

    def play(self) -> int:
        """
        Play the bag as the options say; the exit status.

        Raises ValueError (BagError) for unplayable bags.
        """
        with Bag(self.options.bag) as bag:
            selected, missing = select_topics(bag.topics, self.options.topics)
            for name in missing:
                self.get_logger().warning(f'topic {name} is not in the bag')
            origin = playback_origin(bag.start_ns, bag.end_ns, self.options.start_offset)
            self._create_publishers(selected)
            names = list(self._bag_publishers)
            self._total = sum(bag.topics[name].message_count for name in names)
            promised = {topic.name: topic.message_count for topic in selected}
            self._last_bag_ns = origin
            self._latest_bag_ns = bag.end_ns - 1
            mode = 'deterministic' if self.options.deterministic else f'rate {self.options.rate:g}'
            self._print(f'replay: playing {bag.path}: {self._total} messages on {len(names)} topics, '
                        f'{(bag.end_ns - origin) / 1e9:.1f} s of bag time, {mode}')
            if self.options.clock > 0:
                clock = self.create_publisher(Clock, '/clock', CLOCK_QOS)
                self.create_timer(1.0 / self.options.clock,
                                  lambda: clock.publish(Clock(clock=Time(nanoseconds=self._bag_now_ns()).to_msg())))
            # A terminal shows a progress bar; a log gets the opening and closing lines only.
            with tqdm(desc=f'0/{self._total} messages', total=(bag.end_ns - origin) / 1e9,
                      bar_format=PROGRESS_FORMAT, disable=None) as bar:
                shown = self.create_timer(PROGRESS_PERIOD_S, lambda: self._show_progress(bar, origin, bag.end_ns))
                if self.options.deterministic:
                    self._prepare_answers(bag, names)
                self._wait_for_subscribers()
                started = time.monotonic()
                while True:
                    self._tally = PlaybackTally(promised, self._skip_reasons)
                    self._play_pass(bag, origin)
                    if self._tally.shortfall() or not self.options.loop:
                        break
                self.destroy_timer(shown)
                self._show_progress(bar, origin, bag.end_ns)
                self._wait_for_acknowledgements()
        self._print(self._summary(time.monotonic() - started))
        for topic, (read, announced) in self._tally.surplus().items():
            self.get_logger().warning(f'{topic}: the storage held {read} messages where metadata.yaml '
                                      f'announces {announced}; all were played')
        if self._tally.shortfall():
            self._print(self._tally.shortfall_line())
            return 1
        return 0

    def _create_publishers(self, topics: Sequence[BagTopic]) -> None:
        remaps = self.options.remappings()
        unavailable: dict[str, list[str]] = {}
        for topic in topics:
            cls = message_class(topic.msgtype)
            if cls is None:
                unavailable.setdefault(topic.msgtype, []).append(topic.name)
                self._skip_reasons[topic.name] = f'{topic.msgtype} not installed'
                continue
            if not topic.qos_consistent:
                self.get_logger().warning(f'{topic.name} was recorded from publishers with different QoS; '
                                          'offering reliable, volatile')
            self._bag_publishers[topic.name] = self.create_publisher(cls, remaps.get(topic.name, topic.name),
                                                                     offered_qos_profile(topic))
        for msgtype, names in unavailable.items():
            self.get_logger().warning(f'skipping {", ".join(names)}: message type {msgtype} is not installed')
        if not self._bag_publishers:
            raise ValueError(f'no selected topic has an installed message type (missing: {sorted(unavailable)})')

    def _prepare_answers(self, bag: Bag, names: Sequence[str]) -> None:
        """Subscribe to the answers; wait for the frame topics' subscribers, then for an answering publisher."""
        answers = [
            self.create_subscription(PoseStamped, 'vlp/pose', lambda msg: self._answer(msg.header.stamp),
                                     ANSWER_QOS),
            self.create_subscription(Header, 'vlp/processed', lambda msg: self._answer(msg.stamp), ANSWER_QOS)]
        frames = [self._bag_publishers[name] for name in names if bag.topics[name].msgtype in FRAME_TYPES]
        if self._spin_while(lambda: any(p.get_subscription_count() == 0 for p in frames),
                            FRAME_SUBSCRIBER_WAIT_S):
            self.get_logger().warning(
                'deterministic mode: no subscriber on '
                f'{[p.topic_name for p in frames if p.get_subscription_count() == 0]} '
                f'after {FRAME_SUBSCRIBER_WAIT_S:g} s; their frames wait for no answer')
        # The answering node usually comes up with the frame subscriber; let its publisher match too.
        self._spin_while(lambda: all(a.get_publisher_count() == 0 for a in answers), DISCOVERY_WAIT_S)

    def _answer(self, stamp) -> None:
        if (stamp.sec, stamp.nanosec) == self._pending_stamp:
            self._pending_stamp = None

    def _wait_for_subscribers(self) -> None:
        """
        Wait until every topic has a subscriber, or discovery has settled on some, or DISCOVERY_WAIT_S.

        A publisher counts a subscriber before that subscriber has matched the
        publisher, and what is sent in between is lost to volatile subscribers:
        hence MATCH_SETTLE_S more once some matched.
        """
        publishers = list(self._bag_publishers.values())
        deadline = time.monotonic() + DISCOVERY_WAIT_S
        matched, last_change = 0, time.monotonic()
        while matched < len(publishers) and time.monotonic() < deadline:
            now_matched = sum(p.get_subscription_count() > 0 for p in publishers)
            if now_matched != matched:
                matched, last_change = now_matched, time.monotonic()
            if matched and time.monotonic() - last_change >= DISCOVERY_SETTLE_S:
                return
            self._executor.spin_once(timeout_sec=SPIN_SLICE_S)
        if matched:
            self._spin_for(MATCH_SETTLE_S)

    def _play_pass(self, bag: Bag, origin: int) -> None:
        """Every message of the selection from ``origin`` on, counted in ``self._tally``."""
        self._timeline = None
        self._last_bag_ns = origin
        self._spin_for(self.options.delay)
        for message in self._tally.from_origin(bag.messages(self._tally.promised), origin):
            if self._timeline is None:
                # The schedule starts when the first message has been read, so that
                # opening (or decompressing) the storage does not squeeze its first gaps.
                self._timeline = Timeline(origin, self.options.rate)
                self._loop_start = time.monotonic()
            if self.options.deterministic:
                self._executor.spin_once(timeout_sec=0.0)
            else:
                self._spin_for(self._loop_start + self._timeline.due_s(message.timestamp_ns) - time.monotonic())
            publisher = self._bag_publishers[message.topic]
            publisher.publish(message.data)
            self._published += 1
            self._tally.published[message.topic] += 1
            self._last_bag_ns = message.timestamp_ns
            if self.options.deterministic and message.msgtype in FRAME_TYPES:
                self._await_answer(message, publisher)

    def _await_answer(self, message: BagMessage, publisher: Publisher) -> None:
        if publisher.get_subscription_count() == 0:
            return  # nobody to answer
        self._pending_stamp = header_stamp(message.data)
        self._spin_while(lambda: self._pending_stamp is not None, self.options.answer_timeout)
        if self._pending_stamp is None:
            self._answered += 1
        else:
            self._unanswered += 1
            self._pending_stamp = None

    def _spin_while(self, condition: Callable[[], bool], timeout: float) -> bool:
        """
        Serve callbacks (timers, answers) while ``condition()`` holds, at most ``timeout`` s.

        Returns whether it still holds.
        """
        deadline = time.monotonic() + timeout
        while True:
            remaining = deadline - time.monotonic()
            self._executor.spin_once(timeout_sec=min(max(remaining, 0.0), SPIN_SLICE_S))
            if not condition() or remaining <= 0:
                return condition()

    def _spin_for(self, seconds: float) -> None:
        self._spin_while(lambda: True, seconds)

    def _show_progress(self, bar: tqdm, origin_ns: int, end_ns: int) -> None:
        bar.set_description_str(f'{self._published}/{self._total} messages', refresh=False)
        bar.n = seconds_played(self._bag_now_ns(), origin_ns, end_ns)
        bar.refresh()

    def _bag_now_ns(self) -> int:
        """Bag time being played: the clock in timed playback, the last message in deterministic mode."""
        if self.options.deterministic or self._timeline is None:
            return self._last_bag_ns
        scheduled = self._timeline.bag_time_ns(time.monotonic() - self._loop_start)
        return max(self._last_bag_ns, min(scheduled, self._latest_bag_ns))

    def _wait_for_acknowledgements(self) -> None:
        deadline = time.monotonic() + ACK_WAIT_S
        for publisher in self._bag_publishers.values():
            publisher.wait_for_all_acked(Duration(seconds=max(0.0, deadline - time.monotonic())))

    def _summary(self, elapsed_s: float) -> str:
        line = f'replay: done: published {self._published} messages in {elapsed_s:.1f} s'
        if skipped := self._tally.skipped_text():
            line += f'; {skipped}'
        if self.options.deterministic:
            line += f'; frames answered: {self._answered}, unanswered: {self._unanswered}'
        return line

    @staticmethod
    def _print(line: str) -> None:
        print(line, file=sys.stderr, flush=True)


def main(args: list[str] | None = None) -> int:
    """Play the bag the command line names; exit status 1 for an unplayable bag, 2 for bad options."""
    own, ros = split_ros_arguments(sys.argv if args is None else args)
    parser = command_line_parser()
    command_line = parser.parse_args(own[1:])

    def usage_error(err: Exception) -> int:
        parser.error(str(err))  # exits with status 2

    return run_node(lambda: Replay(command_line), _play, args=own[:1] + ros,
                    start_errors=(ValueError, ParameterException), on_start_error=usage_error)


def _play(node: Replay) -> int:
    try:
        return node.play()
    except ValueError as err:
        print(f'replay: error: {err}', file=sys.stderr, flush=True)
        return 1
