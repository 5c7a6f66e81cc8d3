"""Grid normals of a strip computed as its points arrive, on a grid that advances along track.

Each point is binned once and evaluated once; the normals are those of the whole strip's grid.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from lidarcal_ros.core.allocator import populate_in_background
from lidarcal_ros.core.normals.grid_normals import (
    MIN_BLOCK_POINTS,
    GridNormals,
    cell_size,
    finite_rows,
    flight_frame,
    no_normals,
)
from lidarcal_ros.core.normals.grid_normals_kernels import (
    accumulate_moments,
    fit_blocks,
    flight_cells,
)
from lidarcal_ros.core.normals.grid_planes import (
    CellPlanes,
    block_min_spread,
    dense_moment_grid,
    normals_from_planes,
    plane_table,
    typical_residual,
)

#: A strip's grid (cell size, heading, origin) is fixed by its first points: as many as it
#: takes to reach both this count and this time span (the same points however the stream is
#: cut into parts; the parts before are held until then).
STREAM_START_POINTS = 10_000
STREAM_START_SECONDS = 0.02

#: Fewest rows a later part's points may land behind the watermark (the lowest row of the
#: newest part): the lateness allowed where parts span few rows (a linear scanner's).
_LATE_ROWS = 2

#: The lateness allowed is the median row span of this many of the latest parts
#: (:attr:`StripNormals.late_rows`).
_SPAN_PARTS = 32

#: Rows zeroed ahead of the points at a time, and the least room left ahead when the grid
#: advances in place (:meth:`StripNormals._fit_grid`).
_SPARE_ROWS = 16

#: A part whose points spread over more rows (or columns) than this has outliers: only the
#: points between its 0.1st and 99.9th percentiles plus a margin are binned. (A swath of 2 km
#: in cells of 0.15 m spans some 13000 columns: a lower bound would sort every cloud.)
_MAX_PART_SPAN = 16384

#: Most grid columns (across-track cells) of a strip: bounds memory when points scatter.
_MAX_COLUMNS = 65536


@dataclass
class _Part:
    """Points of one strip added under one key, in the strip's grid frame."""

    key: object
    n: int
    index: np.ndarray | None  # positions of the binned points among the n (None: all)
    u: np.ndarray
    v: np.ndarray
    z: np.ndarray
    iu: np.ndarray
    iv: np.ndarray
    row_min: int
    row_max: int


def _move_rows_down(moments: np.ndarray, by: int, rows: int) -> None:
    """``moments[i] = moments[i + by]`` for ``i < rows``, in blocks that do not overlap
    (numpy would otherwise copy the whole overlapping source first)."""
    if by <= 0 or rows <= 0:
        return
    for a in range(0, rows, by):
        b = min(a + by, rows)
        moments[a:b] = moments[a + by:b + by]


class StripNormals:
    """Grid normals (:func:`~lidarcal_ros.core.normals.grid_normals.grid_normals`) of one strip
    computed as its points arrive.

    Every point is binned into the strip's grid once and evaluated once: the grid (cell,
    heading, origin) is fixed by the strip's first :data:`STREAM_START_POINTS` points and the
    moment sums of its cells are kept from the oldest points not yet evaluated on. A point in
    grid row ``i`` (along track) depends on the cells of rows ``i - 2 .. i + 2`` only, so its
    normal is final once no later point can land in those rows.

    The edge tolerance comes from the typical plane-fit residual of the strip's first points.
    With ``lookahead`` the points of a part are evaluated once the *watermark*, the lowest
    row of the newest part, is :attr:`late_rows` and three rows beyond the part's highest row
    (a scanner's points advance along track; later points land at most :attr:`late_rows`
    behind the newest part's lowest row), which gives exactly the normals of
    :func:`~lidarcal_ros.core.normals.grid_normals.grid_normals` over the whole strip in the
    same grid. :attr:`late_rows` is the median row span of the latest parts, at least 2: a
    later part reaches at most about its own span behind an earlier one's lowest row (a
    spinning multi-beam's revolution spans some 50-100 m along track, and one without returns
    at the swath's edges has its lowest row ahead of the next one's).
    Without ``lookahead`` each part is evaluated as soon as it is added, against the points
    that came before it (least latency; the normals at a part's leading edge see neighbours
    behind them only).

    Parameters
    ----------
    heading_at : callable(t) -> float
        Heading ``kappa`` of the flight line (rad) at a time (s): the grid is aligned with
        it at the median time of the strip's first points.
    lookahead : bool
        See above.
    min_points : int
        Fewest points a block needs for a plane.

    Notes
    -----
    Points that arrive behind rows already dropped, or far outside the part's own extent
    (outliers), are not binned and get no normal (``valid`` False); ``late_points`` counts
    them. The grid keeps :attr:`late_rows` and two rows behind the watermark.

    Attributes
    ----------
    late_rows : int
        Grid rows behind the watermark that later points may land in (see above).
    """

    def __init__(self, heading_at: Callable[[float], float], *, lookahead: bool = True,
                 min_points: int = MIN_BLOCK_POINTS) -> None:
        self._heading_at = heading_at
        self.heading = math.nan
        self.lookahead = lookahead
        self.min_points = min_points
        self.cell: tuple[float, float] = (math.nan, math.nan)
        self.late_points = 0
        self._origin = (0.0, 0.0, 0.0)
        self._noise = 0.0
        self._start: list[tuple[object, np.ndarray, np.ndarray | None]] = []
        self._start_points = 0
        self._moments = np.zeros((0, 0, 10))
        self._row0 = 0
        self._col0 = 0
        self._clean_to = 0  # rows from here on hold stale sums (zeroed before use)
        self._parts: deque[_Part] = deque()
        self._watermark = -(2**62)
        self._spans: deque[int] = deque(maxlen=_SPAN_PARTS)
        self.late_rows = _LATE_ROWS
        self._binned = 0  # points binned since the grid started
        self._first_watermark: int | None = None

    @property
    def moment_grid(self) -> np.ndarray:
        """The grid of moment sums the strip's points are binned into, ``(rows, columns,
        10)`` (empty before the grid starts): it holds the rows still needed, from the oldest
        points not yet evaluated on, and moves along track with the strip (its rows are
        reused in place while the strip's width allows)."""
        return self._moments

    @property
    def started(self) -> bool:
        """Whether the grid exists (the first points fixed the cell)."""
        return math.isfinite(self.cell[0])

    def pending_points(self) -> int:
        """Points added and not yet evaluated."""
        return self._start_points + sum(p.n for p in self._parts)

    def add(self, key: object, xyz: np.ndarray, t: np.ndarray | None = None) -> None:
        """Add the points of one part (a cloud's points of this strip).

        Parameters
        ----------
        key : object
            Returned with the part's normals by :meth:`pop_ready`.
        xyz : (n, 3) float64
            Delivered points, map frame, m (non-finite rows get no normal).
        t : (n,) float64, optional
            Firing times (s), for the cell size of the strip's first points.
        """
        xyz = np.asarray(xyz, dtype=np.float64)
        if not self.started:
            self._start.append((key, xyz, t))
            self._start_points += xyz.shape[0]
            if self._start_points >= STREAM_START_POINTS:
                self._begin(final=False)
            return
        self._bin(key, xyz)

    def add_many(self, parts: list[tuple[object, np.ndarray, np.ndarray | None]]) -> None:
        """:meth:`add` several parts ``(key, xyz, t)`` in the order given, binned in one
        pass once the grid exists (fewer, larger numpy calls for small clouds)."""
        k = 0
        while k < len(parts) and not self.started:  # the strip's first points fix the grid
            self.add(*parts[k])
            k += 1
        rest = parts[k:]
        if len(rest) == 1:
            self._bin(rest[0][0], np.asarray(rest[0][1], dtype=np.float64))
        elif rest:
            xyz = np.concatenate([np.asarray(p[1], dtype=np.float64) for p in rest])
            self._bin_parts([(p[0], p[1].shape[0]) for p in rest], xyz)

    def _begin(self, *, final: bool) -> bool:
        """Fix the grid from the strip's first points and bin the parts held; False if
        there are not enough points yet (or, with ``final``, at all)."""
        xyz = np.concatenate([p[1] for p in self._start])
        n = xyz.shape[0]
        t = np.full(n, np.nan)
        a = 0
        for _key, part_xyz, part_t in self._start:
            if part_t is not None:
                t[a:a + part_xyz.shape[0]] = part_t
            a += part_xyz.shape[0]
        finite = finite_rows(xyz)
        idx = np.flatnonzero(finite)
        # The first points: STREAM_START_POINTS finite ones spanning STREAM_START_SECONDS.
        timed = np.isfinite(t[idx])
        if idx.size >= STREAM_START_POINTS and timed.all():
            t_first = t[idx]
            span = np.maximum.accumulate(t_first) - np.minimum.accumulate(t_first)
            reach = np.flatnonzero(span[STREAM_START_POINTS - 1:] >= STREAM_START_SECONDS)
            if reach.size:
                idx = idx[:STREAM_START_POINTS + int(reach[0])]
            elif not final:
                return False
        elif not final and idx.size < STREAM_START_POINTS:
            return False
        first_t = t[idx] if np.isfinite(t[idx]).all() else None
        mid = float(np.median(first_t)) if first_t is not None and first_t.size else math.nan
        heading = self._heading_at(mid) if math.isfinite(mid) else 0.0
        cell = cell_size(xyz[idx], heading, first_t)
        if not all(math.isfinite(c) and c > 0 for c in cell):
            return False
        self.heading, self.cell = heading, cell
        first = xyz[idx[0]]
        self._origin = (float(first[0]), float(first[1]), float(first[2]))
        self._noise = self._first_noise(xyz[idx])
        start, self._start, self._start_points = self._start, [], 0
        self._bin_parts([(key, part_xyz.shape[0]) for key, part_xyz, _t in start], xyz)
        return True

    def _first_noise(self, xyz: np.ndarray) -> float:
        """Typical plane-fit residual (m) of the strip's first points: the edge tolerance
        of the whole strip (fixed, so that the normals do not depend on the cut)."""
        moments, _, _ = dense_moment_grid(*self._frame(xyz), self.cell)
        if moments is None:
            return 0.0
        blocks, valid = fit_blocks(moments, self.min_points, block_min_spread(self.cell))
        return typical_residual(blocks[:, 4], valid)

    def _frame(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        x0, y0, z0 = self._origin
        u, v = flight_frame(xyz, self.heading, x0, y0)
        return u, v, xyz[:, 2] - z0

    def _bin(self, key: object, xyz: np.ndarray) -> None:
        self._bin_parts([(key, xyz.shape[0])], xyz)

    def _bin_parts(self, parts: list[tuple[object, int]], xyz: np.ndarray) -> None:
        """Bin the points of consecutive parts (``(key, count)``, their points one after the
        other in ``xyz``) in one pass."""
        x0, y0, z0 = self._origin
        u, v, z, iu, iv, finite_index, bounds = flight_cells(
            np.ascontiguousarray(xyz, dtype=np.float64), math.cos(self.heading),
            math.sin(self.heading), x0, y0, z0, 1.0 / self.cell[0], 1.0 / self.cell[1])
        index = None if u.size == xyz.shape[0] else finite_index  # (None: every point)
        r_lo, r_hi, c_lo, c_hi = (int(b) for b in bounds)
        keep = self._inliers(iu, iv, r_lo, r_hi, c_lo, c_hi)
        if keep is not None:
            index = np.flatnonzero(keep) if index is None else index[keep]
            u, v, z, iu, iv = u[keep], v[keep], z[keep], iu[keep], iv[keep]
            if iu.size:
                r_lo, r_hi = int(iu.min()), int(iu.max())
                c_lo, c_hi = int(iv.min()), int(iv.max())
        if iu.size:
            self._fit_grid(r_lo, r_hi, c_lo, c_hi)
            accumulate_moments(self._moments, self._row0, self._col0, iu, iv, u, v, z)
        start = 0
        for key, n in parts:
            # The binned points of this part: a slice (``index`` is sorted).
            if index is None:
                lo, hi, part_index = start, start + n, None
            else:
                lo, hi = np.searchsorted(index, [start, start + n])
                part_index = index[lo:hi] - start
                if part_index.size == n:
                    part_index = None
            piu = iu[lo:hi]
            if not piu.size:
                r_min, r_max = 0, -1
            elif piu.size == iu.size:  # every binned point (one part): the span is known
                r_min, r_max = r_lo, r_hi
            else:
                r_min, r_max = int(piu.min()), int(piu.max())
            self._parts.append(_Part(key, n, part_index, u[lo:hi], v[lo:hi], z[lo:hi], piu,
                                     iv[lo:hi], r_min, r_max))
            if piu.size:
                self._watermark = r_min
                if self._first_watermark is None:
                    self._first_watermark = r_min
                self._binned += piu.size
                self._note_span(r_max - r_min)
            start += n

    def lookahead_points(self) -> float:
        """Points a part waits for before it is evaluated, at the strip's pace so far: the
        rows the watermark must pass (a part's median span, 3 rows of neighbours and
        :attr:`late_rows`) times the points binned per row the watermark advanced (inf
        while it has not advanced: hovering, or the strip's first part)."""
        advanced = self._watermark - (self._first_watermark or self._watermark)
        if advanced <= 0:
            return math.inf
        return (self._median_span() + 3 + self.late_rows) * self._binned / advanced

    def _median_span(self) -> int:
        """The (lower) median row span of the latest parts."""
        spans = sorted(self._spans)
        return spans[(len(spans) - 1) // 2]

    def _note_span(self, rows: int) -> None:
        """Take a part's row span into :attr:`late_rows`: the median span of the latest
        parts (a part with outliers, or a short one, moves it little)."""
        self._spans.append(rows)
        self.late_rows = max(_LATE_ROWS, self._median_span())

    def _inliers(self, iu: np.ndarray, iv: np.ndarray, r_lo: int, r_hi: int, c_lo: int,
                 c_hi: int) -> np.ndarray | None:
        """Points to bin (None: all): not behind the rows kept, not outliers. ``r_lo..r_hi``
        and ``c_lo..c_hi`` are the span of ``iu`` and ``iv``."""
        keep: np.ndarray | None = None
        if iu.size == 0:
            return None
        for idx, lo, hi, lo_bound in (
                (iu, r_lo, r_hi, self._row0 if self._moments.shape[0] else None),
                (iv, c_lo, c_hi, None)):
            if hi - lo > _MAX_PART_SPAN:
                q_lo, q_hi = np.percentile(idx, [0.1, 99.9])
                ok = (idx >= q_lo - 64) & (idx <= q_hi + 64)
                keep = ok if keep is None else keep & ok
            if lo_bound is not None and lo < lo_bound:
                ok = idx >= lo_bound
                keep = ok if keep is None else keep & ok
        if keep is not None:
            self.late_points += int(keep.size - np.count_nonzero(keep))
        return keep

    def _fit_grid(self, r_lo: int, r_hi: int, c_lo: int, c_hi: int) -> None:
        """Make the grid cover rows ``r_lo..r_hi`` and columns ``c_lo..c_hi`` (dropping the
        rows no longer needed first).

        The grid advances along track in place: the rows still needed move to the front of
        the same array, and rows are zeroed just before points first land in them
        (``_clean_to``). A new, larger array is only made while the strip's rows still
        outgrow it, or when it must widen: a fresh array (some 50 MB for a wide swath in fine
        cells) pays its page faults when made and again while the next chunks fill it: advancing
        in place leaves that to a strip's first arrays.
        """
        m = self._moments
        if m.shape[0] == 0:
            pad_c = 16
            self._row0, self._col0 = r_lo - 1, c_lo - pad_c
            self._moments = new_moment_grid((r_hi - r_lo + 64, c_hi - c_lo + 1 + 2 * pad_c,
                                             10))
            self._clean_to = self._row0
            self._clean_ahead(r_hi)
            return
        nrows, ncols, _ = m.shape
        new_c0, new_c1 = self._col0, self._col0 + ncols
        if c_lo < new_c0 or c_hi >= new_c1:
            grow = max(16, ncols // 8)
            new_c0 = min(new_c0, c_lo - grow)
            new_c1 = max(new_c1, c_hi + 1 + grow)
            if new_c1 - new_c0 > _MAX_COLUMNS:  # only via outliers: keep the present range
                new_c0, new_c1 = min(self._col0, c_lo), max(self._col0 + ncols, c_hi + 1)
        same_columns = (new_c0, new_c1) == (self._col0, self._col0 + ncols)
        if r_hi < self._row0 + nrows and same_columns:
            self._clean_ahead(r_hi)
            return
        new_r0 = max(self._row0, min(self._keep_from(), r_lo - 1))
        live = max(self._clean_to - new_r0, 0)  # rows from new_r0 on that may hold sums
        if same_columns and r_hi + 1 - new_r0 + _SPARE_ROWS <= nrows:
            _move_rows_down(m, new_r0 - self._row0, live)
            self._row0, self._clean_to = new_r0, new_r0 + live
            self._clean_ahead(r_hi)
            return
        new_r1 = max(self._row0 + nrows, r_hi + 1 + max(64, (r_hi + 1 - new_r0) // 2))
        grown = new_moment_grid((new_r1 - new_r0, new_c1 - new_c0, 10))
        grown[:live] = 0.0
        grown[:live, self._col0 - new_c0:self._col0 - new_c0 + ncols] = \
            m[new_r0 - self._row0:new_r0 - self._row0 + live]
        self._moments, self._row0, self._col0 = grown, new_r0, new_c0
        self._clean_to = new_r0 + live
        self._clean_ahead(r_hi)

    def _clean_ahead(self, r_hi: int) -> None:
        """Zero the rows up to a few past ``r_hi`` that were not zeroed since they were
        last used (an evaluation reads up to 3 rows past its points)."""
        end = self._row0 + self._moments.shape[0]
        if r_hi + 4 <= self._clean_to or self._clean_to >= end:
            return
        stop = min(end, r_hi + 4 + _SPARE_ROWS)
        self._moments[self._clean_to - self._row0:stop - self._row0] = 0.0
        self._clean_to = stop

    def _keep_from(self) -> int:
        """Lowest row still needed: by the points not yet evaluated and by late points."""
        low = min((p.row_min for p in self._parts if p.row_max >= p.row_min),
                  default=self._watermark)
        return min(low, self._watermark - self.late_rows) - 2

    def pop_ready(self, *, final: bool = False, min_points: int = 0
                  ) -> list[tuple[object, GridNormals]]:
        """Normals of the parts that are final, in the order added (:meth:`take_ready`,
        evaluated at once)."""
        task = self.take_ready(final=final, min_points=min_points)
        return task.run() if task is not None else []

    def take_ready(self, *, final: bool = False, min_points: int = 0) -> NormalsTask | None:
        """The evaluation of the parts that are final, in the order added, as a task that
        may run in another thread: the planes of the grid's cells around them are fitted
        now (later points do not change them), the normals of their points are left to the
        task.

        Parameters
        ----------
        final : bool
            Evaluate every part now (the end of the strip, or a time-out); the grid is kept,
            so later parts still have these points as neighbours.
        min_points : int
            Evaluate only once at least this many points are ready (fewer, larger
            evaluations; ignored with ``final``).

        Returns
        -------
        NormalsTask or None
            None when no part is ready.
        """
        if not self.started:
            if not (final and self._start):
                return None
            if not self._begin(final=True):  # too few points for a grid: no normals
                start, self._start, self._start_points = self._start, [], 0
                none = np.empty(0, dtype=np.int64)
                parts = [_Part(key, xyz.shape[0], None, none, none, none, none, none, 0, -1)
                         for key, xyz, _ in start]
                return NormalsTask(parts, None, 0, 0, self.cell, self.heading, self._noise)
        ready: list[_Part] = []
        count = 0
        for part in self._parts:
            if not (final or not self.lookahead or part.iu.size == 0
                    or part.row_max + 3 + self.late_rows <= self._watermark):
                break
            ready.append(part)
            count += part.n
        if not ready or (count < min_points and not final):
            return None
        for _ in ready:
            self._parts.popleft()
        binned = [p for p in ready if p.iu.size]
        if not binned:
            return NormalsTask(ready, None, 0, 0, self.cell, self.heading, self._noise)
        lo = max(min(p.row_min for p in binned) - 2, self._row0)
        hi = min(max(p.row_max for p in binned) + 3, self._row0 + self._moments.shape[0],
                 self._clean_to)
        iu, iv = _joined([p.iu for p in binned]), _joined([p.iv for p in binned])
        rows = (min(p.row_min for p in binned) - lo, max(p.row_max for p in binned) - lo)
        planes = plane_table(self._moments[lo - self._row0:hi - self._row0], iu, iv, lo,
                             self._col0, self.min_points, block_min_spread(self.cell), rows)
        return NormalsTask(ready, planes, lo, self._col0, self.cell, self.heading, self._noise)


@dataclass
class NormalsTask:
    """The normals of some parts of a strip (:meth:`StripNormals.take_ready`): everything
    their evaluation reads, so that :meth:`run` may run in another thread."""

    parts: list[_Part]
    planes: CellPlanes | None  # of the grid rows around the parts (None: no point binned)
    row0: int  # grid row and column of the planes' first cell
    col0: int
    cell: tuple[float, float]
    heading: float
    noise: float

    @property
    def keys(self) -> list[object]:
        """The keys of the parts, in the order added."""
        return [p.key for p in self.parts]

    def run(self) -> list[tuple[object, GridNormals]]:
        """``(key, normals)`` of each part, in the order added."""
        binned = [p for p in self.parts if p.iu.size]
        out_n: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        if binned:
            nrm, ok, rough = self._evaluate(binned)
            a = 0
            for p in binned:
                b = a + p.iu.size
                out_n.append((nrm[a:b], ok[a:b], rough[a:b]))
                a = b
        results: list[tuple[object, GridNormals]] = []
        it = iter(out_n)
        for p in self.parts:
            if not p.iu.size:
                results.append((p.key, no_normals(p.n, self.cell)))
                continue
            nrm_p, ok_p, rough_p = next(it)
            if p.index is None:
                results.append((p.key, GridNormals(nrm_p, ok_p, self.cell, rough_p)))
                continue
            g = no_normals(p.n, self.cell)
            assert g.rough is not None
            g.normals[p.index], g.valid[p.index], g.rough[p.index] = nrm_p, ok_p, rough_p
            results.append((p.key, g))
        return results

    def run_whole(self) -> GridNormals | None:
        """The normals of all the parts one after the other, without splitting them per part
        (no copies), when every point of every part was binned; else None (use :meth:`run`)."""
        if not self.parts or any(p.index is not None or p.iu.size != p.n for p in self.parts):
            return None
        nrm, ok, rough = self._evaluate(self.parts)
        return GridNormals(nrm, ok, self.cell, rough)

    def _evaluate(self, binned: list[_Part]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        assert self.planes is not None
        u, v, z, iu, iv = (_joined([getattr(p, f) for p in binned])
                           for f in ("u", "v", "z", "iu", "iv"))
        return normals_from_planes(self.planes, iu, iv, self.row0, self.col0, u, v, z,
                                   self.noise, self.heading)


def new_moment_grid(shape: tuple[int, int, int]) -> np.ndarray:
    """A moment grid, uninitialised: :class:`StripNormals` zeroes its rows as the strip
    reaches them. (``np.zeros`` would get memory that a warm-up or an earlier strip freed,
    where calloc must clear every byte: some 60 ms of page faults for the 60 MB grid of a
    wide swath, in one chunk, for rows most of which are used only later.) Its pages are
    faulted in by another thread meanwhile
    (:func:`~lidarcal_ros.core.allocator.populate_in_background`)."""
    grid = np.empty(shape)
    populate_in_background(grid)
    return grid


def _joined(arrays: list[np.ndarray]) -> np.ndarray:
    """The 1-D arrays one after the other: a view when they are consecutive slices of one
    array (parts binned together), else a concatenated copy."""
    if len(arrays) == 1:
        return arrays[0]
    base = arrays[0].base
    if base is not None and all(a.base is base and a.strides == arrays[0].strides
                                for a in arrays):
        start = arrays[0].__array_interface__["data"][0]
        item = arrays[0].itemsize
        pos = start
        for a in arrays:
            if a.__array_interface__["data"][0] != pos:
                break
            pos += a.size * item
        else:
            offset = (start - base.__array_interface__["data"][0]) // item
            if (base.ndim == 1 and base.dtype == arrays[0].dtype
                    and arrays[0].strides == (item,)):
                return base[offset:offset + (pos - start) // item]
    return np.concatenate(arrays)


__all__ = [
    "STREAM_START_POINTS",
    "STREAM_START_SECONDS",
    "NormalsTask",
    "StripNormals",
    "new_moment_grid",
]
