"""
The project's one way to compile a numeric loop: numba's ``njit`` with fixed settings.

Per-lamp work is small arrays (a few hundred rim points, a marker box, a row
profile), where each numpy or OpenCV call costs more in argument handling than in
arithmetic; a frame made ~3,000 such calls. Loops written out and compiled do that
work without the per-call cost. Only the inner numerics are compiled: their
callers stay plain Python with the checks and dataclasses around them.

Settings: ``cache=True`` keeps the machine code on disk, so a process loads it instead of
compiling; ``python -m vlp_ros.pipeline.warm_up`` (run by ``make build``) fills that
cache. The cache notices a change in a kernel's own file only, not in the kernels it
calls from other files, so ``make build`` clears it before compiling afresh.
``error_model='numpy'`` makes a division by zero give inf/nan as numpy does instead
of raising; no ``fastmath``, so results keep IEEE rounding and match the numpy code
they replace to rounding error.

Where the cache lives is decided here, before any kernel is declared: beside the
modules (``__pycache__``) when the package directory is writable (a source tree, a
colcon install of one's own); else ``$ROS_HOME/vlp_ros/numba_cache``, or without
``ROS_HOME`` ``${XDG_CACHE_HOME:-~/.cache}/vlp_ros/numba`` (a read-only install from
apt or a shared workspace). A ``NUMBA_CACHE_DIR`` set by the user wins. When nothing
is writable, the kernels are compiled in memory at every start (minutes) and
one warning line says so.
"""
from __future__ import annotations

from collections.abc import Callable, Mapping
import logging
import os
from pathlib import Path
import tempfile
from typing import TypeVar

import numba

Function = TypeVar('Function', bound=Callable)

PACKAGE_CACHE = Path(__file__).resolve().parent / '__pycache__'


def writable(directory: Path) -> bool:
    """Return whether a file can be created in ``directory`` (made if missing), by trying: mounts and ACLs decide."""
    try:
        directory.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=directory):
            return True
    except OSError:
        return False


def user_cache_directory(environ: Mapping[str, str]) -> Path:
    """Return the cache directory outside the package: under ``ROS_HOME``, else under the user's cache."""
    if environ.get('ROS_HOME'):
        return Path(environ['ROS_HOME']).expanduser() / 'vlp_ros' / 'numba_cache'
    cache_home = environ.get('XDG_CACHE_HOME') or Path.home() / '.cache'
    return Path(cache_home).expanduser() / 'vlp_ros' / 'numba'


def choose_cache(environ: Mapping[str, str]) -> tuple[bool, str | None]:
    """Return whether kernels are cached and the ``NUMBA_CACHE_DIR`` to set (None: leave it as it is)."""
    if environ.get('NUMBA_CACHE_DIR'):
        return writable(Path(environ['NUMBA_CACHE_DIR'])) or writable(PACKAGE_CACHE), None
    if writable(PACKAGE_CACHE):
        return True, None
    directory = user_cache_directory(environ)
    if writable(directory):
        return True, str(directory)
    return False, None


CACHING, _cache_dir = choose_cache(os.environ)
if _cache_dir is not None:
    os.environ['NUMBA_CACHE_DIR'] = _cache_dir
    # Numba reads its environment at import; kernels declared from here on see the directory.
    numba.config.reload_config()
if not CACHING:
    logging.getLogger(__name__).warning(
        'vlp_ros: no writable directory for the numba cache (the package, $ROS_HOME/vlp_ros/numba_cache or '
        '~/.cache/vlp_ros/numba): the kernels are compiled in memory at every start, minutes of CPU; '
        'set ROS_HOME (or NUMBA_CACHE_DIR) to a writable directory to compile them once')


def kernel(function: Function) -> Function:
    """Return ``function`` compiled (on first call, or loaded from the cache) with the project's settings."""
    return numba.njit(cache=CACHING, nogil=True, error_model='numpy')(function)
