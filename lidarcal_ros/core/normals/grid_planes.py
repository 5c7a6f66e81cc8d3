"""Plane fits over a grid of moment sums: the steps of the grid normals, from cells to normals.

Flight frame (``u`` along, ``v`` across, ``z`` up, metres); the method: docs/correction.md,
"Surface normals".
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lidarcal_ros.core.normals.grid_normals_kernels import (
    accumulate_moments,
    cell_planes,
    cells_without_plane,
    centred_sums,
    fit_blocks,
    fit_sums,
    flight_to_map,
    point_normals,
    smallest_eigen_many,
)

#: Largest number of grid cells per point before the dense grid is replaced by a compact one.
_MAX_CELLS_PER_POINT = 4.0

#: A point further than this (m, and three times the typical residual) from its cell's plane,
#: or whose cell's plane fits worse, looks for a nearer plane among the blocks around its cell.
_EDGE_TOLERANCE_M = 0.05


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
    lam_min, lam_mid, vec, ok = smallest_eigen_many(*arrays)
    return lam_min, lam_mid, vec, ok


def fit_block_planes(
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
    residual, normals, valid, centroid = fit_sums(
        np.ascontiguousarray(sums, dtype=np.float64), min_points, min_spread)
    return residual, normals, valid, centroid


def dense_moment_grid(u: np.ndarray, v: np.ndarray, z: np.ndarray, cell: tuple[float, float]
                      ) -> tuple[np.ndarray | None, np.ndarray, np.ndarray]:
    """A grid of cells over points, anchored at their lowest coordinates (``u`` and ``v`` are
    shifted there, in place: moments stay small, indices non-negative): each point's cell
    ``iu, iv`` and the (nu, nv, 10) moment sums of the cells, None where the grid would be
    mostly empty (use :func:`sparse_grid_normals`)."""
    u -= u.min()
    v -= v.min()
    iu = (u * (1.0 / cell[0])).astype(np.int64)
    iv = (v * (1.0 / cell[1])).astype(np.int64)
    nu = int(iu.max()) + 1
    nv = int(iv.max()) + 1
    if nu * nv > _MAX_CELLS_PER_POINT * u.shape[0] + 1024:
        return None, iu, iv
    moments = np.zeros((nu, nv, 10))
    accumulate_moments(moments, 0, 0, iu, iv, u, v, z)
    return moments, iu, iv


def block_min_spread(cell: tuple[float, float]) -> float:
    """Least horizontal variance (m^2) of a block's points for a height-plane fit."""
    return (0.3 * min(cell)) ** 2 / 3.0


def _bin_moments(u: np.ndarray, v: np.ndarray, z: np.ndarray, key: np.ndarray,
                 size: int) -> np.ndarray:
    """The ten moment sums ``n, u, v, z, uu, uv, uz, vv, vz, zz`` of the points per cell
    ``key`` (flat index below ``size``), shape (10, size)."""
    out = np.zeros((1, size, 10))
    accumulate_moments(out, 0, 0, np.zeros(key.shape[0], dtype=np.int64),
                       np.asarray(key, dtype=np.int64), u, v, z)
    return np.ascontiguousarray(out[0].T)


def typical_residual(lam: np.ndarray, ok: np.ndarray) -> float:
    """Typical residual (m) of the blocks' plane fits: root of the median variance."""
    good = lam[::7][ok[::7]]  # a regular sample is enough for the median
    return math.sqrt(float(np.median(good))) if good.size else 0.0


def _centred_sums(moments: np.ndarray, cells: np.ndarray, radius: int) -> np.ndarray:
    """Moment sums (10, m) of the ``(2 radius + 1)^2`` blocks of cells centred on the flat
    cell indices ``cells`` of a (nu, nv, 10) grid (zero beyond it)."""
    return centred_sums(np.ascontiguousarray(moments, dtype=np.float64),
                        np.ascontiguousarray(cells, dtype=np.int64), int(radius))


@dataclass
class CellPlanes:
    """The planes of a grid's cells (:func:`plane_table`): what the normals of the points
    in the grid read.

    Attributes
    ----------
    blocks, valid : (nu * nv, 5) float64, (nu * nv,) bool
        The 2x2 block fits (:func:`~lidarcal_ros.core.normals.grid_normals_kernels.fit_blocks`).
    filled : (f, 5) float64
        The planes of the points' cells whose four blocks all failed, from the 3x3 or 5x5
        block around them.
    best, cell_ok : (nu * nv,) int64 and bool
        The plane of each cell (:func:`~lidarcal_ros.core.normals.grid_normals_kernels.cell_planes`;
        rows of ``filled`` past ``nu * nv``), and whether it has one.
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
        """Typical residual (m) of the blocks' plane fits (:func:`typical_residual`)."""
        return typical_residual(self.blocks[:, 4], self.valid)


def plane_table(moments: np.ndarray, iu: np.ndarray, iv: np.ndarray, row0: int, col0: int,
                min_points: int, min_spread: float, rows: tuple[int, int] | None = None
                ) -> CellPlanes:
    """The planes of the cells of a dense grid, for its points (docs/correction.md, "Surface
    normals").

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
    blocks, valid = fit_blocks(moments, min_points, min_spread, first - 1, last + 2)
    # Each cell: the best of the four 2x2 blocks containing it.
    best, cell_ok = cell_planes(blocks[:, 4], nu, nv, first, last + 1)
    # The cells of the points that lack a plane (not every occupied cell: a grid may reach
    # beyond the points).
    need = cells_without_plane(iu, iv, row0, col0, nv, cell_ok)
    filled: list[np.ndarray] = []
    count = 0
    for radius in (1, 2):
        # (2r+1)^2 blocks centred on the cells that still lack a plane: 3x3 first, then
        # 5x5.
        if radius > 1:
            need = need[~cell_ok[need]]
        if not need.size:
            break
        lam3, vec3, ok3, cen3 = fit_block_planes(_centred_sums(moments, need, radius), min_points,
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
    return CellPlanes(blocks, valid, np.concatenate(filled) if filled else np.empty((0, 5)),
                      best, cell_ok, nu, nv)


def normals_from_planes(planes: CellPlanes, iu: np.ndarray, iv: np.ndarray, row0: int,
                        col0: int, u: np.ndarray, v: np.ndarray, z: np.ndarray, noise: float,
                        heading: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normals (map frame), validity and roughness of points from the planes of their grid's
    cells: the plane of its cell, unless the point lies off it or the plane fits its block
    badly (a cell across an edge): then the nearest of the nine 2x2 blocks' planes
    (:func:`~lidarcal_ros.core.normals.grid_normals_kernels.point_normals`; ``noise``, the typical
    residual of a plane fit in m, sets the edge tolerance)."""
    tol = max(3.0 * noise, _EDGE_TOLERANCE_M)
    return point_normals(planes.blocks, planes.valid, planes.filled, planes.best,
                         planes.cell_ok, planes.nu, planes.nv, iu, iv, row0, col0, u, v, z,
                         tol, math.cos(heading), math.sin(heading))


def dense_grid_normals(
    moments: np.ndarray, iu: np.ndarray, iv: np.ndarray, u: np.ndarray, v: np.ndarray,
    z: np.ndarray, min_points: int, min_spread: float, heading: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normals (map frame), validity and roughness of points from the moment sums of a
    dense grid of cells (docs/correction.md), the edge tolerance from the median residual of
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
    planes = plane_table(moments, iu, iv, 0, 0, min_points, min_spread)
    return normals_from_planes(planes, iu, iv, 0, 0, u, v, z, planes.noise(), heading)


def sparse_grid_normals(
    u: np.ndarray, v: np.ndarray, z: np.ndarray, iu: np.ndarray, iv: np.ndarray,
    heading: float, min_points: int, min_spread: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Like :func:`dense_grid_normals`, for point sets whose grid would be mostly empty: the
    occupied cells are compacted first (``np.unique``) and neighbours found by binary
    search."""
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
        lam, vec, ok, _ = fit_block_planes(block(offs), min_points, min_spread)
        take = ok & (lam < best)
        best[take] = lam[take]
        best_vec[take] = vec[take]
    cell_ok = np.isfinite(best)
    if not cell_ok.all():
        offs = [(a, b) for a in (-1, 0, 1) for b in (-1, 0, 1)]
        _, vec, ok, _ = fit_block_planes(block(offs), min_points, min_spread)
        fill = ~cell_ok & ok
        best_vec[fill] = vec[fill]
        cell_ok |= fill
    good = best[np.isfinite(best)]
    noise = math.sqrt(float(np.median(good))) if good.size else 0.0
    tol = max(3.0 * noise, _EDGE_TOLERANCE_M)
    rough = (best > tol * tol) & cell_ok
    return (_to_map(np.take(best_vec, inverse, axis=0), heading), np.take(cell_ok, inverse),
            np.take(rough, inverse))


def _to_map(n_uvz: np.ndarray, heading: float) -> np.ndarray:
    """Normals from the flight frame (u forward, v right, z up) to the map frame."""
    return flight_to_map(np.asarray(n_uvz, dtype=np.float64), math.cos(heading),
                         math.sin(heading))


__all__ = ["CellPlanes", "block_min_spread", "dense_grid_normals", "dense_moment_grid",
           "fit_block_planes", "normals_from_planes", "plane_table", "smallest_eigen",
           "sparse_grid_normals", "typical_residual"]
