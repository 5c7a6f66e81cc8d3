"""Compiled loops of the local trajectory: points below it, windows, firing positions, geometry.

docs/method.md section 4; the rules of compiled loops: docs/internals.md, "Compiled loops".
"""

from __future__ import annotations

import math

import numpy as np

from lidarcal_ros.core.jit import compiled, inlined


@inlined
def _laser_frame(ti: float, px: float, py: float, pz: float, w: int, t_mean: np.ndarray,
                 p_mean: np.ndarray, velocity: np.ndarray, c: float, s: float
                 ) -> tuple[float, float, float, float, float]:
    """The firing position ``p_mean + velocity (t - t_mean)`` of window ``w`` at time ``ti``
    and the point's ``x`` (across track, heading ``(c, s)``) and ``z`` from it (docs/method.md
    section 4): ``ox, oy, oz, x, z``, m."""
    dt = ti - t_mean[w]
    ox = p_mean[w, 0] + velocity[w, 0] * dt
    oy = p_mean[w, 1] + velocity[w, 1] * dt
    oz = p_mean[w, 2] + velocity[w, 2] * dt
    return ox, oy, oz, (px - ox) * c + (py - oy) * s, pz - oz


@compiled
def below_line(t: np.ndarray, z: np.ndarray, line_t: np.ndarray, line_z: np.ndarray,
               depth: float) -> np.ndarray:
    """``z < np.interp(t, line_t, line_z) - depth`` in one pass (points at least ``depth``
    below a piecewise-linear height, e.g. the trajectory's).

    The interpolation is numpy's, operation for operation (the value at a sample, the
    first or last height beyond the ends, ``slope (t - t_j) + z_j`` between), so the
    comparison decides alike. The previous point's interval is tried first: points come
    in time order.

    Parameters
    ----------
    t, z : (n,) float64
        Times (s) and heights (m) of the points.
    line_t, line_z : (m,) float64, m >= 1
        Sample times, increasing, and heights of the line.
    depth : float
        Least depth below the line, m.
    """
    n = t.shape[0]
    m = line_t.shape[0]
    out = np.empty(n, dtype=np.bool_)
    j = 0
    for i in range(n):
        x = t[i]
        if math.isnan(x):
            out[i] = False
            continue
        # j: the last sample at or before x (-1 before the first)
        if not (0 <= j < m - 1 and line_t[j] <= x < line_t[j + 1]):
            j = np.searchsorted(line_t, x, side="right") - 1
        if j < 0:
            h = line_z[0]
        elif j >= m - 1:
            h = line_z[m - 1]
        elif line_t[j] == x:
            h = line_z[j]
        else:
            slope = (line_z[j + 1] - line_z[j]) / (line_t[j + 1] - line_t[j])
            h = slope * (x - line_t[j]) + line_z[j]
            if math.isnan(h):
                h = slope * (x - line_t[j + 1]) + line_z[j + 1]
                if math.isnan(h) and line_z[j] == line_z[j + 1]:
                    h = line_z[j]
        out[i] = z[i] < h - depth
    return out


@compiled
def sorted_time_windows(traj_t: np.ndarray, t: np.ndarray, window_s: float, min_samples: int
                        ) -> tuple[bool, np.ndarray, np.ndarray, np.ndarray, int, int]:
    """The trajectory window of each point of a time-ordered chunk, in one merging pass.

    The window of time ``t`` holds the samples inside ``(t - window_s, t + window_s)``: from
    ``start = searchsorted(traj_t, t - window_s, "right")`` to
    ``stop = searchsorted(traj_t, t + window_s, "left")``. It serves the point when it holds
    ``min_samples`` samples and brackets ``t``
    (:func:`~lidarcal_ros.core.georeferencing.local_trajectory.windows_cover_points`). Consecutive
    points sharing a window share its line fit.

    Parameters
    ----------
    traj_t : (m,) float64
        Trajectory sample times, s, increasing.
    t : (n,) float64, n >= 1
        Firing times, s.

    Returns
    -------
    in_order : bool
        False when ``t`` is not non-decreasing (or holds NaN); then nothing else is
        meaningful (use the general search).
    start, stop : (k,) int64
        The distinct windows, in order.
    window : (n,) int64
        The window of each point.
    n_bad : int
        Points whose window does not serve them.
    first_bad : int
        The first of them (-1 if none).
    """
    n = t.shape[0]
    m = traj_t.shape[0]
    window = np.empty(n, dtype=np.int64)
    start = np.empty(n, dtype=np.int64)
    stop = np.empty(n, dtype=np.int64)
    last = m - 1
    a = np.searchsorted(traj_t, t[0] - window_s, side="right")
    b = np.searchsorted(traj_t, t[0] + window_s, side="left")
    k = -1
    n_bad = 0
    first_bad = -1
    for i in range(n):
        ti = t[i]
        if not (i == 0 or ti >= t[i - 1]):  # (NaN fails too)
            return False, start[:0], stop[:0], window, 0, -1
        lo = ti - window_s
        hi = ti + window_s
        while a < m and traj_t[a] <= lo:
            a += 1
        while b < m and traj_t[b] < hi:
            b += 1
        if k < 0 or a != start[k] or b != stop[k]:
            k += 1
            start[k], stop[k] = a, b
        window[i] = k
        served = (a < b and traj_t[min(a, last)] <= ti and traj_t[max(b - 1, 0)] >= ti
                  and b - a >= min_samples)
        if not served:
            if n_bad == 0:
                first_bad = i
            n_bad += 1
    return True, start[:k + 1], stop[:k + 1], window, n_bad, first_bad


@compiled
def window_geometry(t: np.ndarray, xyz: np.ndarray, window: np.ndarray, t_mean: np.ndarray,
                    p_mean: np.ndarray, velocity: np.ndarray, kappa_w: np.ndarray,
                    cos_w: np.ndarray, sin_w: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                               np.ndarray, np.ndarray, np.ndarray]:
    """Firing position and laser-frame geometry of each point from the line fitted to its
    trajectory window (docs/method.md section 4).

    Parameters
    ----------
    t : (n,) float64
        Firing times, s.
    xyz : (n, 3) float64
        Points, map frame, m.
    window : (n,) int64
        The window of each point.
    t_mean, p_mean, velocity : (k,), (k, 3), (k, 3) float64
        Each window's line: mean time (s), mean position (m), velocity (m/s).
    kappa_w, cos_w, sin_w : (k,) float64
        Each window's heading (rad), its cosine and sine.

    Returns
    -------
    origin : (n, 3) ``p_mean + velocity (t - t_mean)``, m
    x, z : (n,) ``(xyz - origin) . (cos kappa, sin kappa, 0)`` and the height difference, m
    kappa, cos_kappa, sin_kappa : (n,) the window's heading, its cosine and sine
    sin_beta, cos_beta : (n,) ``-x / r`` and ``-z / r`` with ``r = sqrt(x^2 + z^2)``: the
        mirror angle's sine and cosine (``z < 0``)

    (The mirror angle ``atan(x / z)`` is left to numpy, whose SIMD arctangent is several
    times faster than a scalar one.)
    """
    n = t.shape[0]
    origin = np.empty((n, 3))
    x = np.empty(n)
    z = np.empty(n)
    kappa = np.empty(n)
    cos_kappa = np.empty(n)
    sin_kappa = np.empty(n)
    sin_beta = np.empty(n)
    cos_beta = np.empty(n)
    for i in range(n):
        w = window[i]
        c, s = cos_w[w], sin_w[w]
        ox, oy, oz, xi, zi = _laser_frame(t[i], xyz[i, 0], xyz[i, 1], xyz[i, 2], w, t_mean,
                                          p_mean, velocity, c, s)
        origin[i, 0], origin[i, 1], origin[i, 2] = ox, oy, oz
        x[i], z[i] = xi, zi
        kappa[i], cos_kappa[i], sin_kappa[i] = kappa_w[w], c, s
        inv_r = 1.0 / math.sqrt(xi * xi + zi * zi)
        sin_beta[i], cos_beta[i] = -xi * inv_r, -zi * inv_r
    return origin, x, z, kappa, cos_kappa, sin_kappa, sin_beta, cos_beta


__all__ = ["below_line", "sorted_time_windows", "window_geometry"]
