"""The beacon benchmark on a small run: its printed rows and targets hold what the decoder must do."""
import re

import pytest

from vlp_ros.benchmarks import beacon

# A single-frame row: label, trials, correct %, unmapped recognised %, wrong.
FRAME_ROW = re.compile(r'^(?P<label>\S.*?)\s+(?P<trials>\d+)\s+(?P<correct>[\d.]+)\s+[\d.]+\s+(?P<wrong>\d+)$')
# A tracker row: label, tracks, certain within 5 frames %, bound % (half / any), median frames, unmapped %, wrong.
TRACK_ROW = re.compile(r'^(?P<label>\S.*?)\s+(?P<tracks>\d+)\s+(?P<within>[\d.]+)\s+[\d.]+ / [\d.]+\s+\S+\s+[\d.]+'
                       r'\s+(?P<wrong>\d+)$')
WRONG_IDS = re.compile(r'^(PASS|FAIL)  wrong IDs, (packet|tone): (\d+) in (\d+) ')


@pytest.mark.simulation
def test_a_small_run_identifies_the_target_lamps_and_never_a_wrong_one(capsys: pytest.CaptureFixture[str]) -> None:
    beacon.main(['--trials', '20', '--seed', '3'])
    out = capsys.readouterr().out
    frame_rows = [m for line in out.splitlines() if (m := FRAME_ROW.match(line))]
    track_rows = [m for line in out.splitlines() if (m := TRACK_ROW.match(line))]
    # Every condition of both modes was drawn, and no lamp was given an ID other than its own.
    assert len(frame_rows) >= 40 and len(track_rows) == len(beacon.TRACK_SPANS) * len(beacon.TRACK_PRIORS)
    assert all(int(m['wrong']) == 0 for m in frame_rows + track_rows), out
    wrong_ids = {m[2]: (int(m[3]), int(m[4])) for line in out.splitlines() if (m := WRONG_IDS.match(line))}
    assert set(wrong_ids) == {'packet', 'tone'}
    assert all(wrong == 0 and frames >= 20 for wrong, frames in wrong_ids.values()), wrong_ids
    # Under the targets' conditions (packet: 1.3 packets in view, 4 rows per chip, depth 0.5; tone: 3-4
    # periods) every lamp is identified on its frame; the tracker makes every packet lamp certain in 5 frames.
    by_label = {m['label']: m for m in frame_rows}
    for target in ('TARGET span>=1.3 rpc>=4 d>=0.5', '3-4 periods, all draws', 'TARGET 3-4, advised'):
        assert float(by_label[target]['correct']) == 100.0, by_label[target].group(0)
    tracked = {m['label']: float(m['within']) for m in track_rows}
    assert tracked['0.5-1.3'] == tracked['0.5-1.3, map trusted'] == 100.0, tracked
    # Each target but the reading's time (a speed, judged by full runs) is met.
    targets = out.split('== targets ==')[1].strip().splitlines()
    assert [line for line in targets if line.startswith('FAIL') and 'time per lamp' not in line] == []
    assert len([line for line in targets if line.startswith('PASS')]) >= 9, targets


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
