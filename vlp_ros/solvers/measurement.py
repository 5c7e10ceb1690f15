"""How well a camera pose explains one lamp's observation: residuals in pixels over their noise.

Rim residual: the signed pixel distance of each observed rim point from the
image of the disc edge, to first order (Sampson). The predicted edge is the
conic ``H^-T diag(1, 1, -r^2) H^-1`` in normalised coordinates, H mapping the
lamp plane to the image; its value and gradient at the (once undistorted) rim
point are carried to pixels through the local Jacobian of the lens model, so
the residual is the distance across the edge that ``rim_sigma`` describes and
lens distortion costs nothing per iteration. The first-order error is
~ sigma^2 / (ellipse radius): 1e-3 px for 0.3 px noise on a 90 px lamp.
Marker residual: the pixel offset of the observed centroid from the projection
of the marker's map position through the camera's K and D (OpenCV's model, as
``CameraModel.project``, called directly for its Jacobian).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from vlp_ros.camera import CameraModel
from vlp_ros.lamp_map import Lamp
from vlp_ros.observation import LampObservation

# [e_j]x for the map axes j: rotation perturbations about them.
_AXIS_SKEWS = np.array([[[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]],
                        [[0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [-1.0, 0.0, 0.0]],
                        [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]]])
# Step (normalised units, ~1e-3 px) of the central differences for the lens Jacobian.
_LENS_STEP = 1e-6
_ZERO3 = np.zeros(3)


@dataclass(frozen=True)
class LampMeasurement:
    """One lamp's observation, prepared for repeated residual evaluation.

    ``rim_rays`` (N, 3) are the rim points as homogeneous normalised coordinates;
    ``rim_pixel_jacobian`` (N, 2, 2) is d(normalised)/d(pixel) at each of them;
    ``marker_ray`` is the marker centroid's homogeneous normalised coordinates.
    """

    lamp: Lamp
    camera: CameraModel
    rim_rays: np.ndarray
    rim_pixel_jacobian: np.ndarray
    rim_sigma: float
    marker_pixel: np.ndarray | None
    marker_sigma: float
    marker_ray: np.ndarray | None

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
        marker_ray = None if marker is None else np.append(camera.normalize(marker)[0], 1.0)
        return cls(lamp=lamp, camera=camera,
                   rim_rays=np.column_stack([normalized, np.ones(len(normalized))]),
                   rim_pixel_jacobian=np.linalg.inv(_lens_jacobian(camera, normalized)),
                   rim_sigma=float(observation.rim_sigma), marker_pixel=marker,
                   marker_sigma=float(observation.marker_sigma), marker_ray=marker_ray)

    def thinned(self, max_rim_points: int) -> LampMeasurement:
        """The same measurement on every k-th rim point, at most ``max_rim_points`` of them."""
        step = -(-len(self.rim_rays) // max_rim_points)
        return replace(self, rim_rays=self.rim_rays[::step], rim_pixel_jacobian=self.rim_pixel_jacobian[::step])

    @property
    def residual_count(self) -> int:
        return len(self.rim_rays) + (0 if self.marker_pixel is None else 2)

    def __post_init__(self) -> None:
        # Per-iteration constants, laid out for elementwise products (cheaper than einsum on (N, 2, 2)).
        lens = self.rim_pixel_jacobian
        object.__setattr__(self, '_lens', tuple(np.ascontiguousarray(lens[:, i, j]) for i in (0, 1) for j in (0, 1)))
        marker_map = None if self.marker_pixel is None else self.lamp.marker_position()
        object.__setattr__(self, '_marker_map', marker_map)

    def linearize(self, rotation: np.ndarray, position: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Residuals over their sigmas (M,) for the camera pose (``rotation`` camera to map,
        ``position``) and their Jacobian (M, 6) with respect to the pose perturbation of
        ``covariance.perturbed``."""
        n = len(self.rim_rays)
        residuals, jacobian = np.empty(self.residual_count), np.empty((self.residual_count, 6))
        residuals[:n], jacobian[:n] = self._rim(rotation, position)
        residuals[:n] /= self.rim_sigma
        jacobian[:n] /= self.rim_sigma
        if self.marker_pixel is not None:
            residuals[n:], jacobian[n:] = self._marker(rotation, position)
            residuals[n:] /= self.marker_sigma
            jacobian[n:] /= self.marker_sigma
        return residuals, jacobian

    def lamp_center_in_camera(self, rotation: np.ndarray, position: np.ndarray) -> np.ndarray:
        return (self.lamp.position - position) @ rotation

    def _rim(self, rotation: np.ndarray, position: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # H = R^T A maps lamp-plane (x, y, 1) to rays, A's columns being the lamp's map x
        # and y axes and its centre relative to the camera; the rim's image is the conic
        # C = H^-T Q H^-1, Q = diag(1, 1, -r^2); each rim ray's residual is its pixel
        # distance from C (``_edge_residuals``).
        plane_axes = np.eye(3)
        plane_axes[:, 2] = self.lamp.position - position
        _, image_to_plane = cv2.invert(rotation.T @ plane_axes, flags=cv2.DECOMP_LU)
        q_diagonal = np.array([1.0, 1.0, -self.lamp.radius ** 2])
        conic = image_to_plane.T @ (q_diagonal[:, None] * image_to_plane)
        rays = self.rim_rays
        residual, a = _edge_residuals(rays, rays @ conic, self._lens)
        # Along each of the six perturbations dH of H, dC = -(M + M^T) with M = C dH H^-1.
        d_h = np.zeros((6, 3, 3))
        d_h[:3, :, 2] = -rotation
        d_h[3:] = -(rotation.T @ _AXIS_SKEWS) @ plane_axes
        m = conic @ d_h @ image_to_plane
        d_conic = -(m + m.transpose(0, 2, 1))
        # a^T dC_k h for all k at once: the outer products a h^T against the six flattened dC_k.
        outer = (a[:, :, None] * rays[:, None, :]).reshape(-1, 9)
        return residual, outer @ d_conic.reshape(6, 9).T

    def _marker(self, rotation: np.ndarray, position: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        offset = self._marker_map - position
        pixel, lens = cv2.projectPoints(offset @ rotation, _ZERO3, _ZERO3, self.camera.K, self.camera.D)
        # With zero rvec/tvec the tvec columns are d pixel / d point (camera frame);
        # d point = R^T (offset x dtheta - dp).
        to_pixel = lens[:, 3:6] @ rotation.T
        jacobian = np.empty((2, 6))
        jacobian[:, :3] = -to_pixel
        jacobian[:, 3:] = to_pixel @ cross_matrix(offset)
        return pixel.reshape(2) - self.marker_pixel, jacobian


def _edge_residuals(rays: np.ndarray, c_h: np.ndarray,
                    lens: tuple[np.ndarray, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Each ray's signed pixel distance s from the rim conic C (``c_h`` = C h per ray), and the
    vector a with ds = a^T dC h for any change dC of the conic.

    v = h^T C h, P = G^T (C h)_xy half the pixel gradient (G = d normalised / d pixel,
    ``lens`` its four entries per ray), s = v / (2 |P|). The derivative is exact (it matters
    far from the minimum, where v is large): a = h / (2|P|) - s (G P, 0) / |P|^2.
    """
    g00, g01, g10, g11 = lens
    value = np.einsum('ni,ni->n', rays, c_h)
    p0 = c_h[:, 0] * g00 + c_h[:, 1] * g10
    p1 = c_h[:, 0] * g01 + c_h[:, 1] * g11
    norm2 = p0 * p0 + p1 * p1
    norm = np.sqrt(norm2)
    residual = 0.5 * value / norm
    a = rays * (0.5 / norm)[:, None]
    pull = residual / norm2
    a[:, 0] -= pull * (g00 * p0 + g01 * p1)
    a[:, 1] -= pull * (g10 * p0 + g11 * p1)
    return residual, a


def cross_matrix(v: np.ndarray) -> np.ndarray:
    """[v]x: [v]x @ u = v x u."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _lens_jacobian(camera: CameraModel, normalized: np.ndarray) -> np.ndarray:
    """d(pixel)/d(normalised) (N, 2, 2) at normalised points (N, 2)."""
    if not camera.is_distorted:
        # A pinhole maps normalised to pixel coordinates linearly: K's upper-left block.
        return np.broadcast_to(camera.K[:2, :2], (len(normalized), 2, 2))
    columns = []
    for axis in range(2):
        step = np.zeros(2)
        step[axis] = _LENS_STEP
        forward = camera.project(np.column_stack([normalized + step, np.ones(len(normalized))]))
        backward = camera.project(np.column_stack([normalized - step, np.ones(len(normalized))]))
        columns.append((forward - backward) / (2.0 * _LENS_STEP))
    return np.stack(columns, axis=2)


@dataclass(frozen=True)
class LampMeasurements:
    """Several lamps' measurements evaluated as one: the residuals of each lamp in turn (all rims,
    then all markers), in one pass of array operations over all of them. Per-lamp numpy calls
    dominate the cost of small (thinned) rims, and a multi-lamp fit evaluates them for every
    start it probes."""

    parts: tuple[LampMeasurement, ...]

    def __post_init__(self) -> None:
        parts = self.parts
        rim_counts = [len(m.rim_rays) for m in parts]
        with_marker = [m for m in parts if m.marker_pixel is not None]
        constants = {
            'lamp_of_point': np.repeat(np.arange(len(parts)), rim_counts),
            'rays': np.vstack([m.rim_rays for m in parts]),
            'lens': tuple(np.concatenate([m._lens[i] for m in parts]) for i in range(4)),
            'rim_sigma': np.repeat([m.rim_sigma for m in parts], rim_counts),
            'centres': np.array([m.lamp.position for m in parts]),
            'q_diagonals': np.array([[1.0, 1.0, -m.lamp.radius ** 2] for m in parts]),
            'marker_maps': np.array([m._marker_map for m in with_marker]).reshape(-1, 3),
            'marker_pixels': np.array([m.marker_pixel for m in with_marker]).reshape(-1, 2),
            'marker_sigma': np.repeat([m.marker_sigma for m in with_marker], 2),
        }
        for name, value in constants.items():
            object.__setattr__(self, '_' + name, value)

    @property
    def residual_count(self) -> int:
        return sum(m.residual_count for m in self.parts)

    def linearize(self, rotation: np.ndarray, position: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """As ``LampMeasurement.linearize``, for all the lamps at once."""
        rim, rim_jacobian = self._rims(rotation, position)
        rim /= self._rim_sigma
        rim_jacobian /= self._rim_sigma[:, None]
        if not len(self._marker_maps):
            return rim, rim_jacobian
        markers, marker_jacobian = self._markers(rotation, position)
        return (np.concatenate([rim, markers / self._marker_sigma]),
                np.vstack([rim_jacobian, marker_jacobian / self._marker_sigma[:, None]]))

    def _rims(self, rotation: np.ndarray, position: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # LampMeasurement._rim with one conic per lamp, each point using its lamp's.
        count = len(self.parts)
        plane_axes = np.tile(np.eye(3), (count, 1, 1))
        plane_axes[:, :, 2] = self._centres - position
        image_to_plane = np.linalg.inv(rotation.T @ plane_axes)
        conics = image_to_plane.transpose(0, 2, 1) @ (self._q_diagonals[:, :, None] * image_to_plane)
        rays, lamp = self._rays, self._lamp_of_point
        residual, a = _edge_residuals(rays, np.einsum('ni,nij->nj', rays, conics[lamp]), self._lens)
        d_h = np.zeros((count, 6, 3, 3))
        d_h[:, :3, :, 2] = -rotation
        d_h[:, 3:] = -(rotation.T @ _AXIS_SKEWS)[None] @ plane_axes[:, None]
        m = conics[:, None] @ d_h @ image_to_plane[:, None]
        d_conic = -(m + m.transpose(0, 1, 3, 2)).reshape(count, 6, 9)
        outer = (a[:, :, None] * rays[:, None, :]).reshape(-1, 9)
        return residual, np.einsum('nm,nkm->nk', outer, d_conic[lamp])

    def _markers(self, rotation: np.ndarray, position: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # LampMeasurement._marker for every marker in one projectPoints call.
        offsets = self._marker_maps - position
        camera = self.parts[0].camera
        pixels, lens = cv2.projectPoints(offsets @ rotation, _ZERO3, _ZERO3, camera.K, camera.D)
        to_pixel = lens[:, 3:6].reshape(-1, 2, 3) @ rotation.T
        crosses = np.zeros((len(offsets), 3, 3))
        crosses[:, 0, 1], crosses[:, 0, 2], crosses[:, 1, 2] = -offsets[:, 2], offsets[:, 1], -offsets[:, 0]
        crosses -= crosses.transpose(0, 2, 1)
        jacobian = np.concatenate([-to_pixel, to_pixel @ crosses], axis=2).reshape(-1, 6)
        return (pixels.reshape(-1, 2) - self._marker_pixels).ravel(), jacobian
