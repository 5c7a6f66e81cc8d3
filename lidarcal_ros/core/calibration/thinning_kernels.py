"""Compiled passes of the thinning: which points are the first of their map cell, in one pass.

A flag per cell of the cloud's box where that is small enough, else a hash table of the cells.
"""

from __future__ import annotations

import math

import numpy as np

from lidarcal_ros.core.jit import compiled, inlined


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


__all__ = ["first_in_cells", "first_in_grid"]
