"""
The start and stop code every vlp_ros executable shares, as in ros2/examples.

A process initializes rclpy, builds its node, runs it, and on the way out destroys
the node and shuts rclpy down. Ctrl-C at any moment (while starting, running or
stopping) and an external shutdown are clean stops with exit status 0.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
import signal
from typing import TypeVar

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node

NodeT = TypeVar('NodeT', bound=Node)


def spin(node: Node) -> int:
    """Process the node's callbacks until the process is stopped; the exit status."""
    rclpy.spin(node)
    return 0


def run_node(create: Callable[[], NodeT], run: Callable[[NodeT], int] = spin, *,
             args: Sequence[str] | None = None,
             start_errors: tuple[type[Exception], ...] = (),
             on_start_error: Callable[[Exception], int] | None = None) -> int:
    """
    Build the node with ``create()``, ``run`` it, and stop cleanly; the process's exit status.

    ``start_errors`` raised by ``create()`` (bad parameters or options) are handed to
    ``on_start_error``, whose return value is the exit status.
    """
    try:
        return _run_node(create, run, args, start_errors, on_start_error)
    except KeyboardInterrupt:  # Ctrl-C while starting up or shutting down is a clean stop too
        return 0
    finally:
        # Stopping anyway: a Ctrl-C during interpreter shutdown must not turn a clean exit into a signal death.
        signal.signal(signal.SIGINT, signal.SIG_IGN)


def _run_node(create: Callable[[], NodeT], run: Callable[[NodeT], int], args: Sequence[str] | None,
              start_errors: tuple[type[Exception], ...], on_start_error: Callable[[Exception], int] | None) -> int:
    with rclpy.init(args=args):
        try:
            try:
                node = create()
            except start_errors as err:
                return on_start_error(err)
            try:
                return run(node)
            finally:
                node.destroy_node()
        except ExternalShutdownException:
            return 0
        except RuntimeError:
            # rcl reports a call on a context that Ctrl-C has just shut down as a RuntimeError.
            if rclpy.ok():
                raise
            return 0
