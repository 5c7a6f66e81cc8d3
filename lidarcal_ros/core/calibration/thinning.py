"""Thinning of a strip's points to one per map cell before calibration.

Why, and why per cloud in arrival order: docs/internals.md, "The calibration".
"""

from __future__ import annotations

import numpy as np

from lidarcal_ros.core.calibration.thinning_kernels import first_in_cells, first_in_grid

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


__all__ = ["first_per_cell"]
