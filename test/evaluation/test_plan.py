"""The deployment planner: its maps follow the geometry and the beacon, and the tool runs end to end."""
from __future__ import annotations

import re

import numpy as np
import pytest

from vlp_ros.core.pose import Pose
from vlp_ros.evaluation.floor_plan import (BeaconPlan, ceiling_lamp, Decodability, Deployment, expected_position_error,
                                           lamp_observations, MeasurementNoise, plan_floor, visible_spans)
from vlp_ros.evaluation.plan import main, preset_camera
from vlp_ros.solvers.ambiguity import DisambiguationHints, UpHint
from vlp_ros.solvers.fusion import solve_lamps

NOISE = MeasurementNoise()


def one_lamp(camera: str, ceiling: float, radius: float, room: float = 2.0) -> Deployment:
    return Deployment((room, room), (ceiling_lamp('lamp', 0, room / 2, room / 2, ceiling, radius),),
                      preset_camera(camera))


def test_tool_writes_a_png_and_a_summary(tmp_path, capsys) -> None:
    out = tmp_path / 'plan.png'
    status = main(['--room', '3', '2', '--spacing', '1.5', '--camera', '1080p-lumia', '--points', '6',
                   '--out', str(out)])
    assert status == 0
    assert out.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    printed = capsys.readouterr().out
    fix, single, blind = (float(v) for v in re.search(
        r'fix on ([\d.]+) % of the floor \(([\d.]+) % from a single lamp\); no lamp fully in view on ([\d.]+) %',
        printed).groups())
    median, p95 = (float(v) for v in re.search(r'median ([\d.]+) cm, 95th percentile ([\d.]+) cm', printed).groups())
    # Two lamps 1.5 m apart over a 3 x 2 m floor: every point is covered or not, some by one lamp only;
    # a 1080p camera places itself to about a centimetre (tests below follow its geometry).
    assert fix + blind == pytest.approx(100.0, abs=0.1) and 0.0 < single <= fix < 100.0, printed
    assert 0.1 < median <= p95 < 5.0, printed


@pytest.mark.parametrize('options, complaint', [
    (['--radius', '-0.1'], 'radius'),
    (['--lamps', '1,1', '9,1'], 'outside'),
    (['--lamps', '1;1'], 'X,Y'),
    (['--fx', '1000'], '--width'),
    (['--room', '3', 'wide'], '--room'),
])
def test_bad_options_give_one_line_and_status_2(tmp_path, capsys, options, complaint) -> None:
    out = tmp_path / 'plan.png'
    assert main([*options, '--points', '2', '--out', str(out)]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and complaint in lines[0]
    assert not out.exists()


def test_expected_error_grows_with_lamp_height() -> None:
    plans = [plan_floor(one_lamp('1080p-lumia', ceiling, 0.1), BeaconPlan(), NOISE, points=5)
             for ceiling in (1.6, 2.2, 2.8)]
    covered_by_all = np.all([np.isfinite(p.error_cm) for p in plans], axis=0)
    assert covered_by_all.sum() >= 9
    medians = [np.median(p.error_cm[covered_by_all]) for p in plans]
    assert medians[0] < medians[1] < medians[2]


def test_decodable_floor_shrinks_as_chip_rate_falls() -> None:
    deployment = one_lamp('4k-lumia', 2.0, 0.06)
    plans = [plan_floor(deployment, BeaconPlan(chip_rate=rate), NOISE, points=5) for rate in (16000, 10000, 4000)]
    for level in (Decodability.ONE_FRAME, Decodability.FEW_FRAMES):
        fractions = [p.decodable_fraction(level) for p in plans]
        assert all(a >= b for a, b in zip(fractions, fractions[1:])), (level, fractions)
        assert fractions[0] > fractions[-1], (level, fractions)


def test_a_corner_outside_every_view_has_no_fix() -> None:
    plan = plan_floor(one_lamp('1080p-lumia', 2.0, 0.1, room=6.0), BeaconPlan(chip_rate=16000), NOISE, points=5)
    assert plan.lamps_in_view[0, 0] == 0 and np.isnan(plan.error_cm[0, 0])
    assert plan.decodability[0, 0] == Decodability.NONE
    assert np.isfinite(plan.error_cm[2, 2]) and plan.decodability[2, 2] == Decodability.ONE_FRAME
    assert 0.0 < plan.coverage < 1.0


def test_several_lamps_get_the_covariance_the_full_solver_reports() -> None:
    lamps = tuple(ceiling_lamp(f'lamp_{k}', k, x, 1.0, 2.2, 0.075) for k, x in enumerate((0.5, 1.5)))
    deployment = Deployment((2.0, 2.0), lamps, preset_camera('1080p-wide'))
    pose = Pose(deployment.camera_rotation, [0.8, 0.7, 0.0])
    spans = visible_spans(deployment, pose, NOISE)
    assert len(spans) == 2
    hints = DisambiguationHints([UpHint(pose.up_in_camera(), NOISE.imu_tolerance, NOISE.imu_sigma)])
    solved = solve_lamps(lamp_observations(deployment, pose, spans, NOISE), deployment.camera, hints).pose
    assert expected_position_error(deployment, pose, spans, NOISE) == pytest.approx(
        np.sqrt(np.trace(solved.covariance[:3, :3])), rel=1e-6)


def test_without_an_imu_one_lamp_alone_gives_no_fix() -> None:
    plan = plan_floor(one_lamp('1080p-lumia', 2.0, 0.1), BeaconPlan(), MeasurementNoise(imu_sigma=None), points=5)
    assert np.any(plan.lamps_in_view == 1)
    assert np.all(np.isnan(plan.error_cm))
