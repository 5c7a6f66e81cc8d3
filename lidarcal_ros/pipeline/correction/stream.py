"""Correction of a stream of clouds one after another, with neighbours across cloud boundaries.

What the corrector node and ``lidarcal correct`` both run (docs/correction.md, "A stream of
clouds").
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor, wait
from dataclasses import dataclass
from typing import Any

import numpy as np

from lidarcal_ros.core.flags import FLAG_NO_INTENSITY, FLAG_NOT_CORRECTED
from lidarcal_ros.core.mission import Trajectory
from lidarcal_ros.core.normals.strip_normals import NormalsTask, StripNormals
from lidarcal_ros.errors import LidarcalError
from lidarcal_ros.io.cloud.columns import extract_columns, float32_warning, time_span
from lidarcal_ros.pipeline.correction import batch as correction_batch
from lidarcal_ros.pipeline.correction.apply import (
    CorrectionSettings,
    surface_points,
    trajectory_heading,
)
from lidarcal_ros.pipeline.correction.batch import (
    BatchResult,
    CorrectionBatch,
    HeldCloud,
    OutputPlacer,
    cloud_volume,
    deliver_normals,
)
from lidarcal_ros.pipeline.correction.corrected_cloud import CloudTally, CorrectionStats

__all__ = ["DEFAULT_BATCH_POINTS", "MAX_GRID_GAP_S", "StreamCorrector", "iter_corrected"]

logger = logging.getLogger(__name__)

#: Default batch of the offline correction, points.
DEFAULT_BATCH_POINTS = 200_000
#: Points of a strip held for their look-ahead beyond a batch, at least (the limit is twice
#: what the strip's pace needs, :meth:`StripNormals.lookahead_points`: a spinning scanner's
#: clouds wait for a revolution's depth, some 50 m along track) and at most: bounds memory
#: when the points stop advancing along track (they would otherwise wait for ever).
_MIN_LOOKAHEAD_POINTS = 500_000
_MAX_LOOKAHEAD_POINTS = 3_000_000
#: A strip's normals grid is restarted after a turn of more than this (rad) or a gap in time
#: of more than this (s): the grid is aligned with the flight line. (A pause of more than
#: MAX_GRID_GAP_S in the clouds is where ``lidarcal correct --dask`` cuts a mission in parts.)
_MAX_GRID_TURN_RAD = math.radians(15.0)
MAX_GRID_GAP_S = 2.0


@dataclass
class _Strip:
    """The normals of one strip as its clouds arrive, and where the strip stands."""

    normals: StripNormals
    t_last: float
    #: Heading of the trajectory at the strip's first cloud, rad: what a turn is measured
    #: from (not the grid's, which is known only once the grid starts: a batch may hold the
    #: strip's first points and the turn after them).
    heading: float


class StreamCorrector:
    """Correct a stream of clouds, with neighbours across cloud boundaries (docs/correction.md).

    Parameters
    ----------
    trajectory : Trajectory
        The trajectory of the mission (at least up to the clouds pushed).
    settings : CorrectionSettings
    batch_points : int
        Clouds are corrected in batches of at least this many points (fewer, larger numpy
        calls); 0 corrects each cloud as soon as its normals are final (least latency).
    workers : int
        Batches corrected in parallel threads; 1 corrects in the calling thread.
    lookahead : bool
        Wait until the points after a cloud are there before fitting its normals, so that
        points at a cloud's leading edge have neighbours on both sides: the normals do not
        depend on how the stream is cut into clouds. False fits them at once against the
        points before (least latency).
    source : str
        Topic named in messages.
    place : callable(tag, n, dtype), optional
        Where to build each corrected cloud: an array of ``n`` rows of ``dtype`` (for
        instance inside the buffer it will be sent from), or None for a new array. Called
        from the worker threads.
    on_failed : callable(tag, exception), optional
        Called for each cloud of a batch whose correction raised (a bug, not bad input:
        malformed clouds are refused by :meth:`push`); the stream goes on with the next
        batch. Without it the exception propagates, and the clouds of that batch are lost.
    keep_tallies : bool
        Keep the :class:`CloudTally` of each corrected cloud in :attr:`tallies`, by tag,
        for the caller to take (tags must then be unique).

    Notes
    -----
    The normals of each strip come from one grid per strip (:class:`StripNormals`): every
    point is binned and evaluated once, whatever the clouds' size. :meth:`push` returns the
    corrected clouds that became ready, as ``(tag, array)`` in the order pushed;
    :meth:`release` corrects everything held now (a time-out: later clouds still see these
    points as neighbours); :meth:`flush` ends the stream (and stops the workers). Held in
    memory: the clouds waiting for their look-ahead (a few grid rows), the moment sums of the
    grid rows around them and ``workers + 1`` batches in flight. The output does not depend
    on the number of workers or on timing.
    """

    def __init__(
        self,
        trajectory: Trajectory,
        settings: CorrectionSettings,
        *,
        batch_points: int = DEFAULT_BATCH_POINTS,
        workers: int = 1,
        lookahead: bool = True,
        source: str = "cloud",
        place: OutputPlacer | None = None,
        on_failed: Callable[[Any, Exception], None] | None = None,
        keep_tallies: bool = False,
    ) -> None:
        self.trajectory = trajectory
        self.keep_tallies = keep_tallies
        self.tallies: dict[Any, CloudTally] = {}
        self.place = place
        self.on_failed = on_failed
        self.settings = settings
        self.batch_points = max(int(batch_points), 0)
        self.workers = max(int(workers), 1)
        self.lookahead = lookahead
        self.source = source
        self.stats = CorrectionStats()
        self._queue: deque[HeldCloud] = deque()
        self._strips: dict[int, _Strip] = {}
        self._warned_intensity = False
        self._float32_step = 0.0  # the coarsest FLOAT32 coordinate step warned about
        self._pool: ThreadPoolExecutor | None = None
        self._inflight: deque[tuple[list[Any], Future[Any]]] = deque()
        self._late_done = 0
        self._tasks: list[NormalsTask] = []
        self._unbinned: list[HeldCloud] = []  # queued, not yet given to the strips' grids
        self._unbinned_points = 0
        #: When each strip was flown so far: strip id (-1: clouds without one) -> its points'
        #: earliest and latest time, s (the corrected trajectory's strips).
        self.strip_spans: dict[int, tuple[float, float]] = {}

    @property
    def held_points(self) -> int:
        """Points pushed and not yet released."""
        return sum(len(m) for m in self._queue)

    @property
    def late_points(self) -> int:
        """Points that arrived behind their strip's grid (no normal), so far."""
        return sum(s.normals.late_points for s in self._strips.values()) + self._late_done

    def set_trajectory(self, trajectory: Trajectory) -> None:
        """Use a newer trajectory (e.g. grown while streaming) from the next batch on."""
        self.trajectory = trajectory

    def set_settings(self, settings: CorrectionSettings) -> None:
        """Use new settings (calibration, radiometry) from the next batch on."""
        self.settings = settings

    def start(self) -> None:
        """Start the worker threads now (they otherwise start with the first batch)."""
        if self.workers > 1 and self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=self.workers,
                                            thread_name_prefix="lidarcal-correct")

    def close(self) -> None:
        """Stop the workers (also done by :meth:`flush`)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    def push(self, points: np.ndarray, tag: Any = None) -> list[tuple[Any, np.ndarray]]:
        """Add a cloud (structured array); returns the corrected clouds now ready.

        Raises
        ------
        CloudFormatError
            The cloud lacks ``x, y, z`` or its time field, or has unsupported types (nothing
            is added).
        """
        return self.push_many([(points, tag)])

    def push_many(
        self, clouds: list[tuple[np.ndarray, Any]], *,
        on_error: Callable[[Any, LidarcalError], None] | None = None,
    ) -> list[tuple[Any, np.ndarray]]:
        """Add several clouds at once (one evaluation of the normals for all: a backlog
        catches up faster); returns the corrected clouds now ready.

        Parameters
        ----------
        clouds : list of (structured array, tag)
        on_error : callable(tag, error), optional
            Called for each malformed cloud, which is then skipped; without it the first
            malformed cloud raises before anything is added.
        """
        msgs: list[HeldCloud] = []
        for points, tag in clouds:
            try:
                msgs.append(self._message(points, tag))
            except LidarcalError as exc:
                if on_error is None:
                    raise
                on_error(tag, exc)
        for m in msgs:
            self._enqueue(m)
        if self._unbinned_points >= self.batch_points:
            self._bin_pending()
        return self._drain(final=False)

    def set_lookahead(self, lookahead: bool) -> None:
        """Wait for look-ahead (or not) from the next cloud on."""
        self.lookahead = lookahead
        for s in self._strips.values():
            s.normals.lookahead = lookahead

    def release(self) -> list[tuple[Any, np.ndarray]]:
        """Correct everything held now, without waiting for look-ahead (the strips' grids
        are kept: later clouds still have these points as neighbours); with worker threads,
        waits for the batches in flight."""
        out = self._drain(final=True)
        out.extend(self._collect(wait_all=True))
        return out

    @property
    def in_flight(self) -> int:
        """Batches handed to the worker threads and not yet returned."""
        return len(self._inflight)

    def collect_ready(self, timeout: float = 0.0) -> list[tuple[Any, np.ndarray]]:
        """The corrected clouds of batches the worker threads have finished (in order),
        waiting up to ``timeout`` seconds for the oldest one. Without it the results of
        the last batches before a pause would wait for the next :meth:`push`."""
        if self._inflight and timeout > 0:
            wait([self._inflight[0][1]], timeout=timeout)
        return self._collect(wait_all=False)

    def flush(self) -> list[tuple[Any, np.ndarray]]:
        """Correct everything held (the end of the stream); stop the workers."""
        try:
            out = self.release()
            for s in self._strips.values():
                self._late_done += s.normals.late_points
            self._strips.clear()
        finally:
            self.close()
        return out

    # -- internals -------------------------------------------------------------------

    def _message(self, points: np.ndarray, tag: Any) -> HeldCloud:
        cols = extract_columns(points, time_field=self.settings.time_field, source=self.source,
                               coordinate_tolerance_m=self.settings.coordinate_tolerance_m)
        if cols.coordinate_step_m > self._float32_step:
            self._float32_step = cols.coordinate_step_m
            note = float32_warning(cols.coordinate_step_m, self.settings.coordinate_tolerance_m)
            if note:
                logger.warning("%s: %s", self.source, note)
        if len(points) and cols.intensity is None and not self._warned_intensity:
            logger.warning("%s: clouds without an 'intensity' field: geometry is corrected, "
                           "reflectance is NaN (flag %d)", self.source, FLAG_NO_INTENSITY)
            self._warned_intensity = True
        return HeldCloud(tag, points, cols)

    def _enqueue(self, m: HeldCloud) -> None:
        """Queue a cloud and note the strips among its points (binned later, in batches)."""
        self._queue.append(m)
        if not len(m):
            return
        g = m.columns.strip_id
        if g is None or g.min() == g.max():
            m.strip_parts = [(-1 if g is None else int(g[0]), None)]
        else:
            m.strip_parts = [(int(k), np.flatnonzero(g == k)) for k in np.unique(g)]
        m.parts = len(m.strip_parts)
        self._unbinned.append(m)
        self._unbinned_points += len(m)

    def _bin_pending(self) -> None:
        """Give the points of the queued clouds to the grids of their strips, in order; the
        clouds of a strip are binned together (fewer, larger numpy calls)."""
        batches: dict[int, list[tuple[object, np.ndarray, np.ndarray | None]]] = {}

        def bin_strip(strip_id: int) -> None:
            parts = batches.pop(strip_id, None)
            if parts:
                self._strips[strip_id].normals.add_many(parts)

        for m in self._unbinned:
            cols = m.columns
            # Volume returns stay out of the grids: the planes follow the last returns.
            surface = surface_points(cols.xyz, cloud_volume(cols))
            for strip_id, idx in m.strip_parts:
                xyz = surface if idx is None else surface[idx]
                t = cols.t if idx is None else cols.t[idx]
                t_lo, t_hi = (cols.t_span if idx is None and cols.t_span is not None
                              else time_span(t))
                heading = trajectory_heading(self.trajectory, 0.5 * (t_lo + t_hi))
                strip = self._strips.get(strip_id)
                if strip is not None and self._strip_ended(strip, heading, t_lo):
                    bin_strip(strip_id)
                    self._finish_strip(strip_id)
                    strip = None
                if strip is None:
                    strip = _Strip(StripNormals(self._heading_at, lookahead=self.lookahead),
                                   t_hi, heading)
                    self._strips[strip_id] = strip
                if math.isfinite(t_hi):
                    strip.t_last = (max(strip.t_last, t_hi) if math.isfinite(strip.t_last)
                                    else t_hi)
                    lo, hi = self.strip_spans.get(strip_id, (t_lo, t_hi))
                    self.strip_spans[strip_id] = (min(lo, t_lo), max(hi, t_hi))
                batches.setdefault(strip_id, []).append(((m, idx), xyz, t))
        for strip_id in list(batches):
            bin_strip(strip_id)
        self._unbinned, self._unbinned_points = [], 0

    def _heading_at(self, t: float) -> float:
        return trajectory_heading(self.trajectory, t)

    @staticmethod
    def _strip_ended(strip: _Strip, heading: float, t_lo: float) -> bool:
        """A gap in time or a turn: the strip's grid no longer fits the new points."""
        turn = abs(math.remainder(heading - strip.heading, 2.0 * math.pi))
        if not math.isfinite(turn):
            turn = 0.0
        gap = t_lo - strip.t_last if math.isfinite(t_lo + strip.t_last) else 0.0
        return turn > _MAX_GRID_TURN_RAD or gap > MAX_GRID_GAP_S

    def _finish_strip(self, strip_id: int) -> None:
        strip = self._strips.pop(strip_id)
        self._schedule(strip.normals.take_ready(final=True))
        self._late_done += strip.normals.late_points

    def _schedule(self, task: NormalsTask | None) -> None:
        if task is None:
            return
        self._tasks.append(task)
        for key in task.keys:
            message: HeldCloud = key[0]  # type: ignore[index]
            message.scheduled += 1

    def _drain(self, *, final: bool) -> list[tuple[Any, np.ndarray]]:
        if final and self._unbinned:
            self._bin_pending()
        # Strips that ended long before the newest point: finish them (their last clouds
        # would otherwise wait for a look-ahead that never comes, and hold up the output).
        newest = max((s.t_last for s in self._strips.values()), default=math.nan)
        for strip_id, s in list(self._strips.items()):
            if newest - s.t_last > MAX_GRID_GAP_S:
                self._finish_strip(strip_id)
        for s in self._strips.values():
            # A strip whose points stop advancing along track (hovering, stalled times)
            # would hold its clouds for ever: bounded.
            limit = min(max(2.0 * s.normals.lookahead_points(), _MIN_LOOKAHEAD_POINTS),
                        _MAX_LOOKAHEAD_POINTS)
            stalled = s.normals.pending_points() > limit + self.batch_points
            self._schedule(s.normals.take_ready(final=final or stalled,
                                                min_points=self.batch_points))
        done: list[HeldCloud] = []
        while self._queue and self._queue[0].scheduled == self._queue[0].parts:
            done.append(self._queue.popleft())
        out: list[tuple[Any, np.ndarray]] = []
        if not done:
            return out
        # The evaluations go with the clouds they complete, into a worker; one that also
        # serves a cloud still waiting (for another strip's normals) runs here, now.
        in_job = {id(m) for m in done}
        tasks, self._tasks = self._tasks, []
        job_tasks: list[NormalsTask] = []
        for task in tasks:
            if all(id(key[0]) in in_job for key in task.keys):  # type: ignore[index]
                job_tasks.append(task)
            else:
                deliver_normals(task.run())
        self._submit(CorrectionBatch(job_tasks, done, self.trajectory, self.settings,
                                     self.place), out)
        return out

    def _submit(self, job: CorrectionBatch, out: list[tuple[Any, np.ndarray]]) -> None:
        tags = [m.tag for m in job.messages]
        if self.workers == 1:
            try:
                result = correction_batch.run_batch(job, self.source)
            except Exception as exc:
                self._failed(tags, exc)
                return
            self._account(tags, result, out)
            return
        self.start()
        assert self._pool is not None
        self._inflight.append((tags, self._pool.submit(correction_batch.run_batch, job,
                                                                 self.source)))
        out.extend(self._collect(wait_all=False))

    def _collect(self, *, wait_all: bool) -> list[tuple[Any, np.ndarray]]:
        """Results of finished batches, in order; waits while too many are in flight."""
        out: list[tuple[Any, np.ndarray]] = []
        while self._inflight and (wait_all or self._inflight[0][1].done()
                                  or len(self._inflight) > self.workers):
            tags, future = self._inflight.popleft()
            try:
                result = future.result()
            except Exception as exc:
                self._failed(tags, exc)
                continue
            self._account(tags, result, out)
        return out

    def _failed(self, tags: list[Any], exc: Exception) -> None:
        """A batch raised: its clouds go to ``on_failed`` (or the exception on up)."""
        if self.on_failed is None:
            raise exc
        logger.error("%s: correction of %d cloud(s) failed: %s: %s", self.source, len(tags),
                     type(exc).__name__, exc, exc_info=exc)
        for tag in tags:
            self.on_failed(tag, exc)

    def _account(self, tags: list[Any],
                 result: BatchResult,
                 out: list[tuple[Any, np.ndarray]]) -> None:
        clouds, tallies, seconds, choice = result
        self.stats.clouds += len(clouds)
        self.stats.seconds += seconds
        if choice is not None:
            self.stats.add_model(choice.model, choice.reason,
                                 sum(t.points - t.flagged(FLAG_NOT_CORRECTED) for t in tallies))
        for tag, tally in zip(tags, tallies, strict=True):
            self.stats.add(tally)
            if self.keep_tallies:
                self.tallies[tag] = tally
        out.extend(zip(tags, clouds, strict=True))


def iter_corrected(
    clouds: Iterator[np.ndarray], trajectory: Trajectory, settings: CorrectionSettings, *,
    batch_points: int = DEFAULT_BATCH_POINTS, source: str = "cloud",
) -> Iterator[np.ndarray]:
    """Corrected clouds of an iterable of clouds, in order (in-memory streaming)."""
    corrector = StreamCorrector(trajectory, settings, batch_points=batch_points, source=source)
    for points in clouds:
        for _tag, out in corrector.push(points):
            yield out
    for _tag, out in corrector.flush():
        yield out
