"""The reduced mission of a bounded-memory calibration: what matching needs, chosen in passes.

A calibration matches at most ``max_candidates_per_pair`` points of each pair's point strip to
a TIN of its surface strip. Three passes over a mission's points keep only those: the
strips' footprints, sizes and spans (:class:`StripExtent`); each pair's candidates, the points
of lowest sampling priority in its zone (:class:`LowestPriority`); the surface strips' points
near them (:class:`NearCandidates`) and every point near a control point. Map frame, metres;
times in seconds.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from lidarcal_ros.core.calibration.pairs import FootprintGrid, footprint_keys

#: Key offsets of a footprint cell and its eight neighbours (:func:`footprint_keys`).
NEIGHBOUR_CELL_OFFSETS = np.array([dx * (1 << 32) + dy for dx in (-1, 0, 1) for dy in (-1, 0, 1)],
                                  dtype=np.int64)


@dataclass
class StripExtent:
    """What a calibration needs of a whole strip whose points it does not all hold: its
    point count, footprint cells (:func:`footprint_keys`, sorted unique) and time span (s),
    gathered block by block (:meth:`add`)."""

    strip_id: int
    cell: float
    n_points: int = 0
    cells: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    t0: float = math.inf
    t1: float = -math.inf
    _pending: list[np.ndarray] = field(default_factory=list)

    def add(self, xyz: np.ndarray, t: np.ndarray) -> None:
        """Take a block of the strip's points (in the strip's order)."""
        if not t.size:
            return
        self.n_points += int(t.size)
        self.t0, self.t1 = min(self.t0, float(t.min())), max(self.t1, float(t.max()))
        self._pending.append(np.unique(footprint_keys(xyz, self.cell)))
        if sum(p.size for p in self._pending) > 1 << 20:
            self._merge()

    def _merge(self) -> None:
        if self._pending:
            self.cells = np.unique(np.concatenate([self.cells, *self._pending]))
            self._pending = []

    def finish(self) -> StripExtent:
        """The extent with every block taken into :attr:`cells`."""
        self._merge()
        return self

    @property
    def density(self) -> float:
        """Points per m^2 over its footprint (as ``PairMatcher`` computes it)."""
        return self.n_points / max(self.cells.size * self.cell**2, 1.0)

    @property
    def span(self) -> tuple[float, float]:
        """First and last time (s)."""
        return (self.t0, self.t1) if self.n_points else (0.0, 0.0)


@dataclass(frozen=True)
class PairPlan:
    """A strip pair as :func:`~lidarcal_ros.core.calibration.pairs.find_pair` forms it from
    whole strips: points of strip ``a`` in the ``zone`` cells (sorted footprint keys) matched
    to the TIN of strip ``b`` (indices into the extents)."""

    a: int
    b: int
    zone: np.ndarray


def plan_pairs(extents: Sequence[StripExtent], *, footprint: FootprintGrid,
               min_overlap_cells: int) -> list[PairPlan]:
    """The pairs the strips of ``extents`` (in the order a calibration adds them) form, in
    the order it forms them; the rule of ``find_pair``, on whole strips."""
    out = []
    for j in range(len(extents)):
        for i in range(j):
            ei, ej = extents[i], extents[j]
            if np.intersect1d(ei.cells, ej.cells, assume_unique=True).size < min_overlap_cells:
                continue
            a, b = (i, j) if ei.density <= ej.density else (j, i)
            zone = np.intersect1d(extents[a].cells, footprint.interior(extents[b].cells),
                                  assume_unique=True)
            if zone.size:
                out.append(PairPlan(a, b, zone))
    return out


class LowestPriority:
    """The ``k`` points of lowest priority among those offered block by block, with their
    index in the strip and map x, y (memory of at most ``2 k`` points)."""

    def __init__(self, k: int) -> None:
        self.k = int(k)
        self.priority = np.empty(0)
        self.index = np.empty(0, np.int64)
        self.xy = np.empty((0, 2))

    def add(self, priority: np.ndarray, index: np.ndarray, xy: np.ndarray) -> None:
        """Offer points (their priority, strip index and x, y)."""
        if not priority.size:
            return
        self.priority = np.concatenate([self.priority, priority])
        self.index = np.concatenate([self.index, index])
        self.xy = np.concatenate([self.xy, xy])
        if self.priority.size > 2 * self.k:
            self._trim()

    def _trim(self) -> None:
        if self.priority.size > self.k:
            keep = np.argpartition(self.priority, self.k)[:self.k]
            self.priority, self.index, self.xy = (self.priority[keep], self.index[keep],
                                                  self.xy[keep])

    def result(self) -> tuple[np.ndarray, np.ndarray]:
        """The strip indices (sorted) and x, y of the ``k`` lowest."""
        self._trim()
        order = np.argsort(self.index)
        return self.index[order], self.xy[order]


def neighbourhood_radius(density: float, *, spacings: float, margin_m: float) -> float:
    """Radius (m) of the surface strip's points kept around a candidate: ``spacings`` point
    spacings of a strip of ``density`` points per m^2 (the patch that holds the candidate and
    its neighbours) plus ``margin_m`` (how far the candidate moves against that strip as
    the estimate changes)."""
    return spacings / math.sqrt(max(density, 1e-6)) + margin_m


class NearCandidates:
    """Which of a strip's points lie within ``radius`` metres (horizontally) of candidate
    points ``xy`` (map x, y), or in the footprint ``cells`` (sorted keys of cell ``cell``)."""

    def __init__(self, xy: np.ndarray, radius: float, cells: np.ndarray, cell: float) -> None:
        self.tree = cKDTree(xy) if len(xy) else None
        self.radius = float(radius)
        self.cells = cells
        self.cell = cell

    def __call__(self, xy: np.ndarray) -> np.ndarray:
        """Mask of the points ``xy`` (map x, y) to keep."""
        keep = np.isin(footprint_keys(xy, self.cell), self.cells) if self.cells.size else \
            np.zeros(len(xy), dtype=bool)
        if self.tree is not None and len(xy):
            d, _ = self.tree.query(xy, k=1, distance_upper_bound=self.radius)
            keep |= np.isfinite(d)
        return keep


def control_cells(xy: np.ndarray, cell: float) -> np.ndarray:
    """Sorted footprint keys of the cells holding the map positions ``xy`` and their eight
    neighbours (what the control surface of a point draws on)."""
    if not len(xy):
        return np.empty(0, np.int64)
    return np.unique((footprint_keys(xy, cell)[:, None] + NEIGHBOUR_CELL_OFFSETS).ravel())


__all__ = [
    "NEIGHBOUR_CELL_OFFSETS", "LowestPriority", "NearCandidates", "PairPlan", "StripExtent",
    "control_cells", "neighbourhood_radius", "plan_pairs",
]
