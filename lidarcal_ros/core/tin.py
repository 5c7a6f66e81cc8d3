"""Triangulated irregular network (TIN) of one strip and point-to-patch matching.

A strip's TIN is the Delaunay triangulation of its points' XY (method.md section 6). The
connectivity is computed once from the delivered coordinates: the bias corrections applied
between iterations move points by centimetres to decimetres and vary smoothly across a strip,
so the triangles stay valid and only their vertex coordinates (hence normals) are updated.
That is what keeps re-matching cheap: no triangulation is rebuilt per iteration.

Triangle quality is also judged once: a patch must be small (no long edges across data gaps),
not steeper than a wall limit, and coplanar with its neighbours, which rejects triangles across
walls, ridges, eaves and tree crowns where interpolation between vertices is not the surface.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from lidarcal_ros.core import kernels

logger = logging.getLogger(__name__)

try:  # Shewchuk's Triangle: ~10x faster than qhull on scan patterns; optional.
    import triangle as _triangle  # type: ignore[import-untyped]
except ImportError:  # pragma: no cover - exercised where the wheel is missing
    _triangle = None

#: Query points processed per block (bounds the temporaries of the point location).
_MATCH_BLOCK = 262_144


@dataclass
class TinQuality:
    """Thresholds deciding which triangles may serve as patches.

    Attributes
    ----------
    max_edge_m : float
        Longest horizontal edge, metres.
    max_slope_deg : float
        Steepest patch, degrees from horizontal.
    max_bend_deg : float
        Largest angle between a patch's normal and any neighbour's normal, degrees.
    flat_slope_deg : float
        A patch counts as sloped only if it and all its neighbours are steeper than this,
        degrees: on flat ground the vertices' noise tilts single triangles by several degrees.
    """

    max_edge_m: float = 6.0
    max_slope_deg: float = 70.0
    max_bend_deg: float = 10.0
    flat_slope_deg: float = 5.0


def triangle_normals(vertices: np.ndarray, simplices: np.ndarray) -> np.ndarray:
    """Upward unit normals of triangles.

    Parameters
    ----------
    vertices : (n, 3) float64
        Vertex coordinates (any common origin), metres.
    simplices : (m, 3) int
        Vertex indices of each triangle.

    Returns
    -------
    (m, 3) float64
        Unit normals with non-negative Z; zero vectors for degenerate triangles.
    """
    v0 = vertices[simplices[:, 0]]
    e1 = vertices[simplices[:, 1]] - v0
    e2 = vertices[simplices[:, 2]] - v0
    nrm = np.cross(e1, e2)
    length = np.linalg.norm(nrm, axis=1)
    length[length == 0] = np.inf
    nrm /= length[:, None]
    nrm[nrm[:, 2] < 0] *= -1.0
    return nrm


class Tin:
    """Delaunay TIN over one strip's XY, with per-triangle quality.

    Parameters
    ----------
    xyz : (n, 3) float64
        The strip's points as delivered, map frame, metres.
    quality : TinQuality
        Thresholds for usable patches.
    """

    def __init__(self, xyz: np.ndarray, quality: TinQuality) -> None:
        xyz = np.asarray(xyz, dtype=np.float64)
        # Triangulate about a local origin: projected coordinates (1e5-1e6 m) would cost qhull
        # digits it needs for sub-millimetre geometry.
        self.origin = xyz.mean(axis=0)
        local = xyz - self.origin
        self.simplices, self.neighbors = delaunay(local[:, :2])
        self.quality = quality
        self.usable = self._judge(local)
        self._locator = GridLocator(local[:, :2], self.simplices)
        logger.debug(
            "TIN of %d points: %d triangles, %.0f%% usable",
            xyz.shape[0], self.simplices.shape[0], 100.0 * self.usable.mean(),
        )

    def _judge(self, local: np.ndarray) -> np.ndarray:
        q = self.quality
        tri = local[self.simplices]
        edges = tri[:, [1, 2, 0], :2] - tri[:, :, :2]
        max_edge = np.sqrt((edges**2).sum(axis=2)).max(axis=1)
        nrm = triangle_normals(local, self.simplices)
        ok = (max_edge <= q.max_edge_m) & (nrm[:, 2] >= np.cos(np.radians(q.max_slope_deg)))
        cos_bend = np.cos(np.radians(q.max_bend_deg))
        cos_flat = np.cos(np.radians(q.flat_slope_deg))
        self.sloped = nrm[:, 2] < cos_flat
        for k in range(3):
            nb = self.neighbors[:, k]
            has = nb >= 0
            agree = np.ones_like(ok)
            agree[has] = (nrm[has] * nrm[nb[has]]).sum(axis=1) >= cos_bend
            ok &= agree
            self.sloped &= has
            self.sloped[has] &= nrm[nb[has], 2] < cos_flat
        return ok

    def locate(self, xy: np.ndarray, start: np.ndarray | None = None) -> np.ndarray:
        """Triangle containing each XY (map frame) in the delivered geometry, -1 outside.

        ``start``: triangles to begin the search from (e.g. a previous match), -1 for none.
        """
        return self._locator.locate(xy - self.origin[:2], self.neighbors, start)


def delaunay(xy: np.ndarray, *, backend: str = "auto") -> tuple[np.ndarray, np.ndarray]:
    """Delaunay triangulation of 2-D points.

    Parameters
    ----------
    xy : (n, 2) float64
        Points, ideally about a local origin.
    backend : ``"auto"``, ``"triangle"`` or ``"scipy"``
        ``auto`` uses Triangle when installed, else qhull (scipy).

    Returns
    -------
    simplices : (m, 3) int64
        Vertex indices of each triangle (duplicate points are left out of every triangle).
    neighbors : (m, 3) int64
        Triangle opposite each vertex, -1 on the hull.
    """
    if backend == "triangle" or (backend == "auto" and _triangle is not None):
        if _triangle is None:
            raise ImportError("the 'triangle' package is not installed")
        out = _triangle.triangulate({"vertices": xy}, "Qzn")
        tris = np.asarray(out.get("triangles", np.empty((0, 3))), dtype=np.int64)
        nbrs = np.asarray(out.get("neighbors", np.empty((0, 3))), dtype=np.int64)
        return tris.reshape(-1, 3), nbrs.reshape(-1, 3)
    from scipy.spatial import Delaunay

    tri = Delaunay(xy, qhull_options="Qbb Qc Qz")
    return tri.simplices.astype(np.int64), tri.neighbors.astype(np.int64)


class GridLocator:
    """Point location in a triangulation through a uniform grid of triangle lists.

    Each triangle is listed in every cell its bounding box touches; a query tests the few
    triangles of its cell with precomputed barycentric transforms. Unlike a walk, the cost per
    query does not depend on query order or on queries outside the hull.

    Parameters
    ----------
    xy : (n, 2) float64
        Vertices (local origin).
    simplices : (m, 3) int64
    """

    #: Triangles whose bounding box spans more cells than this are not listed (they are far
    #: longer than the point spacing and never usable as patches).
    MAX_CELLS_PER_TRIANGLE = 64

    def __init__(self, xy: np.ndarray, simplices: np.ndarray) -> None:
        tri = xy[simplices]  # (m, 3, 2)
        lo = tri.min(axis=1)
        hi = tri.max(axis=1)
        extent = hi - lo
        size = float(np.median(np.maximum(extent[:, 0], extent[:, 1]))) if len(tri) else 1.0
        self.cell = max(size, 1e-3)
        self.x0 = xy[:, 0].min() if len(xy) else 0.0
        self.y0 = xy[:, 1].min() if len(xy) else 0.0
        self.nx = int((xy[:, 0].max() - self.x0) / self.cell) + 1 if len(xy) else 1
        self.ny = int((xy[:, 1].max() - self.y0) / self.cell) + 1 if len(xy) else 1
        ix0 = ((lo[:, 0] - self.x0) // self.cell).astype(np.int64)
        iy0 = ((lo[:, 1] - self.y0) // self.cell).astype(np.int64)
        ix1 = ((hi[:, 0] - self.x0) // self.cell).astype(np.int64)
        iy1 = ((hi[:, 1] - self.y0) // self.cell).astype(np.int64)
        wx = ix1 - ix0 + 1
        wy = iy1 - iy0 + 1
        count = wx * wy
        listed = count <= self.MAX_CELLS_PER_TRIANGLE
        tri_ids = np.repeat(np.flatnonzero(listed), count[listed])
        first = np.repeat(np.cumsum(count[listed]) - count[listed], count[listed])
        k = np.arange(tri_ids.size) - first
        cx = ix0[tri_ids] + k % wx[tri_ids]
        cy = iy0[tri_ids] + k // wx[tri_ids]
        cells = cx * self.ny + cy
        order = np.argsort(cells, kind="stable")
        self.entries = tri_ids[order]
        self.starts = np.searchsorted(cells[order], np.arange(self.nx * self.ny + 1))
        # Barycentric transform: (l1, l2) = inv @ (q - a).
        a = tri[:, 0]
        m = np.stack([tri[:, 1] - a, tri[:, 2] - a], axis=2)  # columns b-a, c-a
        det = m[:, 0, 0] * m[:, 1, 1] - m[:, 0, 1] * m[:, 1, 0]
        det[det == 0] = np.inf
        self.inv = np.empty_like(m)
        self.inv[:, 0, 0] = m[:, 1, 1] / det
        self.inv[:, 0, 1] = -m[:, 0, 1] / det
        self.inv[:, 1, 0] = -m[:, 1, 0] / det
        self.inv[:, 1, 1] = m[:, 0, 0] / det
        self.a = np.ascontiguousarray(a)

    def locate(self, q: np.ndarray, neighbors: np.ndarray | None = None,
               start: np.ndarray | None = None) -> np.ndarray:
        """Index of the triangle containing each query point (local XY), -1 if none.

        With ``neighbors`` (triangle opposite each vertex), walks from a triangle listed in the
        query's cell (or from ``start`` where given and >= 0) toward the query, crossing the
        edge with the most negative barycentric coordinate: a few vectorised steps for all
        queries, whatever their order. Queries a walk does not settle fall back to testing
        every triangle listed in their cell.
        """
        if neighbors is None:
            return self._scan(q, np.arange(q.shape[0]))
        out = np.full(q.shape[0], -1, dtype=np.int64)
        ix = np.floor((q[:, 0] - self.x0) / self.cell).astype(np.int64)
        iy = np.floor((q[:, 1] - self.y0) / self.cell).astype(np.int64)
        inside = (ix >= 0) & (ix < self.nx) & (iy >= 0) & (iy < self.ny) & np.isfinite(q).all(1)
        cell = np.where(inside, ix * self.ny + iy, 0)
        has = inside & (self.starts[cell + 1] > self.starts[cell])
        tri = np.where(has, self.entries[np.minimum(self.starts[cell], self.entries.size - 1)], -1)
        if start is not None:
            tri = np.where((start >= 0) & inside, start, tri)
        unsettled = kernels.walk_to_triangles(
            np.ascontiguousarray(q, dtype=np.float64), tri.astype(np.int64, copy=False),
            self.a, self.inv, np.ascontiguousarray(neighbors, dtype=np.int64), self.MAX_WALK,
            out)
        if unsettled.size:  # rare: degenerate walks; settle them by scanning their cells
            out[unsettled] = self._scan(q[unsettled], np.arange(unsettled.size))
        return out

    #: Most walking steps before falling back to a scan.
    MAX_WALK = 64

    def _scan(self, q: np.ndarray, _: np.ndarray) -> np.ndarray:
        """Test every triangle listed in each query's cell."""
        out = np.full(q.shape[0], -1, dtype=np.int64)
        ix = np.floor((q[:, 0] - self.x0) / self.cell).astype(np.int64)
        iy = np.floor((q[:, 1] - self.y0) / self.cell).astype(np.int64)
        inside = (ix >= 0) & (ix < self.nx) & (iy >= 0) & (iy < self.ny) & np.isfinite(q).all(1)
        active = np.flatnonzero(inside)
        cell = ix[active] * self.ny + iy[active]
        start = self.starts[cell]
        count = self.starts[cell + 1] - start
        k = 0
        eps = -1e-12
        while active.size:
            more = count > k
            active, start, count = active[more], start[more], count[more]
            if not active.size:
                break
            t = self.entries[start + k]
            d = q[active] - self.a[t]
            inv = self.inv[t]
            l1 = inv[:, 0, 0] * d[:, 0] + inv[:, 0, 1] * d[:, 1]
            l2 = inv[:, 1, 0] * d[:, 0] + inv[:, 1, 1] * d[:, 1]
            hit = (l1 >= eps) & (l2 >= eps) & (1.0 - l1 - l2 >= eps)
            out[active[hit]] = t[hit]
            keep = ~hit
            active, start, count = active[keep], start[keep], count[keep]
            k += 1
        return out


@dataclass
class PatchMatches:
    """Result of matching query points to a TIN (all arrays over the query points).

    Attributes
    ----------
    valid : (k,) bool
        A usable patch was found within the normal-distance threshold.
    triangle : (k,) int64
        Patch index into ``Tin.simplices`` (-1 where invalid).
    normal : (k, 3) float64
        Upward unit normal of the patch in its current geometry.
    weights : (k, 3) float64
        Barycentric coordinates of the foot of the normal.
    distance : (k,) float64
        Signed normal distance, point minus patch, metres (along ``normal``).
    """

    valid: np.ndarray
    triangle: np.ndarray
    normal: np.ndarray
    weights: np.ndarray
    distance: np.ndarray

    def take(self, index: np.ndarray) -> PatchMatches:
        return PatchMatches(
            self.valid[index], self.triangle[index], self.normal[index],
            self.weights[index], self.distance[index],
        )


def match_to_tin(
    points: np.ndarray,
    tin: Tin,
    vertices: np.ndarray,
    *,
    max_normal_distance: float,
    vertex_shift: np.ndarray | None = None,
    start: np.ndarray | None = None,
) -> PatchMatches:
    """Match points to the closest usable patch of a TIN (method.md section 6).

    A patch qualifies if the foot of the point's normal falls inside it; of the triangle
    containing the point's XY and its three neighbours, the qualifying usable patch with the
    smallest normal distance wins, if that distance is below ``max_normal_distance``.

    Parameters
    ----------
    points : (k, 3) float64
        Query points in their current (corrected) coordinates, map frame, metres.
    tin : Tin
        The other strip's TIN (connectivity from its delivered coordinates).
    vertices : (n, 3) float64
        The TIN's vertices in their current (corrected) coordinates, map frame, metres.
    max_normal_distance : float
        Largest accepted |normal distance|, metres.
    start : (k,) int64, optional
        Triangles to begin each point's search from (its previous match, -1 for none).
    vertex_shift : (n, 3) float64, optional
        ``delivered - current`` for each vertex, used to locate queries in the delivered
        triangulation. None when ``vertices`` are the delivered coordinates.
    """
    k = points.shape[0]
    out = PatchMatches(
        valid=np.zeros(k, dtype=bool),
        triangle=np.full(k, -1, dtype=np.int64),
        normal=np.zeros((k, 3)),
        weights=np.zeros((k, 3)),
        distance=np.full(k, np.nan),
    )
    for b0 in range(0, k, _MATCH_BLOCK):
        b1 = min(k, b0 + _MATCH_BLOCK)
        _match_block(points[b0:b1], tin, vertices, max_normal_distance, vertex_shift,
                     None if start is None else start[b0:b1],
                     out, slice(b0, b1))
    return out


def _match_block(
    points: np.ndarray,
    tin: Tin,
    vertices: np.ndarray,
    max_normal_distance: float,
    vertex_shift: np.ndarray | None,
    start: np.ndarray | None,
    out: PatchMatches,
    where: slice,
) -> None:
    xy = points[:, :2]
    if vertex_shift is None:
        tri = tin.locate(xy, start)
    else:
        # Move the query into the delivered geometry by the local shift of the TIN, taken at
        # its previous match (or at a first guess), then walk from there.
        guess = np.full(xy.shape[0], -1, dtype=np.int64) if start is None else start.copy()
        fresh = guess < 0
        if fresh.any():
            guess[fresh] = tin.locate(xy[fresh])
        found = guess >= 0
        shift = vertex_shift[tin.simplices[guess[found]]].mean(axis=1)[:, :2]
        xy2 = xy.copy()
        xy2[found] += shift
        tri = tin.locate(xy2, guess)
    n = points.shape[0]
    best_tri = np.full(n, -1, dtype=np.int64)
    best_nrm = np.zeros((n, 3))
    best_w = np.zeros((n, 3))
    best_d = np.full(n, np.nan)
    # The patch containing the point's XY settles almost every point; its three neighbours
    # are tried only where it does not qualify (foot of the normal outside it, or unusable).
    kernels.best_patches(np.ascontiguousarray(points, dtype=np.float64), tri, tin.simplices,
                         tin.neighbors, tin.usable,
                         np.ascontiguousarray(vertices, dtype=np.float64),
                         float(max_normal_distance), best_tri, best_d, best_nrm, best_w)
    valid = best_tri >= 0
    out.valid[where] = valid
    out.triangle[where] = best_tri
    out.normal[where] = best_nrm
    out.weights[where] = best_w
    out.distance[where] = best_d
