"""Laser-frame quantities recovered from points and trajectory positions (docs/method.md section 4).

One line fit per distinct window of trajectory samples, not one per point.
"""

from __future__ import annotations

import itertools
import logging
import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from lidarcal_ros.core.georeferencing.heading import (
    HeadingSource,
    choose_heading,
    median_crab_deg,
    window_headings,
)
from lidarcal_ros.core.georeferencing.laser_geometry import LaserGeometry
from lidarcal_ros.core.georeferencing.local_trajectory_kernels import (
    below_line,
    sorted_time_windows,
    window_geometry,
)
from lidarcal_ros.core.mission import Trajectory
from lidarcal_ros.core.normals.grid_normals import finite_rows
from lidarcal_ros.errors import TrajectoryError

logger = logging.getLogger(__name__)

#: Windows processed per block when fitting lines (bounds the memory of the ragged gather).
_FIT_BLOCK_SAMPLES = 4_000_000


@dataclass(frozen=True)
class TrajectoryWindow:
    """The trajectory samples that serve a point fired at ``t``: those in ``(t - window_s,
    t + window_s)``, at least ``min_samples`` of them, bracketing ``t``."""

    #: Half-width ``Dt`` of the window, s (``matching.trajectory_window_s``).
    window_s: float = 0.5
    #: Fewest samples a window may hold; fewer is a trajectory gap at that time.
    min_samples: int = 2


#: The window by default (``matching.trajectory_window_s``'s default).
DEFAULT_WINDOW = TrajectoryWindow()


def _fit_windows(
    traj_t: np.ndarray, traj_xyz: np.ndarray, start: np.ndarray, stop: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares line through samples ``start[k]:stop[k]`` for each window ``k``.

    Returns the window's mean time ``t_mean`` (k,), mean position ``p_mean`` (k, 3) and
    velocity ``v`` (k, 3). Sums are centred per window (two passes) so that absolute GPS times
    and projected coordinates lose no precision.
    """
    lengths = stop - start
    n_windows = start.shape[0]
    t_mean = np.empty(n_windows)
    p_mean = np.empty((n_windows, 3))
    vel = np.empty((n_windows, 3))
    # Blocks of windows whose total sample count stays bounded.
    cum = np.cumsum(lengths)
    block_edges = np.searchsorted(cum, np.arange(_FIT_BLOCK_SAMPLES, cum[-1], _FIT_BLOCK_SAMPLES))
    bounds = np.concatenate(([0], block_edges + 1, [n_windows]))
    bounds = np.unique(np.clip(bounds, 0, n_windows))
    for b0, b1 in itertools.pairwise(bounds):
        s0, ln = start[b0:b1], lengths[b0:b1]
        offsets = np.concatenate(([0], np.cumsum(ln)[:-1]))
        flat = np.repeat(s0 - offsets, ln) + np.arange(int(ln.sum()))
        # Reference each window to its first sample to keep magnitudes small before summing.
        ref_t = np.repeat(traj_t[s0], ln)
        ref_p = np.repeat(traj_xyz[s0], ln, axis=0)
        tt = traj_t[flat] - ref_t
        pp = traj_xyz[flat] - ref_p
        tm = np.add.reduceat(tt, offsets) / ln
        pm = np.add.reduceat(pp, offsets, axis=0) / ln[:, None]
        dt = tt - np.repeat(tm, ln)
        dp = pp - np.repeat(pm, ln, axis=0)
        stt = np.add.reduceat(dt * dt, offsets)
        stp = np.add.reduceat(dt[:, None] * dp, offsets, axis=0)
        t_mean[b0:b1] = tm + traj_t[s0]
        p_mean[b0:b1] = pm + traj_xyz[s0]
        vel[b0:b1] = stp / stt[:, None]
    return t_mean, p_mean, vel


def covered_by_trajectory(
    t: np.ndarray, trajectory: Trajectory, *, window: TrajectoryWindow = DEFAULT_WINDOW
) -> np.ndarray:
    """Which firing times the local trajectory covers: at least ``min_samples`` samples within
    ``(t - window_s, t + window_s)`` bracketing ``t`` (the rule of
    :func:`laser_geometry`, which raises where it fails)."""
    window_s, min_samples = window.window_s, window.min_samples
    t = np.asarray(t, dtype=np.float64)
    traj_t = trajectory.t
    if len(traj_t) < min_samples or t.size == 0:
        return np.zeros(t.shape, dtype=bool)
    t_lo, t_hi = float(t.min()), float(t.max())
    if math.isfinite(t_lo) and math.isfinite(t_hi):
        # Fast path: samples bracket the whole span with every gap shorter than the window, so
        # each (t - w, t + w) holds a sample below and one above t (and min_samples <= 2).
        i0 = int(np.searchsorted(traj_t, t_lo, side="right")) - 1
        i1 = int(np.searchsorted(traj_t, t_hi, side="left"))
        if (min_samples <= 2 and 0 <= i0 < i1 < len(traj_t)
                and float(np.max(np.diff(traj_t[i0:i1 + 1]))) < window_s):
            return np.ones(t.shape, dtype=bool)
    start, stop = _windows(traj_t, t, window_s)
    return windows_cover_points(t, traj_t, start, stop, min_samples)


#: Least depth (m) below the trajectory of a point it serves: no real return comes from
#: within a metre of the sensor, and :func:`laser_geometry` needs the points below it.
MIN_DEPTH_M = 1.0


def served_by_trajectory(
    t: np.ndarray, xyz: np.ndarray, trajectory: Trajectory, *,
    window: TrajectoryWindow = DEFAULT_WINDOW, min_depth_m: float = MIN_DEPTH_M,
    all_finite: bool = False,
) -> np.ndarray:
    """Which points the local trajectory can serve: finite point and time, covered
    (:func:`covered_by_trajectory`), and at least ``min_depth_m`` below the trajectory's
    height at their time (linear interpolation of the samples). A point above the aircraft
    (a spurious return, a wrong time base) would make :func:`laser_geometry` refuse all the
    points given with it.

    Parameters
    ----------
    t : (n,) float64
        Firing times, s.
    xyz : (n, 3) float64
        Points, map frame, m.
    all_finite : bool
        Every point and time is known to be finite (as the caller found while extracting
        them): not checked again.

    Returns
    -------
    (n,) bool
    """
    ok = np.ones(t.shape[0], dtype=bool) if all_finite else np.isfinite(t) & finite_rows(xyz)
    ok &= covered_by_trajectory(t, trajectory, window=window)
    if ok.any():
        ok &= below_line(t, xyz[:, 2], trajectory.t, trajectory.xyz[:, 2],
                         min_depth_m)  # (the heights read in place)
    return ok


def _search(sorted_t: np.ndarray, q: np.ndarray, side: Literal["left", "right"]) -> np.ndarray:
    """``np.searchsorted(sorted_t, q, side)``, in linear time when ``q`` is sorted too.

    Points come in time order and a chunk spans few trajectory samples, so instead of a
    binary search per point the few samples inside ``[q[0], q[-1]]`` are placed among the
    queries and the index is a running count.
    """
    n = q.shape[0]
    if n < 2 or not bool(np.all(q[1:] >= q[:-1])):  # unsorted or NaN: the general search
        return np.searchsorted(sorted_t, q, side=side)
    lo = int(np.searchsorted(sorted_t, q[0], side=side))
    hi = int(np.searchsorted(sorted_t, q[-1], side=side))
    # Sample k is counted from the first query at (right) or past (left) it.
    steps = np.searchsorted(q, sorted_t[lo:hi], side="left" if side == "right" else "right")
    count = np.cumsum(np.bincount(steps, minlength=n + 1)[:n])
    count += lo
    return count


def _windows(traj_t: np.ndarray, t: np.ndarray, window_s: float
             ) -> tuple[np.ndarray, np.ndarray]:
    """First and one-past-last trajectory sample inside ``(t - window_s, t + window_s)``."""
    return (_search(traj_t, t - window_s, side="right"),
            _search(traj_t, t + window_s, side="left"))


def windows_cover_points(
    t: np.ndarray, traj_t: np.ndarray, start: np.ndarray, stop: np.ndarray, min_samples: int
) -> np.ndarray:
    """Which points their trajectory window serves: it holds ``min_samples`` samples at least
    and brackets the point (no extrapolation past a gap).

    Parameters
    ----------
    t : (n,) float64
        Firing times, s.
    traj_t : (m,) float64
        Trajectory sample times, s, increasing.
    start, stop : (n,) int64
        Each point's window: first and one-past-last sample inside ``(t - w, t + w)``.
    min_samples : int

    Returns
    -------
    (n,) bool
    """
    before = start < stop
    last = len(traj_t) - 1
    lo_ok = traj_t[np.minimum(start, last)] <= t
    hi_ok = traj_t[np.maximum(stop - 1, 0)] >= t
    return before & lo_ok & hi_ok & ((stop - start) >= min_samples)


@dataclass(frozen=True)
class WindowLines:
    """The local trajectory of each point: the line fitted to its window (docs/method.md section 4).

    Points sharing the same trajectory samples share a window, so there are a few windows
    per chunk of points, not one per point.

    Attributes
    ----------
    window : (n,) int64
        The window of each point.
    t_mean : (k,) float64
        Each window's mean time, s.
    p_mean : (k, 3) float64
        Its mean position, map frame, m.
    velocity : (k, 3) float64
        Its velocity, m/s: the firing position at ``t`` is ``p_mean + velocity (t - t_mean)``.
    kappa, cos_kappa, sin_kappa : (k,) float64
        Its heading (rad), cosine and sine: ``atan2(-v_x, v_y)``, or the orientation's
        (:mod:`lidarcal_ros.core.georeferencing.heading`).
    heading_from : HeadingSource
        Which: ``TRACK`` or ``ATTITUDE``.
    crab_deg : float
        The median of the attitude's heading less the track's, deg (NaN: no attitude).
    """

    window: np.ndarray
    t_mean: np.ndarray
    p_mean: np.ndarray
    velocity: np.ndarray
    kappa: np.ndarray
    cos_kappa: np.ndarray
    sin_kappa: np.ndarray
    heading_from: HeadingSource = HeadingSource.TRACK
    crab_deg: float = math.nan


def window_lines(
    t: np.ndarray,
    trajectory: Trajectory,
    *,
    window: TrajectoryWindow = DEFAULT_WINDOW,
    source: str = "points",
    heading_source: HeadingSource = HeadingSource.AUTO,
) -> WindowLines:
    """The local-trajectory line of each firing time (the first half of
    :func:`laser_geometry`, whose parameters these are).

    Raises
    ------
    TrajectoryError
        If the trajectory does not cover a point's time (a gap, or outside its span), or is
        stationary there.
    """
    n = t.shape[0]
    window_s, min_samples = window.window_s, window.min_samples
    if len(trajectory) < min_samples:
        raise TrajectoryError(
            f"{source}: trajectory has {len(trajectory)} samples, need at least {min_samples}"
        )
    traj_t = trajectory.t
    # Points in time order (the usual case): windows are runs, found in one pass.
    in_order, win_start, win_stop, inv, n_bad, first = sorted_time_windows(
        traj_t, t, float(window_s), int(min_samples))
    if not in_order:
        start, stop = _windows(traj_t, t, window_s)
        bad = ~windows_cover_points(t, traj_t, start, stop, min_samples)
        n_bad, first = int(bad.sum()), int(np.argmax(bad))
        # One fit per distinct window.
        key = start.astype(np.int64) * (len(traj_t) + 1) + stop
        _, first_idx, inverse = np.unique(key, return_index=True, return_inverse=True)
        win_start, win_stop, inv = start[first_idx], stop[first_idx], inverse.ravel()
    if n_bad:
        raise TrajectoryError(
            f"{source}: trajectory gap at t={t[first]:.3f} s "
            f"({n_bad} of {n} points not covered by >= {min_samples} samples "
            f"within +-{window_s:g} s)"
        )
    t_mean, p_mean, vel = _fit_windows(traj_t, trajectory.xyz, win_start, win_stop)
    speed_h = np.hypot(vel[:, 0], vel[:, 1])
    if np.any(speed_h <= 1e-6):
        raise TrajectoryError(f"{source}: trajectory is stationary; heading undefined")
    kappa = np.arctan2(-vel[:, 0], vel[:, 1])
    heading_from, crab = HeadingSource.TRACK, math.nan
    if heading_source != HeadingSource.TRACK:
        attitude = (None if trajectory.heading is None
                    else window_headings(trajectory.heading, win_start, win_stop))
        crab = median_crab_deg(kappa, attitude)
        kappa = choose_heading(kappa, attitude, heading_source, source=source)
        if kappa is attitude:
            heading_from = HeadingSource.ATTITUDE
    return WindowLines(np.asarray(inv, dtype=np.int64), t_mean, p_mean, vel, kappa,
                       np.cos(kappa), np.sin(kappa), heading_from, crab)


def laser_geometry(
    t: np.ndarray,
    xyz: np.ndarray,
    trajectory: Trajectory,
    *,
    window: TrajectoryWindow = DEFAULT_WINDOW,
    source: str = "points",
    heading_source: HeadingSource = HeadingSource.AUTO,
) -> LaserGeometry:
    """Recover ``x, z, kappa, beta`` for each point (docs/method.md section 4).

    Parameters
    ----------
    t : (n,) float64
        Firing times, seconds, on the trajectory's clock.
    xyz : (n, 3) float64
        Points in the map frame, metres.
    trajectory : Trajectory
        IMU-origin positions.
    window : TrajectoryWindow
        The samples fitted: within ``window_s`` (the half-width ``Dt``, s) of the firing
        time, ``min_samples`` at least (fewer means a trajectory gap at that time).
    source : str
        Name used in error messages (e.g. ``"strip 3"``).
    heading_source : HeadingSource
        Where ``kappa`` comes from: ``track`` (docs/method.md), ``attitude`` (the trajectory's
        orientation) or ``auto`` (:mod:`lidarcal_ros.core.georeferencing.heading`).

    Raises
    ------
    TrajectoryError
        If the trajectory does not cover a point's time (a gap, or outside its span).
    """
    t = np.asarray(t, dtype=np.float64)
    xyz = np.asarray(xyz, dtype=np.float64)
    if t.shape[0] == 0:
        return LaserGeometry.empty()
    lines = window_lines(t, trajectory, window=window, source=source,
                         heading_source=heading_source)
    return geometry_on_lines(t, xyz, lines, source=source)


def geometry_on_lines(t: np.ndarray, xyz: np.ndarray, lines: WindowLines, *,
                      source: str = "points") -> LaserGeometry:
    """The second half of :func:`laser_geometry`: ``x, z, kappa, beta`` and the firing
    position of each point from its local-trajectory line (:func:`window_lines` of ``t``).

    Raises
    ------
    TrajectoryError
        If a point is not below its firing position.
    """
    # Per point, in one pass: the firing position on its window's line, then what
    # geometry.geometry_at computes from it.
    origin, x, z, kappa, cos_kappa, sin_kappa, sin_beta, cos_beta = window_geometry(
        t, xyz, lines.window, lines.t_mean, lines.p_mean, lines.velocity, lines.kappa,
        lines.cos_kappa, lines.sin_kappa)
    with np.errstate(divide="ignore", invalid="ignore"):
        beta = np.arctan(x / z)
    geometry = LaserGeometry(x=x, z=z, kappa=kappa, beta=beta, origin=origin,
                             cos_kappa=cos_kappa, sin_kappa=sin_kappa, sin_beta=sin_beta,
                             cos_beta=cos_beta, heading_from=lines.heading_from,
                             crab_deg=lines.crab_deg)
    above = geometry.z >= 0
    if np.any(above):
        k = int(np.argmax(above))
        raise TrajectoryError(
            f"{source}: point at t={t[k]:.3f} s is not below the trajectory "
            f"(z={geometry.z[k]:.6g} m); wrong trajectory or time base?"
        )
    return geometry


__all__ = [
    "DEFAULT_WINDOW", "MIN_DEPTH_M", "TrajectoryWindow", "WindowLines", "covered_by_trajectory",
    "geometry_on_lines", "laser_geometry", "served_by_trajectory", "window_lines",
    "windows_cover_points",
]
