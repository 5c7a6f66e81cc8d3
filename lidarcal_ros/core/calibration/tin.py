"""Triangulated irregular network (TIN) of one strip and point-to-patch matching.

Delaunay of the points' XY (docs/method.md section 6), triangulated once: later iterations move
its vertices and keep its triangles.
"""

from __future__ import annotations

import enum
import logging
from dataclasses import dataclass

import numpy as np

from lidarcal_ros.core.calibration import tin_kernels

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
        xyz = np.ascontiguousarray(xyz, dtype=np.float64)
        # Triangulate about a local origin: projected coordinates (1e5-1e6 m) would cost qhull
        # digits it needs for sub-millimetre geometry.
        self.origin = xyz.mean(axis=0)
        local = xyz - self.origin
        self.simplices, self.neighbors = delaunay(local[:, :2])
        self.quality = quality
        self.usable = self._judge(local)
        # (the locator reads the points themselves, held anyway, not a local copy)
        self._locator = GridLocator(xyz, self.simplices, self.neighbors,
                                    offset=self.origin[:2])
        logger.debug(
            "TIN of %d points: %d triangles, %.0f%% usable",
            xyz.shape[0], self.simplices.shape[0], 100.0 * self.usable.mean(),
        )

    def _judge(self, local: np.ndarray) -> np.ndarray:
        """Usable patches (and :attr:`sloped`) by the rules of :class:`TinQuality`, in one
        compiled pass (:func:`~lidarcal_ros.core.calibration.tin_kernels.tin_quality`)."""
        q = self.quality
        m = self.simplices.shape[0]
        usable = np.empty(m, dtype=bool)
        self.sloped = np.empty(m, dtype=bool)
        tin_kernels.tin_quality(
            np.ascontiguousarray(local), self.simplices, self.neighbors, float(q.max_edge_m),
            float(np.cos(np.radians(q.max_slope_deg))), float(np.cos(np.radians(q.max_bend_deg))),
            float(np.cos(np.radians(q.flat_slope_deg))), usable, self.sloped)
        return usable

    def locate(self, xy: np.ndarray, start: np.ndarray | None = None) -> np.ndarray:
        """Triangle containing each XY (map frame) in the delivered geometry, -1 outside.

        ``start``: triangles to begin the search from (e.g. a previous match), -1 for none.
        """
        return self._locator.locate(xy - self.origin[:2], start)


class TinBackend(enum.StrEnum):
    """The library that triangulates (:func:`delaunay`)."""

    #: Shewchuk's Triangle (the ``triangle`` package).
    TRIANGLE = "triangle"
    #: qhull, through scipy.
    SCIPY = "scipy"


def delaunay(xy: np.ndarray, *, backend: TinBackend | None = None
             ) -> tuple[np.ndarray, np.ndarray]:
    """Delaunay triangulation of 2-D points.

    Parameters
    ----------
    xy : (n, 2) float64
        Points, ideally about a local origin.
    backend : TinBackend or None
        None: Triangle when installed, else qhull (scipy).

    Returns
    -------
    simplices : (m, 3) int32
        Vertex indices of each triangle (duplicate points are left out of every triangle).
    neighbors : (m, 3) int32
        Triangle opposite each vertex, -1 on the hull.
    """
    if backend is TinBackend.TRIANGLE or (backend is None and _triangle is not None):
        if _triangle is None:
            raise ImportError("the 'triangle' package is not installed")
        out = _triangle.triangulate({"vertices": xy}, "Qzn")
        tris = np.asarray(out.get("triangles", np.empty((0, 3))), dtype=np.int32)
        nbrs = np.asarray(out.get("neighbors", np.empty((0, 3))), dtype=np.int32)
        return tris.reshape(-1, 3), nbrs.reshape(-1, 3)
    from scipy.spatial import Delaunay

    tri = Delaunay(xy, qhull_options="Qbb Qc Qz")
    return tri.simplices.astype(np.int32), tri.neighbors.astype(np.int32)


class GridLocator:
    """Point location in a triangulation through a uniform grid of triangle lists.

    Each triangle is listed in every cell its bounding box touches. A query walks from its
    start triangle (a previous match, or the first one listed in its cell) toward the query,
    crossing the edge with the most negative barycentric coordinate; a walk that does not
    settle falls back to testing every triangle listed in the cell. The cost per query does
    not depend on query order or on queries outside the hull
    (:func:`~lidarcal_ros.core.calibration.tin_kernels.locate_points`).

    Parameters
    ----------
    xy : (n, 2 or more) float64
        Vertices: their first two columns, less ``offset``, are the triangulation's XY.
    simplices : (m, 3) int
    neighbors : (m, 3) int
        Triangle opposite each vertex, -1 on the hull.
    offset : (2,) float64 or None
        The local origin (None: 0); queries are in the local XY.
    """

    #: Triangles whose bounding box spans more cells than this are not listed (they are far
    #: longer than the point spacing and never usable as patches).
    MAX_CELLS_PER_TRIANGLE = 64
    #: Most walking steps before falling back to a scan.
    MAX_WALK = 64

    def __init__(self, xy: np.ndarray, simplices: np.ndarray, neighbors: np.ndarray, *,
                 offset: np.ndarray | None = None) -> None:
        self.xy = np.ascontiguousarray(xy, dtype=np.float64)
        self.offset = np.zeros(2) if offset is None else \
            np.ascontiguousarray(offset, dtype=np.float64)
        self.simplices = simplices
        self.neighbors = neighbors
        size = float(np.median(tin_kernels.triangle_sizes(self.xy, self.offset, simplices))) \
            if len(simplices) else 1.0
        self.cell = max(size, 1e-3)
        x, y = self.xy[:, 0] - self.offset[0], self.xy[:, 1] - self.offset[1]  # (local)
        self.x0 = float(x.min()) if len(x) else 0.0
        self.y0 = float(y.min()) if len(y) else 0.0
        self.nx = int((x.max() - self.x0) / self.cell) + 1 if len(x) else 1
        self.ny = int((y.max() - self.y0) / self.cell) + 1 if len(y) else 1
        del x, y
        # int32 where the lists cannot outgrow it: a bounded calibration's held points lie
        # in small clusters along 30 km strips, whose grids have millions of empty cells
        most = self.MAX_CELLS_PER_TRIANGLE * len(simplices)
        self.starts = np.empty(self.nx * self.ny + 1,
                               dtype=np.int32 if most < 2**31 else np.int64)
        self.entries = tin_kernels.grid_lists(
            self.xy, self.offset, simplices, self.x0, self.y0, self.cell, self.nx, self.ny,
            self.MAX_CELLS_PER_TRIANGLE, self.starts)

    def locate(self, q: np.ndarray, start: np.ndarray | None = None) -> np.ndarray:
        """Index of the triangle containing each query point (local XY), -1 if none;
        ``start``: triangles to begin from (-1: none)."""
        out = np.empty(q.shape[0], dtype=np.int64)
        tin_kernels.locate_points(
            np.ascontiguousarray(q, dtype=np.float64),
            _NO_START if start is None else np.ascontiguousarray(start, dtype=np.int64),
            self.xy, self.offset, self.simplices, self.neighbors, self.entries, self.starts,
            self.x0, self.y0, self.cell, self.nx, self.ny, self.MAX_WALK, out)
        return out


_NO_START = np.zeros(0, dtype=np.int64)
_NO_VERTICES = np.zeros((0, 3))


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
        """The matches of the query points ``index`` selects (an index array or mask)."""
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
    delivered: np.ndarray | None = None,
    start: np.ndarray | None = None,
) -> PatchMatches:
    """Match points to the closest usable patch of a TIN (docs/method.md section 6).

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
    delivered : (n, 3) float64, optional
        Instead of ``vertex_shift``: the vertices as delivered (the shift is then computed
        at the vertices used, not held).
    """
    if vertex_shift is not None and delivered is not None:
        raise ValueError("match_to_tin: vertex_shift or delivered, not both")
    k = points.shape[0]
    out = PatchMatches(
        valid=np.zeros(k, dtype=bool),
        triangle=np.full(k, -1, dtype=np.int64),
        normal=np.zeros((k, 3)),
        weights=np.zeros((k, 3)),
        distance=np.full(k, np.nan),
    )
    # the shift as tin_kernels.shifted_queries takes it: held, or delivered - current
    shift: tuple[np.ndarray, np.ndarray] | None = None
    if delivered is not None:
        shift = (delivered, vertices)
    elif vertex_shift is not None:
        shift = (vertex_shift, _NO_VERTICES)
    for b0 in range(0, k, _MATCH_BLOCK):
        b1 = min(k, b0 + _MATCH_BLOCK)
        _match_block(points[b0:b1], tin, vertices, max_normal_distance, shift,
                     None if start is None else start[b0:b1], out, slice(b0, b1))
    return out


def _match_block(
    points: np.ndarray,
    tin: Tin,
    vertices: np.ndarray,
    max_normal_distance: float,
    shift: tuple[np.ndarray, np.ndarray] | None,
    start: np.ndarray | None,
    out: PatchMatches,
    where: slice,
) -> None:
    xy = points[:, :2]
    if shift is None:
        tri = tin.locate(xy, start)
    else:
        # Move the query into the delivered geometry by the local shift of the TIN, taken at
        # its previous match (or at a first guess), then walk from there.
        guess = np.full(xy.shape[0], -1, dtype=np.int64) if start is None else start.copy()
        fresh = guess < 0
        if fresh.any():
            guess[fresh] = tin.locate(xy[fresh])
        xy2 = tin_kernels.shifted_queries(
            np.ascontiguousarray(xy), guess, tin.simplices,
            *(np.ascontiguousarray(a, dtype=np.float64) for a in shift))
        tri = tin.locate(xy2, guess)
    n = points.shape[0]
    best_tri = np.full(n, -1, dtype=np.int64)
    best_nrm = np.zeros((n, 3))
    best_w = np.zeros((n, 3))
    best_d = np.full(n, np.nan)
    # The patch containing the point's XY settles almost every point; its three neighbours
    # are tried only where it does not qualify (foot of the normal outside it, or unusable).
    tin_kernels.best_patches(np.ascontiguousarray(points, dtype=np.float64), tri,
                             tin.simplices, tin.neighbors, tin.usable,
                             np.ascontiguousarray(vertices, dtype=np.float64),
                             float(max_normal_distance), best_tri, best_d, best_nrm, best_w)
    valid = best_tri >= 0
    out.valid[where] = valid
    out.triangle[where] = best_tri
    out.normal[where] = best_nrm
    out.weights[where] = best_w
    out.distance[where] = best_d


__all__ = ["GridLocator", "PatchMatches", "Tin", "TinBackend", "TinQuality", "delaunay",
           "match_to_tin"]
