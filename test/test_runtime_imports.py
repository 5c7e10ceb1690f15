"""The runtime stands alone (no simulator, evaluation or benchmark code), and the simulator needs no evaluation."""
from __future__ import annotations

import json
from pathlib import Path
import subprocess
import sys

ROOT = Path(__file__).resolve().parents[1]
RUNTIME = ('vlp_ros.nodes.locator', 'vlp_ros.nodes.replay', 'vlp_ros.nodes.survey', 'vlp_ros.compiled.warm_up')
TOOLS = ('vlp_ros.sim', 'vlp_ros.evaluation', 'vlp_ros.benchmarks')


def imported_by(modules: tuple[str, ...], packages: tuple[str, ...] = ('vlp_ros',)) -> list[str]:
    """Return the modules of ``packages`` that importing ``modules`` in a fresh interpreter loads, sorted."""
    code = (f'import importlib, json, sys\n'
            f'for name in {list(modules)!r}:\n'
            f'    importlib.import_module(name)\n'
            f'packages = {list(packages)!r}\n'
            f'print(json.dumps(sorted(m for m in sys.modules if any(m == p or m.startswith(p + ".") '
            f'for p in packages))))\n')
    result = subprocess.run([sys.executable, '-c', code], cwd=ROOT, capture_output=True, text=True, timeout=300,
                            check=True)
    return json.loads(result.stdout.splitlines()[-1])


def test_the_nodes_and_the_warm_up_import_no_tool() -> None:
    loaded = imported_by(RUNTIME)
    assert set(RUNTIME) <= set(loaded)
    tools = [name for name in loaded if any(name == tool or name.startswith(tool + '.') for tool in TOOLS)]
    assert tools == [], f'the runtime imports {tools}'


def test_the_locator_loads_no_heavy_library_it_does_not_need() -> None:
    # Each costs start-up time and memory on the robot's computer; the chi-square and F tails come from
    # scipy.special.
    heavy = ('scipy.stats', 'scipy.optimize', 'matplotlib', 'gtsam')
    assert imported_by(('vlp_ros.nodes.locator',), heavy) == []


def test_the_simulator_imports_no_evaluation_or_benchmark_code() -> None:
    loaded = imported_by(('vlp_ros.sim.__main__',), ('vlp_ros.evaluation', 'vlp_ros.benchmarks'))
    assert loaded == [], f'the simulator imports {loaded}'
