"""The heading ``kappa`` of the local trajectory: from the track, or from the IMU's attitude.

``matching.heading_source`` chooses (docs/method.md section 4); ``kappa`` in radians, the
forward axis along ``(-sin kappa, cos kappa)``. Why a crabbing aircraft needs the attitude:
docs/internals.md, "Point positioning".
"""

from __future__ import annotations

import enum
import logging
import math

import numpy as np

from lidarcal_ros.core.mission import Trajectory
from lidarcal_ros.errors import ConfigError, TrajectoryError

logger = logging.getLogger(__name__)


class HeadingSource(enum.StrEnum):
    """Where a heading comes from: the values of ``matching.heading_source`` (module
    docstring), and ``TRACK`` or ``ATTITUDE``, where a strip's heading came from."""

    AUTO = "auto"
    TRACK = "track"
    ATTITUDE = "attitude"


#: Largest median |attitude - track| heading difference (deg) that ``auto`` takes for a crab:
#: an aircraft crabs by up to about 15 degrees in strong winds; a body frame of another
#: convention differs by 90 or 180.
MAX_CRAB_DEG = 20.0

#: Messages already logged (a stream asks once per chunk; one line is enough).
_LOGGED: set[str] = set()


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Angles (rad) wrapped into ``[-pi, pi)``."""
    return np.mod(np.asarray(a, dtype=np.float64) + math.pi, 2.0 * math.pi) - math.pi


def window_headings(heading: np.ndarray, start: np.ndarray, stop: np.ndarray) -> np.ndarray:
    """The circular mean of ``heading[start[k]:stop[k]]`` for each window ``k`` (rad); NaN
    where a sample of the window has none.

    Parameters
    ----------
    heading : (m,) float64
        ``kappa`` of each trajectory sample, rad (NaN: no orientation).
    start, stop : (k,) int
        Each window's first and one-past-last sample (``start < stop``).
    """
    start = np.asarray(start, dtype=np.int64)
    stop = np.asarray(stop, dtype=np.int64)
    if start.size == 0:
        return np.empty(0)
    # Only the samples the windows reach (a live buffer holds minutes of them).
    lo, hi = int(start.min()), int(stop.max())
    h = heading[lo:hi]
    missing = np.isnan(h)
    c = np.concatenate(([0.0], np.cumsum(np.where(missing, 0.0, np.cos(h)))))
    s = np.concatenate(([0.0], np.cumsum(np.where(missing, 0.0, np.sin(h)))))
    gaps = np.concatenate(([0], np.cumsum(missing)))
    a, b = start - lo, stop - lo
    mean = np.arctan2(s[b] - s[a], c[b] - c[a])
    return np.where(gaps[b] - gaps[a] > 0, np.nan, mean)


def median_crab_deg(track: np.ndarray, attitude: np.ndarray | None) -> float:
    """The median of ``attitude - track`` over windows (deg, signed: positive
    counter-clockwise, the nose left of the track); NaN without a full attitude."""
    if attitude is None or not attitude.size or bool(np.isnan(attitude).any()):
        return math.nan
    return float(np.degrees(np.median(wrap_angle(attitude - track))))


def choose_heading(track: np.ndarray, attitude: np.ndarray | None, mode: HeadingSource, *,
                   source: str = "points") -> np.ndarray:
    """The heading of each window (rad) by ``matching.heading_source`` (docs/method.md section 4).

    Parameters
    ----------
    track : (k,) float64
        The heading of each window's fitted line, rad.
    attitude : (k,) float64 or None
        The windows' heading from the orientation (:func:`window_headings`; NaN where
        missing), or None when the trajectory has no orientation.
    mode : HeadingSource
    source : str
        Named in messages.

    Returns
    -------
    (k,) float64
        ``track`` or ``attitude`` itself (``is`` tells which was taken).

    Raises
    ------
    TrajectoryError
        ``attitude`` asked for where the trajectory has no orientation.
    """
    if mode == HeadingSource.TRACK or track.size == 0:
        return track
    missing = attitude is None or bool(np.isnan(attitude).any())
    if mode == HeadingSource.ATTITUDE:
        if missing:
            raise TrajectoryError(
                f"{source}: matching.heading_source is 'attitude' but the trajectory has no "
                "orientation there (identity or absent); use 'track' or 'auto'")
        assert attitude is not None
        return attitude
    if missing:
        return track
    assert attitude is not None
    crab = abs(median_crab_deg(track, attitude))
    if crab > MAX_CRAB_DEG:
        _log_once(f"trajectory orientation disagrees with the track by {round(crab):.0f} "
                  f"degrees (median; more than the {MAX_CRAB_DEG:g} a crab reaches): heading "
                  "from the track; set matching.heading_source to 'attitude' to use it anyway "
                  "(its body frame must be x forward, y left, z up)")
        return track
    return attitude


def check_orientation(mode: HeadingSource, trajectory: Trajectory, where: str) -> None:
    """Refuse at once what ``attitude`` would refuse strip by strip: a trajectory without
    orientation (ConfigError naming ``where``)."""
    if mode == HeadingSource.ATTITUDE and trajectory.heading is None:
        raise ConfigError(f"{where}: matching.heading_source is 'attitude' but the trajectory's "
                          "poses carry no orientation (identity); use 'track' or 'auto'")


def describe_heading_use(heading_from: dict[int, HeadingSource],
                         crab_deg: dict[int, float] | None = None) -> str | None:
    """One line on where the strips' headings came from (strip id -> ``track`` or
    ``attitude``) and the range of their crab (strip id -> deg, NaN: unknown), or None where
    every one came from the track (docs/method.md as written)."""
    attitude = sorted(k for k, v in heading_from.items() if v == HeadingSource.ATTITUDE)
    if not attitude:
        return None
    track = sorted(k for k, v in heading_from.items() if v != HeadingSource.ATTITUDE)
    text = ("heading from the poses' orientation (IMU) for every strip" if not track else
            f"heading from the poses' orientation (IMU) for strips "
            f"{', '.join(map(str, attitude))}; from the track for {', '.join(map(str, track))}")
    crabs = [c for k, c in (crab_deg or {}).items() if k in attitude and math.isfinite(c)]
    if crabs:
        text += f" (crab {min(crabs):+.1f} to {max(crabs):+.1f} deg)"
    return text


def describe_heading_policy(mode: HeadingSource, has_orientation: bool) -> str:
    """What ``matching.heading_source`` makes of a trajectory with or without orientation."""
    if mode == HeadingSource.TRACK:
        return "from the track (matching.heading_source track)"
    if not has_orientation:
        return "from the track (the poses carry no orientation)"
    if mode == HeadingSource.ATTITUDE:
        return "from the poses' orientation (matching.heading_source attitude)"
    return (f"from the poses' orientation where it agrees with the track within "
            f"{MAX_CRAB_DEG:g} deg, else from the track (matching.heading_source auto)")


def _log_once(message: str) -> None:
    if message not in _LOGGED:
        _LOGGED.add(message)
        logger.warning("%s", message)


__all__ = [
    "MAX_CRAB_DEG", "HeadingSource", "check_orientation", "choose_heading",
    "describe_heading_policy", "describe_heading_use", "median_crab_deg", "window_headings",
    "wrap_angle",
]
