"""How the point and trajectory times of an import meet on the bag's clock (docs/import.md)."""

from __future__ import annotations

import calendar
import datetime
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from lidarcal_ros.errors import TrajectoryError
from lidarcal_ros.io.survey.las_reader import GpsTimeType
from lidarcal_ros.io.survey.trajectory_files import (
    WEEK_S,
    TimeBase,
    TrajectoryFile,
    TrajectoryFileKind,
    gps_to_unix,
    gps_week_of_unix,
    to_gps_seconds,
)

logger = logging.getLogger(__name__)

#: Time bases of raw times, in words.
TIME_BASE_NAMES = {TimeBase.WEEK: "GPS week seconds",
                   TimeBase.ADJUSTED: "adjusted standard GPS time",
                   TimeBase.GPS: "GPS seconds", TimeBase.UNIX: "UNIX seconds"}
#: The time base a LAS header's GPS time type names.
_HEADER_BASES = {GpsTimeType.WEEK: TimeBase.WEEK, GpsTimeType.ADJUSTED: TimeBase.ADJUSTED}


@dataclass
class TimeRule:
    """How raw point and trajectory times map onto the bag's clock.

    Attributes
    ----------
    points_base, trajectory_base : TimeBase
        Of the raw times (trajectory: None without a file).
    week : int or None
        GPS week given to week-second times; None when the bag keeps week seconds.
    clock : TimeBase
        Of the bag: ``UNIX``, or ``WEEK`` where no GPS week is known.
    note : str
        The rule applied, in words.
    """

    points_base: TimeBase
    trajectory_base: TimeBase | None
    week: int | None
    clock: TimeBase
    note: str

    def _convert(self, raw: np.ndarray, base: TimeBase) -> np.ndarray:
        if self.clock is TimeBase.WEEK:
            return np.asarray(raw, dtype=np.float64)
        return gps_to_unix(to_gps_seconds(raw, base, week=self.week))

    def points(self, raw: np.ndarray) -> np.ndarray:
        """Point times on the bag's clock, seconds."""
        return self._convert(raw, self.points_base)

    def trajectory(self, raw: np.ndarray) -> np.ndarray:
        """Trajectory times on the bag's clock, seconds."""
        assert self.trajectory_base is not None
        return self._convert(raw, self.trajectory_base)


def points_time_base(header_base: GpsTimeType, last_time: float, where: str) -> TimeBase:
    """The time base of LAS points: their header's, unless their times cannot be week seconds.

    Parameters
    ----------
    header_base : GpsTimeType
        What the global-encoding bit says.
    last_time : float
        Latest raw point time, seconds.
    where : str
        Named in the warning.
    """
    if header_base is GpsTimeType.WEEK and last_time > 1.5 * WEEK_S:
        # Many producers leave the global-encoding bit at 0 while writing adjusted standard
        # time; week seconds never reach 1.5 weeks, adjusted standard time after 2011 does.
        logger.warning("%s: header says GPS week seconds, but times reach %.0f s; read as "
                       "adjusted standard GPS time", where, last_time)
        return TimeBase.ADJUSTED
    return _HEADER_BASES[header_base]


def gps_week_of_creation(dates: Sequence[datetime.date]) -> int | None:
    """GPS week of the latest LAS creation date (a processing date: only a tie breaker)."""
    if not dates:
        return None
    d = max(dates)
    return gps_week_of_unix(calendar.timegm((d.year, d.month, d.day, 0, 0, 0)))


def trajectory_readings(traj: TrajectoryFile, trajectory_time: TimeBase | None
                        ) -> tuple[list[TimeBase], np.ndarray]:
    """Readings of a trajectory file's times to try, likeliest first, and its raw times.

    Parameters
    ----------
    traj : TrajectoryFile
    trajectory_time : TimeBase or None
        The one base to use; None: chosen (an SBET: week seconds; ASCII: every reading
        plausible for the times' magnitude).

    Returns
    -------
    bases : list of TimeBase
    raw : (n,) float64
        The file's times, seconds; when week seconds come first, those restarting at 0 past
        the end of the week continue past 604800.
    """
    if trajectory_time is not None:
        bases = [trajectory_time]
    elif traj.kind is TrajectoryFileKind.SBET:
        bases = [TimeBase.WEEK]
    else:
        bases = _candidate_bases(traj.t)
    raw = unwrap_week(traj.t) if bases[0] is TimeBase.WEEK else traj.t
    return bases, raw


def _candidate_bases(values: np.ndarray) -> list[TimeBase]:
    """Readings of ASCII trajectory times plausible for their magnitude, likeliest first."""
    lo, hi = float(np.min(values)), float(np.max(values))
    if lo >= 0 and hi <= 1.5 * WEEK_S:
        return [TimeBase.WEEK, TimeBase.ADJUSTED]
    if lo >= 5e8:
        return [TimeBase.GPS, TimeBase.UNIX, TimeBase.ADJUSTED]
    return [TimeBase.ADJUSTED]


def unwrap_week(t: np.ndarray) -> np.ndarray:
    """Week seconds that restart at 0 past the end of the week continue past 604800."""
    jumps = np.flatnonzero(np.diff(t) < -0.5 * WEEK_S)
    if not jumps.size:
        return t
    out = t.copy()
    for j in jumps:
        out[j + 1:] += WEEK_S
    return out


def _overlap(a0: float, a1: float, b0: float, b1: float) -> float:
    """Fraction of [a0, a1] inside [b0, b1] (1 or 0 for an instant)."""
    if a1 <= a0:
        return 1.0 if b0 <= a0 <= b1 else 0.0
    return max(0.0, min(a1, b1) - max(a0, b0)) / (a1 - a0)


def reconcile_times(
    points_base: TimeBase,
    points_range: tuple[float, float],
    trajectory_range: tuple[float, float] | None,
    trajectory_bases: Sequence[TimeBase],
    *,
    gps_week: int | None = None,
    creation_week: int | None = None,
    where: str = "trajectory",
) -> TimeRule:
    """Choose how point and trajectory times meet (docs/import.md, "GPS time").

    Parameters
    ----------
    points_base : TimeBase
        ``WEEK`` or ``ADJUSTED``.
    points_range : (float, float)
        First and last raw point time.
    trajectory_range : (float, float) or None
        First and last raw trajectory time; None: no trajectory file.
    trajectory_bases : sequence of TimeBase
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
        if points_base is TimeBase.ADJUSTED:
            return TimeRule(TimeBase.ADJUSTED, None, None, TimeBase.UNIX,
                            "points in adjusted standard GPS time, written as UNIX time")
        if gps_week is not None:
            return TimeRule(TimeBase.WEEK, None, gps_week, TimeBase.UNIX,
                            f"points in week seconds of GPS week {gps_week} (given), written "
                            "as UNIX time")
        return TimeRule(TimeBase.WEEK, None, None, TimeBase.WEEK,
                        "points in GPS week seconds, written unchanged (no GPS week known)")
    t0, t1 = trajectory_range
    scored: list[tuple[float, int, int, TimeRule]] = []
    tried = []
    for rank, base in enumerate(trajectory_bases):
        tried.append(TIME_BASE_NAMES[base])
        if points_base is base is TimeBase.WEEK and gps_week is None:
            rule = TimeRule(TimeBase.WEEK, TimeBase.WEEK, None, TimeBase.WEEK,
                            "points and trajectory both in GPS week seconds, written unchanged")
            scored.append((_overlap(p0, p1, t0, t1), 0, -rank, rule))
            continue
        for week in _weeks(points_base, (p0, p1), base, (t0, t1), gps_week):
            pg = to_gps_seconds(np.array([p0, p1]), points_base, week=week)
            tg = to_gps_seconds(np.array([t0, t1]), base, week=week)
            cov = _overlap(float(pg[0]), float(pg[1]), float(tg[0]), float(tg[1]))
            note = (f"points in {TIME_BASE_NAMES[points_base]}, trajectory in "
                    f"{TIME_BASE_NAMES[base]}" + (f", GPS week {week}" if week is not None else "")
                    + "; written as UNIX time")
            tie = -abs(week - creation_week) if (week is not None and creation_week is not None
                                                 ) else 0
            scored.append((cov, tie, -rank,
                           TimeRule(points_base, base, week, TimeBase.UNIX, note)))
    best = max(scored, key=lambda s: s[:3]) if scored else None
    if best is None or best[0] <= 0.0:
        readings = ", ".join(tried) or "none"
        raise TrajectoryError(
            f"{where}: times {t0:.3f}-{t1:.3f} s do not overlap the points' times "
            f"{p0:.3f}-{p1:.3f} s ({TIME_BASE_NAMES[points_base]}) under any reading (tried "
            f"{readings}); wrong trajectory file, or give --trajectory-time / --gps-week"
        )
    if best[0] < 1.0:  # (the coverage of every strip is checked, and refused in one line)
        logger.info("%s: the trajectory covers only %.0f%% of the points' time span",
                    where, 100 * best[0])
    return best[3]


def _weeks(points_base: TimeBase, p: tuple[float, float], traj_base: TimeBase,
           t: tuple[float, float], gps_week: int | None) -> list[int | None]:
    """GPS weeks to try for the week-second side (None: no side is in week seconds)."""
    if points_base is not TimeBase.WEEK and traj_base is not TimeBase.WEEK:
        return [None]
    if gps_week is not None:
        return [gps_week]
    if points_base is not TimeBase.WEEK:
        g = float(to_gps_seconds(np.array([p[0]]), points_base)[0])
    elif traj_base is not TimeBase.WEEK:
        g = float(to_gps_seconds(np.array([t[0]]), traj_base)[0])
    else:
        return [None]
    w = int(math.floor(g / WEEK_S))
    return [w, w - 1, w + 1]


__all__ = ["TIME_BASE_NAMES", "TimeRule", "gps_week_of_creation", "points_time_base",
           "reconcile_times", "trajectory_readings", "unwrap_week"]
