"""Choosing among candidate poses with real information only, or declining to choose.

One circle and its marker are explained equally well by two poses. What may
separate them: a known up direction in the camera frame (a static mounting
prior, or gravity from an IMU at rest; given a sigma it is also a measurement
in the fit, which then mostly leaves one candidate), continuity with a recent
pose of the same camera, other lamps in the frame (``fusion``), and, only when
the gap is overwhelming, the fit itself. Every hint must accept the chosen candidate and
reject the others it rules out; otherwise no pose is returned and the reason
says why.

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

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from vlp_ros.pose import Pose
from vlp_ros.solvers.candidates import Choice, PoseCandidate, Reason, distinct
from vlp_ros.solvers.up_measurement import UpMeasurement, unit_direction

COST_GAP = 40.0


@dataclass(frozen=True, eq=False)
class UpHint:
    """Where map +z points in the camera optical frame, from one source (a static mounting
    prior, or the IMU's gravity: an accelerometer at rest measures +g along up; any
    non-zero length). ``tolerance`` (rad) gates: no pose whose up is farther from
    ``vector`` is ever chosen. ``sigma`` (rad), when known, is the standard deviation of
    ``vector``'s error about each of the two axes perpendicular to it; the direction is
    then also a measurement in the pose fit (``UpMeasurement``), not only a gate."""

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
    """What is known about the pose besides the lamps.

    ``up_in_camera``: one ``UpHint`` per source, or its fields as a tuple
    ``(vector, tolerance[, sigma])``. ``recent_pose``: a recent pose of this camera, taken
    ``recent_age`` seconds ago; it counts when ``recent_age <= recent_max_age`` and then
    accepts candidates within ``recent_gate_m`` of it.
    """

    up_in_camera: list[UpHint] = field(default_factory=list)
    recent_pose: Pose | None = None
    recent_gate_m: float = 0.5
    recent_age: float = 0.0
    recent_max_age: float = float('inf')

    def __post_init__(self) -> None:
        self.up_in_camera = [hint if isinstance(hint, UpHint) else UpHint(*hint) for hint in self.up_in_camera]
        if not self.recent_gate_m > 0.0:
            raise ValueError(f'recent_gate_m must be positive, got {self.recent_gate_m}')

    def up_measurements(self) -> list[UpMeasurement]:
        """The up hints that have a sigma, as measurements for the pose fit."""
        return [hint.measurement for hint in self.up_in_camera if hint.measurement is not None]


def choose_candidate(candidates: list[PoseCandidate], hints: DisambiguationHints,
                     cost_reason: Reason = Reason.COST) -> Choice:
    """The candidate the hints (or an overwhelming cost gap, reported as ``cost_reason``)
    single out, or no pose and why."""
    candidates = distinct(candidates)
    if not candidates:
        return Choice(None, Reason.NO_CANDIDATES, 'the solver found no pose')
    remaining = list(range(len(candidates)))
    decided_by: Reason | None = None
    for reason, label, accepts in _hint_tests(hints):
        agreeing = [i for i in range(len(candidates)) if accepts(candidates[i].pose)]
        if not agreeing:
            return Choice(None, Reason.NO_CANDIDATE_AGREES, f'{label} rejects every candidate')
        narrowed = [i for i in remaining if i in agreeing]
        if not narrowed:
            return Choice(None, Reason.CONFLICTING_HINTS, f'{label} rejects the candidate other hints chose')
        if len(narrowed) < len(remaining) and decided_by is None:
            decided_by = reason
        remaining = narrowed
    winner = overwhelming_winner(candidates)
    if winner is not None and winner not in remaining:
        return Choice(None, Reason.CONFLICTING_HINTS, 'the fit overwhelmingly favours a candidate the hints reject')
    if len(remaining) == 1:
        reason = decided_by if decided_by is not None else Reason.UNIQUE
        return Choice(candidates[remaining[0]].pose, reason)
    if winner is not None:
        return Choice(candidates[winner].pose, cost_reason)
    return Choice(None, Reason.AMBIGUOUS, f'{len(remaining)} candidates fit and no hint separates them')


def overwhelming_winner(candidates: list[PoseCandidate]) -> int | None:
    """Index of the cheapest candidate if its cost gap to every other exceeds ``COST_GAP``."""
    if len(candidates) < 2:
        return None
    order = sorted(range(len(candidates)), key=lambda i: candidates[i].cost)
    best, runner_up = candidates[order[0]], candidates[order[1]]
    dof = max(best.residual_count - 6, 1)
    noise_scale = max(best.cost / dof, 1.0)
    return order[0] if (runner_up.cost - best.cost) / noise_scale > COST_GAP else None


def _hint_tests(hints: DisambiguationHints) -> list[tuple[Reason, str, Callable[[Pose], bool]]]:
    tests = []
    for k, hint in enumerate(hints.up_in_camera):
        def accepts_up(pose: Pose, hint=hint) -> bool:
            return _angle(pose.up_in_camera(), hint.vector) <= hint.tolerance
        tests.append((Reason.UP_DIRECTION, f'up direction hint {k}', accepts_up))
    recent = hints.recent_pose
    if recent is not None and hints.recent_age <= hints.recent_max_age:
        def accepts_recent(pose: Pose) -> bool:
            return pose.position_error(recent) <= hints.recent_gate_m
        tests.append((Reason.CONTINUITY, 'the recent pose', accepts_recent))
    return tests


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    return math.acos(min(max(float(a @ b), -1.0), 1.0))
