"""``lidarcal import``: LAS/LAZ flight lines and a trajectory file into a mission bag.

What a survey delivers (LAS 1.0-1.4 / LAZ files, an Applanix SBET or an ASCII trajectory, or
no trajectory at all) becomes a bag of the lidarcal contract (docs/interface.md): strips as
``sensor_msgs/PointCloud2`` chunks on ``/lidar/points`` with ``x, y, z, t`` FLOAT64,
``intensity`` FLOAT32, ``strip_id`` UINT16, ``return_number``, ``number_of_returns`` and
``classification`` UINT8, and the trajectory as ``geometry_msgs/PoseStamped`` on
``/lidar/trajectory`` (the INS attitude where the file has one, else identity), all in one
map frame.

:func:`import_mission` is the one entry point, told what to do by an :class:`ImportOptions`
(:mod:`.import_options`, whose fields the rules below name). Its stages are modules of their
own: :mod:`.import_points` (headers, CRS and units, the one read pass over the points, the
sorted runs), :mod:`.import_time_bases` (*GPS time*), :mod:`.import_strips` (*Strips*),
:mod:`.import_trajectory` (the trajectory file in the map frame, or the estimate),
:mod:`.import_writer` (the bag) and :mod:`.import_report` (what was written).

Rules
-----
Strips
    From ``point_source_id``. Points whose id is 0 while other points have ids, and all the
    points when every point has one and the same id, are split into strips at gaps in GPS
    time longer than ``strip_gap_s``; such strips are numbered 1, 2, ... in time order (or
    after the largest id present). A strip may span several files, a file hold several
    strips.
Coordinates
    Converted to metres: the horizontal unit of the points' CRS (from the LAS header, or
    ``crs``) gives the factor, heights use the vertical unit of a compound CRS, else the
    horizontal one. Geographic (lat/lon) point clouds are refused.
Trajectory positions
    SBET (and ASCII with lat/lon columns) are geographic, EPSG:4979 by default
    (``trajectory_crs`` overrides: the datum of the GNSS processing), projected with pyproj to
    the points' CRS. Against a 2-D projected CRS heights stay ellipsoidal: LAS heights
    delivered in a geoid-based datum then sit N (the geoid undulation, tens of metres) away,
    which shifts ``z`` of docs/method.md section 4 by N out of about 1000 m, about 3 % of the
    design matrix and nothing of the observations: harmless for the estimate, but a
    compound CRS (``--crs EPSG:32633+5773``) converts them properly when PROJ has the geoid
    model (else: a one-line error). ASCII x, y, z are taken to be in the points' CRS unless
    ``trajectory_crs`` says otherwise.
Trajectory attitude
    An SBET's roll, pitch and true heading, or an ASCII trajectory's roll, pitch and heading
    columns, become the poses' orientation (REP-103 quaternions, docs/method.md section 10), the
    heading turned from true to the map's grid north by the meridian convergence; with a
    heading only the poses are level (``full_attitude`` False); without one they carry none
    (identity). :func:`lidarcal_ros.io.survey.trajectory_crs.map_orientation` has the conventions.
GPS time
    LAS global-encoding bit 0 set: Adjusted Standard GPS Time (GPS seconds - 1e9); clear: GPS
    seconds of the week. SBET times are week seconds. ASCII times are read as whichever of
    week seconds, adjusted standard, GPS or UNIX seconds (``trajectory_time``, default: all
    plausible ones for their magnitude) overlaps the points' times, the GPS week of week
    seconds being taken from the absolute side (the week the points or the trajectory fall
    in, trying the neighbouring weeks for flights across a week boundary), or from
    ``gps_week``. When points and trajectory are both in week seconds they are consistent
    as they are and the bag keeps week seconds (``gps_week`` makes them absolute; the LAS
    creation date, a processing date, only breaks ties). Whenever an absolute time is known
    the bag's clock is UNIX (UTC) seconds, the ROS clock, leap seconds applied, as
    ``lidarcal correct`` expects when it writes LAS again. Neither reading overlapping, or a
    strip not covered by trajectory samples: a one-line error.
Trajectory estimate
    Without a trajectory file, rays from the first and last returns of multi-return pulses
    rebuild the sensor path per strip (:mod:`lidarcal_ros.core.trajectory.estimation`), with a
    quality figure per segment. A strip its rays rebuild poorly is kept, flown level at the
    altitude of the strips rebuilt well, with its sigma stated; the report says per strip
    what happened, and only a strip that even that cannot place is left out, with a warning
    saying why.
Memory
    Points are read in chunks and, past ``memory_points``, spilled to sorted run files
    beside the output and merged by time (an external sort), so memory does not grow with
    the number of points. Rays kept for an estimate grow with the flight's duration only.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from lidarcal_ros.errors import ConfigError
from lidarcal_ros.io.survey.las_reader import inspect_las
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
) -> ImportReport:
    """Import LAS/LAZ strips and a trajectory into a mission bag (module docstring).

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
        given = read_delivered_trajectory(options.trajectory, options.trajectory_crs, frame)
    store = RunStore(options.memory_points, out.parent)
    try:
        read = read_points(infos, store, frame, options, report_progress)
        return _assemble_and_write(out, read, header_base, given, options, report_progress)
    finally:
        store.cleanup()


def _time_rule(read: PointsRead, header_base: str, given: DeliveredTrajectory | None,
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


def _assemble_and_write(out: Path, read: PointsRead, header_base: str,
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
