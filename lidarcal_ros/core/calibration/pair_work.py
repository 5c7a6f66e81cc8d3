"""A calibration's per-pair matching run in other processes: the interface and the tasks.

A :class:`PairWork` set on a :class:`~lidarcal_ros.core.calibration.matching.PairMatcher`
(``remote``) matches its strip pairs instead of the threads: the samples chosen, each
iteration's correspondences, the QA's distances, and what is matched against one strip
(the control points, the laser vectors' QA). A pair's task takes strip ``b`` whole (its TIN
built by :func:`with_tin`) and of strip ``a`` the points it matches (:func:`sample_side`),
with a :class:`PairJob`; a strip's task takes the strip and a :class:`StripJob`. Each
computes what the matcher computes in this process, with its own methods, point by point
the same arithmetic, so the estimate is the same.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Protocol, cast

import numpy as np

from lidarcal_ros.core.adjustment.least_squares import Observations
from lidarcal_ros.core.calibration.pairs import CorrectedStrips, PreparedStrip, StripPair
from lidarcal_ros.core.calibration.threads import StageClock, WorkerPool
from lidarcal_ros.core.calibration.tin import Tin
from lidarcal_ros.core.georeferencing.rigorous import LaserVectorQA
from lidarcal_ros.core.mission import ControlPoints, Strip
from lidarcal_ros.core.params import N_PARAMETERS
from lidarcal_ros.core.trajectory.strip_errors import TrajectoryState

if TYPE_CHECKING:  # (the matcher and its options, which drive this module)
    from lidarcal_ros.core.calibration.calibrate import CalibrationSettings
    from lidarcal_ros.core.calibration.matching import PairMatcher


class PairWork(Protocol):
    """Matches a matcher's strip pairs elsewhere; each method returns one item per pair, in
    the order of ``pairs``."""

    def choose(self, matcher: PairMatcher, pairs: Sequence[StripPair]
               ) -> list[tuple[np.ndarray, np.ndarray]]:
        """:meth:`~lidarcal_ros.core.calibration.matching.PairMatcher.choose_sample` of each
        pair."""
        ...

    def observe(self, matcher: PairMatcher, pairs: Sequence[StripPair], delta: np.ndarray,
                threshold: float) -> list[tuple[Observations, np.ndarray]]:
        """:meth:`~lidarcal_ros.core.calibration.matching.PairMatcher.observe` of each pair's
        sample at ``delta`` (the strips corrected by it and the matcher's trajectory errors),
        within ``threshold`` m; each pair's ``last_triangle`` updated."""
        ...

    def distances(self, matcher: PairMatcher, pairs: Sequence[StripPair], delta: np.ndarray,
                  threshold: float) -> list[np.ndarray]:
        """The normal distances (m) of each pair's sample points matched at ``delta`` within
        ``threshold`` m (those matched only); each pair's ``last_triangle`` updated."""
        ...

    def control(self, matcher: PairMatcher, control: ControlPoints,
                seen: dict[int, np.ndarray], delta: np.ndarray, threshold: float, *,
                delivered: bool) -> tuple[Observations, list[tuple[int, int, float]]]:
        """:meth:`~lidarcal_ros.core.calibration.matching.PairMatcher.control_observations`,
        ``seen`` the control points (indices) each strip's footprint holds, by strip."""
        ...

    def laser_qa(self, matcher: PairMatcher, delta: np.ndarray) -> dict[int, LaserVectorQA]:
        """:meth:`~lidarcal_ros.core.calibration.matching.PairMatcher.laser_qa`."""
        ...


@dataclass(frozen=True)
class PairJob:
    """One pair's matching for a task: the pair (its indices, sample or candidates and last
    patches, nothing else), the estimate ``delta`` (8 biases, SI), the trajectory errors,
    the matching threshold (m), and the calibration's settings."""

    settings: CalibrationSettings
    trajectory: TrajectoryState
    pair: StripPair
    delta: np.ndarray
    threshold: float

    @classmethod
    def of(cls, matcher: PairMatcher, pair: StripPair, delta: np.ndarray | None = None,
           threshold: float = 0.0) -> PairJob:
        """The job of ``matcher``'s ``pair`` (copies: the matcher goes on changing; its
        candidates only while it has no sample: they are what a sample is chosen from)."""
        candidates = pair.candidates if pair.sample is None else np.empty(0, np.int64)
        slim = StripPair(pair.index, pair.a, pair.b, pair.coverage, candidates,
                         sample=pair.sample, last_triangle=pair.last_triangle)
        return cls(matcher.settings, _copy_state(matcher.trajectory), slim,
                   np.zeros(N_PARAMETERS) if delta is None else np.array(delta, np.float64),
                   float(threshold))

    def on_side(self) -> PairJob:
        """The job as its task takes it, strip ``a`` being :func:`sample_side` of the pair's
        sample (or, without one, of its candidates): those points numbered 0, 1, ..."""
        pair = self.pair
        if pair.sample is not None:
            slim = replace(pair, sample=np.arange(pair.sample.size))
        else:
            slim = replace(pair, candidates=np.arange(pair.candidates.size))
        return replace(self, pair=slim)


@dataclass(frozen=True)
class StripJob:
    """What is matched against one strip (its index ``strip``) for a task: the estimate
    ``delta`` (8 biases, SI; with ``delivered``, without the trajectory errors), the
    trajectory errors, the matching threshold (m), and the calibration's settings."""

    settings: CalibrationSettings
    trajectory: TrajectoryState
    strip: int
    delta: np.ndarray
    threshold: float = 0.0
    delivered: bool = False

    @classmethod
    def of(cls, matcher: PairMatcher, k: int, delta: np.ndarray, threshold: float = 0.0, *,
           delivered: bool = False) -> StripJob:
        """The job of ``matcher``'s strip ``k`` (copies: the matcher goes on changing)."""
        return cls(matcher.settings, _copy_state(matcher.trajectory), k,
                   np.array(delta, np.float64), float(threshold), delivered)


def _copy_state(state: TrajectoryState) -> TrajectoryState:
    return TrajectoryState(state.model, state.knot_interval_s, list(state.bases),
                           state.params.copy(), list(state.starts))


def with_tin(ps: PreparedStrip, settings: CalibrationSettings) -> PreparedStrip:
    """``ps`` with its TIN built (a task: what the pair tasks take)."""
    ps.tin = Tin(ps.strip.xyz, settings.tin_quality(ps.density))
    return ps


def sample_side(ps: PreparedStrip, index: np.ndarray) -> PreparedStrip:
    """The points ``index`` of ``ps`` alone, in that order (a task: strip ``a`` as a pair's
    task takes it, :meth:`PairJob.on_side`); no TIN, no correction."""
    strip = ps.strip
    return replace(ps, strip=Strip(strip.strip_id, strip.xyz[index], strip.t[index]),
                   geometry0=ps.geometry0.take(index),
                   priority=ps.priority[index] if ps.priority.size else ps.priority,
                   tin=None, corrected=None)


#: By strip (its id() in this process), the lock of the tasks that use it (:func:`_alone_with`).
_STRIP_LOCKS: dict[int, threading.Lock] = {}
_STRIP_LOCKS_LOCK = threading.Lock()


@contextmanager
def _alone_with(ps: PreparedStrip) -> Iterator[None]:
    """``ps`` used by this task alone in this process: the strip held at its home keeps its
    latest correction (``corrected``), which a worker's tasks share and a release forgets,
    so the threads of a worker of several take it in turn (a task reads it more than once)."""
    with _STRIP_LOCKS_LOCK:
        lock = _STRIP_LOCKS.setdefault(id(ps), threading.Lock())
    with lock:
        yield


def _matcher(strips: dict[int, PreparedStrip], settings: CalibrationSettings,
             trajectory: TrajectoryState) -> PairMatcher:
    """A matcher holding ``strips`` at their indices, the job's trajectory errors."""
    from lidarcal_ros.core.calibration.matching import PairMatcher

    matcher = PairMatcher(settings, StageClock(), WorkerPool(1, lambda stage, f: None))
    # (indexed as the calibration's strips: a mapping of those its methods read)
    matcher.strips = cast(list[PreparedStrip], strips)
    matcher.trajectory = trajectory
    return matcher


def _pair_matcher(a: PreparedStrip, b: PreparedStrip, job: PairJob) -> PairMatcher:
    return _matcher({job.pair.a: a, job.pair.b: b}, job.settings, job.trajectory)


def _corrected(matcher: PairMatcher, job: PairJob, *, delivered: bool = False
               ) -> CorrectedStrips:
    return {k: matcher.corrected(k, job.delta, delivered=delivered)
            for k in (job.pair.a, job.pair.b)}


def choose_task(a: PreparedStrip, b: PreparedStrip, job: PairJob
                ) -> tuple[np.ndarray, np.ndarray]:
    """The pair's sample and "before" distances (a task; :meth:`PairWork.choose`; ``a`` and
    the sample as ``job``'s pair numbers its points)."""
    with _alone_with(b):
        matcher = _pair_matcher(a, b, job)
        return matcher.choose_sample(job.pair, _corrected(matcher, job, delivered=True))


def observe_task(a: PreparedStrip, b: PreparedStrip, job: PairJob
                 ) -> tuple[Observations, np.ndarray, np.ndarray | None]:
    """The pair's correspondences, the patch of each sample point (-1: none) and its
    ``last_triangle`` (a task; :meth:`PairWork.observe`)."""
    with _alone_with(b):
        matcher = _pair_matcher(a, b, job)
        obs, patches = matcher.observe(job.pair, job.delta, _corrected(matcher, job),
                                       job.threshold)
    return obs, patches, job.pair.last_triangle


def distances_task(a: PreparedStrip, b: PreparedStrip, job: PairJob
                   ) -> tuple[np.ndarray, np.ndarray | None]:
    """:meth:`~lidarcal_ros.core.calibration.matching.PairMatcher.sample_distances` of the
    pair and its ``last_triangle`` (a task; :meth:`PairWork.distances`)."""
    with _alone_with(b):
        matcher = _pair_matcher(a, b, job)
        distances = matcher.sample_distances(job.pair, job.delta, _corrected(matcher, job),
                                             job.threshold)
    return distances, job.pair.last_triangle


def control_task(ps: PreparedStrip, control: ControlPoints, cps: np.ndarray, job: StripJob
                 ) -> tuple[Observations, list[tuple[int, int, float]]]:
    """The control points ``cps`` (indices) matched to the strip (a task; the strip's part of
    :meth:`PairWork.control`)."""
    with _alone_with(ps):
        matcher = _matcher({job.strip: ps}, job.settings, job.trajectory)
        xyz = matcher.corrected(job.strip, job.delta, delivered=job.delivered)
        return matcher.strip_control_observations(job.strip, control, cps, job.delta, xyz,
                                                  job.threshold)


def laser_qa_task(ps: PreparedStrip, job: StripJob) -> LaserVectorQA:
    """What the laser vectors of the strip's points corrected by the job's estimate say (a
    task; the strip's part of :meth:`PairWork.laser_qa`)."""
    with _alone_with(ps):
        matcher = _matcher({job.strip: ps}, job.settings, job.trajectory)
        return matcher.strip_laser_qa(job.strip, job.delta)


def release_task(ps: PreparedStrip, *done: object) -> None:
    """Forget the strip's latest correction (a task, after ``done``: the tasks that read it;
    a process holds a strip's corrected points only while what matches against it runs,
    24 bytes a point)."""
    with _alone_with(ps):
        ps.corrected = None


__all__ = ["PairJob", "PairWork", "StripJob", "choose_task", "control_task", "distances_task",
           "laser_qa_task", "observe_task", "release_task", "sample_side", "with_tin"]
