"""Choosing among candidate poses with real information only, or declining to choose.

One circle and its marker are explained equally well by two poses. What may
separate them: a known up direction in the camera frame (a static mounting
prior, or gravity from an IMU at rest), continuity with a recent pose of the
same camera, other lamps in the frame (``fusion``), and, only when the gap is
overwhelming, the fit itself. Every hint must accept the chosen candidate and
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

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from vlp_ros.pose import Pose
from vlp_ros.solvers.candidates import Choice, PoseCandidate, Reason, distinct

COST_GAP = 40.0


@dataclass
class DisambiguationHints:
    """What is known about the pose besides the lamps.

    ``up_in_camera``: (where map +z points in the camera optical frame, tolerance in rad)
    per source, e.g. a static mounting prior and the IMU's gravity (an accelerometer at
    rest measures +g along up). ``recent_pose``: a recent pose of this camera, taken
    ``recent_age`` seconds ago; it counts when ``recent_age <= recent_max_age`` and then
    accepts candidates within ``recent_gate_m`` of it.
    """

    up_in_camera: list[tuple[np.ndarray, float]] = field(default_factory=list)
    recent_pose: Pose | None = None
    recent_gate_m: float = 0.5
    recent_age: float = 0.0
    recent_max_age: float = float('inf')

    def __post_init__(self) -> None:
        checked = []
        for direction, tolerance in self.up_in_camera:
            d = np.asarray(direction, dtype=float).reshape(3)
            norm = np.linalg.norm(d)
            if not (np.isfinite(norm) and norm > 0.0):
                raise ValueError(f'up direction {d} is not a finite non-zero vector')
            if not 0.0 < tolerance < np.pi:
                raise ValueError(f'up tolerance must be in (0, pi) rad, got {tolerance}')
            checked.append((d / norm, float(tolerance)))
        self.up_in_camera = checked
        if not self.recent_gate_m > 0.0:
            raise ValueError(f'recent_gate_m must be positive, got {self.recent_gate_m}')


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
    for k, (up, tolerance) in enumerate(hints.up_in_camera):
        def accepts_up(pose: Pose, up=up, tolerance=tolerance) -> bool:
            return _angle(pose.up_in_camera(), up) <= tolerance
        tests.append((Reason.UP_DIRECTION, f'up direction hint {k}', accepts_up))
    recent = hints.recent_pose
    if recent is not None and hints.recent_age <= hints.recent_max_age:
        def accepts_recent(pose: Pose) -> bool:
            return pose.position_error(recent) <= hints.recent_gate_m
        tests.append((Reason.CONTINUITY, 'the recent pose', accepts_recent))
    return tests


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.arccos(np.clip(a @ b, -1.0, 1.0)))
