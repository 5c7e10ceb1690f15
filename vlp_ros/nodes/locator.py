"""
The `locator` node: camera images in, camera poses out.

Callbacks only keep the newest frame. A decoder thread parses and decodes it while the
worker thread runs the frame before it through the ROS-free pipeline
(vlp_ros.pipeline.frame) and publishes: on two cores a frame's JPEG decode (libjpeg-turbo,
which runs without the GIL, as the pipeline's numba kernels do) overlaps the previous
frame's processing. Each stage holds at most one waiting frame, the newest: a frame that
arrives while the stages are busy replaces the waiting one (counted as superseded), so
latency never grows.

The worker first makes the pipeline's compiled kernels ready (vlp_ros.pipeline.warm_up),
so the first frames take no longer than later ones. The node subscribes when they are
loaded from numba's cache; if numba has to compile them (no cache: minutes), it
subscribes at once, drops frames as ``kernels_compiling`` and says so in its
diagnostics, and answers frames from the moment the kernels are ready.
"""
from __future__ import annotations

from collections import deque
from collections.abc import Callable
import ctypes
from dataclasses import dataclass
import gc
import os
import statistics
import sys
import threading
import time

from diagnostic_msgs.msg import DiagnosticArray, KeyValue
from geometry_msgs.msg import Pose as PoseMsg
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
import numba.core.event
import numpy as np
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, qos_profile_sensor_data, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, Imu
from std_msgs.msg import Header
from visualization_msgs.msg import MarkerArray

from vlp_ros.beacon.camera_settings import packet_setting_advice, tone_setting_advice
from vlp_ros.core.camera import CameraModel
from vlp_ros.core.gravity import GravityBuffer
from vlp_ros.core.mounting import publishable_covariance
from vlp_ros.core.pose import Pose
from vlp_ros.images.buffers import FrameBuffers
from vlp_ros.images.conversion import decode_compressed, ImageConversionError, pixels_of
from vlp_ros.images.message import MessageFormatError, parse_compressed_image, parse_image
from vlp_ros.nodes.diagnostics import diagnostic_array
from vlp_ros.nodes.lifecycle import run_node
from vlp_ros.nodes.parameters import check_qos_overrides, declare_locator_parameters
from vlp_ros.nodes.visualization import bgr8_image, lamp_markers
from vlp_ros.pipeline.config import ConfigError, settings_from_parameters
from vlp_ros.pipeline.debug_view import debug_view
from vlp_ros.pipeline.frame import FrameResult, Pipeline
from vlp_ros.pipeline.frame_stats import FrameStats
from vlp_ros.pipeline.warm_up import warm_up

THROTTLE_S = 5.0
# glibc's mallopt parameters (malloc.h).
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_ARENA_MAX = -1, -3, -8
# Every block up to a 4K bgr8 frame's 25 MB comes from the heap, and the heap keeps up to five such frames free.
_HEAP_BLOCK_LIMIT, _HEAP_KEPT_FREE = 32 << 20, 128 << 20
# How often the start checks whether the kernels are ready or being compiled.
_WARM_UP_POLL_S = 0.05


class RecentDurations:
    """The median of a stage's last few durations (s): how long its next run is expected to take."""

    def __init__(self, count: int = 15) -> None:
        self._durations: deque[float] = deque(maxlen=count)

    def add(self, seconds: float) -> None:
        self._durations.append(seconds)

    def median(self) -> float:
        """Return the median; 0 before the first run."""
        return statistics.median(self._durations) if self._durations else 0.0


@dataclass(frozen=True)
class DecodedFrame:
    """A frame the decoder has made ready for the pipeline: its pixels, camera, stamp, frame_id and arrival time."""

    pixels: np.ndarray
    camera: CameraModel
    stamp_ns: int
    frame_id: str
    received: float


class _CompileWatch(numba.core.event.Listener):
    """Sets ``started`` when numba starts compiling a kernel (a kernel not found in its cache)."""

    def __init__(self) -> None:
        self.started = threading.Event()

    def on_start(self, event: numba.core.event.Event) -> None:
        self.started.set()

    def on_end(self, event: numba.core.event.Event) -> None:
        pass


class Locator(Node):

    def __init__(self) -> None:
        # Before anything that can fail: rclpy destroys a node that failed to start, and destroy_node reads these.
        self._pending: tuple[bytes, float] | None = None
        self._decoded: DecodedFrame | None = None
        # When the worker took its frame (None while it waits), and the usual time of each stage.
        self._busy_since: float | None = None
        self._process_times, self._decode_times = RecentDurations(), RecentDurations()
        # The decoder's output arrays, written again once nothing holds their frame: one frame being decoded, one
        # waiting and one being processed.
        self._buffers = FrameBuffers(3)
        self._wake = threading.Condition()
        self._running = True
        self._kernels_ready = threading.Event()
        self._threads: list[threading.Thread] = []
        # Overrides declared on arrival, so that misspelt parameters can be named (nodes.parameters).
        super().__init__('vlp_locator', automatically_declare_parameters_from_overrides=True)
        self.settings = settings_from_parameters(declare_locator_parameters(self))
        self._image_topic = self.resolve_topic_name('image_raw') + (
            '/compressed' if self.settings.image_transport == 'compressed' else '')
        check_qos_overrides(self, self._image_topic)
        self.pipeline = Pipeline(self.settings)
        self.stats = FrameStats()
        self._camera: CameraModel | None = None
        self._gravity = GravityBuffer(self.settings.imu_rotation, self.settings.imu_max_age)

        self.pose_pub = self.create_publisher(PoseStamped, 'vlp/pose', 10)
        self.pose_cov_pub = self.create_publisher(PoseWithCovarianceStamped, 'vlp/pose_with_covariance', 10)
        # The camera optical frame's own pose, whichever frame vlp/pose carries.
        self.camera_pose_pub = self.create_publisher(PoseStamped, 'vlp/camera_pose', 10)
        # One Header per processed frame (stamp = image stamp, frame_id = outcome), so a
        # player can wait for each frame to be answered even when it yields no pose.
        self.processed_pub = self.create_publisher(Header, 'vlp/processed', 10)
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        # What users look at: the map (latched for late subscribers such as RViz) and what the frame showed.
        self.lamps_pub = self.create_publisher(MarkerArray, 'vlp/lamps', QoSProfile(
            depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.debug_image_pub = self.create_publisher(Image, 'vlp/debug_image', 1)
        self._lamps_in_pose: set[int] | None = None
        self.debug_images_drawn = 0
        self._show_lamps_used(set())
        self._advise_on_camera_settings()
        self._report_frames()
        self._start_and_wait_for_kernels()
        self._subscribe()
        self.create_timer(1.0, self._publish_diagnostics)
        self.get_logger().info(
            f'locating with {len(self.settings.lamps)} lamps ({self.settings.beacon.mode} beacon, '
            f'{self.settings.solver} solver) on {self._image_topic}')

    def _advise_on_camera_settings(self) -> None:
        """Warn once of beacon settings under which lamps are identified less often (never wrongly)."""
        beacon = self.settings.beacon
        if beacon.mode == 'tone':
            frequencies = {lamp.name: lamp.frequency for lamp in self.settings.lamps}
            advice = tone_setting_advice(frequencies, beacon.row_time, beacon.exposure, beacon.frequency_tolerance,
                                         beacon.row_time_tolerance)
        else:
            advice = packet_setting_advice(beacon.chip_rate, beacon.row_time, beacon.exposure, beacon.id_bits)
        for text in advice:
            self.get_logger().warning(text)

    def _report_frames(self) -> None:
        mounting = self.settings.mounting
        if mounting is None:
            self.get_logger().info(f'publishing the camera optical frame in {self.settings.map_frame}')
            return
        quaternion = ', '.join(f'{v:.4g}' for v in Rotation.from_matrix(mounting.rotation).as_quat())
        self.get_logger().info(
            f'publishing {self.settings.base_frame} in {self.settings.map_frame}, the camera optical frame at '
            f'{[round(float(v), 4) for v in mounting.translation]} m, [{quaternion}] in it '
            f'(vlp/camera_pose carries the camera)')
        floor = self.settings.floor
        if floor is not None:
            self.get_logger().info(
                f'{self.settings.base_frame} on a horizontal floor at z = {floor.height:g} m: its height known to '
                f'{floor.sigma_height:g} m and its tilt to {floor.sigma_tilt:g} rad (planar.*)')

    def _start_and_wait_for_kernels(self) -> None:
        """
        Start the worker (which first makes the kernels ready) and the decoder.

        Return once the kernels are loaded from the cache, or as soon as numba starts compiling one (minutes).
        """
        watch = _CompileWatch()
        numba.core.event.register('numba:compile', watch)
        try:
            for target, name in ((self._work, 'vlp_locator_worker'), (self._decode, 'vlp_locator_decoder')):
                thread = threading.Thread(target=target, name=name, daemon=True)
                thread.start()
                self._threads.append(thread)
            while not self._kernels_ready.wait(_WARM_UP_POLL_S):
                if watch.started.is_set():
                    self.get_logger().warning(
                        'compiling the numba kernels (no cache for them: minutes); frames are dropped until they '
                        'are ready')
                    return
        finally:
            numba.core.event.unregister('numba:compile', watch)

    def _warm_up(self) -> None:
        """Load (or, without the build's cache, compile) the kernels a frame needs."""
        started = time.monotonic()
        try:
            warm_up()
        except Exception as err:  # frames are still processed; the first ones only take longer
            self.get_logger().warning(f'loading the compiled kernels failed: {err!r}')
        else:
            self.get_logger().info(f'compiled kernels ready in {time.monotonic() - started:.1f} s')
        finally:
            keep_start_objects_out_of_collections()
            keep_frames_in_the_heap()
            self._kernels_ready.set()

    def _subscribe(self) -> None:
        reliability = (ReliabilityPolicy.RELIABLE if self.settings.qos_reliability == 'reliable'
                       else ReliabilityPolicy.BEST_EFFORT)
        qos = QoSProfile(depth=self.settings.qos_depth, reliability=reliability)
        # camera_info and imu before the image: the executor serves the messages waiting at one wake in the
        # order the subscriptions were made, so a camera_info that came before its frame is read before it.
        # Best effort matches both reliable and best-effort publishers.
        self.create_subscription(CameraInfo, 'camera_info', self._on_camera_info, qos_profile_sensor_data)
        if self.settings.imu_enabled:
            self.create_subscription(Imu, 'imu', self._on_imu, QoSProfile(
                depth=50, reliability=ReliabilityPolicy.BEST_EFFORT))
        # The compressed topic is derived from the resolved name so that remapping image_raw moves it too.
        # qos_overrides.<topic>.subscription.* (checked at start) win over qos.*, as in any rclpy node.
        image_type = CompressedImage if self.settings.image_transport == 'compressed' else Image
        subscription = self.create_subscription(image_type, self._image_topic, self._on_frame, qos, raw=True,
                                                qos_overriding_options=QoSOverridingOptions.with_default_policies())
        if subscription.qos_profile.reliability != ReliabilityPolicy.RELIABLE:
            self._warn_without_large_data_transport()

    def _warn_without_large_data_transport(self) -> None:
        large_data = os.environ.get('FASTDDS_BUILTIN_TRANSPORTS', '').upper().startswith('LARGE_DATA')
        # A profiles file means the transports were configured on purpose (e.g. config/fastdds_loopback.xml).
        profiles = os.environ.get('FASTDDS_DEFAULT_PROFILES_FILE') or os.environ.get('FASTRTPS_DEFAULT_PROFILES_FILE')
        if not (large_data or profiles):
            self.get_logger().warning(
                '\n*** FASTDDS_BUILTIN_TRANSPORTS is not LARGE_DATA: with Fast DDS defaults a best-effort '
                'subscriber silently receives NOTHING for images over ~512 KB. ***\n'
                '*** export FASTDDS_BUILTIN_TRANSPORTS=LARGE_DATA (or source scripts/setup_env.sh) for '
                'this node and the camera driver, or set qos.reliability: reliable. ***')

    def _on_frame(self, raw: bytes) -> None:
        self.stats.frame_received()
        if not self._kernels_ready.is_set():
            self.stats.frame_dropped('kernels_compiling')
            return
        if self._camera is None:
            # Decided on arrival: a camera_info that arrives while the frame waits is not its camera's.
            self.stats.frame_dropped('no_camera_info')
            self.get_logger().warning('no valid camera_info yet (K[0] > 0): frames are skipped',
                                      throttle_duration_sec=THROTTLE_S)
            return
        with self._wake:
            if self._pending is not None:
                self.stats.superseded += 1
            self._pending = (raw, time.monotonic())
            self._wake.notify_all()

    def _on_camera_info(self, msg: CameraInfo) -> None:
        try:
            self._camera = CameraModel.from_camera_info(msg.width, msg.height, msg.k, msg.d, msg.distortion_model,
                                                        msg.p, msg.r)
        except ValueError as err:
            self.get_logger().error(f'camera_info ignored: {err}', throttle_duration_sec=THROTTLE_S)

    def _on_imu(self, msg: Imu) -> None:
        a = msg.linear_acceleration
        self._gravity.add(msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec, [a.x, a.y, a.z])

    def _up_at(self, stamp_ns: int) -> np.ndarray | None:
        """Gravity at the image's stamp, waiting up to imu.max_age for the IMU to catch up with the camera."""
        if not self.settings.imu_enabled:
            return None
        deadline = time.monotonic() + self.settings.imu_max_age
        while (self._gravity.newest_stamp_ns or -1) < stamp_ns and time.monotonic() < deadline:
            time.sleep(0.002)
        return self._gravity.up_at(stamp_ns)

    def _next(self, ready: Callable[[], bool]) -> bool:
        """Wait, holding ``_wake``, until ``ready()`` or the node stops; whether the node still runs."""
        while self._running and not ready():
            self._wake.wait(0.5)
        return self._running

    def _decode(self) -> None:
        """Decode the newest frame so that it is ready when the worker is expected to be free."""
        while self._decode_next():
            pass

    def _decode_next(self) -> bool:
        """
        Decode the next frame when it is due; whether the node still runs.

        A function of its own so that nothing refers to the frame's bytes once it returns: a loop's variables
        would hold the last frame (25 MB at 4K raw) while the decoder waits for the next.
        """
        with self._wake:
            while self._running and (delay := self._decode_delay()) != 0.0:
                self._wake.wait(0.5 if delay is None else delay)
            if not self._running:
                return False
            (raw, received), self._pending = self._pending, None
        started = time.monotonic()
        decoded = self._guarded(self._decoded_frame, raw, received)
        self._decode_times.add(time.monotonic() - started)
        if decoded is not None:
            with self._wake:
                self._decoded = decoded
                self._wake.notify_all()
        return True

    def _decode_delay(self) -> float | None:
        """
        Return the seconds until the decoder should start on the waiting frame; None while there is none.

        The decoder starts when the worker is expected to need the frame: its usual processing time after it took
        its own, less the usual decode time. A frame that arrives meanwhile replaces the waiting one; decoding
        earlier would overlap more, but the decoded frame would wait for the worker and grow old.
        """
        if self._pending is None or self._decoded is not None:
            return None
        if self._busy_since is None:
            return 0.0
        due = self._busy_since + self._process_times.median() - self._decode_times.median()
        return max(0.0, due - time.monotonic())

    def _work(self) -> None:
        self._warm_up()
        while self._process_next():
            pass

    def _process_next(self) -> bool:
        """Process and publish the next decoded frame; whether the node still runs. Holds no frame once it returns."""
        with self._wake:
            if not self._next(lambda: self._decoded is not None):
                return False
            frame, self._decoded = self._decoded, None
            self._busy_since = time.monotonic()
            self._wake.notify_all()
        self._guarded(self._process, frame)
        with self._wake:
            self._process_times.add(time.monotonic() - self._busy_since)
            self._busy_since = None
            self._wake.notify_all()
        return True

    def _guarded(self, step: Callable, *args):
        """Return ``step(*args)``; None, the frame dropped and counted, after an internal error."""
        try:
            return step(*args)
        except Exception as err:  # a bad frame must never take the node down
            self.stats.frame_dropped('internal_error')
            self.get_logger().error(f'frame dropped after an internal error: {err!r}',
                                    throttle_duration_sec=THROTTLE_S)
            return None

    def _decoded_frame(self, raw: bytes, received: float) -> DecodedFrame | None:
        """Return the frame's pixels as the pipeline takes them; None (dropped, counted) for a frame unfit for it."""
        try:
            if self.settings.image_transport == 'compressed':
                msg = parse_compressed_image(raw)
                decode = decode_compressed
            else:
                msg = parse_image(raw)
                decode = pixels_of
            pixels = decode(msg, self._buffers)
        except (MessageFormatError, ImageConversionError) as err:
            self.stats.frame_dropped('bad_frame')
            self.get_logger().error(f'frame dropped: {err}', throttle_duration_sec=THROTTLE_S)
            return None
        camera = self._camera
        if (camera.width, camera.height) != (pixels.shape[1], pixels.shape[0]):
            self.stats.frame_dropped('size_mismatch')
            self.get_logger().error(
                f'frame dropped: image is {pixels.shape[1]}x{pixels.shape[0]} but camera_info says '
                f'{camera.width}x{camera.height}', throttle_duration_sec=THROTTLE_S)
            return None
        return DecodedFrame(pixels, camera, msg.stamp_ns, msg.frame_id, received)

    def _process(self, frame: DecodedFrame) -> None:
        result = self.pipeline.process(frame.pixels, frame.camera, frame.stamp_ns * 1e-9, self._up_at(frame.stamp_ns))
        self._publish(result, frame.stamp_ns)
        self.stats.ids_seen(result.decoded_ids, result.unknown_ids)
        self.stats.frame_processed(result.outcome, time.monotonic() - frame.received)
        # After the pose is out, so that neither adds to its latency.
        if result.pose is not None:
            self._show_lamps_used({seen.lamp_id for seen in result.seen if seen.lamp_id is not None})
        self._publish_debug_image(frame.pixels, result, frame.stamp_ns, frame.frame_id)

    def _show_lamps_used(self, lamp_ids: set[int]) -> None:
        if lamp_ids != self._lamps_in_pose:
            self._lamps_in_pose = lamp_ids
            self.lamps_pub.publish(lamp_markers(self.settings.lamps, self.settings.map_frame, lamp_ids))

    def _publish_debug_image(self, pixels: np.ndarray, result: FrameResult, stamp_ns: int, frame_id: str) -> None:
        # Drawing and sending ~1.5 MB costs milliseconds a frame: only for someone looking.
        if self.debug_image_pub.get_subscription_count() == 0:
            return
        header = Header(frame_id=frame_id)
        header.stamp.sec, header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
        self.debug_image_pub.publish(bgr8_image(debug_view(pixels, result), header))
        self.debug_images_drawn += 1

    def _publish(self, result: FrameResult, stamp_ns: int) -> None:
        header = Header(frame_id=self.settings.map_frame)
        header.stamp.sec, header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
        if result.pose is not None:
            self.camera_pose_pub.publish(PoseStamped(header=header, pose=_pose_message(result.pose)))
            mounting = self.settings.mounting
            pose = result.pose if mounting is None else mounting.base_pose(result.pose)
            self.pose_pub.publish(PoseStamped(header=header, pose=_pose_message(pose)))
            covariance = publishable_covariance(pose.covariance)
            # No covariance (the paper's solver gives none) is not published as a fake one:
            # a localization filter would trust it.
            if covariance is not None:
                with_cov = PoseWithCovarianceStamped(header=header)
                with_cov.pose.pose = _pose_message(pose)
                with_cov.pose.covariance = [float(v) for v in covariance.reshape(36)]
                self.pose_cov_pub.publish(with_cov)
            elif pose.covariance is not None:
                self.get_logger().error('vlp/pose_with_covariance withheld: the pose covariance is not finite '
                                        'or has a negative variance', throttle_duration_sec=THROTTLE_S)
        processed = Header(stamp=header.stamp, frame_id=result.outcome)
        self.processed_pub.publish(processed)

    def _publish_diagnostics(self) -> None:
        array = diagnostic_array(self.stats, self._camera is not None, self._image_topic,
                                 self.pipeline.track_restarts, self._kernels_ready.is_set())
        array.status[0].values.append(KeyValue(key='debug images drawn', value=str(self.debug_images_drawn)))
        array.header.stamp = self.get_clock().now().to_msg()
        self.diagnostics_pub.publish(array)

    def destroy_node(self) -> None:
        """Stop the decoder and worker threads (letting their frames finish), then destroy the node."""
        with self._wake:
            self._running = False
            self._wake.notify_all()
        for thread in self._threads:
            thread.join(timeout=5.0)
        super().destroy_node()


def _pose_message(pose: Pose) -> PoseMsg:
    msg = PoseMsg()
    msg.position.x, msg.position.y, msg.position.z = (float(v) for v in pose.position)
    q = pose.quaternion_xyzw()
    msg.orientation.x, msg.orientation.y, msg.orientation.z, msg.orientation.w = (float(v) for v in q)
    return msg


def keep_start_objects_out_of_collections() -> None:
    """
    Leave the objects made until now (numba's and LLVM's, ~150 000) out of Python's cyclic garbage collections.

    A full collection walks every tracked object while it holds Python's lock, which the decoder and the worker
    need between their native calls: with the kernels loaded one took 34-39 ms, a frame's time, once every few
    hundred frames. Frozen, the start's objects are never walked or freed; cycles made later still are.
    """
    gc.collect()
    gc.freeze()


def bound_malloc_arenas() -> None:
    """
    Let glibc keep two malloc arenas, before rclpy starts its threads, instead of one per thread that allocates.

    Each arena keeps what it freed resident (see ``keep_frames_in_the_heap``), so two bound the frames kept.
    """
    _set_malloc_option(_M_ARENA_MAX, 2)


def keep_frames_in_the_heap() -> None:
    """
    Take frame-sized blocks from the heap and keep them there once freed, after the kernels are loaded.

    A frame passes through several blocks of its size (DDS's reassembled sample, the message's bytes, the
    pipeline's temporaries). Mapped afresh, or returned to the system when freed at the heap's top, each is
    faulted in again page by page: with glibc's own thresholds (its trim threshold follows at twice the
    largest block freed, under two frames), three 4K frames' blocks taken and freed fault ~1,800 pages in a
    round, with these none (test_locator_malloc.py). Set after the kernels load so that the start's (numba's
    and LLVM's) allocations keep glibc's defaults.
    """
    _set_malloc_option(_M_MMAP_THRESHOLD, _HEAP_BLOCK_LIMIT)
    _set_malloc_option(_M_TRIM_THRESHOLD, _HEAP_KEPT_FREE)


def _set_malloc_option(option: int, value: int) -> None:
    try:
        ctypes.CDLL(None).mallopt(option, value)
    except (OSError, AttributeError):  # not glibc: its allocator is left as it is
        pass


def main(args: list[str] | None = None) -> int:
    """Run the locator until Ctrl-C; exit status 2 after a parameter error."""
    bound_malloc_arenas()
    return run_node(Locator, args=args, start_errors=(ConfigError,), on_start_error=_report_parameter_error)


def _report_parameter_error(err: Exception) -> int:
    print(f'[vlp_locator] parameter error: {err}', file=sys.stderr)
    return 2
