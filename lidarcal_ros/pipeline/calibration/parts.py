"""``lidarcal calibrate --dask``: the strip pairs matched on the workers, adjusted here.

Each strip, prepared here (its local trajectory, footprint, pairs), goes to one worker, its
home, in a task that builds its TIN there
(:func:`~lidarcal_ros.core.calibration.pair_work.with_tin`), and stays there: a pair's
matching (its samples chosen, each iteration's correspondences, the QA's distances) runs at
the home of its strip ``b`` on the points of strip ``a`` it matches, cut at ``a``'s home
(:func:`~lidarcal_ros.core.calibration.pair_work.sample_side`); the control points and the
laser vectors' QA run at each strip's home. So a worker holds its own strips, not every
strip its pairs touch. The correspondences come back here, where the normal equations (with
the strips' trajectory blocks, docs/method.md section 11) are formed and solved as in a
serial run, so the estimate is the serial run's. A task whose worker dies runs again on
another, its strips' TINs built again from the task's own copy of them (the scheduler's).
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
    StripJob,
    choose_task,
    control_task,
    distances_task,
    laser_qa_task,
    observe_task,
    release_task,
    sample_side,
    with_tin,
)
from lidarcal_ros.core.calibration.pairs import PreparedStrip, StripPair
from lidarcal_ros.core.georeferencing.rigorous import LaserVectorQA
from lidarcal_ros.core.mission import ControlPoints, Strip
from lidarcal_ros.pipeline.executor import (
    CommandTasks,
    Executor,
    TaskFuture,
    deal_heaviest_first,
    results_in_order,
)

__all__ = ["ExecutorPairWork"]

R = TypeVar("R")


class ExecutorPairWork:
    """:class:`~lidarcal_ros.core.calibration.pair_work.PairWork` on an executor's workers
    (each strip sent once, to its home: the calibrators of ``auto`` share them)."""

    def __init__(self, executor: Executor) -> None:
        self.tasks = CommandTasks(executor, "calibrate")
        #: By strip id, the strip sent and its future (sent again where another strip of
        #: that id comes).
        self._strips: dict[int, tuple[PreparedStrip, TaskFuture[PreparedStrip]]] = {}
        #: By (strip a's id, strip b's id), the future of strip a these points were cut from,
        #: the points (indices) and the future of the cut.
        self._sides: dict[tuple[int, int], tuple[TaskFuture[PreparedStrip], np.ndarray,
                                                 TaskFuture[PreparedStrip]]] = {}
        #: The workers (as first asked) and at each the pairs matched there and the points
        #: of the strips it holds.
        self._places: list[str] = []
        self._load: list[tuple[int, ...]] = []
        #: By strip id, the strip dealt a home and that home.
        self._homes: dict[int, tuple[PreparedStrip, str]] = {}
        #: The tasks releasing corrections not known to have run.
        self._releases: list[TaskFuture[None]] = []

    def _strip(self, matcher: PairMatcher, k: int) -> tuple[TaskFuture[PreparedStrip],
                                                             str | None]:
        """Strip ``k`` of ``matcher`` on the workers, with its TIN (submitted once), and its
        home."""
        ps = matcher.strips[k]
        dealt = self._homes.get(ps.strip_id)
        if dealt is None or dealt[0] is not ps:
            self._deal(matcher)
        home = self._homes[ps.strip_id][1] if ps.strip_id in self._homes else None
        sent = self._strips.get(ps.strip_id)
        if sent is not None and sent[0] is ps:
            return sent[1], home
        # (a copy as delivered, of what matching reads: no intensity, no TIN, no correction)
        copy = dataclasses.replace(ps, strip=Strip(ps.strip_id, ps.strip.xyz, ps.strip.t),
                                   tin=None, corrected=None)
        future = self.tasks.submit(with_tin, copy, matcher.settings, key=f"strip{ps.strip_id}",
                                   place=home)
        self._strips[ps.strip_id] = (ps, future)
        return future, home

    def _deal(self, matcher: PairMatcher) -> None:
        """A home for each strip of ``matcher`` without one: a pair's matching runs at the
        home of its strip ``b``, so the strips are dealt the most pairs first, each to the
        worker with the fewest pairs so far (then points: the TINs' memory)."""
        if not self._places:
            self._places = self.tasks.executor.places()
            self._load = [(0, 0)] * len(self._places)
        if not self._places:
            return
        pairs = [0] * len(matcher.strips)
        for pair in matcher.pairs:
            pairs[pair.b] += 1
        todo = [k for k, ps in enumerate(matcher.strips) if ps.strip_id not in self._homes
                or self._homes[ps.strip_id][0] is not ps]
        weights = [(pairs[k], len(matcher.strips[k].strip)) for k in todo]
        for k, b in zip(todo, deal_heaviest_first(weights, self._load), strict=True):
            self._homes[matcher.strips[k].strip_id] = (matcher.strips[k], self._places[b])

    def _side(self, matcher: PairMatcher, pair: StripPair) -> TaskFuture[PreparedStrip]:
        """The points of the pair's strip ``a`` its tasks match (:meth:`PairJob.on_side`),
        cut at that strip's home (once while the strip and the points stay the same)."""
        index = pair.candidates if pair.sample is None else pair.sample
        ids = (matcher.strips[pair.a].strip_id, matcher.strips[pair.b].strip_id)
        strip, home = self._strip(matcher, pair.a)
        cut = self._sides.get(ids)
        if cut is None or cut[0] is not strip or not np.array_equal(cut[1], index):
            cut = (strip, index, self.tasks.submit(sample_side, strip, index,
                                                   key=f"side{ids[0]}-{ids[1]}", place=home))
            self._sides[ids] = cut
        return cut[2]

    def _map(self, fn: Callable[[PreparedStrip, PreparedStrip, PairJob], R],
             matcher: PairMatcher, pairs: Sequence[StripPair], delta: np.ndarray | None,
             threshold: float, name: str) -> list[R]:
        """``fn`` of each pair at the home of its strip ``b``, the pairs of one strip ``b``
        together and that strip's correction released after them."""
        by_b: dict[int, list[int]] = {}
        for i, p in enumerate(pairs):
            by_b.setdefault(p.b, []).append(i)
        futures: dict[int, TaskFuture[R]] = {}
        for b, members in by_b.items():
            strip, home = self._strip(matcher, b)
            for i in members:
                p = pairs[i]
                futures[i] = self.tasks.submit(
                    fn, self._side(matcher, p), strip,
                    PairJob.of(matcher, p, delta, threshold).on_side(),
                    key=f"{name}{p.index}", place=home)
            self._release(strip, home, [futures[i] for i in members])
        return results_in_order([futures[i] for i in range(len(pairs))])

    def _release(self, strip: TaskFuture[PreparedStrip], home: str | None,
                 done: Sequence[TaskFuture[object]]) -> None:
        """The strip's correction forgotten at its home once the tasks ``done`` have run
        (the next that needs it makes it again: with the strips of one process matched in
        turn, one strip is corrected whole at a time, not every one)."""
        # (held till done: Dask forgets a task whose future nobody holds, run or not)
        self._releases = [f for f in self._releases if not f.done()]
        self._releases.append(self.tasks.submit(release_task, strip, *done, key="release",
                                                place=home))

    def choose(self, matcher: PairMatcher, pairs: Sequence[StripPair]
               ) -> list[tuple[np.ndarray, np.ndarray]]:
        """Each pair's sample and "before" distances, chosen on the workers."""
        # (the sample as the side numbers its points, then as strip a does: sorted, as
        # ``stratified_sample`` gives it)
        return [(np.sort(p.candidates[sample]), before) for p, (sample, before) in zip(
            pairs, self._map(choose_task, matcher, pairs, None, 0.0, "choose"), strict=True)]

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

    def control(self, matcher: PairMatcher, control: ControlPoints,
                seen: dict[int, np.ndarray], delta: np.ndarray, threshold: float, *,
                delivered: bool) -> tuple[Observations, list[tuple[int, int, float]]]:
        """The control points matched at each strip's home (in the strips' order)."""
        futures = []
        for k, cps in seen.items():
            strip, home = self._strip(matcher, k)
            job = StripJob.of(matcher, k, delta, threshold, delivered=delivered)
            futures.append(self.tasks.submit(control_task, strip, control, cps, job,
                                             key=f"control{k}", place=home))
            self._release(strip, home, futures[-1:])
        parts = results_in_order(futures)
        return (Observations.concatenate(obs for obs, _ in parts),
                [match for _, found in parts for match in found])

    def laser_qa(self, matcher: PairMatcher, delta: np.ndarray) -> dict[int, LaserVectorQA]:
        """Each strip's laser-vector QA at ``delta``, at its home."""
        ks = [k for k, ps in enumerate(matcher.strips) if not ps.dropped]
        futures = []
        for k in ks:
            strip, home = self._strip(matcher, k)
            futures.append(self.tasks.submit(laser_qa_task, strip,
                                             StripJob.of(matcher, k, delta),
                                             key=f"laserqa{k}", place=home))
            self._release(strip, home, futures[-1:])
        return dict(zip(ks, results_in_order(futures), strict=True))
