"""Thinning of a strip's points to one per map cell before calibration.

The quasi-rigorous method needs surfaces, not every return: its patches are triangles of one
strip's points and its candidates a capped random sample of the other's
(``matching.max_candidates_per_pair``). A sensor firing millions of pulses a second gives
tens of points per square metre, and a calibration holds some 700 bytes per point it loads
(points, triangles, their planes and neighbours): a mission of a few hundred million points
does not fit in memory, nor does a live strip of a few minutes. Keeping the first point of
each ``cell x cell`` square of the map, per strip, bounds the density (``1 / cell^2``) while
keeping the surface's shape down to the cell's size.

The thinning is done per cloud, in arrival order, the same way by ``lidarcal calibrate`` (per
message of the bag) and by the calibrator node (per message on the topic), so that both see
the same points. A cell cut by the boundary of two clouds may keep a point from each.

The choice is one compiled pass over the points (:mod:`lidarcal_ros.core.jit`): a flag per
cell of the cloud's box where that is small enough (:func:`first_in_grid`), else a hash table
of the cells met (:func:`first_in_cells`).
"""

from __future__ import annotations

import math

import numpy as np

from lidarcal_ros.core.jit import compiled, inlined

#: Most cells of the box of a cloud's points thinned with a flag per cell (16 MB); wider
#: clouds, and clouds of several strips, go through a hash table of the cells met.
_MAX_GRID_CELLS = 1 << 24


def first_per_cell(xyz: np.ndarray, group: np.ndarray, cell_m: float, *,
                   valid: np.ndarray | None = None) -> np.ndarray:
    """Which points to keep: the first, in order, of each ``cell_m`` square of the map
    (``x, y``) per group (strip), among the valid ones.

    Parameters
    ----------
    xyz : (n, 3) float64
        Points, map frame, m.
    group : (n,) integer
        Strip id of each point.
    cell_m : float
        Cell size, m (> 0).
    valid : (n,) bool, optional
        Points that count (default: finite ``x`` and ``y``); the others are not kept.

    Returns
    -------
    (n,) bool
    """
    if not cell_m > 0:
        raise ValueError(f"cell_m must be positive, got {cell_m}")
    xyz = np.asarray(xyz, dtype=np.float64)
    if valid is None:
        valid = np.isfinite(xyz[:, 0]) & np.isfinite(xyz[:, 1])
    args = (np.ascontiguousarray(xyz[:, 0]), np.ascontiguousarray(xyz[:, 1]),
            np.ascontiguousarray(group, dtype=np.int64), 1.0 / cell_m,
            np.ascontiguousarray(valid, dtype=bool))
    done, keep = first_in_grid(*args, _MAX_GRID_CELLS)
    return keep if done else first_in_cells(*args)


@inlined
def _cell_index(q: float) -> int:
    """``floor(q)`` as an integer, held within +-2^62 (a wild coordinate shares the cell at
    the limit instead of converting out of range)."""
    return int(np.int64(min(max(math.floor(q), -4.0e18), 4.0e18)))


@inlined
def _cell_slot(u: int, v: int, g: int | np.int64, mask: int) -> int:
    """Home slot of cell ``(u, v)`` of group ``g`` in a table of ``mask + 1`` slots."""
    h = (u * np.int64(-7046029254386353131) + v * np.int64(3266489917)
         + g * np.int64(668265263))
    return int((h ^ (h >> 29)) & mask)


@compiled
def first_in_cells(x: np.ndarray, y: np.ndarray, group: np.ndarray, inv_cell: float,
                   valid: np.ndarray) -> np.ndarray:
    """Which points are the first (in order) of their ``(group, floor(x / cell),
    floor(y / cell))`` cell among the ``valid`` ones: an open-addressing hash table of the
    cells met (grown as they come, so that it stays the size of the cells, which fit in
    cache, not of the points), whatever their extent (``np.unique`` of the keys, with
    ``return_index``, sorts them instead).

    Parameters
    ----------
    x, y : (n,) float64
        Map coordinates, m.
    group : (n,) integer
        Points of different groups (strips) never share a cell.
    inv_cell : float
        ``1 / cell``, 1/m.
    valid : (n,) bool
        Points that may be kept (invalid ones are neither kept nor occupy a cell).

    Returns
    -------
    (n,) bool
    """
    n = x.shape[0]
    size = 1024
    mask = size - 1
    used = np.zeros(size, dtype=np.bool_)
    keys = np.empty((size, 3), dtype=np.int64)
    count = 0
    keep = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        if not valid[i]:
            continue
        u = _cell_index(x[i] * inv_cell)
        v = _cell_index(y[i] * inv_cell)
        g = np.int64(group[i])
        slot = _cell_slot(u, v, g, mask)
        while used[slot] and not (keys[slot, 0] == u and keys[slot, 1] == v
                                  and keys[slot, 2] == g):
            slot = (slot + 1) & mask
        if used[slot]:
            continue
        used[slot] = True
        keys[slot, 0], keys[slot, 1], keys[slot, 2] = u, v, g
        keep[i] = True
        count += 1
        if 2 * count > size:  # half full: twice the slots, every cell placed again
            old_used, old_keys = used, keys
            size *= 2
            mask = size - 1
            used = np.zeros(size, dtype=np.bool_)
            keys = np.empty((size, 3), dtype=np.int64)
            for k in range(old_used.shape[0]):
                if old_used[k]:
                    su, sv, sg = old_keys[k, 0], old_keys[k, 1], old_keys[k, 2]
                    slot = _cell_slot(su, sv, sg, mask)
                    while used[slot]:
                        slot = (slot + 1) & mask
                    used[slot] = True
                    keys[slot, 0], keys[slot, 1], keys[slot, 2] = su, sv, sg
    return keep


@compiled
def first_in_grid(x: np.ndarray, y: np.ndarray, group: np.ndarray, inv_cell: float,
                  valid: np.ndarray, max_cells: int) -> tuple[bool, np.ndarray]:
    """:func:`first_in_cells` for the usual cloud: one group, over few enough cells (at
    most ``max_cells`` in the box of its points) for a flag per cell of that box, set in
    scan order, where the hash table costs a scattered lookup per point.

    Returns
    -------
    done : bool
        False when the cloud is not such a cloud (several groups, too wide a box, nothing
        valid): use :func:`first_in_cells`.
    keep : (n,) bool
    """
    n = x.shape[0]
    keep = np.zeros(n, dtype=np.bool_)
    # The box in cells, as floats: a wild coordinate (1e300 m) must not overflow an integer.
    fu_lo = fv_lo = math.inf
    fu_hi = fv_hi = -math.inf
    g0 = np.int64(0)
    seen = False
    for i in range(n):
        if not valid[i]:
            continue
        g = np.int64(group[i])
        if not seen:
            g0 = g
            seen = True
        elif g != g0:
            return False, keep
        fu = math.floor(x[i] * inv_cell)
        fv = math.floor(y[i] * inv_cell)
        fu_lo, fu_hi = min(fu_lo, fu), max(fu_hi, fu)
        fv_lo, fv_hi = min(fv_lo, fv), max(fv_hi, fv)
    if not seen or (fu_hi - fu_lo + 1.0) * (fv_hi - fv_lo + 1.0) > max_cells:
        return False, keep
    u_lo, u_hi = np.int64(fu_lo), np.int64(fu_hi)
    v_lo, v_hi = np.int64(fv_lo), np.int64(fv_hi)
    nv = v_hi - v_lo + 1
    taken = np.zeros((u_hi - u_lo + 1) * nv, dtype=np.bool_)
    for i in range(n):
        if not valid[i]:
            continue
        k = ((np.int64(math.floor(x[i] * inv_cell)) - u_lo) * nv
             + np.int64(math.floor(y[i] * inv_cell)) - v_lo)
        if not taken[k]:
            taken[k] = True
            keep[i] = True
    return True, keep


__all__ = ["first_in_cells", "first_in_grid", "first_per_cell"]
