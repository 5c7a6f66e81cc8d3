"""Compiled per-point and per-triangle loops of the calibration: the exact removal of the
biases and the laser geometry of the corrected points (:mod:`lidarcal_ros.core.model`,
:mod:`lidarcal_ros.core.geometry`), the point-to-patch design rows
(:mod:`lidarcal_ros.core.calibrate`) and the quality and point locator of a TIN
(:mod:`lidarcal_ros.core.tin`).

In numpy each of these is a dozen passes over (n, 3) or (n, 3, 3) temporaries, run on every
strip at every iteration; here each is one pass, compiled by numba (``nogil``: the
calibration runs them for several strips at once in threads). Every function states the
numpy expression it replaces and does its arithmetic in the same order, so results agree with
it to the last bits or close (transcendental functions come from libm rather than numpy's
loops): the tests hold them to 1e-9 m.

Both point-positioning models run through the same loops: a ``rotation`` with a row per
point is the rigorous model's body frame ``R_ins`` (section 10), an empty one means the level
model's ``R_kappa``, given by ``cos_kappa`` and ``sin_kappa``.
"""

from __future__ import annotations

import math

import numpy as np

from lidarcal_ros.core.jit import compiled, inlined


@inlined
def _to_body(rigorous: bool, rotation: np.ndarray, c: np.ndarray, s: np.ndarray, i: int,
             vx: float, vy: float, vz: float) -> tuple[float, float, float]:
    """``R^T v`` of point ``i`` (:meth:`~lidarcal_ros.core.geometry.LaserGeometry.to_body`)."""
    if rigorous:
        r = rotation[i]
        return (r[0, 0] * vx + r[1, 0] * vy + r[2, 0] * vz,
                r[0, 1] * vx + r[1, 1] * vy + r[2, 1] * vz,
                r[0, 2] * vx + r[1, 2] * vy + r[2, 2] * vz)
    return c[i] * vx + s[i] * vy, -s[i] * vx + c[i] * vy, vz


@inlined
def _to_map(rigorous: bool, rotation: np.ndarray, c: np.ndarray, s: np.ndarray, i: int,
            bx: float, by: float, bz: float) -> tuple[float, float, float]:
    """``R b`` of point ``i`` (:meth:`~lidarcal_ros.core.geometry.LaserGeometry.to_map`)."""
    if rigorous:
        r = rotation[i]
        return (r[0, 0] * bx + r[0, 1] * by + r[0, 2] * bz,
                r[1, 0] * bx + r[1, 1] * by + r[1, 2] * bz,
                r[2, 0] * bx + r[2, 1] * by + r[2, 2] * bz)
    return c[i] * bx - s[i] * by, s[i] * bx + c[i] * by, bz


@compiled
def exact_correction(xyz: np.ndarray, origin: np.ndarray, cos_kappa: np.ndarray,
                     sin_kappa: np.ndarray, rotation: np.ndarray, delta: np.ndarray,
                     boresight: np.ndarray, corrected: np.ndarray, shift: np.ndarray,
                     x: np.ndarray, y: np.ndarray, z: np.ndarray, beta: np.ndarray,
                     sin_beta: np.ndarray, cos_beta: np.ndarray) -> None:
    """The biases removed exactly and the laser geometry of the corrected points, in one
    pass: :func:`lidarcal_ros.core.model.correct_points_exact` followed by
    :func:`lidarcal_ros.core.geometry.geometry_at` and its :meth:`trig`.

    Per point: ``q = R^T (X_b - X_o) - d``, ``rho = q @ boresight`` (``R_B^T q``),
    ``r = hypot(rho_x, rho_z) - dr``, ``theta = atan2(-rho_x, -rho_z) / (1 + dS)``, the
    corrected point ``X_o + R (-r sin theta, rho_y, -r cos theta)``; then, seen from the same
    firing position and frame, ``(x, y, z) = R^T (X_c - X_o)`` (the level model: ``x``
    across the heading, ``z`` the height difference, ``y`` not kept), ``beta = atan(x / z)``
    and ``sin beta = -x / r``, ``cos beta = -z / r`` with ``r`` the range (``hypot(x, z)``
    level, ``|(x, y, z)|`` rigorous).

    Parameters
    ----------
    xyz, origin : (n, 3) float64
        Delivered points and their firing positions, map frame, m.
    cos_kappa, sin_kappa : (n,) float64
        The level model's heading per point (unused when ``rotation`` has a row per point).
    rotation : (n, 3, 3) or (0, 3, 3) float64
        ``R_ins`` per point (rigorous), or empty (level).
    delta : (8,) float64
        Biases, SI.
    boresight : (3, 3) float64
        :func:`~lidarcal_ros.core.model.boresight_matrix` of ``delta``.
    corrected, shift : (n, 3) float64
        Receive the corrected points and ``xyz - corrected``, m.
    x, y, z, beta, sin_beta, cos_beta : (n,) float64
        Receive the geometry of the corrected points (``y`` only for the rigorous model:
        pass an empty array for the level one).
    """
    n = xyz.shape[0]
    rigorous = rotation.shape[0] == n and n > 0
    d0, d1, d2, d6, d7 = delta[0], delta[1], delta[2], delta[6], delta[7]
    b = boresight
    for i in range(n):
        ox, oy, oz = origin[i, 0], origin[i, 1], origin[i, 2]
        qx, qy, qz = _to_body(rigorous, rotation, cos_kappa, sin_kappa, i,
                              xyz[i, 0] - ox, xyz[i, 1] - oy, xyz[i, 2] - oz)
        qx -= d0
        qy -= d1
        qz -= d2
        rx = qx * b[0, 0] + qy * b[1, 0] + qz * b[2, 0]
        ry = qx * b[0, 1] + qy * b[1, 1] + qz * b[2, 1]
        rz = qx * b[0, 2] + qy * b[1, 2] + qz * b[2, 2]
        r_true = math.hypot(rx, rz) - d6
        theta = math.atan2(-rx, -rz) / (1.0 + d7)
        mx, my, mz = _to_map(rigorous, rotation, cos_kappa, sin_kappa, i,
                             -r_true * math.sin(theta), ry, -r_true * math.cos(theta))
        cx, cy, cz = ox + mx, oy + my, oz + mz
        corrected[i, 0], corrected[i, 1], corrected[i, 2] = cx, cy, cz
        shift[i, 0] = xyz[i, 0] - cx
        shift[i, 1] = xyz[i, 1] - cy
        shift[i, 2] = xyz[i, 2] - cz
        ex, ey, ez = cx - ox, cy - oy, cz - oz
        if rigorous:
            gx, gy, gz = _to_body(True, rotation, cos_kappa, sin_kappa, i, ex, ey, ez)
            y[i] = gy
            r = math.sqrt(gx * gx + gy * gy + gz * gz)
        else:
            gx, gz = ex * cos_kappa[i] + ey * sin_kappa[i], ez
            r = math.hypot(gx, gz)
        x[i] = gx
        z[i] = gz
        beta[i] = math.atan(gx / gz)
        inv_r = 1.0 / r
        sin_beta[i] = -gx * inv_r
        cos_beta[i] = -gz * inv_r


@compiled
def add_normal_rows(normal: np.ndarray, index: np.ndarray, weight: np.ndarray,
                    x: np.ndarray, z: np.ndarray, beta: np.ndarray, sin_beta: np.ndarray,
                    cos_beta: np.ndarray, cos_kappa: np.ndarray, sin_kappa: np.ndarray,
                    rotation: np.ndarray, out: np.ndarray) -> None:
    """``out += weight * n^T A`` of point ``index[i]`` of a strip for each observation ``i``
    (:func:`lidarcal_ros.core.model.geometry_normal_rows` of ``geometry.take(index)``, times
    the weights): the normal turned into the body frame, ``n_b = R^T n``, and the row
    ``n_b^T C`` of :func:`~lidarcal_ros.core.model.body_normal_rows`.

    Parameters
    ----------
    normal : (k, 3) float64
        Unit normals, map frame.
    index : (k,) int64
        The strip's point of each observation.
    weight : (k,) float64
        Factor of each row (empty: 1).
    x, z, beta, sin_beta, cos_beta, cos_kappa, sin_kappa : (n,) float64; rotation : (n, 3, 3)
        The strip's geometry (rotation empty for the level model).
    out : (k, 8) float64
        Rows to add to.
    """
    k = normal.shape[0]
    rigorous = rotation.shape[0] == x.shape[0] and x.shape[0] > 0
    weighted = weight.shape[0] == k
    for i in range(k):
        p = index[i]
        nr, nf, nu = _to_body(rigorous, rotation, cos_kappa, sin_kappa, p,
                              normal[i, 0], normal[i, 1], normal[i, 2])
        xp, zp = x[p], z[p]
        lean = zp * nr - xp * nu
        row = (nr, nf, nu, -zp * nf, lean, xp * nf, -sin_beta[p] * nr - cos_beta[p] * nu,
               beta[p] * lean)
        if weighted:
            w = weight[i]
            for j in range(8):
                out[i, j] += w * row[j]
        else:
            for j in range(8):
                out[i, j] += row[j]


@compiled
def tin_quality(local: np.ndarray, simplices: np.ndarray, neighbors: np.ndarray,
                max_edge_m: float, min_cos_slope: float, cos_bend: float, cos_flat: float,
                usable: np.ndarray, sloped: np.ndarray) -> None:
    """Which triangles may serve as patches, and which are clearly sloped
    (:meth:`lidarcal_ros.core.tin.Tin._judge`).

    Usable: the longest horizontal edge at most ``max_edge_m``, the upward unit normal's
    ``z`` at least ``min_cos_slope``, and the normal within the bend of every neighbour's
    (``n . n_neighbour >= cos_bend``). Sloped: the triangle and every neighbour steeper than
    the flat limit (``n_z < cos_flat``), and no hull edge. Normals as
    :func:`~lidarcal_ros.core.tin.triangle_normals` (zero for a degenerate triangle).

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


@compiled
def triangle_boxes(xy: np.ndarray, simplices: np.ndarray) -> np.ndarray:
    """Bounding box of each triangle, ``(m, 4)``: x min, y min, x max, y max (local XY)."""
    m = simplices.shape[0]
    box = np.empty((m, 4))
    for t in range(m):
        a, b, c = simplices[t, 0], simplices[t, 1], simplices[t, 2]
        box[t, 0] = min(xy[a, 0], xy[b, 0], xy[c, 0])
        box[t, 1] = min(xy[a, 1], xy[b, 1], xy[c, 1])
        box[t, 2] = max(xy[a, 0], xy[b, 0], xy[c, 0])
        box[t, 3] = max(xy[a, 1], xy[b, 1], xy[c, 1])
    return box


@compiled
def grid_lists(simplices: np.ndarray, box: np.ndarray, x0: float, y0: float, cell: float,
               nx: int, ny: int, max_cells: int, starts: np.ndarray) -> np.ndarray:
    """The triangle lists of a uniform grid (:class:`lidarcal_ros.core.tin.GridLocator`).

    Each triangle whose bounding box spans at most ``max_cells`` cells is listed in every
    cell the box touches (cell ``(floor((x - x0) / cell), floor((y - y0) / cell))``, index
    ``ix * ny + iy``); the lists are in triangle order, what a stable sort of the cells of
    every listing gives.

    Parameters
    ----------
    simplices : (m, 3) int
    box : (m, 4) float64
        :func:`triangle_boxes`.
    starts : (nx * ny + 1,) int64
        Receives the start of each cell's list in the returned entries.

    Returns
    -------
    (e,) int32
        The lists, cell after cell.
    """
    m = simplices.shape[0]
    n_cells = nx * ny
    counts = np.zeros(n_cells + 1, np.int64)
    span = np.empty((m, 4), np.int64)
    for t in range(m):
        ix0 = np.int64((box[t, 0] - x0) // cell)
        iy0 = np.int64((box[t, 1] - y0) // cell)
        ix1 = np.int64((box[t, 2] - x0) // cell)
        iy1 = np.int64((box[t, 3] - y0) // cell)
        span[t, 0], span[t, 1], span[t, 2], span[t, 3] = ix0, iy0, ix1, iy1
        if (ix1 - ix0 + 1) * (iy1 - iy0 + 1) <= max_cells:
            for cy in range(iy0, iy1 + 1):
                for cx in range(ix0, ix1 + 1):
                    counts[cx * ny + cy + 1] += 1
    for c in range(n_cells):
        counts[c + 1] += counts[c]
    starts[:] = counts
    fill = counts[:n_cells].copy()
    entries = np.empty(counts[n_cells], np.int32)
    for t in range(m):
        ix0, iy0, ix1, iy1 = span[t, 0], span[t, 1], span[t, 2], span[t, 3]
        if (ix1 - ix0 + 1) * (iy1 - iy0 + 1) > max_cells:
            continue
        for cy in range(iy0, iy1 + 1):
            for cx in range(ix0, ix1 + 1):
                c = cx * ny + cy
                entries[fill[c]] = t
                fill[c] += 1
    return entries


@inlined
def _barycentric(xy: np.ndarray, simplices: np.ndarray, t: int, qx: float, qy: float
                 ) -> tuple[float, float]:
    """``(l1, l2) = inv @ (q - a)`` of a query in triangle ``t``: ``a`` its first vertex,
    ``inv`` the inverse of the columns ``b - a``, ``c - a`` (a zero determinant taken as
    infinite). The same operations as the transforms numpy precomputed for every triangle:
    computed where needed, they cost no memory (96 bytes a triangle)."""
    p, q, r = simplices[t, 0], simplices[t, 1], simplices[t, 2]
    ax, ay = xy[p, 0], xy[p, 1]
    m00, m10 = xy[q, 0] - ax, xy[q, 1] - ay
    m01, m11 = xy[r, 0] - ax, xy[r, 1] - ay
    det = m00 * m11 - m01 * m10
    if det == 0:
        det = math.inf
    d0, d1 = qx - ax, qy - ay
    l1 = (m11 / det) * d0 + (-m01 / det) * d1
    l2 = (-m10 / det) * d0 + (m00 / det) * d1
    return l1, l2


@compiled
def locate_points(q: np.ndarray, start: np.ndarray, xy: np.ndarray, simplices: np.ndarray,
                  neighbors: np.ndarray, entries: np.ndarray, starts: np.ndarray, x0: float,
                  y0: float, cell: float, nx: int, ny: int, max_steps: int,
                  out: np.ndarray) -> None:
    """The triangle containing each query (:meth:`lidarcal_ros.core.tin.GridLocator.locate`),
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
    xy : (n, 2) float64; simplices, neighbors : (m, 3) int
        The triangulation.
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
            l1, l2 = _barycentric(xy, simplices, t, qx, qy)
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
            l1, l2 = _barycentric(xy, simplices, tri, qx, qy)
            if l1 >= -1e-12 and l2 >= -1e-12 and 1.0 - l1 - l2 >= -1e-12:
                out[i] = tri
                break


@compiled
def shifted_queries(q: np.ndarray, triangle: np.ndarray, simplices: np.ndarray,
                    vertex_shift: np.ndarray) -> np.ndarray:
    """Queries moved by the mean XY shift of the vertices of their triangle (where it is
    >= 0): ``q + vertex_shift[simplices[triangle]].mean(axis=1)[:, :2]``
    (:func:`lidarcal_ros.core.tin.match_to_tin`)."""
    out = q.copy()
    for i in range(q.shape[0]):
        t = triangle[i]
        if t < 0:
            continue
        a, b, c = simplices[t, 0], simplices[t, 1], simplices[t, 2]
        out[i, 0] += (vertex_shift[a, 0] + vertex_shift[b, 0] + vertex_shift[c, 0]) / 3.0
        out[i, 1] += (vertex_shift[a, 1] + vertex_shift[b, 1] + vertex_shift[c, 1]) / 3.0
    return out


__all__ = ["add_normal_rows", "exact_correction", "grid_lists", "locate_points",
           "shifted_queries", "tin_quality", "triangle_boxes"]
