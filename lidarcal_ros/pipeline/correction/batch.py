"""One batch of a stream's clouds: their normals delivered, the batch corrected, each cloud built.

The :class:`~lidarcal_ros.pipeline.correction.stream.StreamCorrector` chooses the batches;
:func:`run_batch` does the work, in the calling thread or a worker thread.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lidarcal_ros.core.georeferencing.rigorous import ModelChoice
from lidarcal_ros.core.mission import Trajectory
from lidarcal_ros.core.normals.grid_normals import GridNormals, no_normals
from lidarcal_ros.core.normals.strip_normals import NormalsTask
from lidarcal_ros.core.radiometry import volume_returns
from lidarcal_ros.io.cloud.columns import CloudColumns
from lidarcal_ros.pipeline.correction.apply import CorrectionSettings, correct_columns
from lidarcal_ros.pipeline.correction.corrected_cloud import (
    CloudTally,
    build_corrected,
    corrected_dtype,
    row_target,
)

__all__ = [
    "BatchResult", "CorrectionBatch", "HeldCloud", "OutputPlacer", "cloud_volume",
    "deliver_normals", "run_batch",
]

#: ``place(tag, n, dtype)``: an array of ``n`` rows of ``dtype`` to build a corrected cloud
#: in, or None (:class:`~lidarcal_ros.pipeline.correction.stream.StreamCorrector`'s
#: ``place``).
OutputPlacer = Callable[[Any, int, np.dtype], "np.ndarray | None"]
#: What :func:`run_batch` returns: the corrected clouds, their tallies, the seconds spent and
#: the model their points got.
BatchResult = tuple[list[np.ndarray], list[CloudTally], float, ModelChoice | None]


@dataclass
class HeldCloud:
    """A cloud in a :class:`~lidarcal_ros.pipeline.correction.stream.StreamCorrector` waiting
    for the normals of its points.

    Attributes
    ----------
    tag : any
        The caller's name for the cloud.
    points : structured array
        The cloud as delivered.
    columns : CloudColumns
        Its ``x, y, z``, time, intensity and strip columns.
    normals : GridNormals or None
        The normals of its points, filled as its strips' evaluations come.
    strip_parts : list of (strip id, row indices or None)
        The strips among its points (None: every point).
    parts : int
        How many strips.
    scheduled : int
        Parts whose normals are being (or have been) evaluated.
    """

    tag: Any
    points: np.ndarray
    columns: CloudColumns
    normals: GridNormals | None = None
    strip_parts: list[tuple[int, np.ndarray | None]] = field(default_factory=list)
    parts: int = 0
    scheduled: int = 0

    def __len__(self) -> int:
        return int(self.points.shape[0])


@dataclass
class CorrectionBatch:
    """Clouds to be corrected together, and the evaluation of their normals.

    Attributes
    ----------
    tasks : list of NormalsTask
        The evaluations of the normals that serve only these clouds (run with the batch).
    messages : list of HeldCloud
        The clouds, in order.
    trajectory : Trajectory
    settings : CorrectionSettings
    place : OutputPlacer or None
        Where to build each corrected cloud (:class:`~lidarcal_ros.pipeline.
        stream_corrector.StreamCorrector`'s ``place``).
    """

    tasks: list[NormalsTask]
    messages: list[HeldCloud]
    trajectory: Trajectory
    settings: CorrectionSettings
    place: OutputPlacer | None = None


def deliver_normals(results: list[tuple[Any, GridNormals]]) -> None:
    """Put normals evaluated per strip into the clouds they belong to."""
    for key, g in results:
        m: HeldCloud
        idx: np.ndarray | None
        m, idx = key
        if idx is None:
            m.normals = g
        else:
            if m.normals is None:
                m.normals = no_normals(len(m))
            assert m.normals.rough is not None and g.rough is not None
            m.normals.normals[idx] = g.normals
            m.normals.valid[idx] = g.valid
            m.normals.rough[idx] = g.rough
            m.normals.cell_m = g.cell_m


def _whole_normals(job: CorrectionBatch) -> GridNormals | None:
    """The job's normals in one piece when one evaluation covers exactly its clouds, each
    of one strip (the usual case: no per-cloud copies); else None."""
    if len(job.tasks) != 1:
        return None
    keys = job.tasks[0].keys
    if len(keys) != len(job.messages) or any(
            key[1] is not None or key[0] is not m  # type: ignore[index]
            for key, m in zip(keys, job.messages, strict=True)):
        return None
    return job.tasks[0].run_whole()


def _job_strip_ids(msgs: list[HeldCloud]) -> np.ndarray | None:
    """The strip id of every point of the clouds of a job (None where a cloud has none)."""
    if any(m.columns.strip_id is None for m in msgs):
        return None
    return np.concatenate([m.columns.strip_id for m in msgs])


def _job_columns(msgs: list[HeldCloud]
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """xyz, t and intensity (NaN for clouds without) of the clouds of a job, concatenated."""
    if len(msgs) == 1:
        c = msgs[0].columns
        return c.xyz, c.t, c.intensity
    xyz = np.concatenate([m.columns.xyz for m in msgs])
    t = np.concatenate([m.columns.t for m in msgs])
    inten = None
    if any(m.columns.intensity is not None for m in msgs):
        inten = np.concatenate([m.columns.intensity if m.columns.intensity is not None
                                else np.full(len(m), np.nan, np.float32) for m in msgs])
    return xyz, t, inten


def cloud_volume(columns: CloudColumns) -> np.ndarray | None:
    """The volume returns of a cloud (:func:`~lidarcal_ros.core.radiometry.volume_returns`),
    None when it has none."""
    return volume_returns(columns.return_number, columns.number_of_returns)


def _job_volume(msgs: list[HeldCloud]) -> np.ndarray | None:
    """The volume returns of the clouds of a job, concatenated (None: none)."""
    parts = [cloud_volume(m.columns) for m in msgs]
    if all(p is None for p in parts):
        return None
    return np.concatenate([p if p is not None else np.zeros(len(m), bool)
                           for p, m in zip(parts, msgs, strict=True)])


def run_batch(job: CorrectionBatch, source: str) -> BatchResult:
    """Correct one batch of clouds: the corrected clouds, their tallies, seconds spent, and
    the model their points got (``source``: named in messages)."""
    started = time.perf_counter()
    msgs = job.messages
    whole = _whole_normals(job)
    if len(msgs) == 1 and len(msgs[0]):
        done = _run_one(job, msgs[0], whole, source, started)
        if done is not None:
            return done
    for task in job.tasks if whole is None else ():
        deliver_normals(task.run())
    if whole is not None:
        xyz, t, inten = _job_columns(msgs)
        gn = whole
    elif len(msgs) == 1:
        c, g = msgs[0].columns, msgs[0].normals or no_normals(len(msgs[0]))
        xyz, t, inten, gn = c.xyz, c.t, c.intensity, g
    else:
        xyz, t, inten = _job_columns(msgs)
        normals = [m.normals or no_normals(len(m)) for m in msgs]
        rough = [g.rough for g in normals]
        gn = GridNormals(np.concatenate([g.normals for g in normals]),
                         np.concatenate([g.valid for g in normals]),
                         normals[-1].cell_m,
                         np.concatenate([r if r is not None else np.zeros(len(m), bool)
                                         for r, m in zip(rough, msgs, strict=True)]))
    res = correct_columns(xyz, t, inten, job.trajectory, job.settings, normals=gn,
                          source=source,
                          all_finite=all(m.columns.all_finite for m in msgs),
                          volume=_job_volume(msgs), strip_id=_job_strip_ids(msgs))
    out: list[np.ndarray] = []
    tallies: list[CloudTally] = []
    a = 0
    for m in msgs:
        b = a + len(m)
        where = (job.place(m.tag, len(m), corrected_dtype(m.points.dtype))
                 if job.place is not None else None)
        tallies.append(CloudTally.empty())
        out.append(build_corrected(m.points, res, a, b, out=where, tally=tallies[-1]))
        a = b
    return out, tallies, time.perf_counter() - started, res.choice


def _run_one(job: CorrectionBatch, m: HeldCloud, whole: GridNormals | None, source: str,
             started: float) -> BatchResult | None:
    """:func:`run_batch` of one cloud (the usual batch of the node), corrected straight into
    its rows (:func:`~lidarcal_ros.pipeline.correction.corrected_cloud.row_target`); None for a
    layout that needs the columns."""
    points = np.ascontiguousarray(m.points)
    dtype = corrected_dtype(points.dtype)
    where = job.place(m.tag, len(m), dtype) if job.place is not None else None
    out = where if where is not None else np.empty(len(m), dtype=dtype)  # (all written)
    tally = CloudTally.empty()
    target = row_target(points, out, tally.counts)
    if target is None:
        if where is not None:  # (placed: the general path builds the cloud there)
            job.place = _placed(m.tag, where)
        return None
    if whole is None:
        for task in job.tasks:
            deliver_normals(task.run())
    gn = whole if whole is not None else m.normals or no_normals(len(m))
    c = m.columns
    res = correct_columns(c.xyz, c.t, c.intensity, job.trajectory, job.settings, normals=gn,
                          source=source, all_finite=bool(c.all_finite), rows=target,
                          volume=cloud_volume(c), strip_id=c.strip_id)
    return [out], [tally], time.perf_counter() - started, res.choice


def _placed(tag: Any, where: np.ndarray) -> OutputPlacer:
    """A placer that gives ``tag`` the output already placed for it."""
    return lambda t, n, dtype: where if t == tag else None

