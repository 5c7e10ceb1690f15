"""config/robot_localization.example.yaml fuses the locator's topic as robot_localization expects."""
from __future__ import annotations

from conftest import ROOT
import yaml

# robot_localization's 15-state order: x y z, roll pitch yaw, velocities, angular velocities, accelerations.
X, Y, YAW, VX, VY, VYAW = 0, 1, 5, 6, 7, 11


def _filters() -> dict:
    document = yaml.safe_load((ROOT / 'config' / 'robot_localization.example.yaml').read_text())
    return {name: section['ros__parameters'] for name, section in document.items()}


def test_map_filter_fuses_vlp_poses_with_wheel_odometry() -> None:
    params = _filters()['ekf_filter_node_map']
    assert params['world_frame'] == params['map_frame'] == 'map'
    assert params['pose0'] == 'vlp/pose_with_covariance'
    fused = [k for k, on in enumerate(params['pose0_config']) if on]
    assert len(params['pose0_config']) == 15 and fused == [X, Y, YAW]
    assert [k for k, on in enumerate(params['odom0_config']) if on] == [VX, VY, VYAW]
    assert params['two_d_mode'] and params['smooth_lagged_data'] and params['history_length'] >= 0.5
    assert not params['pose0_differential'] and not params['pose0_relative']
    assert params['pose0_rejection_threshold'] > 3.0 and params['pose0_queue_size'] >= 1
    covariance = params['initial_estimate_covariance']
    assert len(covariance) == 225 and covariance[X * 16] >= 1.0 and covariance[YAW * 16] >= 1.0


def test_odom_filter_never_sees_the_absolute_fixes() -> None:
    params = _filters()['ekf_filter_node_odom']
    assert params['world_frame'] == params['odom_frame'] == 'odom'
    assert not any(key.startswith('pose') for key in params)
