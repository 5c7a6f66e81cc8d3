"""Compiled loops of the grid normals: binning, block plane fits, each cell's plane, each normal.

Each function states the numpy expression it replaces and keeps its order of arithmetic
(compiled as :mod:`lidarcal_ros.core.jit` says). Frames: ``u`` along track, ``v`` across
(right), ``z`` up, metres from the grid's origin; a moment grid is ``(rows, columns, 10)``.
"""

from __future__ import annotations

import math

import numpy as np

from lidarcal_ros.core.jit import compiled, inlined

_THIRD_TURN = 2.0 * math.pi / 3.0


@compiled
def accumulate_moments(out: np.ndarray, row0: int, col0: int, iu: np.ndarray, iv: np.ndarray,
                       u: np.ndarray, v: np.ndarray, z: np.ndarray) -> None:
    """Add each point's moments to its cell: ``out[iu - row0, iv - col0] += (1, u, v, z, uu,
    uv, uz, vv, vz, zz)``, in the order of the points.

    Parameters
    ----------
    out : (rows, cols, 10) float64
        Moment sums per cell (modified in place). A cell's ten sums lie together: a point
        touches one or two cache lines, not ten.
    row0, col0 : int
        Grid row and column of ``out[0, 0]``.
    iu, iv : (n,) int64
        Cell row and column of each point (inside ``out``).
    u, v, z : (n,) float64
    """
    for i in range(iu.shape[0]):
        cell = out[iu[i] - row0, iv[i] - col0]
        pu, pv, pz = u[i], v[i], z[i]
        cell[0] += 1.0
        cell[1] += pu
        cell[2] += pv
        cell[3] += pz
        cell[4] += pu * pu
        cell[5] += pu * pv
        cell[6] += pu * pz
        cell[7] += pv * pv
        cell[8] += pv * pz
        cell[9] += pz * pz


@compiled
def _cross(a: tuple[float, float, float], b: tuple[float, float, float]
           ) -> tuple[float, float, float]:
    """``a x b``."""
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


@compiled
def _eigen_smallest(cxx: float, cxy: float, cxz: float, cyy: float, cyz: float, czz: float
                    ) -> tuple[float, float, float, float, float, bool]:
    """Smallest and middle eigenvalue and the smallest eigenvector (``z >= 0``) of one
    symmetric 3x3 matrix; ``ok`` False where the vector is undefined."""
    p1 = cxy * cxy + cxz * cxz + cyz * cyz
    q = (cxx + cyy + czz) * (1.0 / 3.0)
    a = cxx - q
    b = cyy - q
    c = czz - q
    p = math.sqrt((a * a + b * b + c * c + 2.0 * p1) * (1.0 / 6.0))
    det = a * (b * c - cyz * cyz) - cxy * (cxy * c - cyz * cxz) + cxz * (cxy * cyz - b * cxz)
    r = det * (0.5 / (p * p * p))
    if r < -1.0:
        r = -1.0
    elif r > 1.0:
        r = 1.0
    phi = math.acos(r) * (1.0 / 3.0)
    lam_max = q + 2.0 * p * math.cos(phi)
    lam_min = q + 2.0 * p * math.cos(phi + _THIRD_TURN)
    lam_mid = 3.0 * q - lam_max - lam_min
    # The largest cross product of two rows of (C - lam_min I).
    r0 = (cxx - lam_min, cxy, cxz)
    r1 = (cxy, cyy - lam_min, cyz)
    r2 = (cxz, cyz, czz - lam_min)
    vx, vy, vz = _cross(r0, r1)
    best = vx * vx + vy * vy + vz * vz
    for ra, rb in ((r0, r2), (r1, r2)):
        wx, wy, wz = _cross(ra, rb)
        nn = wx * wx + wy * wy + wz * wz
        if nn > best:
            vx, vy, vz, best = wx, wy, wz, nn
    norm = math.sqrt(best)
    ok = norm > 0.0 and p > 0.0 and math.isfinite(norm)
    scale = 1.0 / norm
    if vz < 0.0:
        scale = -scale
    return lam_min, lam_mid, vx * scale, vy * scale, vz * scale, ok


@compiled
def smallest_eigen_many(cxx: np.ndarray, cxy: np.ndarray, cxz: np.ndarray, cyy: np.ndarray,
                        cyz: np.ndarray, czz: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_eigen_smallest` of each of m matrices given as six (m,) arrays."""
    m = cxx.shape[0]
    lam_min = np.empty(m)
    lam_mid = np.empty(m)
    vec = np.empty((m, 3))
    ok = np.empty(m, dtype=np.bool_)
    for k in range(m):
        lo, mid, x, y, zz, good = _eigen_smallest(cxx[k], cxy[k], cxz[k], cyy[k], cyz[k],
                                                  czz[k])
        lam_min[k], lam_mid[k] = lo, mid
        vec[k, 0], vec[k, 1], vec[k, 2] = x, y, zz
        ok[k] = good
    return lam_min, lam_mid, vec, ok


@inlined
def _height_plane(n: float, su: float, sv: float, sz: float, suu: float, suv: float,
                  suz: float, svv: float, svz: float, szz: float, min_points: int,
                  min_spread: float
                  ) -> tuple[float, float, float, float, float, float, float, bool, float,
                             float, float, float, float, float]:
    """The least-squares height plane of a block from its ten moment sums, without a
    branch: residual, normal, centroid and validity as :func:`fit_sums` (inf, NaN where
    the points do not spread in both horizontal directions), then the covariances
    ``cuu, cuv, cuz, cvv, cvz, czz`` for the principal-component fallback."""
    inv = 1.0 / n
    mu = su * inv
    mv = sv * inv
    mz = sz * inv
    cuu = suu * inv - mu * mu
    cuv = suv * inv - mu * mv
    cuz = suz * inv - mu * mz
    cvv = svv * inv - mv * mv
    cvz = svz * inv - mv * mz
    czz = szz * inv - mz * mz
    det = cuu * cvv - cuv * cuv
    half_tr = 0.5 * (cuu + cvv)
    lam_h = half_tr - math.sqrt(max(half_tr * half_tr - det, 0.0))
    ls = (n >= min_points) & (lam_h >= min_spread)
    inv_det = 1.0 / det
    b = (cvv * cuz - cuv * cvz) * inv_det
    c = (cuu * cvz - cuv * cuz) * inv_det
    norm2 = 1.0 + b * b + c * c
    scale = 1.0 / math.sqrt(norm2)
    res = max((czz - b * cuz - c * cvz) / norm2, 0.0)
    return (res if ls else np.inf, -b * scale if ls else np.nan,
            -c * scale if ls else np.nan, scale if ls else np.nan, mu, mv, mz, ls,
            cuu, cuv, cuz, cvv, cvz, czz)


@compiled
def _fit_one(n: float, su: float, sv: float, sz: float, suu: float, suv: float, suz: float,
             svv: float, svz: float, szz: float, min_points: int, min_spread: float,
             residual: np.ndarray, normals: np.ndarray, valid: np.ndarray,
             centroid: np.ndarray, k: int) -> None:
    """Plane fit of one block from its ten moment sums into row ``k`` of the outputs
    (:func:`lidarcal_ros.core.normals.grid_planes.fit_block_planes` has the method): the height
    plane of :func:`_height_plane`, else the principal-component plane."""
    res, nx, ny, nz, mu, mv, mz, height_plane, cuu, cuv, cuz, cvv, cvz, czz = _height_plane(
        n, su, sv, sz, suu, suv, suz, svv, svz, szz, min_points, min_spread)
    centroid[k, 0], centroid[k, 1], centroid[k, 2] = mu, mv, mz
    if height_plane:
        residual[k] = res
        normals[k, 0], normals[k, 1], normals[k, 2] = nx, ny, nz
        valid[k] = True
        return
    if n >= min_points:  # a wall or a single scan line: the principal-component plane
        lam_min, lam_mid, x, y, zz, good = _eigen_smallest(cuu, cuv, cuz, cvv, cvz, czz)
        if good and lam_mid >= min_spread:
            residual[k] = max(lam_min, 0.0)
            normals[k, 0], normals[k, 1], normals[k, 2] = x, y, zz
            valid[k] = True
            return
    residual[k] = np.inf
    normals[k, 0] = normals[k, 1] = normals[k, 2] = np.nan
    valid[k] = False


@compiled
def fit_sums(sums: np.ndarray, min_points: int, min_spread: float
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Plane fits of m blocks from their moment sums (10, m): residual variance (m,),
    normals (m, 3), valid (m,), centroid (m, 3)
    (:func:`lidarcal_ros.core.normals.grid_planes.fit_block_planes`)."""
    m = sums.shape[1]
    residual = np.empty(m)
    normals = np.empty((m, 3))
    valid = np.empty(m, dtype=np.bool_)
    centroid = np.empty((m, 3))
    for k in range(m):
        _fit_one(sums[0, k], sums[1, k], sums[2, k], sums[3, k], sums[4, k], sums[5, k],
                 sums[6, k], sums[7, k], sums[8, k], sums[9, k], min_points, min_spread,
                 residual, normals, valid, centroid, k)
    return residual, normals, valid, centroid


#: Columns of a block table (:func:`fit_blocks`): the unit upward normal of the block's
#: plane, its offset ``normal . centroid`` (m) and its residual variance (m^2, inf without
#: a plane).
BLOCK_COLUMNS = 5

#: Columns of the block sums and fits handled at a time (:func:`fit_blocks`): their
#: transposed sums stay in the first-level cache.
_FIT_TILE = 64


@compiled
def fit_blocks(moments: np.ndarray, min_points: int, min_spread: float, first: int = 0,
               stop: int = -1) -> tuple[np.ndarray, np.ndarray]:
    """Plane fits of the 2x2 blocks anchored at every cell of a (nu, nv, 10) grid (cells
    ``[i:i+2, j:j+2]``, zero beyond the grid), as :func:`fit_sums` of their summed moments,
    flat over the cells; only those anchored in rows ``first`` to ``stop - 1`` (``stop`` -1:
    the last row) when the others are not read (a chunk's points read the blocks of their
    rows and the next ones only).

    Row by row, :data:`_FIT_TILE` columns at a time: the column sums of rows ``i, i+1``
    transposed, the block sums, the height-plane fit of every block in a loop without
    branches (the compiler vectorises it), the principal-component fallback only for the
    few blocks that need it. What is kept of a fit is what the normals read: the table is
    written once and is most of this function's memory traffic.

    Returns
    -------
    blocks : (nu * nv, BLOCK_COLUMNS) float64
        Normal (3), offset ``normal . centroid`` and residual variance of each block
        (NaN, NaN and inf without a plane; not written outside the rows fitted).
    valid : (nu * nv,) bool
        The block has a plane (False outside the rows fitted).
    """
    nu, nv = moments.shape[0], moments.shape[1]
    stop = nu if stop < 0 else min(stop, nu)
    tile = _FIT_TILE
    blocks = np.empty((nu * nv, BLOCK_COLUMNS))
    valid = np.zeros(nu * nv, dtype=np.bool_)
    col = np.zeros((10, tile + 1))  # column sums of rows i, i+1 (zero beyond the grid)
    box = np.empty((10, tile))
    fit = np.empty((8, tile))
    for i in range(max(first, 0), stop):
        below = i + 1 < nu
        for j0 in range(0, nv, tile):
            m = min(tile, nv - j0)
            ends_row = j0 + m >= nv
            for jj in range(m if ends_row else m + 1):
                j = j0 + jj
                if below:
                    for q in range(10):
                        col[q, jj] = moments[i, j, q] + moments[i + 1, j, q]
                else:
                    for q in range(10):
                        col[q, jj] = moments[i, j, q]
            for q in range(10):
                for jj in range(m):
                    box[q, jj] = col[q, jj] + col[q, jj + 1]
                if ends_row:
                    box[q, m - 1] = col[q, m - 1]
            for jj in range(m):
                f = _height_plane(box[0, jj], box[1, jj], box[2, jj], box[3, jj], box[4, jj],
                                  box[5, jj], box[6, jj], box[7, jj], box[8, jj], box[9, jj],
                                  min_points, min_spread)
                fit[0, jj], fit[1, jj], fit[2, jj], fit[3, jj] = f[0], f[1], f[2], f[3]
                fit[4, jj], fit[5, jj], fit[6, jj] = f[4], f[5], f[6]
                fit[7, jj] = 1.0 if f[7] else 0.0
            for jj in range(m):
                if fit[7, jj] == 0.0 and box[0, jj] >= min_points:
                    # a wall or a single scan line: the principal-component plane
                    f = _height_plane(box[0, jj], box[1, jj], box[2, jj], box[3, jj],
                                      box[4, jj], box[5, jj], box[6, jj], box[7, jj],
                                      box[8, jj], box[9, jj], min_points, min_spread)
                    lam_min, lam_mid, x, y, zz, good = _eigen_smallest(
                        f[8], f[9], f[10], f[11], f[12], f[13])
                    if good and lam_mid >= min_spread:
                        fit[0, jj], fit[1, jj], fit[2, jj] = max(lam_min, 0.0), x, y
                        fit[3, jj], fit[7, jj] = zz, 1.0
            base = i * nv + j0
            for jj in range(m):
                nx, ny, nz = fit[1, jj], fit[2, jj], fit[3, jj]
                k = base + jj
                blocks[k, 0], blocks[k, 1], blocks[k, 2] = nx, ny, nz
                blocks[k, 3] = nx * fit[4, jj] + ny * fit[5, jj] + nz * fit[6, jj]
                blocks[k, 4] = fit[0, jj]
                valid[k] = fit[7, jj] != 0.0
    return blocks, valid


@compiled
def cell_planes(residual: np.ndarray, nu: int, nv: int, first: int = 0, stop: int = -1
                ) -> tuple[np.ndarray, np.ndarray]:
    """The plane of each cell: that of the best-fitting (least residual) of the four 2x2
    blocks containing it, anchored at ``(i-1..i, j-1..j)``; ties go to the block anchored at
    the cell, then ``(i-1, j)``, ``(i, j-1)``, ``(i-1, j-1)``. Only for the cells of rows
    ``first`` to ``stop - 1`` (``stop`` -1: the last), which read the blocks anchored from
    row ``first - 1`` on; the other cells get none.

    Parameters
    ----------
    residual : (nu * nv,) float64
        Residual variance of each block's plane (inf without one): the last column of the
        block table of :func:`fit_blocks`.

    Returns
    -------
    best : (nu * nv,) int64
        The block whose plane each cell takes.
    ok : (nu * nv,) bool
        Whether the cell has a plane (finite residual).
    """
    best_block = np.empty(nu * nv, dtype=np.int64)
    ok = np.zeros(nu * nv, dtype=np.bool_)
    stop = nu if stop < 0 else min(stop, nu)
    for i in range(max(first, 0), stop):
        for j in range(nv):
            k = i * nv + j
            best = residual[k]
            a = k
            if i >= 1 and residual[k - nv] < best:
                best, a = residual[k - nv], k - nv
            if j >= 1 and residual[k - 1] < best:
                best, a = residual[k - 1], k - 1
            if i >= 1 and j >= 1 and residual[k - nv - 1] < best:
                best, a = residual[k - nv - 1], k - nv - 1
            best_block[k] = a
            ok[k] = math.isfinite(best)
    return best_block, ok


@compiled
def cells_without_plane(iu: np.ndarray, iv: np.ndarray, row0: int, col0: int, nv: int,
                        cell_ok: np.ndarray) -> np.ndarray:
    """The flat indices (ascending, once each) of the cells holding points that have no
    plane: ``np.flatnonzero(wanted & ~cell_ok)`` where
    ``wanted[(iu - row0) * nv + iv - col0] = True``, without the index temporaries.

    Parameters
    ----------
    iu, iv : (n,) int64
        Cell of each point: row ``iu - row0`` and column ``iv - col0`` of a grid of ``nv``
        columns.
    cell_ok : (nu * nv,) bool
        The cells with a plane.
    """
    size = cell_ok.shape[0]
    mark = np.zeros(size, dtype=np.bool_)
    count = 0
    for i in range(iu.shape[0]):
        k = (iu[i] - row0) * nv + iv[i] - col0
        if not cell_ok[k] and not mark[k]:
            mark[k] = True
            count += 1
    out = np.empty(count, dtype=np.int64)
    j = 0
    for k in range(size):
        if mark[k]:
            out[j] = k
            j += 1
    return out


@compiled
def point_normals(blocks: np.ndarray, valid: np.ndarray, filled: np.ndarray,
                  best: np.ndarray, cell_ok: np.ndarray, nu: int, nv: int, iu: np.ndarray,
                  iv: np.ndarray,
                  row0: int, col0: int, u: np.ndarray, v: np.ndarray, z: np.ndarray,
                  tol: float, cos_h: float, sin_h: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normal, validity and roughness of each point from the planes of the grid's cells.

    A point takes the plane of its cell unless it lies off it (distance above ``tol``) or
    the plane fits its block badly (residual variance above ``tol^2``, a cell across an
    edge); then the nearest of the planes of the nine 2x2 blocks around its cell (score:
    squared distance plus the block's residual variance; ties to the first in row order)
    if that scores better. Rough: the best score is still above ``tol^2``. The normal is
    then turned from the grid's frame to the map's (:func:`flight_to_map`).

    Parameters
    ----------
    blocks, valid : (nu * nv, BLOCK_COLUMNS) float64, (nu * nv,) bool
        The 2x2 block fits (:func:`fit_blocks`).
    filled : (f, BLOCK_COLUMNS) float64
        Planes of cells whose own blocks had none, from larger blocks around them.
    best, cell_ok : (nu * nv,) int64 and bool
        The block whose plane each cell takes, and whether it has one
        (:func:`cell_planes`); ``best - nu * nv`` is the row of ``filled`` where it is
        past the grid's blocks.
    nu, nv : int
        Grid shape.
    iu, iv : (n,) int64
        Cell of each point: row ``iu - row0``, column ``iv - col0`` of the grid.
    u, v, z : (n,) float64
    tol : float
        Edge tolerance, m.
    cos_h, sin_h : float
        Cosine and sine of the grid's heading.

    Returns
    -------
    nrm : (n, 3) float64
        Unit normals, map frame, NaN where the cell has no plane.
    ok : (n,) bool
    rough : (n,) bool
    """
    n = iu.shape[0]
    nrm = np.empty((n, 3))
    ok = np.empty(n, dtype=np.bool_)
    rough = np.zeros(n, dtype=np.bool_)
    tol2 = tol * tol
    size = nu * nv
    for p in range(n):
        i, j = iu[p] - row0, iv[p] - col0
        k = i * nv + j
        if not cell_ok[k]:
            ok[p] = False
            nrm[p, 0] = nrm[p, 1] = nrm[p, 2] = np.nan
            continue
        ok[p] = True
        a = best[k]
        plane = blocks[a] if a < size else filled[a - size]
        nx, ny, nz = plane[0], plane[1], plane[2]
        d = nx * u[p] + ny * v[p] + nz * z[p] - plane[3]
        lam = plane[4]
        if abs(d) > tol or lam > tol2:
            own = d * d + lam
            score_best = np.inf
            bx = by = bz = 0.0
            for di in range(-1, 2):
                ii = i + di
                if ii < 0 or ii >= nu:
                    continue
                for dj in range(-1, 2):
                    jj = j + dj
                    if jj < 0 or jj >= nv:
                        continue
                    b = ii * nv + jj
                    if not valid[b]:
                        continue
                    cx, cy, cz = blocks[b, 0], blocks[b, 1], blocks[b, 2]
                    dk = cx * u[p] + cy * v[p] + cz * z[p] - blocks[b, 3]
                    score = dk * dk + blocks[b, 4]
                    if score < score_best:
                        score_best, bx, by, bz = score, cx, cy, cz
            if score_best < own:
                nx, ny, nz = bx, by, bz
            rough[p] = min(score_best, own) > tol2
        nrm[p, 0] = -sin_h * nx + cos_h * ny
        nrm[p, 1] = cos_h * nx + sin_h * ny
        nrm[p, 2] = nz
    return nrm, ok, rough


@compiled
def flight_to_map(n_uvz: np.ndarray, cos_h: float, sin_h: float) -> np.ndarray:
    """Vectors from the flight frame (``u`` forward, ``v`` right, ``z`` up) to the map frame:
    ``u (-sin_h, cos_h) + v (cos_h, sin_h)``, ``z`` unchanged; (n, 3) in, new (n, 3) out."""
    n = n_uvz.shape[0]
    out = np.empty((n, 3))
    for i in range(n):
        a, b = n_uvz[i, 0], n_uvz[i, 1]
        out[i, 0] = -sin_h * a + cos_h * b
        out[i, 1] = cos_h * a + sin_h * b
        out[i, 2] = n_uvz[i, 2]
    return out


@compiled
def flight_cells(xyz: np.ndarray, cos_h: float, sin_h: float, x0: float, y0: float, z0: float,
                 inv_cell_u: float, inv_cell_v: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                            np.ndarray, np.ndarray]:
    """Flight-frame coordinates and grid cell of each finite point, in one pass
    (``finite = isfinite(x + y + z)``; ``u = -sin_h dx + cos_h dy``,
    ``v = cos_h dx + sin_h dy``, ``z - z0``; ``floor(u inv_cell_u)``,
    ``floor(v inv_cell_v)`` as int64, for the finite rows).

    Every point finite (the usual case): one pass without a branch, which the compiler runs
    several points at a time, and no index written (``index`` empty: the finite points are
    the rows of ``xyz`` in order). Otherwise the finite rows are gathered in a second pass.

    Parameters
    ----------
    xyz : (n, 3) float64
        Points, map frame, m.
    cos_h, sin_h : float
        Cosine and sine of the heading.
    x0, y0, z0 : float
        The frame's origin, map frame, m.
    inv_cell_u, inv_cell_v : float
        Inverse cell size along and across track, 1/m.

    Returns
    -------
    u, v, z : (m,) float64
        The ``m`` finite points, in order, m.
    iu, iv : (m,) int64
        Their cells.
    index : (m,) int64, or (0,) when ``m == n``
        Their rows in ``xyz``.
    bounds : (4,) int64
        ``iu.min(), iu.max(), iv.min(), iv.max()`` (meaningless when ``m == 0``).
    """
    n = xyz.shape[0]
    u = np.empty(n)
    v = np.empty(n)
    z = np.empty(n)
    iu = np.empty(n, dtype=np.int64)
    iv = np.empty(n, dtype=np.int64)
    r_lo, r_hi = np.iinfo(np.int64).max, np.iinfo(np.int64).min
    c_lo, c_hi = r_lo, r_hi
    bad = 0
    for i in range(n):
        px, py, pz = xyz[i, 0], xyz[i, 1], xyz[i, 2]
        finite = math.isfinite(px + py + pz)
        bad += 0 if finite else 1
        dx = px - x0
        dy = py - y0
        pu = -sin_h * dx + cos_h * dy
        pv = cos_h * dx + sin_h * dy
        # (a non-finite row's cell is never used: kept finite for the conversion)
        cu = int(math.floor(pu * inv_cell_u if finite else 0.0))
        cv = int(math.floor(pv * inv_cell_v if finite else 0.0))
        u[i], v[i], z[i] = pu, pv, pz - z0
        iu[i], iv[i] = cu, cv
        r_lo, r_hi = min(r_lo, cu), max(r_hi, cu)
        c_lo, c_hi = min(c_lo, cv), max(c_hi, cv)
    if bad == 0:
        bounds = np.array([r_lo, r_hi, c_lo, c_hi], dtype=np.int64)
        return u, v, z, iu, iv, np.empty(0, dtype=np.int64), bounds
    index = np.empty(n - bad, dtype=np.int64)
    r_lo, r_hi = np.iinfo(np.int64).max, np.iinfo(np.int64).min
    c_lo, c_hi = r_lo, r_hi
    m = 0
    for i in range(n):
        px, py, pz = xyz[i, 0], xyz[i, 1], xyz[i, 2]
        if not math.isfinite(px + py + pz):
            continue
        cu, cv = iu[i], iv[i]
        u[m], v[m], z[m] = u[i], v[i], z[i]
        iu[m], iv[m], index[m] = cu, cv, i
        r_lo, r_hi = min(r_lo, cu), max(r_hi, cu)
        c_lo, c_hi = min(c_lo, cv), max(c_hi, cv)
        m += 1
    bounds = np.array([r_lo, r_hi, c_lo, c_hi], dtype=np.int64)
    return u[:m], v[:m], z[:m], iu[:m], iv[:m], index, bounds


@compiled
def centred_sums(moments: np.ndarray, cells: np.ndarray, radius: int) -> np.ndarray:
    """Moment sums (10, m) of the ``(2 radius + 1)^2`` blocks of cells centred on the flat
    cell indices ``cells`` of a (nu, nv, 10) grid (zero beyond it), the block's cells added
    row by row, column by column.

    Parameters
    ----------
    moments : (nu, nv, 10) float64
    cells : (m,) int64
        Flat indices ``row * nv + column``.
    radius : int
    """
    nu, nv = moments.shape[0], moments.shape[1]
    m = cells.shape[0]
    sums = np.zeros((10, m))
    for k in range(m):
        ci = cells[k] // nv
        cj = cells[k] - ci * nv
        for di in range(-radius, radius + 1):
            ii = ci + di
            if ii < 0 or ii >= nu:
                continue
            for dj in range(-radius, radius + 1):
                jj = cj + dj
                if jj < 0 or jj >= nv:
                    continue
                for q in range(10):
                    sums[q, k] += moments[ii, jj, q]
    return sums


__all__ = ["BLOCK_COLUMNS", "accumulate_moments", "cell_planes", "cells_without_plane",
           "centred_sums", "fit_blocks", "fit_sums", "flight_cells", "flight_to_map",
           "point_normals", "smallest_eigen_many"]
