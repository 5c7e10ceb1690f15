"""
A ground robot on a known floor: python -m vlp_ros.benchmarks.planar [--frames N] [--seed S] [--only TEXT].

The robot of ``sim.planar_drive`` (camera 45 cm up looking up, 1080p 100 deg, lamps of 10-20 cm
2-3 m up, sparse) drives 0.8 m/s on a flat floor (tilt <= 0.3 deg) and a rough one (<= 1.5 deg) in
the looks of docs/simulator.md. Every frame is rendered once and run through two pipelines
with ``base_frame`` and ``camera_in_base`` set: 6-DoF (today's solve) and planar
(``planar.*``, sigma_tilt as the target table sets it, sigma_height the floor's bumps); the
6-DoF solve is given the mount's up direction as a gate (``prior.up_in_camera``, no sigma) to
choose between a lamp's two circle poses, the planar one only the floor. The
published base poses (``Mounting.base_pose``) are scored against the true base: mean position
error, the x-y and yaw errors, mean NEES (6 dof), the share of frames with a lamp in view that
got a pose, wrong fixes (> 0.5 m), and frames refused as off the floor; then each target of the
table with whether it holds.
"""
from __future__ import annotations

import argparse
from collections import Counter
from dataclasses import dataclass, field, replace

import numpy as np

from vlp_ros.core.pose import Pose
from vlp_ros.evaluation.metrics import format_table, WRONG_FIX_M
from vlp_ros.pipeline.config import settings_from_tree
from vlp_ros.pipeline.frame import Pipeline
from vlp_ros.sim.looks import apply_look, LOOKS, transported
from vlp_ros.sim.planar_drive import FLOORS, MOUNTING, mounting_parameters, planar_drive_scenario, planar_parameters
from vlp_ros.solvers.candidates import Reason
from vlp_ros.solvers.covariance import nees


@dataclass(frozen=True)
class Row:
    """One row of the target table: floor, ``planar.sigma_tilt`` (rad), look, and the mean error target (m)."""

    floor: str
    sigma_tilt: float
    look: str
    target_mean_m: float | None  # None: no worse than 6-DoF on the same frames

    @property
    def label(self) -> str:
        return f'{self.floor}, sigma_tilt {self.sigma_tilt:g}, {self.look}'


ROWS = (Row('flat', 0.0026, 'clean', 0.008), Row('flat', 0.0026, 'falloff', 0.010),
        Row('flat', 0.0026, 'realistic', 0.015), Row('rough', 0.013, 'clean', None),
        Row('rough', 0.013, 'falloff', None))
MIN_AVAILABILITY = 0.95
# rad: the 6-DoF solve's static prior, a gate only (no sigma), as for the simulator's robots.
PRIOR_TOLERANCE = 0.1
# m/s and s: both solves' continuity, set for the robot (0.8 m/s, gaps of up to 2-3 s between lamps).
CONTINUITY_MAX_SPEED = 1.0
CONTINUITY_MAX_AGE = 3.0
NEES_RANGE = (3.0, 10.0)


@dataclass
class Scores:
    """One pipeline's base poses over a drive."""

    in_view: int = 0
    posed_in_view: int = 0
    poses: int = 0
    errors: list = field(default_factory=list)
    xy_errors: list = field(default_factory=list)
    yaw_errors: list = field(default_factory=list)
    nees: list = field(default_factory=list)
    wrong: int = 0
    off_the_floor: int = 0
    # Why frames with a lamp in view got no pose.
    missed: Counter = field(default_factory=Counter)

    def add(self, estimate: Pose | None, truth: Pose, lamp_in_view: bool, outcome: str) -> None:
        self.in_view += lamp_in_view
        self.off_the_floor += outcome == Reason.OFF_THE_FLOOR.value
        if estimate is None:
            if lamp_in_view:
                self.missed[outcome] += 1
            return
        self.poses += 1
        self.posed_in_view += lamp_in_view
        error = estimate.error_vector(truth)
        self.errors.append(float(np.linalg.norm(error[:3])))
        self.xy_errors.append(float(np.linalg.norm(error[:2])))
        self.yaw_errors.append(abs(float(np.degrees(error[5]))))
        self.nees.append(nees(estimate, truth))
        self.wrong += self.errors[-1] > WRONG_FIX_M

    @property
    def availability(self) -> float:
        return self.posed_in_view / self.in_view if self.in_view else float('nan')

    def mean(self, values: list) -> float:
        return float(np.mean(values)) if values else float('nan')


def run_row(row: Row, frames: int, seed: int) -> tuple[Scores, Scores]:
    """Return the 6-DoF and the planar scores of one row's drive, on the same rendered frames."""
    floor = FLOORS[row.floor]
    drive, bases = planar_drive_scenario(floor, seed=seed)
    scenario = apply_look(drive, LOOKS[row.look], seed=seed)
    scenario = replace(scenario, poses=scenario.poses[:frames])
    parameters = scenario.locator_parameters(imu=False)
    parameters.update(mounting_parameters())
    # A robot's own top speed and longest gap between lamps (README, "IDs settled by continuity").
    parameters['continuity'] = {'max_speed': CONTINUITY_MAX_SPEED, 'max_age': CONTINUITY_MAX_AGE}
    # Today's level robot: the mount's up direction as a gate between the two circle poses.
    six_dof = Pipeline(settings_from_tree({**parameters, 'prior': {
        'up_in_camera': [float(v) for v in MOUNTING.up_in_camera()], 'tolerance': PRIOR_TOLERANCE}}))
    planar = Pipeline(settings_from_tree({**parameters, **planar_parameters(floor, row.sigma_tilt)}))
    scores = (Scores(), Scores())
    rng = np.random.default_rng(seed)
    for index, (truth, t) in enumerate(zip(bases, scenario.frame_times())):
        frame = scenario.render(index, rng)
        image = transported(scenario, frame.image)
        in_view = any(lamp.fully_inside for lamp in scenario.mapped_truths(frame))
        for pipeline, score in zip((six_dof, planar), scores):
            result = pipeline.process(image, scenario.camera, float(t))
            estimate = None if result.pose is None else MOUNTING.base_pose(result.pose)
            score.add(estimate, truth, in_view, result.outcome)
    return scores


def _cm(value: float) -> str:
    return '-' if np.isnan(value) else f'{100 * value:.2f}'


def score_row(label: str, s: Scores) -> list[str]:
    return [label, str(s.in_view), str(s.poses), f'{100 * s.availability:.1f}', _cm(s.mean(s.errors)),
            _cm(s.mean(s.xy_errors)), f'{s.mean(s.yaw_errors):.3f}', f'{s.mean(s.nees):.2f}', str(s.wrong),
            str(s.off_the_floor), ', '.join(f'{reason} {count}' for reason, count in s.missed.most_common(3))]


HEADER = ('row', 'solve', 'lamp in view', 'poses', 'posed in view %', 'mean cm', 'xy cm', 'yaw deg', 'mean NEES',
          'wrong', 'off floor', 'in view, no pose')


def verdicts(row: Row, six_dof: Scores, planar: Scores) -> list[list[str]]:
    """Each target of ``row``: what it asks, what was measured, and whether it holds."""
    mean = planar.mean(planar.errors)
    if row.target_mean_m is None:
        reference = six_dof.mean(six_dof.errors)
        checks = [(f'mean <= 6-DoF ({_cm(reference)} cm)', f'{_cm(mean)} cm', mean <= reference)]
    else:
        checks = [(f'mean <= {_cm(row.target_mean_m)} cm', f'{_cm(mean)} cm', mean <= row.target_mean_m)]
    low, high = NEES_RANGE
    checks += [(f'posed >= {100 * MIN_AVAILABILITY:.0f} % of frames with a lamp in view',
                f'{100 * planar.availability:.1f} %', planar.availability >= MIN_AVAILABILITY),
               ('0 wrong', str(planar.wrong), planar.wrong == 0),
               (f'mean NEES {low:g}-{high:g}', f'{planar.mean(planar.nees):.2f}',
                low <= planar.mean(planar.nees) <= high)]
    return [[row.label, target, measured, 'holds' if ok else 'MISSES'] for target, measured, ok in checks]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='python -m vlp_ros.benchmarks.planar', description=__doc__.strip()
                                     .splitlines()[0])
    parser.add_argument('--frames', type=int, default=150, help='frames of each drive (10 per second)')
    parser.add_argument('--seed', type=int, default=1)
    parser.add_argument('--only', default='', help='only the rows whose label contains this text')
    args = parser.parse_args(argv)
    rows = [row for row in ROWS if args.only in row.label]
    table, targets = [], []
    for row in rows:
        six_dof, planar = run_row(row, args.frames, args.seed)
        table += [score_row(f'{row.label}', six_dof)[:1] + ['6-DoF'] + score_row('', six_dof)[1:],
                  score_row(f'{row.label}', planar)[:1] + ['planar'] + score_row('', planar)[1:]]
        targets += verdicts(row, six_dof, planar)
        print(f'{row.label}: done', flush=True)
    print(f'planar robot drive, {args.frames} frames a row, seed {args.seed}; base_link scored against the truth')
    print(format_table(table, HEADER))
    print()
    print(format_table(targets, ('row', 'target', 'measured', '')))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
