"""Local surface normals of a LiDAR strip by grid plane fits (for the incidence angle).

Per-point k-nearest-neighbour searches are too slow for a stream of millions of points per
second, so the neighbourhood is a grid: the points are binned into square cells of about 1.5
point spacings in a frame aligned with the flight line (``u`` along, ``v`` across, metres), the
first and second moments of each cell are summed with ``np.bincount``, and a plane is fitted
(principal component analysis, closed-form 3x3 eigen-decomposition) to every 2x2 block of
cells. Each cell takes the normal of the most planar of the four blocks that contain it (the
smallest residual variance), so a cell beside a roof ridge or a building edge takes the block
lying on its own side where there is one; cells whose four blocks are all degenerate (fewer than
``min_points`` points, or all on one scan line) fall back to the 3x3 block centred on them, and
failing that get no normal (NaN). Every point takes the normal of its cell.

Cost: ten ``bincount`` passes over the points and a few dozen array operations over the cells
(about one cell per 2.25 points). Tree crowns, whose bumps are smaller than the blocks, get
the normal of the block they fall in: irregular, as the surface is.

Normals are returned in the map frame, unit length, oriented upward (``n_z >= 0``).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

logger = logging.getLogger(__name__)

#: Cell size in mean point spacings.
CELL_SPACINGS = 1.5
#: Fewest points a block needs for a plane.
MIN_BLOCK_POINTS = 5
#: Largest number of grid cells per point before the dense grid is replaced by a compact one.
_MAX_CELLS_PER_POINT = 4.0
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
    cell_m : float
        Cell size used, metres (NaN if none could be chosen).
    """

    normals: np.ndarray
    valid: np.ndarray
    cell_m: float


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
    c, s = math.cos(heading), math.sin(heading)
    out = np.empty_like(n_uvz)
    # map = u * (-s, c) + v * (c, s)
    out[:, 0] = -s * n_uvz[:, 0] + c * n_uvz[:, 1]
    out[:, 1] = c * n_uvz[:, 0] + s * n_uvz[:, 1]
    out[:, 2] = n_uvz[:, 2]
    return out


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
    p1 = cxy * cxy + cxz * cxz + cyz * cyz
    q = (cxx + cyy + czz) * (1.0 / 3.0)
    a = cxx - q
    b = cyy - q
    c = czz - q
    p = np.sqrt((a * a + b * b + c * c + 2.0 * p1) * (1.0 / 6.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        # det((C - qI) / p) / 2, clipped into the arccos domain.
        det = a * (b * c - cyz * cyz) - cxy * (cxy * c - cyz * cxz) + cxz * (cxy * cyz - b * cxz)
        r = det * (0.5 / (p * p * p))
        np.clip(r, -1.0, 1.0, out=r)
        phi = np.arccos(r)
        phi *= 1.0 / 3.0
        lam_max = q + 2.0 * p * np.cos(phi)
        lam_min = q + 2.0 * p * np.cos(phi + 2.0 * math.pi / 3.0)
        lam_mid = 3.0 * q - lam_max - lam_min
        # Eigenvector of lam_min: the largest cross product of two rows of (C - lam_min I),
        # rows r0 = (d0, cxy, cxz), r1 = (cxy, d1, cyz), r2 = (cxz, cyz, d2).
        d0 = cxx - lam_min
        d1 = cyy - lam_min
        d2 = czz - lam_min
        vec = np.empty((cxx.shape[0], 3))
        vx = cxy * cyz - cxz * d1  # r0 x r1
        vy = cxz * cxy - d0 * cyz
        vz = d0 * d1 - cxy * cxy
        best_n = vx * vx + vy * vy + vz * vz
        vec[:, 0], vec[:, 1], vec[:, 2] = vx, vy, vz
        for wx, wy, wz in (
            (cxy * d2 - cxz * cyz, cxz * cxz - d0 * d2, d0 * cyz - cxy * cxz),  # r0 x r2
            (d1 * d2 - cyz * cyz, cyz * cxz - cxy * d2, cxy * cyz - d1 * cxz),  # r1 x r2
        ):
            nn = wx * wx + wy * wy + wz * wz
            take = nn > best_n
            vec[take, 0], vec[take, 1], vec[take, 2] = wx[take], wy[take], wz[take]
            best_n = np.where(take, nn, best_n)
        norm = np.sqrt(best_n)
        ok = (norm > 0) & (p > 0) & np.isfinite(norm)
        scale = 1.0 / norm
        scale[vec[:, 2] < 0] *= -1.0
        vec *= scale[:, None]
    return lam_min, lam_mid, vec, ok


def _box_sums(moments: np.ndarray, size: int) -> np.ndarray:
    """Sums over ``size x size`` blocks of a (k, nu, nv) stack of cell grids, anchored at each
    cell (block ``[i:i+size, j:j+size]``; zero beyond the grid)."""
    k, nu, nv = moments.shape
    acc = np.zeros((k, nu + size - 1, nv + size - 1))
    for di in range(size):
        for dj in range(size):
            acc[:, di:di + nu, dj:dj + nv] += moments
    return acc[:, size - 1:, size - 1:]


def _fit_sums(
    sums: np.ndarray, min_points: int, min_spread: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Plane fits to blocks given their ten moment sums (10, m).

    Returns the residual variance (``inf`` where there is no valid plane), unit upward normals
    (m, 3) and validity. Only blocks with at least ``min_points`` points are decomposed; a
    block must also spread at least ``min_spread`` (m^2, variance) in its second direction.
    """
    m = sums.shape[1]
    lam = np.full(m, np.inf)
    vec = np.full((m, 3), np.nan)
    ok = np.zeros(m, dtype=bool)
    idx = np.flatnonzero(sums[0] >= min_points)
    if idx.size == 0:
        return lam, vec, ok
    n, su, sv, sz, suu, suv, suz, svv, svz, szz = sums[:, idx]
    inv = 1.0 / n
    mu, mv, mz = su * inv, sv * inv, sz * inv
    lam_min, lam_mid, v, good = smallest_eigen(
        suu * inv - mu * mu, suv * inv - mu * mv, suz * inv - mu * mz,
        svv * inv - mv * mv, svz * inv - mv * mz, szz * inv - mz * mz)
    good &= lam_mid >= min_spread
    sel = idx[good]
    lam[sel] = np.maximum(lam_min[good], 0.0)
    vec[sel] = v[good]
    ok[sel] = True
    return lam, vec, ok


def grid_normals(
    xyz: np.ndarray,
    heading: float,
    *,
    cell_m: float | None = None,
    group: np.ndarray | None = None,
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
    cell_m : float, optional
        Cell size, metres; default ``1.5 *`` :func:`mean_spacing`.
    group : (n,) int, optional
        Points of different groups (strips) are never neighbours.
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
    finite = np.isfinite(xyz).all(axis=1)
    all_finite = bool(finite.all())
    if cell_m is None:
        spacing = mean_spacing(xyz if all_finite else xyz[finite], heading)
        cell_m = CELL_SPACINGS * spacing
    if not (math.isfinite(cell_m) and cell_m > 0):
        return GridNormals(normals, valid, math.nan)
    subsets: list[np.ndarray | None]
    if group is not None and n:
        g = np.asarray(group)
        keys = np.unique(g)
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
        nrm, ok = _fit_group(sub, heading, float(cell_m), min_points)
        nrm[~ok] = np.nan
        if idx is None:
            normals, valid = nrm, ok
        else:
            normals[idx] = nrm
            valid[idx] = ok
    return GridNormals(normals, valid, float(cell_m))


def _fit_group(
    xyz: np.ndarray, heading: float, cell: float, min_points: int
) -> tuple[np.ndarray, np.ndarray]:
    x0, y0 = float(xyz[0, 0]), float(xyz[0, 1])
    u, v = _flight_frame(xyz, heading, x0, y0)
    z = xyz[:, 2] - float(xyz[0, 2])
    fu = np.floor(u * (1.0 / cell))
    fv = np.floor(v * (1.0 / cell))
    iu0, iv0 = float(fu.min()), float(fv.min())
    iu = (fu - iu0).astype(np.int64)
    iv = (fv - iv0).astype(np.int64)
    # Coordinates relative to the grid origin keep the moments small.
    u -= iu0 * cell
    v -= iv0 * cell
    weights = (None, u, v, z, u * u, u * v, u * z, v * v, v * z, z * z)
    min_spread = (0.3 * cell) ** 2 / 3.0
    nu = int(iu.max()) + 1
    nv = int(iv.max()) + 1
    if nu * nv > _MAX_CELLS_PER_POINT * xyz.shape[0] + 1024:
        return _fit_sparse(weights, iu, iv, heading, min_points, min_spread)
    key = iu * nv + iv
    size = nu * nv
    moments = np.stack([np.bincount(key, weights=w, minlength=size) for w in weights])
    moments = moments.reshape(10, nu, nv)
    lam2, vec2, _ = _fit_sums(_box_sums(moments, 2).reshape(10, -1), min_points, min_spread)
    lam2 = lam2.reshape(nu, nv)
    vec2 = vec2.reshape(nu, nv, 3)
    # Each cell: the best of the four 2x2 blocks containing it, anchored at (i-1..i, j-1..j).
    best = lam2.copy()
    choice = np.zeros((nu, nv), dtype=np.int64)
    for code, (di, dj) in enumerate(((1, 0), (0, 1), (1, 1)), start=1):
        shifted = np.full_like(lam2, np.inf)
        shifted[di:, dj:] = lam2[:nu - di, :nv - dj]
        take = shifted < best
        best[take] = shifted[take]
        choice[take] = code
    cell_ok = np.isfinite(best)
    ci = np.arange(nu)[:, None] - np.array([0, 1, 0, 1])[choice]
    cj = np.arange(nv)[None, :] - np.array([0, 0, 1, 1])[choice]
    cell_vec = vec2[np.maximum(ci, 0), np.maximum(cj, 0)]
    need = (moments[0] > 0) & ~cell_ok
    if need.any():
        # 3x3 blocks centred on the occupied cells that still lack a plane.
        ni, nj = np.nonzero(need)
        sums3 = np.zeros((10, ni.size))
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                ii, jj = ni + di, nj + dj
                inside = (ii >= 0) & (ii < nu) & (jj >= 0) & (jj < nv)
                sums3[:, inside] += moments[:, ii[inside], jj[inside]]
        _, vec3, ok3 = _fit_sums(sums3, min_points, min_spread)
        cell_vec[ni[ok3], nj[ok3]] = vec3[ok3]
        cell_ok[ni[ok3], nj[ok3]] = True
    ok = cell_ok.reshape(-1)[key]
    nl = cell_vec.reshape(-1, 3)[key]
    return _to_map(nl, heading), ok


def _fit_sparse(
    weights: tuple[np.ndarray | None, ...], iu: np.ndarray, iv: np.ndarray, heading: float,
    min_points: int, min_spread: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Like the dense path, for point sets whose grid would be mostly empty: the occupied
    cells are compacted first (``np.unique``) and neighbours found by binary search."""
    nv = int(iv.max()) + 3
    key = (iu + 1) * nv + (iv + 1)
    cells, inverse = np.unique(key, return_inverse=True)
    inverse = inverse.reshape(-1)
    m = cells.size
    sums = np.stack([np.bincount(inverse, weights=w, minlength=m) for w in weights])

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
        lam, vec, ok = _fit_sums(block(offs), min_points, min_spread)
        take = ok & (lam < best)
        best[take] = lam[take]
        best_vec[take] = vec[take]
    cell_ok = np.isfinite(best)
    if not cell_ok.all():
        offs = [(a, b) for a in (-1, 0, 1) for b in (-1, 0, 1)]
        _, vec, ok = _fit_sums(block(offs), min_points, min_spread)
        fill = ~cell_ok & ok
        best_vec[fill] = vec[fill]
        cell_ok |= fill
    return _to_map(best_vec[inverse], heading), cell_ok[inverse]
