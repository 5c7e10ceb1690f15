"""
Reading rosbag2 directories for playback: validation, topics, recorded QoS, raw messages.

A thin layer over ``rosbags`` that turns every way a bag can be unusable
(missing, empty, corrupt, unsupported) into one ``BagError`` with a message
a user can act on.
"""
from __future__ import annotations

from collections.abc import Callable, Collection, Iterator, Sequence
from dataclasses import dataclass
import heapq
from pathlib import Path
import struct
from typing import TypeVar

from rosbags.interfaces import Connection, ConnectionExtRosbag2, Qos
from rosbags.rosbag2 import Reader

try:
    from compression import zstd  # Python 3.14, as rosbags uses it
except ImportError:
    from backports import zstd

FRAME_TYPES = frozenset({'sensor_msgs/msg/Image', 'sensor_msgs/msg/CompressedImage'})
# rosbag2's own playback default: a publisher matching every subscriber kind.
DEFAULT_RELIABILITY = 'RELIABLE'
DEFAULT_DURABILITY = 'VOLATILE'
DEFAULT_DEPTH = 10
_UNSET_POLICIES = {'SYSTEM_DEFAULT', 'UNKNOWN'}
# CDR encapsulation ids (XCDR1 and plain XCDR2) and their byte order.
_ENCAPSULATION_ORDER = {0: '>', 1: '<', 6: '>', 7: '<'}
T = TypeVar('T')


class BagError(ValueError):
    """A bag that cannot be played: missing, empty, corrupt or unsupported."""


@dataclass(frozen=True)
class OfferedQos:
    """The QoS a replaying publisher offers (policy names as in rclpy / rmw)."""

    reliability: str = DEFAULT_RELIABILITY
    durability: str = DEFAULT_DURABILITY
    depth: int = DEFAULT_DEPTH


@dataclass(frozen=True)
class BagTopic:
    name: str  # absolute, whatever the bag spells
    msgtype: str
    message_count: int  # as metadata.yaml announces it, summed over the topic's connections
    qos: OfferedQos
    # False when the recorded publishers offered different QoS (then ``qos`` is the default).
    qos_consistent: bool = True
    stored_count: int = 0  # as the storage files' indexes count it
    other_msgtypes: tuple[str, ...] = ()  # further types recorded on this name: unplayable on one topic


@dataclass(frozen=True)
class BagMessage:
    topic: str
    msgtype: str
    timestamp_ns: int
    data: bytes


def adapt_offers(offers: Sequence[Qos]) -> tuple[OfferedQos, bool]:
    """
    Return the offer that reproduces the recorded publishers' QoS, as `ros2 bag play` chooses it.

    Recorded offers that agree on reliability and durability are kept (history
    becomes keep-last 10); disagreeing ones fall back to the default offer and
    report ``False`` so the caller can warn.
    """
    policies = {(_policy(offer.reliability.name, DEFAULT_RELIABILITY),
                 _policy(offer.durability.name, DEFAULT_DURABILITY)) for offer in offers}
    if len(policies) != 1:
        return OfferedQos(), len(policies) == 0
    reliability, durability = policies.pop()
    return OfferedQos(reliability, durability), True


def _policy(name: str, default: str) -> str:
    return default if name in _UNSET_POLICIES else name


def absolute_topic(name: str) -> str:
    """Topics as the graph names them; bags and users may leave out the leading slash."""
    return name if name.startswith('/') else '/' + name


def _group_by_topic(connections: Sequence[Connection]) -> dict[str, list[Connection]]:
    groups: dict[str, list[Connection]] = {}
    for connection in connections:
        groups.setdefault(absolute_topic(connection.topic), []).append(connection)
    return groups


def _offers(connections: Sequence[Connection]) -> list[Qos]:
    offers = []
    for connection in connections:
        assert isinstance(connection.ext, ConnectionExtRosbag2)
        offers += connection.ext.offered_qos_profiles
    return offers


def header_stamp(data: bytes) -> tuple[int, int]:
    """(sec, nanosec) of a CDR message whose first field is a std_msgs/Header (images are)."""
    if len(data) < 12:
        raise ValueError(f'serialized message of {len(data)} bytes is too short for a header stamp')
    encapsulation = data[1]
    if data[0] != 0 or encapsulation not in _ENCAPSULATION_ORDER:
        raise ValueError(f'unsupported CDR encapsulation 0x{data[0]:02x}{data[1]:02x}')
    sec, nanosec = struct.unpack_from(_ENCAPSULATION_ORDER[encapsulation] + 'iI', data, 4)
    return sec, nanosec


class Bag:
    """
    An open rosbag2 directory (sqlite3 or mcap, split, zstd-compressed; metadata v4 to v9).

    Topics are keyed by absolute name and gather every connection recorded on
    them, in metadata.yaml and in the storage files: real bags list a topic once
    per writer, leave out leading slashes, and may hold what metadata.yaml lacks.
    Times and counts of the storage stand beside the metadata's promises, which
    a split bag whose files overlap in time can get wrong.
    """

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise BagError(f'bag {self.path} does not exist')
        if not self.path.is_dir():
            raise BagError(f'bag {self.path} is not a rosbag2 directory (give the directory, not a file)')
        if not (self.path / 'metadata.yaml').is_file():
            raise BagError(f'bag {self.path} has no metadata.yaml: not a rosbag2 directory')
        self._reader = self._guarded('cannot be opened', Reader, self.path)
        self._guarded('cannot be opened', self._reader.open)
        storages = [storage for storage in self._reader.storage.storages if storage.metadata.message_count]
        # From the storage, not metadata.yaml: a split bag's starting_time may be that of one file only.
        self.start_ns: int = min((s.metadata.start_time for s in storages), default=self._reader.start_time)
        self.end_ns: int = max((s.metadata.end_time for s in storages), default=self._reader.end_time)
        self.message_count: int = sum(storage.metadata.message_count for storage in storages)
        self.topics: dict[str, BagTopic] = self._gather_topics()
        if self.message_count == 0:
            self.close()
            raise BagError(f'bag {self.path} is empty: it holds no messages')

    def _storage_connections(self) -> list[Connection]:
        return [c for storage in self._reader.storage.storages for c in storage.connections]

    def _gather_topics(self) -> dict[str, BagTopic]:
        announced = _group_by_topic(self._reader.connections)
        stored = _group_by_topic(self._storage_connections())
        topics = {}
        for name in dict.fromkeys([*announced, *stored]):
            listed, held = announced.get(name, []), stored.get(name, [])
            msgtypes = tuple(dict.fromkeys(c.msgtype for c in listed + held))
            # metadata.yaml's offers are what `ros2 bag play` uses; real bags may leave them '' there.
            offers = _offers(listed) or _offers(held)
            qos, consistent = adapt_offers(offers)
            topics[name] = BagTopic(name, msgtypes[0], sum(c.msgcount for c in listed), qos, consistent,
                                    sum(c.msgcount for c in held), msgtypes[1:])
        return topics

    @property
    def duration_ns(self) -> int:
        return max(0, self.end_ns - self.start_ns)

    def messages(self, topics: Collection[str]) -> Iterator[BagMessage]:
        """
        Every raw message of ``topics`` (absolute names) in timestamp order, over all files and connections.

        The storage reads are not given a start time: callers skip what they do
        not want, and can count it. Raises BagError when the storage turns out
        unreadable, or yields nothing at all.
        """
        wanted = set(topics)
        # Each file on its own, merged by time: files of one bag overlap when several writers split.
        streams = [self._storage_messages(storage, [c for c in storage.connections
                                                    if absolute_topic(c.topic) in wanted])
                   for storage in self._reader.storage.storages]
        stream = heapq.merge(*streams, key=lambda message: message.timestamp_ns)
        count = 0
        while (message := self._guarded(f'became unreadable after {count} messages', next, stream, None)) is not None:
            count += 1
            yield message
        if count == 0:
            raise BagError(f'bag {self.path} holds no readable messages on {sorted(topics)} '
                           f'(its metadata.yaml announces {sum(self.topics[t].message_count for t in topics)})')

    def _storage_messages(self, storage: object, connections: list[Connection]) -> Iterator[BagMessage]:
        # Storage connections, not metadata ones: rosbags matches the two by QoS
        # equality, which real bags break (metadata.yaml and the database spell
        # "infinite" durations differently) and which then silently yields nothing.
        if not connections:
            return
        compressed = self._reader.compression_mode == 'message'
        for connection, timestamp, data in storage.messages(connections):
            yield BagMessage(absolute_topic(connection.topic), connection.msgtype, timestamp,
                             zstd.decompress(data) if compressed else bytes(data))

    def _guarded(self, what: str, function: Callable[..., T], *args: object) -> T:
        # rosbags lets its parsers' errors through unwrapped (apsw, zstd, struct,
        # UnicodeDecodeError, MemoryError on absurd lengths, ...); all mean a corrupt bag.
        try:
            return function(*args)
        except Exception as err:  # noqa: BLE001 - converted into one clear BagError
            text = ' '.join(str(err).split())  # one line, even for YAML parser reports
            detail = f'{type(err).__name__}: {text}' if text else type(err).__name__
            raise BagError(f'bag {self.path} {what} (corrupt or unsupported?): {detail}') from None

    def close(self) -> None:
        if self._reader.is_open:
            self._reader.close()

    def __enter__(self) -> Bag:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()
