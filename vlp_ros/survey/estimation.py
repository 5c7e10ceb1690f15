"""
Camera poses, lamp positions and marker angles estimated together from a survey drive (a pose graph).

Unknowns: every frame's camera pose (a rotation vector applied on the left of its start, and the
position) and every free lamp's centre and marker angle (discs hang horizontal, facing down, so a
lamp's frame is its centre and a turn about map z). Measurements, each whitened by its covariance:

- a sighting: the camera's pose in the lamp's frame, solved from that lamp alone (``sightings``);
- odometry: the base's motion between consecutive frames, in the base frame, with a sigma that
  grows with the distance and the turn (wheel odometry errs by a few per cent of its scale and
  drifts in heading);
- gravity: where map up points in the camera, when the recording has an IMU.

Anchors (lamps with a given position) are held by tight priors. gtsam's Levenberg-Marquardt solves
the factor graph, every measurement under a Huber loss, so a wrong association or a glare-bitten
frame is down-weighted instead of pulling the map; the lamps' covariance is gtsam's marginal at the
solution, scaled up when the sightings' residuals say their stated noise is too small (the a posteriori
variance factor). A sighting's covariance is its pose fit's own; where the residuals show more scatter than
that, a growing share of the fit's allowance for the rim's model error joins it (``MODEL_SHARES``): blurred,
glaring or graded lamps bend a lone lamp's tilt by tenths of a degree that no single frame shows. Each sighting
has two candidates at most: the one nearest the expected up direction starts, and after one solve each
sighting takes the candidate the estimate agrees with and the graph is solved again.
"""
from __future__ import annotations

from collections import Counter, defaultdict
from dataclasses import dataclass, field

import gtsam
from gtsam.symbol_shorthand import L, X
import numpy as np

from vlp_ros.core.mounting import Mounting
from vlp_ros.core.pose import Pose
from vlp_ros.survey.partial_map import Anchor, SurveyedLamp
from vlp_ros.survey.sightings import Sighting

# Wheel odometry: per metre driven, scale error (a few per cent) and heading drift; per radian turned,
# the turn's error; and a floor per step (slip, timing). Rough but on the honest side: the images
# carry the map wherever lamps are in view, odometry only bridges between them.
ODOMETRY_SCALE_SIGMA = 0.03
ODOMETRY_TRANSLATION_FLOOR = 0.001
ODOMETRY_HEADING_PER_METRE = 0.02
# Once its scale and heading drift are calibrated against the images (``calibrated_odometry``), what remains
# of them: the wheels' random slip.
CALIBRATED_SCALE_SIGMA = 0.01
CALIBRATED_HEADING_PER_METRE = 0.005
# Steps shorter than this (m) say little about the odometry's scale and drift.
CALIBRATION_MIN_STEP = 0.05
ODOMETRY_TURN_SIGMA = 0.03
ODOMETRY_ROTATION_FLOOR = 0.001
# Huber loss threshold on whitened residuals (sigmas): beyond it a residual counts linearly.
ROBUST_SCALE = 3.0
# A sighting this far from the robust estimate (chi-square, 6 DoF; 1e-6 for a right one) is a wrong
# association or a broken frame: it is left out, since even linearly weighted it pulls its lamp by sigmas.
GROSS_OUTLIER_CHI2 = 40.0
# Median of chi-square with one degree of freedom (the robust variance factor's reference).
CHI2_1_MEDIAN = 0.4549
# Shares of the sightings' model-error allowance tried, in turn, while their residuals show more scatter than
# their covariance claims (``_Graph.variance_factor`` over 1). Clean frames need none: the allowance is for a
# rim's smooth departures from the model (blur, glare, a diffuser's falloff), which one frame cannot tell from
# the pose, and where a recording shows none, taking it made the sigmas 3-4x too wide.
MODEL_SHARES = (0.03, 0.1, 0.3, 1.0)
# A lamp whose estimate is looser than this is not determined by the recording.
MAX_POSITION_SIGMA = 0.1
MAX_ANGLE_SIGMA = 0.2
# Sigmas (m, rad) of what is held (anchors, a disc's level) and of what is left free (a turn about z).
ANCHOR_SIGMA = 1e-6
FREE_SIGMA = 1e3


@dataclass(frozen=True)
class OdometryStep:
    """The base's measured motion from frame ``first`` to frame ``second``, in the base frame at ``first``."""

    first: int
    second: int
    rotation: np.ndarray
    translation: np.ndarray


@dataclass(frozen=True)
class SurveyData:
    """
    Everything the estimation takes.

    ``frame_count`` frames, indexed as in ``sightings``; ``free_lamps`` the IDs of lamps without a
    position; ``anchors`` by ID; ``up`` measured map up in the camera per frame (IMU) with
    ``up_sigma`` (rad); ``expected_up`` where map up is in the camera for a level robot, to choose
    between a sighting's mirror candidates before anything is estimated, and with ``level_sigma`` (rad)
    a measurement of every frame without an IMU's.
    """

    frame_count: int
    sightings: list[Sighting]
    free_lamps: list[int]
    anchors: dict[int, Anchor]
    odometry: list[OdometryStep] = field(default_factory=list)
    mounting: Mounting | None = None
    up: dict[int, np.ndarray] = field(default_factory=dict)
    up_sigma: float = 0.01
    expected_up: np.ndarray | None = None
    level_sigma: float | None = None


@dataclass(frozen=True)
class SightingResidual:
    frame: int
    lamp_id: int
    chi_square: float
    position_error: float


@dataclass
class SurveyEstimate:
    """
    The estimated lamps by ID, camera poses by frame, and lamps the data cannot determine (ID -> why).

    ``frames_seen`` counts the frames each lamp was sighted in; ``variance_factor`` is how much the
    sightings' stated variances were scaled up.
    """

    lamps: dict[int, SurveyedLamp]
    cameras: dict[int, Pose]
    undetermined: dict[int, str]
    frames_seen: Counter
    residuals: list[SightingResidual]
    variance_factor: float = 1.0


def estimate_survey(data: SurveyData) -> SurveyEstimate:
    """Estimate the free lamps and the anchors' missing marker angles from ``data``; see the module."""
    frames_seen = Counter()
    for frame, lamp_id in {(s.frame, s.lamp_id) for s in data.sightings}:
        frames_seen[lamp_id] += 1
    choice = [_by_expected_up(s, data.up.get(s.frame, data.expected_up)) for s in data.sightings]
    cameras, lamps = _initial_guess(data, choice)
    undetermined = {i: _why_undetermined(i, frames_seen) for i in data.free_lamps if i not in lamps}
    undetermined.update({i: _why_undetermined(i, frames_seen) for i, a in data.anchors.items()
                         if a.marker_angle is None and i not in lamps})
    if not cameras or len(undetermined) == len(data.free_lamps) + sum(
            a.marker_angle is None for a in data.anchors.values()):
        return SurveyEstimate({}, {}, undetermined, frames_seen, [])
    graph = _Graph(data, cameras, lamps)
    graph.solve(choice)
    choice = [graph.nearest_candidate(i) for i in range(len(data.sightings))]
    if graph.steps:
        graph.steps = calibrated_odometry(graph.steps, graph.cameras, data.mounting)
        graph.calibrated = True
    graph.solve(choice)
    for share in MODEL_SHARES:
        if graph.variance_factor(graph.whitened(choice)) <= 1.0:
            break
        graph.model_share = share
        graph.solve(choice)
    graph.excluded = graph.gross_outliers(choice)
    graph.odometry_variance = graph.odometry_variance_factor()
    if graph.excluded or graph.odometry_variance > 1.0:
        graph.solve(choice)
    return graph.estimate(choice, undetermined, frames_seen)


def calibrated_odometry(steps: list[OdometryStep], cameras: dict[int, Pose],
                        mounting: Mounting | None) -> list[OdometryStep]:
    """
    Return ``steps`` corrected for the odometry's scale error and heading drift per metre.

    Both are what the estimated camera poses show against the odometry (medians over the steps
    of at least ``CALIBRATION_MIN_STEP``): wheel odometry errs systematically, by a few per cent of
    its scale and a steady drift, so over the metres between lamps that are never in view together
    the uncorrected error would be centimetres.
    """
    ratios, drifts = [], []
    for step in steps:
        a, b = _base_of(cameras[step.first], mounting), _base_of(cameras[step.second], mounting)
        seen = a.rotation.T @ (b.position - a.position)
        distance = float(np.linalg.norm(step.translation))
        if distance < CALIBRATION_MIN_STEP:
            continue
        ratios.append(float(np.linalg.norm(seen)) / distance)
        turn = a.rotation.T @ b.rotation
        drifts.append((_yaw(step.rotation) - _yaw(turn) + np.pi) % (2.0 * np.pi) / distance - np.pi / distance)
    if not ratios:
        return steps
    scale, drift = float(np.median(ratios)), float(np.median(drifts))
    return [OdometryStep(s.first, s.second,
                         _rz(np.array(-drift * np.linalg.norm(s.translation))) @ s.rotation, scale * s.translation)
            for s in steps]


def _yaw(rotation: np.ndarray) -> float:
    return float(np.arctan2(rotation[1, 0], rotation[0, 0]))


def _why_undetermined(lamp_id: int, frames_seen: Counter) -> str:
    if not frames_seen[lamp_id]:
        return 'never seen with its marker'
    return (f'seen in {frames_seen[lamp_id]} frames, but never with an anchor or with odometry linking it to '
            'one')


def _by_expected_up(sighting: Sighting, up: np.ndarray | None) -> int:
    """Index of the candidate whose map up (its lamp frame's z) is nearest ``up`` (camera frame); else the cheapest."""
    if up is None:
        return 0
    return int(np.argmax([pose.rotation[2] @ up for pose in sighting.candidates]))


def _rz(angle: np.ndarray) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    z, o = np.zeros_like(c), np.ones_like(c)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def _camera_from_lamp(lamp: tuple[np.ndarray, float], relative: Pose) -> Pose:
    turn = _rz(np.array(lamp[1]))
    return Pose(turn @ relative.rotation, lamp[0] + turn @ relative.position)


def _lamp_from_camera(camera: Pose, relative: Pose) -> tuple[np.ndarray, float]:
    frame = camera.rotation @ relative.rotation.T
    return camera.position - frame @ relative.position, float(np.arctan2(frame[1, 0], frame[0, 0]))


def _base_of(camera: Pose, mounting: Mounting | None) -> Pose:
    return camera if mounting is None else mounting.base_pose(camera)


def _camera_of(base: Pose, mounting: Mounting | None) -> Pose:
    return base if mounting is None else mounting.camera_pose(base)


def _initial_guess(data: SurveyData, choice: list[int]) -> tuple[dict[int, Pose], dict[int, tuple[np.ndarray, float]]]:
    """
    Chain poses out from the anchors: a camera from a lamp it saw, a lamp from a camera that saw it.

    Odometry bridges frames where no placed lamp is in view. Frames and lamps that no chain reaches are
    left out: the recording cannot place them.
    """
    lamps: dict[int, tuple[np.ndarray, float]] = {i: (a.position, a.marker_angle) for i, a in data.anchors.items()
                                                  if a.marker_angle is not None}
    positioned_only = {i: a.position for i, a in data.anchors.items() if a.marker_angle is None}
    free = set(data.free_lamps) | set(positioned_only)
    cameras: dict[int, Pose] = {}
    while True:
        changed = True
        while changed:
            changed = False
            for sighting, k in zip(data.sightings, choice):
                relative = sighting.candidates[k]
                if sighting.lamp_id in lamps and sighting.frame not in cameras:
                    cameras[sighting.frame] = _camera_from_lamp(lamps[sighting.lamp_id], relative)
                    changed = True
                elif sighting.frame in cameras and sighting.lamp_id in free and sighting.lamp_id not in lamps:
                    position, angle = _lamp_from_camera(cameras[sighting.frame], relative)
                    lamps[sighting.lamp_id] = (positioned_only.get(sighting.lamp_id, position), angle)
                    changed = True
        bridged = False
        for step in data.odometry:
            for known, unknown, forward in ((step.first, step.second, True), (step.second, step.first, False)):
                if known in cameras and unknown not in cameras:
                    base = _base_of(cameras[known], data.mounting)
                    motion = Pose(step.rotation, step.translation)
                    if not forward:
                        motion = Pose(step.rotation.T, -step.rotation.T @ motion.position)
                    moved = Pose(base.rotation @ motion.rotation, base.position + base.rotation @ motion.position)
                    cameras[unknown] = _camera_of(moved, data.mounting)
                    bridged = True
        if not bridged:
            return cameras, lamps


def _pose3(pose: Pose) -> gtsam.Pose3:
    return gtsam.Pose3(gtsam.Rot3(pose.rotation), np.asarray(pose.position, dtype=float))


def _lamp_pose3(position: np.ndarray, angle: float) -> gtsam.Pose3:
    return gtsam.Pose3(gtsam.Rot3.Rz(angle), np.asarray(position, dtype=float))


def _in_gtsam_order(pose: Pose) -> np.ndarray:
    """
    Return ``pose``'s covariance in gtsam's Pose3 tangent: (rotation, translation), both in the pose's own frame.

    ``Pose``'s is (translation, rotation) in the outer frame: for ``T exp(xi)`` = the perturbed pose,
    xi = (R^T d_rotation, R^T d_translation).
    """
    turn = np.zeros((6, 6))
    turn[:3, 3:] = pose.rotation.T
    turn[3:, :3] = pose.rotation.T
    return turn @ pose.covariance @ turn.T


def _robust(covariance: np.ndarray) -> gtsam.noiseModel.Base:
    return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(ROBUST_SCALE),
                                          gtsam.noiseModel.Gaussian.Covariance(covariance))


class _Graph:
    """The factor graph over the frames and lamps the initial guess reached (gtsam keys x<frame>, l<lamp ID>)."""

    def __init__(self, data: SurveyData, cameras: dict[int, Pose], lamps: dict[int, tuple[np.ndarray, float]]) -> None:
        self.data = data
        self.cameras = dict(cameras)
        self.lamps = dict(lamps)
        self.sightings = [(i, s) for i, s in enumerate(data.sightings) if s.frame in cameras and s.lamp_id in lamps]
        self.steps = [s for s in data.odometry if s.first in cameras and s.second in cameras]
        self.calibrated = False
        # How much the odometry's stated variances are scaled (``odometry_variance_factor``), and where its
        # factors are in the graph.
        self.odometry_variance = 1.0
        self.odometry_factors: list[int] = []
        # How much of the sightings' model-error allowance their covariance takes (``Sighting.measured``).
        self.model_share = 0.0
        # Sightings (by index) left out as gross outliers.
        self.excluded: set[int] = set()

    def solve(self, choice: list[int]) -> None:
        """Optimise from the current poses with the sightings' candidates ``choice``; keep the result."""
        kept = [s for index, s in self.sightings if index not in self.excluded]
        self.used_frames = {s.frame for s in kept} | {f for step in self.steps for f in (step.first, step.second)}
        self.used_lamps = {s.lamp_id for s in kept} | (set(self.data.anchors) & set(self.lamps))
        self.graph = self._factors(choice)
        values = gtsam.Values()
        for frame in self.used_frames:
            values.insert(X(frame), _pose3(self.cameras[frame]))
        for lamp_id in self.used_lamps:
            values.insert(L(lamp_id), _lamp_pose3(*self.lamps[lamp_id]))
        parameters = gtsam.LevenbergMarquardtParams()
        parameters.setMaxIterations(100)
        parameters.setRelativeErrorTol(1e-10)
        parameters.setAbsoluteErrorTol(1e-10)
        self.values = gtsam.LevenbergMarquardtOptimizer(self.graph, values, parameters).optimize()
        for frame in self.used_frames:
            pose = self.values.atPose3(X(frame))
            self.cameras[frame] = Pose(pose.rotation().matrix(), pose.translation())
        for lamp_id in self.used_lamps:
            pose = self.values.atPose3(L(lamp_id))
            heading = pose.rotation().matrix()
            self.lamps[lamp_id] = (np.array(pose.translation()), float(np.arctan2(heading[1, 0], heading[0, 0])))

    def _factors(self, choice: list[int]) -> gtsam.NonlinearFactorGraph:
        graph = gtsam.NonlinearFactorGraph()
        self.odometry_factors = []
        # Every pose held loosely where it starts: a direction that the measurements leave (nearly) free then
        # shows as a huge marginal sigma, and the lamp is reported undetermined, instead of stopping the solve.
        loose = gtsam.noiseModel.Isotropic.Sigma(6, FREE_SIGMA)
        for frame in self.used_frames:
            graph.add(gtsam.PriorFactorPose3(X(frame), _pose3(self.cameras[frame]), loose))
        for lamp_id in self.used_lamps:
            graph.add(gtsam.PriorFactorPose3(L(lamp_id), _lamp_pose3(*self.lamps[lamp_id]), loose))
        for lamp_id in self.used_lamps:
            angle = self.lamps[lamp_id][1]
            anchor = self.data.anchors.get(lamp_id)
            if anchor is not None:
                yaw = ANCHOR_SIGMA if anchor.marker_angle is not None else FREE_SIGMA
                graph.add(gtsam.PriorFactorPose3(L(lamp_id), _lamp_pose3(anchor.position, angle),
                                                 gtsam.noiseModel.Diagonal.Sigmas(
                                                     np.array([ANCHOR_SIGMA, ANCHOR_SIGMA, yaw, *[ANCHOR_SIGMA] * 3]))))
            else:
                # Discs hang level: only the turn about map z is free.
                graph.add(gtsam.PoseRotationPrior3D(L(lamp_id), gtsam.Rot3.Rz(angle), gtsam.noiseModel.Diagonal.Sigmas(
                    np.array([ANCHOR_SIGMA, ANCHOR_SIGMA, FREE_SIGMA]))))
        for index, sighting in self.sightings:
            if index in self.excluded:
                continue
            relative = sighting.measured(choice[index], self.model_share)
            graph.add(gtsam.BetweenFactorPose3(L(sighting.lamp_id), X(sighting.frame), _pose3(relative),
                                               _robust(_in_gtsam_order(relative))))
        mounting = self.data.mounting
        on_base = gtsam.Pose3() if mounting is None else gtsam.Pose3(gtsam.Rot3(mounting.rotation),
                                                                     mounting.translation)
        to_camera = on_base.inverse().AdjointMap()
        for step in self.steps:
            motion = gtsam.Pose3(gtsam.Rot3(step.rotation), step.translation)
            distance = float(np.linalg.norm(step.translation))
            turn = float(np.linalg.norm(gtsam.Rot3.Logmap(gtsam.Rot3(step.rotation))))
            per_metre = CALIBRATED_HEADING_PER_METRE if self.calibrated else ODOMETRY_HEADING_PER_METRE
            rotation_sigma = per_metre * distance + ODOMETRY_TURN_SIGMA * turn + ODOMETRY_ROTATION_FLOOR
            scale = CALIBRATED_SCALE_SIGMA if self.calibrated else ODOMETRY_SCALE_SIGMA
            translation_sigma = scale * distance + ODOMETRY_TRANSLATION_FLOOR
            covariance = self.odometry_variance * np.diag([rotation_sigma ** 2] * 3 + [translation_sigma ** 2] * 3)
            self.odometry_factors.append(graph.size())
            graph.add(gtsam.BetweenFactorPose3(X(step.first), X(step.second),
                                               on_base.inverse().compose(motion).compose(on_base),
                                               _robust(to_camera @ covariance @ to_camera.T)))
        for frame in self.used_frames:
            up, sigma = self.data.up.get(frame), self.data.up_sigma
            if up is None:
                up, sigma = self.data.expected_up, self.data.level_sigma
            if up is not None and sigma is not None:
                graph.add(gtsam.AttitudeFactorPose3(X(frame), gtsam.Unit3(np.array([0.0, 0.0, 1.0])),
                                                    _robust(np.eye(2) * sigma ** 2),
                                                    gtsam.Unit3(np.asarray(up, dtype=float))))
        return graph

    def sighting_errors(self, choice: list[int]) -> tuple[np.ndarray, list[Pose]]:
        """(S, 6) errors of the chosen candidates (position in the lamp frame, rotation vector), and them."""
        errors, measured = [], []
        for index, sighting in self.sightings:
            relative = sighting.measured(choice[index], self.model_share)
            position, angle = self.lamps[sighting.lamp_id]
            camera = self.cameras[sighting.frame]
            turn = _rz(np.array(angle))
            predicted = Pose(turn.T @ camera.rotation, turn.T @ (camera.position - position))
            errors.append(predicted.error_vector(relative))
            measured.append(relative)
        return np.array(errors).reshape(-1, 6), measured

    def variance_factor(self, whitened: np.ndarray) -> float:
        """
        Return the sightings' a posteriori variance factor, never below 1: how far their stated noise falls short.

        Robust, as the fit is: the median of the squared whitened residuals ``whitened`` (S, 6) of the sightings
        kept, over that of chi-square with one degree of freedom, times residuals over redundancy (the residuals
        less the unknowns they determine: six per camera, four per free lamp), which the fit's own share of the
        residuals takes away.
        """
        kept = np.array([w for (index, _), w in zip(self.sightings, whitened) if index not in self.excluded])
        free = sum(4 if i not in self.data.anchors else 1 for i in self.used_lamps
                   if i not in self.data.anchors or self.data.anchors[i].marker_angle is None)
        redundancy = kept.size - 6 * len(self.used_frames) - free
        if redundancy <= 0:
            return 1.0
        return max(1.0, float(np.median(kept ** 2)) / CHI2_1_MEDIAN * kept.size / redundancy)

    def odometry_variance_factor(self) -> float:
        """
        Return how much the odometry's variances must grow for its residuals to match them (at least 1).

        Its chi-square per residual at the solution: a robot's odometry may be noisier than the model of its
        errors says, and the images, which carry the map, must then not be held to it.
        """
        if not self.odometry_factors:
            return self.odometry_variance
        chi_square = sum(2.0 * self.graph.at(i).error(self.values) for i in self.odometry_factors)
        return max(1.0, self.odometry_variance * chi_square / (6 * len(self.odometry_factors)))

    def whitened(self, choice: list[int]) -> np.ndarray:
        """Return the sightings' errors (S, 6) whitened by their covariance."""
        errors, measured = self.sighting_errors(choice)
        return np.einsum('sij,sj->si', _whitening(measured), errors)

    def gross_outliers(self, choice: list[int]) -> set[int]:
        """Return the indices of the sightings whose chi-square at the estimate exceeds ``GROSS_OUTLIER_CHI2``."""
        chi_squares = np.sum(self.whitened(choice) ** 2, axis=1)
        return {index for (index, _), chi in zip(self.sightings, chi_squares) if chi > GROSS_OUTLIER_CHI2}

    def nearest_candidate(self, index: int) -> int:
        """Index of sighting ``index``'s candidate the estimate agrees with best (Mahalanobis)."""
        sighting = self.data.sightings[index]
        if len(sighting.candidates) == 1 or sighting.frame not in self.cameras or sighting.lamp_id not in self.lamps:
            return 0
        position, angle = self.lamps[sighting.lamp_id]
        camera = self.cameras[sighting.frame]
        turn = _rz(np.array(angle))
        predicted = Pose(turn.T @ camera.rotation, turn.T @ (camera.position - position))
        scores = []
        for k in range(len(sighting.candidates)):
            candidate = sighting.measured(k, self.model_share)
            error = predicted.error_vector(candidate)
            scores.append(float(error @ np.linalg.solve(candidate.covariance, error)))
        return int(np.argmin(scores))

    def estimate(self, choice: list[int], undetermined: dict[int, str], frames_seen: Counter) -> SurveyEstimate:
        errors, measured = self.sighting_errors(choice)
        whitened = np.einsum('sij,sj->si', _whitening(measured), errors)
        chi_squares = np.sum(whitened ** 2, axis=1)
        factor = self.variance_factor(whitened)
        residuals = [SightingResidual(s.frame, s.lamp_id, float(c), float(np.linalg.norm(e[:3])))
                     for (_, s), c, e in zip(self.sightings, chi_squares, errors)]
        marginals = _marginal_covariances(self.graph, self.values)
        lamps, undetermined = {}, dict(undetermined)
        free = [i for i in self.lamps if i not in self.data.anchors or self.data.anchors[i].marker_angle is None]
        for lamp_id in free:
            if lamp_id not in self.used_lamps:
                undetermined[lamp_id] = 'every sighting of it disagrees with the rest of the survey'
                continue
            position, angle = self.lamps[lamp_id]
            covariance = factor * marginals(L(lamp_id))
            heading = _rz(np.array(angle))
            position_covariance = heading @ covariance[3:, 3:] @ heading.T
            if lamp_id in self.data.anchors:
                position_covariance = np.zeros((3, 3))
            angle_sigma = float(np.sqrt(max(covariance[2, 2], 0.0)))
            position_sigma = np.sqrt(np.maximum(np.diag(position_covariance), 0.0))
            if not (np.all(position_sigma < MAX_POSITION_SIGMA) and angle_sigma < MAX_ANGLE_SIGMA):
                undetermined[lamp_id] = (f'too loosely determined (sigma {1e2 * position_sigma.max():.1f} cm, '
                                         f'marker {np.degrees(angle_sigma):.1f} deg)')
                continue
            lamps[lamp_id] = SurveyedLamp(np.array(position), angle, position_covariance, angle_sigma)
        cameras = {f: self.cameras[f] for f in self.used_frames}
        return SurveyEstimate(lamps, cameras, undetermined, frames_seen, residuals, factor)


def _marginal_covariances(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values):
    """
    Return a function from a key to its marginal covariance (6, 6) at ``values``.

    gtsam's sparse ``Marginals``, or where its Cholesky factorisation finds the system too poorly conditioned, the
    pseudo-inverse of the dense information matrix.
    """
    try:
        return gtsam.Marginals(graph, values).marginalCovariance
    except RuntimeError:
        keys = list(values.keys())
        ordering = gtsam.Ordering()
        for key in keys:
            ordering.push_back(key)
        information, _ = graph.linearize(values).hessian(ordering)
        covariance = np.linalg.pinv(information)
        start = {key: 6 * index for index, key in enumerate(keys)}
        return lambda key: covariance[start[key]:start[key] + 6, start[key]:start[key] + 6]


def _whitening(measured: list[Pose]) -> np.ndarray:
    """(S, 6, 6) matrices W with W^T W the inverse covariance of each measured pose."""
    covariances = np.array([m.covariance for m in measured]).reshape(-1, 6, 6)
    factors = np.linalg.cholesky(covariances + 1e-14 * np.eye(6))
    return np.linalg.inv(factors)


def per_lamp_residuals(estimate: SurveyEstimate) -> dict[int, tuple[float, float]]:
    """Return per lamp the RMS position residual (m) in its sightings' lamp frames and mean chi-square (6 dof)."""
    grouped = defaultdict(list)
    for r in estimate.residuals:
        grouped[r.lamp_id].append(r)
    return {i: (float(np.sqrt(np.mean([r.position_error ** 2 for r in rs]))),
                float(np.mean([r.chi_square for r in rs]))) for i, rs in grouped.items()}
