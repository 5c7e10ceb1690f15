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

Anchors (lamps with a given position) are held fixed. scipy's sparse trust-region least squares
(``least_squares``, finite differences over the known sparsity) solves it with a Huber loss, so
a wrong association or a glare-bitten frame is down-weighted instead of pulling the map. The
lamps' covariance is the inverse of the Gauss-Newton information at the solution, scaled up when
the sightings' residuals say their stated noise is too small.
"""
from __future__ import annotations

from collections import Counter, defaultdict
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix
from scipy.spatial.transform import Rotation

from vlp_ros.core.mounting import Mounting
from vlp_ros.core.pose import Pose
from vlp_ros.survey.partial_map import Anchor, SurveyedLamp
from vlp_ros.survey.sightings import Sighting

# Wheel odometry: per metre driven, scale error (a few per cent) and heading drift; per radian turned,
# the turn's error; and a floor per step (slip, timing). Rough but on the honest side: the images
# carry the map wherever lamps are in view, odometry only bridges between them.
ODOMETRY_SCALE_SIGMA = 0.03
ODOMETRY_TRANSLATION_FLOOR = 0.005
ODOMETRY_HEADING_PER_METRE = 0.02
ODOMETRY_TURN_SIGMA = 0.03
ODOMETRY_ROTATION_FLOOR = 0.003
# Huber loss threshold on whitened residuals (sigmas): beyond it a residual counts linearly.
ROBUST_SCALE = 3.0
# Median of chi-square with one degree of freedom: the sightings' residuals' median square over it
# says how far their stated noise falls short.
CHI2_1_MEDIAN = 0.4549
# A lamp whose estimate is looser than this is not determined by the recording.
MAX_POSITION_SIGMA = 0.1
MAX_ANGLE_SIGMA = 0.2
_POSITION_COLUMNS = (0, 1, 2)
_ANGLE_COLUMN = 3


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
    between a sighting's mirror candidates before anything is estimated.
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
    odometry_chi_square: float = 0.0
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
    problem = _Problem(data, cameras, lamps)
    solution = problem.solve(choice)
    rechosen = [_nearest_candidate(s, problem, solution.x) for s in data.sightings]
    if rechosen != choice:
        choice = rechosen
        solution = problem.solve(choice)
    return problem.estimate(solution, choice, undetermined, frames_seen)


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
                        motion = Pose(step.rotation.T, -step.rotation.T @ step.translation)
                    moved = Pose(base.rotation @ motion.rotation, base.position + base.rotation @ motion.translation)
                    cameras[unknown] = _camera_of(moved, data.mounting)
                    bridged = True
        if not bridged:
            return cameras, lamps


class _Problem:
    """The least-squares problem over the frames and lamps the initial guess reached."""

    def __init__(self, data: SurveyData, cameras: dict[int, Pose], lamps: dict[int, tuple[np.ndarray, float]]) -> None:
        self.data = data
        self.frames = sorted(cameras)
        self.frame_column = {f: 6 * i for i, f in enumerate(self.frames)}
        self.start_rotations = Rotation.from_matrix(np.array([cameras[f].rotation for f in self.frames]))
        x0 = [np.concatenate([np.zeros(3), cameras[f].position]) for f in self.frames]
        column = 6 * len(self.frames)
        # Per lamp: (position columns or None, angle column or None), and its fixed values.
        self.lamp_columns: dict[int, tuple[int | None, int | None]] = {}
        self.fixed: dict[int, tuple[np.ndarray, float]] = {}
        for lamp_id, (position, angle) in sorted(lamps.items()):
            anchor = data.anchors.get(lamp_id)
            if anchor is not None and anchor.marker_angle is not None:
                self.fixed[lamp_id] = (anchor.position, anchor.marker_angle)
            elif anchor is not None:
                self.lamp_columns[lamp_id] = (None, column)
                self.fixed[lamp_id] = (anchor.position, 0.0)
                x0.append(np.array([angle]))
                column += 1
            else:
                self.lamp_columns[lamp_id] = (column, column + 3)
                self.fixed[lamp_id] = (np.zeros(3), 0.0)
                x0.append(np.append(position, angle))
                column += 4
        self.x0 = np.concatenate(x0)
        self.sightings = [(i, s) for i, s in enumerate(data.sightings) if s.frame in cameras and s.lamp_id in lamps]
        self.steps = [s for s in data.odometry if s.first in cameras and s.second in cameras]
        self.ups = [(f, u) for f, u in sorted(data.up.items()) if f in cameras]
        self._prepare_odometry()

    def _prepare_odometry(self) -> None:
        steps = self.steps
        self.step_rotations = np.array([s.rotation for s in steps]).reshape(-1, 3, 3)
        self.step_translations = np.array([s.translation for s in steps]).reshape(-1, 3)
        distance = np.linalg.norm(self.step_translations, axis=1)
        turn = Rotation.from_matrix(self.step_rotations).magnitude() if steps else np.zeros(0)
        self.step_sigmas = np.column_stack([
            np.repeat((ODOMETRY_SCALE_SIGMA * distance + ODOMETRY_TRANSLATION_FLOOR)[:, None], 3, axis=1),
            np.repeat((ODOMETRY_HEADING_PER_METRE * distance + ODOMETRY_TURN_SIGMA * turn
                       + ODOMETRY_ROTATION_FLOOR)[:, None], 3, axis=1)])

    def cameras_at(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Camera rotations (F, 3, 3) and positions (F, 3) of ``self.frames``."""
        blocks = x[:6 * len(self.frames)].reshape(-1, 6)
        rotations = (Rotation.from_rotvec(blocks[:, :3]) * self.start_rotations).as_matrix()
        return rotations, blocks[:, 3:]

    def lamp_at(self, x: np.ndarray, lamp_id: int) -> tuple[np.ndarray, float]:
        position, angle = self.fixed[lamp_id]
        columns = self.lamp_columns.get(lamp_id)
        if columns is None:
            return position, angle
        start, angle_column = columns
        if start is not None:
            position = x[start:start + 3]
        return position, float(x[angle_column])

    def residuals(self, x: np.ndarray, choice: list[int]) -> np.ndarray:
        rotations, positions = self.cameras_at(x)
        parts = [self._sighting_residuals(x, choice, rotations, positions).ravel()]
        if self.steps:
            parts.append(self._odometry_residuals(rotations, positions).ravel())
        if self.ups:
            index = np.array([self.frames.index(f) for f, _ in self.ups])
            measured = np.array([u for _, u in self.ups])
            parts.append(((rotations[index, 2, :] - measured) / self.data.up_sigma).ravel())
        return np.concatenate(parts)

    def sighting_errors(self, x: np.ndarray, choice: list[int], rotations: np.ndarray,
                        positions: np.ndarray) -> tuple[np.ndarray, list[Pose]]:
        """(S, 6) errors of the chosen candidates (position in the lamp frame, rotation vector), and them."""
        frame_index = {f: i for i, f in enumerate(self.frames)}
        rows = [frame_index[s.frame] for _, s in self.sightings]
        lamps = [self.lamp_at(x, s.lamp_id) for _, s in self.sightings]
        measured = [s.candidates[choice[i]] for i, s in self.sightings]
        turns = _rz(np.array([angle for _, angle in lamps]))
        centres = np.array([position for position, _ in lamps])
        relative_rotations = np.einsum('sji,sjk->sik', turns, rotations[rows])
        relative_positions = np.einsum('sji,sj->si', turns, positions[rows] - centres)
        measured_rotations = np.array([m.rotation for m in measured])
        rotation_errors = Rotation.from_matrix(
            np.einsum('sij,skj->sik', relative_rotations, measured_rotations)).as_rotvec()
        return np.column_stack([relative_positions - np.array([m.position for m in measured]),
                                rotation_errors]), measured

    def _sighting_residuals(self, x: np.ndarray, choice: list[int], rotations: np.ndarray,
                            positions: np.ndarray) -> np.ndarray:
        errors, measured = self.sighting_errors(x, choice, rotations, positions)
        return np.einsum('sij,sj->si', _whitening(measured), errors)

    def _odometry_residuals(self, rotations: np.ndarray, positions: np.ndarray) -> np.ndarray:
        index = {f: i for i, f in enumerate(self.frames)}
        first = np.array([index[s.first] for s in self.steps])
        second = np.array([index[s.second] for s in self.steps])
        mounting = self.data.mounting
        base_rotations, base_positions = rotations, positions
        if mounting is not None:
            base_rotations = rotations @ mounting.rotation.T
            base_positions = positions - base_rotations @ mounting.translation
        a, b = base_rotations[first], base_rotations[second]
        moved = np.einsum('sji,sjk->sik', a, b)
        shift = np.einsum('sji,sj->si', a, base_positions[second] - base_positions[first])
        turn = Rotation.from_matrix(np.einsum('sij,skj->sik', moved, self.step_rotations)).as_rotvec()
        return np.column_stack([shift - self.step_translations, turn]) / self.step_sigmas

    def sparsity(self) -> lil_matrix:
        rows = 6 * len(self.sightings) + 6 * len(self.steps) + 3 * len(self.ups)
        pattern = lil_matrix((rows, len(self.x0)), dtype=int)
        row = 0
        for _, sighting in self.sightings:
            columns = list(range(self.frame_column[sighting.frame], self.frame_column[sighting.frame] + 6))
            start, angle_column = self.lamp_columns.get(sighting.lamp_id, (None, None))
            columns += ([] if start is None else list(range(start, start + 3))) + (
                [] if angle_column is None else [angle_column])
            pattern[row:row + 6, columns] = 1
            row += 6
        for step in self.steps:
            for frame in (step.first, step.second):
                pattern[row:row + 6, self.frame_column[frame]:self.frame_column[frame] + 6] = 1
            row += 6
        for frame, _ in self.ups:
            pattern[row:row + 3, self.frame_column[frame]:self.frame_column[frame] + 3] = 1
            row += 3
        return pattern

    def solve(self, choice: list[int]):
        """Return scipy's least-squares result from ``self.x0`` with the candidates ``choice``."""
        result = least_squares(self.residuals, self.x0, jac_sparsity=self.sparsity(), method='trf',
                               loss='huber', f_scale=ROBUST_SCALE, x_scale='jac', tr_solver='lsmr',
                               xtol=1e-10, ftol=1e-10, max_nfev=200, args=(choice,))
        self.x0 = result.x
        return result

    def estimate(self, solution, choice: list[int], undetermined: dict[int, str],
                 frames_seen: Counter) -> SurveyEstimate:
        x = solution.x
        rotations, positions = self.cameras_at(x)
        cameras = {f: Pose(rotations[i], positions[i]) for i, f in enumerate(self.frames)}
        errors, measured = self.sighting_errors(x, choice, rotations, positions)
        whitened = np.einsum('sij,sj->si', _whitening(measured), errors)
        chi_squares = np.sum(whitened ** 2, axis=1)
        factor = max(1.0, float(np.median(whitened ** 2)) / CHI2_1_MEDIAN) if len(whitened) else 1.0
        jacobian = solution.jac
        information = (jacobian.T @ jacobian).toarray()
        covariance = factor * np.linalg.pinv(information)
        residuals = [SightingResidual(s.frame, s.lamp_id, float(c), float(np.linalg.norm(e[:3])))
                     for (_, s), c, e in zip(self.sightings, chi_squares, errors)]
        lamps = {}
        undetermined = dict(undetermined)
        for lamp_id, (start, angle_column) in self.lamp_columns.items():
            position, angle = self.lamp_at(x, lamp_id)
            if start is None:
                position_covariance = np.zeros((3, 3))
            else:
                position_covariance = covariance[start:start + 3, start:start + 3]
            angle_sigma = float(np.sqrt(max(covariance[angle_column, angle_column], 0.0)))
            position_sigma = np.sqrt(np.maximum(np.diag(position_covariance), 0.0))
            if not (np.all(position_sigma < MAX_POSITION_SIGMA) and angle_sigma < MAX_ANGLE_SIGMA):
                undetermined[lamp_id] = (f'too loosely determined (sigma {1e2 * position_sigma.max():.1f} cm, '
                                         f'marker {np.degrees(angle_sigma):.1f} deg)')
                continue
            lamps[lamp_id] = SurveyedLamp(np.array(position), float(np.arctan2(np.sin(angle), np.cos(angle))),
                                          position_covariance, angle_sigma)
        odometry = self._odometry_residuals(rotations, positions) if self.steps else np.zeros((0, 6))
        return SurveyEstimate(lamps, cameras, undetermined, frames_seen, residuals,
                              float(np.sum(odometry ** 2)), factor)


def _nearest_candidate(sighting: Sighting, problem: _Problem, x: np.ndarray) -> int:
    """Index of the sighting's candidate the estimate agrees with best (Mahalanobis), where it was solved."""
    if len(sighting.candidates) == 1 or sighting.frame not in problem.frame_column:
        return 0
    if sighting.lamp_id not in problem.fixed:
        return 0
    rotations, positions = problem.cameras_at(x)
    index = problem.frames.index(sighting.frame)
    position, angle = problem.lamp_at(x, sighting.lamp_id)
    turn = _rz(np.array(angle))
    rotation, centre = turn.T @ rotations[index], turn.T @ (positions[index] - position)
    scores = []
    for candidate in sighting.candidates:
        error = np.concatenate([centre - candidate.position,
                                Rotation.from_matrix(rotation @ candidate.rotation.T).as_rotvec()])
        scores.append(float(error @ np.linalg.solve(candidate.covariance, error)))
    return int(np.argmin(scores))


def _whitening(measured: list[Pose]) -> np.ndarray:
    """(S, 6, 6) matrices W with W^T W the inverse covariance of each measured pose."""
    covariances = np.array([m.covariance for m in measured]).reshape(-1, 6, 6)
    factors = np.linalg.cholesky(covariances + 1e-14 * np.eye(6))
    return np.linalg.inv(factors)


def lamps_by_name(estimate: SurveyEstimate, names: dict[int, str]) -> dict[str, SurveyedLamp]:
    return {names[i]: lamp for i, lamp in estimate.lamps.items()}


def per_lamp_residuals(estimate: SurveyEstimate) -> dict[int, tuple[float, float]]:
    """Per lamp: RMS position residual (m) in its sightings' lamp frames and mean chi-square (6 dof)."""
    grouped = defaultdict(list)
    for r in estimate.residuals:
        grouped[r.lamp_id].append(r)
    return {i: (float(np.sqrt(np.mean([r.position_error ** 2 for r in rs]))), float(np.mean([r.chi_square for r in rs])))
            for i, rs in grouped.items()}
