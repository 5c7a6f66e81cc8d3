"""A calibration's per-pair matching run in other processes: the interface and the tasks.

A :class:`PairWork` set on a :class:`~lidarcal_ros.core.calibration.matching.PairMatcher`
(``remote``) matches its strip pairs instead of the threads: the samples chosen, each
iteration's correspondences, the QA's distances. Each task is a pure function of the two
prepared strips (their TINs built by :func:`with_tin`) and a :class:`PairJob`, and computes
what the matcher computes in this process, with its own methods, so the estimate is the same.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol, cast

import numpy as np

from lidarcal_ros.core.adjustment.least_squares import Observations
from lidarcal_ros.core.calibration.pairs import CorrectedStrips, PreparedStrip, StripPair
from lidarcal_ros.core.calibration.threads import StageClock, WorkerPool
from lidarcal_ros.core.calibration.tin import Tin
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


def _copy_state(state: TrajectoryState) -> TrajectoryState:
    return TrajectoryState(state.model, state.knot_interval_s, list(state.bases),
                           state.params.copy(), list(state.starts))


def with_tin(ps: PreparedStrip, settings: CalibrationSettings) -> PreparedStrip:
    """``ps`` with its TIN built (a task: what the pair tasks take)."""
    ps.tin = Tin(ps.strip.xyz, settings.tin_quality(ps.density))
    return ps


def _matcher(a: PreparedStrip, b: PreparedStrip, job: PairJob) -> PairMatcher:
    """A matcher holding the pair's two strips at their indices, the job's trajectory
    errors."""
    from lidarcal_ros.core.calibration.matching import PairMatcher

    matcher = PairMatcher(job.settings, StageClock(), WorkerPool(1, lambda stage, f: None))
    # (indexed as the calibration's strips: a mapping of the two its methods read)
    matcher.strips = cast(list[PreparedStrip], {job.pair.a: a, job.pair.b: b})
    matcher.trajectory = job.trajectory
    return matcher


def _corrected(matcher: PairMatcher, job: PairJob, *, delivered: bool = False
               ) -> CorrectedStrips:
    return {k: matcher.corrected(k, job.delta, delivered=delivered)
            for k in (job.pair.a, job.pair.b)}


def choose_task(a: PreparedStrip, b: PreparedStrip, job: PairJob
                ) -> tuple[np.ndarray, np.ndarray]:
    """The pair's sample and "before" distances (a task; :meth:`PairWork.choose`)."""
    matcher = _matcher(a, b, job)
    return matcher.choose_sample(job.pair, _corrected(matcher, job, delivered=True))


def observe_task(a: PreparedStrip, b: PreparedStrip, job: PairJob
                 ) -> tuple[Observations, np.ndarray, np.ndarray | None]:
    """The pair's correspondences, the patch of each sample point (-1: none) and its
    ``last_triangle`` (a task; :meth:`PairWork.observe`)."""
    matcher = _matcher(a, b, job)
    obs, patches = matcher.observe(job.pair, job.delta, _corrected(matcher, job),
                                   job.threshold)
    return obs, patches, job.pair.last_triangle


def distances_task(a: PreparedStrip, b: PreparedStrip, job: PairJob
                   ) -> tuple[np.ndarray, np.ndarray | None]:
    """:meth:`~lidarcal_ros.core.calibration.matching.PairMatcher.sample_distances` of the
    pair and its ``last_triangle`` (a task; :meth:`PairWork.distances`)."""
    matcher = _matcher(a, b, job)
    distances = matcher.sample_distances(job.pair, job.delta, _corrected(matcher, job),
                                         job.threshold)
    return distances, job.pair.last_triangle


__all__ = ["PairJob", "PairWork", "choose_task", "distances_task", "observe_task", "with_tin"]
