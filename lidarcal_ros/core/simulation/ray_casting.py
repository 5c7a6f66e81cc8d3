"""Rays cast into a simulated surface: where each pulse meets the ground, a roof, a crown or a wall.

The search: docs/internals.md, "The simulator". Everything in the surface's local frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lidarcal_ros.core.simulation.object_tops import NO_OBJECT
from lidarcal_ros.core.simulation.surface import Surface
from lidarcal_ros.errors import ConfigError


@dataclass
class RayHits:
    """Result of :func:`cast_rays` (all in the surface's local frame).

    Attributes
    ----------
    t : (n,) float64
        Distance along each (unit) ray to the hit, metres.
    xyz : (n, 3) float64
        Hit points, local coordinates.
    on_wall : (n,) bool
        The ray stopped on a vertical face (building wall or crown edge).
    inside : (n, 3) float64
        A point within 1e-6 m of the hit on the object side (used to classify wall hits).
    """

    t: np.ndarray
    xyz: np.ndarray
    on_wall: np.ndarray
    inside: np.ndarray


def cast_rays(
    surface: Surface,
    origins: np.ndarray,
    directions: np.ndarray,
    *,
    step: float = 0.5,
    tol: float = 1e-6,
    block: int = 262_144,
) -> RayHits:
    """First intersection of downward rays with the surface (walls included).

    Parameters
    ----------
    surface : Surface
    origins : (n, 3) float64
        Ray origins, *local* coordinates (map minus ``surface.origin``), above the surface.
    directions : (n, 3) float64
        Unit directions, pointing down (``d_z < 0``), at most ~60 deg off nadir.
    step : float
        Longest march step along a ray, metres (<= 0.5 m).
    tol : float
        Bisection stops when the bracket is shorter than this, metres.
    block : int
        Rays processed at a time (bounds memory).

    Returns
    -------
    RayHits
    """
    origins = np.ascontiguousarray(origins, dtype=np.float64).reshape(-1, 3)
    directions = np.ascontiguousarray(directions, dtype=np.float64).reshape(-1, 3)
    if origins.shape != directions.shape:
        raise ConfigError("cast_rays: origins and directions differ in shape")
    if np.any(directions[:, 2] >= -1e-3):
        raise ConfigError("cast_rays: every ray must point down")
    n = origins.shape[0]
    t_all = np.empty(n)
    wall_all = np.zeros(n, dtype=bool)
    inside_all = np.empty((n, 3))
    for i0 in range(0, n, block):
        i1 = min(i0 + block, n)
        t, wall, t_in = _cast_block(surface, origins[i0:i1], directions[i0:i1], step, tol)
        t_all[i0:i1] = t
        wall_all[i0:i1] = wall
        inside_all[i0:i1] = origins[i0:i1] + t_in[:, None] * directions[i0:i1]
    xyz = origins + t_all[:, None] * directions
    return RayHits(t=t_all, xyz=xyz, on_wall=wall_all, inside=inside_all)


def _cast_block(
    surface: Surface, o: np.ndarray, d: np.ndarray, step: float, tol: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One block of :func:`cast_rays`: the distance to each hit, whether it is on a wall, and
    the distance to a point just inside the object hit."""
    n = o.shape[0]
    t_g = surface.ground_hit(o, d)
    t_hit = t_g.copy()
    t_in = t_g.copy()
    wall = np.zeros(n, dtype=bool)
    tops = surface.object_tops
    if tops is None:
        return t_hit, wall, t_in
    step = min(step, 0.5)
    dxy = np.hypot(d[:, 0], d[:, 1])
    tan_max = float(np.max(dxy / -d[:, 2]))
    ground_min = float(np.min(o[:, 2] + t_g * d[:, 2]))
    reach = max(tops.max_top - ground_min, 0.0) * tan_max + 1.0
    gx = o[:, 0] + t_g * d[:, 0]
    gy = o[:, 1] + t_g * d[:, 1]
    z_top = tops.coarse_max(gx, gy, reach).astype(np.float64)
    t_top = np.maximum((o[:, 2] - z_top) / -d[:, 2], 0.0)
    cand = np.flatnonzero((z_top > NO_OBJECT / 2) & (t_top < t_g))
    if cand.size == 0:
        return t_hit, wall, t_in
    # sample the stretch [t_top, t_g] at <= one raster cell horizontally; a segment whose lower
    # end is above the dilated max of its upper end's cell cannot meet an object
    res = tops.res
    length_h = (t_g[cand] - t_top[cand]) * dxy[cand]
    k_need = np.ceil(length_h / (0.999 * res)).astype(np.int64) + 1
    k_bucket = np.maximum(2, 2 ** np.ceil(np.log2(np.maximum(k_need, 2))).astype(np.int64))
    t_start = np.full(cand.size, np.inf)
    for kb in np.unique(k_bucket):
        sel = np.flatnonzero(k_bucket == kb)
        idx = cand[sel]
        frac = np.linspace(0.0, 1.0, int(kb))
        ts = t_top[idx, None] + (t_g[idx] - t_top[idx])[:, None] * frac[None, :]
        xs = o[idx, 0, None] + ts * d[idx, 0, None]
        ys = o[idx, 1, None] + ts * d[idx, 1, None]
        zs = o[idx, 2, None] + ts * d[idx, 2, None]
        m = tops.fine_max(xs[:, :-1].ravel(), ys[:, :-1].ravel()).reshape(len(idx), -1)
        unsafe = zs[:, 1:] <= m
        has = unsafe.any(axis=1)
        j = np.argmax(unsafe, axis=1)
        rows = np.arange(len(idx))
        mj = m[rows, j].astype(np.float64)
        t_m = (o[idx, 2] - mj) / -d[idx, 2]
        ts_j = ts[rows, j]
        t_start[sel] = np.where(has, np.maximum(ts_j, t_m), np.inf)
    march = np.isfinite(t_start)
    idx = cand[march]
    if idx.size == 0:
        return t_hit, wall, t_in
    lo = t_start[march]
    tg = t_g[idx]
    lo = np.minimum(lo, tg)
    hi = np.empty_like(lo)
    # march: find the first step whose end is below the surface (or reaches the ground hit)
    active = np.arange(idx.size)
    cur = lo.copy()
    while active.size:
        ii = idx[active]
        nxt = np.minimum(cur[active] + step, tg[active])
        x = o[ii, 0] + nxt * d[ii, 0]
        y = o[ii, 1] + nxt * d[ii, 1]
        z = o[ii, 2] + nxt * d[ii, 2]
        below = (z <= surface.height_local(x, y)) | (nxt >= tg[active])
        done = active[below]
        lo[done] = cur[done]
        hi[done] = nxt[below]
        cur[active[~below]] = nxt[~below]
        active = active[~below]
    # bisection: lo above the surface, hi below it (or at the ground hit)
    n_iter = max(int(math.ceil(math.log2(max(step, tol) / tol))) + 1, 1)
    for _ in range(n_iter):
        mid = 0.5 * (lo + hi)
        x = o[idx, 0] + mid * d[idx, 0]
        y = o[idx, 1] + mid * d[idx, 1]
        z = o[idx, 2] + mid * d[idx, 2]
        below = z <= surface.height_local(x, y)
        hi = np.where(below, mid, hi)
        lo = np.where(below, lo, mid)
    # a wall: the surface jumps across the final (sub-micrometre) bracket
    h_lo = surface.height_local(o[idx, 0] + lo * d[idx, 0], o[idx, 1] + lo * d[idx, 1])
    h_hi = surface.height_local(o[idx, 0] + hi * d[idx, 0], o[idx, 1] + hi * d[idx, 1])
    is_wall = (h_hi - h_lo) > 1e-3
    t_hit[idx] = 0.5 * (lo + hi)
    t_in[idx] = hi
    wall[idx] = is_wall
    return t_hit, wall, t_in


__all__ = ["RayHits", "cast_rays"]
