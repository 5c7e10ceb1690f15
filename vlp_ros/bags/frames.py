"""Camera frames of a rosbag2 recording, each with its camera_info and IMU up, for running the pipeline offline."""
from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from rosbags.typesys import get_typestore, Stores

from vlp_ros.bags.reader import Bag, BagError
from vlp_ros.core.camera import CameraModel
from vlp_ros.core.gravity import GravityBuffer
from vlp_ros.images.conversion import decode_compressed, pixels_of
from vlp_ros.images.message import parse_compressed_image, parse_image

TYPESTORE = get_typestore(Stores.LATEST)


@dataclass
class RecordedFrame:
    stamp_ns: int
    image: np.ndarray
    camera: CameraModel | None
    up: np.ndarray | None


@dataclass(frozen=True)
class RecordingTopics:
    image: str = '/image_raw'
    camera_info: str = '/camera_info'
    imu: str = '/imu'
    ground_truth: str = '/ground_truth/pose'


def stamp_ns(header) -> int:
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def require_topic(bag: Bag, topic: str) -> None:
    if topic not in bag.topics:
        raise BagError(f'bag {bag.path} has no topic {topic} (it has {", ".join(sorted(bag.topics))})')


def recorded_frames(bag_path: Path | str, topics: RecordingTopics,
                    gravity: GravityBuffer | None) -> Iterator[RecordedFrame]:
    """
    Every image of the recording in order, with its camera_info and (if wanted) IMU up.

    An image is handed out once everything logged at its time has been read, since
    drivers publish the camera_info and IMU sample of a frame in either order.
    """
    with Bag(bag_path) as bag:
        for topic in (topics.image, topics.camera_info):
            require_topic(bag, topic)
        wanted = [topics.image, topics.camera_info]
        if gravity is not None:
            require_topic(bag, topics.imu)
            wanted.append(topics.imu)
        camera, waiting = None, []
        for message in bag.messages(wanted):
            if waiting and camera is not None and message.timestamp_ns > waiting[-1].timestamp_ns:
                yield from (_frame(m.data, m.msgtype, camera, gravity) for m in waiting)
                waiting = []
            if message.topic == topics.camera_info:
                info = TYPESTORE.deserialize_cdr(message.data, message.msgtype)
                camera = CameraModel.from_camera_info(info.width, info.height, info.k, info.d, info.distortion_model,
                                                      info.p, info.r)
            elif message.topic == topics.imu:
                imu = TYPESTORE.deserialize_cdr(message.data, message.msgtype)
                a = imu.linear_acceleration
                gravity.add(stamp_ns(imu.header), [a.x, a.y, a.z])
            else:
                waiting.append(message)
        if camera is not None:
            yield from (_frame(m.data, m.msgtype, camera, gravity) for m in waiting)


def _frame(data: bytes, msgtype: str, camera: CameraModel | None, gravity: GravityBuffer | None) -> RecordedFrame:
    if msgtype == 'sensor_msgs/msg/CompressedImage':
        msg = parse_compressed_image(data)
        image = decode_compressed(msg)
    else:
        msg = parse_image(data)
        image = pixels_of(msg)
    up = None if gravity is None else gravity.up_at(msg.stamp_ns)
    return RecordedFrame(msg.stamp_ns, image, camera, up)
