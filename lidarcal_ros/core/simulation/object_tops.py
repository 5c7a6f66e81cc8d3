"""Conservative rasters of the highest object top, for finding where a ray may meet an object.

Local coordinates; a fine raster and a coarse one whose maxima are cached.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy.ndimage import maximum_filter

#: The height of a cell no object touches, metres (below any terrain).
NO_OBJECT = np.float32(-1.0e9)
#: Fine cells per coarse cell, along each axis.
COARSE_FACTOR = 32

#: Footprints of a kind of object: centres x and y, the half-side of a square holding each,
#: and each one's top, local coordinates, metres (four (n,) arrays).
Footprints = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


class ObjectTops:
    """The highest object top around any position (module docstring).

    Parameters
    ----------
    extent : (xmin, xmax, ymin, ymax)
        Where objects may stand, local coordinates, metres.
    footprints : sequence of Footprints
        Every object, each kind's arrays in turn; a cell takes ``top + 0.01`` of every square
        (enlarged by 1 cm) that touches it.

    Attributes
    ----------
    res : float
        Side of a fine cell, metres.
    max_top : float
        The highest top of all (with the 1 cm margin), metres; ``-inf`` without objects.
    """

    def __init__(self, extent: Sequence[float], footprints: Sequence[Footprints]) -> None:
        xmin, xmax, ymin, ymax = extent
        area = (xmax - xmin) * (ymax - ymin)
        res = max(1.0, math.sqrt(area / 1.2e7))
        self.res = res
        self.x0, self.y0 = xmin - 2.0 * res, ymin - 2.0 * res
        nx = int(math.ceil((xmax - xmin) / res)) + 4
        ny = int(math.ceil((ymax - ymin) / res)) + 4
        m = np.full((ny, nx), NO_OBJECT, dtype=np.float32)
        for cxs, cys, radii, tops in footprints:
            for x, y, r, z in zip(cxs, cys, radii + 0.01, tops):
                i0 = max(int((x - r - self.x0) // res), 0)
                i1 = min(int((x + r - self.x0) // res) + 1, nx)
                j0 = max(int((y - r - self.y0) // res), 0)
                j1 = min(int((y + r - self.y0) // res) + 1, ny)
                sub = m[j0:j1, i0:i1]
                np.maximum(sub, np.float32(z + 0.01), out=sub)
        self._fine = maximum_filter(m, size=3, mode="constant", cval=NO_OBJECT)
        # coarse raster: max over blocks of the fine (undilated) raster
        f = COARSE_FACTOR
        self._coarse_res = f * res
        cny, cnx = -(-ny // f), -(-nx // f)
        pad = np.full((cny * f, cnx * f), NO_OBJECT, dtype=np.float32)
        pad[:ny, :nx] = m
        self._coarse = pad.reshape(cny, f, cnx, f).max(axis=(1, 3))
        self._coarse_by_reach: dict[int, np.ndarray] = {}
        any_object = any(len(fp[0]) for fp in footprints)
        self.max_top = float(m.max()) if any_object else -math.inf

    def fine_max(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Highest object top (float32, metres) in the fine cell of each position and its
        neighbours; :data:`NO_OBJECT` off the raster."""
        ny, nx = self._fine.shape
        ix = np.floor((x - self.x0) * (1.0 / self.res)).astype(np.int64)
        iy = np.floor((y - self.y0) * (1.0 / self.res)).astype(np.int64)
        valid = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
        m = self._fine[np.clip(iy, 0, ny - 1), np.clip(ix, 0, nx - 1)]
        return np.where(valid, m, NO_OBJECT)

    def coarse_max(self, x: np.ndarray, y: np.ndarray, reach: float) -> np.ndarray:
        """Highest object top (float32, metres) within at least ``reach`` metres
        (horizontally) of each position."""
        cells = int(math.ceil(reach / self._coarse_res)) + 1
        if cells not in self._coarse_by_reach:
            self._coarse_by_reach[cells] = maximum_filter(
                self._coarse, size=2 * cells + 1, mode="constant", cval=NO_OBJECT)
        grid = self._coarse_by_reach[cells]
        ny, nx = grid.shape
        ix = np.floor((x - self.x0) / self._coarse_res).astype(np.int64)
        iy = np.floor((y - self.y0) / self._coarse_res).astype(np.int64)
        # a point outside the grid may still be near objects on its edge: clip (conservative)
        return grid[np.clip(iy, 0, ny - 1), np.clip(ix, 0, nx - 1)]


__all__ = ["COARSE_FACTOR", "NO_OBJECT", "Footprints", "ObjectTops"]
