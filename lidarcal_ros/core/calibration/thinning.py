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

The choice is one compiled pass over the points
(:mod:`lidarcal_ros.core.calibration.thinning_kernels`): a flag per cell of the cloud's box where
that is small enough, else a hash table of the cells met.
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
