"""
One pose from every identified lamp of a frame.

A joint least squares (the paper's eq. 15, generalised to exact perspective, any number of
lamps and lamps without markers).

Starts: each lamp's two circle poses, their yaw from the lamp's marker or, without
one, from the image of another lamp's centre (exact for any number of lamps); and
for four or more lamps SQPnP on the lamp centres (with three lamps on one ceiling
SQPnP returned three poses, none of them right). Starts that lead to the same pose
are refined once; every distinct joint minimum is a candidate. A wrong single-lamp candidate puts the
camera metres away, where the other lamps would be seen elsewhere, so its joint
minimum costs far more than the true one: ``ambiguity.choose_candidate`` then
decides on the (statistically bounded) cost gap and reports MULTI_LAMP, still
subject to every hint. Lamps that cannot be explained by one pose at all (a
misidentified lamp, a wrong map entry) give INCONSISTENT_LAMPS.

Point lamps (map radius 0, ``point_lamps``) join the same fit as projected points: they
give disc lamps their heading like any lamp centre, and start poses of their own (P3P,
or two points and an up direction); a pose above a point lamp is not one it was seen from.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
import threading

import cv2
import numpy as np

from vlp_ros.core.camera import CameraModel
from vlp_ros.core.ellipse import ellipse_from_conic
from vlp_ros.core.lamp_map import Lamp
from vlp_ros.core.observation import LampObservation
from vlp_ros.core.pose import Pose
from vlp_ros.solvers.ambiguity import choose_candidate, DisambiguationHints
from vlp_ros.solvers.candidates import Choice, distinct, explains_the_image, PoseCandidate, Reason
from vlp_ros.solvers.circle_pose import circle_poses, normalized_conic
from vlp_ros.solvers.covariance import with_lamp_position_uncertainty
from vlp_ros.solvers.floor import Floor, on_floor, tilted_off_the_floor, yaw_from_continuity
from vlp_ros.solvers.measurement import LampMeasurement, LampMeasurements
from vlp_ros.solvers.perspective import pose_from_circle, solve_lamp, widened_where_up_disagrees
from vlp_ros.solvers.point_lamps import (point_starts, PointLampMeasurement, pose_from_opencv, seen_from_below,
                                         two_points_with_up)
from vlp_ros.solvers.refinement import descend, forecast_from, FORECAST_MARGIN, linearize, Measurement, refine_pose
from vlp_ros.solvers.up_measurement import UpMeasurement, with_agreeing_up

# Poses closer than this (m, rad) lead to the same minimum: follow only the cheapest.
_SAME_START_M = 0.05
_SAME_START_RAD = 0.05
# Each start is first followed on a thinned copy of the data. Any pose that explains
# all lamps explains each one, so it lies within single-lamp error of one of that
# lamp's candidates, i.e. of a start, and is reached from there in 2-5 iterations
# (quadratic convergence). A start still over ``_HOPELESS_FACTOR`` times the best
# minimum's chi-square after ``refinement.PATIENCE`` iterations (wrong candidates
# creep along plateaus ~1000x above it), or not converged within
# ``_PROBE_ITERATIONS``, cannot lead to a competitive pose and is dropped, as is one
# that has come near a minimum already reached.
_PROBE_RIM_POINTS = 16
_PROBE_ITERATIONS = 10
_HOPELESS_FACTOR = 100.0
_PNP_MIN_LAMPS = 4
# The latest disc lamps' measurements (and their thinned copies), by the identity of their observation, lamp and
# camera: the solves of one frame (each ID tried with the geometry is a solve of most of the same lamps) build
# each once. An entry holds those three objects, so their ids are not reused while it is kept.
_MEASURED: dict[tuple[int, int, int], tuple[object, ...]] = {}
_MEASURED_KEPT = 32
_MEASURED_LOCK = threading.Lock()


def solve_lamps(pairs: list[tuple[LampObservation, Lamp]], camera: CameraModel,
                hints: DisambiguationHints, floor: Floor | None = None) -> Choice:
    """
    Return the camera pose from all identified lamps of one frame, or no pose and why.

    ``floor``: the robot's base moves on a horizontal floor, a measurement of every candidate
    (``solvers.floor``). The covariance includes the uncertainty of the lamps' map positions
    (``Lamp.position_sigma``).
    """
    choice = _chosen_pose(pairs, camera, hints, floor)
    if choice.pose is None or choice.pose.covariance is None or all(l.position_sigma is None for _, l in pairs):
        return choice
    return replace(choice, pose=Pose(choice.pose.rotation, choice.pose.position,
                                     _with_map_uncertainty(choice.pose, pairs, camera, hints, floor)))


def _with_map_uncertainty(pose: Pose, pairs: list[tuple[LampObservation, Lamp]], camera: CameraModel,
                          hints: DisambiguationHints, floor: Floor | None) -> np.ndarray:
    measurements = [(PointLampMeasurement if lamp.is_point else LampMeasurement).from_observation(obs, lamp, camera)
                    for obs, lamp in pairs]
    jacobians = [m.linearize(pose.rotation, pose.position)[1] for m in measurements]
    other = sum((j.T @ j for j in (m.linearize(pose.rotation, pose.position)[1] for m in hints.up_measurements())),
                np.zeros((6, 6)))
    if floor is not None:
        floor_jacobian = floor.linearize(pose)[1]
        other = other + floor_jacobian.T @ floor_jacobian
    return with_lamp_position_uncertainty(pose.covariance, jacobians, other, [lamp.position_sigma for _, lamp in pairs])


def _chosen_pose(pairs: list[tuple[LampObservation, Lamp]], camera: CameraModel,
                 hints: DisambiguationHints, floor: Floor | None) -> Choice:
    if not pairs:
        return Choice(None, Reason.NO_CANDIDATES, 'no identified lamp')
    ids = [lamp.id for _, lamp in pairs]
    if len(set(ids)) != len(ids):
        return Choice(None, Reason.INCONSISTENT_LAMPS, f'one lamp identified twice in the frame: {sorted(ids)}')
    up = hints.up_measurements()
    # Several lamps' fit takes the floor's tilt in: small lamps leave it loose, and the fit would slide off.
    floor_up = [] if floor is None else [floor.up_measurement()]
    points = sum(lamp.is_point for _, lamp in pairs)
    if points == len(pairs) and 2 * points + 2 * len(up) + 2 * len(floor_up) < 6:
        return Choice(None, Reason.NO_CANDIDATES, f'{points} point lamp(s) leave the pose free: it takes three, '
                                                  'or two and an up direction with a sigma')
    if len(pairs) == 1:
        observation, lamp = pairs[0]
        if observation.marker is None:
            return _headed_by_continuity(observation, lamp, camera, hints, floor)
        candidates = solve_lamp(observation, lamp, camera, up)
        explaining = [c for c in candidates if explains_the_image(c)]
        if candidates and not explaining:
            return Choice(None, Reason.POOR_FIT, f'best single-lamp chi-square {candidates[0].cost:.0f} for '
                                                 f'{candidates[0].residual_count - 6} degrees of freedom')
        return _chosen(explaining, hints, floor)
    directions = [hint.vector for hint in hints.up_in_camera]
    # The floor's up direction starts poses from the lamps' centres: the circle poses' mirror may mislead.
    level = [] if floor is None else [floor.mounting.up_in_camera()]
    candidates = with_agreeing_up(
        lambda agreeing: joint_candidates(pairs, camera, [*agreeing, *floor_up], directions, level), up)
    candidates = widened_where_up_disagrees(candidates, up, np.mean([lamp.position for _, lamp in pairs], axis=0))
    if not candidates:
        return Choice(None, Reason.INCONSISTENT_LAMPS, 'no start led to a pose that explains all lamps')
    best = candidates[0]
    if not explains_the_image(best) and floor is not None and tilted_off_the_floor(best, floor):
        return Choice(None, Reason.OFF_THE_FLOOR, 'the lamps tilt the robot plainly off the floor')
    if not explains_the_image(best):
        return Choice(None, Reason.INCONSISTENT_LAMPS,
                      f'best joint chi-square {best.cost:.0f} for {best.residual_count - 6} degrees of freedom')
    choice = _chosen(candidates, hints, floor, tilt=False, cost_reason=Reason.MULTI_LAMP)
    # A single joint minimum is the other lamps' doing: each lamp alone has two.
    return replace(choice, reason=Reason.MULTI_LAMP) if choice.reason is Reason.UNIQUE else choice


def _chosen(candidates: list[PoseCandidate], hints: DisambiguationHints, floor: Floor | None, tilt: bool = True,
            cost_reason: Reason = Reason.COST) -> Choice:
    """``choose_candidate`` among the candidates, first fused with the floor (its tilt too unless not ``tilt``)."""
    if floor is not None and candidates:
        candidates, contradicting = on_floor(candidates, floor, tilt)
        if not candidates:
            return Choice(None, Reason.OFF_THE_FLOOR, f'{contradicting} candidate(s), each plainly off the floor')
    return choose_candidate(candidates, hints, cost_reason=cost_reason)


def _headed_by_continuity(observation: LampObservation, lamp: Lamp, camera: CameraModel,
                          hints: DisambiguationHints, floor: Floor | None) -> Choice:
    """One disc lamp without its marker: on the floor, headed as the recent pose; else no pose."""
    if floor is None or not hints.continuity_counts:
        return Choice(None, Reason.NO_CANDIDATES, f'lamp {lamp.name!r} alone, without its marker, leaves the yaw free')
    candidates, contradicting = yaw_from_continuity(observation, lamp, camera, floor, hints.recent_pose,
                                                    hints.recent_age)
    if not candidates and contradicting:
        return Choice(None, Reason.OFF_THE_FLOOR, f'{contradicting} candidate(s), each plainly off the floor')
    return choose_candidate(candidates, hints)


def joint_candidates(pairs: list[tuple[LampObservation, Lamp]], camera: CameraModel,
                     up: Sequence[UpMeasurement] = (), up_directions: Sequence[np.ndarray] = (),
                     level_directions: Sequence[np.ndarray] = ()) -> list[PoseCandidate]:
    """
    Distinct refined joint poses (cheapest first, covariance set) for two or more lamps and any measured up directions.

    ``up_directions`` (camera frame, measured or not) start poses from two point lamps;
    ``level_directions`` (the floor's) from the two lamp centres, discs or points, farthest apart in the image.
    """
    measured = [_measured(obs, lamp, camera) for obs, lamp in pairs if not lamp.is_point]
    discs = [measurement for measurement, _ in measured]
    points = [PointLampMeasurement.from_observation(obs, lamp, camera) for obs, lamp in pairs if lamp.is_point]
    measurements = [*discs, *points]
    if sum(m.residual_count for m in (*measurements, *up)) < 6:
        return []
    starts = _starts(discs, points, level_directions) + point_starts(points, list(up_directions))
    # Joined once: every start is scored and probed on it.
    coarse = [LampMeasurements((*(thinned for _, thinned in measured), *points, *up))]
    reached: list[tuple[Pose, float]] = []

    def known_or_hopeless(pose: Pose, cost: float) -> bool:
        return any(_near(pose, minimum) for minimum, _ in reached) or \
            cost > _HOPELESS_FACTOR * min((c for _, c in reached), default=np.inf)

    for start, forecast in _distinct_poses(starts, coarse):
        best = min((c for _, c in reached), default=np.inf)
        if forecast > FORECAST_MARGIN * _HOPELESS_FACTOR * best:
            continue
        probe = descend(start, coarse, _PROBE_ITERATIONS, give_up=known_or_hopeless)
        if probe is not None and not any(_near(probe[0], minimum) for minimum, _ in reached):
            reached.append(probe)
    refined = (refine_pose(pose, measurements, up) for pose, _ in reached)
    return distinct([candidate for candidate in refined
                     if candidate is not None and seen_from_below(candidate.pose, points)])


def _measured(observation: LampObservation, lamp: Lamp,
              camera: CameraModel) -> tuple[LampMeasurement, LampMeasurement]:
    """Return the disc lamp's measurement and its copy thinned for probing, built once while kept in ``_MEASURED``."""
    key = (id(observation), id(lamp), id(camera))
    with _MEASURED_LOCK:
        entry = _MEASURED.get(key)
    if entry is None:
        measurement = LampMeasurement.from_observation(observation, lamp, camera)
        entry = (observation, lamp, camera, measurement, measurement.thinned(_PROBE_RIM_POINTS))
        with _MEASURED_LOCK:
            while len(_MEASURED) >= _MEASURED_KEPT:
                del _MEASURED[next(iter(_MEASURED))]
            _MEASURED[key] = entry
    return entry[3], entry[4]


def _starts(discs: list[LampMeasurement], points: Sequence[PointLampMeasurement] = (),
            level_directions: Sequence[np.ndarray] = ()) -> list[Pose]:
    """
    Return each disc lamp's circle poses, and SQPnP on all lamp centres when there are enough of them.

    The circle poses are headed by the lamp's marker or the farthest other lamp. For each of
    ``level_directions``, the pose with that up direction from the two centres farthest apart.
    """
    conics = [normalized_conic(m.rim_rays[:, :2]) for m in discs]
    centres = np.array([ellipse_from_conic(conic)[:2] for conic in conics] + [m.ray[:2] for m in points])
    rays = np.column_stack([centres, np.ones(len(centres))])
    measurements = [*discs, *points]
    starts = []
    for i, (measurement, conic) in enumerate(zip(discs, conics)):
        lamp = measurement.lamp
        if measurement.marker_ray is not None:
            ray, target = measurement.marker_ray, lamp.marker_position()
        else:
            # The farthest other lamp in the image gives the best-conditioned heading.
            j = max((k for k in range(len(measurements)) if k != i), key=lambda k: np.linalg.norm(rays[k] - rays[i]))
            ray, target = rays[j], measurements[j].lamp.position
        for circle in circle_poses(conic, lamp.radius):
            pose = pose_from_circle(circle, lamp, ray, target)
            if pose is not None:
                starts.append(pose)
    if len(measurements) >= _PNP_MIN_LAMPS:
        starts.extend(pnp_starts(np.array([m.lamp.position for m in measurements]), centres))
    if level_directions and len(measurements) >= 2:
        i, j = max(((i, j) for i in range(len(rays)) for j in range(i)),
                   key=lambda pair: np.linalg.norm(rays[pair[0]] - rays[pair[1]]))
        positions = np.array([measurements[i].lamp.position, measurements[j].lamp.position])
        for up in level_directions:
            starts.extend(two_points_with_up(positions, rays[[i, j]], up))
    return starts


def pnp_starts(lamp_positions: np.ndarray, image_centres: np.ndarray) -> list[Pose]:
    """
    Return the solutions of SQPnP for the lamp centres seen at the ellipse centres.

    The ellipse centres are close enough to the projected circle centres for a start.
    """
    try:
        _, rvecs, tvecs, _ = cv2.solvePnPGeneric(lamp_positions, image_centres.reshape(-1, 1, 2), np.eye(3), None,
                                                 flags=cv2.SOLVEPNP_SQPNP)
    except cv2.error:
        return []
    return [pose_from_opencv(rvec, tvec) for rvec, tvec in zip(rvecs, tvecs)]


def _distinct_poses(starts: list[Pose], measurements: list[Measurement]) -> list[tuple[Pose, float]]:
    """
    Return the poses with a finite joint cost, cheapest first, one per neighbourhood.

    Each comes with the chi-square its Gauss-Newton model forecasts (from the same linearisation).
    """
    scored = []
    for start in starts:
        try:
            residuals, jacobian = linearize(measurements, start)
        except np.linalg.LinAlgError:
            continue
        cost = float(residuals @ residuals)
        if np.isfinite(cost):
            scored.append((cost, start, forecast_from(residuals, jacobian)))
    kept: list[tuple[Pose, float]] = []
    for _, start, forecast in sorted(scored, key=lambda item: item[0]):
        if not any(_near(start, k) for k, _ in kept):
            kept.append((start, forecast))
    return kept


def _near(a: Pose, b: Pose) -> bool:
    return a.position_error(b) < _SAME_START_M and a.rotation_error(b) < _SAME_START_RAD
