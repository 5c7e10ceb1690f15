"""
Observations of a camera the solvers do not model, seen through the ideal pinhole camera with its K.

The solver kernels model plumb_bob exactly (projection and its Jacobian). For the other
models (rational_polynomial, equidistant, a rectified frame turned by camera_info's R) each
observation's rim points and marker are mapped to the pixels of the pinhole camera with the
same K (``CameraModel.undistort_pixels``), the rim ellipse is refitted there, and the pixel
noise is carried through the mapping's local Jacobian J:

- a rim point moves across the edge: the raw edge normal n maps to a distance of
  sigma / |J^-T n| across the mapped edge; the lamp's rim_sigma becomes the RMS of that
  over its rim points (the solvers take one sigma per lamp);
- the marker centroid's isotropic sigma becomes sigma * sqrt(|det J|), the geometric mean
  of the mapped axes.

Detection and beacon decoding stay on the raw image; only the solvers see the mapped lamps.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from vlp_ros.core.camera import CameraModel, PLUMB_BOB
from vlp_ros.core.ellipse import conic_from_ellipse, fit_ellipse
from vlp_ros.core.lamp_map import Lamp
from vlp_ros.core.observation import LampObservation

# Central differences over half a pixel: the mapping is smooth on that scale, its Jacobian exact to < 1e-6.
STEP_PX = 0.5


def solver_view(pairs: list[tuple[LampObservation, Lamp]],
                camera: CameraModel) -> tuple[list[tuple[LampObservation, Lamp]], CameraModel]:
    """
    Return the (observation, lamp) pairs and camera the solvers take.

    Unchanged for plumb_bob, else mapped to the pinhole.
    """
    if camera.model == PLUMB_BOB:
        return pairs, camera
    return [(seen_through_pinhole(observation, camera), lamp) for observation, lamp in pairs], camera.pinhole()


def seen_through_pinhole(observation: LampObservation, camera: CameraModel) -> LampObservation:
    """``observation`` (raw pixels of ``camera``) in the pixels of ``camera.pinhole()``, noise carried along."""
    if not observation.rim_usable:
        return _light_seen_through_pinhole(observation, camera)
    rim = np.asarray(observation.rim_points, dtype=float).reshape(-1, 2)
    mapped_rim, jacobians = _mapped_with_jacobians(camera, rim)
    conic = conic_from_ellipse(observation.ellipse)
    normals = rim @ conic[:2, :2].T + conic[:2, 2]
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    across = 1.0 / np.linalg.norm(np.einsum('nji,nj->ni', np.linalg.inv(jacobians), normals), axis=1)
    changes = {'ellipse': fit_ellipse(mapped_rim), 'rim_points': mapped_rim,
               'rim_sigma': float(observation.rim_sigma * np.sqrt(np.mean(across ** 2)))}
    if observation.marker is not None:
        marker, marker_jacobian = _mapped_with_jacobians(
            camera, np.asarray(observation.marker, dtype=float).reshape(1, 2))
        changes.update(marker=marker[0],
                       marker_sigma=float(observation.marker_sigma * np.sqrt(abs(np.linalg.det(marker_jacobian[0])))))
        if observation.marker_covariance is not None:
            to_pinhole = marker_jacobian[0]
            changes.update(marker_covariance=to_pinhole @ observation.marker_covariance @ to_pinhole.T)
    return replace(observation, **changes)


def _light_seen_through_pinhole(observation: LampObservation, camera: CameraModel) -> LampObservation:
    """Return a rim-less observation (a point lamp's light): its centre mapped, its sigma as the marker's."""
    centre, jacobian = _mapped_with_jacobians(camera, observation.center.reshape(1, 2))
    ellipse = np.array(observation.ellipse, dtype=float)
    ellipse[:2] = centre[0]
    sigma = observation.center_sigma
    return replace(observation, ellipse=ellipse,
                   center_sigma=None if sigma is None else float(sigma * np.sqrt(abs(np.linalg.det(jacobian[0])))))


def _mapped_with_jacobians(camera: CameraModel, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole pixels (N, 2) of raw ``pixels`` (N, 2) and d(pinhole)/d(raw) (N, 2, 2) at each."""
    offsets = STEP_PX * np.array([[0.0, 0.0], [1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])
    mapped = camera.undistort_pixels((pixels[None, :, :] + offsets[:, None, :]).reshape(-1, 2)).reshape(5, -1, 2)
    jacobians = np.stack([mapped[1] - mapped[2], mapped[3] - mapped[4]], axis=2) / (2.0 * STEP_PX)
    return mapped[0], jacobians
