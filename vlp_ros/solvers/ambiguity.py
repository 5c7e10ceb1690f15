"""
Choosing among candidate poses with real information only, or declining to choose.

One circle and its marker are explained equally well by two poses. What may
separate them: a known up direction in the camera frame (a static mounting
prior, or gravity from an IMU at rest; given a sigma it is also a measurement
in the fit, which then mostly leaves one candidate), continuity with a recent
pose of the same camera, other lamps in the frame (``fusion``), and, only when
the gap is overwhelming, the fit itself. Every up hint must accept the chosen
candidate and reject the others it rules out; otherwise no pose is returned and the
reason says why.

Continuity is evidence, never a veto over decisive evidence. Its gate grows with the
time since the recent pose (``recent_gate_m + recent_max_speed * recent_age``), so a
camera that moved or lost the lamps for a while is not shut out. When the up hints,
the other lamps or an overwhelming cost gap single out one candidate, that candidate
is chosen even if it is outside the gate, and the choice says the track restarts
(the camera jumped, or the recent pose was wrong). Only when nothing else decides
does continuity pick the one candidate within its gate, or, rejecting them all,
leave the frame without a pose.

Cost rule. Let A be the cheapest candidate and B another, with chi-squares
c_A < c_B over the same residuals. If B were the truth, A could undercut it by
the gap g = c_B - c_A only through noise: to first order g ~ -|m|^2 - 2 m.e
with m the difference of their predictions, e ~ N(0, I), so
P(g > G) = Phi(-(G + |m|^2) / (2 |m|)) <= Phi(-sqrt(G)) for every m. With
G = 40 a wrong pick has probability <= 1.5e-10 per decision. The gap is first
divided by the reduced chi-square of A when that exceeds 1, so noise that is
larger than its stated sigma does not fake a gap.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import math

import numpy as np

from vlp_ros.core.pose import Pose
from vlp_ros.solvers.candidates import Choice, distinct, PoseCandidate, Reason
from vlp_ros.solvers.up_measurement import unit_direction, UpMeasurement

COST_GAP = 40.0


@dataclass(frozen=True, eq=False)
class UpHint:
    """
    Where map +z points in the camera optical frame, from one source, and how far it may be trusted.

    The source is a static mounting prior, or the IMU's gravity: an accelerometer at rest measures +g
    along up; any non-zero length. ``tolerance`` (rad) gates: no pose whose up is farther from
    ``vector`` is ever chosen. ``sigma`` (rad), when known, is the standard deviation of
    ``vector``'s error about each of the two axes perpendicular to it; the direction is
    then also a measurement in the pose fit (``UpMeasurement``), not only a gate.
    """

    vector: np.ndarray
    tolerance: float
    sigma: float | None = None
    measurement: UpMeasurement | None = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if not 0.0 < self.tolerance < np.pi:
            raise ValueError(f'up tolerance must be in (0, pi) rad, got {self.tolerance}')
        object.__setattr__(self, 'vector', unit_direction(self.vector))
        object.__setattr__(self, 'tolerance', float(self.tolerance))
        object.__setattr__(self, 'measurement', None if self.sigma is None else UpMeasurement(self.vector, self.sigma))


@dataclass
class DisambiguationHints:
    """
    What is known about the pose besides the lamps.

    ``up_in_camera``: one ``UpHint`` per source, or its fields as a tuple
    ``(vector, tolerance[, sigma])``. ``recent_pose``: a recent pose of this camera, taken
    ``recent_age`` seconds ago; it counts when ``recent_age <= recent_max_age`` and then
    accepts candidates within ``recent_gate()`` of it: ``recent_gate_m`` plus the
    distance ``recent_max_speed`` (m/s) covers in ``recent_age``.
    """

    up_in_camera: list[UpHint] = field(default_factory=list)
    recent_pose: Pose | None = None
    recent_gate_m: float = 0.5
    recent_age: float = 0.0
    recent_max_age: float = float('inf')
    recent_max_speed: float = 0.0

    def __post_init__(self) -> None:
        self.up_in_camera = [hint if isinstance(hint, UpHint) else UpHint(*hint) for hint in self.up_in_camera]
        if not self.recent_gate_m > 0.0:
            raise ValueError(f'recent_gate_m must be positive, got {self.recent_gate_m}')
        if not self.recent_max_speed >= 0.0:
            raise ValueError(f'recent_max_speed must be non-negative, got {self.recent_max_speed}')
        if not self.recent_age >= 0.0:
            raise ValueError(f'recent_age must be non-negative, got {self.recent_age}')

    @property
    def continuity_counts(self) -> bool:
        """Whether a recent pose is known and young enough to vouch for this frame."""
        return self.recent_pose is not None and self.recent_age <= self.recent_max_age

    def recent_gate(self) -> float:
        """How far (m) from the recent pose a candidate may be and still continue it."""
        return self.recent_gate_m + self.recent_max_speed * self.recent_age

    def up_measurements(self) -> list[UpMeasurement]:
        """Return the up hints that have a sigma, as measurements for the pose fit."""
        return [hint.measurement for hint in self.up_in_camera if hint.measurement is not None]


def choose_candidate(candidates: list[PoseCandidate], hints: DisambiguationHints,
                     cost_reason: Reason = Reason.COST) -> Choice:
    """
    Return the candidate the hints (or an overwhelming cost gap) single out, or no pose and why.

    An overwhelming cost gap is reported as ``cost_reason``. A candidate singled out against
    continuity restarts the track (``Choice.restarts_track``).
    """
    candidates = distinct(candidates)
    if not candidates:
        return Choice(None, Reason.NO_CANDIDATES, 'the solver found no pose')
    remaining = list(range(len(candidates)))
    decided_by: Reason | None = None
    for k, hint in enumerate(hints.up_in_camera):
        agreeing = [i for i in range(len(candidates)) if _up_accepts(hint, candidates[i].pose)]
        if not agreeing:
            return Choice(None, Reason.NO_CANDIDATE_AGREES, f'up direction hint {k} rejects every candidate')
        narrowed = [i for i in remaining if i in agreeing]
        if not narrowed:
            return Choice(None, Reason.CONFLICTING_HINTS, f'up direction hint {k} rejects the candidate '
                                                          'other hints chose')
        if len(narrowed) < len(remaining) and decided_by is None:
            decided_by = Reason.UP_DIRECTION
        remaining = narrowed
    winner = overwhelming_winner(candidates)
    if winner is not None and winner not in remaining:
        return Choice(None, Reason.CONFLICTING_HINTS, 'the fit overwhelmingly favours a candidate the hints reject')
    if len(remaining) == 1:
        return _continued_or_restarted(candidates[remaining[0]].pose, decided_by or Reason.UNIQUE, hints)
    if winner is not None:
        return _continued_or_restarted(candidates[winner].pose, cost_reason, hints)
    return _decided_by_continuity([candidates[i].pose for i in remaining], hints)


def _continued_or_restarted(pose: Pose, reason: Reason, hints: DisambiguationHints) -> Choice:
    """``pose``, decided without continuity: it continues the recent pose, or restarts the track."""
    if not hints.continuity_counts:
        return Choice(pose, reason)
    distance = pose.position_error(hints.recent_pose)
    if distance <= hints.recent_gate():
        return Choice(pose, reason)
    return Choice(pose, reason, f'track restarted: {distance:.2f} m from the recent pose, beyond its '
                                f'{hints.recent_gate():.2f} m gate', restarts_track=True)


def _decided_by_continuity(poses: list[Pose], hints: DisambiguationHints) -> Choice:
    """Return the one of ``poses`` (which nothing else separates) within the recent pose's gate, or no pose and why."""
    if not hints.continuity_counts:
        return Choice(None, Reason.AMBIGUOUS, f'{len(poses)} candidates fit and no hint separates them')
    gate = hints.recent_gate()
    agreeing = [pose for pose in poses if pose.position_error(hints.recent_pose) <= gate]
    if not agreeing:
        return Choice(None, Reason.NO_CANDIDATE_AGREES, f'the recent pose rejects every candidate (none within '
                                                        f'{gate:.2f} m, {hints.recent_age:.2f} s after it)')
    if len(agreeing) == 1:
        return Choice(agreeing[0], Reason.CONTINUITY)
    return Choice(None, Reason.AMBIGUOUS, f'{len(agreeing)} candidates fit within {gate:.2f} m of the recent pose '
                                          'and no hint separates them')


def overwhelming_winner(candidates: list[PoseCandidate]) -> int | None:
    """Index of the cheapest candidate if its cost gap to every other exceeds ``COST_GAP``."""
    if len(candidates) < 2:
        return None
    order = sorted(range(len(candidates)), key=lambda i: candidates[i].cost)
    best, runner_up = candidates[order[0]], candidates[order[1]]
    dof = max(best.residual_count - 6, 1)
    noise_scale = max(best.cost / dof, 1.0)
    return order[0] if (runner_up.cost - best.cost) / noise_scale > COST_GAP else None


def _up_accepts(hint: UpHint, pose: Pose) -> bool:
    return _angle(pose.up_in_camera(), hint.vector) <= hint.tolerance


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    return math.acos(min(max(float(a @ b), -1.0), 1.0))
