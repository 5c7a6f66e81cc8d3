"""Digital surface models for flight planning: GeoTIFF or NumPy ``.npy`` grids.

Heights in metres in the plan's map frame; the formats: docs/internals.md, "Flight planning".
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from lidarcal_ros.core.simulation.raster_terrain import RasterTerrain
from lidarcal_ros.errors import ConfigError, InputError

logger = logging.getLogger(__name__)

_PIXEL_SCALE = 33550
_TIEPOINT = 33922
_TRANSFORMATION = 34264
_GEOKEYS = 34735
_GDAL_NODATA = 42113
_RASTER_TYPE_KEY = 1025
_PIXEL_IS_POINT = 2


def read_dsm(
    path: str | os.PathLike[str],
    *,
    cell_m: float | None = None,
    north_west: tuple[float, float] | None = None,
    centre: tuple[float, float] | None = None,
) -> RasterTerrain:
    """Read a DSM (docs/internals.md, "Flight planning").

    Parameters
    ----------
    path : path-like
        ``.tif`` / ``.tiff`` (GeoTIFF) or ``.npy``.
    cell_m : float, optional
        ``.npy`` only: cell size, metres (default 1).
    north_west : (float, float), optional
        ``.npy`` only: map X of the western and Y of the northern edge, metres.
    centre : (float, float), optional
        ``.npy`` only, without ``north_west``: the grid is centred here (map frame, m).

    Raises
    ------
    InputError
        Missing or unreadable file, not a height grid, no georeference.
    ConfigError
        Georeference options that do not fit the file.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: DSM file not found")
    suffix = p.suffix.lower()
    if suffix == ".npy":
        return _read_npy(p, cell_m=cell_m, north_west=north_west, centre=centre)
    if suffix in (".tif", ".tiff"):
        if cell_m is not None or north_west is not None:
            raise ConfigError(f"{p}: a GeoTIFF carries its own georeference; drop "
                              "terrain_cell_m / terrain_origin")
        return _read_geotiff(p)
    raise InputError(f"{p}: unknown DSM format '{p.suffix}' (GeoTIFF .tif or NumPy .npy)")


def _read_npy(p: Path, *, cell_m: float | None, north_west: tuple[float, float] | None,
              centre: tuple[float, float] | None) -> RasterTerrain:
    try:
        z = np.load(p, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise InputError(f"{p}: not a NumPy array file ({exc})") from None
    if z.ndim != 2 or not np.issubdtype(z.dtype, np.number):
        raise InputError(f"{p}: expected a 2-D array of heights, got {z.dtype} {z.shape}")
    cell = 1.0 if cell_m is None else float(cell_m)
    if not cell > 0:
        raise ConfigError(f"{p}: terrain_cell_m must be positive, got {cell_m}")
    rows, cols = z.shape
    if north_west is None:
        cx, cy = centre if centre is not None else (0.0, 0.0)
        north_west = (cx - 0.5 * cols * cell, cy + 0.5 * rows * cell)
    return _terrain(p, z.astype(np.float64), north_west[0], north_west[1], cell)


def _read_geotiff(p: Path) -> RasterTerrain:
    import tifffile

    try:
        with tifffile.TiffFile(p) as tif:
            page = tif.pages[0]
            tags = page.tags  # type: ignore[union-attr]
            z = page.asarray().astype(np.float64)
            scale = tags.get(_PIXEL_SCALE)
            tie = tags.get(_TIEPOINT)
            transform = tags.get(_TRANSFORMATION)
            geokeys = tags.get(_GEOKEYS)
            nodata = tags.get(_GDAL_NODATA)
            scale_v = None if scale is None else tuple(scale.value)
            tie_v = None if tie is None else tuple(tie.value)
            transform_v = None if transform is None else tuple(transform.value)
            geokeys_v = None if geokeys is None else tuple(geokeys.value)
            nodata_v = None if nodata is None else nodata.value
    except (OSError, ValueError, IndexError, tifffile.TiffFileError) as exc:
        raise InputError(f"{p}: not a readable GeoTIFF ({exc})") from None
    if z.ndim == 3 and 1 in z.shape:
        z = z.reshape([n for n in z.shape if n != 1])
    if z.ndim != 2:
        raise InputError(f"{p}: expected one band of heights, got shape {z.shape}")
    if transform_v is not None:
        m = np.asarray(transform_v, dtype=np.float64).reshape(4, 4)
        if abs(m[0, 1]) > 1e-12 or abs(m[1, 0]) > 1e-12:
            raise InputError(f"{p}: rotated grids are not supported (ModelTransformation)")
        scale_v = (m[0, 0], -m[1, 1], 0.0)
        tie_v = (0.0, 0.0, 0.0, m[0, 3], m[1, 3], 0.0)
    if scale_v is None or tie_v is None:
        raise InputError(f"{p}: no georeference (ModelPixelScale / ModelTiepoint tags)")
    sx, sy = float(scale_v[0]), float(scale_v[1])
    if not (sx > 0 and sy > 0) or abs(sx - sy) > 1e-6 * sx:
        raise InputError(f"{p}: cells must be square, got {sx} x {sy}")
    i, j, x, y = (float(v) for v in (tie_v[0], tie_v[1], tie_v[3], tie_v[4]))
    west, north = x - i * sx, y + j * sy
    if geokeys_v is not None and _pixel_is_point(geokeys_v):
        west, north = west - 0.5 * sx, north + 0.5 * sy
    if nodata_v is not None:
        try:
            z[z == float(str(nodata_v).strip("\x00 "))] = np.nan
        except ValueError:
            logger.warning("%s: cannot read the no-data value %r; ignored", p, nodata_v)
    return _terrain(p, z, west, north, sx)


def _pixel_is_point(geokeys: tuple[int, ...]) -> bool:
    """GTRasterTypeGeoKey == RasterPixelIsPoint in a GeoKeyDirectory."""
    n = int(geokeys[3]) if len(geokeys) > 3 else 0
    for k in range(n):
        key, loc, _count, value = geokeys[4 + 4 * k: 8 + 4 * k]
        if key == _RASTER_TYPE_KEY and loc == 0:
            return int(value) == _PIXEL_IS_POINT
    return False


def _terrain(p: Path, z: np.ndarray, west: float, north: float, cell: float
             ) -> RasterTerrain:
    try:
        return RasterTerrain(z, west=west, north=north, cell_m=cell)
    except ConfigError as exc:
        raise InputError(f"{p}: {exc}") from None


__all__ = ["read_dsm"]
