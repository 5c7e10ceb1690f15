"""
How well a camera pose explains one lamp's observation: residuals in pixels over their noise.

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
``CameraModel.project``). Both are evaluated by ``fit_kernels``.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from vlp_ros.core.camera import CameraModel, PLUMB_BOB
from vlp_ros.core.lamp_map import Lamp
from vlp_ros.core.observation import LampObservation
from vlp_ros.solvers.fit_kernels import joined, linearize, rim_terms, Terms

if TYPE_CHECKING:
    from vlp_ros.solvers.up_measurement import UpMeasurement


@dataclass(frozen=True)
class LampMeasurement:
    """
    One lamp's observation, prepared for repeated residual evaluation.

    ``rim_rays`` (N, 3) are the rim points as homogeneous normalised coordinates;
    ``rim_pixel_jacobian`` (N, 2, 2) is d(normalised)/d(pixel) at each of them;
    ``marker_ray`` is the marker centroid's homogeneous normalised coordinates; ``terms``
    all of it as the residual kernels take it.
    """

    lamp: Lamp
    camera: CameraModel
    rim_rays: np.ndarray
    rim_pixel_jacobian: np.ndarray
    rim_sigma: float
    marker_pixel: np.ndarray | None
    marker_sigma: float
    marker_ray: np.ndarray | None
    # The prior sigma (px) of the rim's smooth error patterns (``LampObservation.rim_model_sigma``).
    rim_model_sigma: float = 0.0
    # The marker pixel's covariance (2x2, px^2; None: ``marker_sigma`` on either axis).
    marker_covariance: np.ndarray | None = None

    @classmethod
    def from_observation(cls, observation: LampObservation, lamp: Lamp,
                         camera: CameraModel) -> LampMeasurement:
        if camera.model != PLUMB_BOB:
            raise ValueError(f'the solvers model plumb_bob, not {camera.model!r}: see vlp_ros.solvers.pinhole_view')
        rim = np.asarray(observation.rim_points, dtype=float).reshape(-1, 2)
        if len(rim) < 5:
            raise ValueError(f'lamp {lamp.name!r}: need at least 5 rim points, got {len(rim)}')
        if not np.isfinite(rim).all():
            raise ValueError(f'lamp {lamp.name!r}: rim points are not all finite')
        if not observation.rim_sigma > 0.0:
            raise ValueError(f'lamp {lamp.name!r}: rim_sigma must be positive, got {observation.rim_sigma}')
        marker = marker_ray = None
        if observation.marker is not None:
            marker = np.asarray(observation.marker, dtype=float).reshape(2)
            if not np.isfinite(marker).all():
                raise ValueError(f'lamp {lamp.name!r}: marker pixel is not finite')
            if not observation.marker_sigma > 0.0:
                raise ValueError(f'lamp {lamp.name!r}: marker_sigma must be positive, '
                                 f'got {observation.marker_sigma}')
            marker_ray = np.append(camera.normalize(marker)[0], 1.0)
            covariance = observation.marker_covariance
            if covariance is not None and not _is_covariance(covariance):
                raise ValueError(f'lamp {lamp.name!r}: marker_covariance must be a positive definite 2x2 matrix')
        rays, lens = rim_terms(camera.normalize(rim), camera.K, camera.D, camera.is_distorted,
                               camera.pinhole_pixel_inverse)
        return cls(lamp=lamp, camera=camera, rim_rays=rays, rim_pixel_jacobian=lens,
                   rim_sigma=float(observation.rim_sigma), marker_pixel=marker,
                   marker_sigma=float(observation.marker_sigma), marker_ray=marker_ray,
                   rim_model_sigma=float(observation.rim_model_sigma),
                   marker_covariance=None if marker is None or observation.marker_covariance is None
                   else np.array(observation.marker_covariance, dtype=float).reshape(2, 2))

    def thinned(self, max_rim_points: int) -> LampMeasurement:
        """Return the same measurement on every k-th rim point, at most ``max_rim_points`` of them."""
        step = -(-len(self.rim_rays) // max_rim_points)
        return replace(self, rim_rays=self.rim_rays[::step], rim_pixel_jacobian=self.rim_pixel_jacobian[::step])

    @property
    def residual_count(self) -> int:
        return len(self.rim_rays) + (0 if self.marker_pixel is None else 2)

    def __post_init__(self) -> None:
        lamp, count = self.lamp, len(self.rim_rays)
        markers = {}
        if self.marker_pixel is not None:
            markers = {'marker_maps': lamp.marker_position().reshape(1, 3),
                       'marker_pixels': np.array(self.marker_pixel, dtype=float).reshape(1, 2),
                       'marker_whitening': marker_whitening(self.marker_sigma, self.marker_covariance)[None]}
        terms = Terms(rays=np.ascontiguousarray(self.rim_rays, dtype=float),
                      lens=np.ascontiguousarray(self.rim_pixel_jacobian, dtype=float).reshape(count, 4),
                      rim_sigma=np.full(count, self.rim_sigma), lamp_of_point=np.zeros(count, dtype=np.int64),
                      centres=np.array(lamp.position, dtype=float).reshape(1, 3),
                      radii_squared=np.array([lamp.radius ** 2]),
                      intrinsics=self.camera.K, distortion=self.camera.D, **markers)
        object.__setattr__(self, 'terms', terms)

    def linearize(self, rotation: np.ndarray, position: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """
        Return the residuals over their sigmas (M,) for the camera pose and their Jacobian (M, 6).

        The pose is ``rotation`` camera to map and ``position``; the Jacobian is with respect to the pose
        perturbation of ``covariance.perturbed``: the rim points' in order, then the marker's.
        """
        return linearize(self.terms, rotation, position)

    def lamp_center_in_camera(self, rotation: np.ndarray, position: np.ndarray) -> np.ndarray:
        return (self.lamp.position - position) @ rotation


@dataclass(frozen=True)
class LampMeasurements:
    """
    Several lamps' measurements, and any up measurements (``UpMeasurement``), evaluated as one.

    They are evaluated all rims, then all markers, then all up directions, each kind in the order of the
    parts, with their ``Terms`` joined once: a multi-lamp fit evaluates them for every start it probes.
    """

    parts: tuple[LampMeasurement | UpMeasurement, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, 'terms', joined([m.terms for m in self.parts]))

    @property
    def residual_count(self) -> int:
        return self.terms.residual_count

    def linearize(self, rotation: np.ndarray, position: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """As ``LampMeasurement.linearize``, for all the parts at once."""
        return linearize(self.terms, rotation, position)


def marker_whitening(sigma: float, covariance: np.ndarray | None) -> np.ndarray:
    """
    Return W (2x2) with W^T W the inverse of a marker pixel's covariance (``sigma`` on either axis if None).

    W = L^-1 for the Cholesky factor L L^T = covariance: its residuals W d are independent with unit variance.
    """
    if covariance is None:
        return np.eye(2) / sigma
    return np.ascontiguousarray(np.linalg.inv(np.linalg.cholesky(0.5 * (covariance + covariance.T))))


def _is_covariance(covariance: np.ndarray) -> bool:
    matrix = np.asarray(covariance, dtype=float)
    if matrix.shape != (2, 2) or not np.isfinite(matrix).all():
        return False
    return bool(matrix[0, 0] > 0.0 and matrix[0, 0] * matrix[1, 1] - matrix[0, 1] * matrix[1, 0] > 0.0)


# Modes of model error per lamp in ``rim_error_modes``: the offset and the first two harmonics.
RIM_MODES = 5


def rim_error_modes(terms: Terms, rotation: np.ndarray, position: np.ndarray) -> np.ndarray:
    """
    Return how model error can move each rim point of ``terms`` across the edge, for the camera pose.

    The pose is ``rotation`` camera to map and ``position``: (N, ``RIM_MODES``) px per unit of each
    mode, the shape times 1, cos t, sin t, cos 2t, sin 2t of the point's angle t round its disc.

    The shape (mean 1 per lamp) is inverse to the image scale across the edge there: a diffuser's
    falloff or a glare halo changes the light by a fixed share per metre of the disc; blurred
    by the optics over a fixed number of pixels, it moves the half-level crossing by fewer pixels
    where the disc is drawn larger (its near side). The harmonics up to the second are what one
    lamp's ellipse absorbs (its centre, axes and orientation), so its residuals cannot show them:
    measured on an independent renderer's blurred frames at the true pose, 0.3-0.4 px inward and
    0.6 px in the second harmonic (rows and columns of a rolling-shutter lamp read differently),
    where clean frames are within 0.05 px.
    """
    rays_in_map = np.ascontiguousarray(terms.rays, dtype=float) @ rotation.T
    centres = terms.centres[terms.lamp_of_point]
    along = (centres[:, 2] - position[2]) / rays_in_map[:, 2]
    on_disc = position + along[:, None] * rays_in_map
    radial = on_disc - centres
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    # The image of a point a millimetre further out on the disc.
    outward = (on_disc + 1e-3 * radial - position) @ rotation
    moved = outward[:, :2] / outward[:, 2:3] - terms.rays[:, :2] / terms.rays[:, 2:3]
    shape = 1.0 / np.linalg.norm(moved, axis=1)
    for lamp in range(len(terms.centres)):
        mine = terms.lamp_of_point == lamp
        shape[mine] /= shape[mine].mean()
    cos, sin = radial[:, 0], radial[:, 1]
    return shape[:, None] * np.column_stack([np.ones_like(cos), cos, sin, cos * cos - sin * sin, 2.0 * cos * sin])
