"""The radiometric section of ``lidarcal report``: variance-to-mean ratio per slope class, maps."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from lidarcal_ros.core.qa.swath_differences import BlockGrid
from lidarcal_ros.core.radiometry import describe_alpha
from lidarcal_ros.io.report.content import MapRaster, RadiometrySection, SlopeClass
from lidarcal_ros.pipeline.correction.apply import CorrectionSettings
from lidarcal_ros.pipeline.correction.reflectance import TargetMeasurement
from lidarcal_ros.pipeline.report.block import BlockPass, cell_sums

__all__ = [
    "MIN_CLASS_POINTS", "SLOPE_CLASS_EDGES_DEG", "mean_raster", "radiometry_section",
    "slope_class_statistics",
]

#: Bounds of the terrain-slope classes of the variance-to-mean ratio, degrees.
SLOPE_CLASS_EDGES_DEG: tuple[float, ...] = (0.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0, 90.0)
#: Fewest points for a class's statistics (NaN below).
MIN_CLASS_POINTS = 30


def slope_class_statistics(
    slope_deg: np.ndarray,
    intensity: np.ndarray,
    reflectance: np.ndarray,
    edges_deg: Sequence[float] = SLOPE_CLASS_EDGES_DEG,
    *,
    min_points: int = MIN_CLASS_POINTS,
) -> list[SlopeClass]:
    """Variance-to-mean ratio of intensity and of reflectance per terrain-slope class.

    The variance-to-mean ratio depends on the unit; so that the two compare, the reflectance
    is put on the intensity's scale first: multiplied by one factor for every class, the
    ratio of their means over all the points given.

    Parameters
    ----------
    slope_deg : (n,) float
        Terrain slope of each point, degrees from horizontal.
    intensity, reflectance : (n,) float
        Recorded intensity and reflectance of the same points, finite.
    edges_deg : sequence of float
        Class bounds, degrees, increasing; a class is ``[lo, hi)`` (the last also holds
        ``hi``).
    min_points : int
        Classes with fewer points get NaN statistics.

    Returns
    -------
    list of SlopeClass
        One per class, in order.
    """
    edges = np.asarray(edges_deg, dtype=np.float64)
    which = np.clip(np.searchsorted(edges, slope_deg, side="right") - 1, 0, edges.size - 2)
    mean_refl = float(np.mean(reflectance, dtype=np.float64)) if reflectance.size else 0.0
    scale = float(np.mean(intensity, dtype=np.float64)) / mean_refl if mean_refl > 0 else 1.0
    out = []
    for k in range(edges.size - 1):
        members = which == k
        n = int(np.count_nonzero(members))
        stats = [math.nan] * 4
        if n >= min_points:
            inten = np.asarray(intensity[members], dtype=np.float64)
            refl = np.asarray(reflectance[members], dtype=np.float64)
            stats = [_variance_to_mean_ratio(inten), _variance_to_mean_ratio(refl * scale),
                     float(inten.mean()), float(refl.mean())]
        out.append(SlopeClass(float(edges[k]), float(edges[k + 1]), n, *stats))
    return out


def _variance_to_mean_ratio(values: np.ndarray) -> float:
    """Variance (ddof 1) over mean; NaN for a non-positive mean."""
    mean = float(values.mean())
    return float(values.var(ddof=1)) / mean if mean > 0 else math.nan


def mean_raster(xy: np.ndarray, values: np.ndarray, *, x0: float, y0: float, cell_m: float,
                shape: tuple[int, int]) -> MapRaster:
    """Mean of ``values`` per cell of a grid (rows south to north).

    Parameters
    ----------
    xy : (n, 2) float
        Map-frame positions, metres.
    values : (n,) float
        Finite values.
    x0, y0 : float
        South-west corner of the grid, metres.
    cell_m : float
        Cell size, metres.
    shape : (int, int)
        ``(rows, columns)``; points outside are ignored.
    """
    sums, counts = cell_sums(xy, values, x0=x0, y0=y0, cell_m=cell_m, shape=shape)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(counts > 0, sums / counts, np.nan)
    return MapRaster(mean.reshape(shape), x0, y0, cell_m)


def radiometry_section(
    passed: BlockPass,
    settings: CorrectionSettings,
    map_grid: BlockGrid,
    target: TargetMeasurement | None = None,
) -> RadiometrySection | None:
    """Slope statistics of intensity and reflectance, and their maps (None where no strip
    carries intensity)."""
    if not passed.n_radiometric or not passed.map_sums[2].any():
        return None
    x0, y0, cell, shape = map_grid.x0, map_grid.y0, map_grid.cell_m, (map_grid.ny, map_grid.nx)
    with np.errstate(invalid="ignore", divide="ignore"):
        count = passed.map_sums[2]
        maps = [np.where(count > 0, passed.map_sums[row] / count, np.nan).reshape(shape)
                for row in (0, 1)]
    slope, intensity, reflectance = (np.concatenate(parts) if parts else np.zeros(0)
                                     for parts in (passed.slope, passed.intensity,
                                                   passed.reflectance))
    classes = slope_class_statistics(slope, intensity, reflectance)
    model = settings.radiometry
    notes = [f"Atmosphere: {describe_alpha(model)}."]
    if target is not None:
        notes.append(f"The {target.describe()}.")
    notes.append("Left out of the slope statistics: points not corrected, without a surface "
                 "normal or intensity, and rough neighbourhoods (edges, vegetation), whose "
                 "slope and incidence are uncertain. Terrain slope from the grid normals of "
                 "the radiometric correction.")
    return RadiometrySection(
        slope_classes=classes, intensity=MapRaster(maps[0], x0, y0, cell),
        reflectance=MapRaster(maps[1], x0, y0, cell), n_points=passed.n_radiometric,
        n_used=int(slope.size), meaning=model.meaning, unit=model.unit, notes=notes)

