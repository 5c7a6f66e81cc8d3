"""Local surface normals of a LiDAR strip by grid plane fits (for the incidence angle).

:func:`grid_normals` is the entry; the method, its cells and its cost: docs/correction.md,
"Surface normals". Normals in the map frame, unit length, upward (``n_z >= 0``).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from lidarcal_ros.core.normals.grid_planes import (
    block_min_spread,
    dense_grid_normals,
    dense_moment_grid,
    sparse_grid_normals,
)

logger = logging.getLogger(__name__)

#: Cell size in point spacings (along and across track each), while that stays within
#: :data:`_CELL_MAX_M`; never below :data:`_SPARSE_CELL_SPACINGS` spacings. Against the
#: simulation's truth, where points are dense (cells below a metre) blocks of some 16 points
#: give lower reflectance and incidence errors than cells of 1.5 spacings (the range noise
#: averages out; the nine-plane search keeps edges sharp), for fewer cells to bin and fit;
#: where they are sparse (cells of metres) the larger cells straddle more roof edges.
CELL_SPACINGS = 2.0
#: Cell size in point spacings where :data:`CELL_SPACINGS` would pass :data:`_CELL_MAX_M`.
_SPARSE_CELL_SPACINGS = 1.5
#: Largest cell side (m) that :data:`CELL_SPACINGS` may give.
_CELL_MAX_M = 1.0


#: Fewest points a block needs for a plane.
MIN_BLOCK_POINTS = 5

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
    u, v = flight_frame(xyz[::step], heading, float(xyz[0, 0]), float(xyz[0, 1]))
    lo, hi = np.percentile(u, [1.0, 99.0])
    lo_v, hi_v = np.percentile(v, [1.0, 99.0])
    area = max(float(hi - lo), 1e-3) * max(float(hi_v - lo_v), 1e-3)
    return math.sqrt(area / (0.98 * n))


def _cell_side(spacing: float) -> float:
    """A cell's side (m) for a point spacing (m): :data:`CELL_SPACINGS` spacings up to
    :data:`_CELL_MAX_M`, at least :data:`_SPARSE_CELL_SPACINGS` spacings."""
    return min(CELL_SPACINGS * spacing, max(_SPARSE_CELL_SPACINGS * spacing, _CELL_MAX_M))


def cell_size(
    xyz: np.ndarray, heading: float, t: np.ndarray | None = None
) -> tuple[float, float]:
    """Grid cell ``(along, across)`` in metres for a piece of strip: :data:`CELL_SPACINGS`
    spacings each, within :data:`_CELL_MAX_M` (:func:`_cell_side`).

    With the firing times ``t``, the across-track spacing is the median lateral distance
    between consecutive pulses (the in-sweep spacing) and the along-track spacing the area per
    point divided by it (the sweep spacing); their ratio is kept within 1/8..8. Without
    ``t`` (or where that fails) the cell is square, from :func:`mean_spacing`.

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
    square = (_cell_side(s), _cell_side(s))
    n = xyz.shape[0]
    if t is None or n < 20:
        return square
    m = min(n, 4 * _SPACING_SAMPLE)
    start = (n - m) // 2
    sl = slice(start, start + m)
    _, v = flight_frame(xyz[sl], heading, float(xyz[0, 0]), float(xyz[0, 1]))
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
    return _cell_side(along), _cell_side(across)


def flight_frame(
    xyz: np.ndarray, heading: float, x0: float, y0: float
) -> tuple[np.ndarray, np.ndarray]:
    """Along-track ``u`` and across-track ``v`` (right) coordinates relative to (x0, y0)."""
    c, s = math.cos(heading), math.sin(heading)
    dx = xyz[:, 0] - x0
    dy = xyz[:, 1] - y0
    u = -s * dx + c * dy
    v = c * dx + s * dy
    return u, v


def grid_normals(
    xyz: np.ndarray,
    heading: float,
    *,
    cell_m: float | tuple[float, float] | None = None,
    group: np.ndarray | None = None,
    t: np.ndarray | None = None,
    min_points: int = MIN_BLOCK_POINTS,
) -> GridNormals:
    """Upward unit normals of the surface around each point (docs/correction.md, "Surface normals").

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
    u, v = flight_frame(xyz, heading, x0, y0)
    z = xyz[:, 2] - float(xyz[0, 2])
    min_spread = block_min_spread(cell)
    moments, iu, iv = dense_moment_grid(u, v, z, cell)
    if moments is None:
        return sparse_grid_normals(u, v, z, iu, iv, heading, min_points, min_spread)
    return dense_grid_normals(moments, iu, iv, u, v, z, min_points, min_spread, heading)


def no_normals(n: int, cell: tuple[float, float] = (math.nan, math.nan)) -> GridNormals:
    """``n`` points without a normal (NaN, not valid, not rough)."""
    return GridNormals(np.full((n, 3), np.nan), np.zeros(n, dtype=bool), cell,
                       np.zeros(n, dtype=bool))


__all__ = [
    "CELL_SPACINGS",
    "MIN_BLOCK_POINTS",
    "GridNormals",
    "cell_size",
    "finite_rows",
    "flight_frame",
    "grid_normals",
    "mean_spacing",
    "no_normals",
]
