"""What a replay plays and when: options, topic selection, remapping, the time schedule."""
from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field

from vlp_ros.bags.reader import absolute_topic, BagMessage, BagTopic

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
    """
    Return the bag topics to play and the requested names the bag does not have.

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
    if sum(max(topic.message_count, topic.stored_count) for topic in selected) == 0:
        raise ValueError(f'the selected topics {[topic.name for topic in selected]} hold no messages')
    for topic in selected:
        if topic.other_msgtypes:
            raise ValueError(f'topic {topic.name} was recorded with several message types '
                             f'{[topic.msgtype, *topic.other_msgtypes]}, which one topic cannot carry; '
                             'leave it out with --topics')
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


def seconds_played(bag_time_ns: int, origin_ns: int, end_ns: int) -> float:
    """Bag time played from ``origin_ns`` when playback is at ``bag_time_ns``, within [0, end_ns - origin_ns]."""
    return min(max(0, bag_time_ns - origin_ns), end_ns - origin_ns) / 1e9


@dataclass
class PlaybackTally:
    """
    One pass's books, per topic: what metadata.yaml promises, what was read, published or skipped.

    The promise for the selection is the metadata's count less what was read
    before the start offset: the metadata counts whole topics only.
    """

    promised: Mapping[str, int]  # metadata.yaml's count of each topic read (played or skipped)
    skip_reasons: Mapping[str, str] = field(default_factory=dict)  # topics read but deliberately not played
    before_start: Counter = field(default_factory=Counter)
    read: Counter = field(default_factory=Counter)
    published: Counter = field(default_factory=Counter)

    def from_origin(self, messages: Iterable[BagMessage], origin_ns: int) -> Iterator[BagMessage]:
        """Yield the messages at or after ``origin_ns`` that are to be published; counts all of them."""
        for message in messages:
            if message.timestamp_ns < origin_ns:
                self.before_start[message.topic] += 1
                continue
            self.read[message.topic] += 1
            if message.topic not in self.skip_reasons:
                yield message

    def promised_from_origin(self, topic: str) -> int:
        return max(0, self.promised[topic] - self.before_start[topic])

    def shortfall(self) -> dict[str, tuple[int, int]]:
        """{topic: (published or skipped, promised)} for every topic that fell short of its promise."""
        short = {}
        for topic in self.promised:
            delivered = self.read[topic] if topic in self.skip_reasons else self.published[topic]
            if delivered < self.promised_from_origin(topic):
                short[topic] = (delivered, self.promised_from_origin(topic))
        return short

    def surplus(self) -> dict[str, tuple[int, int]]:
        """{topic: (read, promised)} where the storage held more than metadata.yaml announces."""
        return {topic: (self.read[topic], self.promised_from_origin(topic)) for topic in self.promised
                if self.read[topic] > self.promised_from_origin(topic)}

    def shortfall_line(self) -> str:
        short = self.shortfall()
        delivered, promised = (sum(counts) for counts in zip(*short.values()))
        topics = ', '.join(f'{topic} {got} of {want}' for topic, (got, want) in short.items())
        return (f'replay: error: incomplete: {delivered} of the {promised} messages that metadata.yaml '
                f'promises for the selection were played on {topics}')

    def skipped_text(self) -> str:
        """'' when nothing was skipped, else how many messages of which topics, and why."""
        if not self.skip_reasons:
            return ''
        topics = ', '.join(f'{topic} {self.read[topic]} ({reason})' for topic, reason in self.skip_reasons.items())
        return f'skipped {sum(self.read[topic] for topic in self.skip_reasons)} messages: {topics}'
