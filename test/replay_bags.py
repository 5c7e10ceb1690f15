"""Synthetic rosbag2 directories for the replay tests, written with rosbags (ROS-free)."""
from __future__ import annotations

from collections.abc import Callable
from contextlib import closing
from dataclasses import dataclass, field
from pathlib import Path
import shutil
import sqlite3

from conftest import SHARED_DATA
import numpy as np
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
from rosbags.typesys import get_typestore, Stores
import yaml

SHARED_BAGS = SHARED_DATA / 'rosbag2'
TYPESTORE = get_typestore(Stores.ROS2_KILTED)
T0_NS = 1_700_000_000_000_000_000
STRING = 'std_msgs/msg/String'
IMAGE = 'sensor_msgs/msg/Image'
CAMERA_INFO = 'sensor_msgs/msg/CameraInfo'


@dataclass(frozen=True)
class Recorded:
    topic: str
    msgtype: str
    timestamp_ns: int
    data: bytes
    connection: int = field(default=0, compare=False)  # which of the topic's recorded publishers


def offer(reliability: QosReliability = QosReliability.RELIABLE,
          durability: QosDurability = QosDurability.VOLATILE, depth: int = 10) -> Qos:
    infinite = QosTime(2147483647, 4294967295)
    return Qos(QosHistory.KEEP_LAST, depth, reliability, durability, infinite, infinite,
               QosLiveliness.AUTOMATIC, infinite, False)


def _serialize(message: object, msgtype: str) -> bytes:
    return bytes(TYPESTORE.serialize_cdr(message, msgtype))


def _header(stamp_ns: int, frame_id: str) -> object:
    types = TYPESTORE.types
    stamp = types['builtin_interfaces/msg/Time'](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
    return types['std_msgs/msg/Header'](stamp=stamp, frame_id=frame_id)


def string_data(text: str) -> bytes:
    return _serialize(TYPESTORE.types[STRING](data=text), STRING)


def image_data(stamp_ns: int, frame_id: str = 'camera') -> bytes:
    image = TYPESTORE.types[IMAGE](header=_header(stamp_ns, frame_id), height=2, width=3, encoding='mono8',
                                   is_bigendian=0, step=3, data=np.arange(6, dtype=np.uint8))
    return _serialize(image, IMAGE)


def camera_info_data(stamp_ns: int) -> bytes:
    info = TYPESTORE.types[CAMERA_INFO](
        header=_header(stamp_ns, 'camera'), height=2, width=3, distortion_model='plumb_bob',
        d=np.zeros(5), k=np.eye(3).ravel(), r=np.eye(3).ravel(), p=np.zeros(12), binning_x=0, binning_y=0,
        roi=TYPESTORE.types['sensor_msgs/msg/RegionOfInterest'](x_offset=0, y_offset=0, height=0, width=0,
                                                                do_rectify=False))
    return _serialize(info, CAMERA_INFO)


def chatter(count: int, period_s: float, topic: str = '/chatter') -> list[Recorded]:
    """``count`` String messages 'hello k', ``period_s`` apart."""
    return [Recorded(topic, STRING, T0_NS + round(k * period_s * 1e9), string_data(f'hello {k}'))
            for k in range(count)]


def write_bag(path: Path, messages: list[Recorded], *, storage: str = 'sqlite3', version: int = 9,
              compression: str | None = None, qos: dict[str, list[Qos]] | None = None) -> Path:
    """Return a bag as rosbags writes it; ``compression`` is a zstd mode name: 'file', 'message' or 'storage'."""
    writer = Writer(path, version=version, storage_plugin=StoragePlugin[storage.upper()])
    if compression:
        writer.set_compression(CompressionMode[compression.upper()], CompressionFormat.ZSTD)
    with writer:
        connections = {}
        for message in messages:
            key = (message.topic, message.msgtype, message.connection)
            if key not in connections:
                # A topic's further connections differ in their offered depth, as rosbags wants them distinct.
                offers = (qos or {}).get(message.topic, [offer(depth=10 + message.connection)])
                # Types rosbags does not know (no Python module anywhere) get a made-up String-like definition.
                known = message.msgtype in TYPESTORE.fielddefs
                connections[key] = writer.add_connection(
                    message.topic, message.msgtype, typestore=TYPESTORE, offered_qos_profiles=offers,
                    msgdef=None if known else 'string data', rihs01=None if known else 'RIHS01_' + '0' * 64)
            writer.write(connections[key], message.timestamp_ns, message.data)
    return path


def write_split_bag(path: Path, messages: list[Recorded], parts: int, *, storage: str = 'sqlite3') -> Path:
    """One bag split over ``parts`` storage files, as `ros2 bag record --max-bag-size` leaves it."""
    chunks = [list(chunk) for chunk in np.array_split(np.array(messages, dtype=object), parts)]
    return _join_files(path, chunks, storage)


def write_overlapping_split_bag(path: Path, files: list[list[Recorded]], *, storage: str = 'sqlite3') -> Path:
    """
    One bag of several files that overlap in time, as several writers leave it.

    Its metadata.yaml takes starting_time from the first file, which need not
    hold the earliest message (rosbag2's own multi-file test recordings do so).
    """
    return _join_files(path, files, storage)


def _join_files(path: Path, files: list[list[Recorded]], storage: str) -> Path:
    pieces = [write_bag(path.parent / f'{path.name}_part{k}', chunk, storage=storage)
              for k, chunk in enumerate(files)]
    path.mkdir()
    metadata = [_metadata(piece) for piece in pieces]
    names = []
    for k, (piece, info) in enumerate(zip(pieces, metadata)):
        source = piece / info['relative_file_paths'][0]
        target = path / f'{path.name}_{k}{source.suffix}'
        shutil.move(source, target)
        names.append(target.name)
        shutil.rmtree(piece)
    messages = [message for chunk in files for message in chunk]
    stamps = [message.timestamp_ns for message in messages]
    merged = metadata[0]
    merged['relative_file_paths'] = names
    merged['message_count'] = len(messages)
    merged['duration']['nanoseconds'] = max(stamps) - merged['starting_time']['nanoseconds_since_epoch']
    # One entry per recorded connection, as rosbags writes them, with the counts of all files.
    entries: dict[str, dict] = {}
    for info in metadata:
        for entry in info['topics_with_message_count']:
            key = yaml.safe_dump(entry['topic_metadata'])
            entries.setdefault(key, {**entry, 'message_count': 0})['message_count'] += entry['message_count']
    merged['topics_with_message_count'] = list(entries.values())
    merged['files'] = [{**file_info, 'path': name}
                       for info, name in zip(metadata, names) for file_info in info['files']]
    _write_metadata(path, merged)
    return path


def _metadata(path: Path) -> dict:
    return yaml.safe_load((path / 'metadata.yaml').read_text())['rosbag2_bagfile_information']


def _write_metadata(path: Path, info: dict) -> None:
    (path / 'metadata.yaml').write_text(yaml.safe_dump({'rosbag2_bagfile_information': info}))


def set_metadata_version(path: Path, version: int) -> Path:
    info = _metadata(path)
    info['version'] = version
    _write_metadata(path, info)
    return path


def copy_bag(source: Path, target: Path) -> Path:
    """Return a writable copy (the shared recordings are read-only)."""
    shutil.copytree(source, target)
    for item in target.iterdir():
        item.chmod(0o644)
    return target


def edit_metadata(path: Path, edit: Callable[[dict], None]) -> Path:
    info = _metadata(path)
    edit(info)
    _write_metadata(path, info)
    return path


def storage_file(path: Path) -> Path:
    return path / _metadata(path)['relative_file_paths'][0]


def sqlite3_topic_data(database: Path, topic: str, start_ns: int = 0) -> list[bytes]:
    """
    Return the raw messages of ``topic`` from ``start_ns`` on, in time order, read with plain sqlite3.

    An oracle independent of rosbags.
    """
    with closing(sqlite3.connect(f'file:{database}?mode=ro', uri=True)) as connection:
        rows = connection.execute(
            'SELECT data FROM messages JOIN topics ON messages.topic_id = topics.id '
            'WHERE topics.name = ? AND timestamp >= ? ORDER BY timestamp', (topic, start_ns))
        return [bytes(data) for (data,) in rows]


def overlapping_recording() -> list[list[Recorded]]:
    """
    Three files of one recording that overlap in time, the first starting last.

    /a in files 0 and 2, /b in file 1, and /c from two connections, one in file 1 and one in file 2
    (160 messages).
    """

    def strings(topic: str, steps: range, connection: int = 0) -> list[Recorded]:
        # Topics a nanosecond apart, so that the recorded order is the timestamp order.
        offset = ord(topic[-1]) - ord('a')
        return [Recorded(topic, STRING, T0_NS + j * 10**7 + offset, string_data(f'{topic} {j}'), connection)
                for j in steps]

    def by_time(messages: list[Recorded]) -> list[Recorded]:
        return sorted(messages, key=lambda m: m.timestamp_ns)

    return [strings('/a', range(20, 60)),
            by_time(strings('/b', range(0, 40)) + strings('/c', range(0, 60, 2))),
            by_time(strings('/a', range(0, 20)) + strings('/c', range(1, 60, 2), connection=1))]


def by_topic(messages: list[Recorded]) -> dict[str, list[bytes]]:
    """{topic: its messages' bytes in timestamp order}: what a subscriber of each topic must receive."""
    topics: dict[str, list[bytes]] = {}
    for message in sorted(messages, key=lambda m: m.timestamp_ns):
        topics.setdefault(message.topic, []).append(message.data)
    return topics
