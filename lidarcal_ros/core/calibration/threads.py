"""The worker threads of a calibration and the CPU time of its stages.

:class:`WorkerPool` runs the per-strip and per-pair work of a calibration (TINs, corrections,
matching) in ``workers`` threads for the duration of a ``with`` block, reporting progress;
the result does not depend on the number of threads. :class:`StageClock` sums the CPU seconds
the threads spend in each stage.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import TypeVar

_T = TypeVar("_T")
_R = TypeVar("_R")


class StageClock:
    """CPU seconds spent in each stage of a calibration, summed over its threads (thread
    time: what the work costs, whatever else the machine runs). A stage entered within
    another pauses it, so the stages add up to the time spent in any of them."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self._lock = threading.Lock()
        self._local = threading.local()

    @contextmanager
    def __call__(self, stage: str) -> Iterator[None]:
        """A context in which the calling thread's CPU time counts to ``stage`` (the stage it was
        in pauses until the context ends)."""
        local = self._local
        outer: str | None = getattr(local, "stage", None)
        now = time.thread_time()
        if outer is not None:
            self._add(outer, now - local.since)
        local.stage, local.since = stage, now
        try:
            yield
        finally:
            now = time.thread_time()
            self._add(stage, now - local.since)
            local.stage, local.since = outer, now

    def _add(self, stage: str, seconds: float) -> None:
        with self._lock:
            self.seconds[stage] = self.seconds.get(stage, 0.0) + seconds


class WorkerPool:
    """Up to ``workers`` threads, started by :meth:`threads` for a ``with`` block.

    Parameters
    ----------
    workers : int
        Threads to run in (1: none, the caller's thread does the work).
    progress : callable
        Called with (stage, fraction done in [0, 1]) as :meth:`map` proceeds.
    """

    def __init__(self, workers: int, progress: Callable[[str, float], None]) -> None:
        self.workers = workers
        self._progress = progress
        self._pool: ThreadPoolExecutor | None = None

    @property
    def running(self) -> bool:
        """Whether the threads are started (within :meth:`threads`, with ``workers > 1``)."""
        return self._pool is not None

    @contextmanager
    def threads(self) -> Iterator[None]:
        """The threads for the duration of a ``with`` block; nested blocks share the outer
        one's."""
        if self._pool is not None or self.workers <= 1:
            yield
            return
        self._pool = ThreadPoolExecutor(max_workers=self.workers,
                                        thread_name_prefix="lidarcal-calibrate")
        try:
            yield
        finally:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    def map(self, fn: Callable[[_T], _R], items: Sequence[_T], stage: str | None = None, *,
            in_turn: bool = False) -> list[_R]:
        """``[fn(item) for item in items]``, in the threads while they run (``in_turn``: one
        after another in the caller's thread all the same), reporting progress in
        ``stage``."""
        if stage:
            self._progress(stage, 0.0)
        if self._pool is None or len(items) < 2 or in_turn:
            out = []
            for i, item in enumerate(items):
                out.append(fn(item))
                if stage:
                    self._progress(stage, (i + 1) / len(items))
            return out
        futures = [self._pool.submit(fn, item) for item in items]
        results = []
        try:
            for i, future in enumerate(futures):
                results.append(future.result())
                if stage:
                    self._progress(stage, (i + 1) / len(items))
        finally:
            for future in futures:
                future.cancel()
        return results


__all__ = ["StageClock", "WorkerPool"]
