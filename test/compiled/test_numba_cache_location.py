"""Where numba caches the kernels of a read-only install: under ROS_HOME, or in memory with one warning."""
from __future__ import annotations

import os
from pathlib import Path
import shutil
import stat
import subprocess
import sys

from conftest import ROOT
import pytest

# Root writes through any permission bits; without these capabilities it is held to them like a service account.
AS_AN_ACCOUNT = ['setpriv', '--bounding-set', '-dac_override,-dac_read_search,-fowner',
                 '--inh-caps', '-dac_override,-dac_read_search,-fowner'] if os.geteuid() == 0 else []
RUN_A_KERNEL = ('import numpy as np\n'
                'from vlp_ros.compiled.small_arrays import median\n'
                'print(median(np.array([3.0, 1.0, 2.0])))\n')


def installed_package() -> Path:
    """Return the installed vlp_ros package (of the sourced install space), else the source tree's."""
    from ament_index_python.packages import PackageNotFoundError, get_package_prefix
    try:
        found = list(Path(get_package_prefix('vlp_ros')).glob('lib/python3*/site-packages/vlp_ros'))
    except PackageNotFoundError:
        found = []
    return found[0] if found else ROOT / 'vlp_ros'


def read_only(path: Path) -> Path:
    """Make ``path`` and everything below it read-only for everybody; return it."""
    for item in [path, *path.rglob('*')]:
        item.chmod(item.stat().st_mode & ~(stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH))
    return path


def writable_again(path: Path) -> None:
    """Let the test's owner write ``path`` and everything below it again (to clean up)."""
    for item in [path, *path.rglob('*')]:
        item.chmod(item.stat().st_mode | stat.S_IWUSR)


@pytest.fixture
def read_only_install(tmp_path: Path):
    """Yield a copy of the installed package without numba's cache, read-only, as an apt install is."""
    if AS_AN_ACCOUNT and shutil.which('setpriv') is None:
        pytest.skip('running as root without setpriv: permission bits cannot be enforced')
    site = tmp_path / 'site'
    shutil.copytree(installed_package(), site / 'vlp_ros', ignore=shutil.ignore_patterns('*.nbi', '*.nbc'))
    read_only(site)
    yield site
    writable_again(site)


def run_kernel(site: Path, env: dict[str, str]) -> subprocess.CompletedProcess:
    """Run a kernel of the package in ``site`` in a fresh interpreter, as an account held to permissions."""
    environ = {k: v for k, v in os.environ.items() if k not in ('NUMBA_CACHE_DIR', 'XDG_CACHE_HOME', 'ROS_HOME')}
    environ.update(env, PYTHONPATH=str(site), PYTHONDONTWRITEBYTECODE='1')
    return subprocess.run([*AS_AN_ACCOUNT, sys.executable, '-c', RUN_A_KERNEL], cwd=site, env=environ,
                          capture_output=True, text=True, timeout=300)


def cache_files(directory: Path) -> list[Path]:
    """Return numba's cache index files below ``directory``."""
    return sorted(directory.rglob('*.nbi'))


def test_a_read_only_install_caches_under_ros_home(read_only_install: Path, tmp_path: Path) -> None:
    home, ros_home = tmp_path / 'home', tmp_path / 'ros'
    home.mkdir()
    result = run_kernel(read_only_install, {'HOME': str(home), 'ROS_HOME': str(ros_home)})
    assert result.returncode == 0, result.stderr
    assert float(result.stdout.split()[-1]) == 2.0
    assert cache_files(ros_home / 'vlp_ros' / 'numba_cache'), 'no cache under ROS_HOME'
    assert not cache_files(read_only_install) and not cache_files(home)
    assert 'numba cache' not in result.stderr


def test_without_ros_home_the_user_cache_serves(read_only_install: Path, tmp_path: Path) -> None:
    home = tmp_path / 'home'
    home.mkdir()
    result = run_kernel(read_only_install, {'HOME': str(home)})
    assert result.returncode == 0, result.stderr
    assert cache_files(home / '.cache' / 'vlp_ros' / 'numba')


def test_nothing_writable_compiles_in_memory_with_one_warning(read_only_install: Path, tmp_path: Path) -> None:
    home, ros_home = tmp_path / 'home', tmp_path / 'ros'
    for directory in (home, ros_home):
        directory.mkdir()
        read_only(directory)
    result = run_kernel(read_only_install, {'HOME': str(home), 'ROS_HOME': str(ros_home)})
    writable_again(home)
    writable_again(ros_home)
    assert result.returncode == 0, result.stderr
    assert float(result.stdout.split()[-1]) == 2.0
    warnings = [line for line in result.stderr.splitlines() if 'numba cache' in line]
    assert len(warnings) == 1 and 'ROS_HOME' in warnings[0] and 'minute' in warnings[0], result.stderr
    assert not cache_files(tmp_path)
