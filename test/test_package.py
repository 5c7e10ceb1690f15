"""The package as ROS 2 sees it: ament index, executables, params files, graph, signals."""
from __future__ import annotations

import os

from conftest import ROOT, spin_until
import pytest

from vlp_ros.nodes.dds_environment import installed_executable

pytestmark = pytest.mark.dds

EXECUTABLES = ['locator', 'replay']


def test_ament_index_registers_package() -> None:
    from ament_index_python.packages import get_package_prefix, get_package_share_directory
    prefix = get_package_prefix('vlp_ros')
    assert os.path.isfile(os.path.join(prefix, 'share', 'ament_index', 'resource_index', 'packages', 'vlp_ros'))
    assert os.path.isfile(os.path.join(get_package_share_directory('vlp_ros'), 'package.xml'))


@pytest.mark.parametrize('name', EXECUTABLES)
def test_ros2_run_resolves_installed_executable(name: str) -> None:
    path = installed_executable(name)
    assert path.is_file() and os.access(path, os.X_OK)
    assert path.parent == ROOT / 'install' / 'vlp_ros' / 'lib' / 'vlp_ros'


def _write_params(tmp_path, node_name: str, frame: str):
    path = tmp_path / 'params.yaml'
    path.write_text(f'{node_name}:\n  ros__parameters:\n    map_frame: {frame}\n'
                    '    leds: {names: [a], a: {id: 1, position: [0, 0, 2], radius: 0.05}}\n')
    return path


def _remote_parameter(test_node, node_name: str, name: str):
    from rcl_interfaces.srv import GetParameters
    client = test_node.create_client(GetParameters, f'/{node_name}/get_parameters')
    # Waits end when their condition holds: generous ones cost nothing on a fast machine.
    assert client.wait_for_service(timeout_sec=60.0), f'{node_name} offers no parameter service'
    future = client.call_async(GetParameters.Request(names=[name]))
    assert spin_until(test_node, future.done, 30.0)
    return future.result().values[0]


def test_locator_loads_params_file_and_joins_graph(start_process, test_node, tmp_path) -> None:
    params = _write_params(tmp_path, 'vlp_locator', 'building_7')
    locator = start_process('locator', '--ros-args', '--params-file', params)

    def visible() -> bool:
        return ('vlp_locator', '/') in test_node.get_node_names_and_namespaces()

    assert spin_until(test_node, visible, 60.0), locator.output()
    assert _remote_parameter(test_node, 'vlp_locator', 'map_frame').string_value == 'building_7'
    assert locator.interrupt() == 0, locator.output()
    assert 'Traceback' not in locator.output()


def test_replay_joins_graph_and_exits_cleanly_on_sigint(start_process, test_node) -> None:
    bag = ROOT.parent / 'shared' / 'data' / 'rosbag2' / 'talker_sqlite3'
    replay = start_process('replay', bag, '--loop', '--ros-args', '-r', '__node:=vlp_replay_sigint')

    def visible() -> bool:
        return ('vlp_replay_sigint', '/') in test_node.get_node_names_and_namespaces()

    assert spin_until(test_node, visible, 60.0), replay.output()
    assert replay.interrupt() == 0, replay.output()
    assert 'Traceback' not in replay.output()
