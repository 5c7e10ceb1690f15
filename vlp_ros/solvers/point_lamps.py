"""
Point lamps (map radius 0).

The centre of a lamp's light as a projected point, and where poses from such points
start.

A point lamp is a bare LED, or a lamp too small or too soft for an ellipse. Its measurement
is the offset of the observed centre of its light from the projection of its map position
(through the camera's K and D), over the centre's sigma: the same projected-point residual
as a disc lamp's marker (``fit_kernels``), so point lamps, disc lamps and up directions
join one least-squares fit and its covariance.

Each point gives two residuals: three points fix the pose (P3P, up to four solutions, all
explaining the image exactly), two points fix it with a measured up direction (closed form
below, at most two). A point lamp shines down, so a pose above any point lamp is not one
from which it was seen. The remaining solutions are told apart as the disc lamps' are
(``ambiguity``): by other lamps, the up direction's gate, continuity, or not at all.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import math

import cv2
import numpy as np

from vlp_ros.core.camera import CameraModel
from vlp_ros.core.lamp_map import Lamp
from vlp_ros.core.observation import LampObservation
from vlp_ros.core.pose import Pose
from vlp_ros.solvers.fit_kernels import linearize, Terms

# The ellipse centre of a detected blob, from N rim points of sigma s across the edge, has a
# spread of ~ s sqrt(2 / N) per axis for independent points; blur and stripes correlate
# neighbouring rim points, so it is taken as this many times that. Measured on the simulator's
# bare LEDs (vlp_ros.sim.point_lamps, 4K, 24 photos, 100 centres): 1.4 gives a mean chi-square
# of 2.08 per centre (2 is honest) and pose NEES 7.0, 1.6 gives 1.59 and 5.3. The floor (px)
# only keeps a perfectly smooth rim from claiming an exact centre.
_RIM_CORRELATION = 1.5
CENTER_SIGMA_FLOOR = 0.01


def center_sigma(observation: LampObservation) -> float:
    """
    Return standard deviation (px, per axis) of the observation's centre as a point lamp's image.

    The detector's own when it measured the centre, else from the rim's fit.
    """
    if observation.center_sigma is not None:
        return float(observation.center_sigma)
    count = max(len(observation.rim_points), 1)
    return max(_RIM_CORRELATION * float(observation.rim_sigma) * math.sqrt(2.0 / count), CENTER_SIGMA_FLOOR)


@dataclass(frozen=True, eq=False)
class PointLampMeasurement:
    """
    A point lamp seen at ``pixel`` (raw, distorted) with ``sigma`` (px, per axis).

    ``ray`` is that pixel's homogeneous normalised coordinates.
    """

    lamp: Lamp
    camera: CameraModel
    pixel: np.ndarray
    sigma: float
    ray: np.ndarray = field(init=False, repr=False)
    terms: Terms = field(init=False, repr=False)

    residual_count = 2

    @classmethod
    def from_observation(cls, observation: LampObservation, lamp: Lamp, camera: CameraModel) -> PointLampMeasurement:
        return cls(lamp, camera, observation.center, center_sigma(observation))

    def __post_init__(self) -> None:
        pixel = np.asarray(self.pixel, dtype=float).reshape(2)
        if not np.isfinite(pixel).all():
            raise ValueError(f'lamp {self.lamp.name!r}: centre pixel is not finite')
        if not (math.isfinite(self.sigma) and self.sigma > 0.0):
            raise ValueError(f'lamp {self.lamp.name!r}: centre sigma must be positive, got {self.sigma}')
        object.__setattr__(self, 'pixel', pixel)
        object.__setattr__(self, 'ray', np.append(self.camera.normalize(pixel)[0], 1.0))
        object.__setattr__(self, 'terms', Terms(
            marker_maps=np.array(self.lamp.position, dtype=float).reshape(1, 3), marker_pixels=pixel.reshape(1, 2),
            marker_whitening=np.eye(2).reshape(1, 2, 2) / float(self.sigma), intrinsics=self.camera.K,
            distortion=self.camera.D))

    def thinned(self, max_rim_points: int) -> PointLampMeasurement:
        """Itself: a point has no rim to thin (as ``LampMeasurement.thinned``)."""
        return self

    def linearize(self, rotation: np.ndarray, position: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Residuals over sigma (2,) and their Jacobian (2, 6), as ``LampMeasurement.linearize``."""
        return linearize(self.terms, rotation, position)

    def lamp_center_in_camera(self, rotation: np.ndarray, position: np.ndarray) -> np.ndarray:
        return (self.lamp.position - position) @ rotation


def seen_from_below(pose: Pose, points: list[PointLampMeasurement]) -> bool:
    """Whether the camera is below every point lamp, which shines down."""
    return all(pose.position[2] < m.lamp.position[2] for m in points)


def point_starts(points: list[PointLampMeasurement], up_directions: list[np.ndarray]) -> list[Pose]:
    """
    Poses from the points alone.

    P3P on the three that span the largest triangle in the image, and, for each up
    direction, the closed form on the two farthest apart.
    """
    starts = []
    rays = np.array([m.ray for m in points])
    positions = np.array([m.lamp.position for m in points])
    if len(points) >= 3:
        triple = max(((i, j, k) for i in range(len(points)) for j in range(i) for k in range(j)),
                     key=lambda t: _triangle_area(rays[list(t), :2]))
        starts.extend(p3p_poses(positions[list(triple)], rays[list(triple), :2]))
    if len(points) >= 2:
        i, j = max(((i, j) for i in range(len(points)) for j in range(i)),
                   key=lambda pair: np.linalg.norm(rays[pair[0]] - rays[pair[1]]))
        for up in up_directions:
            starts.extend(two_points_with_up(positions[[i, j]], rays[[i, j]], up))
    return starts


def p3p_poses(positions: np.ndarray, normalized: np.ndarray) -> list[Pose]:
    """Every solution of P3P for three map points (3, 3) seen at normalised coordinates (3, 2)."""
    try:
        count, rvecs, tvecs = cv2.solveP3P(np.ascontiguousarray(positions, dtype=float).reshape(3, 1, 3),
                                           np.ascontiguousarray(normalized, dtype=float).reshape(3, 1, 2),
                                           np.eye(3), None, flags=cv2.SOLVEPNP_P3P)
    except cv2.error:
        return []
    return [pose_from_opencv(rvec, tvec) for rvec, tvec in zip(rvecs[:count], tvecs[:count])]


def pose_from_opencv(rvec: np.ndarray, tvec: np.ndarray) -> Pose:
    """Return the camera pose of OpenCV's map-to-camera rotation vector and translation."""
    map_to_camera, _ = cv2.Rodrigues(rvec)
    return Pose(map_to_camera.T, -map_to_camera.T @ np.asarray(tvec, dtype=float).reshape(3))


def two_points_with_up(positions: np.ndarray, rays: np.ndarray, up: np.ndarray) -> list[Pose]:
    """
    Return the poses that see map points ``positions`` (2, 3) along camera rays ``rays`` (2, 3), up along ``up``.

    That is with map +z along ``up`` in the camera: at most two (the camera's height solves a quadratic).

    With R0 turning camera vectors into a levelled frame (R0 up = e_z) and d_i = R0 ray_i, a
    camera at height h sees point i at depth l_i = (z_i - h) / d_iz along d_i; the yaw turns
    the levelled horizontal offset l_1 d_1 - l_2 d_2 onto the points' horizontal offset, so
    the two must be equally long: a quadratic in h.
    """
    up = np.asarray(up, dtype=float) / np.linalg.norm(up)
    levelling = _levelling(up)
    d = (levelling @ np.asarray(rays, dtype=float).T).T
    if np.any(np.abs(d[:, 2]) < 1e-9):
        return []
    z = positions[:, 2]
    # l_1 d_1 - l_2 d_2 = (z_1 - h) a - (z_2 - h) b = (z_1 a - z_2 b) - h (a - b), a = d_1 / d_1z, b = d_2 / d_2z.
    a, b = d[0, :2] / d[0, 2], d[1, :2] / d[1, 2]
    constant, slope = z[0] * a - z[1] * b, a - b
    target = np.linalg.norm(positions[0, :2] - positions[1, :2])
    roots = np.roots([slope @ slope, -2.0 * constant @ slope, constant @ constant - target ** 2])
    poses = []
    for h in roots:
        if abs(h.imag) > 1e-9 * max(1.0, abs(h.real)):
            continue
        h = float(h.real)
        depths = (z - h) / d[:, 2]
        if not np.all(depths > 0.0):
            continue
        seen = depths[0] * d[0, :2] - depths[1] * d[1, :2]
        wanted = positions[0, :2] - positions[1, :2]
        yaw = math.atan2(wanted[1], wanted[0]) - math.atan2(seen[1], seen[0])
        turn = np.array([[math.cos(yaw), -math.sin(yaw), 0.0], [math.sin(yaw), math.cos(yaw), 0.0], [0.0, 0.0, 1.0]])
        rotation = turn @ levelling
        poses.append(Pose(rotation, positions[0] - depths[0] * (rotation @ rays[0])))
    return poses


def _triangle_area(corners: np.ndarray) -> float:
    (ax, ay), (bx, by) = corners[1] - corners[0], corners[2] - corners[0]
    return abs(ax * by - ay * bx)


def _levelling(up: np.ndarray) -> np.ndarray:
    """Return a rotation taking camera vectors to a frame whose +z is ``up`` (unit)."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, up)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(up, x), up])
