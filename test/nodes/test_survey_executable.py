"""
The installed ``survey`` executable on a recorded bag: the independent renderer's survey drive.

See foreign_frames/README.md.

Its partial map leaves one listed lamp out (seen, so reported as unlisted with its count) and lists one
lamp the drive never passes (so the exit status is 1 and that lamp is named). Every other lamp is
surveyed to the targets and the written file is loaded by the locator's own parameter reader.
"""
from __future__ import annotations

from pathlib import Path
import subprocess

from conftest import SHARED_DATA
import numpy as np
import pytest

from vlp_ros.nodes.dds_environment import installed_executable
from vlp_ros.pipeline.config import settings_from_params_file, settings_from_tree

import yaml

pytestmark = pytest.mark.dds

DRIVE = SHARED_DATA / 'foreign_frames' / 'survey_drive_clean'
UNLISTED, ABSENT = 's11', 's12'


def run_survey(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([str(installed_executable('survey')), *map(str, args)], capture_output=True, text=True,
                          timeout=900)


def partial_with_a_lamp_left_out_and_one_never_seen(tmp_path: Path) -> tuple[Path, int]:
    document = yaml.safe_load((DRIVE / 'partial.yaml').read_text())
    leds = document['vlp_locator']['ros__parameters']['leds']
    unlisted_id = leds.pop(UNLISTED)['id']
    leds['names'] = [n for n in leds['names'] if n != UNLISTED] + [ABSENT]
    leds[ABSENT] = {'id': 200, 'radius': 0.075, 'marker_distance': 0.0675}
    path = tmp_path / 'partial.yaml'
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path, unlisted_id


@pytest.mark.skipif(not DRIVE.exists(), reason='the shared foreign frames are not here')
def test_survey_maps_the_recorded_drive_names_what_it_cannot_and_reports_unlisted_lamps(tmp_path: Path) -> None:
    partial, unlisted_id = partial_with_a_lamp_left_out_and_one_never_seen(tmp_path)
    out, report = tmp_path / 'surveyed.yaml', tmp_path / 'report'
    result = run_survey(DRIVE / 'bag', '--params', partial, '--out', out, '--report', report)
    assert result.returncode == 1, result.stdout + result.stderr
    errors = [line for line in result.stderr.splitlines() if 'error' in line]
    assert len(errors) == 1 and f'lamp {ABSENT} (ID 200)' in errors[0], result.stderr
    assert f'ID {unlisted_id} in ' in result.stdout, result.stdout
    # Nothing is written for the lamp never seen; without it the file is a map the locator loads.
    document = yaml.safe_load(out.read_text())
    tree = document['vlp_locator']['ros__parameters']
    assert 'position' not in tree['leds'][ABSENT]
    del tree['leds'][ABSENT]
    tree['leds']['names'].remove(ABSENT)
    surveyed = settings_from_tree(tree)
    truth = settings_from_params_file(DRIVE / 'truth.yaml')
    errors, angles = [], []
    for lamp in surveyed.lamps:
        true = truth.lamps.get(lamp.id)
        errors.append(np.linalg.norm(lamp.position - true.position))
        angles.append(np.angle(np.exp(1j * (lamp.marker_angle - true.marker_angle))))
        # Anchors exact (zero sigmas), surveyed lamps with the sigmas of their estimate.
        assert np.all(lamp.position_sigma == 0.0) == (lamp.name in ('s2', 's4', 's9')), lamp.name
    assert np.sqrt(np.mean(np.square(errors))) <= 0.01 and max(errors) <= 0.025, errors
    assert np.degrees(np.sqrt(np.mean(np.square(angles)))) <= 0.5, np.degrees(angles)
    assert {p.name for p in report.iterdir()} == {'plan.png', 'lamps.md', 'lamps.csv', 'residuals.csv'}
    assert 's7 | 47 | surveyed' in (report / 'lamps.md').read_text()


def test_a_bad_params_file_stops_survey_with_one_line_naming_the_parameter(tmp_path: Path) -> None:
    params = tmp_path / 'partial.yaml'
    leds = {'names': ['a', 'b', 'c'],
            'a': {'id': 1, 'radius': 0.075, 'position': [0.0, 0.0, 2.6]},
            'b': {'id': 2, 'radius': 0.075, 'position': [1.2, 0.0, 2.6], 'position_sigma': [0.001, -0.001, 0.0]},
            'c': {'id': 3, 'radius': 0.075}}
    params.write_text(yaml.safe_dump({'vlp_locator': {'ros__parameters': {'leds': leds}}}))
    result = run_survey(tmp_path / 'no_bag', '--params', params, '--out', tmp_path / 'out.yaml')
    assert result.returncode == 2
    assert result.stderr.strip().count('\n') == 0 and 'leds.b.position_sigma' in result.stderr, result.stderr
    assert not (tmp_path / 'out.yaml').exists()
