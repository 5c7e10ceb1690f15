"""
A survey recording read into what the estimation takes: sightings per frame, odometry and gravity.

Frames go through the pipeline in order (its beacon evidence builds up across frames, as in the
locator). Odometry (nav_msgs/Odometry of the base, deserialised by rosbags, no ROS package needed)
is interpolated to the frames' stamps; each pair of consecutive frames with lamps in view that
odometry spans becomes one measured motion.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from vlp_ros.bags.frames import recorded_frames, RecordingTopics, require_topic, stamp_ns, TYPESTORE
from vlp_ros.bags.reader import Bag
from vlp_ros.core.gravity import GravityBuffer
from vlp_ros.pipeline.frame import Pipeline
from vlp_ros.survey.estimation import OdometryStep, SurveyData
from vlp_ros.survey.partial_map import PartialMap
from vlp_ros.survey.sightings import frame_sightings, FrameSightings

# Odometry is interpolated only between samples this close in time (s).
MAX_ODOMETRY_GAP = 0.5
# How far (rad) a robot's camera strays from its level mounting: floors, wheels and suspension rock it by
# tenths of a degree (the simulator's robots: 0.7 deg). It holds the tilt that one lamp alone leaves loose.
LEVEL_SIGMA = np.radians(1.0)


@dataclass(frozen=True)
class SurveyTopics:
    image: str = '/image_raw'
    camera_info: str = '/camera_info'
    imu: str = '/imu'
    odometry: str = '/odom'


@dataclass
class SurveyRecording:
    """The frames' sightings, the estimation's input built from them, and the recording's length (s)."""

    frames: list[FrameSightings]
    data: SurveyData
    duration: float
    imu_used: bool


def image_topic_of(bag: Path | str, partial: PartialMap, given: str | None) -> str:
    """Return ``given``, else the bag's image topic the params' ``image_transport`` names (either when both exist)."""
    if given:
        return given
    with Bag(bag) as opened:
        raw, compressed = '/image_raw', '/image_raw/compressed'
        preferred = compressed if partial.settings.image_transport == 'compressed' else raw
        if preferred in opened.topics:
            return preferred
        return compressed if compressed in opened.topics else raw


def read_survey(bag: Path | str, partial: PartialMap, topics: SurveyTopics,
                progress: Callable[[int, int], None] | None = None) -> SurveyRecording:
    """Run every frame through the pipeline and gather the estimation's input (``progress(done, total)``)."""
    settings = partial.settings
    with Bag(bag) as opened:
        duration = opened.duration_ns * 1e-9
        require_topic(opened, topics.image)
        total = opened.topics[topics.image].message_count or opened.topics[topics.image].stored_count
        has_odometry = topics.odometry in opened.topics
        has_imu = settings.imu_enabled and topics.imu in opened.topics
    gravity = GravityBuffer(settings.imu_rotation, settings.imu_max_age) if has_imu else None
    pipeline = Pipeline(settings)
    frames: list[FrameSightings] = []
    ups: dict[int, np.ndarray] = {}
    recording_topics = RecordingTopics(topics.image, topics.camera_info, topics.imu)
    for done, frame in enumerate(recorded_frames(bag, recording_topics, gravity), 1):
        if frame.camera is not None:
            sightings = frame_sightings(pipeline, len(frames), frame.image, frame.camera, frame.stamp_ns)
            if frame.up is not None:
                ups[len(frames)] = frame.up
            frames.append(sightings)
        if progress is not None:
            progress(done, total)
    odometry = odometry_steps(bag, topics.odometry, frames, partial) if has_odometry else []
    ids = {lamp.name: lamp.id for lamp in settings.lamps}
    data = SurveyData(frame_count=len(frames),
                      sightings=[s for frame in frames for s in frame.sightings],
                      free_lamps=[ids[name] for name in partial.surveyed],
                      anchors={ids[name]: anchor for name, anchor in partial.anchors.items()},
                      odometry=odometry, mounting=settings.mounting,
                      up=dict(ups), up_sigma=settings.imu_sigma or 0.01,
                      expected_up=_expected_up(partial), level_sigma=_level_sigma(partial))
    return SurveyRecording(frames, data, duration, bool(ups))


def _expected_up(partial: PartialMap) -> np.ndarray | None:
    """Map up in the camera for a level base (the mounting), else the params' static prior, else None."""
    settings = partial.settings
    if settings.mounting is not None:
        return settings.mounting.up_in_camera()
    return settings.prior_up


def _level_sigma(partial: PartialMap) -> float | None:
    """How well the expected up is known: a level robot's mounting, or the params' prior sigma (None: not at all)."""
    settings = partial.settings
    if settings.mounting is not None:
        return LEVEL_SIGMA
    return settings.prior_sigma if settings.prior_up is not None else None


def odometry_poses(bag: Path | str, topic: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stamps (s), positions (N, 3) and xyzw quaternions (N, 4) of nav_msgs/Odometry poses, in time order."""
    stamps, positions, quaternions = [], [], []
    with Bag(bag) as opened:
        for message in opened.messages([topic]):
            msg = TYPESTORE.deserialize_cdr(message.data, message.msgtype)
            p, q = msg.pose.pose.position, msg.pose.pose.orientation
            stamps.append(stamp_ns(msg.header) * 1e-9)
            positions.append([p.x, p.y, p.z])
            quaternions.append([q.x, q.y, q.z, q.w])
    order = np.argsort(stamps, kind='stable')
    return np.asarray(stamps)[order], np.asarray(positions, dtype=float)[order], np.asarray(quaternions)[order]


def odometry_steps(bag: Path | str, topic: str, frames: list[FrameSightings], partial: PartialMap
                   ) -> list[OdometryStep]:
    """Return the base's odometry motion between consecutive frames with sightings, where odometry spans both."""
    stamps, positions, quaternions = odometry_poses(bag, topic)
    if len(stamps) < 2:
        return []
    stamps, unique = np.unique(stamps, return_index=True)
    positions, rotations = positions[unique], Rotation.from_quat(quaternions[unique])
    slerp = Slerp(stamps, rotations)
    poses = {}
    for index, frame in enumerate(frames):
        t = frame.stamp_ns * 1e-9
        if not frame.sightings or not stamps[0] <= t <= stamps[-1]:
            continue
        after = int(np.searchsorted(stamps, t))
        before = max(after - 1, 0)
        if stamps[min(after, len(stamps) - 1)] - stamps[before] > MAX_ODOMETRY_GAP:
            continue
        position = np.array([np.interp(t, stamps, positions[:, axis]) for axis in range(3)])
        poses[index] = (slerp([t]).as_matrix()[0], position)
    ordered = sorted(poses)
    steps = []
    for first, second in zip(ordered, ordered[1:]):
        (ra, pa), (rb, pb) = poses[first], poses[second]
        steps.append(OdometryStep(first, second, ra.T @ rb, ra.T @ (pb - pa)))
    return steps
