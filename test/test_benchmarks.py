"""Smoke tests: the accuracy and pipeline speed benchmarks run end to end and print their tables."""
from __future__ import annotations

import numpy as np
import pytest

from vlp_ros.benchmarks import accuracy, pipeline_speed


def test_accuracy_prints_every_setup_and_solver(capsys: pytest.CaptureFixture[str]) -> None:
    assert accuracy.main(['--quick', '--frames', '2']) == 0
    out = capsys.readouterr().out
    for setup in ('paper 4K 2 m', 'paper 4K 1.5 m', 'paper 1080p 2 m', 'paper 1080p 1.5 m', 'robot'):
        for solver in accuracy.SOLVERS:
            assert f'{setup} {solver} ' in out
    for section in ('Targets', 'Why frames had no pose', 'Wrong fixes:', 'published (Zhang et al. 2017)'):
        assert section in out


def test_accuracy_rejects_zero_frames() -> None:
    with pytest.raises(SystemExit):
        accuracy.main(['--quick', '--frames', '0'])


def test_pipeline_speed_prints_each_case_with_its_ratio(capsys: pytest.CaptureFixture[str]) -> None:
    pipeline_speed.main(['--poses', '1', '--repeats', '1'])
    out = capsys.readouterr().out
    for case in ('paper 1080p, 1 lamp', 'paper 4k, 1 lamp', 'robot 1080p, 2-3 lamps'):
        line = next(line for line in out.splitlines() if line.startswith(case))
        ratio = float(line.split()[-3])
        assert ratio > 0.0


def test_accuracy_drives_the_robot_as_fast_as_asked() -> None:
    drive = accuracy.Drive(speed=1.0, turn_rate=0.5)
    rows = [setup for setup in accuracy.look_setups(True, 0, drive) if setup.family == 'robot drive']
    assert rows
    for setup in rows:
        scenario = setup.scenario
        positions = np.array([pose.position for pose in scenario.poses])
        speeds = np.linalg.norm(np.diff(positions, axis=0), axis=1) * scenario.frame_rate
        assert np.median(speeds) == pytest.approx(1.0, rel=0.05)


def test_accuracy_rejects_a_drive_that_does_not_move() -> None:
    with pytest.raises(SystemExit):
        accuracy.main(['--quick', '--drive-speed', '0'])
