"""
The warm-up reaches every numba kernel of the runtime, so none compiles on a robot's first frames.

Numba lists a kernel's compiled argument types in its dispatcher's ``signatures``. A kernel called only
inside other kernels is compiled into its callers: when they are compiled afresh, numba compiles it on its
own too (it then has a signature), but when their machine code comes from the cache, its dispatcher is never
asked and keeps none. So a kernel counts as ready when it has a signature or a ready kernel calls it.
Run as a script, this file runs the warm-up in its own interpreter and prints what each kernel holds.
"""
from __future__ import annotations

from collections.abc import Iterator
import importlib
import json
import os
from pathlib import Path
import pkgutil
import subprocess
import sys
from types import CodeType

from numba.core.dispatcher import Dispatcher

import vlp_ros

ROOT = Path(__file__).resolve().parents[1]
# The tools and the nodes call the runtime's kernels and declare none a node would run.
OUTSIDE_THE_RUNTIME = ('vlp_ros.sim', 'vlp_ros.evaluation', 'vlp_ros.benchmarks', 'vlp_ros.nodes')


def runtime_kernels() -> dict[str, Dispatcher]:
    """Import every module of the runtime; return each numba kernel they declare by its qualified name."""
    kernels = {}
    for module in pkgutil.walk_packages(vlp_ros.__path__, 'vlp_ros.'):
        if not module.name.startswith(OUTSIDE_THE_RUNTIME):
            for value in vars(importlib.import_module(module.name)).values():
                if isinstance(value, Dispatcher):
                    kernels[qualified_name(value)] = value
    return kernels


def qualified_name(kernel: Dispatcher) -> str:
    return f'{kernel.py_func.__module__}.{kernel.py_func.__qualname__}'


def code_objects(code: CodeType) -> Iterator[CodeType]:
    """Yield ``code`` and the code nested in it."""
    yield code
    for constant in code.co_consts:
        if isinstance(constant, CodeType):
            yield from code_objects(constant)


def kernels_called_by(kernel: Dispatcher) -> list[str]:
    """Return the kernels that ``kernel`` calls: the global names in its code that are kernels."""
    names = {name for code in code_objects(kernel.py_func.__code__) for name in code.co_names}
    found = (kernel.py_func.__globals__.get(name) for name in names)
    return sorted(qualified_name(callee) for callee in found if isinstance(callee, Dispatcher))


def report_after_warm_up() -> dict[str, dict]:
    """Run the warm-up; return, for every kernel, whether it has a compiled signature and the kernels it calls."""
    kernels = runtime_kernels()
    from vlp_ros.pipeline.warm_up import warm_up
    warm_up()
    return {name: {'compiled': bool(kernel.signatures), 'calls': kernels_called_by(kernel)}
            for name, kernel in kernels.items()}


def ready(report: dict[str, dict]) -> set[str]:
    """Return the kernels that are compiled or called, at any depth, by a compiled one."""
    found = {name for name, kernel in report.items() if kernel['compiled']}
    waiting = list(found)
    while waiting:
        for callee in report[waiting.pop()]['calls']:
            if callee not in found:
                found.add(callee)
                waiting.append(callee)
    return found


def test_the_warm_up_makes_every_kernel_ready() -> None:
    # The source tree's package, as the other tests import it (a script's own directory comes first on its path).
    path = os.pathsep.join(filter(None, (str(ROOT), os.environ.get('PYTHONPATH'))))
    result = subprocess.run([sys.executable, __file__], cwd=ROOT, env={**os.environ, 'PYTHONPATH': path},
                            capture_output=True, text=True, timeout=280)
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout.splitlines()[-1])
    assert len(report) > 100, 'the kernels were not found'
    missing = sorted(set(report) - ready(report))
    assert missing == [], 'kernels the warm-up does not reach (compiled on a first frame):\n' + '\n'.join(missing)


if __name__ == '__main__':
    print(json.dumps(report_after_warm_up()))
