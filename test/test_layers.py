"""
The package's layers import one way, and the runtime stands alone: without ROS below the nodes, without tools.

A module imports from its own subpackage and the layers below it only, never from a higher layer nor from
another subpackage of its own layer. The runtime is everything up to the nodes; the simulator, evaluation and
benchmarks are tools above it (each may use those below). The order is read statically, every import
statement (in functions too), so a violation is named by file and line without importing anything.
"""
from __future__ import annotations

import json
import subprocess
import sys

from source_imports import imports_in, module_name, python_files, ROOT, SourceImport

LAYERS = (
    ('compiled',),
    ('core',),
    ('images', 'detection', 'beacon'),
    ('bags', 'solvers'),
    ('pipeline',),
    ('survey',),
    ('nodes',),
    ('sim',),
    ('evaluation',),
    ('benchmarks',),
)
LAYER_OF = {subpackage: level for level, subpackages in enumerate(LAYERS) for subpackage in subpackages}
# Benchmarks of the nodes themselves: the cost of the locator's visualization messages (it builds
# them), the locator's start-up time (it watches for the locator's subscription over DDS) and the
# camera rate it keeps up with (it streams frames into the locator over DDS).
NEEDS_ROS = {'vlp_ros.benchmarks.visualization_cost', 'vlp_ros.benchmarks.startup', 'vlp_ros.benchmarks.camera_rate'}


def subpackage(module: str) -> str | None:
    """Return the subpackage of vlp_ros that ``module`` is in, None for vlp_ros itself."""
    parts = module.split('.')
    return parts[1] if len(parts) > 1 else None


def breaks_the_order(found: SourceImport) -> bool:
    """Return whether ``found`` imports a vlp_ros layer above its file's, or a sibling of the same layer."""
    if found.top != 'vlp_ros' or (target := subpackage(found.name)) is None:
        return False
    source = subpackage(module_name(found.path))
    # vlp_ros's own __init__ lies beneath every subpackage.
    return source is None or (source != target and LAYER_OF[target] >= LAYER_OF[source])


def test_every_subpackage_has_a_layer() -> None:
    modules = {module_name(path) for path in python_files('vlp_ros')}
    subpackages = {subpackage(module) for module in modules} - {None}
    assert subpackages == set(LAYER_OF), f'place {subpackages - set(LAYER_OF)} in LAYERS'


def test_no_module_imports_a_higher_layer_or_a_sibling() -> None:
    found = [str(found) for path in python_files('vlp_ros') for found in imports_in(path) if breaks_the_order(found)]
    assert found == [], 'imports against the layers (' + ' < '.join('/'.join(layer) for layer in LAYERS) + '):\n' \
        + '\n'.join(found)


def modules_loaded(modules: list[str], packages: tuple[str, ...]) -> list[str]:
    """Return the modules of ``packages`` that importing ``modules`` in a fresh interpreter loads, sorted."""
    code = (f'import importlib, json, sys\n'
            f'for name in {modules!r}:\n'
            f'    importlib.import_module(name)\n'
            f'packages = {list(packages)!r}\n'
            f'print(json.dumps(sorted(m for m in sys.modules if any(m == p or m.startswith(p + ".") '
            f'for p in packages))))\n')
    result = subprocess.run([sys.executable, '-c', code], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout.splitlines()[-1])


def test_no_module_outside_the_nodes_loads_rclpy() -> None:
    # Whatever it imports, also through libraries: the core and the tools run on plain Python.
    modules = sorted(module_name(path) for path in python_files('vlp_ros'))
    ros_free = [module for module in modules if subpackage(module) != 'nodes' and module not in NEEDS_ROS]
    script = ('import importlib, sys\n'
              f'for name in {ros_free!r}:\n'
              '    importlib.import_module(name)\n'
              '    assert "rclpy" not in sys.modules, f"{name} loads rclpy"\n')
    result = subprocess.run([sys.executable, '-c', script], cwd=ROOT, capture_output=True, text=True, timeout=240)
    assert result.returncode == 0, result.stderr


def test_the_locator_loads_no_heavy_library_it_does_not_need() -> None:
    # Each costs start-up time and memory on the robot's computer; the chi-square and F tails come from
    # scipy.special.
    heavy = ('scipy.stats', 'scipy.optimize', 'matplotlib', 'gtsam')
    assert modules_loaded(['vlp_ros.nodes.locator'], heavy) == []
