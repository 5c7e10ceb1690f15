"""
The locator's start-up time: python -m vlp_ros.benchmarks.startup [--prefix DIR ...] [--runs N].

Starts the installed ``locator`` executable (of each install prefix given, the package's
prefix in an install space: ``install/vlp_ros``) and times, from just before the process
starts, until its subscription to the image topic is visible over DDS
(``get_subscriptions_info_by_topic``): what a camera driver waits for before frames are
used. Warm: the install tree as built (``make build`` filled its numba cache). Cold: a
copy of it without the cache, as a first start on a fresh install (or every start where
nothing is writable) pays: the locator subscribes as soon as numba starts compiling and
answers frames only once the kernels are ready, minutes later (its log says when). Prints
the median and range of ``--runs`` starts of each.
"""
from __future__ import annotations

import argparse
from collections.abc import Sequence
import os
from pathlib import Path
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

import rclpy

from vlp_ros.evaluation.metrics import format_table
from vlp_ros.nodes.dds_environment import claim_domain_id, loopback_profile, stop_process, use_loopback_dds

IMAGE_TOPICS = ('/image_raw', '/image_raw/compressed')


def site_packages(prefix: Path) -> Path:
    """Return the directory of ``prefix`` that holds the vlp_ros package."""
    return next(prefix.glob('lib/python3*/site-packages'))


def without_cache(prefix: Path, workdir: Path) -> Path:
    """Return a copy of the install prefix ``prefix`` under ``workdir`` with numba's cache files removed."""
    copy = workdir / 'prefix'
    shutil.copytree(prefix, copy, symlinks=True)
    for path in copy.rglob('*.nb[ic]'):
        path.unlink()
    return copy


def locator_subscribed(node) -> bool:
    """Return whether a locator's subscription to the image topic is in ``node``'s view of the graph."""
    return any(info.node_name == 'vlp_locator' for topic in IMAGE_TOPICS
               for info in node.get_subscriptions_info_by_topic(topic))


def wait_until_gone(node, timeout: float = 60.0) -> None:
    """Wait until the graph no longer shows a locator stopped before (so that it is not taken for the next)."""
    deadline = time.monotonic() + timeout
    while locator_subscribed(node):
        if time.monotonic() > deadline:
            raise TimeoutError('a stopped locator still shows in the graph')
        time.sleep(0.1)


def time_to_subscription(node, prefix: Path, params: Path, timeout: float) -> float:
    """Return the seconds from starting ``prefix``'s locator to its image subscription being visible."""
    wait_until_gone(node)
    env = dict(os.environ, PYTHONPATH=f'{site_packages(prefix)}{os.pathsep}{os.environ.get("PYTHONPATH", "")}')
    args = [str(prefix / 'lib' / 'vlp_ros' / 'locator'), '--ros-args', '--params-file', str(params)]
    started = time.monotonic()
    process = subprocess.Popen(args, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                               stderr=subprocess.PIPE, text=True)
    try:
        while time.monotonic() - started < timeout:
            if locator_subscribed(node):
                return time.monotonic() - started
            if process.poll() is not None:
                raise RuntimeError(f'the locator of {prefix} exited: {process.stderr.read()[-2000:]}')
            time.sleep(0.02)
        raise TimeoutError(f'no image subscription of the locator of {prefix} within {timeout:.0f} s')
    finally:
        stop_process(process, timeout=20.0)


def startup_times(node, prefix: Path, params: Path, cold: bool, runs: int, timeout: float) -> list[float]:
    """Return ``runs`` start-up times of ``prefix``'s locator, each cold one from a fresh copy without cache."""
    times = []
    for _ in range(runs):
        if not cold:
            times.append(time_to_subscription(node, prefix, params, timeout))
            continue
        with tempfile.TemporaryDirectory(prefix='vlp_startup_') as workdir:
            times.append(time_to_subscription(node, without_cache(prefix, Path(workdir)), params, timeout))
    return times


def main(argv: Sequence[str] | None = None) -> int:
    """Time the starts of each prefix and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument('--prefix', type=Path, action='append',
                        help='install prefix of vlp_ros (repeatable; default: the one sourced)')
    parser.add_argument('--params', type=Path, help='params file (default: the installed locator.example.yaml)')
    parser.add_argument('--runs', type=int, default=3)
    parser.add_argument('--only', choices=('warm', 'cold'), help='time only warm or only cold starts')
    parser.add_argument('--timeout', type=float, default=900.0, help='seconds a start may take')
    args = parser.parse_args(argv)
    from ament_index_python.packages import get_package_prefix
    prefixes = args.prefix or [Path(get_package_prefix('vlp_ros'))]
    params = args.params or prefixes[0] / 'share' / 'vlp_ros' / 'config' / 'locator.example.yaml'
    use_loopback_dds(loopback_profile(), claim_domain_id())
    rclpy.init()
    node = rclpy.create_node('vlp_startup_timer')
    rows = []
    try:
        for prefix in prefixes:
            for kind in ('warm', 'cold'):
                if args.only not in (None, kind):
                    continue
                times = startup_times(node, prefix.resolve(), params, kind == 'cold', args.runs, args.timeout)
                rows.append([str(prefix), kind, str(len(times)), f'{statistics.median(times):.1f}',
                             f'{min(times):.1f}-{max(times):.1f}'])
                print(f'{prefix} {kind}: ' + ', '.join(f'{t:.1f}' for t in times), file=sys.stderr, flush=True)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    print(f'load average at the end: {", ".join(f"{v:.1f}" for v in os.getloadavg())}')
    print(format_table(rows, ('prefix', 'start', 'runs', 'median s', 'range s')))
    return 0


if __name__ == '__main__':
    sys.exit(main())
