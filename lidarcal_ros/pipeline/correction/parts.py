"""``lidarcal correct --dask``: the clouds corrected in parts by workers, assembled here in order.

The mission is cut only where its clouds pause for longer than
:data:`~lidarcal_ros.pipeline.correction.stream.MAX_GRID_GAP_S` (between strips): there every
strip's normals grid restarts in a serial run too, so each part, corrected from a fresh
:class:`~lidarcal_ros.pipeline.correction.stream.StreamCorrector` with the whole trajectory,
gives the bytes the serial run gives. Workers read the bag from its path (which they must
share) and write each part's corrected clouds to a file beside the output, atomically (a part
run again after its worker died writes it whole again); this process writes the output from
the parts in the input's order, with the same writer calls as :func:`correct_bag`.
"""

from __future__ import annotations

import logging
import math
import os
import shutil
import socket
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lidarcal_ros.core.mission import Trajectory
from lidarcal_ros.core.radiometry import describe_alpha
from lidarcal_ros.errors import InputError
from lidarcal_ros.io.bag.prefetch import WriteBehind
from lidarcal_ros.io.cloud.columns import resolve_time_field
from lidarcal_ros.pipeline.correction import bag as bag_correction
from lidarcal_ros.pipeline.correction.apply import CorrectionSettings
from lidarcal_ros.pipeline.correction.corrected_cloud import CorrectionStats
from lidarcal_ros.pipeline.correction.stream import MAX_GRID_GAP_S, StreamCorrector
from lidarcal_ros.pipeline.correction.trajectory_gate import TrajectoryGate
from lidarcal_ros.pipeline.executor import Executor, TaskFuture, results_in_turn

__all__ = ["PARTS_PER_WORKER", "CloudSpan", "correct_in_parts", "plan_parts"]

logger = logging.getLogger(__name__)

#: Parts per worker (more balance the load; each part reads the bag up to its first cloud).
PARTS_PER_WORKER = 2


@dataclass(frozen=True)
class CloudSpan:
    """A cloud of the input as the parts are planned: its points and their earliest and
    latest finite time (s; NaN where none)."""

    points: int
    t_min: float
    t_max: float


def plan_parts(clouds: list[CloudSpan], parts: int) -> list[tuple[int, int]]:
    """Up to ``parts`` ranges ``[first, end)`` of cloud indices, covering every cloud in
    order, of about equal points, cut only before a cloud whose points all come more than
    :data:`MAX_GRID_GAP_S` after every point before it. One range where there is no such
    pause, or where a cloud with points has no finite time (its place is unknown)."""
    n = len(clouds)
    if n == 0:
        return []
    if any(c.points and not math.isfinite(c.t_min) for c in clouds):
        return [(0, n)]
    t_min = np.array([c.t_min if c.points else np.inf for c in clouds])
    t_max = np.array([c.t_max if c.points else -np.inf for c in clouds])
    before = np.maximum.accumulate(t_max)  # latest time up to each cloud
    after = np.minimum.accumulate(t_min[::-1])[::-1]  # earliest from each cloud on
    # (strictly more than the gap, as the corrector restarts its grids)
    cuts = [k for k in range(1, n) if after[k] - before[k - 1] > MAX_GRID_GAP_S]
    counts = np.array([c.points for c in clouds], dtype=np.int64)
    share = counts.sum() / max(parts, 1)
    ranges: list[tuple[int, int]] = []
    first = 0
    for k in cuts:
        if int(counts[first:k].sum()) >= share and len(ranges) < parts - 1:
            ranges.append((first, k))
            first = k
    ranges.append((first, n))
    return ranges


@dataclass(frozen=True)
class _PartTask:
    """One part for a worker: the clouds ``[first, end)`` of ``bag``'s ``points_topic``,
    corrected with ``trajectory`` (its frame ``frame``) and ``settings`` into ``path``."""

    bag: str
    points_topic: str
    frame: str
    trajectory: Trajectory
    settings: CorrectionSettings
    kind: str
    batch_points: int
    first: int
    end: int
    path: str


@dataclass
class _PartResult:
    """What a worker returns of a part: where each corrected cloud is in its file
    (``(log time ns, byte offset, bytes, dtype)``, dtype None for a bag's message bytes),
    its counts, the strips' time spans and the clouds' time field."""

    clouds: list[tuple[int, int, int, np.dtype[Any] | None]] = field(default_factory=list)
    stats: CorrectionStats = field(default_factory=CorrectionStats)
    strip_spans: dict[int, tuple[float, float]] = field(default_factory=dict)
    time_field: str | None = None


def _correct_part(task: _PartTask) -> _PartResult:
    """Correct a part (on a worker): the clouds read from the bag, corrected as
    :func:`correct_bag` corrects them, their bytes written to ``task.path`` atomically."""
    from lidarcal_ros.io.bag.reader import open_bag

    for path, what in ((task.bag, "the input"), (os.path.dirname(task.path), "the output's "
                                                 "folder")):
        if not os.path.exists(path):
            raise InputError(f"{path}: not found on Dask worker {socket.gethostname()}: the "
                             f"workers must see {what} at the same path (a shared file "
                             "system)")
    messages = bag_correction._CorrectedMessages() if task.kind == "bag" else None
    corrector = StreamCorrector(task.trajectory, task.settings, batch_points=task.batch_points,
                                source=task.points_topic, keep_tallies=messages is not None,
                                place=None if messages is None else messages.place)
    gate = TrajectoryGate.known(corrector, task.frame, source=task.bag,
                                topic=task.points_topic)
    result = _PartResult()
    partial = f"{task.path}.partial"
    offset = 0
    with open_bag(task.bag) as bag, open(partial, "wb") as out:

        def keep(done: list[tuple[Any, np.ndarray]]) -> None:
            nonlocal offset
            for k, corrected in done:
                if messages is not None:
                    ns, data = messages.release(k, corrector.tallies.pop(k).dense)
                    dtype = None
                else:
                    ns, data, dtype = 0, np.ascontiguousarray(corrected), corrected.dtype
                out.write(data.data)
                result.clouds.append((ns, offset, data.nbytes, dtype))
                offset += data.nbytes

        for k, (topic, msgtype, ns, raw) in enumerate(bag.messages([task.points_topic])):
            if k >= task.end:
                break
            if k < task.first:
                continue
            msg, points = bag_correction._cloud_points(bag, msgtype, raw, topic)
            if result.time_field is None and len(points):
                result.time_field = resolve_time_field(points, task.settings.time_field,
                                                       source=topic)
            if messages is not None:
                messages.hold(k, ns, msg)
            for tag, ready in gate.cloud(k, msg, points):
                keep(corrector.push(ready, tag))
        keep(corrector.flush())
    os.replace(partial, task.path)
    result.stats, result.strip_spans = corrector.stats, corrector.strip_spans
    return result


class _Parts:
    """The parts' futures and files, read back in order."""

    def __init__(self, futures: list[TaskFuture[_PartResult]], paths: list[str],
                 progress: Any) -> None:
        self._futures, self._paths, self._progress = futures, paths, progress
        self.stats = CorrectionStats()
        self.strip_spans: dict[int, tuple[float, float]] = {}
        self.time_field: str | None = None

    def __iter__(self) -> Any:
        """``(log time ns, array)`` of every corrected cloud, in order (uint8 message bytes
        for a bag, the corrected points for LAS), the parts' counts merged as they come."""
        for i, (part, path) in enumerate(zip(results_in_turn(self._futures), self._paths,
                                             strict=True)):
            self.stats.merge(part.stats)
            for strip, (lo, hi) in part.strip_spans.items():
                old = self.strip_spans.get(strip, (lo, hi))
                self.strip_spans[strip] = (min(old[0], lo), max(old[1], hi))
            self.time_field = self.time_field or part.time_field
            data = (np.memmap(path, dtype=np.uint8, mode="r") if os.path.getsize(path)
                    else np.zeros(0, np.uint8))
            for ns, offset, nbytes, dtype in part.clouds:
                chunk = data[offset:offset + nbytes]
                yield ns, (chunk if dtype is None else chunk.view(dtype))
            if self._progress:
                self._progress("correcting", (i + 1) / len(self._futures))


def correct_in_parts(bag: Any, request: Any, executor: Executor
                     ) -> bag_correction.CorrectionReport:
    """:func:`~lidarcal_ros.pipeline.correction.bag.correct_bag` after its checks, the
    clouds corrected in parts by ``executor`` (``request``: its ``_Request``)."""
    from lidarcal_ros.io.cloud.trajectory_messages import TrajectorySamples

    points_topic, traj_topic, _corrected_topic = request.topics
    out_path: Path = request.out_path
    kind = bag_correction.output_kind(out_path)
    if request.progress:
        request.progress("reading trajectory", 0.0)
    samples = TrajectorySamples()
    poses = bag_correction._PoseMessages() if request.moved_topic is not None else None
    add = bag_correction._pose_reader(bag, traj_topic, samples)
    spans: list[CloudSpan] = []
    for topic, msgtype, ns, raw in bag.messages([points_topic, traj_topic]):
        if topic == traj_topic:
            add(msgtype, raw)
            if poses is not None:
                poses.add(ns, msgtype, raw)
        else:
            spans.append(_cloud_span(bag, msgtype, raw, topic, request.settings.time_field))
    trajectory, frame = bag_correction._checked_trajectory(bag, traj_topic, samples,
                                                           request.settings)
    settings, meaning = bag_correction.radiometry_of(bag, request, request.settings)
    ranges = plan_parts(spans, PARTS_PER_WORKER * executor.workers)
    logger.info("%s: %d clouds in %d parts on %s", bag.path, len(spans), len(ranges),
                executor.description)
    # The part files sit beside the output (a path the workers share), removed on every
    # way out.
    folder = tempfile.mkdtemp(prefix=f".{out_path.name}.parts-", dir=out_path.parent)
    try:
        paths = [os.path.join(folder, f"part-{i:05d}") for i in range(len(ranges))]
        futures = [executor.submit(_correct_part, _PartTask(
            str(bag.path), points_topic, frame, trajectory, settings, kind,
            request.options.batch_points, first, end, path), key=f"lidarcal-correct-{path}")
            for (first, end), path in zip(ranges, paths, strict=True)]
        parts = _Parts(futures, paths, request.progress)
        corrector = StreamCorrector(trajectory, settings, source=points_topic)
        corrector.stats = parts.stats
        corrector.strip_spans = parts.strip_spans
        report = bag_correction.CorrectionReport(
            out_path, kind, corrector.stats, frame_id=frame,
            atmosphere=describe_alpha(settings.radiometry),
            reflectance=meaning, warnings=list(request.warnings))
        job = bag_correction._Job(
            bag, corrector, TrajectoryGate.known(corrector, frame, source=str(bag.path),
                                                 topic=points_topic),
            out_path, points_topic, traj_topic, request.topics[2], request.options.overwrite,
            max(len(spans), 1), request.progress, report, request.moved_topic, poses)
        if kind == "las":
            _assemble_las(job, parts, request.options.crs)
        else:
            _assemble_bag(job, parts)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    report.frame_id = frame
    if request.options.trajectory_out is not None:
        bag_correction._write_trajectory_file(job, Path(request.options.trajectory_out),
                                              request.options)
    return report


def _cloud_span(bag: Any, msgtype: str, raw: bytes, topic: str, time_field: str) -> CloudSpan:
    """A cloud's points and time span (s)."""
    _msg, points = bag_correction._cloud_points(bag, msgtype, raw, topic)
    if not len(points):
        return CloudSpan(0, math.nan, math.nan)
    t = points[resolve_time_field(points, time_field, source=topic)]
    finite = t[np.isfinite(t)]
    if not len(finite):
        return CloudSpan(len(points), math.nan, math.nan)
    return CloudSpan(len(points), float(finite.min()), float(finite.max()))


def _assemble_bag(job: Any, parts: _Parts) -> None:
    """The output bag from the parts: the calls to the writer
    :func:`~lidarcal_ros.pipeline.correction.bag.correct_bag` makes, in its order."""
    bag = job.bag
    with bag_correction.bag_output(job) as (writer, copied, output):
        if copied is not None:  # (the other messages are in the output already)
            for k, cloud in enumerate(parts):
                output.hold(k)
                output.corrected(k, *cloud)
                output.emit()
        else:
            clouds = iter(parts)
            for k, (topic, msgtype, ns, raw) in enumerate(bag.messages(None)):
                output.pass_through(k, topic, msgtype, ns, raw)
                if topic == job.points_topic:
                    output.hold(k)
                    output.corrected(k, *next(clouds))
                output.emit()
        output.emit_all()
        bag_correction._check_something_corrected(job.corrector.stats, bag.path,
                                                  job.points_topic)
        if job.moved_topic is not None:
            bag_correction._write_moved_poses(job, writer)


def _assemble_las(job: Any, parts: _Parts, crs: Any) -> None:
    """The output LAS/LAZ file from the parts, in the runs
    :func:`~lidarcal_ros.pipeline.correction.bag.correct_bag` writes."""
    from lidarcal_ros.io.survey.las_writer import LasChunkWriter

    settings = job.corrector.settings
    with LasChunkWriter(job.out_path, time_field=settings.time_field, crs=crs,
                        overwrite=job.overwrite,
                        reflectance_description=settings.radiometry.las_description,
                        ) as writer, WriteBehind(bag_correction._write_parts(writer),
                                                 name="lidarcal-las") as write_run:
        runs = bag_correction.LasRuns(write_run)
        for _ns, corrected in parts:
            if parts.time_field is not None:
                writer.time_field = parts.time_field
            runs.add([(None, corrected)])
        runs.add([], final=True)
        write_run.finish()
        bag_correction._check_something_corrected(job.corrector.stats, job.bag.path,
                                                  job.points_topic)
    bag_correction.las_warnings(job.report, writer.stats, job.out_path)
