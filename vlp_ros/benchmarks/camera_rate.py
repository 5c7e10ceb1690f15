"""
Camera rate through the node: python -m vlp_ros.benchmarks.camera_rate [--scene NAME ...] [--look NAME ...].

For each scene and look of ``pipeline_speed``, renders ``--frames`` frames of the scene (camera poses
with a lamp in view), starts the installed ``locator`` (its own process, over DDS on loopback, an
unshared domain) and publishes the frames to it in turn at ``--rate`` frames/s for ``--seconds``,
as a camera driver does: best effort, depth 1, ``camera_info`` with each image, stamped when sent
(bgr8 ``image_raw``, or JPEG on ``image_raw/compressed`` for the JPEG look). The locator processes
the newest frame and drops the ones that arrive while it is busy. Reports per case the share of
frames answered (a ``vlp/processed`` header with the frame's stamp), the share that reached a pose,
the latency from sending to the answer (median, max), and the locator's peak resident memory (VmHWM),
against the targets: at least 95 % of frames answered, latency median at most 33 ms, RSS at most
450 MB.

The frames are sent from this process, which serialises them (a 4K frame is 25 MB) on the same
cores: on a 2-core machine the sender's share of the CPU is part of what the numbers show.
"""
from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path
import subprocess
import sys
import tempfile
import time

import numpy as np
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Header

from vlp_ros.benchmarks.pipeline_speed import lamp_poses, scene, SCENES, SPEED_LOOKS
from vlp_ros.benchmarks.startup import locator_subscribed, wait_until_gone
from vlp_ros.core.camera import CameraModel
from vlp_ros.evaluation.metrics import format_table
from vlp_ros.nodes.dds_environment import (claim_domain_id, installed_executable, loopback_profile, stop_process,
                                           use_loopback_dds)
from vlp_ros.sim.looks import apply_look, LOOKS
from vlp_ros.sim.recording import write_params
from vlp_ros.sim.render import render_frame
from vlp_ros.sim.scenarios import Scenario
from vlp_ros.sim.sensor import encode_jpeg

# A camera driver's publisher: best effort, the newest frame only (README, "The environment it needs").
CAMERA_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
ANSWER_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)
MIN_ANSWERED, MAX_LATENCY_MEDIAN_S, MAX_RSS_MB = 0.95, 0.033, 450.0
# After the last frame, answers still in flight get this long.
DRAIN_S = 2.0


def camera_info(camera: CameraModel) -> CameraInfo:
    """Return the camera_info a driver sends with each image of ``camera``."""
    msg = CameraInfo(width=camera.width, height=camera.height, distortion_model=camera.model)
    msg.d = [float(v) for v in camera.D]
    msg.k = [float(v) for v in camera.K.reshape(-1)]
    msg.r = [float(v) for v in np.eye(3).reshape(-1)]
    msg.p = [float(v) for v in np.hstack([camera.K, np.zeros((3, 1))]).reshape(-1)]
    return msg


def frame_messages(scenario: Scenario, count: int, rng: np.random.Generator) -> list[Image | CompressedImage]:
    """Return ``count`` frames of ``scenario`` with a lamp in view, as the messages a camera driver sends."""
    messages: list[Image | CompressedImage] = []
    for index in lamp_poses(scenario, count):
        image = render_frame(scenario.camera, scenario.poses[index], scenario.lamps + scenario.clutter,
                             scenario.sensor, float(scenario.frame_times()[index]), rng).image
        if scenario.jpeg_quality is not None:
            messages.append(CompressedImage(format='jpeg', data=encode_jpeg(image, scenario.jpeg_quality).tobytes()))
            continue
        height, width = image.shape[:2]
        messages.append(Image(height=height, width=width, encoding='bgr8', step=width * 3,
                              data=np.ascontiguousarray(image).tobytes()))
    return messages


def peak_rss_mb(pid: int) -> float:
    """Return the process's peak resident set size (VmHWM) in MB."""
    for line in Path(f'/proc/{pid}/status').read_text().splitlines():
        if line.startswith('VmHWM:'):
            return int(line.split()[1]) / 1024.0
    return float('nan')


class Stream:
    """Sends frames to the locator and times its answers (``vlp/processed``) by stamp."""

    def __init__(self, node, compressed: bool) -> None:
        self.node = node
        topic = 'image_raw/compressed' if compressed else 'image_raw'
        self.images = node.create_publisher(CompressedImage if compressed else Image, topic, CAMERA_QOS)
        self.infos = node.create_publisher(CameraInfo, 'camera_info', CAMERA_QOS)
        self.sent: dict[int, float] = {}
        self.answers: dict[int, tuple[float, str]] = {}
        node.create_subscription(Header, 'vlp/processed', self._on_processed, ANSWER_QOS)

    def _on_processed(self, msg: Header) -> None:
        stamp = msg.stamp.sec * 1_000_000_000 + msg.stamp.nanosec
        self.answers[stamp] = (time.monotonic(), msg.frame_id)

    def send(self, image: Image | CompressedImage, info: CameraInfo) -> None:
        """Publish ``image`` with ``info``, stamped now."""
        stamp = self.node.get_clock().now().to_msg()
        image.header = info.header = Header(stamp=stamp, frame_id='camera')
        self.infos.publish(info)
        self.sent[stamp.sec * 1_000_000_000 + stamp.nanosec] = time.monotonic()
        self.images.publish(image)


def run_case(node, executor, scenario: Scenario, messages: list, seconds: float, rate: float,
             workdir: Path) -> tuple[Stream, float]:
    """Stream ``messages`` into a fresh locator for ``scenario``; return the stream and the locator's peak RSS (MB)."""
    params = workdir / 'params.yaml'
    write_params(params, scenario, imu=False)
    wait_until_gone(node)
    log = open(workdir / 'locator.log', 'w')
    process = subprocess.Popen([str(installed_executable('locator')), '--ros-args', '--params-file', str(params)],
                               stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT)
    try:
        while not locator_subscribed(node):
            if process.poll() is not None:
                raise RuntimeError(f'the locator exited: see {workdir / "locator.log"}')
            executor.spin_once(timeout_sec=0.05)
        stream = Stream(node, scenario.jpeg_quality is not None)
        info = camera_info(scenario.camera)
        # Let the new publishers match the locator's subscriptions before the first frame.
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        started = time.monotonic()
        for n in range(int(round(seconds * rate))):
            while time.monotonic() < started + n / rate:
                executor.spin_once(timeout_sec=max(0.0, min(0.005, started + n / rate - time.monotonic())))
            stream.send(messages[n % len(messages)], info)
        deadline = time.monotonic() + DRAIN_S
        while time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        rss = peak_rss_mb(process.pid)
        node.destroy_publisher(stream.images)
        node.destroy_publisher(stream.infos)
        return stream, rss
    finally:
        stop_process(process, timeout=20.0)
        log.close()


def case_row(name: str, look: str, stream: Stream, rss: float) -> list[str]:
    """Return the table row of one streamed case."""
    answered = [stamp for stamp in stream.sent if stamp in stream.answers]
    latencies = np.array([stream.answers[s][0] - stream.sent[s] for s in answered]) * 1e3
    posed = sum(stream.answers[s][1] == 'pose' for s in answered)
    share = len(answered) / max(len(stream.sent), 1)
    median = float(np.median(latencies)) if latencies.size else float('nan')
    met = share >= MIN_ANSWERED and median <= 1e3 * MAX_LATENCY_MEDIAN_S and rss <= MAX_RSS_MB
    return [name, look, str(len(stream.sent)), f'{100 * share:.0f}', f'{100 * posed / max(len(stream.sent), 1):.0f}',
            f'{median:.0f}', f'{latencies.max():.0f}' if latencies.size else '-', f'{rss:.0f}',
            'yes' if met else 'NO']


def main(argv: Sequence[str] | None = None) -> int:
    """Stream every case and print the table."""
    parser = argparse.ArgumentParser(prog='python -m vlp_ros.benchmarks.camera_rate',
                                     description=__doc__.strip().splitlines()[0])
    parser.add_argument('--scene', action='append', choices=SCENES, default=None, help='only these scenes')
    parser.add_argument('--look', action='append', choices=SPEED_LOOKS, default=None, help='only these looks')
    parser.add_argument('--seconds', type=float, default=10.0, help='streaming time per case')
    parser.add_argument('--rate', type=float, default=30.0, help='frames per second')
    parser.add_argument('--frames', type=int, default=6, help='distinct frames per case, sent in turn')
    parser.add_argument('--seed', type=int, default=3)
    args = parser.parse_args(argv)
    if args.seconds <= 0.0 or args.rate <= 0.0 or args.frames < 1:
        parser.error('--seconds, --rate and --frames must be positive')
    use_loopback_dds(loopback_profile(), claim_domain_id())
    rclpy.init()
    node = rclpy.create_node('vlp_camera_rate')
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    rng = np.random.default_rng(args.seed)
    rows = []
    try:
        for name in args.scene or SCENES:
            base = scene(name, args.seed)
            for look in args.look or SPEED_LOOKS:
                scenario = apply_look(base, LOOKS[look], args.seed)
                messages = frame_messages(scenario, args.frames, rng)
                with tempfile.TemporaryDirectory(prefix='vlp_camera_rate_') as workdir:
                    stream, rss = run_case(node, executor, scenario, messages, args.seconds, args.rate, Path(workdir))
                rows.append(case_row(name, look, stream, rss))
                print(' '.join(rows[-1]), file=sys.stderr, flush=True)
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
    print(f'Frames sent at {args.rate:g} frames/s for {args.seconds:g} s per case ({args.frames} distinct frames); '
          f'targets: answered >= {100 * MIN_ANSWERED:.0f} %, latency median <= {1e3 * MAX_LATENCY_MEDIAN_S:.0f} ms, '
          f'peak RSS <= {MAX_RSS_MB:.0f} MB')
    print(format_table(rows, ('scene', 'look', 'sent', 'answered %', 'posed %', 'latency median ms',
                              'latency max ms', 'peak RSS MB', 'met')))
    return 0


if __name__ == '__main__':
    sys.exit(main())
