"""
launch/vlp.launch.py starts what the package installs, with the arguments the README gives it.

The launch and launch_ros packages come only with a ROS installation (no PyPI wheels), so the file is read
as source: its actions and substitutions are resolved here as ``ros2 launch`` would, from the installed package.
"""
from __future__ import annotations

import ast
from dataclasses import dataclass, field
from importlib.metadata import distribution
import os
from pathlib import Path
import re

from ament_index_python.packages import get_package_share_directory
from source_imports import ROOT

from vlp_ros.nodes.dds_environment import installed_executable
from vlp_ros.nodes.replay import command_line_parser

import yaml

LAUNCH_FILE = ROOT / 'launch' / 'vlp.launch.py'
BAG = '/data/recording'


@dataclass(frozen=True)
class LaunchCall:
    """A launch action or substitution as the file builds it: its class's name and arguments."""

    kind: str
    args: tuple = ()
    keywords: dict = field(default_factory=dict)


def literal(node: ast.expr, names: dict[str, ast.expr]) -> object:
    """Return the value of ``node``: launch classes as LaunchCall, variables by what they were assigned."""
    if isinstance(node, ast.Name):
        return literal(names[node.id], names)
    if isinstance(node, ast.List):
        return [literal(element, names) for element in node.elts]
    if isinstance(node, ast.Call):
        return LaunchCall(node.func.id, tuple(literal(a, names) for a in node.args),
                          {k.arg: literal(k.value, names) for k in node.keywords})
    return ast.literal_eval(node)


def launch_entities() -> list[LaunchCall]:
    """Return what ``generate_launch_description`` puts in its LaunchDescription."""
    function = next(node for node in ast.parse(LAUNCH_FILE.read_text()).body
                    if isinstance(node, ast.FunctionDef) and node.name == 'generate_launch_description')
    names = {target.id: node.value for node in function.body if isinstance(node, ast.Assign)
             for target in node.targets}
    returned = next(node.value for node in function.body if isinstance(node, ast.Return))
    description = literal(returned, names)
    assert description.kind == 'LaunchDescription'
    return description.args[0]


ENTITIES = launch_entities()
ARGUMENTS = {entity.args[0]: entity.keywords.get('default_value') for entity in ENTITIES
             if entity.kind == 'DeclareLaunchArgument'}
NODES = {entity.keywords['executable']: entity for entity in ENTITIES if entity.kind == 'Node'}


def resolved(value: object, given: dict[str, str]) -> object:
    """Return ``value`` with its substitutions made, for the launch arguments ``given`` and the defaults."""
    if isinstance(value, list):
        return [resolved(element, given) for element in value]
    if not isinstance(value, LaunchCall):
        return value
    if value.kind == 'LaunchConfiguration':
        name = value.args[0]
        return given[name] if name in given else resolved(ARGUMENTS[name], given)
    if value.kind == 'FindPackageShare':
        return get_package_share_directory(value.args[0])
    if value.kind == 'PathJoinSubstitution':
        return os.path.join(*resolved(value.args[0], given))
    raise AssertionError(f'no resolution for {value.kind}')


def test_it_starts_the_installed_executables_of_the_package() -> None:
    scripts = {entry.name for entry in distribution('vlp_ros').entry_points if entry.group == 'console_scripts'}
    assert set(NODES) == {'locator', 'replay'}
    for executable, node in NODES.items():
        assert node.keywords['package'] == 'vlp_ros'
        assert executable in scripts
        assert os.access(installed_executable(executable), os.X_OK)


def test_the_default_params_file_is_installed_and_names_the_launched_locator() -> None:
    (params,) = resolved(NODES['locator'].keywords['parameters'], {'bag': BAG})
    installed = Path(params)
    source = ROOT / installed.relative_to(get_package_share_directory('vlp_ros'))
    assert source.parent == ROOT / 'config'
    assert installed.read_text() == source.read_text()
    # A params file applies to the nodes it names: under any other name the locator would start unconfigured.
    assert NODES['locator'].keywords['name'] in yaml.safe_load(source.read_text())


def test_replay_accepts_the_arguments_it_is_given() -> None:
    arguments = command_line_parser().parse_args(resolved(NODES['replay'].keywords['arguments'], {'bag': BAG}))
    assert arguments.bag == BAG
    assert arguments.rate == float(ARGUMENTS['rate'])


def test_the_docs_launch_it_with_its_arguments() -> None:
    commands = re.findall(r'ros2 launch vlp_ros vlp\.launch\.py(.*)', (ROOT / 'docs' / 'nodes.md').read_text())
    assert commands, 'docs/nodes.md shows no launch command'
    required = {name for name, default in ARGUMENTS.items() if default is None}
    for command in commands:
        given = set(re.findall(r'(\w+):=', command))
        assert given <= set(ARGUMENTS), f'{given - set(ARGUMENTS)} are no arguments of the launch file'
        assert required <= given, f'the README leaves out {required - given}'
