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
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from lidarcal_ros.core.calibration.pairs import FootprintGrid, footprint_keys, stratified_sample
from lidarcal_ros.core.calibration.tin import PatchMatches, Tin, TinQuality, match_to_tin

#: By (strip id of the point strip, strip id of the surface strip), a pair's sample points
#: chosen in passes (:class:`SampleChooser`): their indices into the point strip as held, and
#: their normal distances (m) to the surface strip as delivered (its "before" QA).
ChosenSamples = Mapping[tuple[int, int], tuple[np.ndarray, np.ndarray]]

#: Key offsets of a footprint cell and its eight neighbours (:func:`footprint_keys`).
NEIGHBOUR_CELL_OFFSETS = np.array([dx * (1 << 32) + dy for dx in (-1, 0, 1) for dy in (-1, 0, 1)],
                                  dtype=np.int64)


@dataclass
class StripExtent:
    """What a calibration needs of a whole strip whose points it does not all hold: its
    point count, footprint cells (:func:`footprint_keys`, sorted unique), the last block
    of the mission that put a point in each cell (:attr:`last`) and time span (s),
    gathered block by block (:meth:`add`)."""

    strip_id: int
    cell: float
    n_points: int = 0
    cells: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    #: By cell of :attr:`cells`, the number of the last block (:meth:`add`'s ``block``)
    #: holding one of the strip's points there.
    last: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    t0: float = math.inf
    t1: float = -math.inf
    _pending: list[tuple[np.ndarray, int]] = field(default_factory=list)

    def add(self, xyz: np.ndarray, t: np.ndarray, *, block: int = 0) -> None:
        """Take a block of the strip's points (in the strip's order), number ``block`` in
        the mission's order (blocks numbered as they come, increasing)."""
        if not t.size:
            return
        self.n_points += int(t.size)
        self.t0, self.t1 = min(self.t0, float(t.min())), max(self.t1, float(t.max()))
        self._pending.append((np.unique(footprint_keys(xyz, self.cell)), int(block)))
        if sum(p.size for p, _ in self._pending) > 1 << 20:
            self._merge()

    def _merge(self) -> None:
        if self._pending:
            keys = np.concatenate([self.cells, *(p for p, _ in self._pending)])
            last = np.concatenate([self.last, *(np.full(p.size, b, np.int64)
                                                for p, b in self._pending)])
            # each cell once, with its latest block (sorted by cell, then block)
            order = np.lexsort((last, keys))
            keys, last = keys[order], last[order]
            final = np.append(keys[1:] != keys[:-1], True)
            self.cells, self.last = keys[final], last[final]
            self._pending = []

    def last_block_near(self, xy: np.ndarray, radius: float) -> np.ndarray:
        """For each map position ``xy`` (columns x, y), the last block holding a point of
        the strip within ``radius`` metres of it (every cell within reach; -1: none), once
        :meth:`finish` has run."""
        ring = max(1, math.ceil(radius / self.cell))
        keys = footprint_keys(xy, self.cell)
        out = np.full(len(keys), -1, np.int64)
        if not self.cells.size:
            return out
        for dx in range(-ring, ring + 1):
            for dy in range(-ring, ring + 1):
                k = keys + dx * (1 << 32) + dy
                at = np.minimum(np.searchsorted(self.cells, k), self.cells.size - 1)
                hit = self.cells[at] == k
                out[hit] = np.maximum(out[hit], self.last[at[hit]])
        return out

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
    index in the strip and map x, y, z (memory of at most ``2 k`` points)."""

    def __init__(self, k: int) -> None:
        self.k = int(k)
        self.priority = np.empty(0)
        self.index = np.empty(0, np.int64)
        self.xyz = np.empty((0, 3))

    def add(self, priority: np.ndarray, index: np.ndarray, xyz: np.ndarray) -> None:
        """Offer points (their priority, strip index and x, y, z)."""
        if not priority.size:
            return
        self.priority = np.concatenate([self.priority, priority])
        self.index = np.concatenate([self.index, index])
        self.xyz = np.concatenate([self.xyz, xyz])
        if self.priority.size > 2 * self.k:
            self._trim()

    def _trim(self) -> None:
        if self.priority.size > self.k:
            keep = np.argpartition(self.priority, self.k)[:self.k]
            self.priority, self.index, self.xyz = (self.priority[keep], self.index[keep],
                                                   self.xyz[keep])

    def result(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The strip indices (sorted), x, y, z and priorities of the ``k`` lowest."""
        self._trim()
        order = np.argsort(self.index)
        return self.index[order], self.xyz[order], self.priority[order]


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


def in_sorted(sorted_keys: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """Mask of ``keys`` found in ``sorted_keys`` (sorted, unique; a binary search each)."""
    if not sorted_keys.size:
        return np.zeros(keys.shape, dtype=bool)
    at = np.minimum(np.searchsorted(sorted_keys, keys), sorted_keys.size - 1)
    return sorted_keys[at] == keys


class SampleChooser:
    """One pair's sample points chosen as the mission's blocks go by, as
    :meth:`~lidarcal_ros.core.calibration.matching.PairMatcher.choose_samples` chooses them
    from whole strips: the candidates matched at zero correction to a TIN of the surface
    strip's points within ``radius`` metres of them, then :func:`stratified_sample`.

    The surface strip's points are offered block by block (:meth:`offer`); a candidate is
    matched once the blocks have passed the last that holds a surface point within reach
    (``ready``: that block's number, :meth:`StripExtent.last_block_near`), so what is held is
    the surface near the candidates still waiting, not the strip.

    Parameters
    ----------
    index, xyz, priority : (c,) int64, (c, 3) float64, (c,) float64
        The candidates: indices into the whole point strip (sorted), map x, y, z (m) as
        delivered, sampling priorities.
    ready : (c,) int64
        Block after which each candidate's surface is complete.
    radius : float
        Radius (m) of the surface held around a candidate.
    quality : TinQuality
        The surface strip's patch rules.
    threshold : float
        Largest normal distance matched, m (the first threshold).
    per_class_cap, flat_class_factor : int
        As :func:`stratified_sample`.
    cell : float
        Footprint cell of ``keys`` (:meth:`offer`), m.
    batch : int
        Candidates matched together (one TIN) at the least, until the last, unless more than
        ``max_held`` surface points are held.
    max_held : int
        Surface points held beyond which the candidates ready are matched however few.
    """

    def __init__(self, index: np.ndarray, xyz: np.ndarray, priority: np.ndarray,
                 ready: np.ndarray, *, radius: float, quality: TinQuality, threshold: float,
                 per_class_cap: int, flat_class_factor: int, cell: float,
                 batch: int = 8192, max_held: int = 1 << 18) -> None:
        self.index, self.xyz, self.priority = index, xyz, priority
        self.ready = ready
        self.order = np.argsort(ready, kind="stable")
        #: ``ready`` in the order of ``order`` (searched at every block that goes by)
        self._ready_in_order = ready[self.order]
        self.radius, self.quality, self.threshold = float(radius), quality, float(threshold)
        self.per_class_cap, self.flat_class_factor = per_class_cap, flat_class_factor
        self.batch, self.max_held = int(batch), int(max_held)
        self.cell = cell
        n = len(index)
        self.valid = np.zeros(n, dtype=bool)
        self.normal = np.zeros((n, 3))
        self.distance = np.full(n, np.nan)
        self.done = 0  # candidates matched, in the order of ``order``
        ring = max(1, math.ceil(self.radius / cell))
        offsets = np.array([dx * (1 << 32) + dy for dx in range(-ring, ring + 1)
                            for dy in range(-ring, ring + 1)], dtype=np.int64)
        self.near_cells = np.unique((footprint_keys(xyz, cell)[:, None] + offsets).ravel()) \
            if n else np.empty(0, np.int64)
        self._held: list[np.ndarray] = []
        self._n_held = 0
        self._waiting = self._tree(self.order)

    def _tree(self, which: np.ndarray) -> cKDTree | None:
        return cKDTree(self.xyz[which, :2]) if which.size else None

    def _near(self, tree: cKDTree | None, xyz: np.ndarray) -> np.ndarray:
        if tree is None or not len(xyz):
            return np.zeros(len(xyz), dtype=bool)
        d, _ = tree.query(xyz[:, :2], k=1, distance_upper_bound=self.radius)
        return np.isfinite(d)

    @property
    def held(self) -> int:
        """Surface points held."""
        return self._n_held

    def offer(self, xyz: np.ndarray, keys: np.ndarray) -> None:
        """Take a block of the surface strip's points (map x, y, z, m; ``keys`` their
        :func:`footprint_keys` of this chooser's ``cell``): those near a waiting candidate
        are held."""
        near = in_sorted(self.near_cells, keys)
        if not near.any():
            return
        pts = xyz[near]
        pts = pts[self._near(self._waiting, pts)]
        if len(pts):
            self._held.append(pts)
            self._n_held += len(pts)

    def passed(self, block: int) -> None:
        """The blocks up to ``block`` have all been offered: match the candidates they
        complete (``batch`` at a time, fewer where more than ``max_held`` points wait)."""
        upto = int(np.searchsorted(self._ready_in_order, block, side="right"))
        if upto - self.done >= self.batch or (upto > self.done and
                                              self.held > self.max_held):
            self._match(upto)

    def _match(self, upto: int) -> None:
        which = self.order[self.done:upto]
        held = np.concatenate([np.empty((0, 3)), *self._held])
        surface = held[self._near(self._tree(which), held)]
        if len(surface) >= 3:
            m = match_to_tin(self.xyz[which], Tin(surface, self.quality), surface,
                             max_normal_distance=self.threshold)
            self.valid[which], self.normal[which] = m.valid, m.normal
            self.distance[which] = m.distance
        self.done = upto
        self._waiting = self._tree(self.order[upto:])
        held = held[self._near(self._waiting, held)]
        self._held = [held] if len(held) else []
        self._n_held = len(held)

    def result(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Once every block has been offered: the sample (indices into the whole point
        strip, sorted), its points' x, y, z (m) and the normal distance (m) of each as
        delivered."""
        if self.done < len(self.index):
            self._match(len(self.index))
        n = len(self.index)
        matches = PatchMatches(self.valid, np.full(n, -1, np.int64), self.normal,
                               np.zeros((n, 3)), self.distance)
        picked = stratified_sample(matches, np.arange(n), self.priority,
                                   per_class_cap=self.per_class_cap,
                                   flat_class_factor=self.flat_class_factor)
        before = self.distance[picked]
        return self.index[picked], self.xyz[picked], before[np.isfinite(before)]


__all__ = [
    "NEIGHBOUR_CELL_OFFSETS", "ChosenSamples", "LowestPriority", "NearCandidates", "PairPlan",
    "SampleChooser", "StripExtent", "control_cells", "in_sorted", "neighbourhood_radius",
    "plan_pairs",
]
