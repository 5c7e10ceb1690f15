"""The survey benchmark's quick rows (exact observations): the estimation within the targets on a simulated drive."""
from __future__ import annotations

from printed_tables import printed_tables
import pytest

from vlp_ros.benchmarks import survey

pytestmark = pytest.mark.simulation


def test_the_exact_rows_of_a_drive_are_printed_within_the_targets(capsys) -> None:
    assert survey.main(['--exact-only', '--exact-seeds', '2']) == 0
    [rows] = printed_tables(capsys.readouterr().out)
    with_odometry = rows['exact seed 2 / odometry']
    assert with_odometry['lamps'] == '9/9' and 'exact seed 2 / images only' in rows
    assert float(with_odometry['RMS cm']) <= 1.0 and float(with_odometry['max cm']) <= 2.5
    assert float(with_odometry['marker RMS deg']) <= 0.5
