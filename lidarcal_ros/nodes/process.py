"""A node process: ROS started with lidarcal's own signal handling, nodes spun, a clean stop.

:func:`run_main` is the ``main`` of every node's console script and of ``lidarcal run
--single-process``: SIGINT and SIGTERM end the spin loop (exit status 0, no traceback), each
node's ``close()`` runs, and a refused start-up configuration is one ``lidarcal: error:`` line.
"""

from __future__ import annotations

import logging
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import rclpy
from rclpy.node import Node

from lidarcal_ros.core.allocator import NODE_TRIM_THRESHOLD_BYTES, tune_allocator
from lidarcal_ros.errors import LidarcalError

__all__ = ["Shutdown", "run_main", "spin_nodes", "start_ros"]


class Shutdown:
    """SIGINT / SIGTERM turn into a flag the spin loop polls (clean exit, no traceback)."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self.signal: int | None = None
        self._previous: dict[int, Any] = {}

    def install(self) -> Shutdown:
        """Handle SIGINT and SIGTERM with this (from the main thread only: elsewhere nothing
        changes); itself."""
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum: int, _frame: Any) -> None:
        self.signal = signum
        self.event.set()

    def restore(self) -> None:
        """Put back the signal handlers :meth:`install` replaced."""
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous.clear()

    @property
    def requested(self) -> bool:
        """Whether a shutdown was asked for (a signal, or the event set)."""
        return self.event.is_set()


def spin_nodes(
    nodes: Sequence[Node], context: Any, shutdown: Shutdown, *, threads: int = 4
) -> None:
    """Spin ``nodes`` until ``shutdown`` is requested: on a multi-threaded executor, or a
    single-threaded one with ``threads=1`` (each callback runs in the spinning thread: no
    hand-over to a pool thread, which costs interpreter-lock switches)."""
    from rclpy.executors import (
        ExternalShutdownException,
        MultiThreadedExecutor,
        SingleThreadedExecutor,
    )

    executor: Any = (SingleThreadedExecutor(context=context) if threads == 1 else
                     MultiThreadedExecutor(num_threads=threads, context=context))
    for n in nodes:
        executor.add_node(n)
    log = nodes[0].get_logger() if nodes else None
    try:
        while not shutdown.requested and context.ok():
            try:
                executor.spin_once(timeout_sec=0.1)
            except (KeyboardInterrupt, ExternalShutdownException):
                raise
            except Exception as exc:  # a callback failed: report it, keep the nodes running
                if log is not None:
                    log.error(f"callback failed: {type(exc).__name__}: {exc}",
                              throttle_duration_sec=5.0)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        # Let callbacks in flight finish before the executor destroys its guard condition
        # (rclpy's MultiThreadedExecutor.shutdown does not wait for them).
        deadline = time.monotonic() + 5.0
        while any(not f.done() for f in getattr(executor, "_futures", ())) and \
                time.monotonic() < deadline:
            time.sleep(0.01)
        executor.shutdown(timeout_sec=2.0)


def start_ros(argv: list[str]) -> tuple[Any, Shutdown]:
    """Initialise a ROS context with lidarcal's own SIGINT/SIGTERM handling (``Shutdown``).

    The allocator is tuned first (:func:`lidarcal_ros.core.allocator.tune_allocator`): every
    cloud taken from or handed to DDS is a buffer of several MB, and with glibc's defaults
    each one is mapped and faulted in afresh, which costs a raw subscription about four times
    the CPU of the copy itself.
    """
    from rclpy.context import Context
    from rclpy.signals import SignalHandlerOptions

    tune_allocator(single_arena=False, trim_threshold_bytes=NODE_TRIM_THRESHOLD_BYTES)
    shutdown = Shutdown().install()
    context = Context()
    rclpy.init(args=argv, context=context, signal_handler_options=SignalHandlerOptions.NO)
    return context, shutdown


def run_main(
    factories: Sequence[Callable[..., Node]],
    args: Sequence[str] | None = None,
    *,
    threads: int = 4,
) -> int:
    """Start nodes in this process (``--ros-args`` in ``args``), spin, stop cleanly on SIGINT
    or SIGTERM; returns the exit status (0, or 1 with a one-line reason on bad start-up
    configuration)."""
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    context, shutdown = start_ros(list(sys.argv if args is None else args))
    nodes: list[Node] = []
    status = 0
    try:
        for factory in factories:
            nodes.append(factory(context=context))
        spin_nodes(nodes, context, shutdown, threads=threads)
    except LidarcalError as exc:
        print(f"lidarcal: error: {exc}", file=sys.stderr)
        status = 1
    except KeyboardInterrupt:
        pass
    finally:
        for n in reversed(nodes):
            close = getattr(n, "close", None)
            try:
                if close is not None:
                    close()
                n.destroy_node()
            except Exception as exc:  # shutting down: report, continue
                print(f"lidarcal: error stopping {n.get_name()}: {exc}", file=sys.stderr)
        context.try_shutdown()
        shutdown.restore()
    return status

