"""``lidarcal import``: LAS/LAZ flight lines and a trajectory file into a mission bag.

What a survey delivers (LAS 1.0-1.4 / LAZ files, an Applanix SBET or an ASCII trajectory, or
no trajectory at all) becomes a bag of the lidarcal contract (shared/interface.md): strips as
``sensor_msgs/PointCloud2`` chunks on ``/lidar/points`` with ``x, y, z, t`` FLOAT64,
``intensity`` FLOAT32, ``strip_id`` UINT16, ``return_number``, ``number_of_returns`` and
``classification`` UINT8, and the trajectory as ``geometry_msgs/PoseStamped`` on
``/lidar/trajectory`` (the INS attitude where the file has one, else identity), all in one
map frame.

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
    which shifts ``z`` of method.md section 4 by N out of about 1000 m, about 3 % of the
    design matrix and nothing of the observations: harmless for the estimate, but a
    compound CRS (``--crs EPSG:32633+5773``) converts them properly when PROJ has the geoid
    model (else: a one-line error). ASCII x, y, z are taken to be in the points' CRS unless
    ``trajectory_crs`` says otherwise.
Trajectory attitude
    An SBET's roll, pitch and true heading, or an ASCII trajectory's roll, pitch and heading
    columns, become the poses' orientation (REP-103 quaternions, method.md section 10), the
    heading turned from true to the map's grid north by the meridian convergence; with a
    heading only the poses are level (``full_attitude`` False); without one they carry none
    (identity). :func:`lidarcal_ros.io.trajectory_files.map_orientation` has the conventions.
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
    rebuild the sensor path per strip (:mod:`lidarcal_ros.core.trajectory_estimation`), with a
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
import math
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lidarcal_ros.core.attitude import attitude_from_quaternions
from lidarcal_ros.core.georeferencing import choose_model
from lidarcal_ros.core.mission import Trajectory, screen_samples
from lidarcal_ros.core.overlap_grid import OverlapGrid, PairQA
from lidarcal_ros.core.trajectory_estimation import (
    EstimatedTrajectory,
    EstimateSettings,
    estimate_trajectory,
)
from lidarcal_ros.core.trajectory_rays import RayBudget, RayCollector, rays_from_returns
from lidarcal_ros.errors import ConfigError, InputError, TrajectoryError
from lidarcal_ros.io.bag import BagWriter, seconds_to_ns
from lidarcal_ros.io.las_reader import LasFileInfo, crs_units, inspect_las, iter_las_chunks
from lidarcal_ros.io.trajectory_files import (
    WEEK_S,
    TrajectoryFile,
    gps_to_unix,
    gps_week_of_unix,
    map_orientation,
    project,
    read_trajectory_file,
    to_gps_seconds,
)

logger = logging.getLogger(__name__)

Progress = Callable[[str, float], None]

#: Point layout of the bag (aligned, little-endian).
POINT_DTYPE = np.dtype(
    [("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("t", "<f8"), ("intensity", "<f4"),
     ("strip_id", "<u2"), ("return_number", "u1"), ("number_of_returns", "u1"),
     ("classification", "u1")],
    align=True,
)
RETURNS = ("all", "first", "last")
_GAP_BIN_MAX_S = 0.5
#: Keys of ``estimate_options`` that go to the :class:`RayCollector`, not the estimate.
_COLLECTOR_OPTIONS = ("bin_s", "per_bin", "max_per_bin", "max_rays")


# ---------------------------------------------------------------------------- time bases
@dataclass
class TimeRule:
    """How raw point and trajectory times map onto the bag's clock.

    Attributes
    ----------
    points_base, trajectory_base : str
        ``week``, ``adjusted``, ``gps`` or ``unix`` (trajectory: None without a file).
    week : int or None
        GPS week given to week-second times; None when the bag keeps week seconds.
    clock : ``"unix"`` or ``"week"``
    note : str
        The rule applied, in words.
    """

    points_base: str
    trajectory_base: str | None
    week: int | None
    clock: str
    note: str

    def _convert(self, raw: np.ndarray, base: str) -> np.ndarray:
        if self.clock == "week":
            return np.asarray(raw, dtype=np.float64)
        return gps_to_unix(to_gps_seconds(raw, base, week=self.week))

    def points(self, raw: np.ndarray) -> np.ndarray:
        """Point times on the bag's clock, seconds."""
        return self._convert(raw, self.points_base)

    def trajectory(self, raw: np.ndarray) -> np.ndarray:
        """Trajectory times on the bag's clock, seconds."""
        assert self.trajectory_base is not None
        return self._convert(raw, self.trajectory_base)


_LABEL = {"week": "GPS week seconds", "adjusted": "adjusted standard GPS time",
          "gps": "GPS seconds", "unix": "UNIX seconds"}


def _candidate_bases(values: np.ndarray) -> list[str]:
    """Readings of ASCII trajectory times plausible for their magnitude, likeliest first."""
    lo, hi = float(np.min(values)), float(np.max(values))
    if lo >= 0 and hi <= 1.5 * WEEK_S:
        return ["week", "adjusted"]
    if lo >= 5e8:
        return ["gps", "unix", "adjusted"]
    return ["adjusted"]


def _overlap(a0: float, a1: float, b0: float, b1: float) -> float:
    """Fraction of [a0, a1] inside [b0, b1] (1 or 0 for an instant)."""
    if a1 <= a0:
        return 1.0 if b0 <= a0 <= b1 else 0.0
    return max(0.0, min(a1, b1) - max(a0, b0)) / (a1 - a0)


def reconcile_times(
    points_base: str,
    points_range: tuple[float, float],
    trajectory_range: tuple[float, float] | None,
    trajectory_bases: Sequence[str],
    *,
    gps_week: int | None = None,
    creation_week: int | None = None,
    where: str = "trajectory",
) -> TimeRule:
    """Choose how point and trajectory times meet (module docstring, *GPS time*).

    Parameters
    ----------
    points_base : ``"week"`` or ``"adjusted"``
    points_range : (float, float)
        First and last raw point time.
    trajectory_range : (float, float) or None
        First and last raw trajectory time; None: no trajectory file.
    trajectory_bases : sequence of str
        Readings of the trajectory times to try, likeliest first.
    gps_week : int, keyword-only
        GPS week of week-second times, if known.
    creation_week : int, keyword-only
        GPS week of the LAS creation date (tie breaker).
    where : str, keyword-only
        Named in error messages.

    Raises
    ------
    TrajectoryError
        No reading makes the trajectory overlap the points.
    """
    p0, p1 = points_range
    if trajectory_range is None:
        if points_base == "adjusted":
            return TimeRule("adjusted", None, None, "unix",
                            "points in adjusted standard GPS time, written as UNIX time")
        if gps_week is not None:
            return TimeRule("week", None, gps_week, "unix",
                            f"points in week seconds of GPS week {gps_week} (given), written "
                            "as UNIX time")
        return TimeRule("week", None, None, "week",
                        "points in GPS week seconds, written unchanged (no GPS week known)")
    t0, t1 = trajectory_range
    scored: list[tuple[float, int, int, TimeRule]] = []
    tried = []
    for rank, base in enumerate(trajectory_bases):
        tried.append(_LABEL[base])
        if points_base == "week" and base == "week" and gps_week is None:
            rule = TimeRule("week", "week", None, "week",
                            "points and trajectory both in GPS week seconds, written unchanged")
            scored.append((_overlap(p0, p1, t0, t1), 0, -rank, rule))
            continue
        for week in _weeks(points_base, (p0, p1), base, (t0, t1), gps_week):
            pg = to_gps_seconds(np.array([p0, p1]), points_base, week=week)
            tg = to_gps_seconds(np.array([t0, t1]), base, week=week)
            cov = _overlap(float(pg[0]), float(pg[1]), float(tg[0]), float(tg[1]))
            note = (f"points in {_LABEL[points_base]}, trajectory in {_LABEL[base]}"
                    + (f", GPS week {week}" if week is not None else "")
                    + "; written as UNIX time")
            tie = -abs(week - creation_week) if (week is not None and creation_week is not None
                                                 ) else 0
            scored.append((cov, tie, -rank, TimeRule(points_base, base, week, "unix", note)))
    best = max(scored, key=lambda s: s[:3]) if scored else None
    if best is None or best[0] <= 0.0:
        readings = ", ".join(tried) or "none"
        raise TrajectoryError(
            f"{where}: times {t0:.3f}-{t1:.3f} s do not overlap the points' times "
            f"{p0:.3f}-{p1:.3f} s ({_LABEL[points_base]}) under any reading (tried {readings}); "
            "wrong trajectory file, or give --trajectory-time / --gps-week"
        )
    if best[0] < 1.0:  # (the coverage of every strip is checked, and refused in one line)
        logger.info("%s: the trajectory covers only %.0f%% of the points' time span",
                    where, 100 * best[0])
    return best[3]


def _weeks(points_base: str, p: tuple[float, float], traj_base: str, t: tuple[float, float],
           gps_week: int | None) -> list[int | None]:
    """GPS weeks to try for the week-second side (None: no side is in week seconds)."""
    if points_base != "week" and traj_base != "week":
        return [None]
    if gps_week is not None:
        return [gps_week]
    if points_base != "week":
        g = float(to_gps_seconds(np.array([p[0]]), points_base)[0])
    elif traj_base != "week":
        g = float(to_gps_seconds(np.array([t[0]]), traj_base)[0])
    else:
        return [None]
    w = int(math.floor(g / WEEK_S))
    return [w, w - 1, w + 1]


# ---------------------------------------------------------------------------- report
@dataclass
class StripSummary:
    """One strip of the imported mission."""

    strip_id: int
    source: str  # "point_source_id N" or "GPS-time gap"
    n_points: int = 0
    t_first: float = math.inf
    t_last: float = -math.inf
    files: set[str] = field(default_factory=set)


@dataclass
class ImportReport:
    """What :func:`import_mission` wrote."""

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
    #: Range (min, max) of the poses' roll and pitch, degrees, when they carry the attitude.
    attitude_range_deg: dict[str, tuple[float, float]] = field(default_factory=dict)
    #: The point-positioning model ``matching.model auto`` will give the mission, and why.
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


# ---------------------------------------------------------------------------- spilling
class _RunStore:
    """Points buffered in memory, spilled as time-sorted runs past a limit."""

    def __init__(self, limit: int, directory: Path) -> None:
        self.limit = max(1000, int(limit))
        self.directory = directory
        self._buffer: list[np.ndarray] = []
        self._buffered = 0
        self.runs: list[Path] = []
        self._tmp: Path | None = None

    def add(self, points: np.ndarray) -> None:
        if not len(points):
            return
        self._buffer.append(points)
        self._buffered += len(points)
        if self._buffered >= self.limit:
            self._spill()

    def _sorted_buffer(self) -> np.ndarray:
        arr = np.concatenate(self._buffer) if self._buffer else np.empty(0, POINT_DTYPE)
        self._buffer, self._buffered = [], 0
        return arr[np.argsort(arr["t"], kind="stable")]

    def _spill(self) -> None:
        if self._tmp is None:
            self._tmp = Path(tempfile.mkdtemp(prefix=".lidarcal-import-", dir=self.directory))
        path = self._tmp / f"run{len(self.runs):05d}.npy"
        try:
            np.save(path, self._sorted_buffer())
        except OSError as exc:
            raise InputError(f"{path}: cannot spill points ({exc.strerror or exc})") from None
        self.runs.append(path)

    def sources(self) -> list[np.ndarray]:
        """The sorted runs (memory-mapped) and the sorted in-memory rest."""
        rest = self._sorted_buffer()
        out = [np.load(p, mmap_mode="r") for p in self.runs]
        if len(rest):
            out.append(rest)
        return out

    def cleanup(self) -> None:
        if self._tmp is not None:
            shutil.rmtree(self._tmp, ignore_errors=True)
            self._tmp = None


def _merged_windows(
    sources: list[np.ndarray], t_start: float, step: float, limit: int
) -> Iterator[np.ndarray]:
    """Points of time-sorted ``sources`` in time order, in windows of whole ``step`` cells
    from ``t_start`` holding about ``limit`` points (at least one cell)."""
    pos = [0] * len(sources)
    times = [s["t"] for s in sources]
    ends = [len(s) for s in sources]
    while True:
        live = [i for i in range(len(sources)) if pos[i] < ends[i]]
        if not live:
            return
        t_min = min(float(times[i][pos[i]]) for i in live)
        t_max = max(float(times[i][ends[i] - 1]) for i in live)
        k0 = math.floor((t_min - t_start) / step)
        k_last = math.floor((t_max - t_start) / step)

        def count(k: int, live: list[int] = live) -> int:
            edge = t_start + (k + 1) * step
            return sum(int(np.searchsorted(times[i], edge, side="left")) - pos[i] for i in live)

        lo, hi = k0, k_last
        if count(hi) > limit:
            while lo < hi:  # largest k with count(k) <= limit, at least k0
                mid = (lo + hi + 1) // 2
                if count(mid) <= limit:
                    lo = mid
                else:
                    hi = mid - 1
            k = lo
        else:
            k = k_last
        edge = t_start + (k + 1) * step
        parts = []
        for i in live:
            stop = int(np.searchsorted(times[i], edge, side="left")) if k < k_last else ends[i]
            if stop > pos[i]:
                parts.append(np.asarray(sources[i][pos[i]:stop]))
                pos[i] = stop
        if not parts:
            continue
        window = np.concatenate(parts) if len(parts) > 1 else parts[0].copy()
        yield window[np.argsort(window["t"], kind="stable")]


# ---------------------------------------------------------------------------- strips
class _StripMap:
    """Raw (point_source_id, raw time) -> strip id (module docstring, *Strips*)."""

    def __init__(self, occupancy: dict[int, set[int]], bin_s: float, gap_s: float) -> None:
        ids = sorted(occupancy)
        self.by_gap_all = len(ids) == 1
        self.labelled = set() if self.by_gap_all else {i for i in ids if i != 0}
        unl: set[int] = set()
        for i in ids:
            if i not in self.labelled:
                unl |= occupancy[i]
        bins = np.array(sorted(unl), dtype=np.int64)
        gap_bins = max(1, int(math.ceil(gap_s / bin_s)))
        if bins.size:
            cut = np.flatnonzero(np.diff(bins) > gap_bins) + 1
            starts = bins[np.concatenate(([0], cut))]
        else:
            starts = np.empty(0, dtype=np.int64)
        self.segment_starts = starts.astype(np.float64) * bin_s  # raw times
        first_new = (max(self.labelled) + 1) if self.labelled else 1
        if self.by_gap_all and ids[0] != 0 and starts.size == 1:
            first_new = ids[0]  # one strip with one id: keep it
        self.segment_ids = np.arange(first_new, first_new + starts.size, dtype=np.int64)
        if self.segment_ids.size and self.segment_ids[-1] > 65535:
            raise InputError(f"{self.segment_ids.size} strips split at GPS-time gaps do not fit "
                             "UINT16 strip ids; raise --strip-gap")
        self.bin_s = bin_s

    def source_of(self, strip_id: int) -> str:
        if strip_id in self.labelled or (self.by_gap_all and self.segment_ids.size == 1
                                         and strip_id == self.segment_ids[0] != 1):
            return f"point_source_id {strip_id}"
        return "split at GPS-time gaps"

    def map(self, psid: np.ndarray, t_raw: np.ndarray) -> np.ndarray:
        out = psid.astype(np.int64)
        unl = np.ones(psid.shape, dtype=bool) if self.by_gap_all else psid == 0
        if unl.any():
            k = np.searchsorted(self.segment_starts, t_raw[unl], side="right") - 1
            out[unl] = self.segment_ids[np.clip(k, 0, self.segment_ids.size - 1)]
        return out


def _resolve_crs(infos: list[LasFileInfo], crs: str | None) -> Any:
    from lidarcal_ros.io.las import parse_crs

    if crs:
        return parse_crs(crs)
    found = [(i.path, i.crs) for i in infos if i.crs is not None]
    if not found:
        return None
    first_path, first = found[0]
    for path, other in found[1:]:
        if not other.equals(first, ignore_axis_order=True):
            raise InputError(f"{path}: CRS '{other.name}' differs from '{first.name}' of "
                             f"{first_path}; give --crs to choose")
    return first


def _trajectory_crs(text: str | None, traj: TrajectoryFile) -> Any:
    import pyproj

    from lidarcal_ros.io.las import parse_crs

    if text:
        c = parse_crs(text)
    elif traj.geographic:
        c = pyproj.CRS.from_epsg(4979)
    else:
        return None
    if c.is_geographic and len(c.axis_info) < 3:
        c = c.to_3d()
    return c


def _trajectory_in_map(
    traj: TrajectoryFile, points_crs: Any, traj_crs: Any, factors: tuple[float, float]
) -> np.ndarray:
    """Trajectory positions in the map frame (points' CRS scaled to metres)."""
    hfac, vfac = factors
    if traj_crs is None:  # already in the points' CRS and units
        pos = np.column_stack([traj.a, traj.b, traj.c])
        return pos * np.array([hfac, hfac, vfac])
    if points_crs is None:
        raise InputError(
            f"{traj.path}: the trajectory is in {traj_crs.name} but the points' CRS is unknown "
            "(no CRS in the LAS headers): give --crs EPSG:N"
        )
    pos = project(traj, traj_crs, points_crs)
    three_d = points_crs.is_compound or len(points_crs.axis_info) >= 3
    return pos * np.array([hfac, hfac, vfac if three_d else 1.0])


def _unwrap_week(t: np.ndarray) -> np.ndarray:
    """Week seconds that restart at 0 past the end of the week continue past 604800."""
    jumps = np.flatnonzero(np.diff(t) < -0.5 * WEEK_S)
    if not jumps.size:
        return t
    out = t.copy()
    for j in jumps:
        out[j + 1:] += WEEK_S
    return out


def _check_coverage(traj: Trajectory, strips: list[StripSummary], where: str, *,
                    max_gap_s: float = 2.0) -> None:
    """Every strip's span must lie inside the trajectory, without gaps over ``max_gap_s``
    (the calibration's local line fits need samples on both sides of every point)."""
    tt = traj.t
    for s in strips:
        if not len(tt) or tt[0] > s.t_first or tt[-1] < s.t_last:
            span = f"{tt[0]:.3f}-{tt[-1]:.3f} s" if len(tt) else "nothing"
            raise TrajectoryError(
                f"{where}: trajectory covers {span} but strip {s.strip_id} spans "
                f"{s.t_first:.3f}-{s.t_last:.3f} s; it does not cover the points' times"
            )
        a = max(int(np.searchsorted(tt, s.t_first, side="right")) - 1, 0)
        b = min(int(np.searchsorted(tt, s.t_last, side="left")), len(tt) - 1)
        if b > a:
            gaps = np.diff(tt[a:b + 1])
            k = int(np.argmax(gaps))
            if gaps[k] > max_gap_s:
                raise TrajectoryError(
                    f"{where}: trajectory gap of {gaps[k]:.2f} s at {tt[a + k]:.3f} s inside "
                    f"strip {s.strip_id}; it does not cover the points' times"
                )


def _decimate(t: np.ndarray, rate_hz: float) -> np.ndarray:
    """Indices keeping at most ``rate_hz`` samples per second (0: all)."""
    if rate_hz <= 0 or t.size < 3:
        return np.arange(t.size)
    dt = float(np.median(np.diff(t)))
    step = max(1, int(round((1.0 / rate_hz) / dt))) if dt > 0 else 1
    keep = np.arange(0, t.size, step)
    if keep[-1] != t.size - 1:
        keep = np.append(keep, t.size - 1)
    return keep


def import_mission(
    inputs: Sequence[str | os.PathLike[str]],
    output: str | os.PathLike[str],
    *,
    trajectory: str | os.PathLike[str] | None = "estimate",
    crs: str | None = None,
    trajectory_crs: str | None = None,
    trajectory_time: str = "auto",
    gps_week: int | None = None,
    strip_gap_s: float = 10.0,
    returns: str = "all",
    frame_id: str = "map",
    chunk_seconds: float = 0.1,
    points_topic: str = "/lidar/points",
    trajectory_topic: str = "/lidar/trajectory",
    trajectory_rate_hz: float = 50.0,
    memory_points: int = 2_000_000,
    chunk_points: int = 1_000_000,
    qa_cell_m: float = 2.0,
    estimate_options: dict[str, Any] | None = None,
    overwrite: bool = False,
    progress: Progress | None = None,
) -> ImportReport:
    """Import LAS/LAZ strips and a trajectory into a mission bag (module docstring).

    Parameters
    ----------
    inputs : sequence of path-like
        LAS/LAZ files (1.0-1.4; point formats with GPS time).
    output : path-like
        rosbag2 directory, or a bare ``.mcap`` file.
    trajectory : path-like, ``"estimate"`` or None, keyword-only
        SBET, ASCII trajectory, or ``"estimate"`` (also None) to rebuild it from multiple
        returns.
    crs : str, keyword-only
        CRS of the points (``EPSG:N``), overriding the LAS headers.
    trajectory_crs : str, keyword-only
        CRS of the trajectory positions (default EPSG:4979 for SBET and lat/lon columns, the
        points' CRS for ASCII x, y, z).
    trajectory_time : str, keyword-only
        ``auto``, ``week``, ``adjusted``, ``gps`` or ``unix``: time base of the trajectory.
    gps_week : int, keyword-only
        GPS week of week-second times.
    strip_gap_s : float, keyword-only
        GPS-time gap that separates strips where point source ids do not, seconds.
    returns : ``"all"``, ``"first"`` or ``"last"``, keyword-only
        Which returns go into the bag (all returns feed a trajectory estimate).
    frame_id : str, keyword-only
        Map frame name of clouds and poses.
    chunk_seconds : float, keyword-only
        Scanning time per PointCloud2 chunk, seconds.
    points_topic, trajectory_topic : str, keyword-only
    trajectory_rate_hz : float, keyword-only
        Trajectory samples kept per second (0: all); estimates are sampled at 10 Hz.
    memory_points : int, keyword-only
        Points held in memory before spilling sorted runs to disk.
    chunk_points : int, keyword-only
        Points decoded per LAS read.
    qa_cell_m : float, keyword-only
        Cell of the overlap QA grid, metres (0: no QA). Per pair of strips, the mean heights
        of last returns in cells both strips cover and where both are smooth (standard
        deviation <= 15 cm) are compared: :class:`PairQA`. Its memory grows with the area
        flown over the cell's area (32 bytes a cell and strip), not with the points.
    estimate_options : dict, keyword-only
        Keyword arguments of :func:`~lidarcal_ros.core.trajectory_estimation.estimate_trajectory`.
    overwrite : bool, keyword-only
        Replace an existing output bag.
    progress : callable(stage, fraction), keyword-only

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
        Bad option values.
    """
    if not inputs:
        raise ConfigError("import: no LAS/LAZ input files")
    if returns not in RETURNS:
        raise ConfigError(f"--returns must be one of {', '.join(RETURNS)}, got '{returns}'")
    if trajectory_time not in ("auto", "week", "adjusted", "gps", "unix"):
        raise ConfigError(f"--trajectory-time: unknown time base '{trajectory_time}'")
    if not strip_gap_s > 0:
        raise ConfigError(f"--strip-gap must be positive, got {strip_gap_s}")
    if not chunk_seconds > 0:
        raise ConfigError(f"chunk_seconds must be positive, got {chunk_seconds}")
    out = Path(output)
    if (out.exists() or out.is_symlink()) and not overwrite:
        raise ConfigError(f"{out}: exists (use --overwrite to replace it)")
    if not out.parent.is_dir():
        raise ConfigError(f"{out}: parent directory {out.parent} does not exist")
    report_progress = progress or (lambda stage, fraction: None)
    estimate = trajectory is None or str(trajectory) == "estimate"

    # -- headers, CRS, units
    paths = [Path(p) for p in inputs]
    infos = [inspect_las(p) for p in paths]
    bases = {i.gps_time_type for i in infos}
    if len(bases) > 1:
        adj = next(i.path for i in infos if i.gps_time_type == "adjusted")
        week = next(i.path for i in infos if i.gps_time_type == "week")
        raise InputError(f"{week}: GPS week time, but {adj} holds adjusted standard GPS time; "
                         "import them separately or convert one")
    points_base = bases.pop()
    points_crs = _resolve_crs(infos, crs)
    if points_crs is not None and not points_crs.is_projected and not (
            points_crs.is_compound and points_crs.sub_crs_list[0].is_projected):
        where = crs or str(next(i.path for i in infos if i.crs is not None))
        raise InputError(f"{where}: CRS '{points_crs.name}' is not projected; lidarcal needs "
                         "a projected map frame in metres (reproject the points, or --crs)")
    factors = crs_units(points_crs) if points_crs is not None else (1.0, 1.0)
    if factors != (1.0, 1.0):
        logger.warning("coordinates in %s are converted to metres (x%g, heights x%g)",
                       points_crs.name, factors[0], factors[1])
    scale = np.array([factors[0], factors[0], factors[1]])
    total = sum(i.point_count for i in infos)

    # -- trajectory file (read before the points: a bad file fails fast)
    traj_file: TrajectoryFile | None = None
    traj_xyz: np.ndarray | None = None
    traj_orientation: np.ndarray | None = None
    full_attitude = False
    if not estimate:
        traj_file = read_trajectory_file(Path(str(trajectory)))
        traj_crs = _trajectory_crs(trajectory_crs, traj_file)
        traj_xyz = _trajectory_in_map(traj_file, points_crs, traj_crs, factors)
        traj_orientation, full_attitude = map_orientation(
            traj_file, traj_crs, points_crs if traj_crs else None)

    # -- read pass: spill points, gather strip statistics (and rays)
    store = _RunStore(memory_points, out.parent)
    gap_bin = min(_GAP_BIN_MAX_S, strip_gap_s / 4.0)
    occupancy: dict[int, set[int]] = {}
    per_psid: dict[int, list[Any]] = {}  # psid -> [count, tmin, tmax, files]
    collector = RayCollector(RayBudget(**({} if not estimate else {
        k: v for k, v in (estimate_options or {}).items() if k in _COLLECTOR_OPTIONS})))
    n_read = 0
    n_kept = 0
    returns_seen = [0, 0]  # first and last returns of multi-return pulses
    try:
        for info in infos:
            if info.point_count == 0 and len(infos) > 1:
                logger.warning("%s: no points", info.path)
            for chunk in iter_las_chunks(info.path, chunk_points=chunk_points):
                n = len(chunk)
                xyz = chunk.xyz * scale
                t = chunk.gps_time
                if not np.isfinite(t).all():
                    raise InputError(f"{info.path}: non-finite GPS time")
                psid = chunk.point_source_id
                n_read += n
                if estimate:
                    collector.add(rays_from_returns(
                        xyz, t, psid, chunk.return_number, chunk.number_of_returns))
                    multi = chunk.number_of_returns >= 2
                    returns_seen[0] += int(np.count_nonzero(multi & (chunk.return_number == 1)))
                    returns_seen[1] += int(np.count_nonzero(
                        multi & (chunk.return_number == chunk.number_of_returns)))
                rn = chunk.return_number.astype(np.int16)
                nr = chunk.number_of_returns.astype(np.int16)
                if returns == "first":
                    keep = rn <= 1
                elif returns == "last":
                    keep = (rn >= nr) | (nr <= 1)
                else:
                    keep = np.ones(n, dtype=bool)
                for value in np.unique(psid):
                    sel = psid == value
                    ts = t[sel]
                    rec = per_psid.setdefault(int(value), [0, math.inf, -math.inf, set()])
                    rec[0] += int(sel.sum())
                    rec[1] = min(rec[1], float(ts.min()))
                    rec[2] = max(rec[2], float(ts.max()))
                    rec[3].add(info.path.name)
                    occupancy.setdefault(int(value), set()).update(
                        np.unique(np.floor(ts / gap_bin).astype(np.int64)).tolist())
                m = int(keep.sum())
                pts = np.empty(m, dtype=POINT_DTYPE)
                pts["x"], pts["y"], pts["z"] = xyz[keep, 0], xyz[keep, 1], xyz[keep, 2]
                pts["t"] = t[keep]
                pts["intensity"] = chunk.intensity[keep]
                pts["strip_id"] = psid[keep]
                pts["return_number"] = chunk.return_number[keep]
                pts["number_of_returns"] = chunk.number_of_returns[keep]
                pts["classification"] = chunk.classification[keep]
                store.add(pts)
                n_kept += m
                report_progress("reading", n_read / max(total, 1))
        if n_kept == 0:
            where = str(paths[0]) if len(paths) == 1 else f"{paths[0]} (and {len(paths) - 1} more)"
            raise InputError(f"{where}: no points to import (--returns {returns})" if n_read
                             else f"{where}: no points in the "
                             f"{'file' if len(paths) == 1 else 'files'}")
        return _finish(
            out, paths, infos, store, occupancy, per_psid, collector, n_read, n_kept,
            gap_bin=gap_bin, strip_gap_s=strip_gap_s, points_base=points_base,
            returns_seen=(returns_seen[0], returns_seen[1]),
            traj_file=traj_file, traj_xyz=traj_xyz, traj_orientation=traj_orientation,
            full_attitude=full_attitude,
            trajectory_time=trajectory_time,
            gps_week=gps_week, estimate_options=estimate_options, points_crs=points_crs,
            factors=factors, frame_id=frame_id, chunk_seconds=chunk_seconds,
            points_topic=points_topic, trajectory_topic=trajectory_topic,
            trajectory_rate_hz=trajectory_rate_hz, memory_points=memory_points,
            qa_cell_m=qa_cell_m, overwrite=overwrite, progress=report_progress,
        )
    finally:
        store.cleanup()


def _finish(
    out: Path,
    paths: list[Path],
    infos: list[LasFileInfo],
    store: _RunStore,
    occupancy: dict[int, set[int]],
    per_psid: dict[int, list[Any]],
    collector: RayCollector,
    n_read: int,
    n_kept: int,
    *,
    gap_bin: float,
    strip_gap_s: float,
    points_base: str,
    returns_seen: tuple[int, int],
    traj_file: TrajectoryFile | None,
    traj_xyz: np.ndarray | None,
    traj_orientation: np.ndarray | None,
    full_attitude: bool,
    trajectory_time: str,
    gps_week: int | None,
    estimate_options: dict[str, Any] | None,
    points_crs: Any,
    factors: tuple[float, float],
    frame_id: str,
    chunk_seconds: float,
    points_topic: str,
    trajectory_topic: str,
    trajectory_rate_hz: float,
    memory_points: int,
    qa_cell_m: float,
    overwrite: bool,
    progress: Progress,
) -> ImportReport:
    strip_map = _StripMap(occupancy, gap_bin, strip_gap_s)
    p0 = min(r[1] for r in per_psid.values())
    p1 = max(r[2] for r in per_psid.values())
    if points_base == "week" and p1 > 1.5 * WEEK_S:
        # Many producers leave the global-encoding bit at 0 while writing adjusted standard
        # time; week seconds never reach 1.5 weeks, adjusted standard time after 2011 does.
        logger.warning("%s: header says GPS week seconds, but times reach %.0f s; read as "
                       "adjusted standard GPS time", paths[0], p1)
        points_base = "adjusted"

    # -- time rule
    creation = [i.creation_date for i in infos if i.creation_date is not None]
    creation_week = None
    if creation:
        import calendar

        d = max(creation)
        creation_week = gps_week_of_unix(calendar.timegm((d.year, d.month, d.day, 0, 0, 0)))
    traj_t_raw: np.ndarray | None = None
    if traj_file is not None:
        traj_t_raw = traj_file.t
        if trajectory_time != "auto":
            cand = [trajectory_time]
        elif traj_file.kind == "sbet":
            cand = ["week"]
        else:
            cand = _candidate_bases(traj_t_raw)
        if "week" in cand and cand[0] == "week":
            traj_t_raw = _unwrap_week(traj_t_raw)
        rule = reconcile_times(points_base, (p0, p1),
                               (float(traj_t_raw.min()), float(traj_t_raw.max())), cand,
                               gps_week=gps_week, creation_week=creation_week,
                               where=str(traj_file.path))
    else:
        rule = reconcile_times(points_base, (p0, p1), None, (), gps_week=gps_week,
                               creation_week=creation_week)
    logger.info("time: %s", rule.note)

    # -- strips (times on the bag's clock)
    strips: dict[int, StripSummary] = {}
    for psid, (_count, t_lo, t_hi, files) in per_psid.items():
        if strip_map.by_gap_all or psid == 0:  # every gap segment inside [t_lo, t_hi]
            k0 = int(np.searchsorted(strip_map.segment_starts, t_lo, side="right")) - 1
            k1 = int(np.searchsorted(strip_map.segment_starts, t_hi, side="right")) - 1
            seg_ids = strip_map.segment_ids[max(k0, 0):k1 + 1].tolist()
        else:
            seg_ids = [psid]
        for sid in seg_ids:
            strips.setdefault(sid, StripSummary(sid, strip_map.source_of(sid))).files |= files
    # exact counts and spans come from the write pass; estimate spans from occupancy
    spans_raw: dict[int, list[float]] = {}
    for psid, bins in occupancy.items():
        b = np.array(sorted(bins), dtype=np.float64)
        t_lo_b = b * gap_bin
        ids = strip_map.map(np.full(b.size, psid, dtype=np.uint16), t_lo_b + 0.5 * gap_bin)
        for sid in np.unique(ids):
            sel = ids == sid
            lo = max(float(t_lo_b[sel].min()), per_psid[psid][1])
            hi = min(float(t_lo_b[sel].max() + gap_bin), per_psid[psid][2])
            span = spans_raw.setdefault(int(sid), [math.inf, -math.inf])
            span[0], span[1] = min(span[0], lo), max(span[1], hi)

    # -- trajectory on the bag's clock
    estimated: EstimatedTrajectory | None = None
    dropped: list[int] = []
    attitude_range: dict[str, tuple[float, float]] = {}
    if traj_file is not None:
        assert traj_t_raw is not None and traj_xyz is not None
        t_clock = rule.trajectory(traj_t_raw)
        c0, c1 = rule.points(np.array([p0, p1]))
        # the file's samples screened as a whole, at the file's times (a warning line counts
        # what is left out)
        usable = screen_samples(traj_t_raw, traj_xyz, str(traj_file.path))
        whole = Trajectory.from_samples(
            t_clock[usable], traj_xyz[usable],
            None if traj_orientation is None else traj_orientation[usable],
            full_attitude=full_attitude)
        inside = np.flatnonzero((whole.t >= c0 - 5.0) & (whole.t <= c1 + 5.0))
        traj = whole.take(inside[_decimate(whole.t[inside], trajectory_rate_hz)])
        kind, attitude_range = _trajectory_kind(traj, traj_file)
        # fail fast: strip spans known to the gap-bin resolution (exact check while writing)
        inner = []
        for sid, (lo, hi) in spans_raw.items():
            exact = sid in strip_map.labelled or not (strip_map.by_gap_all or 0 in per_psid)
            pad = 0.0 if exact else gap_bin
            a, b = rule.points(np.array([lo + pad, max(lo + pad, hi - pad)]))
            inner.append(StripSummary(sid, "", 1, float(a), float(b)))
        _check_coverage(traj, inner, str(traj_file.path))
    else:
        rays = collector.rays()
        rays.group = strip_map.map(rays.group.astype(np.uint16), rays.t)
        rays.t = rule.points(rays.t)
        spans = {sid: tuple(float(v) for v in rule.points(np.array(s)))
                 for sid, s in spans_raw.items()}
        opts = {k: v for k, v in (estimate_options or {}).items()
                if k not in _COLLECTOR_OPTIONS}
        if not len(rays):
            raise TrajectoryError(
                f"{paths[0]}: no trajectory can be rebuilt from multiple returns: "
                + (f"{returns_seen[0]} first and {returns_seen[1]} last returns of multi-return "
                   "pulses, but no pulse holds both (thinned to one return per pulse?)"
                   if any(returns_seen) else "no point belongs to a pulse with several returns")
                + "; give a trajectory file with --trajectory"
            )
        estimated = estimate_trajectory(rays, spans, EstimateSettings(**opts))  # type: ignore[arg-type]
        dropped = sorted(estimated.failed_strips)
        if len(dropped) == len(spans):
            worst = next((q for q in estimated.segments if q.level == "ERROR"), None)
            why = f" (strip {worst.strip_id}: {worst.message})" if worst is not None else ""
            raise TrajectoryError(
                f"{paths[0]}: no strip's trajectory could be rebuilt from multiple returns"
                f"{why}; give a trajectory file with --trajectory"
            )
        for outcome in estimated.strips:
            if not outcome.kept or outcome.fallback:
                logger.warning("trajectory estimate, %s", outcome.summary)
        traj = estimated.trajectory
        kind = "estimated from multiple returns"

    # -- write pass
    t_start = p0
    kept_strips = {sid: s for sid, s in strips.items() if sid not in dropped}
    grid = None
    if qa_cell_m > 0:
        grid = OverlapGrid(qa_cell_m, (float(infos[0].mins[0] * factors[0]),
                                        float(infos[0].mins[1] * factors[0])))
    n_points, n_poses = _write_bag(
        out, store, strip_map, rule, traj, kept_strips, t_start=t_start, grid=grid,
        frame_id=frame_id, chunk_seconds=chunk_seconds, points_topic=points_topic,
        trajectory_topic=trajectory_topic, memory_points=memory_points, overwrite=overwrite,
        progress=progress, n_total=n_kept,
        coverage_where=str(traj_file.path) if traj_file is not None else "trajectory estimate",
    )
    crs_name = points_crs.name if points_crs is not None else "unknown (coordinates as stored)"
    return ImportReport(
        output=out, n_files=len(paths), n_points=n_points, n_read=n_read,
        strips=[kept_strips[k] for k in sorted(kept_strips) if kept_strips[k].n_points],
        trajectory_kind=kind, n_poses=n_poses, time_rule=rule, crs_name=crs_name,
        unit_factors=factors, estimate=estimated, dropped_strips=dropped,
        spilled_runs=len(store.runs), overlaps=grid.pairs() if grid is not None else [],
        attitude_range_deg=attitude_range,
        model=_model_note(traj),
    )


def _model_note(traj: Trajectory) -> str:
    """The model ``matching.model auto`` gives the whole trajectory, and why."""
    if len(traj) < 2:
        return ""
    choice = choose_model(traj, float(traj.t[0]), float(traj.t[-1]))
    return f"{choice.model} ({choice.reason})"


def _trajectory_kind(traj: Trajectory, traj_file: TrajectoryFile
                     ) -> tuple[str, dict[str, tuple[float, float]]]:
    """What the imported poses carry, in words, and the range of their roll and pitch
    (degrees, from the quaternions written: what the calibration will see)."""
    name = f"{traj_file.kind.upper()} {traj_file.path.name}"
    if traj.orientation is None:
        return f"{name}, positions only", {}
    if not traj.full_attitude:
        return f"{name}, with heading only", {}
    roll, pitch, _ = attitude_from_quaternions(traj.orientation)
    ranges = {label: (float(np.degrees(np.nanmin(v))), float(np.degrees(np.nanmax(v))))
              for label, v in (("roll", roll), ("pitch", pitch))}
    return f"{name}, with attitude (roll, pitch, heading)", ranges


def _write_bag(
    out: Path,
    store: _RunStore,
    strip_map: _StripMap,
    rule: TimeRule,
    traj: Trajectory,
    strips: dict[int, StripSummary],
    *,
    t_start: float,
    grid: OverlapGrid | None,
    frame_id: str,
    chunk_seconds: float,
    points_topic: str,
    trajectory_topic: str,
    memory_points: int,
    overwrite: bool,
    progress: Progress,
    n_total: int,
    coverage_where: str,
) -> tuple[int, int]:
    """Merge the runs by time and write clouds and poses in log-time order.

    Strip spans are checked against the trajectory as the clouds are written (the spans are
    final only then); a strip not covered aborts the bag with a TrajectoryError.
    """
    sources = store.sources()
    pose_ns = [seconds_to_ns(float(v)) for v in traj.t]
    pose_i = 0
    written = 0
    tt = traj.t

    def covered(sid: int, a: float, b: float) -> None:
        if not len(tt) or tt[0] > a or tt[-1] < b:
            span = f"{tt[0]:.3f}-{tt[-1]:.3f} s" if len(tt) else "nothing"
            raise TrajectoryError(
                f"{coverage_where}: trajectory covers {span} but strip {sid} has points at "
                f"{a:.3f}-{b:.3f} s; it does not cover the points' times"
            )

    with BagWriter(out, overwrite=overwrite) as writer:
        for window in _merged_windows(sources, t_start, chunk_seconds,
                                      max(memory_points, 10_000)):
            sid = strip_map.map(window["strip_id"], window["t"])
            chunk_k = np.floor((window["t"] - t_start) / chunk_seconds).astype(np.int64)
            window["t"] = rule.points(window["t"])
            keep = np.isin(sid, np.fromiter(strips, dtype=np.int64))
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
                s = strips[int(sid[a])]
                t_lo, t_hi = float(part["t"][0]), float(part["t"][-1])
                covered(s.strip_id, t_lo, t_hi)
                s.n_points += b - a
                s.t_first, s.t_last = min(s.t_first, t_lo), max(s.t_last, t_hi)
                stamp = seconds_to_ns(t0)
                while pose_i < len(pose_ns) and pose_ns[pose_i] <= stamp:
                    writer.write_trajectory_pose(trajectory_topic, pose_ns[pose_i],
                                                 frame_id, traj, pose_i)
                    pose_i += 1
                writer.write_cloud(points_topic, stamp, frame_id, part)
                written += b - a
            progress("writing", written / max(n_total, 1))
        while pose_i < len(pose_ns):
            writer.write_trajectory_pose(trajectory_topic, pose_ns[pose_i], frame_id, traj,
                                         pose_i)
            pose_i += 1
        _check_coverage(traj, [s for s in strips.values() if s.n_points], coverage_where)
    return written, len(pose_ns)
