"""Strip-to-strip height differences over the whole block (the "dz image" of LiDAR QA).

Which cells count as smooth, and the mosaic's sign: docs/internals.md, "Quality measures".
Map frame, metres; numpy only.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

#: Steepest terrain of a smooth cell, degrees (the LBS assesses swath differences on open,
#: level ground: on a slope a horizontal offset shows as a height difference).
SMOOTH_SLOPE_DEG = 10.0
#: Largest spread (max - min) of a strip's heights carried to a cell centre for the cell to
#: be one surface, metres (ten times a typical range noise).
MAX_CELL_SPREAD_M = 0.3
#: Fewest points of a strip in a cell.
MIN_CELL_POINTS = 2


@dataclass(frozen=True)
class BlockGrid:
    """Square cells over the block.

    Attributes
    ----------
    x0, y0 : float
        Map-frame south-west corner, metres.
    cell_m : float
    nx, ny : int
        Columns (east) and rows (north).
    """

    x0: float
    y0: float
    cell_m: float
    nx: int
    ny: int

    @classmethod
    def covering(cls, lo: np.ndarray, hi: np.ndarray, cell_m: float) -> BlockGrid:
        """The grid of ``cell_m`` cells covering the box ``lo``-``hi`` (map frame, m)."""
        nx = int(math.floor((float(hi[0]) - float(lo[0])) / cell_m)) + 1
        ny = int(math.floor((float(hi[1]) - float(lo[1])) / cell_m)) + 1
        return cls(float(lo[0]), float(lo[1]), float(cell_m), nx, ny)

    def keys(self, xy: np.ndarray) -> np.ndarray:
        """Cell key ``row * nx + column`` of each position (-1 outside the grid)."""
        col = np.floor((xy[:, 0] - self.x0) / self.cell_m)
        row = np.floor((xy[:, 1] - self.y0) / self.cell_m)
        inside = (col >= 0) & (col < self.nx) & (row >= 0) & (row < self.ny)
        return np.where(inside, row * self.nx + col, -1).astype(np.int64)

    def centres(self, keys: np.ndarray) -> np.ndarray:
        """Map-frame centres (k, 2) of cells, metres."""
        row, col = np.divmod(keys, self.nx)
        return np.column_stack([self.x0 + (col + 0.5) * self.cell_m,
                                self.y0 + (row + 0.5) * self.cell_m])

    def extent(self) -> tuple[float, float, float, float]:
        """``(left, right, bottom, top)``, map frame, metres (for ``imshow``)."""
        return (self.x0, self.x0 + self.nx * self.cell_m, self.y0,
                self.y0 + self.ny * self.cell_m)


@dataclass(frozen=True)
class CellHeights:
    """One strip's smooth cells: sorted keys and the height there (metres)."""

    keys: np.ndarray
    z: np.ndarray

    @classmethod
    def empty(cls) -> CellHeights:
        """No cell at all."""
        return cls(np.zeros(0, dtype=np.int64), np.zeros(0))


def cell_heights(grid: BlockGrid, xyz: np.ndarray, normals: np.ndarray,
                 smooth: np.ndarray) -> CellHeights:
    """A strip's surface on ``grid`` (docs/internals.md, "Quality measures").

    Parameters
    ----------
    xyz : (n, 3) float
        The strip's points, map frame, metres.
    normals : (n, 3) float
        Unit surface normals (NaN: none).
    smooth : (n,) bool
        Points on smooth ground (trusted normal, gentle slope); a cell counts only when all
        its points are, at least :data:`MIN_CELL_POINTS`, their heights at its centre
        agree within :data:`MAX_CELL_SPREAD_M`, and its neighbours holding points count
        too.
    """
    keys = grid.keys(xyz[:, :2])
    inside = keys >= 0
    if not inside.any():
        return CellHeights.empty()
    all_keys, inverse = np.unique(keys[inside], return_inverse=True)
    total = np.bincount(inverse, minlength=all_keys.size)
    ok = np.asarray(smooth, dtype=bool)[inside]
    with np.errstate(invalid="ignore"):
        ok &= normals[inside, 2] > 0.0
    good = np.bincount(inverse[ok], minlength=all_keys.size)
    centre = grid.centres(all_keys)[inverse[ok]]
    p, n = xyz[inside][ok], normals[inside][ok]
    z = p[:, 2] - (n[:, 0] * (centre[:, 0] - p[:, 0])
                   + n[:, 1] * (centre[:, 1] - p[:, 1])) / n[:, 2]
    sums = np.bincount(inverse[ok], weights=z, minlength=all_keys.size)
    keep = (good == total) & (total >= MIN_CELL_POINTS)
    # Spread of the heights per cell: sorted by cell, the extremes of each run.
    order = np.argsort(inverse[ok], kind="stable")
    cells = inverse[ok][order]
    if cells.size:
        starts = np.flatnonzero(np.r_[True, cells[1:] != cells[:-1]])
        spread = np.zeros(all_keys.size)
        spread[cells[starts]] = (np.maximum.reduceat(z[order], starts)
                                 - np.minimum.reduceat(z[order], starts))
        keep &= spread <= MAX_CELL_SPREAD_M
    height = sums / np.maximum(total, 1)
    keep &= ~_next_to(grid, all_keys, keep, height)
    return CellHeights(all_keys[keep], height[keep])


def _next_to(grid: BlockGrid, keys: np.ndarray, kept: np.ndarray,
             height: np.ndarray) -> np.ndarray:
    """Which of the cells ``keys`` (sorted) have among their eight neighbours a cell not
    ``kept``, or a kept one whose ``height`` steps from theirs by more than a slope of
    :data:`SMOOTH_SLOPE_DEG` and the spread allow."""
    out = np.zeros(keys.size, dtype=bool)
    row, col = np.divmod(keys, grid.nx)
    rise = math.tan(math.radians(SMOOTH_SLOPE_DEG)) * grid.cell_m
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            if dr == dc == 0:
                continue
            r, c = row + dr, col + dc
            inside = (r >= 0) & (r < grid.ny) & (c >= 0) & (c < grid.nx)
            neighbour = np.where(inside, r * grid.nx + c, -1)
            at = np.clip(np.searchsorted(keys, neighbour), 0, keys.size - 1)
            found = inside & (keys[at] == neighbour)
            step = np.abs(height[at] - height)
            limit = rise * math.hypot(dr, dc) + MAX_CELL_SPREAD_M
            out |= found & (~kept[at] | (kept[at] & (step > limit)))
    return out


@dataclass(frozen=True)
class PairDifference:
    """Height differences of one strip pair over their common smooth cells.

    Attributes
    ----------
    earlier, later : int
        Strip ids, by flight time; ``dz`` is later minus earlier.
    before, after : (k,) float64
        ``dz`` as delivered and after calibration, metres (the cells common to both strips
        in each state, so the counts may differ slightly).
    """

    earlier: int
    later: int
    before: np.ndarray
    after: np.ndarray

    @property
    def strips(self) -> tuple[int, int]:
        """The pair's strip ids, smaller first."""
        a, b = sorted((self.earlier, self.later))
        return a, b


@dataclass(frozen=True)
class DzStatistics:
    """RMSDz and largest |dz| of a set of differences (metres; NaN when empty)."""

    n_cells: int
    rmsdz: float
    max_abs: float

    @classmethod
    def of(cls, dz: np.ndarray) -> DzStatistics:
        """The statistics of the differences ``dz`` (metres; NaN when there are none)."""
        if not dz.size:
            return cls(0, math.nan, math.nan)
        return cls(int(dz.size), float(np.sqrt(np.mean(dz * dz))), float(np.max(np.abs(dz))))


@dataclass
class SwathDifferences:
    """The block's swath-to-swath height differences before and after calibration.

    Attributes
    ----------
    grid : BlockGrid
    before, after : (ny, nx) float32
        The block mosaics (docs/internals.md), metres; NaN where fewer than two strips have a
        smooth cell.
    pairs : list of PairDifference
        Pairs with at least one common smooth cell, by strip ids.
    """

    grid: BlockGrid
    before: np.ndarray
    after: np.ndarray
    pairs: list[PairDifference]

    def statistics(self, state: str) -> DzStatistics:
        """Over every pair's cells, ``before`` or ``after``."""
        parts = [getattr(p, state) for p in self.pairs]
        return DzStatistics.of(np.concatenate(parts) if parts else np.zeros(0))


def _difference(a: CellHeights, b: CellHeights) -> tuple[np.ndarray, np.ndarray]:
    """Common keys and ``b - a`` there."""
    keys, ia, ib = np.intersect1d(a.keys, b.keys, assume_unique=True, return_indices=True)
    return keys, b.z[ib] - a.z[ia]


def swath_differences(
    grid: BlockGrid,
    strips: Sequence[tuple[int, float, CellHeights, CellHeights]],
) -> SwathDifferences:
    """Pair differences and block mosaics.

    Parameters
    ----------
    grid : BlockGrid
    strips : sequence of (strip id, flight time, heights before, heights after)
        Flight time (s) orders each pair.
    """
    ordered = sorted(strips, key=lambda s: (s[1], s[0]))
    mosaics = {}
    largest = {}
    for state in ("before", "after"):
        mosaics[state] = np.full(grid.nx * grid.ny, np.nan, dtype=np.float32)
        largest[state] = np.full(grid.nx * grid.ny, -1.0)
    pairs = []
    for i, (id_a, _, before_a, after_a) in enumerate(ordered):
        for id_b, _, before_b, after_b in ordered[i + 1:]:
            dz = {}
            for state, a, b in (("before", before_a, before_b), ("after", after_a, after_b)):
                keys, d = _difference(a, b)
                dz[state] = d
                bigger = np.abs(d) > largest[state][keys]
                mosaics[state][keys[bigger]] = d[bigger]
                largest[state][keys[bigger]] = np.abs(d[bigger])
            if dz["before"].size or dz["after"].size:
                pairs.append(PairDifference(id_a, id_b, dz["before"], dz["after"]))
    pairs.sort(key=lambda p: p.strips)
    shape = (grid.ny, grid.nx)
    return SwathDifferences(grid, mosaics["before"].reshape(shape),
                            mosaics["after"].reshape(shape), pairs)


__all__ = [
    "MAX_CELL_SPREAD_M",
    "MIN_CELL_POINTS",
    "SMOOTH_SLOPE_DEG",
    "BlockGrid",
    "CellHeights",
    "DzStatistics",
    "PairDifference",
    "SwathDifferences",
    "cell_heights",
    "swath_differences",
]
