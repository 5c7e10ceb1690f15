"""The project's one way to compile a numeric loop: numba's ``njit`` with fixed settings.

Per-lamp work is small arrays (a few hundred rim points, a marker box, a row
profile), where each numpy or OpenCV call costs more in argument handling than in
arithmetic; a frame made ~3,000 such calls. Loops written out and compiled do that
work without the per-call cost. Only the inner numerics are compiled: their
callers stay plain Python with the checks and dataclasses around them.

Settings: ``cache=True`` keeps the machine code beside the module (``__pycache__``,
or numba's user cache where that is read-only), so a process loads it instead of
compiling; ``python -m vlp_ros.compiled.warm_up`` (run by ``make build``) fills that
cache. The cache notices a change in a kernel's own file only, not in the kernels it
calls from other files, so ``make build`` clears it before compiling afresh.
``error_model='numpy'`` makes a division by zero give inf/nan as numpy does instead
of raising; no ``fastmath``, so results keep IEEE rounding and match the numpy code
they replace to rounding error.
"""
from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

import numba

Function = TypeVar('Function', bound=Callable)


def kernel(function: Function) -> Function:
    """``function`` compiled (on first call, or loaded from the cache) with the project's settings."""
    return numba.njit(cache=True, nogil=True, error_model='numpy')(function)
