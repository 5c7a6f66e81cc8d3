"""What an import wrote, as :class:`ImportReport` and its readable lines."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from lidarcal_ros.core.qa.overlap_grid import PairQA
from lidarcal_ros.core.trajectory.estimation import EstimatedTrajectory
from lidarcal_ros.pipeline.importing.strips import StripSummary
from lidarcal_ros.pipeline.importing.time_bases import TimeRule


@dataclass
class ImportReport:
    """What :func:`~lidarcal_ros.pipeline.importing.importer.import_mission` wrote.

    Attributes
    ----------
    output : Path
        The bag.
    n_files : int
        LAS/LAZ files read.
    n_points, n_read : int
        Points written, and read.
    strips : list of StripSummary
        The strips written, in id order.
    trajectory_kind : str
        What the trajectory is, in words.
    n_poses : int
    time_rule : TimeRule
        How the points' and trajectory's times became the bag's clock.
    crs_name : str
    unit_factors : (float, float)
        Horizontal and height factors applied to reach metres.
    estimate : EstimatedTrajectory or None
        The trajectory estimate and its quality, when rebuilt from the points.
    dropped_strips : list of int
        Strips left out: no trajectory could be rebuilt for them.
    spilled_runs : int
        Sorted runs spilled to disk (0: the points fitted in memory).
    overlaps : list of PairQA
        Overlap QA per pair of strips.
    attitude_range_deg : dict of str to (float, float)
        Range (min, max) of the poses' roll and pitch, degrees, when they carry the attitude.
    model : str
        The point-positioning model ``matching.model auto`` will give the mission, and why.
    """

    output: Path
    n_files: int
    n_points: int
    n_read: int
    strips: list[StripSummary]
    trajectory_kind: str
    n_poses: int
    time_rule: TimeRule
    crs_name: str
    unit_factors: tuple[float, float]
    estimate: EstimatedTrajectory | None = None
    dropped_strips: list[int] = field(default_factory=list)
    spilled_runs: int = 0
    overlaps: list[PairQA] = field(default_factory=list)
    attitude_range_deg: dict[str, tuple[float, float]] = field(default_factory=dict)
    model: str = ""

    def lines(self) -> list[str]:
        """A readable summary."""
        out = [f"imported {self.n_points} of {self.n_read} points from {self.n_files} file(s) "
               f"into {self.output}: {len(self.strips)} strips, {self.n_poses} poses "
               f"({self.trajectory_kind})",
               f"  CRS: {self.crs_name}" + (
                   f" (coordinates x{self.unit_factors[0]:g}, heights x"
                   f"{self.unit_factors[1]:g} to metres)"
                   if self.unit_factors != (1.0, 1.0) else ""),
               f"  time: {self.time_rule.note}"]
        if self.attitude_range_deg:
            out.append("  attitude: " + ", ".join(
                f"{name} {lo:+.1f}..{hi:+.1f} deg"
                for name, (lo, hi) in self.attitude_range_deg.items()))
        if self.model:
            out.append(f"  model (matching.model auto): {self.model}")
        for s in self.strips:
            out.append(f"  strip {s.strip_id:>5}: {s.n_points:>9} points, "
                       f"{s.t_last - s.t_first:7.1f} s, {s.source}, "
                       f"{len(s.files)} file(s)")
        if self.estimate is not None:
            out.append("  trajectory estimate per strip:")
            out.extend(f"    {s.summary}" for s in self.estimate.strips)
            out.append("  trajectory estimate per segment (rays, RMS ray distance, position "
                       "sigma, height, level):")
            for q in self.estimate.segments:
                out.append(f"    strip {q.strip_id:>5} {q.t_end - q.t_start:6.1f} s: "
                           f"{q.n_rays:>6} rays, RMS {q.rms_m:6.2f} m, sigma {q.sigma_m:6.2f} m,"
                           f" height {q.height_m:7.1f} m, {q.level}"
                           + (f" ({q.message})" if q.message else "")
                           + (f"; {q.fallback}" if q.fallback else ""))
        if self.overlaps:
            out.append("  overlap QA (last returns, smooth cells; median and robust RMS of "
                       "A - B heights):")
            for pq in self.overlaps:
                out.append(f"    strips {pq.strip_a:>5} & {pq.strip_b:<5} coverage "
                           f"{pq.coverage * 100:5.1f}%, {pq.n_cells:>6} cells, median "
                           f"{pq.median_dz * 100:+6.1f} cm, RMS {pq.rms_dz * 100:5.1f} cm, "
                           f"{pq.level}")
        if self.dropped_strips:
            out.append("  left out (no trajectory could be rebuilt): strips "
                       + ", ".join(str(s) for s in self.dropped_strips))
        return out


__all__ = ["ImportReport"]
