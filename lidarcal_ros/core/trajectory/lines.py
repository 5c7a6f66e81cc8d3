"""Flight lines of a trajectory: the spans where its track holds a steady heading, turns left out.

A UAV (or any) mission recorded as one stream has no strip ids: its strips are the lines
flown, split from the trajectory where the heading of the track (map frame, from the
positions) turns by less than a few degrees a second, for long enough to be a line.
"""

from __future__ import annotations

import math
from itertools import pairwise

import numpy as np

from lidarcal_ros.core.georeferencing.heading import wrap_angle
from lidarcal_ros.core.mission import Trajectory
from lidarcal_ros.errors import ConfigError

#: Fastest turn of the track's heading still on a line, deg/s (a multirotor's sway of
#: centimetres at periods of seconds turns its track by under half a degree a second).
MAX_TURN_RATE_DEG_S = 2.0
#: Half the interval the track's velocity is taken over, s (averages out the sway).
WINDOW_S = 1.0
#: Shortest line kept, s.
MIN_LINE_S = 5.0
#: Slowest ground speed of a line, m/s (a hover has no track).
MIN_SPEED_MPS = 1.0


def straight_lines(trajectory: Trajectory, *, max_turn_rate_deg_s: float = MAX_TURN_RATE_DEG_S,
                   window_s: float = WINDOW_S, min_line_s: float = MIN_LINE_S,
                   min_speed_mps: float = MIN_SPEED_MPS) -> np.ndarray:
    """The time spans of the lines flown (docstring of the module).

    The track's velocity at each sample is the chord of the positions ``window_s`` before
    and after it; its heading's rate the change of that heading over the same interval. A
    sample is on a line where the horizontal speed is at least ``min_speed_mps`` and the
    rate at most ``max_turn_rate_deg_s``; a run of such samples without a gap of more than
    ``2 window_s`` is a line, trimmed by ``window_s`` at each end (the rate is an average over
    twice that: a turn may begin within it), kept if ``min_line_s`` long.

    Returns
    -------
    (k, 2) float64
        Each line's first and last time, s, in time order.
    """
    for name, value in (("max_turn_rate_deg_s", max_turn_rate_deg_s), ("window_s", window_s),
                        ("min_line_s", min_line_s), ("min_speed_mps", min_speed_mps)):
        if not (math.isfinite(value) and value > 0.0):
            raise ConfigError(f"flight lines: {name} must be positive, got {value}")
    t, xy = trajectory.t, trajectory.xyz[:, :2]
    none = np.empty((0, 2))
    if t.size < 3:
        return none
    lo = np.searchsorted(t, t - window_s)
    hi = np.searchsorted(t, t + window_s, side="right") - 1
    span = t[hi] - t[lo]
    with np.errstate(invalid="ignore", divide="ignore"):
        v = (xy[hi] - xy[lo]) / span[:, None]
    heading = np.arctan2(v[:, 1], v[:, 0])
    with np.errstate(invalid="ignore", divide="ignore"):
        rate = np.abs(wrap_angle(heading[hi] - heading[lo])) / span
    moving = np.hypot(v[:, 0], v[:, 1]) >= min_speed_mps
    # (comparisons with NaN are False: samples without a span are on no line)
    steady = moving[lo] & moving[hi] & moving & (rate <= math.radians(max_turn_rate_deg_s))
    gap = np.diff(t) > 2.0 * window_s
    # runs of steady samples, broken at gaps
    edge = np.flatnonzero(np.diff(steady.astype(np.int8)) != 0) + 1
    cuts = np.unique(np.concatenate([[0], edge, np.flatnonzero(gap) + 1, [t.size]]))
    out = []
    for a, b in pairwise(cuts):
        if not steady[a]:
            continue
        t0, t1 = t[a] + window_s, t[b - 1] - window_s
        if t1 - t0 >= min_line_s:
            out.append((t0, t1))
    return np.array(out, dtype=np.float64).reshape(-1, 2) if out else none


def line_of(t: np.ndarray, lines: np.ndarray) -> np.ndarray:
    """The line (index into ``lines``, :func:`straight_lines`) each time ``t`` (s) falls in,
    -1 outside every line (int64)."""
    t = np.asarray(t, dtype=np.float64)
    lines = np.asarray(lines, dtype=np.float64).reshape(-1, 2)
    k = np.searchsorted(lines[:, 0], t, side="right") - 1
    inside = (k >= 0) & (t <= lines[np.clip(k, 0, None), 1]) if lines.size else \
        np.zeros(t.shape, dtype=bool)
    return np.where(inside, k, -1).astype(np.int64)


__all__ = ["MAX_TURN_RATE_DEG_S", "MIN_LINE_S", "MIN_SPEED_MPS", "WINDOW_S", "line_of",
           "straight_lines"]
