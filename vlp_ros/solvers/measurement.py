"""How well a camera pose explains one lamp's observation: residuals in pixels over their noise.

Rim residual: the signed pixel distance of each observed rim point from the
image of the disc edge, to first order (Sampson). The predicted edge is the
conic ``H^-T diag(1, 1, -r^2) H^-1`` in normalised coordinates, H mapping the
lamp plane to the image; its value and gradient at the (once undistorted) rim
point are carried to pixels through the local Jacobian of the lens model, so
the residual is the distance across the edge that ``rim_sigma`` describes and
lens distortion costs nothing per iteration. The first-order error is
~ sigma^2 / (ellipse radius): 1e-3 px for 0.3 px noise on a 90 px lamp.
Marker residual: the pixel offset of the observed centroid from
``CameraModel.project`` of the marker's map position.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vlp_ros.camera import CameraModel
from vlp_ros.lamp_map import Lamp
from vlp_ros.observation import LampObservation

# Step (normalised units, ~1e-3 px) of the central differences for the lens Jacobian.
_LENS_STEP = 1e-6


@dataclass(frozen=True)
class LampMeasurement:
    """One lamp's observation, prepared for repeated residual evaluation.

    ``rim_rays`` (N, 3) are the rim points as homogeneous normalised coordinates;
    ``rim_pixel_jacobian`` (N, 2, 2) is d(normalised)/d(pixel) at each of them.
    """

    lamp: Lamp
    camera: CameraModel
    rim_rays: np.ndarray
    rim_pixel_jacobian: np.ndarray
    rim_sigma: float
    marker_pixel: np.ndarray | None
    marker_sigma: float

    @classmethod
    def from_observation(cls, observation: LampObservation, lamp: Lamp,
                         camera: CameraModel) -> LampMeasurement:
        rim = np.asarray(observation.rim_points, dtype=float).reshape(-1, 2)
        if len(rim) < 5:
            raise ValueError(f'lamp {lamp.name!r}: need at least 5 rim points, got {len(rim)}')
        if not np.all(np.isfinite(rim)):
            raise ValueError(f'lamp {lamp.name!r}: rim points are not all finite')
        if not observation.rim_sigma > 0.0:
            raise ValueError(f'lamp {lamp.name!r}: rim_sigma must be positive, got {observation.rim_sigma}')
        marker = None
        if observation.marker is not None:
            marker = np.asarray(observation.marker, dtype=float).reshape(2)
            if not np.all(np.isfinite(marker)):
                raise ValueError(f'lamp {lamp.name!r}: marker pixel is not finite')
            if not observation.marker_sigma > 0.0:
                raise ValueError(f'lamp {lamp.name!r}: marker_sigma must be positive, '
                                 f'got {observation.marker_sigma}')
        normalized = camera.normalize(rim)
        return cls(lamp=lamp, camera=camera,
                   rim_rays=np.column_stack([normalized, np.ones(len(normalized))]),
                   rim_pixel_jacobian=np.linalg.inv(_lens_jacobian(camera, normalized)),
                   rim_sigma=float(observation.rim_sigma), marker_pixel=marker,
                   marker_sigma=float(observation.marker_sigma))

    @property
    def residual_count(self) -> int:
        return len(self.rim_rays) + (0 if self.marker_pixel is None else 2)

    def linearize(self, rotation: np.ndarray, position: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Residuals over their sigmas (M,) for the camera pose (``rotation`` camera to map,
        ``position``) and their Jacobian (M, 6) with respect to the pose perturbation of
        ``covariance.perturbed``."""
        rim, rim_jacobian = self._rim(rotation, position)
        if self.marker_pixel is None:
            return rim / self.rim_sigma, rim_jacobian / self.rim_sigma
        marker, marker_jacobian = self._marker(rotation, position)
        return (np.concatenate([rim / self.rim_sigma, marker / self.marker_sigma]),
                np.vstack([rim_jacobian / self.rim_sigma, marker_jacobian / self.marker_sigma]))

    def lamp_center_in_camera(self, rotation: np.ndarray, position: np.ndarray) -> np.ndarray:
        return (self.lamp.position - position) @ rotation

    def _rim(self, rotation: np.ndarray, position: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # H = R^T A maps lamp-plane (x, y, 1) to rays; A's columns are the lamp's map
        # x and y axes and its centre relative to the camera.
        plane_axes = np.column_stack([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], self.lamp.position - position])
        image_to_plane = np.linalg.inv(rotation.T @ plane_axes)
        plane = self.rim_rays @ image_to_plane.T
        radius2 = self.lamp.radius ** 2
        value = plane[:, 0] ** 2 + plane[:, 1] ** 2 - radius2 * plane[:, 2] ** 2
        # Half the gradient of the value with respect to the ray, per point.
        half_gradient = (plane * np.array([1.0, 1.0, -radius2])) @ image_to_plane
        pixel_gradient = np.einsum('nji,nj->ni', self.rim_pixel_jacobian, half_gradient[:, :2])
        scale = 0.5 / np.hypot(pixel_gradient[:, 0], pixel_gradient[:, 1])
        # d value = -2 g^T dH w, dH w = R^T (q x dtheta - w3 dp), q = A w, g = half_gradient.
        m = half_gradient @ rotation.T
        q = plane @ plane_axes.T
        jacobian = np.empty((len(plane), 6))
        jacobian[:, :3] = 2.0 * plane[:, 2:3] * m
        jacobian[:, 3] = 2.0 * (m[:, 2] * q[:, 1] - m[:, 1] * q[:, 2])
        jacobian[:, 4] = 2.0 * (m[:, 0] * q[:, 2] - m[:, 2] * q[:, 0])
        jacobian[:, 5] = 2.0 * (m[:, 1] * q[:, 0] - m[:, 0] * q[:, 1])
        # The derivative of the normaliser is left out: it multiplies the value, which is
        # zero for noise-free data, so this is the Jacobian the Fisher information needs.
        return value * scale, jacobian * scale[:, None]

    def _marker(self, rotation: np.ndarray, position: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        offset = self.lamp.marker_position() - position
        pixel, lens = cv2.projectPoints(offset @ rotation, np.zeros(3), np.zeros(3),
                                        self.camera.K, self.camera.D)
        # With zero rvec/tvec the tvec columns are d pixel / d point (camera frame);
        # d point = R^T (offset x dtheta - dp).
        to_pixel = lens[:, 3:6] @ rotation.T
        jacobian = np.hstack([-to_pixel, to_pixel @ _cross_matrix(offset)])
        return pixel.reshape(2) - self.marker_pixel, jacobian


def _cross_matrix(v: np.ndarray) -> np.ndarray:
    """[v]x: [v]x @ u = v x u."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _lens_jacobian(camera: CameraModel, normalized: np.ndarray) -> np.ndarray:
    """d(pixel)/d(normalised) (N, 2, 2) at normalised points (N, 2)."""
    columns = []
    for axis in range(2):
        step = np.zeros(2)
        step[axis] = _LENS_STEP
        forward = camera.project(np.column_stack([normalized + step, np.ones(len(normalized))]))
        backward = camera.project(np.column_stack([normalized - step, np.ones(len(normalized))]))
        columns.append((forward - backward) / (2.0 * _LENS_STEP))
    return np.stack(columns, axis=2)
