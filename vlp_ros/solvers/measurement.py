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

from dataclasses import dataclass, replace

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

    def thinned(self, max_rim_points: int) -> LampMeasurement:
        """The same measurement on every k-th rim point, at most ``max_rim_points`` of them."""
        step = -(-len(self.rim_rays) // max_rim_points)
        return replace(self, rim_rays=self.rim_rays[::step], rim_pixel_jacobian=self.rim_pixel_jacobian[::step])

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
        # H = R^T A maps lamp-plane (x, y, 1) to rays, A's columns being the lamp's map x
        # and y axes and its centre relative to the camera. For a ray h: w = H^-1 h,
        # value v = w^T Q w, half gradient g = H^-T Q w, pixel gradient / 2 P = G^T g_xy
        # with G = d normalised / d pixel, residual s = v / (2 |P|).
        plane_axes = np.eye(3)
        plane_axes[:, 2] = self.lamp.position - position
        image_to_plane = np.linalg.inv(rotation.T @ plane_axes)
        q_diagonal = np.array([1.0, 1.0, -self.lamp.radius ** 2])
        w = self.rim_rays @ image_to_plane.T
        value = (w * w) @ q_diagonal
        g = (w * q_diagonal) @ image_to_plane
        pixel = self._to_pixel_gradient(g)
        norm2 = pixel[:, 0] ** 2 + pixel[:, 1] ** 2
        norm = np.sqrt(norm2)
        residual = 0.5 * value / norm
        # Exact derivatives along the six perturbations dH of H: dv = -2 g.(dH w),
        # dg = -H^-T (dH^T g + Q H^-1 dH w). Exactness matters far from the minimum,
        # where the value is large (starts from a wrong candidate).
        map_gradient = g @ rotation.T
        in_map = w @ plane_axes.T
        count = len(w)
        dh_w = np.empty((6, count, 3))
        dh_t_g = np.zeros((6, count, 3))
        dh_w[:3] = -w[None, :, 2:3] * rotation[:, None, :]
        dh_t_g[:3, :, 2] = -map_gradient.T
        dh_w[3:] = -(_axis_crosses(in_map) @ rotation)
        dh_t_g[3:] = _axis_crosses(map_gradient) @ plane_axes
        d_value = -2.0 * np.einsum('knj,nj->kn', dh_w, g)
        d_g = -(dh_t_g + (dh_w @ image_to_plane.T) * q_diagonal) @ image_to_plane[:, :2]
        # P . dP = dg_xy . (G P): the pixel gradient's change is only needed along itself.
        along = np.sum(self.rim_pixel_jacobian * pixel[:, None, :], axis=2)
        d_norm_term = d_g[..., 0] * along[:, 0] + d_g[..., 1] * along[:, 1]
        jacobian = 0.5 * d_value / norm - residual * d_norm_term / norm2
        return residual, jacobian.T

    def _to_pixel_gradient(self, ray_gradient: np.ndarray) -> np.ndarray:
        jacobian = self.rim_pixel_jacobian
        return ray_gradient[:, 0:1] * jacobian[:, 0, :] + ray_gradient[:, 1:2] * jacobian[:, 1, :]

    def _marker(self, rotation: np.ndarray, position: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        offset = self.lamp.marker_position() - position
        pixel, lens = cv2.projectPoints(offset @ rotation, np.zeros(3), np.zeros(3),
                                        self.camera.K, self.camera.D)
        # With zero rvec/tvec the tvec columns are d pixel / d point (camera frame);
        # d point = R^T (offset x dtheta - dp).
        to_pixel = lens[:, 3:6] @ rotation.T
        jacobian = np.hstack([-to_pixel, to_pixel @ _cross_matrix(offset)])
        return pixel.reshape(2) - self.marker_pixel, jacobian


def _axis_crosses(v: np.ndarray) -> np.ndarray:
    """e_j x v (3, N, 3) for j = 0, 1, 2 and rows v (N, 3)."""
    out = np.zeros((3,) + v.shape)
    out[0, :, 1], out[0, :, 2] = -v[:, 2], v[:, 1]
    out[1, :, 0], out[1, :, 2] = v[:, 2], -v[:, 0]
    out[2, :, 0], out[2, :, 1] = -v[:, 1], v[:, 0]
    return out


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
