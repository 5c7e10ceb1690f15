"""
What the package declares and installs: package.xml's dependencies against the imports, and its licence.

package.xml is what rosdep installs from, so every third-party import of the package (its modules and
launch files: exec_depend) and of its tests (test_depend) must be declared there, and nothing else.
"""
from __future__ import annotations

import ast
from importlib.metadata import metadata
from pathlib import Path

from ament_index_python.packages import get_package_share_directory
from catkin_pkg.package import parse_package
from source_imports import imports_in, python_files, ROOT, SourceImport, third_party

# rosdep keys of the Python libraries imported; any other import is a ROS package of the same name.
PYTHON_KEYS = {
    # backports.zstd: rosbags installs it (before Python 3.14, which has compression.zstd) and reads bags with it.
    'backports': 'python3-rosbags-pip',
    'catkin_pkg': 'python3-catkin-pkg',
    'cv2': 'python3-opencv',
    'matplotlib': 'python3-matplotlib',
    'numba': 'python3-numba',
    'numpy': 'python3-numpy',
    'pytest': 'python3-pytest',
    'rosbags': 'python3-rosbags-pip',
    'scipy': 'python3-scipy',
    'simplejpeg': 'python3-simplejpeg-pip',
    'tqdm': 'python3-tqdm',
    'yaml': 'python3-yaml',
}
PACKAGE = parse_package(str(ROOT))
# The tests' own helper modules, imported by name from test/.
TEST_HELPERS = frozenset(path.stem for path in (ROOT / 'test').rglob('*.py'))


def needed_keys(found: list[SourceImport]) -> dict[str, str]:
    """Return each rosdep key that ``found`` needs, with the first import that needs it."""
    keys: dict[str, str] = {}
    for each in found:
        keys.setdefault(PYTHON_KEYS.get(each.top, each.top), str(each))
    return keys


def imports_of_the_package() -> list[SourceImport]:
    return [found for path in python_files('vlp_ros', 'launch') for found in imports_in(path) if third_party(found)]


def imports_of_the_tests() -> list[SourceImport]:
    return [found for path in python_files('test') for found in imports_in(path)
            if third_party(found, TEST_HELPERS)]


def declared(*kinds: str) -> set[str]:
    return {dependency.name for kind in kinds for dependency in getattr(PACKAGE, kind)}


def test_package_xml_is_valid() -> None:
    PACKAGE.validate()
    assert PACKAGE.name == 'vlp_ros'


def test_every_import_of_the_package_is_an_exec_dependency() -> None:
    missing = {key: where for key, where in needed_keys(imports_of_the_package()).items()
               if key not in declared('exec_depends')}
    assert missing == {}, 'add to package.xml as exec_depend:\n' + '\n'.join(f'{k} ({w})' for k, w in missing.items())


def test_every_import_of_the_tests_is_a_dependency() -> None:
    missing = {key: where for key, where in needed_keys(imports_of_the_tests()).items()
               if key not in declared('exec_depends', 'test_depends')}
    assert missing == {}, 'add to package.xml as test_depend:\n' + '\n'.join(f'{k} ({w})' for k, w in missing.items())


def test_every_dependency_is_imported_where_it_is_declared() -> None:
    assert declared('exec_depends') - set(needed_keys(imports_of_the_package())) == set()
    assert declared('test_depends') - set(needed_keys(imports_of_the_tests())) == set()
    assert declared('exec_depends') & declared('test_depends') == set()


def setup_keyword(name: str) -> object:
    """Return the literal value of keyword ``name`` in setup.py's ``setup()`` call."""
    calls = [node for node in ast.walk(ast.parse((ROOT / 'setup.py').read_text()))
             if isinstance(node, ast.Call) and getattr(node.func, 'id', None) == 'setup']
    return ast.literal_eval(next(k.value for k in calls[0].keywords if k.arg == name))


def test_the_licence_is_declared_alike_and_installed() -> None:
    assert [str(licence) for licence in PACKAGE.licenses] == [setup_keyword('license')] == ['Apache-2.0']
    assert [licence.file for licence in PACKAGE.licenses] == ['LICENSE']
    text = (ROOT / 'LICENSE').read_text()
    assert 'Apache License' in text and 'Version 2.0, January 2004' in text
    # As built by colcon, which the nodes and `ros2 launch` run from.
    assert metadata('vlp_ros')['License'] == 'Apache-2.0'
    assert (Path(get_package_share_directory('vlp_ros')) / 'LICENSE').read_text() == text
