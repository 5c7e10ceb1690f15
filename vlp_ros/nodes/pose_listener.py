"""
Playing a recording through the installed nodes and collecting what the locator answers.

The ROS part of `make demo` and of the node tests: ``replay --deterministic`` feeds a
fresh ``locator`` (two processes over DDS) while a PoseListener in this process records
the poses and per-frame outcomes by image stamp.
"""
from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
import subprocess
import time

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped
import numpy as np
import rclpy
from rclpy.node import Node
from std_msgs.msg import Header

from vlp_ros.core.pose import Pose
from vlp_ros.nodes.dds_environment import installed_executable, stop_process


class PoseListener:
    """Collects the locator's answers (poses with covariance, and per-frame outcomes) by image stamp."""

    def __init__(self, node: Node) -> None:
        self.node = node
        self.poses: dict[int, Pose] = {}
        self.outcomes: dict[int, str] = {}
        self.latency_ms = float('nan')
        self.diagnostics_received = 0
        self.node.create_subscription(PoseWithCovarianceStamped, 'vlp/pose_with_covariance', self._on_pose, 100)
        self.node.create_subscription(Header, 'vlp/processed', self._on_processed, 100)
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics, 10)

    @staticmethod
    def _stamp(header: Header) -> int:
        return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec

    def _on_pose(self, msg: PoseWithCovarianceStamped) -> None:
        p, q = msg.pose.pose.position, msg.pose.pose.orientation
        pose = Pose.from_quaternion([q.x, q.y, q.z, q.w], [p.x, p.y, p.z])
        pose.covariance = np.array(msg.pose.covariance).reshape(6, 6)
        self.poses[self._stamp(msg.header)] = pose

    def _on_processed(self, msg: Header) -> None:
        self.outcomes[self._stamp(msg)] = msg.frame_id

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        self.diagnostics_received += 1
        for status in msg.status:
            for kv in status.values:
                if kv.key == 'latency median (ms)' and kv.value != 'nan':
                    self.latency_ms = float(kv.value)

    def spin_until_diagnostics(self, count: int, timeout: float) -> None:
        """Process answers until ``count`` more diagnostics have arrived, or ``timeout`` s have passed."""
        target = self.diagnostics_received + count
        deadline = time.monotonic() + timeout
        while self.diagnostics_received < target and time.monotonic() < deadline:
            rclpy.spin_once(self.node, timeout_sec=0.02)

    def spin_for(self, seconds: float) -> None:
        """Process the answers that arrive in the next ``seconds``."""
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            rclpy.spin_once(self.node, timeout_sec=0.02)


@contextmanager
def listening_node(name: str) -> Iterator[PoseListener]:
    """Initialize rclpy and yield a PoseListener on a node called ``name``; shut both down after."""
    rclpy.init()
    listener = PoseListener(rclpy.create_node(name))
    try:
        yield listener
    finally:
        listener.node.destroy_node()
        rclpy.try_shutdown()


def _start(name: str, *args: str, log: Path) -> subprocess.Popen:
    with open(log, 'wb') as out:
        return subprocess.Popen([str(installed_executable(name)), *map(str, args)], stdout=out,
                                stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True)


def play_through_nodes(bag: Path, params: Path, frames: int, listener: PoseListener, logs: Path,
                       topics: Sequence[str], progress: Callable[[int, int], None] | None = None) -> float:
    """
    Replay ``topics`` of ``bag`` into a fresh locator, wait for every frame's answer; return the wall time (s).

    ``topics`` starts with the image and camera_info topics. The listener's answers
    are reset first: recordings may share stamps. ``progress(answered, frames)`` is
    told how many frames were answered.
    """
    report = progress or (lambda done, total: None)
    listener.poses.clear()
    listener.outcomes.clear()
    locator = _start('locator', '--ros-args', '--params-file', params, log=logs / f'{bag.name}_locator.log')
    replay = None
    try:
        # The locator loads its kernels (a minute when their cache is cold) before it subscribes
        # (to the IMU only when its params enable it).
        while not all(listener.node.count_subscribers(topic) for topic in topics[:2]):
            if locator.poll() is not None:
                raise RuntimeError(f'locator exited: see {logs / (bag.name + "_locator.log")}')
            listener.spin_for(0.1)
        started = time.monotonic()
        replay = _start('replay', bag, '--deterministic', '--topics', *topics, log=logs / f'{bag.name}_replay.log')
        answered = -1
        while replay.poll() is None:
            listener.spin_for(0.1)
            count = len(listener.outcomes)
            if count != answered:
                answered = count
                report(min(count, frames), frames)
        # Diagnostics come once a second: the second after the last answer counts every frame.
        listener.spin_until_diagnostics(2, 5.0)
        report(frames, frames)
        if replay.returncode != 0:
            raise RuntimeError(f'replay failed: see {logs / (bag.name + "_replay.log")}')
        return time.monotonic() - started
    finally:
        for process in (replay, locator):
            if process is not None:
                stop_process(process)
