"""Compiled per-point and per-cell loops of the core: the grid normals
(:mod:`lidarcal_ros.core.normals`), the trajectory windows and laser geometry of each point
(:func:`lidarcal_ros.core.local_trajectory.laser_geometry`), eq. [13]
(:func:`lidarcal_ros.core.model.point_offsets`) and the rows of a corrected cloud
(:func:`lidarcal_ros.pipeline.correction.build_corrected`).

numpy spends most of their time streaming temporaries through memory: ten weighted
``bincount`` passes per binning, a copy of the grid per block sum, a handful of gathers,
(n, 3) intermediates and masks per point. These loops do the same arithmetic in one pass each,
compiled by numba (``nopython``, ``nogil``: threads of the correction run them in parallel),
cached on disk next to this module (or in numba's user cache where that is read-only). The
busiest are written so that the compiler can vectorise them (no branch, indices counted from
a block's start): the arithmetic of several points at a time in one register, the same
operations in the same order, hence the same results.

Every function states the numpy expression it replaces; the arithmetic is done in the same
order, so results agree with it to the last bits or close (transcendental functions come from
libm rather than numpy's SIMD loops).

Frames: ``u`` along track, ``v`` across track (right), ``z`` up, metres, relative to the
grid's origin; a moment grid is ``(rows, columns, 10)``, the sums ``n, u, v, z, uu, uv, uz,
vv, vz, zz`` of a cell side by side, and a lone set of sums is a ``(10,)`` column.
"""

from __future__ import annotations

import math

import numpy as np

from lidarcal_ros.core.attitude import pose_on_segment, segment_spline
from lidarcal_ros.core.flags import (
    FLAG_GRAZING,
    FLAG_NO_INTENSITY,
    FLAG_NO_NORMAL,
    FLAG_NOT_CORRECTED,
    FLAG_ROUGH,
)
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


@compiled
def _fit_one(n: float, su: float, sv: float, sz: float, suu: float, suv: float, suz: float,
             svv: float, svz: float, szz: float, min_points: int, min_spread: float,
             residual: np.ndarray, normals: np.ndarray, valid: np.ndarray,
             centroid: np.ndarray, k: int) -> None:
    """Plane fit of one block from its ten moment sums into row ``k`` of the outputs
    (``normals._fit_sums`` has the method)."""
    inv = 1.0 / n
    mu, mv, mz = su * inv, sv * inv, sz * inv
    cuu = suu * inv - mu * mu
    cuv = suv * inv - mu * mv
    cvv = svv * inv - mv * mv
    cuz = suz * inv - mu * mz
    cvz = svz * inv - mv * mz
    czz = szz * inv - mz * mz
    centroid[k, 0], centroid[k, 1], centroid[k, 2] = mu, mv, mz
    det = cuu * cvv - cuv * cuv
    half_tr = 0.5 * (cuu + cvv)
    lam_h = half_tr - math.sqrt(max(half_tr * half_tr - det, 0.0))
    enough = n >= min_points
    if enough and lam_h >= min_spread:
        inv_det = 1.0 / det
        b = (cvv * cuz - cuv * cvz) * inv_det
        c = (cuu * cvz - cuv * cuz) * inv_det
        norm2 = 1.0 + b * b + c * c
        scale = 1.0 / math.sqrt(norm2)
        residual[k] = max((czz - b * cuz - c * cvz) / norm2, 0.0)
        normals[k, 0], normals[k, 1], normals[k, 2] = -b * scale, -c * scale, scale
        valid[k] = True
        return
    if enough:  # a wall or a single scan line: the principal-component plane
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
    normals (m, 3), valid (m,), centroid (m, 3) (``normals._fit_sums``)."""
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
def fit_blocks(moments: np.ndarray, min_points: int, min_spread: float, first: int = 0,
               stop: int = -1) -> tuple[np.ndarray, np.ndarray]:
    """Plane fits of the 2x2 blocks anchored at every cell of a (nu, nv, 10) grid (cells
    ``[i:i+2, j:j+2]``, zero beyond the grid), as :func:`fit_sums` of their summed moments
    (``_fit_sums(_box_sums(moments, 2))``), flat over the cells; only those anchored in
    rows ``first`` to ``stop - 1`` (``stop`` -1: the last row) when the others are not read
    (a chunk's points read the blocks of their rows and the next ones only).

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


@inlined
def _laser_frame(ti: float, px: float, py: float, pz: float, w: int, t_mean: np.ndarray,
                 p_mean: np.ndarray, velocity: np.ndarray, c: float, s: float
                 ) -> tuple[float, float, float, float, float]:
    """The firing position ``p_mean + velocity (t - t_mean)`` of window ``w`` at time ``ti``
    and the point's ``x`` (across track, heading ``(c, s)``) and ``z`` from it (method.md
    section 4): ``ox, oy, oz, x, z``, m."""
    dt = ti - t_mean[w]
    ox = p_mean[w, 0] + velocity[w, 0] * dt
    oy = p_mean[w, 1] + velocity[w, 1] * dt
    oz = p_mean[w, 2] + velocity[w, 2] * dt
    return ox, oy, oz, (px - ox) * c + (py - oy) * s, pz - oz


@inlined
def _body_offset(d: tuple[float, float, float, float, float, float, float, float], x: float,
                 z: float, beta: float, sin_beta: float, cos_beta: float
                 ) -> tuple[float, float, float]:
    """``C @ delta`` of one point: the displacement the biases cause in the body frame
    (right, forward, up), m; the columns ``C`` of method.md section 10, as
    :func:`lidarcal_ros.core.model.point_offsets` documents."""
    right = d[0] + z * d[4] - sin_beta * d[6] + z * beta * d[7]
    fwd = d[1] - z * d[3] + x * d[5]
    up = d[2] - x * d[4] - cos_beta * d[6] - x * beta * d[7]
    return right, fwd, up


@inlined
def _bias_offset(d: tuple[float, float, float, float, float, float, float, float], x: float,
                 z: float, beta: float, sin_beta: float, cos_beta: float, c: float, s: float
                 ) -> tuple[float, float, float]:
    """``A @ delta`` of one point (method.md eq. [8], map frame, m): the body-frame
    displacement rotated by the heading ``(c, s)``."""
    right, fwd, up = _body_offset(d, x, z, beta, sin_beta, cos_beta)
    return c * right - s * fwd, s * right + c * fwd, up


@compiled
def bias_offsets(delta: np.ndarray, x: np.ndarray, z: np.ndarray, beta: np.ndarray,
                 cos_kappa: np.ndarray, sin_kappa: np.ndarray, sin_beta: np.ndarray,
                 cos_beta: np.ndarray, base: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """``A @ delta`` of each point (map frame, m), or ``base - A @ delta`` (eq. [13]) when
    ``base`` has a row per point (an empty ``base``: the offsets).

    The body-frame displacement (right, forward, up), rotated by kappa (method.md eq. [8]),
    or by each point's ``rotation`` (n, 3, 3; section 10) when it has a row per point, as
    :func:`lidarcal_ros.core.model.point_offsets` documents.
    """
    n = x.shape[0]
    out = np.empty((n, 3))
    d = (delta[0], delta[1], delta[2], delta[3], delta[4], delta[5], delta[6], delta[7])
    corrected = base.shape[0] == n and n > 0
    rigorous = rotation.shape[0] == n and n > 0
    for i in range(n):
        if rigorous:
            right, fwd, up = _body_offset(d, x[i], z[i], beta[i], sin_beta[i], cos_beta[i])
            r = rotation[i]
            ox = r[0, 0] * right + r[0, 1] * fwd + r[0, 2] * up
            oy = r[1, 0] * right + r[1, 1] * fwd + r[1, 2] * up
            oz = r[2, 0] * right + r[2, 1] * fwd + r[2, 2] * up
        else:
            ox, oy, oz = _bias_offset(d, x[i], z[i], beta[i], sin_beta[i], cos_beta[i],
                                      cos_kappa[i], sin_kappa[i])
        if corrected:
            out[i, 0] = base[i, 0] - ox
            out[i, 1] = base[i, 1] - oy
            out[i, 2] = base[i, 2] - oz
        else:
            out[i, 0], out[i, 1], out[i, 2] = ox, oy, oz
    return out


@compiled
def below_line(t: np.ndarray, z: np.ndarray, line_t: np.ndarray, line_z: np.ndarray,
               depth: float) -> np.ndarray:
    """``z < np.interp(t, line_t, line_z) - depth`` in one pass (points at least ``depth``
    below a piecewise-linear height, e.g. the trajectory's).

    The interpolation is numpy's, operation for operation (the value at a sample, the
    first or last height beyond the ends, ``slope (t - t_j) + z_j`` between), so the
    comparison decides alike. The previous point's interval is tried first: points come
    in time order.

    Parameters
    ----------
    t, z : (n,) float64
        Times (s) and heights (m) of the points.
    line_t, line_z : (m,) float64, m >= 1
        Sample times, increasing, and heights of the line.
    depth : float
        Least depth below the line, m.
    """
    n = t.shape[0]
    m = line_t.shape[0]
    out = np.empty(n, dtype=np.bool_)
    j = 0
    for i in range(n):
        x = t[i]
        if math.isnan(x):
            out[i] = False
            continue
        # j: the last sample at or before x (-1 before the first)
        if not (0 <= j < m - 1 and line_t[j] <= x < line_t[j + 1]):
            j = np.searchsorted(line_t, x, side="right") - 1
        if j < 0:
            h = line_z[0]
        elif j >= m - 1:
            h = line_z[m - 1]
        elif line_t[j] == x:
            h = line_z[j]
        else:
            slope = (line_z[j + 1] - line_z[j]) / (line_t[j + 1] - line_t[j])
            h = slope * (x - line_t[j]) + line_z[j]
            if math.isnan(h):
                h = slope * (x - line_t[j + 1]) + line_z[j + 1]
                if math.isnan(h) and line_z[j] == line_z[j + 1]:
                    h = line_z[j]
        out[i] = z[i] < h - depth
    return out


@compiled
def sorted_time_windows(traj_t: np.ndarray, t: np.ndarray, window_s: float, min_samples: int
                        ) -> tuple[bool, np.ndarray, np.ndarray, np.ndarray, int, int]:
    """The trajectory window of each point of a time-ordered chunk, in one merging pass.

    The window of time ``t`` holds the samples inside ``(t - window_s, t + window_s)``: from
    ``start = searchsorted(traj_t, t - window_s, "right")`` to
    ``stop = searchsorted(traj_t, t + window_s, "left")``. It serves the point when it holds
    ``min_samples`` samples and brackets ``t``
    (:func:`~lidarcal_ros.core.local_trajectory._bracketed`). Consecutive points sharing a
    window share its line fit.

    Parameters
    ----------
    traj_t : (m,) float64
        Trajectory sample times, s, increasing.
    t : (n,) float64, n >= 1
        Firing times, s.

    Returns
    -------
    in_order : bool
        False when ``t`` is not non-decreasing (or holds NaN); then nothing else is
        meaningful (use the general search).
    start, stop : (k,) int64
        The distinct windows, in order.
    window : (n,) int64
        The window of each point.
    n_bad : int
        Points whose window does not serve them.
    first_bad : int
        The first of them (-1 if none).
    """
    n = t.shape[0]
    m = traj_t.shape[0]
    window = np.empty(n, dtype=np.int64)
    start = np.empty(n, dtype=np.int64)
    stop = np.empty(n, dtype=np.int64)
    last = m - 1
    a = np.searchsorted(traj_t, t[0] - window_s, side="right")
    b = np.searchsorted(traj_t, t[0] + window_s, side="left")
    k = -1
    n_bad = 0
    first_bad = -1
    for i in range(n):
        ti = t[i]
        if not (i == 0 or ti >= t[i - 1]):  # (NaN fails too)
            return False, start[:0], stop[:0], window, 0, -1
        lo = ti - window_s
        hi = ti + window_s
        while a < m and traj_t[a] <= lo:
            a += 1
        while b < m and traj_t[b] < hi:
            b += 1
        if k < 0 or a != start[k] or b != stop[k]:
            k += 1
            start[k], stop[k] = a, b
        window[i] = k
        served = (a < b and traj_t[min(a, last)] <= ti and traj_t[max(b - 1, 0)] >= ti
                  and b - a >= min_samples)
        if not served:
            if n_bad == 0:
                first_bad = i
            n_bad += 1
    return True, start[:k + 1], stop[:k + 1], window, n_bad, first_bad


@compiled
def window_geometry(t: np.ndarray, xyz: np.ndarray, window: np.ndarray, t_mean: np.ndarray,
                    p_mean: np.ndarray, velocity: np.ndarray, kappa_w: np.ndarray,
                    cos_w: np.ndarray, sin_w: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                               np.ndarray, np.ndarray, np.ndarray]:
    """Firing position and laser-frame geometry of each point from the line fitted to its
    trajectory window (method.md section 4).

    Parameters
    ----------
    t : (n,) float64
        Firing times, s.
    xyz : (n, 3) float64
        Points, map frame, m.
    window : (n,) int64
        The window of each point.
    t_mean, p_mean, velocity : (k,), (k, 3), (k, 3) float64
        Each window's line: mean time (s), mean position (m), velocity (m/s).
    kappa_w, cos_w, sin_w : (k,) float64
        Each window's heading (rad), its cosine and sine.

    Returns
    -------
    origin : (n, 3) ``p_mean + velocity (t - t_mean)``, m
    x, z : (n,) ``(xyz - origin) . (cos kappa, sin kappa, 0)`` and the height difference, m
    kappa, cos_kappa, sin_kappa : (n,) the window's heading, its cosine and sine
    sin_beta, cos_beta : (n,) ``-x / r`` and ``-z / r`` with ``r = sqrt(x^2 + z^2)``: the
        mirror angle's sine and cosine (``z < 0``)

    (The mirror angle ``atan(x / z)`` is left to numpy, whose SIMD arctangent is several
    times faster than a scalar one.)
    """
    n = t.shape[0]
    origin = np.empty((n, 3))
    x = np.empty(n)
    z = np.empty(n)
    kappa = np.empty(n)
    cos_kappa = np.empty(n)
    sin_kappa = np.empty(n)
    sin_beta = np.empty(n)
    cos_beta = np.empty(n)
    for i in range(n):
        w = window[i]
        c, s = cos_w[w], sin_w[w]
        ox, oy, oz, xi, zi = _laser_frame(t[i], xyz[i, 0], xyz[i, 1], xyz[i, 2], w, t_mean,
                                          p_mean, velocity, c, s)
        origin[i, 0], origin[i, 1], origin[i, 2] = ox, oy, oz
        x[i], z[i] = xi, zi
        kappa[i], cos_kappa[i], sin_kappa[i] = kappa_w[w], c, s
        inv_r = 1.0 / math.sqrt(xi * xi + zi * zi)
        sin_beta[i], cos_beta[i] = -xi * inv_r, -zi * inv_r
    return origin, x, z, kappa, cos_kappa, sin_kappa, sin_beta, cos_beta


#: ``(atan(x) - x) / x^3`` as a polynomial in ``x^2`` on ``0 <= x <= tan(pi/8)`` (lowest
#: order first): a Chebyshev least-squares fit to numpy's arctan on that interval, degree 5;
#: :func:`atan_poly` is within 4e-11 rad of it everywhere (test_kernels).
_ATAN_COEFFS = (-0.33333333309346724, 0.19999982577414943, -0.14284358755605978,
                0.11074431763228341, -0.08643818118436813, 0.050907470841734664)
#: ``(asin(x) - x) / x^3`` as a polynomial in ``x^2`` on ``0 <= x <= 1/2``, fitted alike
#: (degree 6); :func:`acos_poly` is within 1e-10 rad of numpy's arccos on [0, 1].
_ASIN_COEFFS = (0.1666666667454038, 0.07499994167680879, 0.04464702851563003,
                0.03027839999860813, 0.02354782561152891, 0.010783899233701058,
                0.030712755360604242)
_TAN_PI_8 = math.tan(math.pi / 8.0)
_TAN_3PI_8 = math.tan(3.0 * math.pi / 8.0)


@inlined
def atan_poly(q: float) -> float:
    """``atan(q)`` (rad) to 4e-11 from a polynomial after the classic range reduction
    (``atan(a) = pi/4 + atan((a - 1) / (a + 1)) = pi/2 + atan(-1 / a)``): a few
    multiply-adds, where glibc's scalar arctangent costs some 12 ns a call on a 2 GHz
    machine. NaN gives NaN."""
    a = abs(q)
    base = 0.0
    x = a
    if a > _TAN_3PI_8:
        base, x = 0.5 * math.pi, -1.0 / a
    elif a > _TAN_PI_8:
        base, x = 0.25 * math.pi, (a - 1.0) / (a + 1.0)
    z = x * x
    c = _ATAN_COEFFS
    poly = c[0] + z * (c[1] + z * (c[2] + z * (c[3] + z * (c[4] + z * c[5]))))
    return math.copysign(base + (x + x * z * poly), q)


@inlined
def _asin_half(x: float) -> float:
    """``asin(x)`` for ``0 <= x <= 1/2`` (:data:`_ASIN_COEFFS`)."""
    z = x * x
    c = _ASIN_COEFFS
    poly = c[0] + z * (c[1] + z * (c[2] + z * (c[3] + z * (c[4] + z * (c[5] + z * c[6])))))
    return x + x * z * poly


@inlined
def acos_poly(c: float) -> float:
    """``acos(c)`` (rad) for ``0 <= c <= 1`` to 1e-10 (``acos c = 2 asin(sqrt((1 - c) / 2))``
    above 1/2, ``pi/2 - asin c`` below; :func:`atan_poly` says why). NaN gives NaN."""
    if c > 0.5:
        return 2.0 * _asin_half(math.sqrt((1.0 - c) * 0.5))
    return 0.5 * math.pi - _asin_half(c)


@inlined
def _level_frame(ti: float, w: int, lines: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                                 np.ndarray]
                 ) -> tuple[float, float, float, float, float, float, float, float, float,
                            float, float, float]:
    """The firing position on window ``w``'s line at time ``ti`` and ``R_kappa`` (row by
    row), in the form of :func:`lidarcal_ros.core.attitude.pose_on_segment`'s: the level
    model of method.md section 4 as a rotation like the rigorous one's."""
    t_mean, p_mean, velocity, cos_w, sin_w = lines
    dt = ti - t_mean[w]
    c, s = cos_w[w], sin_w[w]
    return (p_mean[w, 0] + velocity[w, 0] * dt, p_mean[w, 1] + velocity[w, 1] * dt,
            p_mean[w, 2] + velocity[w, 2] * dt, c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0)


#: Points per block of :func:`correct_returns`: its columns (some 40 values a point) stay
#: in the first caches between the block's loops.
_RETURNS_BLOCK = 256


@inlined
def _return_beam(px: float, py: float, pz: float, ox: float, oy: float, oz: float,
                 r00: float, r01: float, r02: float, r10: float, r11: float, r12: float,
                 r20: float, r21: float, r22: float,
                 d: tuple[float, float, float, float, float, float, float, float],
                 n0: float, n1: float, n2: float, rigorous: bool
                 ) -> tuple[float, float, float, float, float, float, float]:
    """One return from its firing point ``o`` and body frame ``R`` (row by row): ``beta``
    (NaN at or above the firing point), the corrected point (eq. [13]), the range, the scan
    angle and the incidence cosine (NaN without a normal) as :func:`correct_returns`
    documents; no branch but selects, so that a loop over it runs in vector registers."""
    dx, dy, dz = px - ox, py - oy, pz - oz
    x = r00 * dx + r10 * dy + r20 * dz
    z = r02 * dx + r12 * dy + r22 * dz
    q = x / z
    b = atan_poly(q) if z < 0.0 else np.nan
    r2 = x * x + z * z
    if rigorous:  # section 10's r = |rho_hat|; section 4 recovers no along-track part
        y = r01 * dx + r11 * dy + r21 * dz
        r2 += y * y
    inv_r = 1.0 / math.sqrt(r2)
    right, fwd, up = _body_offset(d, x, z, b, -x * inv_r, -z * inv_r)
    cx = px - (r00 * right + r01 * fwd + r02 * up)  # eq. [13]
    cy = py - (r10 * right + r11 * fwd + r12 * up)
    cz = pz - (r20 * right + r21 * fwd + r22 * up)
    # The beam from the firing point to the corrected return.
    rx, ry, rz = cx - ox, cy - oy, cz - oz
    r = math.sqrt(rx * rx + ry * ry + rz * rz)
    # the tangent's change, ``d`` in correct_returns' docstring
    dtan = (r00 * rx + r10 * ry + r20 * rz) / (r02 * rx + r12 * ry + r22 * rz) - q
    g = 1.0 / (1.0 + q * q)
    scan = b + dtan * g - q * dtan * dtan * g * g
    cos_t = abs((n0 * rx + n1 * ry + n2 * rz) * (1.0 / r))
    return b, cx, cy, cz, r, scan, 1.0 if cos_t > 1.0 else cos_t  # (NaN stays NaN)


@compiled
def correct_returns(t: np.ndarray, xyz: np.ndarray, ok: np.ndarray, window: np.ndarray,
                    rigorous: bool,
                    lines: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray],
                    poses: tuple[np.ndarray, np.ndarray, np.ndarray],
                    delta: np.ndarray, normals: np.ndarray, rough: np.ndarray,
                    intensity: np.ndarray,
                    radiometry: tuple[np.float32, np.float32, np.float32, np.float32],
                    out: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                               np.ndarray],
                    rows: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                np.ndarray]) -> None:
    """Correct each return and derive its beam quantities and reflectance, in one compiled
    call (:func:`lidarcal_ros.pipeline.correction.correct_columns`, whose module docstring gives
    the steps): the firing position and body frame of each point (a window's line and
    heading, method.md section 4, or the INS attitude interpolated between samples, section
    10, :func:`lidarcal_ros.core.attitude.interpolated_frames`), ``beta = atan(x / z)``,
    eq. [13] as :func:`bias_offsets`, then range, scan angle, incidence and
    :meth:`lidarcal_ros.core.radiometry.RadiometricModel.reflectance` (in float32, operation
    for operation) and the ``correction_flags`` bits (:mod:`lidarcal_ros.core.flags`).

    The arithmetic costs more than the memory traffic, and the libm arctangent and arc
    cosine of each point more than the rest of it. So ``beta`` and the incidence come from
    :func:`atan_poly` and :func:`acos_poly` (within 1e-10 rad; the incidence from the float64
    cosine, where a float32 one would lose up to 3e-4 rad near normal incidence), and the
    scan angle ``atan(x_c / z_c)`` of the corrected return from ``beta`` of the delivered
    one: their tangents differ by ``d``, of the order of the biases (below 1e-3), and
    ``atan(q + d) = atan(q) + d / (1 + q^2) - q d^2 / (1 + q^2)^2`` up to a ``d^3`` term
    below 1e-9 rad. The points go in blocks of :data:`_RETURNS_BLOCK`: each point's frame
    is looked up (level) or interpolated (rigorous) into columns of the block, then the
    arithmetic of the whole block runs without a branch, several points at a time in the
    processor's vector registers (:func:`_return_beam`), and the radiometry after it; the
    operations, and so the results, are those of a point at a time.

    Parameters
    ----------
    t, xyz : (n,), (n, 3) float64
        Firing times (s) and delivered points (map frame, m).
    ok : (n,) bool
        Points the trajectory serves (covered, finite, below it); the others, and any whose
        frame puts it at or above the firing point, are flagged not corrected.
    window : (m,) int64
        For each ``ok`` point in order (``m = ok.sum()``): its window (level) or the sample
        starting its trajectory segment (rigorous).
    rigorous : bool
        Which model: ``poses`` (section 10) or ``lines`` (section 4) give the frames.
    lines : (t_mean, p_mean, velocity, cos_w, sin_w)
        The windows' lines (:class:`~lidarcal_ros.core.local_trajectory.WindowLines`):
        (k,), (k, 3), (k, 3), (k,), (k,) float64.
    poses : (traj_t, traj_xyz, traj_q)
        The trajectory's samples: (s,), (s, 3), (s, 4) float64 (unit quaternions in one
        hemisphere, :class:`~lidarcal_ros.core.mission.Trajectory`).
    delta : (8,) float64
        Biases to remove (method.md order, SI).
    normals : (n, 3) float64
        Unit surface normals, map frame (NaN: none).
    rough : (n,) bool, or empty
        Uncertain normals (none when empty).
    intensity : (n,) float32, or empty
        Recorded intensity (the cloud has none when empty).
    radiometry : (c_min, c_doubt, scale, two_alpha) float32
        :meth:`~lidarcal_ros.core.radiometry.RadiometricModel.kernel_constants`.
    out : (out_xyz, range_m, incidence, scan_angle, reflectance, flags)
        Written: corrected points (n, 3) float64 (the delivered ones where not corrected),
        m; range, incidence, scan angle, reflectance (n,) float32 (m, rad, rad, the
        reflectance's unit; NaN where unknown); the ``correction_flags`` bits (n,) uint8.
        Not written with ``rows`` (may be empty then).
    rows : (out_words, in_words, x, y, z, reflectance, range, incidence, scan_angle, flags,
        tally), or ``out_words`` empty
        The corrected cloud's rows to write instead of ``out``, as
        :func:`fill_corrected_rows` writes them from ``out`` (its arguments but for the
        columns): each block of points goes from the first-level cache into its rows, not
        through ``out`` and a second pass.
    """
    out_xyz, range_m, incidence, scan_angle, reflectance, flags = out
    (out_words, in_words, x_row, y_row, z_row, refl_row, range_row, inc_row, scan_row,
     flags_row, tally) = rows
    in_rows = out_words.shape[0] == t.shape[0]
    k_words, m_words = in_words.shape[1], out_words.shape[1]
    # The tally in four interleaved sets of counts (one counter incremented point after point
    # would make each increment wait for the one before); added up at the end.
    counts = np.zeros((4, 257), dtype=np.int64)
    c_min, c_doubt, scale, two_alpha = radiometry
    traj_t, traj_xyz, traj_q = poses
    t_mean, p_mean, velocity, cos_w, sin_w = lines
    n = t.shape[0]
    nan32 = np.float32(np.nan)
    has_rough = rough.shape[0] == n
    has_intensity = intensity.shape[0] == n
    no_intensity = np.uint8(0 if has_intensity else FLAG_NO_INTENSITY)
    d = (delta[0], delta[1], delta[2], delta[3], delta[4], delta[5], delta[6], delta[7])
    size = _RETURNS_BLOCK
    # The block's columns: the point, its normal, firing point and frame (level: the
    # heading's cosine and sine in rows 9-10; rigorous: R row by row in rows 9-17), whether
    # it is served, its roughness and intensity; then what the beam gives.
    col = np.empty((18, size))
    served = np.empty(size, dtype=np.bool_)
    corrected = np.empty(size, dtype=np.bool_)
    flag_col = np.empty(size, dtype=np.uint8)
    rough_col = np.zeros(size, dtype=np.bool_)
    level_col = np.full(size, np.nan, dtype=np.float32)
    beam = np.empty((8, size))
    gain = np.empty(size, dtype=np.float32)
    current = -1
    spline = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    j = 0
    # Every point served and the level model (the usual case): a point's window is its own
    # index, and the windows come in runs of thousands of points (a window changes with each
    # trajectory sample), over which the line's parameters are constants.
    runs = not rigorous and window.shape[0] == n
    for a in range(0, n, size):
        m = min(size, n - a)
        # 1. Each point's frame (the window's line, or the attitude's cubic between the
        #    samples around it: points come in time order, a segment serves thousands).
        pts, nrm = xyz[a:a + m], normals[a:a + m]
        for k in range(m):
            col[0, k], col[1, k], col[2, k] = pts[k, 0], pts[k, 1], pts[k, 2]
            col[3, k], col[4, k], col[5, k] = nrm[k, 0], nrm[k, 1], nrm[k, 2]
        if has_rough:
            rgh = rough[a:a + m]
            for k in range(m):
                rough_col[k] = rgh[k]
        if has_intensity:
            lvl = intensity[a:a + m]
            for k in range(m):
                level_col[k] = lvl[k]
        if runs:
            for k in range(m):
                served[k] = True
            # 2. The beam of every point of the block, run by run (in vector registers).
            k0 = 0
            while k0 < m:
                w = window[a + k0]
                k1 = k0 + 1
                while k1 < m and window[a + k1] == w:
                    k1 += 1
                tm, c, s = t_mean[w], cos_w[w], sin_w[w]
                p0, p1, p2 = p_mean[w, 0], p_mean[w, 1], p_mean[w, 2]
                v0, v1, v2 = velocity[w, 0], velocity[w, 1], velocity[w, 2]
                tt, cr, br = t[a + k0:a + k1], col[:, k0:k1], beam[:, k0:k1]
                for k in range(k1 - k0):
                    dt = tt[k] - tm
                    res = _return_beam(cr[0, k], cr[1, k], cr[2, k], p0 + v0 * dt,
                                       p1 + v1 * dt, p2 + v2 * dt, c, -s, 0.0, s, c, 0.0,
                                       0.0, 0.0, 1.0, d, cr[3, k], cr[4, k], cr[5, k], False)
                    for row in range(7):
                        br[row, k] = res[row]
                    br[7, k] = acos_poly(res[6])
                k0 = k1
        else:
            for k in range(m):
                i = a + k
                served[k] = ok[i]
                if not ok[i]:
                    for row in range(6, 18):
                        col[row, k] = 0.0
                    continue
                w = window[j]
                j += 1
                if rigorous:
                    if w != current:
                        spline = segment_spline(w, traj_t, traj_q)
                        current = w
                    f = pose_on_segment(t[i], w, spline, traj_t, traj_xyz, traj_q)
                    for row in range(12):
                        col[6 + row, k] = f[row]
                else:
                    dt = t[i] - t_mean[w]
                    col[6, k] = p_mean[w, 0] + velocity[w, 0] * dt
                    col[7, k] = p_mean[w, 1] + velocity[w, 1] * dt
                    col[8, k] = p_mean[w, 2] + velocity[w, 2] * dt
                    col[9, k], col[10, k] = cos_w[w], sin_w[w]
            # 2. The beam of every point of the block (in vector registers).
            if rigorous:
                for k in range(m):
                    res = _return_beam(col[0, k], col[1, k], col[2, k], col[6, k],
                                       col[7, k], col[8, k], col[9, k], col[10, k],
                                       col[11, k], col[12, k], col[13, k], col[14, k],
                                       col[15, k], col[16, k], col[17, k], d, col[3, k],
                                       col[4, k], col[5, k], True)
                    for row in range(7):
                        beam[row, k] = res[row]
                    beam[7, k] = acos_poly(res[6])
            else:
                for k in range(m):
                    c, s = col[9, k], col[10, k]
                    res = _return_beam(col[0, k], col[1, k], col[2, k], col[6, k],
                                       col[7, k], col[8, k], c, -s, 0.0, s, c, 0.0, 0.0,
                                       0.0, 1.0, d, col[3, k], col[4, k], col[5, k], False)
                    for row in range(7):
                        beam[row, k] = res[row]
                    beam[7, k] = acos_poly(res[6])
        # 3. The two-way attenuation (libm's exponential: a call per point).
        if has_intensity:
            for k in range(m):
                gain[k] = math.exp(two_alpha * np.float32(beam[4, k]))
        # 4. Reflectance and flags (without a branch, as step 2).
        for k in range(m):
            good = served[k] and not math.isnan(beam[0, k])
            cos_t = beam[6, k]
            r32 = np.float32(beam[4, k])
            fl = no_intensity
            if math.isnan(cos_t):
                fl |= FLAG_NO_NORMAL
            uncertain = rough_col[k]
            if uncertain:
                fl |= FLAG_ROUGH
            # RadiometricModel.reflectance: the clamped cosine (NaN stays NaN), bounded
            # further where the normal is uncertain, then the radar equation.
            level = level_col[k]
            if has_intensity and not math.isfinite(level):
                fl |= FLAG_NO_INTENSITY
            cos32 = np.float32(cos_t)
            grazing = cos32 < c_min
            if has_intensity and grazing:
                fl |= FLAG_GRAZING
            cos_eff = c_min if grazing else cos32
            if (uncertain or grazing) and cos_eff < c_doubt:
                cos_eff = c_doubt
            g32 = gain[k]
            g32 *= r32
            g32 *= r32
            g32 *= scale
            g32 /= cos_eff
            g32 *= level
            gain[k] = g32 if good and has_intensity else nan32
            flag_col[k] = fl if good else FLAG_NOT_CORRECTED | no_intensity
            corrected[k] = good
        # 5. Written out (the points not corrected keep their coordinates, NaN in the derived
        #    fields): into the cloud's rows, or a field at a time.
        if in_rows:
            for k in range(m):
                i = a + k
                for word in range(k_words):
                    out_words[i, word] = in_words[i, word]
                for word in range(k_words, m_words):
                    out_words[i, word] = 0
                good = corrected[k]
                px = beam[1, k] if good else col[0, k]
                py = beam[2, k] if good else col[1, k]
                pz = beam[3, k] if good else col[2, k]
                bits = flag_col[k]
                counts[k & 3, bits] += 1
                if not (math.isfinite(px) and math.isfinite(py) and math.isfinite(pz)):
                    counts[k & 3, 256] += 1
                x_row[i], y_row[i], z_row[i] = px, py, pz
                refl_row[i] = gain[k]
                range_row[i] = np.float32(beam[4, k]) if good else nan32
                inc_row[i] = np.float32(beam[7, k]) if good else nan32
                scan_row[i] = np.float32(beam[5, k]) if good else nan32
                flags_row[i] = bits
            continue
        for k in range(m):
            good = corrected[k]
            out_xyz[a + k, 0] = beam[1, k] if good else col[0, k]
            out_xyz[a + k, 1] = beam[2, k] if good else col[1, k]
            out_xyz[a + k, 2] = beam[3, k] if good else col[2, k]
        for k in range(m):
            range_m[a + k] = np.float32(beam[4, k]) if corrected[k] else nan32
        for k in range(m):
            scan_angle[a + k] = np.float32(beam[5, k]) if corrected[k] else nan32
        for k in range(m):
            incidence[a + k] = np.float32(beam[7, k]) if corrected[k] else nan32
        for k in range(m):
            reflectance[a + k] = gain[k]
        for k in range(m):
            flags[a + k] = flag_col[k]
    if in_rows:
        for lane in range(4):
            for bits in range(257):
                tally[bits] += counts[lane, bits]


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
    index : (m,) int64
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
    index = np.empty(n, dtype=np.int64)
    r_lo, r_hi = np.iinfo(np.int64).max, np.iinfo(np.int64).min
    c_lo, c_hi = r_lo, r_hi
    m = 0
    for i in range(n):
        px, py, pz = xyz[i, 0], xyz[i, 1], xyz[i, 2]
        if not math.isfinite(px + py + pz):
            continue
        dx = px - x0
        dy = py - y0
        pu = -sin_h * dx + cos_h * dy
        pv = cos_h * dx + sin_h * dy
        cu = int(math.floor(pu * inv_cell_u))
        cv = int(math.floor(pv * inv_cell_v))
        u[m], v[m], z[m] = pu, pv, pz - z0
        iu[m], iv[m], index[m] = cu, cv, i
        r_lo, r_hi = min(r_lo, cu), max(r_hi, cu)
        c_lo, c_hi = min(c_lo, cv), max(c_hi, cv)
        m += 1
    bounds = np.array([r_lo, r_hi, c_lo, c_hi], dtype=np.int64)
    return u[:m], v[:m], z[:m], iu[:m], iv[:m], index[:m], bounds


@compiled
def fill_corrected_rows(out_words: np.ndarray, in_words: np.ndarray, x: np.ndarray,
                        y: np.ndarray, z: np.ndarray, xyz: np.ndarray, reflectance: np.ndarray,
                        range_m: np.ndarray, incidence: np.ndarray, scan_angle: np.ndarray,
                        flags: np.ndarray, reflectance_in: np.ndarray, range_in: np.ndarray,
                        incidence_in: np.ndarray, scan_angle_in: np.ndarray,
                        flags_in: np.ndarray, tally: np.ndarray) -> None:
    """Write corrected rows, one row at a time: the input row's words, zeros after them,
    then the corrected coordinates and the added fields (``rows[:, :k] = input rows;
    rows[:, k:] = 0; out[name] = column`` for each field, as numpy does it in nine passes
    over the output); and count, in the same pass, what the cloud's users ask of it
    (how many points are flagged, whether it is dense), which would otherwise take a pass
    each over the written rows.

    Parameters
    ----------
    out_words : (n, m) uint32 or uint64
        The output rows as 4- or 8-byte words (written whole).
    in_words : (n, k) of the same type, k <= m
        The input rows as words.
    x, y, z, reflectance, range_m, incidence, scan_angle, flags : (n,)
        Views of the output's fields (into ``out_words``' memory), written after the words
        of their row.
    xyz : (n, 3) float64
        Corrected coordinates, m.
    reflectance_in, range_in, incidence_in, scan_angle_in, flags_in : (n,)
        The added fields' values.
    tally : (257,) int64
        Added to: ``tally[f]``, the rows whose flags byte is ``f``
        (``np.bincount(flags_in, minlength=256)``); ``tally[256]``, the rows with a
        non-finite corrected coordinate.
    """
    n, m = out_words.shape
    k = in_words.shape[1]
    for i in range(n):
        f = flags_in[i]
        tally[f] += 1
        if not (math.isfinite(xyz[i, 0]) and math.isfinite(xyz[i, 1])
                and math.isfinite(xyz[i, 2])):
            tally[256] += 1
        for j in range(k):
            out_words[i, j] = in_words[i, j]
        for j in range(k, m):
            out_words[i, j] = 0
        x[i] = xyz[i, 0]
        y[i] = xyz[i, 1]
        z[i] = xyz[i, 2]
        reflectance[i] = reflectance_in[i]
        range_m[i] = range_in[i]
        incidence[i] = incidence_in[i]
        scan_angle[i] = scan_angle_in[i]
        flags[i] = f


@compiled
def byte_counts(values: np.ndarray) -> np.ndarray:
    """How many times each byte value occurs: ``np.bincount(values, minlength=256)`` for a
    uint8 array, in one pass and without the interpreter lock (bincount first widens the
    array to 8-byte integers).

    Parameters
    ----------
    values : (n,) uint8

    Returns
    -------
    (256,) int64
    """
    counts = np.zeros(256, dtype=np.int64)
    for i in range(values.shape[0]):
        counts[values[i]] += 1
    return counts


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


@compiled
def best_patches(points: np.ndarray, tri: np.ndarray, simplices: np.ndarray,
                 neighbors: np.ndarray, usable: np.ndarray, vertices: np.ndarray,
                 max_normal_distance: float, best_tri: np.ndarray, best_d: np.ndarray,
                 best_nrm: np.ndarray, best_w: np.ndarray) -> None:
    """Point-to-patch matching of :func:`lidarcal_ros.core.tin.match_to_tin`: per point, the
    triangle ``tri`` containing its XY, and only where that one does not qualify its three
    neighbours; of the qualifying candidates (usable, not degenerate, foot of the normal
    inside with barycentric weights of at least ``-1e-9``, ``|distance| <=
    max_normal_distance``) the first with the smallest ``|distance|`` wins.

    Each candidate's arithmetic is that of the numpy formulation it replaces, operation for
    operation, about the query point as origin: edges ``e1 = v1 - v0``, ``e2 = v2 - v0``;
    upward unit normal ``n = e1 x e2 / |e1 x e2|``; signed distance ``-(n . v0)``; foot
    ``-dist n``; barycentric weights of the foot from the Gram matrix of the edges.

    Parameters
    ----------
    points : (k, 3) float64
        Queries, current coordinates, m.
    tri : (k,) int64
        Triangle containing each query's XY in the delivered geometry, -1: none.
    simplices : (m, 3) int64; neighbors : (m, 3) int64; usable : (m,) bool
        The TIN.
    vertices : (n, 3) float64
        Its vertices, current coordinates, m.
    max_normal_distance : float
    best_tri, best_d, best_nrm, best_w : (k,), (k,), (k, 3), (k, 3)
        Receive the winning triangle (-1: none), signed distance (m), unit normal and the
        foot's barycentric weights; left as given where no candidate qualifies.
    """
    for i in range(points.shape[0]):
        first = tri[i]
        if first < 0:
            continue
        best_abs = math.inf
        for c in range(4):
            cand = first if c == 0 else neighbors[first, c - 1]
            if c == 1 and best_tri[i] >= 0:
                break  # the containing patch qualified: its neighbours are not tried
            if cand < 0 or not usable[cand]:
                continue
            a0 = simplices[cand, 0]
            a1 = simplices[cand, 1]
            a2 = simplices[cand, 2]
            ax = vertices[a0, 0] - points[i, 0]
            ay = vertices[a0, 1] - points[i, 1]
            az = vertices[a0, 2] - points[i, 2]
            e1x = (vertices[a1, 0] - points[i, 0]) - ax
            e1y = (vertices[a1, 1] - points[i, 1]) - ay
            e1z = (vertices[a1, 2] - points[i, 2]) - az
            e2x = (vertices[a2, 0] - points[i, 0]) - ax
            e2y = (vertices[a2, 1] - points[i, 1]) - ay
            e2z = (vertices[a2, 2] - points[i, 2]) - az
            nx = e1y * e2z - e1z * e2y
            ny = e1z * e2x - e1x * e2z
            nz = e1x * e2y - e1y * e2x
            length = math.sqrt(nx * nx + ny * ny + nz * nz)
            if not length > 0:
                continue
            if nz < 0:
                length *= -1.0  # upward normals
            nx, ny, nz = nx / length, ny / length, nz / length
            dist = -(nx * ax + ny * ay + nz * az)
            px, py, pz = -dist * nx - ax, -dist * ny - ay, -dist * nz - az
            d00 = e1x * e1x + e1y * e1y + e1z * e1z
            d01 = e1x * e2x + e1y * e2y + e1z * e2z
            d11 = e2x * e2x + e2y * e2y + e2z * e2z
            d20 = px * e1x + py * e1y + pz * e1z
            d21 = px * e2x + py * e2y + pz * e2z
            denom = d00 * d11 - d01 * d01
            if denom == 0:
                denom = math.inf
            wv = (d11 * d20 - d01 * d21) / denom
            ww = (d00 * d21 - d01 * d20) / denom
            wu = 1.0 - wv - ww
            if not (wu >= -1e-9 and wv >= -1e-9 and ww >= -1e-9):
                continue
            if not abs(dist) <= max_normal_distance or not abs(dist) < best_abs:
                continue
            best_abs = abs(dist)
            best_tri[i] = cand
            best_d[i] = dist
            best_nrm[i, 0], best_nrm[i, 1], best_nrm[i, 2] = nx, ny, nz
            best_w[i, 0], best_w[i, 1], best_w[i, 2] = wu, wv, ww


@compiled
def all_finite3(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> bool:
    """``np.isfinite(x).all() and np.isfinite(y).all() and np.isfinite(z).all()`` in one pass
    over the rows (the fields of a structured cloud, strided), stopping at the first
    non-finite value."""
    for i in range(x.shape[0]):
        if not (math.isfinite(x[i]) and math.isfinite(y[i]) and math.isfinite(z[i])):
            return False
    return True


@inlined
def _low_high(v: float, lo: float, hi: float) -> tuple[float, float]:
    """``lo, hi`` widened to ``v`` (a NaN ``v`` leaves them), without a branch."""
    return (v if v < lo else lo), (v if v > hi else hi)


@compiled
def finite_range(values: np.ndarray) -> tuple[float, float]:
    """``(np.fmin.reduce(values), np.fmax.reduce(values))`` in one pass (a field of a
    structured cloud, strided): the least and greatest values ignoring NaN, ``(nan, nan)``
    when all are NaN or there are none. Four running extremes, not one: one is a chain of
    dependent comparisons a value long, four overlap (the node reads every cloud's times
    this way, 200 000 of them per 50 ms at 4M points/s)."""
    n = values.shape[0]
    lo0 = lo1 = lo2 = lo3 = math.inf
    hi0 = hi1 = hi2 = hi3 = -math.inf
    body = n - n % 4
    for i in range(0, body, 4):
        lo0, hi0 = _low_high(values[i], lo0, hi0)
        lo1, hi1 = _low_high(values[i + 1], lo1, hi1)
        lo2, hi2 = _low_high(values[i + 2], lo2, hi2)
        lo3, hi3 = _low_high(values[i + 3], lo3, hi3)
    for i in range(body, n):
        lo0, hi0 = _low_high(values[i], lo0, hi0)
    lo = min(min(lo0, lo1), min(lo2, lo3))
    hi = max(max(hi0, hi1), max(hi2, hi3))
    if not lo <= hi:  # nothing but NaN (an infinite value counts: inf <= inf)
        return math.nan, math.nan
    return float(lo), float(hi)


@compiled
def gather_columns(x: np.ndarray, y: np.ndarray, z: np.ndarray, t: np.ndarray,
                   intensity: np.ndarray, strip_id: np.ndarray, xyz_out: np.ndarray,
                   t_out: np.ndarray, intensity_out: np.ndarray, strip_id_out: np.ndarray
                   ) -> tuple[float, float, int]:
    """:func:`gather_xyz` plus ``t_out[:] = t``, ``intensity_out[:] = intensity`` and
    ``strip_id_out[:] = strip_id`` (each converted to the output's type), in one pass over
    the rows of a structured cloud instead of one per field. An empty ``intensity`` or
    ``strip_id`` (the cloud has none) is skipped.

    Returns
    -------
    t_lo, t_hi : float
        :func:`finite_range` of ``t``, found in the same pass.
    non_finite : int
        Rows with a non-finite ``x``, ``y``, ``z`` or ``t`` (none: the checks for them can
        be skipped).
    """
    has_intensity = intensity.shape[0] == x.shape[0]
    has_strip_id = strip_id.shape[0] == x.shape[0]
    lo = math.inf
    hi = -math.inf
    seen = False
    non_finite = 0
    for i in range(x.shape[0]):
        xi, yi, zi, ti = x[i], y[i], z[i], t[i]
        xyz_out[i, 0] = xi
        xyz_out[i, 1] = yi
        xyz_out[i, 2] = zi
        t_out[i] = ti
        if has_intensity:
            intensity_out[i] = intensity[i]
        if has_strip_id:
            strip_id_out[i] = strip_id[i]
        if ti == ti:  # (not NaN)
            seen = True
            lo = min(lo, ti)
            hi = max(hi, ti)
        if not (math.isfinite(xi) and math.isfinite(yi) and math.isfinite(zi)
                and math.isfinite(ti)):
            non_finite += 1
    if not seen:
        return math.nan, math.nan, non_finite
    return float(lo), float(hi), non_finite


@compiled
def gather_xyz(x: np.ndarray, y: np.ndarray, z: np.ndarray, out: np.ndarray) -> None:
    """``out[:, 0], out[:, 1], out[:, 2] = x, y, z`` (float64; FLOAT32 fields widened
    exactly) in one pass over the rows of a structured cloud."""
    for i in range(x.shape[0]):
        out[i, 0] = x[i]
        out[i, 1] = y[i]
        out[i, 2] = z[i]


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
