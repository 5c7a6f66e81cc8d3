"""Compiled loops of a TIN: triangle quality, the locating grid, point location and matching.

The rules of compiled loops: docs/internals.md, "Compiled loops".
"""

from __future__ import annotations

import math

import numpy as np

from lidarcal_ros.core.jit import compiled, inlined


@compiled
def tin_quality(local: np.ndarray, simplices: np.ndarray, neighbors: np.ndarray,
                max_edge_m: float, min_cos_slope: float, cos_bend: float, cos_flat: float,
                usable: np.ndarray, sloped: np.ndarray) -> None:
    """Which triangles may serve as patches, and which are clearly sloped
    (:meth:`lidarcal_ros.core.calibration.tin.Tin._judge`).

    Usable: the longest horizontal edge at most ``max_edge_m``, the upward unit normal's
    ``z`` at least ``min_cos_slope``, and the normal within the bend of every neighbour's
    (``n . n_neighbour >= cos_bend``). Sloped: the triangle and every neighbour steeper than
    the flat limit (``n_z < cos_flat``), and no hull edge. Normals as
    :func:`~lidarcal_ros.core.calibration.tin.triangle_normals` (zero for a degenerate triangle).

    Parameters
    ----------
    local : (n, 3) float64
        Vertices about the TIN's origin, m.
    simplices, neighbors : (m, 3) int
    usable, sloped : (m,) bool
        Receive the verdicts.
    """
    m = simplices.shape[0]
    nrm = np.empty((m, 3))
    for t in range(m):
        a0, a1, a2 = simplices[t, 0], simplices[t, 1], simplices[t, 2]
        longest = 0.0
        for e in range(3):
            p = simplices[t, e]
            q = simplices[t, (e + 1) % 3]
            dx = local[q, 0] - local[p, 0]
            dy = local[q, 1] - local[p, 1]
            longest = max(longest, math.sqrt(dx * dx + dy * dy))
        e1x = local[a1, 0] - local[a0, 0]
        e1y = local[a1, 1] - local[a0, 1]
        e1z = local[a1, 2] - local[a0, 2]
        e2x = local[a2, 0] - local[a0, 0]
        e2y = local[a2, 1] - local[a0, 1]
        e2z = local[a2, 2] - local[a0, 2]
        nx = e1y * e2z - e1z * e2y
        ny = e1z * e2x - e1x * e2z
        nz = e1x * e2y - e1y * e2x
        length = math.sqrt(nx * nx + ny * ny + nz * nz)
        if length == 0:
            length = math.inf
        nx, ny, nz = nx / length, ny / length, nz / length
        if nz < 0:
            nx, ny, nz = -nx, -ny, -nz
        nrm[t, 0], nrm[t, 1], nrm[t, 2] = nx, ny, nz
        usable[t] = longest <= max_edge_m and nz >= min_cos_slope
        sloped[t] = nz < cos_flat
    for t in range(m):
        for k in range(3):
            nb = neighbors[t, k]
            if nb < 0:
                sloped[t] = False
                continue
            dot = nrm[t, 0] * nrm[nb, 0] + nrm[t, 1] * nrm[nb, 1] + nrm[t, 2] * nrm[nb, 2]
            if not dot >= cos_bend:
                usable[t] = False
            if not nrm[nb, 2] < cos_flat:
                sloped[t] = False


@inlined
def _box(xy: np.ndarray, off: np.ndarray, simplices: np.ndarray, t: int
         ) -> tuple[float, float, float, float]:
    """Bounding box of triangle ``t``: x min, y min, x max, y max (local XY: ``xy - off``)."""
    a, b, c = simplices[t, 0], simplices[t, 1], simplices[t, 2]
    ax, bx, cx = xy[a, 0] - off[0], xy[b, 0] - off[0], xy[c, 0] - off[0]
    ay, by, cy = xy[a, 1] - off[1], xy[b, 1] - off[1], xy[c, 1] - off[1]
    return min(ax, bx, cx), min(ay, by, cy), max(ax, bx, cx), max(ay, by, cy)


@compiled
def triangle_sizes(xy: np.ndarray, off: np.ndarray, simplices: np.ndarray) -> np.ndarray:
    """The larger side of each triangle's bounding box, ``(m,)``, m (vertices ``xy - off``:
    see :func:`grid_lists`)."""
    m = simplices.shape[0]
    size = np.empty(m)
    for t in range(m):
        x0, y0, x1, y1 = _box(xy, off, simplices, t)
        size[t] = max(x1 - x0, y1 - y0)
    return size


@inlined
def _cells_of(xy: np.ndarray, off: np.ndarray, simplices: np.ndarray, t: int, x0: float,
              y0: float, cell: float) -> tuple[np.int64, np.int64, np.int64, np.int64]:
    """First and last grid column and row triangle ``t``'s bounding box touches."""
    bx0, by0, bx1, by1 = _box(xy, off, simplices, t)
    return (np.int64((bx0 - x0) // cell), np.int64((by0 - y0) // cell),
            np.int64((bx1 - x0) // cell), np.int64((by1 - y0) // cell))


@compiled
def grid_lists(xy: np.ndarray, off: np.ndarray, simplices: np.ndarray, x0: float, y0: float,
               cell: float, nx: int, ny: int, max_cells: int, starts: np.ndarray
               ) -> np.ndarray:
    """The triangle lists of a uniform grid
    (:class:`lidarcal_ros.core.calibration.tin.GridLocator`).

    Each triangle whose bounding box spans at most ``max_cells`` cells is listed in every
    cell the box touches (cell ``(floor((x - x0) / cell), floor((y - y0) / cell))``, index
    ``ix * ny + iy``); the lists are in triangle order, what a stable sort of the cells of
    every listing gives. The boxes are computed in each of the two passes rather than held
    (64 bytes a triangle, 128 with their cells: a large TIN's biggest temporaries).

    Parameters
    ----------
    xy : (n, 2 or more) float64; off : (2,) float64
        Vertices, m: their local XY is ``xy[:, :2] - off`` (computed where used: a copy
        would cost 16 bytes a point for as long as the grid is held).
    simplices : (m, 3) int
    starts : (nx * ny + 1,) int32 or int64
        Receives the start of each cell's list in the returned entries.

    Returns
    -------
    (e,) int32
        The lists, cell after cell.
    """
    m = simplices.shape[0]
    n_cells = nx * ny
    counts = starts  # (counted in place: a long strip's grid has millions of cells)
    counts[:] = 0
    for t in range(m):
        ix0, iy0, ix1, iy1 = _cells_of(xy, off, simplices, t, x0, y0, cell)
        if (ix1 - ix0 + 1) * (iy1 - iy0 + 1) <= max_cells:
            for cy in range(iy0, iy1 + 1):
                for cx in range(ix0, ix1 + 1):
                    counts[cx * ny + cy + 1] += 1
    for c in range(n_cells):
        counts[c + 1] += counts[c]
    fill = counts[:n_cells].copy()
    entries = np.empty(counts[n_cells], np.int32)
    for t in range(m):
        ix0, iy0, ix1, iy1 = _cells_of(xy, off, simplices, t, x0, y0, cell)
        if (ix1 - ix0 + 1) * (iy1 - iy0 + 1) > max_cells:
            continue
        for cy in range(iy0, iy1 + 1):
            for cx in range(ix0, ix1 + 1):
                c = cx * ny + cy
                entries[fill[c]] = t
                fill[c] += 1
    return entries


@inlined
def _barycentric(xy: np.ndarray, off: np.ndarray, simplices: np.ndarray, t: int, qx: float,
                 qy: float) -> tuple[float, float]:
    """``(l1, l2) = inv @ (q - a)`` of a query in triangle ``t``: ``a`` its first vertex,
    ``inv`` the inverse of the columns ``b - a``, ``c - a`` (a zero determinant taken as
    infinite). The same operations as the transforms numpy precomputed for every triangle:
    computed where needed, they cost no memory (96 bytes a triangle)."""
    p, q, r = simplices[t, 0], simplices[t, 1], simplices[t, 2]
    ax, ay = xy[p, 0] - off[0], xy[p, 1] - off[1]
    m00, m10 = (xy[q, 0] - off[0]) - ax, (xy[q, 1] - off[1]) - ay
    m01, m11 = (xy[r, 0] - off[0]) - ax, (xy[r, 1] - off[1]) - ay
    det = m00 * m11 - m01 * m10
    if det == 0:
        det = math.inf
    d0, d1 = qx - ax, qy - ay
    l1 = (m11 / det) * d0 + (-m01 / det) * d1
    l2 = (-m10 / det) * d0 + (m00 / det) * d1
    return l1, l2


@compiled
def locate_points(q: np.ndarray, start: np.ndarray, xy: np.ndarray, off: np.ndarray,
                  simplices: np.ndarray, neighbors: np.ndarray, entries: np.ndarray,
                  starts: np.ndarray, x0: float, y0: float, cell: float, nx: int, ny: int,
                  max_steps: int, out: np.ndarray) -> None:
    """The triangle containing each query
    (:meth:`lidarcal_ros.core.calibration.tin.GridLocator.locate`),
    -1 outside.

    A query outside the grid (or not finite) is outside. Otherwise the walk starts at its
    ``start`` triangle where that is given (``start`` has a row per query and the row is
    >= 0), else at the first triangle listed in its cell (none listed: outside), and steps
    toward the query: the barycentric coordinates ``(1 - l1 - l2, l1, l2)`` all at least
    ``-1e-12``: found; otherwise it crosses the edge opposite the most negative one (the
    first of equals, as ``np.argmin``), and past the hull the query is outside. A walk not
    settled within ``max_steps`` (degenerate) falls back to testing every triangle listed in
    the query's cell, in order (the first whose coordinates are all at least ``-1e-12``).

    Parameters
    ----------
    q : (k, 2) float64
        Queries, the triangulation's local XY.
    start : (k,) or (0,) int64
    xy : (n, 2 or more) float64; off : (2,) float64; simplices, neighbors : (m, 3) int
        The triangulation (its vertices ``xy[:, :2] - off``).
    entries, starts, x0, y0, cell, nx, ny
        The grid (:func:`grid_lists`).
    out : (k,) int64
        Receives the triangles.
    """
    k = q.shape[0]
    use_start = start.shape[0] == k
    for i in range(k):
        out[i] = -1
        qx, qy = q[i, 0], q[i, 1]
        if not (math.isfinite(qx) and math.isfinite(qy)):
            continue
        fx = math.floor((qx - x0) / cell)
        fy = math.floor((qy - y0) / cell)
        if not (0 <= fx < nx and 0 <= fy < ny):
            continue
        c = np.int64(fx) * ny + np.int64(fy)
        t = -1
        if use_start and start[i] >= 0:
            t = start[i]
        elif starts[c + 1] > starts[c]:
            t = entries[starts[c]]
        if t < 0:
            continue
        settled = False
        for _ in range(max_steps):
            l1, l2 = _barycentric(xy, off, simplices, t, qx, qy)
            worst, low = 0, 1.0 - l1 - l2
            if l1 < low:
                worst, low = 1, l1
            if l2 < low:
                worst, low = 2, l2
            if low >= -1e-12:
                out[i] = t
                settled = True
                break
            t = neighbors[t, worst]
            if t < 0:  # stepped out of the hull: outside
                settled = True
                break
        if settled:
            continue
        for e in range(starts[c], starts[c + 1]):  # rare: a degenerate walk
            tri = entries[e]
            l1, l2 = _barycentric(xy, off, simplices, tri, qx, qy)
            if l1 >= -1e-12 and l2 >= -1e-12 and 1.0 - l1 - l2 >= -1e-12:
                out[i] = tri
                break


@compiled
def shifted_queries(q: np.ndarray, triangle: np.ndarray, simplices: np.ndarray,
                    shift: np.ndarray, current: np.ndarray) -> np.ndarray:
    """Queries moved by the mean XY shift of the vertices of their triangle (where it is
    >= 0): ``q + vertex_shift[simplices[triangle]].mean(axis=1)[:, :2]``
    (:func:`lidarcal_ros.core.calibration.tin.match_to_tin`), ``vertex_shift`` being
    ``shift`` where ``current`` is empty, else ``shift - current`` (``shift`` then the
    delivered vertices, ``current`` the corrected ones: the shift of the vertices used
    only)."""
    out = q.copy()
    difference = current.shape[0] > 0
    for i in range(q.shape[0]):
        t = triangle[i]
        if t < 0:
            continue
        a, b, c = simplices[t, 0], simplices[t, 1], simplices[t, 2]
        for j in range(2):
            sa, sb, sc = shift[a, j], shift[b, j], shift[c, j]
            if difference:
                sa, sb, sc = sa - current[a, j], sb - current[b, j], sc - current[c, j]
            out[i, j] += (sa + sb + sc) / 3.0
    return out


@compiled
def best_patches(points: np.ndarray, tri: np.ndarray, simplices: np.ndarray,
                 neighbors: np.ndarray, usable: np.ndarray, vertices: np.ndarray,
                 max_normal_distance: float, best_tri: np.ndarray, best_d: np.ndarray,
                 best_nrm: np.ndarray, best_w: np.ndarray) -> None:
    """Point-to-patch matching of :func:`lidarcal_ros.core.calibration.tin.match_to_tin`: per point,
    the triangle ``tri`` containing its XY, and only where that one does not qualify its three
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


__all__ = ["best_patches", "grid_lists", "locate_points", "shifted_queries", "tin_quality",
           "triangle_sizes"]
