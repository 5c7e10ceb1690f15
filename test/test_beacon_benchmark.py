"""Smoke test: the beacon benchmark runs end to end on the simulator and prints its tables and targets."""
import pytest

from vlp_ros.benchmarks import beacon


def test_benchmark_prints_tables_targets_and_times(capsys: pytest.CaptureFixture[str]) -> None:
    beacon.main(['--trials', '20', '--seed', '3'])
    out = capsys.readouterr().out
    for section in ('packet mode, one frame', 'across frames (tracker', 'tone mode, one frame', '== time ==',
                    '== targets =='):
        assert section in out
    assert 'decode / copy' in out
    targets = out.split('== targets ==')[1]
    assert targets.count('PASS') + targets.count('FAIL') == 7


def test_benchmark_rejects_no_trials() -> None:
    with pytest.raises(SystemExit):
        beacon.main(['--trials', '0'])
