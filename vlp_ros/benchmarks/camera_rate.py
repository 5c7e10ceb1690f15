"""
Camera rate through the node: python -m vlp_ros.benchmarks.camera_rate [--scene NAME] [--look NAME] [--recording DIR].

Streams frames into the installed ``locator`` (its own process, over DDS on loopback, an unshared domain) at
``--rate`` frames/s for ``--seconds``, as a camera driver does: best effort, depth 1, ``camera_info`` (and the
accelerometer's reading on ``imu`` where there is one) with each image, everything stamped when sent. Two kinds
of stream:

- a scene and look of ``pipeline_speed`` rendered by the simulator: ``--frames`` frames up to a camera pose with
  a lamp in view (the robot's own video, or a still scene's pose held still), raw bgr8 on ``image_raw`` (4K:
  25 MB a frame) or JPEG on ``image_raw/compressed`` for the JPEG look; the locator runs with ``imu.enabled``
  (one lamp held still is ambiguous without gravity);
- a recording of another renderer (``--recording DIR``: a folder with ``bag/`` and ``params.yaml``, as in
  ../shared/data/foreign_frames): its JPEG frames on ``image_raw/compressed`` with its camera_info and IMU,
  looped with fresh stamps, the locator run with the folder's params.yaml.

Without options every scene and look and every recording under ``../shared/data/foreign_frames`` is streamed.
Reports per stream the share of frames answered (a ``vlp/processed`` header with the frame's stamp), the share
that reached a pose, the share the locator received and the frames it superseded (its ``/diagnostics``: it
processes the newest frame and drops the ones that arrive while it is busy), the latency from the frame's stamp
(when it was sent) to its answer arriving here (median, max) and the locator's own median from a frame's arrival
to its answer (its ``/diagnostics``), and the locator's peak resident memory (VmHWM),
against the targets: at least 95 % of frames answered, latency median at most 33 ms, RSS at most 450 MB.

The frames are sent from a process of their own, serialised once (each send writes its stamp into the
bytes); its copies of the frames run on the same cores: on a 2-core machine the sender's share of the CPU is
part of what the numbers show.
"""
from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import dataclass
import multiprocessing
from pathlib import Path
import struct
import subprocess
import sys
import tempfile
import time

from diagnostic_msgs.msg import DiagnosticArray
import numpy as np
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, Imu
from std_msgs.msg import Header

from vlp_ros.bags.reader import Bag, header_stamp
from vlp_ros.benchmarks.pipeline_speed import lamp_poses, scene, SCENES, SPEED_LOOKS, VIDEO_SCENES
from vlp_ros.benchmarks.startup import locator_subscribed, wait_until_gone
from vlp_ros.core.camera import CameraModel
from vlp_ros.evaluation.metrics import format_table
from vlp_ros.nodes.dds_environment import (claim_domain_id, installed_executable, loopback_profile, stop_process,
                                           use_loopback_dds)
from vlp_ros.sim.imu import specific_force
from vlp_ros.sim.looks import apply_look, LOOKS
from vlp_ros.sim.recording import write_params
from vlp_ros.sim.render import render_frame
from vlp_ros.sim.scenarios import Scenario
from vlp_ros.sim.sensor import encode_jpeg

# A camera driver's publisher: best effort, the newest frame only (README, "The environment it needs").
CAMERA_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
ANSWER_QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.BEST_EFFORT)
MIN_ANSWERED, MAX_LATENCY_MEDIAN_S, MAX_RSS_MB = 0.95, 0.033, 450.0
# After the last frame, answers still in flight get this long.
DRAIN_S = 2.0
# Where a serialised message that starts with a std_msgs/Header (little-endian CDR) holds its stamp: after the
# 4-byte encapsulation header.
STAMP_OFFSET, STAMP_FORMAT = 4, '<iI'
CDR_LITTLE_ENDIAN = b'\x00\x01'
RECORDINGS = Path('../shared/data/foreign_frames')
IMAGE, INFO, IMU = 'image', 'camera_info', 'imu'


@dataclass
class Stream:
    """
    What one case sends: per frame, serialised messages (topic kind, CDR bytes) in the order they are sent.

    ``params`` is the locator's params file (YAML text).
    """

    scene: str
    look: str
    compressed: bool
    frames: list[list[tuple[str, bytes]]]
    params: str


def camera_info(camera: CameraModel) -> CameraInfo:
    """Return the camera_info a driver sends with each image of ``camera``."""
    msg = CameraInfo(width=camera.width, height=camera.height, distortion_model=camera.model)
    msg.d = [float(v) for v in camera.D]
    msg.k = [float(v) for v in camera.K.reshape(-1)]
    msg.r = [float(v) for v in np.eye(3).reshape(-1)]
    msg.p = [float(v) for v in np.hstack([camera.K, np.zeros((3, 1))]).reshape(-1)]
    return msg


def imu_message(force: np.ndarray, noise_std: float) -> Imu:
    """Return an accelerometer-only Imu message (orientation and angular velocity marked absent)."""
    msg = Imu()
    msg.orientation_covariance[0] = msg.angular_velocity_covariance[0] = -1.0
    msg.linear_acceleration.x, msg.linear_acceleration.y, msg.linear_acceleration.z = (float(v) for v in force)
    msg.linear_acceleration_covariance = [float(v) for v in (np.eye(3) * noise_std ** 2).reshape(-1)]
    return msg


def frame_messages(name: str, scenario: Scenario, count: int,
                   rng: np.random.Generator) -> tuple[list[Image | CompressedImage], list[Imu]]:
    """
    Return ``count`` frames of ``scenario`` with a lamp in view, as a camera driver sends them, and the IMU at each.

    A video scene's own consecutive frames (a lamp in each); a still scene's pose held still (the beacon moving on).
    """
    shown = lamp_poses(scenario, len(scenario.poses))
    runs = [i for i in shown if all(j in shown for j in range(i - count + 1, i + 1))]
    video = name in VIDEO_SCENES and bool(runs)
    index = runs[len(runs) // 2] if video else shown[len(shown) // 2]
    start = float(scenario.frame_times()[index])
    messages: list[Image | CompressedImage] = []
    imus: list[Imu] = []
    for k in range(count):
        pose = index - count + 1 + k if video else index
        imus.append(imu_message(specific_force(scenario.poses[pose], scenario.accelerations[pose], scenario.imu_noise,
                                               rng), scenario.imu_noise))
        image = render_frame(scenario.camera, scenario.poses[pose], scenario.lamps + scenario.clutter,
                             scenario.sensor, start + (k - count + 1) / scenario.frame_rate, rng).image
        if scenario.jpeg_quality is not None:
            messages.append(CompressedImage(format='jpeg', data=encode_jpeg(image, scenario.jpeg_quality).tobytes()))
            continue
        height, width = image.shape[:2]
        messages.append(Image(height=height, width=width, encoding='bgr8', step=width * 3,
                              data=np.ascontiguousarray(image).tobytes()))
    return messages, imus


def serialised(message) -> bytes:
    """Return ``message`` serialised with an empty stamp (written when sent) and the camera's frame_id."""
    message.header = Header(frame_id='camera')
    return serialize_message(message)


def simulated_stream(name: str, look: str, frames: int, seed: int, rng: np.random.Generator,
                     workdir: Path) -> Stream:
    """Return ``frames`` rendered frames of scene ``name`` in ``look``, each after its IMU and camera_info."""
    scenario = apply_look(scene(name, seed), LOOKS[look], seed)
    messages, imus = frame_messages(name, scenario, frames, rng)
    info = serialised(camera_info(scenario.camera))
    params = workdir / 'params.yaml'
    write_params(params, scenario, imu=True)
    return Stream(name, look, scenario.jpeg_quality is not None,
                  [[(IMU, serialised(imu)), (INFO, info), (IMAGE, serialised(message))]
                   for message, imu in zip(messages, imus)], params.read_text())


def recorded_stream(folder: Path) -> Stream:
    """
    Return the JPEG frames of a recording (``folder``/bag, ``folder``/params.yaml) as a camera driver sends them.

    Each frame goes after the camera_info recorded last before it and the IMU reading nearest its stamp.
    """
    bag = Bag(folder / 'bag')
    topics = [topic for topic in ('/image_raw/compressed', '/camera_info', '/imu') if topic in bag.topics]
    images, infos, imus = [], [], []
    for message in bag.messages(topics):
        if message.data[:2] != CDR_LITTLE_ENDIAN:
            raise ValueError(f'{folder}: {message.topic} is not little-endian CDR')
        stamp = header_stamp(message.data)
        kind = {'/image_raw/compressed': images, '/camera_info': infos, '/imu': imus}[message.topic]
        kind.append((stamp[0] * 1_000_000_000 + stamp[1], message.data))
    bag.close()
    if not images or not infos:
        raise ValueError(f'{folder}: no /image_raw/compressed frames or no /camera_info in its bag')
    frames = []
    for stamp, data in images:
        info = max((m for m in infos if m[0] <= stamp), default=infos[0], key=lambda m: m[0])[1]
        sent = [(INFO, info), (IMAGE, data)]
        if imus:
            sent.insert(0, (IMU, min(imus, key=lambda m: abs(m[0] - stamp))[1]))
        frames.append(sent)
    look = next((word for word in reversed(folder.name.split('_')) if word in LOOKS), '-')
    return Stream(f'recorded {folder.name.removesuffix("_" + look)}', look, True, frames,
                  (folder / 'params.yaml').read_text())


def send_frames(stream: Stream, seconds: float, rate: float) -> None:
    """
    Publish ``stream``'s frames in turn at ``rate`` for ``seconds``, each stamped when sent.

    Runs in a process of its own (``run_case``), so that sending does not delay the answers.
    """
    rclpy.init()
    node = rclpy.create_node('vlp_camera_rate_sender')
    publishers = {IMAGE: node.create_publisher(CompressedImage if stream.compressed else Image,
                                               'image_raw/compressed' if stream.compressed else 'image_raw',
                                               CAMERA_QOS),
                  INFO: node.create_publisher(CameraInfo, 'camera_info', CAMERA_QOS),
                  IMU: node.create_publisher(Imu, 'imu', CAMERA_QOS)}
    # Serialised once: each send only writes its stamp into the bytes, as a camera driver's buffer is sent as it is.
    frames = [[(kind, bytearray(data)) for kind, data in frame] for frame in stream.frames]
    # Let the publishers match the locator's subscriptions before the first frame.
    deadline = time.monotonic() + 10.0
    while publishers[IMAGE].get_subscription_count() == 0 and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(0.5)
    started = time.monotonic()
    for n in range(int(round(seconds * rate))):
        time.sleep(max(0.0, started + n / rate - time.monotonic()))
        stamp = node.get_clock().now().to_msg()
        for kind, data in frames[n % len(frames)]:
            struct.pack_into(STAMP_FORMAT, data, STAMP_OFFSET, stamp.sec, stamp.nanosec)
            publishers[kind].publish(bytes(data))
    node.destroy_node()
    rclpy.try_shutdown()


def peak_rss_mb(pid: int) -> float:
    """Return the process's peak resident set size (VmHWM) in MB."""
    for line in Path(f'/proc/{pid}/status').read_text().splitlines():
        if line.startswith('VmHWM:'):
            return int(line.split()[1]) / 1024.0
    return float('nan')


class Answers:
    """
    The locator's answers (``vlp/processed``): per image stamp, the latency from the stamp and the outcome.

    And its last ``/diagnostics``, as key -> value.
    """

    def __init__(self, node) -> None:
        self.node = node
        self.latency: dict[int, float] = {}
        self.outcome: dict[int, str] = {}
        self.diagnostics: dict[str, str] = {}
        node.create_subscription(Header, 'vlp/processed', self._on_processed, ANSWER_QOS)
        node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics, 10)

    def _on_processed(self, msg: Header) -> None:
        stamp = msg.stamp.sec * 1_000_000_000 + msg.stamp.nanosec
        self.latency[stamp] = (self.node.get_clock().now().nanoseconds - stamp) * 1e-9
        self.outcome[stamp] = msg.frame_id

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name == 'vlp_ros: locator':
                self.diagnostics = {value.key: value.value for value in status.values}


def run_case(node, executor, stream: Stream, seconds: float, rate: float, workdir: Path) -> tuple[Answers, int, float]:
    """
    Stream ``stream`` into a fresh locator.

    Return its answers, the frames sent and the locator's peak RSS (MB).
    """
    params = workdir / 'params.yaml'
    params.write_text(stream.params)
    wait_until_gone(node)
    log = open(workdir / 'locator.log', 'w')
    process = subprocess.Popen([str(installed_executable('locator')), '--ros-args', '--params-file', str(params)],
                               stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT)
    try:
        while not locator_subscribed(node):
            if process.poll() is not None:
                raise RuntimeError(f'the locator exited: see {workdir / "locator.log"}')
            executor.spin_once(timeout_sec=0.05)
        answers = Answers(node)
        sender = multiprocessing.get_context('spawn').Process(target=send_frames, args=(stream, seconds, rate))
        sender.start()
        while sender.is_alive():
            executor.spin_once(timeout_sec=0.01)
        # Until the answers in flight and a /diagnostics sent after the last frame are in.
        deadline = time.monotonic() + DRAIN_S
        while time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.01)
        rss = peak_rss_mb(process.pid)
        return answers, int(round(seconds * rate)), rss
    finally:
        stop_process(process, timeout=20.0)
        log.close()


def case_row(stream: Stream, answers: Answers, sent: int, rss: float) -> list[str]:
    """Return the table row of one streamed case."""
    latencies = np.array(list(answers.latency.values())) * 1e3
    posed = sum(outcome == 'pose' for outcome in answers.outcome.values())
    share = len(latencies) / max(sent, 1)
    median = float(np.median(latencies)) if latencies.size else float('nan')
    met = share >= MIN_ANSWERED and median <= 1e3 * MAX_LATENCY_MEDIAN_S and rss <= MAX_RSS_MB
    received = int(answers.diagnostics.get('frames received', 0))
    superseded = answers.diagnostics.get('frames superseded by newer ones', '-')
    return [stream.scene, stream.look, str(sent), f'{100 * received / max(sent, 1):.0f}', superseded,
            f'{100 * share:.0f}', f'{100 * posed / max(sent, 1):.0f}', f'{median:.0f}',
            f'{latencies.max():.0f}' if latencies.size else '-',
            answers.diagnostics.get('latency median (ms)', '-'), f'{rss:.0f}', 'yes' if met else 'NO']


def recordings(folders: Sequence[Path]) -> list[Path]:
    """Return the recording folders given, or every one under RECORDINGS whose bag has JPEG frames."""
    if folders:
        return list(folders)
    if not RECORDINGS.is_dir():
        return []
    return [folder for folder in sorted(RECORDINGS.iterdir())
            if (folder / 'params.yaml').is_file() and (folder / 'bag').is_dir()]


def main(argv: Sequence[str] | None = None) -> int:
    """Stream every case and print the table."""
    parser = argparse.ArgumentParser(prog='python -m vlp_ros.benchmarks.camera_rate',
                                     description=__doc__.strip().splitlines()[0])
    parser.add_argument('--scene', action='append', choices=SCENES, default=None, help='only these scenes')
    parser.add_argument('--look', action='append', choices=SPEED_LOOKS, default=None, help='only these looks')
    parser.add_argument('--recording', action='append', type=Path, default=[],
                        help=f'a recording folder (bag/, params.yaml); default: those under {RECORDINGS}')
    parser.add_argument('--seconds', type=float, default=10.0, help='streaming time per case')
    parser.add_argument('--rate', type=float, default=30.0, help='frames per second')
    parser.add_argument('--frames', type=int, default=6, help='distinct rendered frames per case, sent in turn')
    parser.add_argument('--seed', type=int, default=3)
    args = parser.parse_args(argv)
    if args.seconds <= 0.0 or args.rate <= 0.0 or args.frames < 1:
        parser.error('--seconds, --rate and --frames must be positive')
    for folder in args.recording:
        if not ((folder / 'params.yaml').is_file() and (folder / 'bag').is_dir()):
            parser.error(f'--recording {folder}: needs bag/ and params.yaml')
    simulate = not args.recording or bool(args.scene or args.look)
    folders = recordings(args.recording) if not (args.scene or args.look) or args.recording else []
    use_loopback_dds(loopback_profile(), claim_domain_id())
    rclpy.init()
    node = rclpy.create_node('vlp_camera_rate')
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    rng = np.random.default_rng(args.seed)
    cases = [(name, look) for name in (args.scene or SCENES) for look in (args.look or SPEED_LOOKS)] if simulate else []
    rows = []
    try:
        for case in [*cases, *folders]:
            with tempfile.TemporaryDirectory(prefix='vlp_camera_rate_') as workdir:
                stream = (recorded_stream(case) if isinstance(case, Path)
                          else simulated_stream(*case, args.frames, args.seed, rng, Path(workdir)))
                answers, sent, rss = run_case(node, executor, stream, args.seconds, args.rate, Path(workdir))
            rows.append(case_row(stream, answers, sent, rss))
            print(' '.join(rows[-1]), file=sys.stderr, flush=True)
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
    print(f'Frames sent at {args.rate:g} frames/s for {args.seconds:g} s per case ({args.frames} distinct rendered '
          f'frames, or every frame of a recording); targets: answered >= {100 * MIN_ANSWERED:.0f} %, latency median '
          f'<= {1e3 * MAX_LATENCY_MEDIAN_S:.0f} ms, peak RSS <= {MAX_RSS_MB:.0f} MB')
    print(format_table(rows, ('scene', 'look', 'sent', 'received %', 'superseded', 'answered %', 'posed %',
                              'latency median ms', 'latency max ms', 'in locator ms', 'peak RSS MB', 'met')))
    return 0


if __name__ == '__main__':
    sys.exit(main())
