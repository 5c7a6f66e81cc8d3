"""Nodes spun in a background thread and a bag replayed into them, for the node tests."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any


@contextlib.contextmanager
def spinning(context: Any, *nodes: Any) -> Iterator[None]:
    """Spin ``nodes`` in a multi-threaded executor in a background thread meanwhile."""
    from rclpy.executors import MultiThreadedExecutor

    executor = MultiThreadedExecutor(num_threads=4, context=context)
    for n in nodes:
        executor.add_node(n)
    stop = threading.Event()

    def spin() -> None:
        while not stop.is_set():
            executor.spin_once(timeout_sec=0.05)

    thread = threading.Thread(target=spin, daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join(timeout=10)
        executor.shutdown(timeout_sec=5)


def replay_payload(bag: Path, rate: float, *options: str) -> str:
    """``lidarcal replay`` of a UAV payload's clouds and odometry (the default queue, 2 s of
    each topic at ``rate``; ``--linger 10``: none lost to a slow subscriber; ``options``
    added, e.g. ``--start``); its stdout."""
    res = subprocess.run(
        [sys.executable, "-m", "lidarcal_ros", "replay", str(bag), "--rate", str(rate),
         "--topics", "/velodyne_points", "/ins/odometry", "--wait-for-subscribers", "20",
         "--linger", "10", *options],
        env=dict(os.environ), capture_output=True, text=True, timeout=120, check=False)
    assert res.returncode == 0, res.stderr
    return res.stdout
