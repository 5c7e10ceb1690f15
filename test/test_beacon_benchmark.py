"""Smoke test: the beacon benchmark runs end to end on the simulator and prints its tables and targets."""
import pytest

from vlp_ros.benchmarks import beacon


def test_benchmark_prints_tables_targets_and_times(capsys: pytest.CaptureFixture[str]) -> None:
    beacon.main(['--trials', '20', '--seed', '3'])
    out = capsys.readouterr().out
    for section in ('packet mode, one frame', 'across frames (tracker', 'tone mode, one frame', '== time ==',
                    '== targets =='):
        assert section in out
    assert 'read / copy' in out
    # The tracker table holds what a noiseless decoder could do with the same frames.
    assert 'bound %' in out.split('across frames (tracker')[1].split('== tone')[0]
    targets = out.split('== targets ==')[1]
    assert targets.count('PASS') + targets.count('FAIL') == 11
    # The tone target with the camera set as the locator advises, and on every draw.
    tone = out.split('tone mode, one frame')[1]
    assert 'TARGET 3-4, advised' in tone and '3-4 periods, all draws' in tone
    # Demosaiced Bayer frames (rows mixed with their neighbours) have a row of their own.
    assert 'Bayer RGGB, demosaiced' in out.split('tone mode, one frame')[1]


def test_benchmark_rejects_no_trials() -> None:
    with pytest.raises(SystemExit):
        beacon.main(['--trials', '0'])


def test_coverage_bound_needs_every_bit_in_view_across_frames():
    lamp = beacon.MAP_IDS[3]
    # A whole packet in view: one frame suffices.
    assert beacon.ideal_frames(lamp, [(5.3, 29.3)], 0.01, 0.5) == 1
    # The same half packet every frame never shows the other half's bits.
    assert beacon.ideal_frames(lamp, [(2.0, 14.0)] * 5, 0.01, 0.5) == 6
    # Two halves that together show every bit: certain once both are seen.
    assert beacon.ideal_frames(lamp, [(2.0, 14.0), (2.0, 14.0), (13.0, 25.0)], 0.01, 0.5) == 3
