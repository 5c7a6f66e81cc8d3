"""``lidarcal import``: LAS/LAZ flight lines and a trajectory file into a mission bag.

:func:`import_mission` runs the stages (the modules beside this one) as an
:class:`~lidarcal_ros.pipeline.importing.options.ImportOptions` says. The rules for strips,
coordinates, trajectory files, time bases and the trajectory estimate: docs/import.md.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from lidarcal_ros.errors import ConfigError
from lidarcal_ros.io.survey.las_reader import GpsTimeType, inspect_las
from lidarcal_ros.pipeline.executor import Executor
from lidarcal_ros.pipeline.importing.options import ImportOptions
from lidarcal_ros.pipeline.importing.points import (
    PointsRead,
    Progress,
    RunStore,
    header_time_base,
    points_frame,
    read_points,
)
from lidarcal_ros.pipeline.importing.strips import assemble_strips
from lidarcal_ros.pipeline.importing.summary import ImportReport
from lidarcal_ros.pipeline.importing.time_bases import (
    TimeRule,
    gps_week_of_creation,
    points_time_base,
    reconcile_times,
    trajectory_readings,
)
from lidarcal_ros.pipeline.importing.trajectory import (
    BagTrajectory,
    DeliveredTrajectory,
    model_note,
    read_delivered_trajectory,
    trajectory_from_file,
    trajectory_from_rays,
)
from lidarcal_ros.pipeline.importing.writer import write_bag

logger = logging.getLogger(__name__)


def import_mission(
    inputs: Sequence[str | os.PathLike[str]],
    output: str | os.PathLike[str],
    options: ImportOptions | None = None,
    progress: Progress | None = None,
    *,
    executor: Executor | None = None,
) -> ImportReport:
    """Import LAS/LAZ strips and a trajectory into a mission bag (docs/import.md).

    Parameters
    ----------
    inputs : sequence of path-like
        LAS/LAZ files (1.0-1.4; point formats with GPS time).
    output : path-like
        rosbag2 directory, or a bare ``.mcap`` file.
    options : ImportOptions, optional
        The trajectory, CRSs, time bases, strips, topics, memory and QA settings (default:
        :class:`ImportOptions`'s defaults: the trajectory estimated from multiple returns).
    progress : callable(stage, fraction), optional
    executor : Executor, optional
        Read the files there, each by a worker (``--dask``:
        :mod:`lidarcal_ros.pipeline.importing.parts`; the same bag); None: here.

    Returns
    -------
    ImportReport

    Raises
    ------
    InputError
        Unreadable or inconsistent inputs (one line naming the file at fault).
    TrajectoryError
        Trajectory unreadable, not covering the points' times, or not rebuildable.
    ConfigError
        No inputs, or an output that exists (without ``overwrite``) or has no parent
        directory.
    """
    options = options or ImportOptions()
    if not inputs:
        raise ConfigError("import: no LAS/LAZ input files")
    out = Path(output)
    if (out.exists() or out.is_symlink()) and not options.overwrite:
        raise ConfigError(f"{out}: exists (use --overwrite to replace it)")
    if not out.parent.is_dir():
        raise ConfigError(f"{out}: parent directory {out.parent} does not exist")
    report_progress = progress or (lambda stage, fraction: None)

    infos = [inspect_las(p) for p in inputs]
    header_base = header_time_base(infos)
    frame = points_frame(infos, options.crs)
    given = None  # (read before the points: a bad file fails fast)
    if not options.estimates_trajectory:
        assert options.trajectory is not None
        given = read_delivered_trajectory(options.trajectory, options.trajectory_crs, frame,
                                          accuracy=options.trajectory_accuracy)
    store = RunStore(options.memory_points, out.parent)
    try:
        if executor is None:
            read = read_points(infos, store, frame, options, report_progress)
        else:
            from lidarcal_ros.pipeline.importing.parts import read_in_parts

            read = read_in_parts(infos, store, frame, options, report_progress, executor)
        return _assemble_and_write(out, read, header_base, given, options, report_progress)
    finally:
        store.cleanup()


def _time_rule(read: PointsRead, header_base: GpsTimeType, given: DeliveredTrajectory | None,
               options: ImportOptions) -> tuple[TimeRule, np.ndarray | None]:
    """How the times meet (:mod:`.import_time_bases`), and the trajectory file's raw times
    as read under it (None without a file)."""
    points_base = points_time_base(header_base, read.time_range[1], str(read.infos[0].path))
    week = gps_week_of_creation([i.creation_date for i in read.infos
                                 if i.creation_date is not None])
    if given is None:
        return reconcile_times(points_base, read.time_range, None, (),
                               gps_week=options.gps_week, creation_week=week), None
    bases, raw_t = trajectory_readings(given.file, options.trajectory_time)
    rule = reconcile_times(points_base, read.time_range,
                           (float(raw_t.min()), float(raw_t.max())), bases,
                           gps_week=options.gps_week, creation_week=week,
                           where=str(given.file.path))
    return rule, raw_t


def _assemble_and_write(out: Path, read: PointsRead, header_base: GpsTimeType,
                        given: DeliveredTrajectory | None, options: ImportOptions,
                        progress: Progress) -> ImportReport:
    """From the points read to the bag written: strips, time rule, trajectory, bag."""
    strips = assemble_strips(read, options.strip_gap_s)
    rule, raw_t = _time_rule(read, header_base, given, options)
    logger.info("time: %s", rule.note)
    trajectory: BagTrajectory
    if given is not None:
        assert raw_t is not None
        trajectory = trajectory_from_file(given, raw_t, rule, strips, read.time_range,
                                          options.trajectory_rate_hz)
    else:
        trajectory = trajectory_from_rays(read, strips, rule, options.estimate)
    strips.leave_out(trajectory.dropped_strips)
    written = write_bag(out, read, strips, rule, trajectory, options, progress)
    summaries = strips.summaries
    return ImportReport(
        output=out, n_files=len(read.infos), n_points=written.n_points, n_read=read.n_read,
        strips=[summaries[k] for k in sorted(summaries) if summaries[k].n_points],
        trajectory_kind=trajectory.kind, n_poses=written.n_poses, time_rule=rule,
        crs_name=read.frame.name, unit_factors=read.frame.unit_factors,
        estimate=trajectory.estimate,
        dropped_strips=trajectory.dropped_strips, spilled_runs=len(read.store.runs),
        overlaps=written.overlaps, attitude_range_deg=trajectory.attitude_range_deg,
        model=model_note(trajectory.trajectory),
    )


__all__ = ["import_mission"]
