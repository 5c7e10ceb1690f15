"""Pose accuracy in simulation: python -m vlp_ros.benchmarks.accuracy [--quick] [--seed S] [--frames N] [--figures DIR].

The seed paper's experiment reproduced in this process (no ROS, no bags): every
frame is rendered by the frame simulator and run through ``Pipeline.process``
with the up direction a camera-mounted accelerometer measures (the scenario's
IMU noise), taken through the locator's ``GravityBuffer``. Setups: a 3 m x 3 m
grid with the lamp 1.5 m and 2 m above a hand-held phone (several postures per
point), with a 4K camera of the Lumia 1020's field of view and with a 1080p one;
and the robot (1080p wide-angle camera looking up from 0.45 m under a row of
15 cm lamps 1.2 m apart, 1-3 lamps in view). Each setup's frames go through the
paper's solver and the perspective solver alike, each in one pipeline for the
whole setup, as the locator node runs (the paper's photos are independent: no
continuity between them). Prints one table (setup x solver), the targets, why
frames had no pose, and the wrong fixes: counted by row with the stage at fault,
the first few of each row in full. Frame k of a setup is rendered from its own
random stream ([seed, setup number, k]), so a frame can be reproduced alone.
"""
from __future__ import annotations

import argparse
import sys
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from vlp_ros.detection import detect_lamps
from vlp_ros.evaluation.evaluate import grid_point
from vlp_ros.evaluation.metrics import (TABLE_HEADER, WRONG_FIX_M, ErrorSummary, FrameOutcome, format_table,
                                        summarize, summary_row)
from vlp_ros.evaluation.report import PAPER_PUBLISHED_MEAN_M, Evaluation, write_report
from vlp_ros.gravity import GravityBuffer
from vlp_ros.pipeline import FrameResult, Pipeline
from vlp_ros.progress import progress_bar
from vlp_ros.sim.imu import specific_force
from vlp_ros.sim.render import RenderedFrame, render_frame
from vlp_ros.sim.scenarios import Scenario, paper_scenario, robot_scenario

SOLVERS = ('paper', 'perspective')
HEIGHTS = (2.0, 1.5)
# A detected marker or lamp centre further than this (px) from its true image is reported as bad.
BAD_MARKER_PX = 3.0
BAD_CENTRE_PX = 5.0


@dataclass(frozen=True)
class Setup:
    """One simulated recording; ``number`` picks its random streams."""

    family: str
    group: str
    scenario: Scenario
    number: int

    @property
    def label(self) -> str:
        return f'{self.family} {self.group}'.strip()


@dataclass
class WrongFix:
    """A published pose further than WRONG_FIX_M from the truth, with what the frame showed."""

    setup: str
    solver: str
    index: int
    error_m: float
    decided_by: str
    stage: str
    findings: str


@dataclass
class SetupRun:
    outcomes: dict[str, list[FrameOutcome]] = field(default_factory=dict)
    wrong_fixes: list[WrongFix] = field(default_factory=list)


def setups(quick: bool, seed: int, frames: int | None) -> list[Setup]:
    """The paper's grid at both heights with both cameras, then the robot's drive."""
    points, postures = (3, 1) if quick else (7, 3)
    made = []
    for family, kind in (('paper 4K', '4k'), ('paper 1080p', '1080p')):
        for height in HEIGHTS:
            scenario = paper_scenario(kind, height=height, points=points, postures=postures, seed=seed)
            made.append((family, f'{height:g} m', scenario))
    robot = robot_scenario(seed=seed)
    made.append(('robot', '', robot.truncated(90) if quick else robot))
    return [Setup(family, group, scenario if frames is None else scenario.truncated(min(frames, len(scenario.poses))),
                  number)
            for number, (family, group, scenario) in enumerate(made)]


def run_setup(setup: Setup, seed: int, progress: Callable[[int], None] | None = None) -> SetupRun:
    """Every frame of ``setup`` through one pipeline per solver."""
    scenario = setup.scenario
    settings = scenario.locator_settings()
    # The paper's solver is measured as published: without the fit gate the locator applies.
    pipelines = {solver: Pipeline(replace(settings, solver=solver), gate_fit=solver != 'paper') for solver in SOLVERS}
    gravity = GravityBuffer(settings.imu_rotation, settings.imu_max_age)
    run = SetupRun({solver: [] for solver in SOLVERS})
    for index, (truth, stamp) in enumerate(zip(scenario.poses, scenario.frame_times())):
        rng = np.random.default_rng([seed, setup.number, index])
        frame = render_frame(scenario.camera, truth, scenario.lamps, scenario.sensor, float(stamp), rng)
        stamp_ns = int(round(stamp * 1e9))
        gravity.add(stamp_ns, specific_force(truth, scenario.accelerations[index], scenario.imu_noise, rng))
        up = gravity.up_at(stamp_ns)
        for solver, pipeline in pipelines.items():
            result = pipeline.process(frame.image, scenario.camera, float(stamp), up)
            run.outcomes[solver].append(FrameOutcome(truth, result.pose, setup.group, grid_point(truth.position[:2]),
                                                     result.outcome))
            if result.pose is not None and result.pose.position_error(truth) > WRONG_FIX_M:
                run.wrong_fixes.append(WrongFix(setup.label, solver, index, result.pose.position_error(truth),
                                                result.detail, *diagnose(frame, result, up)))
        if progress is not None:
            progress(index + 1)
    return run


def diagnose(frame: RenderedFrame, result: FrameResult, up: np.ndarray | None) -> tuple[str, str]:
    """Which stage a wrong fix came from, and the evidence: the decoded IDs against the lamps
    in view, the detected ellipses and markers against their true images, the fix against gravity."""
    in_view = sorted(t.lamp_id for t in frame.lamps if t.visible)
    findings = [f'decoded {sorted(result.decoded_ids)}, in view {in_view}']
    stages = []
    misread = sorted(set(result.decoded_ids) - set(in_view))
    if misread:
        stages.append(f'beacon: wrong ID {misread}')
    observations = detect_lamps(frame.image)
    for truth in (t for t in frame.lamps if t.visible and t.ellipse is not None):
        nearest = min(observations, key=lambda o: np.linalg.norm(o.center - truth.ellipse[:2]), default=None)
        if nearest is None or np.linalg.norm(nearest.center - truth.ellipse[:2]) > BAD_CENTRE_PX:
            stages.append(f'detection: lamp {truth.lamp_id} missed or misplaced')
            continue
        if nearest.marker is None:
            findings.append(f'lamp {truth.lamp_id}: no marker')
            continue
        marker_px = float(np.linalg.norm(nearest.marker - truth.marker_pixel))
        off_axis = np.degrees(np.arccos(truth.center_camera[2] / np.linalg.norm(truth.center_camera)))
        findings.append(f'lamp {truth.lamp_id} ({off_axis:.0f} deg off the optical axis): centre off by '
                        f'{np.linalg.norm(nearest.center - truth.ellipse[:2]):.1f} px, marker by {marker_px:.1f} px')
        if marker_px > BAD_MARKER_PX:
            stages.append(f'detection: bad marker on lamp {truth.lamp_id}')
    if up is not None:
        tilt = np.degrees(np.arccos(np.clip(result.pose.up_in_camera() @ up, -1.0, 1.0)))
        truth_tilt = np.degrees(np.arccos(np.clip(frame.pose.up_in_camera() @ up, -1.0, 1.0)))
        findings.append(f'fix {tilt:.1f} deg from measured gravity (truth {truth_tilt:.1f} deg)')
    return '; '.join(stages) or 'solver (detection and ID right)', '; '.join(findings)


def row_label(setup: Setup, solver: str) -> str:
    return f'{setup.label} {solver}'


def results_table(runs: list[tuple[Setup, SetupRun]]) -> tuple[str, dict[str, ErrorSummary]]:
    """The table of every setup x solver, and the summaries by row label."""
    rows, summaries = [], {}
    for setup, run in runs:
        for solver in SOLVERS:
            summary = summarize(run.outcomes[solver])
            summaries[row_label(setup, solver)] = summary
            rate = 100.0 * summary.no_pose / summary.frames if summary.frames else float('nan')
            rows.append(summary_row(row_label(setup, solver), summary) + [f'{rate:.1f}'])
    return format_table(rows, TABLE_HEADER + ('no pose %',)), summaries


def _target(rows: list[list[str]], label: str, summaries: dict[str, ErrorSummary], what: str,
            value: float, met: bool | None, unit: str) -> None:
    if label in summaries:
        shown = '-' if np.isnan(value) else f'{value:.3g}{unit}'
        rows.append([label, what, shown, '-' if met is None else ('yes' if met else 'NO')])


def targets_table(runs: list[tuple[Setup, SetupRun]], summaries: dict[str, ErrorSummary]) -> str:
    """Each target next to what this run measured (NaN, i.e. no poses, never meets one)."""
    rows: list[list[str]] = []
    for setup, _ in runs:
        label, s = row_label(setup, 'perspective'), summaries[row_label(setup, 'perspective')]
        if setup.family == 'paper 4K':
            limit = 0.5 if setup.group == '2 m' else 0.4
            _target(rows, label, summaries, f'mean <= {limit} cm', 100 * s.mean_m, 100 * s.mean_m <= limit, ' cm')
            _target(rows, label, summaries, 'p95 <= 1.5 cm', 100 * s.p95_m, 100 * s.p95_m <= 1.5, ' cm')
            _target(rows, label, summaries, 'orientation mean <= 0.15 deg', s.orientation_mean_deg,
                    s.orientation_mean_deg <= 0.15, ' deg')
        if setup.family == 'robot':
            _target(rows, label, summaries, 'mean <= 1.0 cm', 100 * s.mean_m, 100 * s.mean_m <= 1.0, ' cm')
        _target(rows, label, summaries, 'wrong fixes = 0', s.wrong_fixes, s.wrong_fixes == 0, '')
        _target(rows, label, summaries, 'mean NEES in [4, 8]', s.mean_nees, 4.0 <= s.mean_nees <= 8.0, '')
    for setup, _ in runs:
        published = PAPER_PUBLISHED_MEAN_M.get(setup.group)
        label = row_label(setup, 'paper')
        if setup.family == 'paper 4K' and published is not None:
            _target(rows, label, summaries, f'published (Zhang et al. 2017): mean {100 * published:.2f} cm',
                    100 * summaries[label].mean_m, None, ' cm')
    return format_table(rows, ('row', 'target', 'measured', 'met'))


def no_pose_table(runs: list[tuple[Setup, SetupRun]]) -> str:
    """How many frames of each row ended without a pose, by the pipeline's outcome."""
    counts = {row_label(setup, solver): Counter(o.reason for o in run.outcomes[solver] if o.estimate is None)
              for setup, run in runs for solver in SOLVERS}
    reasons = sorted(set().union(*counts.values()))
    rows = [[label, *(str(c.get(reason, 0)) for reason in reasons)] for label, c in counts.items()]
    return format_table(rows, ('frames without a pose', *reasons))


def wrong_fix_report(wrong: list[WrongFix], seed: int, examples: int) -> str:
    """Every wrong fix counted by row, stage and deciding hint; the first ``examples`` of each row in full."""
    if not wrong:
        return 'Wrong fixes: none'
    rows: dict[str, list[WrongFix]] = {}
    for w in wrong:
        rows.setdefault(f'{w.setup} {w.solver}', []).append(w)

    def tally(values: list[str]) -> str:
        return ', '.join(f'{value} x{count}' for value, count in Counter(values).most_common())

    table = [[label, str(len(items)), f'{100 * max(w.error_m for w in items):.1f}', tally([w.stage for w in items]),
              tally([w.decided_by or '-' for w in items])] for label, items in rows.items()]
    lines = [f'Wrong fixes: {len(wrong)}',
             format_table(table, ('row', 'wrong fixes', 'max cm', 'stage at fault', 'chosen by'))]
    for label, items in rows.items():
        for w in items[:examples]:
            lines.append(f'- {label}, seed {seed}, frame {w.index}: error {100 * w.error_m:.1f} cm, '
                         f'chosen by {w.decided_by or "-"}; {w.findings}')
        if len(items) > examples:
            lines.append(f'  ({len(items) - examples} more in {label}: frames '
                         f'{", ".join(str(w.index) for w in items[examples:])})')
    return '\n'.join(lines)


def write_figures(runs: list[tuple[Setup, SetupRun]], folder: Path) -> list[Path]:
    """One paper-style report (figures and summary) per setup family."""
    summaries = []
    for family in dict.fromkeys(setup.family for setup, _ in runs):
        series = {solver: [o for setup, run in runs if setup.family == family for o in run.outcomes[solver]]
                  for solver in SOLVERS}
        evaluation = Evaluation(f'{family} (simulated, benchmarks.accuracy)', series)
        summaries.append(write_report(evaluation, folder / family.replace(' ', '_')))
    return summaries


def _arguments(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog='python -m vlp_ros.benchmarks.accuracy', description=__doc__.splitlines()[0])
    parser.add_argument('--quick', action='store_true', help='3 x 3 grid, one posture, 3 s of robot drive')
    parser.add_argument('--seed', type=int, default=2017)
    parser.add_argument('--frames', type=int, default=None, help='at most this many frames per setup')
    parser.add_argument('--examples', type=int, default=3, help='wrong fixes shown in full per row')
    parser.add_argument('--figures', type=Path, default=None, help='write paper-style figures into this folder')
    args = parser.parse_args(argv)
    if args.frames is not None and args.frames < 1:
        parser.error(f'--frames must be at least 1, got {args.frames}')
    return args


def main(argv: list[str] | None = None) -> int:
    args = _arguments(argv)
    runs = []
    for setup in setups(args.quick, args.seed, args.frames):
        total = len(setup.scenario.poses)
        runs.append((setup, run_setup(setup, args.seed,
                                      lambda done, total=total, label=setup.label: progress_bar(done, total, label))))
    table, summaries = results_table(runs)
    print(f'Pose accuracy in simulation (seed {args.seed}{", quick" if args.quick else ""}); '
          f'errors in 3D, wrong fix = error > {100 * WRONG_FIX_M:.0f} cm')
    print(table)
    print('\nTargets')
    print(targets_table(runs, summaries))
    print('\nWhy frames had no pose')
    print(no_pose_table(runs))
    print()
    print(wrong_fix_report([w for _, run in runs for w in run.wrong_fixes], args.seed, args.examples))
    if args.figures is not None:
        for summary in write_figures(runs, args.figures):
            print(f'figures: {summary}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
