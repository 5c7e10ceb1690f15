"""
Pose accuracy in simulation.

    python -m vlp_ros.benchmarks.accuracy [--quick] [--seed S] [--frames N] [--only TEXT] [--drive-speed V]
        [--drive-turn-rate W] [--figures DIR]

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

Then the looks of real lamps and cameras (``vlp_ros.sim.looks``) and the hard
cases of markers, stills and driving, through the perspective solver: the paper's hand-held 4K stills
at 2 m with the paper's rim marker under each look, raw and as JPEG, and under the
realistic look with its halo, blur and falloff (another functional form too) varied
(``sim.looks.VARIED_LOOKS``); markers from
0.5 r to straddling the rim; stills 0.1 s and 2 s apart with continuity on; the
robot under diffuser falloff and the realistic look; five packet lamps over the
robot with its IMU, clean and realistic; a robot driving and turning
under packet lamps 2.4 m apart (gaps with no lamp in view); robot stills under
tone lamps. For each: availability (poses per frame with a mapped lamp fully in
view, and why the rest had none), wrong fixes, mean NEES and poses beyond their
99.9 % chi-square bound; then each row's targets with the measured values,
and per look its mean error, p95, mean NEES and share of poses beyond the bound against
the optics targets (``optics_targets_table``), each with whether it holds.
"""
from __future__ import annotations

import argparse
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
import sys

import numpy as np
from scipy.stats import chi2
from tqdm import tqdm

from vlp_ros.core.gravity import GravityBuffer
from vlp_ros.detection import detect_lamps
from vlp_ros.evaluation.evaluate import grid_point
from vlp_ros.evaluation.metrics import (ErrorSummary, format_table, FrameOutcome, nees_or_nan, summarize, summary_row,
                                        TABLE_HEADER, WRONG_FIX_M)
from vlp_ros.evaluation.paper_solver import PublishedPaperSolver
from vlp_ros.evaluation.report import Evaluation, PAPER_PUBLISHED_MEAN_M, write_report
from vlp_ros.pipeline.config import settings_from_tree
from vlp_ros.pipeline.frame import FrameResult, Pipeline
from vlp_ros.sim.imu import specific_force
from vlp_ros.sim.looks import apply_look, LOOKS, transported, VARIED_LOOKS
from vlp_ros.sim.render import LampTruth, RenderedFrame
from vlp_ros.sim.scenarios import (as_stills, DRIVE_SPEED, DRIVE_TURN_RATE, paper_scenario, robot_drive_scenario,
                                   robot_scenario, robot_tone_scenario, Scenario, with_rim_markers)

SOLVERS = ('paper', 'perspective')
HEIGHTS = (2.0, 1.5)
# The hand-held looks: every effect alone, then together, on the paper's 4K stills at 2 m.
HAND_HELD_LOOKS = ('clean', 'blur', 'glare', 'falloff', 'saturated', 'clutter', 'jpeg', 'row_time_error',
                   'realistic', 'realistic_jpeg')
# Marker centres (fractions of r): inside, the paper's marginal point, straddling the rim.
MARKER_DISTANCES = (0.5, 0.9, 1.0)
# A 6-DoF NEES beyond this is outside the 99.9 % chi-square bound.
NEES_BOUND = float(chi2.ppf(0.999, 6))
# After a gap with no lamp in view, the drive target counts the poses on this many frames with one.
FRAMES_AFTER_GAP = 3
# A detected marker or lamp centre further than this (px) from its true image is reported as bad.
BAD_MARKER_PX = 3.0
BAD_CENTRE_PX = 5.0


@dataclass(frozen=True)
class Setup:
    """
    One simulated recording; ``number`` picks its random streams.

    ``targets`` name the kinds of target that apply to it (``_row_targets``),
    none for today's setups.
    """

    family: str
    group: str
    scenario: Scenario
    number: int
    solvers: tuple[str, ...] = SOLVERS
    targets: tuple[str, ...] = ()

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
    """Per solver, each frame's outcome; ``in_view[k]``: frame k shows a mapped lamp fully."""

    outcomes: dict[str, list[FrameOutcome]] = field(default_factory=dict)
    wrong_fixes: list[WrongFix] = field(default_factory=list)
    in_view: list[bool] = field(default_factory=list)


@dataclass(frozen=True)
class Drive:
    """How the robot of the drive rows moves: 0.8 m/s weaving, unless asked otherwise."""

    speed: float = DRIVE_SPEED
    turn_rate: float = DRIVE_TURN_RATE


def setups(quick: bool, seed: int, frames: int | None, drive: Drive = Drive()) -> list[Setup]:
    """
    Return the setups, numbered in order.

    The paper's grid at both heights with both cameras, the robot's drive, then the looks and hard cases.
    """
    points, postures = (3, 1) if quick else (7, 3)
    made = []
    for family, kind in (('paper 4K', '4k'), ('paper 1080p', '1080p')):
        for height in HEIGHTS:
            scenario = paper_scenario(kind, height=height, points=points, postures=postures, seed=seed)
            made.append(Setup(family, f'{height:g} m', scenario, 0))
    robot = robot_scenario(seed=seed)
    made.append(Setup('robot', '', robot.truncated(90) if quick else robot, 0))
    made += look_setups(quick, seed, drive)
    return [replace(setup, number=number,
                    scenario=setup.scenario if frames is None
                    else setup.scenario.truncated(min(frames, len(setup.scenario.poses))))
            for number, setup in enumerate(made)]


def look_setups(quick: bool, seed: int, drive: Drive = Drive()) -> list[Setup]:
    """Return the looks and the hard cases (markers, stills, driving, tone), through the perspective solver only."""
    points, postures = (3, 1) if quick else (5, 2)
    paper = paper_scenario('4k', height=2.0, points=points, postures=postures, seed=seed)
    marginal = with_rim_markers(paper, 0.9, 0.1)
    only = ('perspective',)
    made = [Setup('hand-held 4K 2 m', f'look {name}', apply_look(marginal, LOOKS[name], seed), 0, only,
                  ('hand-held look', 'falloff') if name == 'falloff' else ('hand-held look',))
            for name in HAND_HELD_LOOKS]
    made += [Setup('hand-held 4K 2 m', f'look {name}', apply_look(marginal, look, seed), 0, only, ('varied look',))
             for name, look in VARIED_LOOKS.items()]
    made += [Setup('hand-held 4K 2 m', f'marker at {distance:g} r', with_rim_markers(paper, distance, 0.1), 0, only,
                   ('marker',)) for distance in MARKER_DISTANCES]
    made += [Setup('hand-held 4K 2 m', f'stills {interval:g} s apart', as_stills(marginal, interval), 0, only,
                   ('stills',)) for interval in (0.1, 2.0)]
    robot = robot_scenario(seed=seed).truncated(90 if quick else 240)
    made += [Setup('robot row', f'look {name}', apply_look(robot, LOOKS[name], seed), 0, only, targets)
             for name, targets in (('falloff', ('falloff',)), ('realistic', ('any look',)))]
    driven = robot_drive_scenario(seed=seed, speed=drive.speed, turn_rate=drive.turn_rate)
    driven = driven.truncated(70) if quick else driven
    made += [Setup('robot drive', f'look {name}', apply_look(driven, LOOKS[name], seed), 0, only, targets)
             for name, targets in (('clean', ('drive',)), ('overexposed', ('drive',)), ('falloff', ('falloff',)),
                                   ('realistic', ('any look',)))]
    five = robot_scenario(lamp_count=5, seed=seed).truncated(60 if quick else 180)
    made += [Setup('robot five packet lamps IMU', f'look {name}', apply_look(five, LOOKS[name], seed), 0, only,
                   ('any look',)) for name in ('clean', 'realistic')]
    tone = robot_tone_scenario(seed=seed, frames=12 if quick else 24)
    made += [Setup('robot tone', f'look {name}', apply_look(tone, LOOKS[name], seed), 0, only, ('tone',))
             for name in ('clean', 'realistic', 'realistic_jpeg')]
    return made


def run_setup(setup: Setup, seed: int, progress: Callable[[], None] | None = None) -> SetupRun:
    """Every frame of ``setup`` through one pipeline per solver; ``progress()`` after each."""
    scenario = setup.scenario
    settings = settings_from_tree(scenario.locator_parameters(imu=True))
    # The paper's solver is measured as published: without the fit gate the locator applies.
    pipelines = {solver: PublishedPaperSolver(settings) if solver == 'paper'
                 else Pipeline(replace(settings, solver=solver)) for solver in setup.solvers}
    gravity = GravityBuffer(settings.imu_rotation, settings.imu_max_age)
    run = SetupRun({solver: [] for solver in setup.solvers})
    for index, (truth, stamp) in enumerate(zip(scenario.poses, scenario.frame_times())):
        rng = np.random.default_rng([seed, setup.number, index])
        frame = scenario.render(index, rng)
        image = transported(scenario, frame.image)
        mapped = scenario.mapped_truths(frame)
        run.in_view.append(any(t.fully_inside for t in mapped))
        stamp_ns = int(round(stamp * 1e9))
        gravity.add(stamp_ns, specific_force(truth, scenario.accelerations[index], scenario.imu_noise, rng))
        up = gravity.up_at(stamp_ns)
        for solver, pipeline in pipelines.items():
            result = pipeline.process(image, scenario.camera, float(stamp), up)
            run.outcomes[solver].append(FrameOutcome(truth, result.pose, setup.group, grid_point(truth.position[:2]),
                                                     result.outcome))
            if result.pose is not None and result.pose.position_error(truth) > WRONG_FIX_M:
                run.wrong_fixes.append(WrongFix(setup.label, solver, index, result.pose.position_error(truth),
                                                result.detail, *diagnose(frame, image, mapped, result, up)))
        if progress is not None:
            progress()
    return run


def diagnose(frame: RenderedFrame, image: np.ndarray, mapped: list[LampTruth], result: FrameResult,
             up: np.ndarray | None) -> tuple[str, str]:
    """
    Which stage a wrong fix came from, and the evidence.

    The decoded IDs against the mapped lamps in view, the detected ellipses and markers (in
    ``image``, as the locator got it) against their true images, the fix against gravity.
    """
    in_view = sorted(t.lamp_id for t in mapped if t.visible)
    findings = [f'decoded {sorted(result.decoded_ids)}, in view {in_view}']
    stages = []
    misread = sorted(set(result.decoded_ids) - set(in_view))
    if misread:
        stages.append(f'beacon: wrong ID {misread}')
    observations = detect_lamps(image)
    for truth in (t for t in mapped if t.visible and t.ellipse is not None):
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
    """Return the table of every setup x solver, and the summaries by row label."""
    rows, summaries = [], {}
    for setup, run in runs:
        for solver in setup.solvers:
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
    runs = [(setup, run) for setup, run in runs if not setup.targets]
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


@dataclass
class Availability:
    """
    How often a row answered where it could.

    ``in_view`` frames show a mapped lamp fully, ``posed`` of them got a pose (``elsewhere``:
    poses on the other frames); ``reasons`` why the rest got none; ``gaps`` spans without such a
    lamp that the recording resumes after (for FRAMES_AFTER_GAP frames with a lamp, or fewer with
    a pose), ``recovered`` of them with a pose within FRAMES_AFTER_GAP frames with a lamp;
    ``beyond_bound``: poses whose NEES is outside the 99.9 % chi-square bound.
    """

    frames: int
    in_view: int
    posed: int
    elsewhere: int
    reasons: Counter
    gaps: int
    recovered: int
    beyond_bound: int

    @property
    def rate(self) -> float:
        return self.posed / self.in_view if self.in_view else float('nan')


def availability(run: SetupRun, solver: str) -> Availability:
    outcomes = run.outcomes[solver]
    posed = [o.estimate is not None for o in outcomes]
    in_view = run.in_view
    starts, recovered = [], 0
    for start in (k for k in range(1, len(in_view)) if in_view[k] and not in_view[k - 1]):
        window = [k for k in range(start, len(in_view)) if in_view[k]][:FRAMES_AFTER_GAP]
        # A gap the recording ends too soon after to tell is not judged, unless it was recovered.
        if len(window) == FRAMES_AFTER_GAP or any(posed[k] for k in window):
            starts.append(start)
            recovered += any(posed[k] for k in window)
    nees_values = [nees_or_nan(o.estimate, o.truth) for o in outcomes if o.estimate is not None]
    return Availability(
        frames=len(outcomes), in_view=sum(in_view), posed=sum(p and v for p, v in zip(posed, in_view)),
        elsewhere=sum(p and not v for p, v in zip(posed, in_view)),
        reasons=Counter(o.reason for o, p, v in zip(outcomes, posed, in_view) if v and not p),
        gaps=len(starts), recovered=recovered, beyond_bound=sum(1 for n in nees_values if n > NEES_BOUND))


def availability_table(runs: list[tuple[Setup, SetupRun]], summaries: dict[str, ErrorSummary]) -> str:
    """Per look or hard case: availability, wrong fixes, accuracy, NEES, and why frames with a lamp had no pose."""
    rows = []
    for setup, run in runs:
        if not setup.targets:
            continue
        for solver in setup.solvers:
            a, s = availability(run, solver), summaries[row_label(setup, solver)]
            reasons = ', '.join(f'{reason} {count}' for reason, count in a.reasons.most_common()) or '-'
            rows.append([row_label(setup, solver), str(a.frames), str(a.in_view), str(a.posed),
                         '-' if np.isnan(a.rate) else f'{100 * a.rate:.1f}', str(a.elsewhere),
                         f'{a.recovered}/{a.gaps}' if a.gaps else '-', str(s.wrong_fixes),
                         '-' if np.isnan(s.mean_m) else f'{100 * s.mean_m:.2f}',
                         '-' if np.isnan(s.mean_nees) else f'{s.mean_nees:.3g}', str(a.beyond_bound), reasons])
    return format_table(rows, ('row', 'frames', 'lamp in view', 'poses', 'available %', 'poses w/o lamp',
                               'gaps recovered', 'wrong', 'mean cm', 'mean NEES', 'NEES > 99.9 %',
                               'why no pose (frames with a lamp)'))


def _shown(value: float, unit: str = '') -> str:
    return '-' if np.isnan(value) else f'{value:.3g}{unit}'


def _row_targets(kind: str, a: Availability, s: ErrorSummary) -> list[tuple[str, str, bool]]:
    """
    Return what a kind of target asks of a row: (target, measured, met) each.

    A row without poses meets no target but 'wrong fixes = 0'.
    """
    available = ('pose on >= 90 % of frames with a lamp in view', _shown(100 * a.rate, ' %'), a.rate >= 0.9)
    wrong = ('wrong fixes = 0', str(s.wrong_fixes), s.wrong_fixes == 0)
    nees_range = ('mean NEES in [4, 8]', _shown(s.mean_nees), 4.0 <= s.mean_nees <= 8.0)
    bound = ('poses beyond 99.9 % chi-square = 0', f'{a.beyond_bound} of {s.poses}',
             a.beyond_bound == 0 and s.poses > 0)
    recovered = (f'gaps with a pose within {FRAMES_AFTER_GAP} frames = all', f'{a.recovered} of {a.gaps}',
                 a.gaps > 0 and a.recovered == a.gaps)
    return {
        'hand-held look': [available, wrong, nees_range],
        'tone': [available, wrong],
        'marker': [available, wrong],
        'stills': [available, wrong],
        'drive': [available, recovered, wrong],
        'falloff': [nees_range, bound],
        'any look': [wrong, nees_range, bound],
        'varied look': [available, wrong],
    }[kind]


# Mean 3D error targets (cm) of the optics rows: the hand-held 4K stills at 2 m with an IMU, the robot under
# tone lamps and under five packet lamps with its IMU, and the drive under sparse lamps.
OPTICS_MEAN_TARGET_CM = {
    'hand-held 4K 2 m look clean': 0.3,
    'hand-held 4K 2 m look falloff': 0.6,
    'hand-held 4K 2 m look realistic_jpeg': 1.0,
    'robot tone look realistic': 0.5,
    'robot five packet lamps IMU look realistic': 0.5,
    'robot drive look clean': 1.5,
    'robot drive look falloff': 2.0,
}
# Every optics row: mean NEES in this range, at most this share of poses beyond the 99.9 % bound,
# availability and no wrong fix as before.
OPTICS_NEES_RANGE = (3.0, 10.0)
OPTICS_MAX_BEYOND = 0.01


def optics_targets_table(runs: list[tuple[Setup, SetupRun]], summaries: dict[str, ErrorSummary]) -> str:
    """
    Return every look row with its mean error, p95, mean NEES, share beyond the bound, targets and whether they hold.

    The targets: the row's mean error where ``OPTICS_MEAN_TARGET_CM`` sets one, mean NEES in
    ``OPTICS_NEES_RANGE``, at most ``OPTICS_MAX_BEYOND`` of the poses beyond the bound, availability
    >= 90 % and no wrong fix.
    """
    rows = []
    for setup, run in runs:
        if not setup.targets or not setup.group.startswith('look'):
            continue
        label = row_label(setup, 'perspective')
        a, s = availability(run, 'perspective'), summaries[label]
        beyond = a.beyond_bound / s.poses if s.poses else float('nan')
        limit = OPTICS_MEAN_TARGET_CM.get(setup.label)
        checks = [('NEES 3-10', OPTICS_NEES_RANGE[0] <= s.mean_nees <= OPTICS_NEES_RANGE[1]),
                  ('<= 1 % beyond', beyond <= OPTICS_MAX_BEYOND), ('>= 90 % available', a.rate >= 0.9),
                  ('0 wrong', s.wrong_fixes == 0)]
        if limit is not None:
            checks.insert(0, (f'mean <= {limit:g} cm', 100 * s.mean_m <= limit))
        rows.append([label, _shown(100 * s.mean_m), _shown(100 * s.p95_m), _shown(s.mean_nees),
                     _shown(100 * beyond, ' %'), _shown(100 * a.rate, ' %'), str(s.wrong_fixes),
                     ', '.join(what for what, _ in checks),
                     'yes' if all(met for _, met in checks) else
                     'NO: ' + ', '.join(what for what, met in checks if not met)])
    return format_table(rows, ('row', 'mean cm', 'p95 cm', 'mean NEES', 'beyond 99.9 %', 'available', 'wrong',
                               'targets', 'hold'))


def row_targets_table(runs: list[tuple[Setup, SetupRun]], summaries: dict[str, ErrorSummary]) -> str:
    """Return each row's targets next to what this run measured (no poses never meets one)."""
    rows = []
    for setup, run in runs:
        for kind in setup.targets:
            label = row_label(setup, 'perspective')
            a = availability(run, 'perspective')
            for what, shown, met in _row_targets(kind, a, summaries[label]):
                rows.append([label, what, shown, 'yes' if met else 'NO'])
    return format_table(rows, ('row', 'target', 'measured', 'met'))


def no_pose_table(runs: list[tuple[Setup, SetupRun]]) -> str:
    """How many frames of each of today's rows ended without a pose, by the pipeline's outcome."""
    counts = {row_label(setup, solver): Counter(o.reason for o in run.outcomes[solver] if o.estimate is None)
              for setup, run in runs if not setup.targets for solver in setup.solvers}
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
    """One paper-style report (figures and summary) per family of today's setups."""
    summaries = []
    for family in dict.fromkeys(setup.family for setup, _ in runs if not setup.targets):
        series = {solver: [o for setup, run in runs if setup.family == family for o in run.outcomes[solver]]
                  for solver in SOLVERS}
        evaluation = Evaluation(f'{family} (simulated, benchmarks.accuracy)', series)
        summaries.append(write_report(evaluation, folder / family.replace(' ', '_')))
    return summaries


def _arguments(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog='python -m vlp_ros.benchmarks.accuracy',
                                     description=__doc__.strip().splitlines()[0])
    parser.add_argument('--quick', action='store_true',
                        help='3 x 3 grid, one posture, 3 s of robot row, 7 s of drive, 12 tone stills')
    parser.add_argument('--only', action='append', default=None, metavar='TEXT',
                        help='run only the setups whose label contains TEXT (repeatable), e.g. "look realistic"')
    parser.add_argument('--seed', type=int, default=2017)
    parser.add_argument('--frames', type=int, default=None, help='at most this many frames per setup')
    parser.add_argument('--examples', type=int, default=3, help='wrong fixes shown in full per row')
    parser.add_argument('--figures', type=Path, default=None, help='write paper-style figures into this folder')
    parser.add_argument('--drive-speed', type=float, default=Drive.speed, metavar='V',
                        help=f"m/s of the drive rows' robot (default {Drive.speed:g})")
    parser.add_argument('--drive-turn-rate', type=float, default=Drive.turn_rate, metavar='W',
                        help=f'largest heading rate (rad/s) of its weave (default {Drive.turn_rate:g})')
    args = parser.parse_args(argv)
    if args.frames is not None and args.frames < 1:
        parser.error(f'--frames must be at least 1, got {args.frames}')
    if not (args.drive_speed > 0.0 and args.drive_turn_rate >= 0.0):
        parser.error(f'--drive-speed must be positive and --drive-turn-rate not negative, got {args.drive_speed} '
                     f'and {args.drive_turn_rate}')
    return args


def main(argv: list[str] | None = None) -> int:
    args = _arguments(argv)
    runs = []
    drive = Drive(args.drive_speed, args.drive_turn_rate)
    chosen = [setup for setup in setups(args.quick, args.seed, args.frames, drive)
              if args.only is None or any(text in setup.label for text in args.only)]
    if not chosen:
        print(f'no setup matches --only {" ".join(args.only)}', file=sys.stderr)
        return 2
    for setup in chosen:
        with tqdm(desc=setup.label, total=len(setup.scenario.poses), unit='frame', disable=None) as bar:
            runs.append((setup, run_setup(setup, args.seed, bar.update)))
    table, summaries = results_table(runs)
    driven = '' if drive == Drive() else f', drive {drive.speed:g} m/s turning up to {drive.turn_rate:g} rad/s'
    print(f'Pose accuracy in simulation (seed {args.seed}{", quick" if args.quick else ""}{driven}); '
          f'errors in 3D, wrong fix = error > {100 * WRONG_FIX_M:.0f} cm')
    print(table)
    if any(not setup.targets for setup, _ in runs):
        print('\nTargets')
        print(targets_table(runs, summaries))
        print('\nWhy frames had no pose')
        print(no_pose_table(runs))
    if any(setup.targets for setup, _ in runs):
        print(f'\nLooks of real lamps and cameras, and hard cases: availability = poses on frames with a '
              f'mapped lamp fully in view; NEES bound {NEES_BOUND:.1f} (99.9 %, 6 DoF)')
        print(availability_table(runs, summaries))
        print('\nTargets per row')
        print(row_targets_table(runs, summaries))
        print(f'\nOptics targets per look (mean NEES {OPTICS_NEES_RANGE[0]:g}-{OPTICS_NEES_RANGE[1]:g}, '
              f'<= {100 * OPTICS_MAX_BEYOND:g} % of poses beyond the 99.9 % bound, as in every row)')
        print(optics_targets_table(runs, summaries))
    print()
    print(wrong_fix_report([w for _, run in runs for w in run.wrong_fixes], args.seed, args.examples))
    if args.figures is not None:
        for summary in write_figures(runs, args.figures):
            print(f'figures: {summary}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
