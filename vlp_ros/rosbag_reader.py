"""Reading rosbag2 directories for playback: validation, topics, recorded QoS, raw messages.

A thin layer over ``rosbags`` that turns every way a bag can be unusable
(missing, empty, corrupt, unsupported) into one ``BagError`` with a message
a user can act on.
"""
from __future__ import annotations

import struct
from collections.abc import Callable, Collection, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

from rosbags.interfaces import Connection, ConnectionExtRosbag2, Qos
from rosbags.rosbag2 import Reader

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
    name: str
    msgtype: str
    message_count: int
    qos: OfferedQos
    # False when the recorded publishers offered different QoS (then ``qos`` is the default).
    qos_consistent: bool = True


@dataclass(frozen=True)
class BagMessage:
    topic: str
    msgtype: str
    timestamp_ns: int
    data: bytes


def adapt_offers(offers: Sequence[Qos]) -> tuple[OfferedQos, bool]:
    """The offer that reproduces the recorded publishers' QoS, as `ros2 bag play` chooses it.

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
    """An open rosbag2 directory (sqlite3 or mcap, split, zstd-compressed; metadata v4 to v9)."""

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
        self.start_ns: int = self._reader.start_time
        self.end_ns: int = self._reader.end_time
        self.message_count: int = self._reader.message_count
        self.topics: dict[str, BagTopic] = {}
        for connection in self._reader.connections:
            self._add_topic(connection)
        if self.message_count == 0:
            self.close()
            raise BagError(f'bag {self.path} is empty: it holds no messages')

    def _add_topic(self, connection: Connection) -> None:
        # The metadata.yaml of rosbag2 lists each topic once; its QoS is what `ros2 bag play` offers.
        assert isinstance(connection.ext, ConnectionExtRosbag2)
        qos, consistent = adapt_offers(connection.ext.offered_qos_profiles)
        self.topics[connection.topic] = BagTopic(connection.topic, connection.msgtype,
                                                 connection.msgcount, qos, consistent)

    @property
    def duration_ns(self) -> int:
        return max(0, self.end_ns - self.start_ns)

    def messages(self, topics: Collection[str], start_ns: int | None = None) -> Iterator[BagMessage]:
        """Raw messages of ``topics`` in recorded order, from ``start_ns`` on.

        Raises BagError when the storage turns out unreadable, or yields nothing at all.
        """
        wanted = {(name, self.topics[name].msgtype) for name in topics}
        # Storage connections, not metadata ones: rosbags matches the two by QoS
        # equality, which real bags break (metadata.yaml and the database spell
        # "infinite" durations differently) and which then silently yields nothing.
        connections = [c for storage in self._reader.storage.storages for c in storage.connections
                       if (c.topic, c.msgtype) in wanted]
        stream = self._reader.storage.messages(connections, start_ns)
        count = 0
        while (item := self._guarded(f'became unreadable after {count} messages', next, stream, None)) is not None:
            connection, timestamp, data = item
            count += 1
            yield BagMessage(connection.topic, connection.msgtype, timestamp, bytes(data))
        if count == 0:
            raise BagError(f'bag {self.path} holds no readable messages on {sorted(topics)} '
                           f'(its metadata.yaml announces {self.message_count} in all)')

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
