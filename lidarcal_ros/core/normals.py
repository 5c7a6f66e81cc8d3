"""Local surface normals of a LiDAR strip by grid plane fits (for the incidence angle).

Per-point k-nearest-neighbour searches are too slow for a stream of millions of points per
second, so the neighbourhood is a grid: the points are binned into cells of 1.5 point spacings
in a frame aligned with the flight line (``u`` along, ``v`` across, metres), the first and
second moments of each cell are summed (the ten sums of a cell side by side), and a plane is
fitted to every 2x2 block of cells (least-squares height plane; principal components for the
few blocks whose points do not spread in both horizontal directions, e.g. walls). Each cell
takes the plane of the most planar of the four blocks that contain it (smallest residual
variance), so a cell beside a roof ridge or a building edge takes the block lying on its own
side where there is one; a cell whose four blocks are all degenerate (fewer than
``min_points`` points, or all on one scan line) falls back to the 3x3 block centred on it,
then to the 5x5 one, and failing that gets no normal (NaN).

Every point takes the plane of its cell, unless it lies off that plane (further than three
times the typical residual, at least 5 cm) or the plane fits its block badly: then it takes,
among the planes of the nine 2x2 blocks around its cell, the one that is nearest to it (squared
distance plus the block's residual variance). This keeps normals sharp up to about a point
spacing from edges and ridges. A point whose best plane still fits badly is reported *rough*
(vegetation, edges): its normal, hence its incidence angle, is uncertain. Tree crowns, whose
bumps are smaller than the blocks, get the normal of the block they fall in: irregular, as the
surface is, and rough.

A linear (zig-zag) scanner samples anisotropically: points follow each other closely along a
sweep while the sweeps are further apart (twice their mean distance near the swath edges,
where consecutive sweeps meet). :func:`cell_size` therefore measures the spacing across track
from consecutive pulses and the spacing along track from the area per point, and the cells
are rectangles of 1.5 of each; a 2x2 block then always spans two sweeps.

Cost (compiled loops, :mod:`lidarcal_ros.core.normals_kernels`): one pass over the points to bin
them, one over the cells (about one cell per 2.25 points) to fit the blocks and choose each
cell's plane, one over the points for their normals; a nine-plane search for the few per cent
of points near edges.

Normals are returned in the map frame, unit length, oriented upward (``n_z >= 0``).
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from lidarcal_ros.core import normals_kernels
from lidarcal_ros.core.allocator import populate_in_background

logger = logging.getLogger(__name__)

#: Cell size in mean point spacings.
CELL_SPACINGS = 1.5
#: Fewest points a block needs for a plane.
MIN_BLOCK_POINTS = 5
#: Largest number of grid cells per point before the dense grid is replaced by a compact one.
_MAX_CELLS_PER_POINT = 4.0
#: A point further than this (m, and three times the typical residual) from its cell's plane,
#: or whose cell's plane fits worse, looks for a nearer plane among the blocks around its cell.
_EDGE_TOLERANCE_M = 0.05
#: Points used at most to estimate the spacing (a regular subsample beyond).
_SPACING_SAMPLE = 20_000


@dataclass
class GridNormals:
    """Result of :func:`grid_normals`.

    Attributes
    ----------
    normals : (n, 3) float64
        Unit upward normals, map frame; NaN where ``valid`` is False.
    valid : (n,) bool
        A plane could be fitted to the point's neighbourhood.
    cell_m : (float, float)
        Cell used, ``(along, across)`` metres (NaN if none could be chosen).
    rough : (n,) bool
        The plane fits the point's neighbourhood badly (mean squared distance of its points
        plus the point's own squared distance above ``(3 sigma_noise)^2``, at least
        ``(5 cm)^2``): an edge, vegetation; the normal, hence the incidence, is uncertain.
    """

    normals: np.ndarray
    valid: np.ndarray
    cell_m: tuple[float, float]
    rough: np.ndarray | None = None


def finite_rows(xyz: np.ndarray) -> np.ndarray:
    """Rows of an (n, 3) array whose three values are finite (faster than
    ``np.isfinite(xyz).all(axis=1)``)."""
    with np.errstate(invalid="ignore", over="ignore"):
        return np.isfinite(xyz[:, 0] + xyz[:, 1] + xyz[:, 2])


def mean_spacing(xyz: np.ndarray, heading: float) -> float:
    """Mean point spacing (m) of a piece of strip: ``sqrt(area / n)`` with the area that of
    the flight-aligned rectangle (1st to 99th percentile) the points cover.

    Parameters
    ----------
    xyz : (n, 3) float
        Points, map frame, metres.
    heading : float
        Heading ``kappa`` of the flight line, radians (``atan2(-d_x, d_y)``).

    Returns
    -------
    float
        Metres; NaN for fewer than 10 points.
    """
    n = xyz.shape[0]
    if n < 10:
        return math.nan
    step = max(1, n // _SPACING_SAMPLE)
    u, v = _flight_frame(xyz[::step], heading, float(xyz[0, 0]), float(xyz[0, 1]))
    lo, hi = np.percentile(u, [1.0, 99.0])
    lo_v, hi_v = np.percentile(v, [1.0, 99.0])
    area = max(float(hi - lo), 1e-3) * max(float(hi_v - lo_v), 1e-3)
    return math.sqrt(area / (0.98 * n))


def cell_size(
    xyz: np.ndarray, heading: float, t: np.ndarray | None = None
) -> tuple[float, float]:
    """Grid cell ``(along, across)`` in metres for a piece of strip: 1.5 spacings each.

    With the firing times ``t``, the across-track spacing is the median lateral distance
    between consecutive pulses (the in-sweep spacing) and the along-track spacing the area per
    point divided by it (the sweep spacing); their ratio is kept within 1/8..8. Without
    ``t`` (or where that fails) the cell is square, 1.5 :func:`mean_spacing`.

    Parameters
    ----------
    xyz : (n, 3) float
        Finite points, map frame, m.
    heading : float
        Heading of the flight line, rad.
    t : (n,) float, optional
        Firing times, s (consecutive points should be consecutive pulses, as delivered).

    Returns
    -------
    (float, float)
        NaN when there are too few points.
    """
    s = mean_spacing(xyz, heading)
    if not math.isfinite(s):
        return math.nan, math.nan
    square = (CELL_SPACINGS * s, CELL_SPACINGS * s)
    n = xyz.shape[0]
    if t is None or n < 20:
        return square
    m = min(n, 4 * _SPACING_SAMPLE)
    start = (n - m) // 2
    sl = slice(start, start + m)
    _, v = _flight_frame(xyz[sl], heading, float(xyz[0, 0]), float(xyz[0, 1]))
    dt = np.diff(np.asarray(t[sl], dtype=np.float64))
    good = dt > 0
    if good.sum() < 10:
        return square
    good &= dt <= 3.0 * float(np.median(dt[good]))
    across = float(np.median(np.abs(np.diff(v))[good]))
    if not (math.isfinite(across) and across > 0):
        return square
    across = min(max(across, s / math.sqrt(8.0)), s * math.sqrt(8.0))
    along = s * s / across
    return CELL_SPACINGS * along, CELL_SPACINGS * across


def _flight_frame(
    xyz: np.ndarray, heading: float, x0: float, y0: float
) -> tuple[np.ndarray, np.ndarray]:
    """Along-track ``u`` and across-track ``v`` (right) coordinates relative to (x0, y0)."""
    c, s = math.cos(heading), math.sin(heading)
    dx = xyz[:, 0] - x0
    dy = xyz[:, 1] - y0
    u = -s * dx + c * dy
    v = c * dx + s * dy
    return u, v


def _to_map(n_uvz: np.ndarray, heading: float) -> np.ndarray:
    """Normals from the flight frame (u forward, v right, z up) to the map frame."""
    return normals_kernels.flight_to_map(np.asarray(n_uvz, dtype=np.float64), math.cos(heading),
                                 math.sin(heading))


def smallest_eigen(
    cxx: np.ndarray, cxy: np.ndarray, cxz: np.ndarray,
    cyy: np.ndarray, cyz: np.ndarray, czz: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Smallest and middle eigenvalues and the smallest eigenvector of symmetric 3x3 matrices.

    Closed form (trigonometric solution of the characteristic cubic), vectorised over 1-D
    arrays of the six distinct entries.

    Returns
    -------
    lam_min, lam_mid : (m,) float64
    vec : (m, 3) float64
        Unit eigenvector of ``lam_min`` with ``vec_z >= 0``.
    ok : (m,) bool
        False where the vector is undefined (isotropic or zero matrix).
    """
    arrays = [np.ascontiguousarray(c, dtype=np.float64) for c in (cxx, cxy, cxz, cyy, cyz, czz)]
    lam_min, lam_mid, vec, ok = normals_kernels.smallest_eigen_many(*arrays)
    return lam_min, lam_mid, vec, ok


def _fit_sums(
    sums: np.ndarray, min_points: int, min_spread: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Plane fits to blocks given their ten moment sums (10, m).

    A least-squares height plane ``z = a + b u + c v`` where the points spread in both
    horizontal directions (both eigenvalues of their horizontal covariance at least
    ``min_spread``, m^2); the principal-component plane (:func:`smallest_eigen`) for the few
    blocks that do not (walls, single scan lines), valid if the points spread over a plane.

    Returns
    -------
    residual : (m,) float64
        Residual variance normal to the plane, m^2 (``inf`` where there is no valid plane).
    normals : (m, 3) float64
        Unit upward normals in the frame of the sums (NaN where not valid).
    valid : (m,) bool
    centroid : (m, 3) float64
        Mean point of each block, frame of the sums.
    """
    residual, normals, valid, centroid = normals_kernels.fit_sums(
        np.ascontiguousarray(sums, dtype=np.float64), min_points, min_spread)
    return residual, normals, valid, centroid


def grid_normals(
    xyz: np.ndarray,
    heading: float,
    *,
    cell_m: float | tuple[float, float] | None = None,
    group: np.ndarray | None = None,
    t: np.ndarray | None = None,
    min_points: int = MIN_BLOCK_POINTS,
) -> GridNormals:
    """Upward unit normals of the surface around each point (module docstring).

    Parameters
    ----------
    xyz : (n, 3) float64
        Points of one piece of strip (or several, told apart by ``group``), map frame, m.
        Non-finite points get no normal and are nobody's neighbour.
    heading : float
        Heading ``kappa`` of the flight line, radians; aligns the grid with the scan pattern.
    cell_m : float or (float, float), optional
        Cell size (square, or ``(along, across)``), metres; default :func:`cell_size`.
    group : (n,) int, optional
        Points of different groups (strips) are never neighbours.
    t : (n,) float, optional
        Firing times, s, for :func:`cell_size` when ``cell_m`` is not given.
    min_points : int
        Fewest points a block needs.

    Returns
    -------
    GridNormals
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    n = xyz.shape[0]
    normals = np.full((n, 3), np.nan)
    valid = np.zeros(n, dtype=bool)
    rough = np.zeros(n, dtype=bool)
    finite = finite_rows(xyz)
    all_finite = bool(finite.all())
    if cell_m is None:
        cell = cell_size(xyz if all_finite else xyz[finite], heading,
                         None if t is None else (t if all_finite else t[finite]))
    elif isinstance(cell_m, tuple):
        cell = (float(cell_m[0]), float(cell_m[1]))
    else:
        cell = (float(cell_m), float(cell_m))
    if not all(math.isfinite(c) and c > 0 for c in cell):
        return GridNormals(normals, valid, (math.nan, math.nan), rough)
    subsets: list[np.ndarray | None]
    if group is not None and n:
        g = np.asarray(group)
        # min == max first: a chunk of one strip (the usual case) needs no hashing.
        keys = g[:1] if g.min() == g.max() else np.unique(g)
        if keys.size > 1:
            subsets = [np.flatnonzero(finite & (g == k)) for k in keys]
        else:
            subsets = [None if all_finite else np.flatnonzero(finite)]
    else:
        subsets = [None if all_finite else np.flatnonzero(finite)]
    for idx in subsets:
        sub = xyz if idx is None else xyz[idx]
        if sub.shape[0] < min_points:
            continue
        nrm, ok, rgh = _fit_group(sub, heading, cell, min_points)
        nrm[~ok] = np.nan
        if idx is None:
            normals, valid, rough = nrm, ok, rgh
        else:
            normals[idx] = nrm
            valid[idx] = ok
            rough[idx] = rgh
    return GridNormals(normals, valid, cell, rough)


def _fit_group(
    xyz: np.ndarray, heading: float, cell: tuple[float, float], min_points: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    x0, y0 = float(xyz[0, 0]), float(xyz[0, 1])
    u, v = _flight_frame(xyz, heading, x0, y0)
    z = xyz[:, 2] - float(xyz[0, 2])
    min_spread = _min_spread(cell)
    moments, iu, iv = _dense_moments(u, v, z, cell)
    if moments is None:
        return _fit_sparse(u, v, z, iu, iv, heading, min_points, min_spread)
    return _grid_planes(moments, iu, iv, u, v, z, min_points, min_spread, heading)


def _dense_moments(u: np.ndarray, v: np.ndarray, z: np.ndarray, cell: tuple[float, float]
                   ) -> tuple[np.ndarray | None, np.ndarray, np.ndarray]:
    """A grid of cells over points, anchored at their lowest coordinates (``u`` and ``v`` are
    shifted there, in place: moments stay small, indices non-negative): each point's cell
    ``iu, iv`` and the (nu, nv, 10) moment sums of the cells, None where the grid would be
    mostly empty (use :func:`_fit_sparse`)."""
    u -= u.min()
    v -= v.min()
    iu = (u * (1.0 / cell[0])).astype(np.int64)
    iv = (v * (1.0 / cell[1])).astype(np.int64)
    nu = int(iu.max()) + 1
    nv = int(iv.max()) + 1
    if nu * nv > _MAX_CELLS_PER_POINT * u.shape[0] + 1024:
        return None, iu, iv
    moments = np.zeros((nu, nv, 10))
    normals_kernels.accumulate_moments(moments, 0, 0, iu, iv, u, v, z)
    return moments, iu, iv


def _min_spread(cell: tuple[float, float]) -> float:
    """Least horizontal variance (m^2) of a block's points for a height-plane fit."""
    return (0.3 * min(cell)) ** 2 / 3.0


def _bin_moments(u: np.ndarray, v: np.ndarray, z: np.ndarray, key: np.ndarray,
                 size: int) -> np.ndarray:
    """The ten moment sums ``n, u, v, z, uu, uv, uz, vv, vz, zz`` of the points per cell
    ``key`` (flat index below ``size``), shape (10, size)."""
    out = np.zeros((1, size, 10))
    normals_kernels.accumulate_moments(out, 0, 0, np.zeros(key.shape[0], dtype=np.int64),
                               np.asarray(key, dtype=np.int64), u, v, z)
    return np.ascontiguousarray(out[0].T)


def _median_noise(lam: np.ndarray, ok: np.ndarray) -> float:
    """Typical residual (m) of the blocks' plane fits: root of the median variance."""
    good = lam[::7][ok[::7]]  # a regular sample is enough for the median
    return math.sqrt(float(np.median(good))) if good.size else 0.0


def _centred_sums(moments: np.ndarray, cells: np.ndarray, radius: int) -> np.ndarray:
    """Moment sums (10, m) of the ``(2 radius + 1)^2`` blocks of cells centred on the flat
    cell indices ``cells`` of a (nu, nv, 10) grid (zero beyond it)."""
    return normals_kernels.centred_sums(np.ascontiguousarray(moments, dtype=np.float64),
                                np.ascontiguousarray(cells, dtype=np.int64), int(radius))


@dataclass
class _Planes:
    """The planes of a grid's cells (:func:`_plane_table`): what the normals of the points
    in the grid read.

    Attributes
    ----------
    blocks, valid : (nu * nv, 5) float64, (nu * nv,) bool
        The 2x2 block fits (:func:`~lidarcal_ros.core.normals_kernels.fit_blocks`).
    filled : (f, 5) float64
        The planes of the points' cells whose four blocks all failed, from the 3x3 or 5x5
        block around them.
    best, cell_ok : (nu * nv,) int64 and bool
        The plane of each cell (:func:`~lidarcal_ros.core.normals_kernels.cell_planes`; rows of
        ``filled`` past ``nu * nv``), and whether it has one.
    nu, nv : int
        Grid shape.
    """

    blocks: np.ndarray
    valid: np.ndarray
    filled: np.ndarray
    best: np.ndarray
    cell_ok: np.ndarray
    nu: int
    nv: int

    def noise(self) -> float:
        """Typical residual (m) of the blocks' plane fits (:func:`_median_noise`)."""
        return _median_noise(self.blocks[:, 4], self.valid)


def _plane_table(moments: np.ndarray, iu: np.ndarray, iv: np.ndarray, row0: int, col0: int,
                 min_points: int, min_spread: float, rows: tuple[int, int] | None = None
                 ) -> _Planes:
    """The planes of the cells of a dense grid, for its points (module docstring).

    Parameters
    ----------
    moments : (nu, nv, 10) float64
        Moment sums per cell (:func:`_bin_moments`); cells beyond the grid count as empty.
    iu, iv : (n,) int64
        Cell of each point: row ``iu - row0``, column ``iv - col0`` of the grid. A cell of
        theirs without a plane of its own blocks takes that of the 3x3 block of cells around
        it, failing that of the 5x5 one (e.g. the newest scan line when nothing beyond it
        has arrived yet).
    rows : (int, int), optional
        The first and last grid row holding points (all rows by default): only the planes
        of their cells and the blocks those read (a row either side) are fitted.
    """
    nu, nv, _ = moments.shape
    first, last = (0, nu - 1) if rows is None else rows
    blocks, valid = normals_kernels.fit_blocks(moments, min_points, min_spread, first - 1, last + 2)
    # Each cell: the best of the four 2x2 blocks containing it.
    best, cell_ok = normals_kernels.cell_planes(blocks[:, 4], nu, nv, first, last + 1)
    # The cells of the points that lack a plane (not every occupied cell: a grid may reach
    # beyond the points).
    need = normals_kernels.cells_without_plane(iu, iv, row0, col0, nv, cell_ok)
    filled: list[np.ndarray] = []
    count = 0
    for radius in (1, 2):
        # (2r+1)^2 blocks centred on the cells that still lack a plane: 3x3 first, then
        # 5x5.
        if radius > 1:
            need = need[~cell_ok[need]]
        if not need.size:
            break
        lam3, vec3, ok3, cen3 = _fit_sums(_centred_sums(moments, need, radius), min_points,
                                          min_spread)
        fill = need[ok3]
        table = np.empty((fill.size, 5))
        table[:, :3] = vec3[ok3]
        table[:, 3] = np.einsum("ij,ij->i", vec3[ok3], cen3[ok3])
        table[:, 4] = lam3[ok3]
        best[fill] = nu * nv + count + np.arange(fill.size)
        cell_ok[fill] = True
        filled.append(table)
        count += fill.size
    return _Planes(blocks, valid, np.concatenate(filled) if filled else np.empty((0, 5)),
                   best, cell_ok, nu, nv)


def _point_normals(planes: _Planes, iu: np.ndarray, iv: np.ndarray, row0: int, col0: int,
                   u: np.ndarray, v: np.ndarray, z: np.ndarray, noise: float, heading: float
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normals (map frame), validity and roughness of points from the planes of their grid's
    cells: the plane of its cell, unless the point lies off it or the plane fits its block
    badly (a cell across an edge): then the nearest of the nine 2x2 blocks' planes
    (:func:`~lidarcal_ros.core.normals_kernels.point_normals`; ``noise``, the typical residual of a
    plane fit in m, sets the edge tolerance)."""
    tol = max(3.0 * noise, _EDGE_TOLERANCE_M)
    return normals_kernels.point_normals(planes.blocks, planes.valid, planes.filled, planes.best,
                                 planes.cell_ok, planes.nu, planes.nv, iu, iv, row0, col0,
                                 u, v, z, tol, math.cos(heading), math.sin(heading))


def _grid_planes(
    moments: np.ndarray, iu: np.ndarray, iv: np.ndarray, u: np.ndarray, v: np.ndarray,
    z: np.ndarray, min_points: int, min_spread: float, heading: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normals (map frame), validity and roughness of points from the moment sums of a
    dense grid of cells (module docstring), the edge tolerance from the median residual of
    the grid's blocks.

    Parameters
    ----------
    moments : (nu, nv, 10) float64
        Moment sums per cell (:func:`_bin_moments`), in the frame of ``u, v, z``.
    iu, iv : (n,) int64
        Cell of each point in the grid.
    u, v, z : (n,) float64
        The points, same frame as the moments, m.
    heading : float
        Heading of the grid's frame, rad.
    """
    planes = _plane_table(moments, iu, iv, 0, 0, min_points, min_spread)
    return _point_normals(planes, iu, iv, 0, 0, u, v, z, planes.noise(), heading)


def _fit_sparse(
    u: np.ndarray, v: np.ndarray, z: np.ndarray, iu: np.ndarray, iv: np.ndarray,
    heading: float, min_points: int, min_spread: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Like the dense path, for point sets whose grid would be mostly empty: the occupied
    cells are compacted first (``np.unique``) and neighbours found by binary search."""
    nv = int(iv.max()) + 3
    key = (iu + 1) * nv + (iv + 1)
    cells, inverse = np.unique(key, return_inverse=True)
    inverse = inverse.reshape(-1)
    m = cells.size
    sums = _bin_moments(u, v, z, inverse, m)

    def block(offsets: list[tuple[int, int]]) -> np.ndarray:
        acc = np.zeros_like(sums)
        for ou, ov in offsets:
            target = cells + (ou * nv + ov)
            pos = np.minimum(np.searchsorted(cells, target), m - 1)
            hit = cells[pos] == target
            acc[:, hit] += sums[:, pos[hit]]
        return acc

    best = np.full(m, np.inf)
    best_vec = np.full((m, 3), np.nan)
    for bu, bv in ((0, 0), (-1, 0), (0, -1), (-1, -1)):
        offs = [(bu + a, bv + b) for a in (0, 1) for b in (0, 1)]
        lam, vec, ok, _ = _fit_sums(block(offs), min_points, min_spread)
        take = ok & (lam < best)
        best[take] = lam[take]
        best_vec[take] = vec[take]
    cell_ok = np.isfinite(best)
    if not cell_ok.all():
        offs = [(a, b) for a in (-1, 0, 1) for b in (-1, 0, 1)]
        _, vec, ok, _ = _fit_sums(block(offs), min_points, min_spread)
        fill = ~cell_ok & ok
        best_vec[fill] = vec[fill]
        cell_ok |= fill
    good = best[np.isfinite(best)]
    noise = math.sqrt(float(np.median(good))) if good.size else 0.0
    tol = max(3.0 * noise, _EDGE_TOLERANCE_M)
    rough = (best > tol * tol) & cell_ok
    return (_to_map(np.take(best_vec, inverse, axis=0), heading), np.take(cell_ok, inverse),
            np.take(rough, inverse))


# ---------------------------------------------------------------------------- streaming
#: A strip's grid (cell size, heading, origin) is fixed by its first points: as many as it
#: takes to reach both this count and this time span (the same points however the stream is
#: cut into parts; the parts before are held until then).
STREAM_START_POINTS = 10_000
STREAM_START_SECONDS = 0.02
#: Rows kept behind the oldest points not yet evaluated, so that points arriving a little
#: late (behind the watermark) still land in the grid.
_LATE_ROWS = 2
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
    """Grid normals (:func:`grid_normals`) of one strip computed as its points arrive.

    Every point is binned into the strip's grid once and evaluated once: the grid (cell,
    heading, origin) is fixed by the strip's first :data:`STREAM_START_POINTS` points and the
    moment sums of its cells are kept from the oldest points not yet evaluated on. A point in
    grid row ``i`` (along track) depends on the cells of rows ``i - 2 .. i + 2`` only, so its
    normal is final once no later point can land in those rows.

    The edge tolerance comes from the typical plane-fit residual of the strip's first points.
    With ``lookahead`` the points of a part are evaluated once the *watermark*, the lowest
    row of the newest part, is three rows beyond the part's highest row (a scanner's points
    advance along track; the newest part's lowest row bounds where later points land), which
    gives exactly the normals of :func:`grid_normals` over the whole strip in the same grid.
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
    them.
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
        moments, _, _ = _dense_moments(*self._frame(xyz), self.cell)
        if moments is None:
            return 0.0
        blocks, valid = normals_kernels.fit_blocks(moments, self.min_points, _min_spread(self.cell))
        return _median_noise(blocks[:, 4], valid)

    def _frame(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        x0, y0, z0 = self._origin
        u, v = _flight_frame(xyz, self.heading, x0, y0)
        return u, v, xyz[:, 2] - z0

    def _bin(self, key: object, xyz: np.ndarray) -> None:
        self._bin_parts([(key, xyz.shape[0])], xyz)

    def _bin_parts(self, parts: list[tuple[object, int]], xyz: np.ndarray) -> None:
        """Bin the points of consecutive parts (``(key, count)``, their points one after the
        other in ``xyz``) in one pass."""
        x0, y0, z0 = self._origin
        u, v, z, iu, iv, finite_index, bounds = normals_kernels.flight_cells(
            np.ascontiguousarray(xyz, dtype=np.float64), math.cos(self.heading),
            math.sin(self.heading), x0, y0, z0, 1.0 / self.cell[0], 1.0 / self.cell[1])
        index = None if finite_index.size == xyz.shape[0] else finite_index
        r_lo, r_hi, c_lo, c_hi = (int(b) for b in bounds)
        keep = self._inliers(iu, iv, r_lo, r_hi, c_lo, c_hi)
        if keep is not None:
            index = finite_index[keep]
            u, v, z, iu, iv = u[keep], v[keep], z[keep], iu[keep], iv[keep]
            if iu.size:
                r_lo, r_hi = int(iu.min()), int(iu.max())
                c_lo, c_hi = int(iv.min()), int(iv.max())
        if iu.size:
            self._fit_grid(r_lo, r_hi, c_lo, c_hi)
            normals_kernels.accumulate_moments(self._moments, self._row0, self._col0, iu, iv, u, v, z)
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
            r_min, r_max = (int(piu.min()), int(piu.max())) if piu.size else (0, -1)
            self._parts.append(_Part(key, n, part_index, u[lo:hi], v[lo:hi], z[lo:hi], piu,
                                     iv[lo:hi], r_min, r_max))
            if piu.size:
                self._watermark = r_min
            start += n

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
        outgrow it, or when it must widen. (A fresh array of some 50 MB, for a wide swath in
        fine cells, cost about 90 ms in page faults at each regrowth and about as much again
        while the next chunks filled it; now only a strip's first arrays pay that.)
        """
        m = self._moments
        if m.shape[0] == 0:
            pad_c = 16
            self._row0, self._col0 = r_lo - 1, c_lo - pad_c
            self._moments = _new_grid((r_hi - r_lo + 64, c_hi - c_lo + 1 + 2 * pad_c, 10))
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
        grown = _new_grid((new_r1 - new_r0, new_c1 - new_c0, 10))
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
        return min(low, self._watermark) - 2 - _LATE_ROWS

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
                    or part.row_max + 3 <= self._watermark):
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
        planes = _plane_table(self._moments[lo - self._row0:hi - self._row0], iu, iv, lo,
                              self._col0, self.min_points, _min_spread(self.cell), rows)
        return NormalsTask(ready, planes, lo, self._col0, self.cell, self.heading, self._noise)


@dataclass
class NormalsTask:
    """The normals of some parts of a strip (:meth:`StripNormals.take_ready`): everything
    their evaluation reads, so that :meth:`run` may run in another thread."""

    parts: list[_Part]
    planes: _Planes | None  # of the grid rows around the parts (None: no point binned)
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
        return _point_normals(self.planes, iu, iv, self.row0, self.col0, u, v, z, self.noise,
                              self.heading)


def _new_grid(shape: tuple[int, int, int]) -> np.ndarray:
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


def no_normals(n: int, cell: tuple[float, float] = (math.nan, math.nan)) -> GridNormals:
    """``n`` points without a normal (NaN, not valid, not rough)."""
    return GridNormals(np.full((n, 3), np.nan), np.zeros(n, dtype=bool), cell,
                       np.zeros(n, dtype=bool))
