"""Running the installed nodes on one machine: where they are, an unshared domain, loopback DDS."""
from __future__ import annotations

import fcntl
import os
from pathlib import Path
import signal
import subprocess

_held_locks: list = []


def claim_domain_id(first: int = 1, last: int = 100) -> int:
    """
    Lowest ROS domain in [first, last] that no other process on this machine has claimed.

    The claim is a lock file held until this process exits, so concurrent test runs
    and demos never see each other's nodes.
    """
    for domain in range(first, last + 1):
        handle = open(f'/tmp/vlp_ros_domain_{domain}.lock', 'w')
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            handle.close()
            continue
        _held_locks.append(handle)
        return domain
    raise RuntimeError(f'every ROS domain from {first} to {last} is claimed on this machine')


def use_loopback_dds(profile: Path, domain_id: int) -> None:
    """
    Configure this process and its children: ``profile`` is config/fastdds_loopback.xml.

    Not ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST: it swaps in transports that drop
    camera-sized best-effort messages (see the profile's comment).
    """
    os.environ['ROS_DOMAIN_ID'] = str(domain_id)
    os.environ.pop('ROS_AUTOMATIC_DISCOVERY_RANGE', None)
    os.environ.pop('FASTDDS_BUILTIN_TRANSPORTS', None)
    os.environ['FASTDDS_DEFAULT_PROFILES_FILE'] = str(profile)
    os.environ['RMW_IMPLEMENTATION'] = 'rmw_fastrtps_cpp'


def installed_executable(name: str) -> Path:
    """Return the file `ros2 run vlp_ros <name>` would execute."""
    from ament_index_python.packages import get_package_prefix
    return Path(get_package_prefix('vlp_ros')) / 'lib' / 'vlp_ros' / name


def loopback_profile() -> Path:
    """Return the installed config/fastdds_loopback.xml."""
    from ament_index_python.packages import get_package_share_directory
    return Path(get_package_share_directory('vlp_ros')) / 'config' / 'fastdds_loopback.xml'


def stop_process(process: subprocess.Popen, timeout: float = 10.0) -> None:
    """Stop a started node as Ctrl-C would, and kill it if it has not exited within ``timeout`` s."""
    if process.poll() is None:
        process.send_signal(signal.SIGINT)
        try:
            process.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
