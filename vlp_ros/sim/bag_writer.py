"""
rosbag2 recordings of simulated frames: image, camera info, IMU, ground-truth pose and wheel odometry.

Every message of a frame carries the frame's stamp (when its row 0 started
exposing) in its header and as its log time.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import get_typestore, Stores

from vlp_ros.core.camera import CameraModel
from vlp_ros.core.pose import Pose
from vlp_ros.sim.render import RenderedFrame
from vlp_ros.sim.sensor import encode_jpeg

TYPESTORE = get_typestore(Stores.ROS2_LYRICAL)
STORAGES = {'sqlite3': StoragePlugin.SQLITE3, 'mcap': StoragePlugin.MCAP}
CAMERA_FRAME = 'camera_optical_frame'
MAP_FRAME = 'map'
IMAGE_TOPIC = '/image_raw'
COMPRESSED_TOPIC = '/image_raw/compressed'
# image_transport's format string for a JPEG of a bgr8 image.
JPEG_FORMAT = 'bgr8; jpeg compressed bgr8'
CAMERA_INFO_TOPIC = '/camera_info'
IMU_TOPIC = '/imu'
GROUND_TRUTH_TOPIC = '/ground_truth/pose'
ODOMETRY_TOPIC = '/odom'
ODOMETRY_FRAME = 'odom'
BASE_FRAME = 'base_link'


def _qos(reliability: QosReliability, depth: int) -> Qos:
    unset = QosTime(sec=0, nsec=0)
    return Qos(QosHistory.KEEP_LAST, depth, reliability, QosDurability.VOLATILE, unset, unset,
               QosLiveliness.AUTOMATIC, unset, False)


# What a camera driver offers: sensor-data QoS for the streams, reliable for calibration and truth.
TOPICS = {
    IMAGE_TOPIC: ('sensor_msgs/msg/Image', _qos(QosReliability.BEST_EFFORT, 5)),
    COMPRESSED_TOPIC: ('sensor_msgs/msg/CompressedImage', _qos(QosReliability.BEST_EFFORT, 5)),
    CAMERA_INFO_TOPIC: ('sensor_msgs/msg/CameraInfo', _qos(QosReliability.RELIABLE, 10)),
    IMU_TOPIC: ('sensor_msgs/msg/Imu', _qos(QosReliability.BEST_EFFORT, 50)),
    GROUND_TRUTH_TOPIC: ('geometry_msgs/msg/PoseStamped', _qos(QosReliability.RELIABLE, 10)),
    ODOMETRY_TOPIC: ('nav_msgs/msg/Odometry', _qos(QosReliability.RELIABLE, 10)),
}


class SimBagWriter:
    """
    Writes frames to a new rosbag2 directory (``storage``: sqlite3 or mcap).

    Use as a context manager.

    With ``jpeg_quality`` the images go as JPEG on /image_raw/compressed (for
    ``image_transport: compressed``) instead of raw on /image_raw. With ``odometry`` the bag has
    /odom (``write_odometry``).
    """

    def __init__(self, path: Path | str, storage: str = 'sqlite3', imu: bool = False,
                 jpeg_quality: int | None = None, odometry: bool = False) -> None:
        if storage not in STORAGES:
            raise ValueError(f'storage must be one of {", ".join(STORAGES)}, got {storage!r}')
        path = Path(path)
        if path.exists():
            raise ValueError(f'{path} exists already; choose a new output path')
        self._writer = Writer(path, version=9, storage_plugin=STORAGES[storage])
        self._writer.open()
        self._connections = {}
        self._jpeg_quality = jpeg_quality
        skipped = {IMAGE_TOPIC if jpeg_quality is not None else COMPRESSED_TOPIC} | (set() if imu else {IMU_TOPIC})
        skipped |= set() if odometry else {ODOMETRY_TOPIC}
        for topic, (msgtype, qos) in TOPICS.items():
            if topic in skipped:
                continue
            self._connections[topic] = self._writer.add_connection(
                topic, msgtype, typestore=TYPESTORE, offered_qos_profiles=[qos])
        self.frames = 0

    def write_frame(self, frame: RenderedFrame, stamp_ns: int, specific_force: np.ndarray | None = None,
                    imu_noise: float = 0.0) -> None:
        """Image, camera info, ground truth and (if the bag has an IMU topic) ``specific_force``."""
        if (IMU_TOPIC in self._connections) != (specific_force is not None):
            raise ValueError('give specific_force exactly when the bag was opened with imu=True')
        header = _header(stamp_ns, CAMERA_FRAME)
        # The image last, as a driver's frame completes after its IMU sample and calibration:
        # a player that waits for each frame's answer has then sent everything it needs.
        if specific_force is not None:
            self._write(IMU_TOPIC, stamp_ns, imu_message(specific_force, imu_noise, header))
        self._write(CAMERA_INFO_TOPIC, stamp_ns, camera_info_message(frame.camera, header))
        self._write(GROUND_TRUTH_TOPIC, stamp_ns, pose_message(frame.pose, _header(stamp_ns, MAP_FRAME)))
        if self._jpeg_quality is None:
            self._write(IMAGE_TOPIC, stamp_ns, image_message(frame.image, frame.encoding, header))
        else:
            if frame.encoding != 'bgr8':
                raise ValueError(f'JPEG needs a bgr8 image, not {frame.encoding}')
            self._write(COMPRESSED_TOPIC, stamp_ns, compressed_image_message(
                encode_jpeg(frame.image, self._jpeg_quality), header))
        self.frames += 1

    def write_odometry(self, stamp_ns: int, base: Pose) -> None:
        """nav_msgs/Odometry of the base in the odometry frame (pose only; twist zero, covariances unknown)."""
        types = TYPESTORE.types
        pose = pose_message(base, _header(stamp_ns, ODOMETRY_FRAME)).pose
        twist = types['geometry_msgs/msg/Twist'](linear=types['geometry_msgs/msg/Vector3'](x=0.0, y=0.0, z=0.0),
                                                 angular=types['geometry_msgs/msg/Vector3'](x=0.0, y=0.0, z=0.0))
        self._write(ODOMETRY_TOPIC, stamp_ns, types['nav_msgs/msg/Odometry'](
            header=_header(stamp_ns, ODOMETRY_FRAME), child_frame_id=BASE_FRAME,
            pose=types['geometry_msgs/msg/PoseWithCovariance'](pose=pose, covariance=np.zeros(36)),
            twist=types['geometry_msgs/msg/TwistWithCovariance'](twist=twist, covariance=np.zeros(36))))

    def _write(self, topic: str, stamp_ns: int, message: object) -> None:
        self._writer.write(self._connections[topic], stamp_ns,
                           TYPESTORE.serialize_cdr(message, TOPICS[topic][0]))

    def close(self) -> None:
        self._writer.close()

    def __enter__(self) -> SimBagWriter:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


def _header(stamp_ns: int, frame_id: str) -> object:
    Time = TYPESTORE.types['builtin_interfaces/msg/Time']
    Header = TYPESTORE.types['std_msgs/msg/Header']
    return Header(stamp=Time(sec=int(stamp_ns // 1_000_000_000), nanosec=int(stamp_ns % 1_000_000_000)),
                  frame_id=frame_id)


def image_message(image: np.ndarray, encoding: str, header: object) -> object:
    Image = TYPESTORE.types['sensor_msgs/msg/Image']
    height, width = image.shape[:2]
    return Image(header=header, height=height, width=width, encoding=encoding, is_bigendian=0,
                 step=image.strides[0], data=np.ascontiguousarray(image).reshape(-1))


def compressed_image_message(data: np.ndarray, header: object) -> object:
    CompressedImage = TYPESTORE.types['sensor_msgs/msg/CompressedImage']
    return CompressedImage(header=header, format=JPEG_FORMAT, data=data)


def camera_info_message(camera: CameraModel, header: object) -> object:
    CameraInfo = TYPESTORE.types['sensor_msgs/msg/CameraInfo']
    RegionOfInterest = TYPESTORE.types['sensor_msgs/msg/RegionOfInterest']
    projection = np.hstack([camera.K, np.zeros((3, 1))])
    return CameraInfo(header=header, height=camera.height, width=camera.width, distortion_model=camera.model,
                      d=camera.D.astype(float), k=camera.K.reshape(-1), r=np.eye(3).reshape(-1),
                      p=projection.reshape(-1), binning_x=0, binning_y=0,
                      roi=RegionOfInterest(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))


def pose_message(pose: Pose, header: object) -> object:
    types = TYPESTORE.types
    q = pose.quaternion_xyzw()
    return types['geometry_msgs/msg/PoseStamped'](
        header=header,
        pose=types['geometry_msgs/msg/Pose'](
            position=types['geometry_msgs/msg/Point'](x=float(pose.position[0]), y=float(pose.position[1]),
                                                      z=float(pose.position[2])),
            orientation=types['geometry_msgs/msg/Quaternion'](x=float(q[0]), y=float(q[1]), z=float(q[2]),
                                                              w=float(q[3]))))


def imu_message(specific_force: np.ndarray, noise_std: float, header: object) -> object:
    """Accelerometer only: orientation and angular velocity are marked absent (covariance[0] = -1)."""
    types = TYPESTORE.types
    Vector3 = types['geometry_msgs/msg/Vector3']
    absent = np.zeros(9)
    absent[0] = -1.0
    return types['sensor_msgs/msg/Imu'](
        header=header,
        orientation=types['geometry_msgs/msg/Quaternion'](x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=absent.copy(),
        angular_velocity=Vector3(x=0.0, y=0.0, z=0.0),
        angular_velocity_covariance=absent.copy(),
        linear_acceleration=Vector3(x=float(specific_force[0]), y=float(specific_force[1]),
                                    z=float(specific_force[2])),
        linear_acceleration_covariance=(np.eye(3) * noise_std ** 2).reshape(-1))
