"""Shared harness for tests that start the real vlp_ros executables as separate processes.

Isolation: every test run holds its own ROS_DOMAIN_ID (a lock file per domain, so
concurrent runs on one machine never share one), DDS traffic stays on loopback and
shared memory (config/fastdds_loopback.xml), logs go under build/, and every
process a test starts is stopped by PID afterwards.
"""
from __future__ import annotations

import fcntl
import os
import signal
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / 'shared' / 'data'
LOOPBACK_PROFILE = ROOT / 'config' / 'fastdds_loopback.xml'
_domain_lock = None


def _claim_domain_id() -> int:
    """Lowest ROS domain (1..100) that no other test run on this machine holds."""
    global _domain_lock
    for domain in range(1, 101):
        handle = open(f'/tmp/vlp_ros_test_domain_{domain}.lock', 'w')
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            handle.close()
            continue
        _domain_lock = handle  # held until this process exits
        return domain
    raise RuntimeError('no free ROS domain id for the test run')


def pytest_configure(config: pytest.Config) -> None:
    # Set before any rclpy.init in this process and inherited by every child.
    os.environ['ROS_DOMAIN_ID'] = str(_claim_domain_id())
    # Not ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST: it swaps in transports that drop
    # camera-sized best-effort messages (see the profile's comment).
    os.environ.pop('ROS_AUTOMATIC_DISCOVERY_RANGE', None)
    os.environ.pop('FASTDDS_BUILTIN_TRANSPORTS', None)
    os.environ['FASTDDS_DEFAULT_PROFILES_FILE'] = str(LOOPBACK_PROFILE)
    os.environ['RMW_IMPLEMENTATION'] = 'rmw_fastrtps_cpp'
    log_dir = ROOT / 'build' / 'test_logs' / str(os.getpid())
    log_dir.mkdir(parents=True, exist_ok=True)
    os.environ['ROS_LOG_DIR'] = str(log_dir)


def executable(name: str) -> Path:
    """The file `ros2 run vlp_ros <name>` would execute."""
    from ament_index_python.packages import get_package_prefix
    return Path(get_package_prefix('vlp_ros')) / 'lib' / 'vlp_ros' / name


class RosProcess:
    """A started executable whose output is kept in files for assertions and failure reports."""

    def __init__(self, args: list[str], workdir: Path, label: str, env: dict[str, str] | None = None) -> None:
        self.args = args
        self.stdout_path = workdir / f'{label}.stdout'
        self.stderr_path = workdir / f'{label}.stderr'
        with open(self.stdout_path, 'wb') as out, open(self.stderr_path, 'wb') as err:
            self.popen = subprocess.Popen(args, stdout=out, stderr=err, stdin=subprocess.DEVNULL,
                                          start_new_session=True, env=env)

    @property
    def pid(self) -> int:
        return self.popen.pid

    def stdout(self) -> str:
        return self.stdout_path.read_text(errors='replace')

    def stderr(self) -> str:
        return self.stderr_path.read_text(errors='replace')

    def output(self) -> str:
        return self.stdout() + self.stderr()

    def wait(self, timeout: float) -> int:
        return self.popen.wait(timeout=timeout)

    def interrupt(self, timeout: float = 10.0) -> int:
        """SIGINT, as Ctrl-C would send, and the exit status."""
        if self.popen.poll() is None:
            self.popen.send_signal(signal.SIGINT)
        return self.popen.wait(timeout=timeout)

    def stop(self) -> None:
        """Stop the process by PID whatever state it is in: SIGINT, then SIGKILL."""
        if self.popen.poll() is None:
            try:
                self.interrupt(timeout=5.0)
            except subprocess.TimeoutExpired:
                os.killpg(self.popen.pid, signal.SIGKILL)
                self.popen.wait(timeout=5.0)


@pytest.fixture
def start_process(tmp_path: Path) -> Iterator[Callable[..., RosProcess]]:
    """start_process('locator', '--ros-args', ..., env=None) runs an installed executable; all are stopped after the test."""
    started: list[RosProcess] = []

    def start(name: str, *args: str, env: dict[str, str] | None = None) -> RosProcess:
        path = executable(name)
        process = RosProcess([str(path), *map(str, args)], tmp_path, f'{name}{len(started)}', env)
        started.append(process)
        return process

    yield start
    for process in started:
        process.stop()


@pytest.fixture(scope='session')
def rclpy_context() -> Iterator[None]:
    import rclpy
    rclpy.init()
    yield
    rclpy.try_shutdown()


@pytest.fixture
def test_node(rclpy_context: None, request: pytest.FixtureRequest):
    """A node in the test process, for talking to the executables over DDS."""
    import rclpy
    node = rclpy.create_node('vlp_test_' + request.node.name.replace('[', '_').replace(']', '_')[:40].strip('_'))
    yield node
    node.destroy_node()


def spin_until(node, condition: Callable[[], bool], timeout: float) -> bool:
    """Spin ``node`` until ``condition()`` holds or ``timeout`` seconds pass; whether it held."""
    import rclpy
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        rclpy.spin_once(node, timeout_sec=0.05)
    return condition()
