"""What a replay plays and when: options, topic selection, remapping, the time schedule."""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from vlp_ros.rosbag_reader import BagTopic

DEFAULT_CLOCK_HZ = 40.0  # as `ros2 bag play --clock` without a rate


@dataclass(frozen=True)
class PlaybackOptions:
    """The replay's settings, from its command line or ROS parameters of the same names."""

    bag: str
    topics: tuple[str, ...] = ()  # empty: every topic of the bag
    remap: tuple[str, ...] = ()  # FROM:=TO rules
    rate: float = 1.0
    loop: bool = False
    start_offset: float = 0.0  # seconds into the bag
    delay: float = 0.0  # seconds before playing (each loop)
    clock: float = 0.0  # /clock rate in Hz, 0: no /clock
    deterministic: bool = False
    answer_timeout: float = 2.0  # seconds a frame may stay unanswered in deterministic mode

    def __post_init__(self) -> None:
        if not self.bag:
            raise ValueError('no bag given: pass the bag directory (or set the parameter "bag")')
        if not self.rate > 0:
            raise ValueError(f'rate must be positive, got {self.rate}')
        for name in ('start_offset', 'delay', 'clock'):
            if not getattr(self, name) >= 0:
                raise ValueError(f'{name} must be zero or positive, got {getattr(self, name)}')
        if not self.answer_timeout > 0:
            raise ValueError(f'answer_timeout must be positive, got {self.answer_timeout}')
        parse_remaps(self.remap)

    def remappings(self) -> dict[str, str]:
        return parse_remaps(self.remap)


def absolute_topic(name: str) -> str:
    """Bag topics are absolute; users may leave out the leading slash."""
    return name if name.startswith('/') else '/' + name


def parse_remaps(rules: Sequence[str]) -> dict[str, str]:
    """{bag topic: published topic} from FROM:=TO rules."""
    remaps: dict[str, str] = {}
    for rule in rules:
        source, separator, target = rule.partition(':=')
        if not separator or not source.strip() or not target.strip():
            raise ValueError(f'remap rule {rule!r} is not of the form FROM:=TO')
        remaps[absolute_topic(source.strip())] = target.strip()
    return remaps


def select_topics(bag_topics: Mapping[str, BagTopic],
                  requested: Sequence[str]) -> tuple[list[BagTopic], list[str]]:
    """The bag topics to play and the requested names the bag does not have.

    Raises ValueError when nothing requested is in the bag or the selection holds no message.
    """
    if not requested:
        selected = list(bag_topics.values())
        missing: list[str] = []
    else:
        names = dict.fromkeys(absolute_topic(name) for name in requested)
        selected = [bag_topics[name] for name in names if name in bag_topics]
        missing = [name for name in names if name not in bag_topics]
        if not selected:
            raise ValueError(f'none of the topics {list(names)} is in the bag; it has {sorted(bag_topics)}')
    if sum(topic.message_count for topic in selected) == 0:
        raise ValueError(f'the selected topics {[topic.name for topic in selected]} hold no messages')
    return selected, missing


def playback_origin(start_ns: int, end_ns: int, start_offset_s: float) -> int:
    """Bag time at which playback starts; ValueError when the offset lies past the bag's end."""
    origin = start_ns + round(start_offset_s * 1e9)
    if origin >= end_ns:
        raise ValueError(f'start offset {start_offset_s} s is past the end of the bag '
                         f'({(end_ns - start_ns) / 1e9:.3f} s long)')
    return origin


@dataclass(frozen=True)
class Timeline:
    """Maps bag time to seconds of playback, scaled by ``rate``."""

    origin_ns: int
    rate: float

    def due_s(self, timestamp_ns: int) -> float:
        return max(0.0, (timestamp_ns - self.origin_ns) / 1e9 / self.rate)

    def bag_time_ns(self, elapsed_s: float) -> int:
        return self.origin_ns + round(elapsed_s * self.rate * 1e9)


def progress_line(published: int, total: int, bag_time_ns: int, origin_ns: int, end_ns: int) -> str:
    """One compact status line; the percentage is of bag time, which start offsets keep honest."""
    span = max(1, end_ns - origin_ns)
    played = min(max(0, bag_time_ns - origin_ns), span)
    return (f'replay: {published}/{total} messages, {played / 1e9:.1f}/{span / 1e9:.1f} s '
            f'({100.0 * played / span:.0f}%)')
