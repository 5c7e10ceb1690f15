"""Pinhole camera with plumb_bob distortion, as described by sensor_msgs/CameraInfo."""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import cv2
import numpy as np

from vlp_ros.compiled import kernel


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics K (3x3) and plumb_bob distortion D = (k1, k2, p1, p2, k3)."""

    width: int
    height: int
    K: np.ndarray
    D: np.ndarray = field(default_factory=lambda: np.zeros(5))

    def __post_init__(self) -> None:
        object.__setattr__(self, 'K', np.asarray(self.K, dtype=float).reshape(3, 3))
        d = np.zeros(5)
        given = np.asarray(self.D, dtype=float).ravel()[:5]
        d[:given.size] = given
        object.__setattr__(self, 'D', d)

    @classmethod
    def from_horizontal_fov(cls, width: int, height: int, hfov_rad: float,
                            D: np.ndarray | None = None) -> CameraModel:
        """Square pixels, principal point at the image centre."""
        f = 0.5 * width / np.tan(0.5 * hfov_rad)
        K = np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
        return cls(width, height, K, np.zeros(5) if D is None else D)

    @classmethod
    def from_camera_info(cls, width: int, height: int, k, d, distortion_model: str) -> CameraModel:
        """From sensor_msgs/CameraInfo fields; ValueError for an uncalibrated K or a non-plumb_bob model."""
        K = np.asarray(k, dtype=float).reshape(3, 3)
        if not K[0, 0] > 0.0:
            raise ValueError('camera_info is uncalibrated (K[0] <= 0)')
        D = np.asarray(d, dtype=float).ravel()
        if distortion_model not in ('plumb_bob', '') and np.any(D != 0.0):
            raise ValueError(f'camera_info distortion model {distortion_model!r} is not supported (plumb_bob only)')
        return cls(int(width), int(height), K, D[:5])

    @property
    def focal(self) -> float:
        return float(0.5 * (self.K[0, 0] + self.K[1, 1]))

    # Cached (in the instance's __dict__, which a frozen dataclass allows): the solvers ask per lamp.
    @cached_property
    def is_distorted(self) -> bool:
        return bool(np.any(self.D != 0.0))

    # d(normalised)/d(pixel) without distortion, per lamp otherwise: cached like is_distorted.
    @cached_property
    def pinhole_pixel_inverse(self) -> np.ndarray:
        """d(normalised)/d(pixel) (2, 2) of the pinhole part: K's upper-left block inverted."""
        return np.linalg.inv(self.K[:2, :2])

    def project(self, points_camera: np.ndarray) -> np.ndarray:
        """Pixel coordinates (N, 2) of points (N, 3) given in the camera optical frame."""
        p = np.asarray(points_camera, dtype=float).reshape(-1, 3)
        pixels, _ = cv2.projectPoints(p, np.zeros(3), np.zeros(3), self.K, self.D)
        return pixels.reshape(-1, 2)

    def normalize(self, pixels: np.ndarray) -> np.ndarray:
        """Undistorted normalised image coordinates (N, 2) (z = 1 plane) of pixels (N, 2)."""
        if not self.is_distorted:
            return _pinhole_normalized(np.ascontiguousarray(pixels, dtype=float).reshape(-1, 2), self.K)
        px = np.asarray(pixels, dtype=float).reshape(-1, 1, 2)
        return cv2.undistortPoints(
            px, self.K, self.D, None, None, None,
            (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-12)).reshape(-1, 2)

    def undistort_pixels(self, pixels: np.ndarray) -> np.ndarray:
        """Pixel coordinates (N, 2) that an ideal pinhole camera with the same K would see."""
        n = self.normalize(pixels)
        return n @ self.K[:2, :2].T + self.K[:2, 2]


@kernel
def _pinhole_normalized(pixels, k):
    """``CameraModel.normalize`` without distortion: K inverted on each pixel (N, 2)."""
    normalized = np.empty((pixels.shape[0], 2))
    for n in range(pixels.shape[0]):
        normalized[n, 0] = (pixels[n, 0] - k[0, 2] - k[0, 1] * (pixels[n, 1] - k[1, 2]) / k[1, 1]) / k[0, 0]
        normalized[n, 1] = (pixels[n, 1] - k[1, 2]) / k[1, 1]
    return normalized
