"""``lidarcal calibrate --dask``: the strip pairs matched on the workers, adjusted here.

Each strip, prepared here (its local trajectory, footprint, pairs), goes to the workers once,
in a task that builds its TIN (:func:`~lidarcal_ros.core.calibration.pair_work.with_tin`);
each pair's matching (its samples chosen, each iteration's correspondences, the QA's
distances) is then a task on the two strips' results, which the workers keep and pass among
themselves. The correspondences come back here, where the normal equations (with the strips'
trajectory blocks, docs/method.md section 11) are formed and solved as in a serial run, so
the estimate is the serial run's. A task whose worker dies runs again on another, its strips'
TINs built again from the task's own copy of them (the scheduler's).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import TypeVar

import numpy as np

from lidarcal_ros.core.adjustment.least_squares import Observations
from lidarcal_ros.core.calibration.matching import PairMatcher
from lidarcal_ros.core.calibration.pair_work import (
    PairJob,
    choose_task,
    distances_task,
    observe_task,
    with_tin,
)
from lidarcal_ros.core.calibration.pairs import PreparedStrip, StripPair
from lidarcal_ros.pipeline.executor import (
    CommandTasks,
    Executor,
    TaskFuture,
    results_in_order,
)

__all__ = ["ExecutorPairWork"]

R = TypeVar("R")


class ExecutorPairWork:
    """:class:`~lidarcal_ros.core.calibration.pair_work.PairWork` on an executor's workers
    (each strip sent once: the calibrators of ``auto`` share them)."""

    def __init__(self, executor: Executor) -> None:
        self.tasks = CommandTasks(executor, "calibrate")
        #: By strip id, the strip sent and its future (sent again where another strip of
        #: that id comes).
        self._strips: dict[int, tuple[PreparedStrip, TaskFuture[PreparedStrip]]] = {}

    def _strip(self, matcher: PairMatcher, k: int) -> TaskFuture[PreparedStrip]:
        """Strip ``k`` of ``matcher`` on the workers, with its TIN (submitted once)."""
        ps = matcher.strips[k]
        sent = self._strips.get(ps.strip_id)
        if sent is not None and sent[0] is ps:
            return sent[1]
        # (a copy as delivered: no TIN, no correction held)
        copy = dataclasses.replace(ps, tin=None, corrected=None)
        future = self.tasks.submit(with_tin, copy, matcher.settings, key=f"strip{ps.strip_id}")
        self._strips[ps.strip_id] = (ps, future)
        return future

    def _map(self, fn: Callable[[PreparedStrip, PreparedStrip, PairJob], R],
             matcher: PairMatcher, pairs: Sequence[StripPair], delta: np.ndarray | None,
             threshold: float, name: str) -> list[R]:
        futures = [self.tasks.submit(fn, self._strip(matcher, p.a), self._strip(matcher, p.b),
                                     PairJob.of(matcher, p, delta, threshold),
                                     key=f"{name}{p.index}") for p in pairs]
        return results_in_order(futures)

    def choose(self, matcher: PairMatcher, pairs: Sequence[StripPair]
               ) -> list[tuple[np.ndarray, np.ndarray]]:
        """Each pair's sample and "before" distances, chosen on the workers."""
        return self._map(choose_task, matcher, pairs, None, 0.0, "choose")

    def observe(self, matcher: PairMatcher, pairs: Sequence[StripPair], delta: np.ndarray,
                threshold: float) -> list[tuple[Observations, np.ndarray]]:
        """Each pair's correspondences at ``delta``, matched on the workers."""
        out = []
        for pair, (obs, patches, last) in zip(pairs, self._map(
                observe_task, matcher, pairs, delta, threshold, "observe"), strict=True):
            pair.last_triangle = last
            out.append((obs, patches))
        return out

    def distances(self, matcher: PairMatcher, pairs: Sequence[StripPair], delta: np.ndarray,
                  threshold: float) -> list[np.ndarray]:
        """Each pair's normal distances at ``delta``, matched on the workers."""
        out = []
        for pair, (distance, last) in zip(pairs, self._map(
                distances_task, matcher, pairs, delta, threshold, "qa"), strict=True):
            pair.last_triangle = last
            out.append(distance)
        return out
