"""Writing an import's bag: the points merged by time into clouds, the poses between them.

Map frame, metres; times on the bag's clock (docs/interface.md, docs/import.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lidarcal_ros.core.qa.overlap_grid import OverlapGrid, PairQA
from lidarcal_ros.errors import TrajectoryError
from lidarcal_ros.io.bag.format import seconds_to_ns
from lidarcal_ros.io.bag.writer import BagWriter
from lidarcal_ros.pipeline.importing.options import ImportOptions
from lidarcal_ros.pipeline.importing.points import PointsRead, Progress, merged_windows
from lidarcal_ros.pipeline.importing.strips import StripAssembly
from lidarcal_ros.pipeline.importing.time_bases import TimeRule
from lidarcal_ros.pipeline.importing.trajectory import BagTrajectory, check_coverage


@dataclass
class BagWritten:
    """What :func:`write_bag` wrote.

    Attributes
    ----------
    n_points, n_poses : int
    overlaps : list of PairQA
        The overlap QA per pair of strips (empty without QA).
    """

    n_points: int
    n_poses: int
    overlaps: list[PairQA] = field(default_factory=list)


def write_bag(output: Path, read: PointsRead, strips: StripAssembly, rule: TimeRule,
              trajectory: BagTrajectory, options: ImportOptions, progress: Progress
              ) -> BagWritten:
    """Merge the runs by time and write clouds and poses in log-time order (docs/import.md).

    Only the strips in ``strips.summaries`` are written; their counts and spans are filled in.

    Raises
    ------
    TrajectoryError
        A strip not covered by the trajectory (the bag is not kept).
    """
    traj = trajectory.trajectory
    summaries = strips.summaries
    t_start = read.time_range[0]
    grid = None
    if options.qa_cell_m > 0:
        hfac = read.frame.unit_factors[0]
        grid = OverlapGrid(options.qa_cell_m, (float(read.infos[0].mins[0] * hfac),
                                               float(read.infos[0].mins[1] * hfac)))
    sources = read.store.sources()
    pose_ns = [seconds_to_ns(float(v)) for v in traj.t]
    pose_i = 0
    written = 0
    tt = traj.t
    frame_id, chunk_seconds = options.frame_id, options.chunk_seconds

    def covered(sid: int, a: float, b: float) -> None:
        if not len(tt) or tt[0] > a or tt[-1] < b:
            span = f"{tt[0]:.3f}-{tt[-1]:.3f} s" if len(tt) else "nothing"
            raise TrajectoryError(
                f"{trajectory.source}: trajectory covers {span} but strip {sid} has points at "
                f"{a:.3f}-{b:.3f} s; it does not cover the points' times"
            )

    with BagWriter(output, overwrite=options.overwrite) as writer:
        for window in merged_windows(sources, t_start, chunk_seconds,
                                     max(options.memory_points, 10_000)):
            sid = strips.map.map(window["strip_id"], window["t"])
            chunk_k = np.floor((window["t"] - t_start) / chunk_seconds).astype(np.int64)
            window["t"] = rule.points(window["t"])
            keep = np.isin(sid, np.fromiter(summaries, dtype=np.int64))
            if not keep.all():
                window, sid, chunk_k = window[keep], sid[keep], chunk_k[keep]
            window["strip_id"] = sid
            if grid is not None and len(window):
                last = ((window["return_number"] >= window["number_of_returns"])
                        | (window["number_of_returns"] <= 1))
                grid.add(sid[last], np.column_stack([window["x"][last], window["y"][last],
                                                     window["z"][last]]))
            order = np.lexsort((window["t"], sid, chunk_k))
            window, sid, chunk_k = window[order], sid[order], chunk_k[order]
            new = np.ones(len(window), dtype=bool)
            new[1:] = (sid[1:] != sid[:-1]) | (chunk_k[1:] != chunk_k[:-1])
            starts = np.flatnonzero(new)
            stops = np.append(starts[1:], len(window))
            events = sorted(zip(window["t"][starts].tolist(), starts.tolist(), stops.tolist(),
                                strict=True))
            for t0, a, b in events:
                part = window[a:b]
                s = summaries[int(sid[a])]
                t_lo, t_hi = float(part["t"][0]), float(part["t"][-1])
                covered(s.strip_id, t_lo, t_hi)
                s.n_points += b - a
                s.t_first, s.t_last = min(s.t_first, t_lo), max(s.t_last, t_hi)
                stamp = seconds_to_ns(t0)
                while pose_i < len(pose_ns) and pose_ns[pose_i] <= stamp:
                    writer.write_trajectory_pose(options.trajectory_topic, pose_ns[pose_i],
                                                 frame_id, traj, pose_i)
                    pose_i += 1
                writer.write_cloud(options.points_topic, stamp, frame_id, part)
                written += b - a
            progress("writing", written / max(read.n_kept, 1))
        while pose_i < len(pose_ns):
            writer.write_trajectory_pose(options.trajectory_topic, pose_ns[pose_i], frame_id,
                                         traj, pose_i)
            pose_i += 1
        check_coverage(traj, [s for s in summaries.values() if s.n_points], trajectory.source)
    return BagWritten(written, len(pose_ns), grid.pairs() if grid is not None else [])


__all__ = ["BagWritten", "write_bag"]
