"""A gridded DSM of a real site as the surface of a simulation: flight planning over the site.

:class:`RasterTerrain` is a :class:`~lidarcal_ros.core.simulation.surface.Surface` whose heights are
interpolated bilinearly between cell centres. Read one from a file with
:func:`~lidarcal_ros.io.survey.dsm.read_dsm`.
"""

from __future__ import annotations

import math

import numpy as np

from lidarcal_ros.core.simulation.surface import CLASS_REFLECTANCE, SOIL, Surface
from lidarcal_ros.errors import ConfigError


class RasterTerrain(Surface):
    """A gridded DSM (a height per cell) as the surface of a simulation: flight planning over
    the real site.

    Heights are interpolated bilinearly between cell centres (continuous, so a ray meets
    the surface once per crossing); outside the grid the edge cells continue. The surface
    is one height field: no walls, no classes (open soil, reflectance 0.3).

    Parameters
    ----------
    heights : (rows, cols) float
        Heights, metres; row 0 is the northern edge (as in a GeoTIFF); NaN cells (no data)
        take the height of the nearest valid cell.
    west, north : float
        Map X of the grid's western edge and Y of its northern edge, metres.
    cell_m : float
        Cell size, metres.
    """

    def __init__(self, heights: np.ndarray, *, west: float, north: float,
                 cell_m: float) -> None:
        z = np.asarray(heights, dtype=np.float64)
        if z.ndim != 2 or min(z.shape) < 2:
            raise ConfigError(f"DSM must be a 2-D grid of at least 2 x 2 cells, got shape "
                              f"{z.shape}")
        if not (math.isfinite(cell_m) and cell_m > 0):
            raise ConfigError(f"DSM cell size must be positive, got {cell_m}")
        valid = np.isfinite(z)
        if not valid.any():
            raise ConfigError("DSM holds no valid height")
        if not valid.all():
            from scipy.ndimage import distance_transform_edt

            nearest = distance_transform_edt(~valid, return_distances=False,
                                             return_indices=True)
            z = z[tuple(nearest)]
        self._z = z
        self._west, self._north, self._cell = float(west), float(north), float(cell_m)
        rows, cols = z.shape
        self.kind = "dsm"
        self.origin = (0.0, 0.0)
        self.extent = (self._west, self._west + cols * cell_m, self._north - rows * cell_m,
                       self._north)
        self.object_tops = None  # no objects: rays meet the height field directly
        self._z_lo, self._z_hi = float(z.min()), float(z.max())

    def _grid(self, x: np.ndarray, y: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Cell-centre index (floor) and fraction of each position, clamped to the grid."""
        rows, cols = self._z.shape
        fc = np.clip((np.asarray(x, dtype=np.float64) - self._west) / self._cell - 0.5,
                     0.0, cols - 1.000001)
        fr = np.clip((self._north - np.asarray(y, dtype=np.float64)) / self._cell - 0.5,
                     0.0, rows - 1.000001)
        c0 = fc.astype(np.int64)
        r0 = fr.astype(np.int64)
        return r0, c0, fr - r0, fc - c0

    def ground_local(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """The height interpolated bilinearly between cell centres at local (x, y) (n,), metres."""
        r0, c0, v, u = self._grid(x, y)
        z = self._z
        top = z[r0, c0] * (1 - u) + z[r0, c0 + 1] * u
        bottom = z[r0 + 1, c0] * (1 - u) + z[r0 + 1, c0 + 1] * u
        return top * (1 - v) + bottom * v

    def _ground_grad_local(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r0, c0, v, u = self._grid(x, y)
        z = self._z
        dz_du = (z[r0, c0 + 1] - z[r0, c0]) * (1 - v) + (z[r0 + 1, c0 + 1] - z[r0 + 1, c0]) * v
        dz_dv = (z[r0 + 1, c0] - z[r0, c0]) * (1 - u) + (z[r0 + 1, c0 + 1] - z[r0, c0 + 1]) * u
        # Rows run southward: y decreases as v grows.
        return dz_du / self._cell, -dz_dv / self._cell

    def height_local(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """The height at local (x, y) (n,), metres: the ground, as the DSM has no objects."""
        return self.ground_local(x, y)

    def class_and_reflectance_local(self, x: np.ndarray, y: np.ndarray
                                    ) -> tuple[np.ndarray, np.ndarray]:
        """Open soil and its reflectance everywhere (n,): a DSM has no classes."""
        n = np.asarray(x).size
        return np.full(n, SOIL, dtype=np.int8), np.full(n, CLASS_REFLECTANCE[SOIL])

    def normal_local(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Upward unit normal (n, 3) of the interpolated height field at local (x, y) (n,)."""
        gx, gy = self._ground_grad_local(x, y)
        n = np.stack([-gx, -gy, np.ones_like(gx)], axis=-1)
        return n / np.linalg.norm(n, axis=-1, keepdims=True)

    def wall_normal_local(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """(0, 0, 1) for every local (x, y) (n,): a DSM has no walls."""
        out = np.zeros((np.asarray(x).size, 3))
        out[:, 2] = 1.0
        return out

    @property
    def n_buildings(self) -> int:
        """0: a DSM has no buildings of its own."""
        return 0

    @property
    def n_trees(self) -> int:
        """0: a DSM has no trees of its own."""
        return 0

    @property
    def height_range(self) -> tuple[float, float]:
        """Lowest and highest height of the grid, metres."""
        return self._z_lo, self._z_hi

    def describe(self) -> dict[str, object]:
        """Summary for a truth file."""
        return {"kind": "dsm", "shape": list(self._z.shape), "cell_m": self._cell,
                "west": self._west, "north": self._north,
                "height_range": [self._z_lo, self._z_hi]}

    def covers(self, x: np.ndarray, y: np.ndarray) -> bool:
        """Whether every map position lies on the grid."""
        xmin, xmax, ymin, ymax = self.extent
        return bool(np.all((x >= xmin) & (x <= xmax) & (y >= ymin) & (y <= ymax)))

    def ground_hit(self, origins: np.ndarray, directions: np.ndarray, *, block: int = 32_768
                   ) -> np.ndarray:
        """Distance along each downward ray to the first crossing of the height field.

        The ray is sampled from the grid's highest to its lowest height at steps of half a
        cell horizontally (a bilinear surface has no feature narrower than a cell), and the
        first crossing found is refined by bisection.
        """
        o, d = origins, directions
        n = o.shape[0]
        out = np.empty(n)
        dxy = np.hypot(d[:, 0], d[:, 1])
        for i0 in range(0, n, block):
            sl = slice(i0, min(n, i0 + block))
            oo, dd = o[sl], d[sl]
            t_hi = (oo[:, 2] - (self._z_hi + 1.0)) / -dd[:, 2]
            t_lo = (oo[:, 2] - (self._z_lo - 1.0)) / -dd[:, 2]
            span = (t_lo - t_hi) * dxy[sl]
            steps = max(2, int(math.ceil(float(span.max()) / (0.5 * self._cell))) + 1)
            frac = np.linspace(0.0, 1.0, steps)
            ts = t_hi[:, None] + (t_lo - t_hi)[:, None] * frac[None, :]
            above = (oo[:, 2, None] + ts * dd[:, 2, None]
                     - self.ground_local(oo[:, 0, None] + ts * dd[:, 0, None],
                                          oo[:, 1, None] + ts * dd[:, 1, None])) > 0
            j = np.argmin(above, axis=1)  # first sample below the surface
            rows = np.arange(ts.shape[0])
            a, b = ts[rows, np.maximum(j - 1, 0)], ts[rows, j]
            for _ in range(48):
                mid = 0.5 * (a + b)
                f = (oo[:, 2] + mid * dd[:, 2]
                     - self.ground_local(oo[:, 0] + mid * dd[:, 0], oo[:, 1] + mid * dd[:, 1]))
                a = np.where(f > 0, mid, a)
                b = np.where(f > 0, b, mid)
            out[sl] = 0.5 * (a + b)
        return out


__all__ = ["RasterTerrain"]
