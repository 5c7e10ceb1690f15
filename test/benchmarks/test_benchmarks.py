"""The accuracy and pipeline speed benchmarks on small runs: their printed rows hold what the pipeline must do."""
from __future__ import annotations

import numpy as np
from printed_tables import printed_tables
import pytest

from vlp_ros.benchmarks import accuracy, pipeline_speed

# The accuracy targets (mean error, cm; mean orientation error, deg) per setup of the perspective solver;
# the 1080p photos, which have none of their own, within twice the 4K pixel's error.
ACCURACY_BOUNDS = {'paper 4K 2 m': (0.5, 0.15), 'paper 4K 1.5 m': (0.4, 0.15), 'paper 1080p 2 m': (2.0, 0.5),
                   'paper 1080p 1.5 m': (2.0, 0.5), 'robot': (1.0, 0.5)}


@pytest.mark.simulation
def test_accuracy_locates_every_quick_frame_within_the_targets_and_never_wrongly(capsys) -> None:
    frames = 2
    assert accuracy.main(['--quick', '--frames', str(frames)]) == 0
    out = capsys.readouterr().out
    tables = printed_tables(out)
    results = tables[0]

    def table_with(column: str) -> dict:
        return next((t for t in tables if t and column in next(iter(t.values()))), {})

    availability, row_targets, optics = table_with('NEES > 99.9 %'), table_with('target'), table_with('hold')
    assert {f'{setup} {solver}' for setup in ACCURACY_BOUNDS for solver in accuracy.SOLVERS} <= set(results)
    for setup, (mean_cm, orientation_deg) in ACCURACY_BOUNDS.items():
        row = results[f'{setup} perspective']
        assert int(row['poses']) == frames and int(row['wrong fixes']) == 0, (setup, row)
        assert float(row['mean cm']) < mean_cm and float(row['orient. mean deg']) < orientation_deg, (setup, row)
    # The perspective solver never publishes a wrong fix, nor a pose beyond its covariance's 99.9 % bound,
    # under any look or robot case (the paper's solver is the published baseline, wrong fixes and all).
    assert all(int(row['wrong fixes']) == 0 for label, row in results.items() if label.endswith('perspective'))
    assert availability and all(int(row['wrong']) == 0 and int(row['NEES > 99.9 %']) == 0
                                for row in availability.values()), availability
    assert 'published (Zhang et al. 2017)' in out and row_targets
    # Every look row states its mean error, p95, NEES and share beyond the bound, its targets and whether they
    # hold, which follows from what it measured.
    looks = {label for label in availability if ' look ' in label}
    assert looks and set(optics) == looks, optics
    for label, row in optics.items():
        if row['mean NEES'] != '-' and not 3.0 <= float(row['mean NEES']) <= 10.0:
            assert row['hold'].startswith('NO'), (label, row)


def test_accuracy_rejects_zero_frames() -> None:
    with pytest.raises(SystemExit):
        accuracy.main(['--quick', '--frames', '0'])


@pytest.mark.simulation
def test_pipeline_speed_locates_the_frame_of_each_case_it_times(capsys: pytest.CaptureFixture[str]) -> None:
    pipeline_speed.main(['--quick'])
    rows = printed_tables(capsys.readouterr().out)[0]
    # The times are judged by full runs; a case whose frame has no pose would time a pipeline that gave up.
    assert set(rows) == set(pipeline_speed.SCENES)
    assert all(row['posed'] == '1/1' and row['look'] == 'clean' for row in rows.values()), rows


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
