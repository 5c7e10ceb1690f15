"""
Shared harness for tests that start the real vlp_ros executables as separate processes.

Isolation: every test run holds its own ROS_DOMAIN_ID (a lock file per domain, so
concurrent runs on one machine never share one), DDS traffic stays on loopback and
shared memory (config/fastdds_loopback.xml), logs go under build/, and every
process a test starts is stopped by PID afterwards.
"""
from __future__ import annotations

from collections.abc import Callable, Iterator
import os
from pathlib import Path
import signal
import subprocess
import time

import pytest

from vlp_ros.nodes.dds_environment import claim_domain_id, installed_executable, use_loopback_dds

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / 'shared' / 'data'
LOOPBACK_PROFILE = ROOT / 'config' / 'fastdds_loopback.xml'


def pytest_configure(config: pytest.Config) -> None:
    # Set before any rclpy.init in this process and inherited by every child.
    use_loopback_dds(LOOPBACK_PROFILE, claim_domain_id())
    log_dir = ROOT / 'build' / 'test_logs' / str(os.getpid())
    log_dir.mkdir(parents=True, exist_ok=True)
    os.environ['ROS_LOG_DIR'] = str(log_dir)


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
    """
    Return a function that runs an installed executable; every process it started is stopped after the test.

    Called as start_process('locator', '--ros-args', ..., env=None).
    """
    started: list[RosProcess] = []

    def start(name: str, *args: str, env: dict[str, str] | None = None) -> RosProcess:
        path = installed_executable(name)
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


def located_through_the_nodes(test_node, start_process: Callable[..., RosProcess], bag: Path, params: Path,
                              topics, imu: bool, group: str) -> list:
    """
    Return each frame's outcome against the bag's truth, with ``bag`` played through the installed nodes.

    Every frame of the recording at ``bag`` is played by the installed replay into the installed
    locator (``params``), one frame at a time; the outcomes are returned once every frame was
    answered with its own stamp.
    """
    from vlp_ros.evaluation.demo import outcomes_from_answers
    from vlp_ros.evaluation.recording import ground_truth
    from vlp_ros.nodes.pose_listener import PoseListener
    truth = ground_truth(bag, topics.ground_truth)
    listener = PoseListener(test_node)
    locator = start_process('locator', '--ros-args', '--params-file', params)
    # Subscribed once its kernels are loaded, which takes as long as the machine is busy.
    assert spin_until(test_node, lambda: test_node.count_subscribers(topics.image) > 0, 120.0), locator.output()
    # Every frame waits for its answer however slow the machine: an answer the replay stops waiting for
    # lets the next frame in, and a third one then replaces that one in the locator's queue unseen. A kernel
    # that the build's warm-up did not reach compiles on its first frame, past a minute on a loaded machine
    # (a bare-LED JPEG still in a fresh-clone CI run): each frame is given three.
    replay = start_process('replay', bag, '--deterministic', '--answer-timeout', '180', '--topics', topics.image,
                           topics.camera_info, *([topics.imu] if imu else []))
    assert spin_until(test_node, lambda: replay.popen.poll() is not None, 900.0), replay.output()
    # The locator's log says why a frame had no answer (e.g. it came before any camera_info).
    assert replay.popen.returncode == 0 and 'unanswered: 0' in replay.stderr(), replay.output() + locator.output()
    spin_until(test_node, lambda: set(listener.outcomes) == set(truth), 10.0)
    assert set(listener.outcomes) == set(truth), 'every frame answered once, with its own stamp'
    assert set(listener.poses) <= set(truth)
    return outcomes_from_answers(truth, listener, group)
