"""
Surveying the lamps: python -m vlp_ros.benchmarks.survey [--seeds S ...] [--looks L ...] [--exact-only].

Three kinds of drive, each surveyed with its odometry and from images alone:

- ``foreign``: the independent renderer's survey drive (foreign_frames/README.md), through the whole
  ``survey`` path (bag, pipeline, estimation);
- ``sim``: the simulator's survey drives (``sim.survey_drive``: 12 lamps 1.2-2.4 m apart, 3 anchors,
  wheel odometry 2 % off in scale and drifting in heading), rendered in each of ``--looks`` (clean and
  realistic by default) and surveyed the same way;
- ``exact``: the same drives from exactly projected lamps with 0.3 px noise (no image): the estimation alone.

Per row: lamp position error RMS and max against the truth, marker angle RMS, mean NEES of the positions
(3 DoF; honest about 3), undetermined lamps, and the survey's CPU time over the recording's duration.
Then, for each rendered simulator drive, the locator on another drive under the same lamps (passes
across the survey's) with the true map and with the surveyed one: mean 3D error and their ratio.
"""
from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path
import tempfile
import time

import numpy as np

from vlp_ros.evaluation.metrics import format_table
from vlp_ros.pipeline.config import settings_from_params_file, settings_from_tree
from vlp_ros.pipeline.frame import Pipeline
from vlp_ros.sim.looks import apply_look, LOOKS
from vlp_ros.sim.survey_drive import (crossing_drive, exact_survey_data, record_survey_drive, survey_drive,
                                      SurveyDrive, truth_parameters)
from vlp_ros.survey.estimation import estimate_survey, SurveyData, SurveyEstimate
from vlp_ros.survey.partial_map import load_partial_map, surveyed_document
from vlp_ros.survey.recording import image_topic_of, read_survey, SurveyTopics

import yaml

FOREIGN = Path(__file__).resolve().parents[2].parent / 'shared' / 'data' / 'foreign_frames' / 'survey_drive_clean'
HEADER = ('drive / mode', 'lamps', 'RMS cm', 'max cm', 'marker RMS deg', 'NEES', 'undetermined', 'CPU s',
          'CPU / duration')
LOCATOR_HEADER = ('drive', 'frames', 'poses true map', 'mean cm true map', 'poses surveyed', 'mean cm surveyed',
                  'ratio', 'NEES surveyed')


def accuracy_row(label: str, mode: str, truth: dict[int, tuple[np.ndarray, float]], estimate: SurveyEstimate,
                 cpu: float, duration: float) -> list[str]:
    """Return one row of the survey table; ``truth`` is each free lamp's (position, marker angle) by ID."""
    errors = [estimate.lamps[i].position - truth[i][0] for i in truth if i in estimate.lamps]
    angles = [np.angle(np.exp(1j * (estimate.lamps[i].marker_angle - truth[i][1]))) for i in truth
              if i in estimate.lamps]
    nees = [e @ np.linalg.solve(estimate.lamps[i].position_covariance, e)
            for e, i in zip(errors, [i for i in truth if i in estimate.lamps])]
    distance = np.linalg.norm(errors, axis=1) if errors else np.array([np.nan])
    return [f'{label} / {mode}', f'{len(errors)}/{len(truth)}', f'{100 * np.sqrt(np.mean(distance ** 2)):.2f}',
            f'{100 * distance.max():.2f}', f'{np.degrees(np.sqrt(np.mean(np.square(angles)))):.3f}',
            f'{np.mean(nees):.2f}', str(len(estimate.undetermined)), f'{cpu:.1f}', f'{cpu / duration:.2f}']


def surveyed_both_ways(label: str, data: SurveyData, truth: dict[int, tuple[np.ndarray, float]], read_cpu: float,
                       duration: float) -> tuple[list[list[str]], SurveyEstimate]:
    """Return rows with the odometry and from images alone (the reading's CPU in both), and the first estimate."""
    rows, first = [], None
    for mode, given in (('odometry', data), ('images only', replace(data, odometry=[]))):
        started = time.process_time()
        estimate = estimate_survey(given)
        cpu = read_cpu + time.process_time() - started
        rows.append(accuracy_row(label, mode, truth, estimate, cpu, duration))
        first = first or estimate
    return rows, first


def truth_of(lamps, free: list[int]) -> dict[int, tuple[np.ndarray, float]]:
    by_id = {lamp.id: lamp for lamp in lamps}
    return {i: (by_id[i].position, by_id[i].marker_angle) for i in free}


def survey_bag(folder: Path, truth_file: Path, label: str) -> tuple[list[list[str]], Path, SurveyEstimate]:
    """Survey ``folder``/bag with ``folder``/partial.yaml; return rows, the surveyed params file and estimate."""
    partial = load_partial_map(folder / 'partial.yaml')
    started = time.process_time()
    recording = read_survey(folder / 'bag', partial, SurveyTopics(image=image_topic_of(folder / 'bag', partial, None)))
    read_cpu = time.process_time() - started
    truth = settings_from_params_file(truth_file).lamps
    rows, estimate = surveyed_both_ways(label, recording.data, truth_of(truth, recording.data.free_lamps), read_cpu,
                                        recording.duration)
    names = {lamp.id: lamp.name for lamp in partial.lamps}
    surveyed = folder / 'surveyed.yaml'
    lamps = {names[i]: lamp for i, lamp in estimate.lamps.items()}
    surveyed.write_text(yaml.safe_dump(surveyed_document(partial, lamps), sort_keys=False))
    return rows, surveyed, estimate


def locator_row(label: str, drive: SurveyDrive, surveyed: Path, seed: int) -> list[str]:
    """Return the row of the locator on a crossing drive with the true map and the surveyed one (same frames)."""
    other = crossing_drive(drive, seed)
    rng = np.random.default_rng(seed)
    true_settings = settings_from_tree(truth_parameters(drive))
    try:
        surveyed_settings = settings_from_params_file(surveyed)
    except ValueError as err:
        return [label, str(len(other.scenario.poses)), '-', '-', '-', f'not loadable: {err}', '-', '-']
    pipelines = [Pipeline(true_settings), Pipeline(surveyed_settings)]
    errors: list[list[float]] = [[], []]
    nees = []
    for index, t in enumerate(other.scenario.frame_times()):
        frame = other.scenario.render(index, rng)
        for k, pipeline in enumerate(pipelines):
            pose = pipeline.process(frame.image, frame.camera, float(t)).pose
            if pose is not None:
                errors[k].append(pose.position_error(frame.pose))
                if k == 1 and pose.covariance is not None:
                    e = pose.error_vector(frame.pose)
                    nees.append(float(e @ np.linalg.solve(pose.covariance, e)))
    means = [100 * np.mean(e) if e else np.nan for e in errors]
    return [label, str(len(other.scenario.poses)), str(len(errors[0])), f'{means[0]:.2f}', str(len(errors[1])),
            f'{means[1]:.2f}', f'{means[1] / means[0]:.2f}', f'{np.mean(nees):.1f}' if nees else '-']


def _arguments(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog='python -m vlp_ros.benchmarks.survey', description=__doc__.splitlines()[1])
    parser.add_argument('--seeds', type=int, nargs='+', default=[1], help='simulator drives to render and survey')
    parser.add_argument('--exact-seeds', type=int, nargs='*', default=[1, 2, 3],
                        help='simulator drives surveyed from exact observations')
    parser.add_argument('--looks', nargs='+', default=['clean', 'realistic'], choices=sorted(LOOKS),
                        help="the simulator's looks to render the drives in (docs/simulator.md)")
    parser.add_argument('--exact-only', action='store_true', help='no rendering: the exact rows only')
    parser.add_argument('--foreign', type=Path, default=FOREIGN, help='the foreign survey drive folder')
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = _arguments(argv)
    rows, locator_rows = [], []
    for seed in args.exact_seeds:
        drive = survey_drive(seed)
        started = time.process_time()
        data = exact_survey_data(drive, np.random.default_rng(seed + 100))
        read_cpu = time.process_time() - started
        duration = len(drive.scenario.poses) / drive.scenario.frame_rate
        rows += surveyed_both_ways(f'exact seed {seed}', data, truth_of(drive.lamps, data.free_lamps), read_cpu,
                                   duration)[0]
    if not args.exact_only:
        if (args.foreign / 'bag').exists():
            rows += survey_bag(args.foreign, args.foreign / 'truth.yaml', 'foreign survey_drive_clean')[0]
        for seed in args.seeds:
            for look in args.looks:
                drive = survey_drive(seed)
                drive = replace(drive, scenario=apply_look(drive.scenario, LOOKS[look], seed))
                label = f'sim seed {seed} {look}'
                with tempfile.TemporaryDirectory() as scratch:
                    folder = record_survey_drive(drive, Path(scratch) / 'drive', np.random.default_rng(seed))
                    bag_rows, surveyed, _ = survey_bag(folder, folder / 'truth.yaml', label)
                    rows += bag_rows
                    locator_rows.append(locator_row(label, drive, surveyed, seed + 1))
    print('Surveyed lamps against the truth (targets: RMS <= 1.0 cm, max <= 2.5 cm, marker RMS <= 0.5 deg, '
          'NEES 1.5-6, CPU <= 2 x duration; images only: x2)')
    print(format_table(rows, HEADER))
    if locator_rows:
        print('\nThe locator on another drive under the same lamps (target: mean error surveyed <= 1.5 x true map)')
        print(format_table(locator_rows, LOCATOR_HEADER))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
