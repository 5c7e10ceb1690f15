"""Frames, IMU and ground truth of a rosbag2 recording, for evaluating the pipeline on it."""
from __future__ import annotations

from pathlib import Path

from vlp_ros.bags.frames import recorded_frames, RecordedFrame, RecordingTopics, require_topic, stamp_ns, TYPESTORE
from vlp_ros.bags.reader import Bag
from vlp_ros.core.pose import Pose

__all__ = ['RecordedFrame', 'RecordingTopics', 'ground_truth', 'recorded_frames']


def ground_truth(bag_path: Path | str, topic: str) -> dict[int, Pose]:
    """Return true camera poses by header stamp (ns), from geometry_msgs/PoseStamped messages."""
    with Bag(bag_path) as bag:
        require_topic(bag, topic)
        truth = {}
        for message in bag.messages([topic]):
            msg = TYPESTORE.deserialize_cdr(message.data, message.msgtype)
            p, q = msg.pose.position, msg.pose.orientation
            truth[stamp_ns(msg.header)] = Pose.from_quaternion([q.x, q.y, q.z, q.w], [p.x, p.y, p.z])
        return truth
