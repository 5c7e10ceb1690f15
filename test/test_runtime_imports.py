"""The runtime stands alone: the nodes and the warm-up import no simulator, evaluation or benchmark code."""
from __future__ import annotations

import json
from pathlib import Path
import subprocess
import sys

ROOT = Path(__file__).resolve().parents[1]
RUNTIME = ('vlp_ros.nodes.locator', 'vlp_ros.nodes.replay', 'vlp_ros.nodes.survey', 'vlp_ros.compiled.warm_up')
TOOLS = ('vlp_ros.sim', 'vlp_ros.evaluation', 'vlp_ros.benchmarks')


def imported_by(modules: tuple[str, ...]) -> list[str]:
    """Return the vlp_ros modules that importing ``modules`` in a fresh interpreter loads, sorted."""
    code = (f'import importlib, json, sys\n'
            f'for name in {list(modules)!r}:\n'
            f'    importlib.import_module(name)\n'
            f'print(json.dumps(sorted(m for m in sys.modules if m == "vlp_ros" or m.startswith("vlp_ros."))))\n')
    result = subprocess.run([sys.executable, '-c', code], cwd=ROOT, capture_output=True, text=True, timeout=300,
                            check=True)
    return json.loads(result.stdout.splitlines()[-1])


def test_the_nodes_and_the_warm_up_import_no_tool() -> None:
    loaded = imported_by(RUNTIME)
    assert set(RUNTIME) <= set(loaded)
    tools = [name for name in loaded if any(name == tool or name.startswith(tool + '.') for tool in TOOLS)]
    assert tools == [], f'the runtime imports {tools}'
