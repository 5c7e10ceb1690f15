"""
Camera models of sensor_msgs/CameraInfo: plumb_bob, rational_polynomial, equidistant, rectified.

Projection and undistortion are OpenCV's own (``cv2.projectPoints`` / ``cv2.undistortPoints``
with 5 or 8 coefficients, ``cv2.fisheye`` for equidistant). An image that is already rectified
(camera_info D all zero, P given) is a pinhole camera with K' = P[:3, :3]; when camera_info's R
is not the identity, its pixels are rays of the rectified frame, turned back into the camera's
optical frame (the frame the pose is of) by R^T.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import cv2
import numpy as np

from vlp_ros.compiled import kernel

PLUMB_BOB = 'plumb_bob'
RATIONAL_POLYNOMIAL = 'rational_polynomial'
EQUIDISTANT = 'equidistant'
RECTIFIED = 'rectified'  # not a camera_info name: rectified pixels in a frame rotated by camera_info's R
# Distortion coefficients per model, in camera_info's order.
COEFFICIENTS = {PLUMB_BOB: 5, RATIONAL_POLYNOMIAL: 8, EQUIDISTANT: 4, RECTIFIED: 0}
CAMERA_INFO_MODELS = (PLUMB_BOB, RATIONAL_POLYNOMIAL, EQUIDISTANT)
# A calibration's R is orthonormal to its printed precision: anything farther is not a rotation.
ROTATION_TOLERANCE = 1e-6
UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-12)
# Strong wide-angle distortion converges in more fixed-point steps than plumb_bob's 20.
WIDE_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)


@dataclass(frozen=True)
class CameraModel:
    """
    Intrinsics K (3x3) and the distortion D of ``model``.

    Plumb_bob (k1, k2, p1, p2, k3), rational_polynomial (k1, k2, p1, p2, k3, k4, k5, k6),
    equidistant (k1, k2, k3, k4), or rectified (no D; ``rectification`` is camera_info's R,
    rectified frame from camera frame).
    """

    width: int
    height: int
    K: np.ndarray
    D: np.ndarray = field(default_factory=lambda: np.zeros(5))
    model: str = PLUMB_BOB
    rectification: np.ndarray = field(default_factory=lambda: np.eye(3))

    def __post_init__(self) -> None:
        if self.model not in COEFFICIENTS:
            raise ValueError(f'camera model {self.model!r} is not one of {", ".join(COEFFICIENTS)}')
        # C-contiguous whatever it came from (P[:, :3] of a camera_info is not): the kernels that take K are
        # compiled for one array layout, and another would compile again on a node's first frame.
        object.__setattr__(self, 'K', np.ascontiguousarray(np.asarray(self.K, dtype=float).reshape(3, 3)))
        d = np.zeros(COEFFICIENTS[self.model])
        given = np.asarray(self.D, dtype=float).ravel()[:d.size]
        d[:given.size] = given
        object.__setattr__(self, 'D', d)
        object.__setattr__(self, 'rectification',
                           np.ascontiguousarray(np.asarray(self.rectification, dtype=float).reshape(3, 3)))

    @classmethod
    def from_horizontal_fov(cls, width: int, height: int, hfov_rad: float,
                            D: np.ndarray | None = None) -> CameraModel:
        """Square pixels, principal point at the image centre."""
        f = 0.5 * width / np.tan(0.5 * hfov_rad)
        K = np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
        return cls(width, height, K, np.zeros(5) if D is None else D)

    @classmethod
    def from_camera_info(cls, width: int, height: int, k, d, distortion_model: str,
                         p=None, r=None) -> CameraModel:
        """
        From sensor_msgs/CameraInfo fields (``p``, ``r``: its P and R, optional).

        D all zero: the pixels are undistorted (rectified); with P given (P[0] > 0) the camera
        is K' = P[:3, :3] turned by R, whatever the model's name. Otherwise D is read as
        ``distortion_model`` (plumb_bob, or '' for plumb_bob; rational_polynomial;
        equidistant), and P and R, which describe the rectified image, are not used.
        ValueError for an uncalibrated K, another model, or too few coefficients.
        """
        K = np.asarray(k, dtype=float).reshape(3, 3)
        if not K[0, 0] > 0.0:
            raise ValueError('camera_info is uncalibrated (K[0] <= 0)')
        D = np.asarray(d, dtype=float).ravel()
        if not np.any(D != 0.0):
            return _undistorted_camera(int(width), int(height), K, p, r)
        model = PLUMB_BOB if distortion_model == '' else distortion_model
        if model not in CAMERA_INFO_MODELS:
            raise ValueError(f'camera_info distortion model {distortion_model!r} is not supported '
                             f'({", ".join(CAMERA_INFO_MODELS)})')
        count = COEFFICIENTS[model]
        if model != PLUMB_BOB and (D.size < count or np.any(D[count:] != 0.0)):
            raise ValueError(f'camera_info distortion model {model!r} takes {count} coefficients, got D of {D.size}')
        return cls(int(width), int(height), K, D[:count], model)

    @property
    def focal(self) -> float:
        return float(0.5 * (self.K[0, 0] + self.K[1, 1]))

    # Cached (in the instance's __dict__, which a frozen dataclass allows): the solvers ask per lamp.
    # Not a pinhole camera: distortion, or a model that is no pinhole whatever its D.
    @cached_property
    def is_distorted(self) -> bool:
        return bool(np.any(self.D != 0.0)) or self.model in (EQUIDISTANT, RECTIFIED)

    # d(normalised)/d(pixel) without distortion, per lamp otherwise: cached like is_distorted.
    @cached_property
    def pinhole_pixel_inverse(self) -> np.ndarray:
        """d(normalised)/d(pixel) (2, 2) of the pinhole part: K's upper-left block inverted."""
        return np.linalg.inv(self.K[:2, :2])

    def pinhole(self) -> CameraModel:
        """Return the ideal pinhole camera with the same K (no distortion): ``undistort_pixels`` maps to its pixels."""
        return CameraModel(self.width, self.height, self.K)

    def project(self, points_camera: np.ndarray) -> np.ndarray:
        """Pixel coordinates (N, 2) of points (N, 3) given in the camera optical frame."""
        p = np.asarray(points_camera, dtype=float).reshape(-1, 1, 3)
        if self.model == EQUIDISTANT:
            pixels, _ = cv2.fisheye.projectPoints(p, np.zeros(3), np.zeros(3), self.K, self.D)
        elif self.model == RECTIFIED:
            pixels, _ = cv2.projectPoints(p, cv2.Rodrigues(self.rectification)[0], np.zeros(3), self.K, None)
        else:
            pixels, _ = cv2.projectPoints(p, np.zeros(3), np.zeros(3), self.K, self.D)
        return pixels.reshape(-1, 2)

    def normalize(self, pixels: np.ndarray) -> np.ndarray:
        """Undistorted normalised image coordinates (N, 2) (z = 1 plane) of pixels (N, 2)."""
        if not self.is_distorted:
            return _pinhole_normalized(np.ascontiguousarray(pixels, dtype=float).reshape(-1, 2), self.K)
        px = np.asarray(pixels, dtype=float).reshape(-1, 1, 2)
        if self.model == PLUMB_BOB:
            normalized = cv2.undistortPoints(px, self.K, self.D, None, None, None, UNDISTORT_CRITERIA)
        elif self.model == RATIONAL_POLYNOMIAL:
            normalized = cv2.undistortPoints(px, self.K, self.D, None, None, None, WIDE_UNDISTORT_CRITERIA)
        elif self.model == EQUIDISTANT:
            normalized = cv2.fisheye.undistortPoints(px, self.K, self.D, criteria=WIDE_UNDISTORT_CRITERIA)
        else:
            normalized = cv2.undistortPoints(px, self.K, None, R=self.rectification.T)
        return normalized.reshape(-1, 2)

    def undistort_pixels(self, pixels: np.ndarray) -> np.ndarray:
        """Pixel coordinates (N, 2) that an ideal pinhole camera with the same K would see."""
        n = self.normalize(pixels)
        return n @ self.K[:2, :2].T + self.K[:2, 2]


def _undistorted_camera(width: int, height: int, K: np.ndarray, p, r) -> CameraModel:
    """Return a camera_info without distortion: K, or K' = P[:3, :3] turned by R where P is given."""
    P = None if p is None else np.asarray(p, dtype=float).reshape(3, 4)
    if P is None or not P[0, 0] > 0.0:
        return CameraModel(width, height, K)
    R = np.eye(3) if r is None else np.asarray(r, dtype=float).reshape(3, 3)
    R = R if np.any(R != 0.0) else np.eye(3)  # an unset R (all zero) is no rotation
    if not (np.allclose(R @ R.T, np.eye(3), atol=ROTATION_TOLERANCE) and np.linalg.det(R) > 0.0):
        raise ValueError('camera_info R is not a rotation')
    if np.allclose(R, np.eye(3), atol=ROTATION_TOLERANCE):
        return CameraModel(width, height, P[:, :3])
    return CameraModel(width, height, P[:, :3], model=RECTIFIED, rectification=R)


@kernel
def _pinhole_normalized(pixels, k):
    """``CameraModel.normalize`` without distortion: K inverted on each pixel (N, 2)."""
    normalized = np.empty((pixels.shape[0], 2))
    for n in range(pixels.shape[0]):
        normalized[n, 0] = (pixels[n, 0] - k[0, 2] - k[0, 1] * (pixels[n, 1] - k[1, 2]) / k[1, 1]) / k[0, 0]
        normalized[n, 1] = (pixels[n, 1] - k[1, 2]) / k[1, 1]
    return normalized
