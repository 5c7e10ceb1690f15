"""The covariance honesty benchmark runs end to end and prints both tables."""
from __future__ import annotations

import numpy as np
import pytest

from vlp_ros.benchmarks import covariance_honesty


def test_prints_detection_and_pose_tables_for_every_setup(capsys: pytest.CaptureFixture[str]) -> None:
    assert covariance_honesty.main(['--frames', '1']) == 0
    out = capsys.readouterr().out
    assert 'rim chi2 (5)' in out and 'NEES mean' in out
    for setup in ('paper 4K 2 m', 'paper 4K 1.5 m', 'robot (prior)'):
        assert out.count(f'{setup} clean') == 2


def test_measures_each_look_asked_for_with_ids_from_the_truth(capsys: pytest.CaptureFixture[str]) -> None:
    assert covariance_honesty.main(['--frames', '1', '--look', 'falloff', '--ids-from-truth']) == 0
    out = capsys.readouterr().out
    assert 'IDs from the truth' in out and out.count('robot (prior) falloff') == 2 and 'clean' not in out


def test_absorbed_chi_square_keeps_only_what_the_jacobian_spans() -> None:
    jacobian = np.array([[1.0, 0.0], [0.0, 2.0], [0.0, 0.0], [0.0, 0.0]])
    residuals = np.array([1.0, 2.0, 3.0, 4.0])
    assert covariance_honesty.absorbed_chi_square(residuals, jacobian) == pytest.approx(5.0)


def test_rejects_zero_frames() -> None:
    with pytest.raises(SystemExit):
        covariance_honesty.main(['--frames', '0'])
