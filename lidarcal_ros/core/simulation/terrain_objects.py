"""The buildings and trees of the analytic terrain, each kind on its own jittered grid.

At most one object per cell, so a query is O(1); local coordinates, metres; ``k`` arguments
are flat object indices.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from lidarcal_ros.core.simulation.object_tops import Footprints

#: Roof type codes.
FLAT_ROOF, GABLE_ROOF, HIP_ROOF, SHED_ROOF = 0, 1, 2, 3
ROOF_TYPE_NAMES: dict[int, str] = {
    FLAT_ROOF: "flat", GABLE_ROOF: "gable", HIP_ROOF: "hip", SHED_ROOF: "shed",
}
BUILDING_CELL = 56.0  # m, one building at most per cell
TREE_CELL = 24.0  # m, one tree at most per cell

#: ``clear(x, y, radius, road_gap)``: whether objects of horizontal ``radius`` (m) centred at
#: (x, y) stay ``road_gap`` metres off every road, clear of the control points and inside the
#: extent (a bool per object).
ClearTest = Callable[[np.ndarray, np.ndarray, np.ndarray, float], np.ndarray]
#: ``ground(x, y)``: the bare ground's height, metres.
GroundHeight = Callable[[np.ndarray, np.ndarray], np.ndarray]


@dataclass(frozen=True)
class _Grid:
    """A jittered grid of cells of side ``cell`` whose lower-left corner is (x0, y0)."""

    x0: float
    y0: float
    shape: tuple[int, int]
    cell: float

    @classmethod
    def centred(cls, extent: Sequence[float], cell: float) -> _Grid:
        """As many whole cells as fit the extent, centred in it."""
        xmin, xmax, ymin, ymax = extent
        nx = max(int((xmax - xmin) // cell), 1)
        ny = max(int((ymax - ymin) // cell), 1)
        return cls(xmin + 0.5 * ((xmax - xmin) - nx * cell),
                   ymin + 0.5 * ((ymax - ymin) - ny * cell), (ny, nx), cell)

    def centres(self, rng: np.random.Generator, slack: np.ndarray | float
                ) -> tuple[np.ndarray, np.ndarray]:
        """Each cell's centre moved by up to ``slack`` metres along x and y (x drawn first)."""
        ny, nx = self.shape
        ix = np.arange(nx)[None, :]
        iy = np.arange(ny)[:, None]
        cx = self.x0 + (ix + 0.5) * self.cell + rng.uniform(-1.0, 1.0, self.shape) * slack
        cy = self.y0 + (iy + 0.5) * self.cell + rng.uniform(-1.0, 1.0, self.shape) * slack
        return cx, cy

    def cells(self, x: np.ndarray, y: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Column and row of each position's cell and whether it lies on the grid."""
        ny, nx = self.shape
        ix = np.floor((x - self.x0) * (1.0 / self.cell)).astype(np.int64)
        iy = np.floor((y - self.y0) * (1.0 / self.cell)).astype(np.int64)
        return ix, iy, (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)

    def candidates(self, x: np.ndarray, y: np.ndarray, present: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
        """Indices of the positions whose cell holds an object, and that object's index."""
        ix, iy, valid = self.cells(x, y)
        flat = np.where(valid, iy * self.shape[1] + ix, 0)
        sel = np.flatnonzero(valid & present[flat])
        return sel, flat[sel]


def _rotate_to_map(u: np.ndarray, v: np.ndarray, c: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Horizontal (n, 3) vectors of components (u, v) in a frame turned by (cos, sin)."""
    return np.stack([u * c - v * s, u * s + v * c, np.zeros_like(u)], axis=-1)


@dataclass(frozen=True)
class _Objects:
    """Objects on a jittered grid, at most one a cell, each turned by an azimuth.

    Attributes
    ----------
    grid : _Grid
        The cells.
    present : (n,) bool
        An object stands in the cell.
    cx, cy : (n,) float64
        Centre, metres.
    cos, sin : (n,) float64
        The object's azimuth.
    reflectance_factor : (n,) float64
        Its departure from its class reflectance (0.9-1.1).
    """

    grid: _Grid
    present: np.ndarray
    cx: np.ndarray
    cy: np.ndarray
    cos: np.ndarray
    sin: np.ndarray
    reflectance_factor: np.ndarray

    @property
    def count(self) -> int:
        return int(self.present.sum())

    def lookup(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Indices of the positions inside an object's footprint, and that object's."""
        sel, k = self.grid.candidates(x, y, self.present)
        if sel.size == 0:
            return sel, sel
        u, v = self.local_uv(x[sel], y[sel], k)
        inside = self._inside(u, v, k)
        return sel[inside], k[inside]

    def local_uv(self, x: np.ndarray, y: np.ndarray, k: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
        """Positions in object ``k``'s frame: ``u`` along its azimuth, ``v`` across."""
        dx = x - self.cx[k]
        dy = y - self.cy[k]
        c, s = self.cos[k], self.sin[k]
        return dx * c + dy * s, -dx * s + dy * c

    def _inside(self, u: np.ndarray, v: np.ndarray, k: np.ndarray) -> np.ndarray:
        """Whether positions (u, v) of object ``k``'s frame lie in its footprint."""
        raise NotImplementedError


@dataclass(frozen=True)
class Buildings(_Objects):
    """Buildings on a jittered grid (docs/internals.md), their azimuth that of the long side.

    Attributes
    ----------
    (besides ``grid``, ``present``, ``cx``, ``cy``, ``cos``, ``sin`` and
    ``reflectance_factor`` of every kind of object; per-building (n,) arrays)
    a, b : half the long and the short side, metres
    roof : roof type code
    tan_slope : tangent of the roof's slope
    shed_u, shed_v, shed_offset : a shed roof's uphill direction in the building's (u, v)
        frame and the offset to its low eave, metres
    base, eave, top : ground under the centre, eave height above it, and the highest point
        (absolute), metres
    half_diagonal : half the footprint's diagonal, metres
    """

    a: np.ndarray
    b: np.ndarray
    roof: np.ndarray
    tan_slope: np.ndarray
    shed_u: np.ndarray
    shed_v: np.ndarray
    shed_offset: np.ndarray
    base: np.ndarray
    eave: np.ndarray
    top: np.ndarray
    half_diagonal: np.ndarray

    @classmethod
    def draw(cls, rng: np.random.Generator, extent: Sequence[float], *, populated: bool,
             clear: ClearTest, ground: GroundHeight) -> Buildings:
        """Buildings in 85% of the cells (none unless ``populated``) where ``clear`` allows
        them, standing on ``ground``."""
        grid = _Grid.centred(extent, BUILDING_CELL)
        shape = grid.shape
        long_side = rng.uniform(12.0, 40.0, shape)
        short_side = np.minimum(rng.uniform(10.0, 24.0, shape), long_side)
        a, b = 0.5 * long_side, 0.5 * short_side
        half_diag = np.hypot(a, b)
        slack = np.maximum(0.5 * BUILDING_CELL - half_diag - 3.0, 0.0)
        cx, cy = grid.centres(rng, slack)
        azimuth = rng.uniform(0.0, 2.0 * math.pi, shape)
        roof = rng.choice(
            np.array([FLAT_ROOF, GABLE_ROOF, HIP_ROOF, SHED_ROOF], dtype=np.int8),
            size=shape, p=[0.15, 0.4, 0.25, 0.2],
        )
        slope_deg = np.where(
            roof == SHED_ROOF, rng.uniform(10.0, 35.0, shape), rng.uniform(15.0, 45.0, shape)
        )
        slope_deg = np.where(roof == FLAT_ROOF, 0.0, slope_deg)
        tan_slope = np.tan(np.radians(slope_deg))
        shed_aspect = rng.uniform(0.0, 2.0 * math.pi, shape)
        eave = rng.uniform(4.0, 20.0, shape)
        has = rng.uniform(0.0, 1.0, shape) < (0.85 if populated else 0.0)
        fx, fy, hd = cx.ravel(), cy.ravel(), half_diag.ravel()
        present = has.ravel() & clear(fx, fy, hd, 3.0)
        base = ground(fx, fy)
        ridge = np.where(
            roof == SHED_ROOF,
            (a * np.abs(np.cos(shed_aspect)) + b * np.abs(np.sin(shed_aspect))) * 2.0 * tan_slope,
            b * tan_slope,
        ).ravel()
        su, sv = np.cos(shed_aspect).ravel(), np.sin(shed_aspect).ravel()
        a, b = a.ravel(), b.ravel()
        return cls(
            grid=grid, present=present, cx=fx, cy=fy, cos=np.cos(azimuth).ravel(),
            sin=np.sin(azimuth).ravel(), a=a, b=b, roof=roof.ravel(),
            tan_slope=tan_slope.ravel(), shed_u=su, shed_v=sv,
            shed_offset=a * np.abs(su) + b * np.abs(sv), base=base, eave=eave.ravel(),
            top=base + eave.ravel() + ridge, half_diagonal=hd,
            reflectance_factor=rng.uniform(0.9, 1.1, shape).ravel(),
        )

    def _inside(self, u: np.ndarray, v: np.ndarray, k: np.ndarray) -> np.ndarray:
        return (np.abs(u) <= self.a[k]) & (np.abs(v) <= self.b[k])

    def roof_height(self, x: np.ndarray, y: np.ndarray, k: np.ndarray) -> np.ndarray:
        """Height of building ``k``'s roof above (x, y), metres."""
        u, v = self.local_uv(x, y, k)
        a, b = self.a[k], self.b[k]
        t = self.tan_slope[k]
        roof = self.roof[k]
        gable = b - np.abs(v)
        rise = np.where(roof == HIP_ROOF, np.minimum(gable, a - np.abs(u)), gable)
        shed = self.shed_u[k] * u + self.shed_v[k] * v + self.shed_offset[k]
        rise = np.where(roof == SHED_ROOF, shed, rise)
        rise = np.where(roof == FLAT_ROOF, 0.0, rise)
        return self.base[k] + self.eave[k] + rise * t

    def roof_gradient(self, x: np.ndarray, y: np.ndarray, k: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
        """d(height)/dx and d(height)/dy of building ``k``'s roof at (x, y)."""
        u, v = self.local_uv(x, y, k)
        a, b = self.a[k], self.b[k]
        t = self.tan_slope[k]
        roof = self.roof[k]
        sv = np.where(v >= 0.0, 1.0, -1.0)
        su = np.where(u >= 0.0, 1.0, -1.0)
        hu = np.zeros_like(u)
        hv = -sv * t  # gable
        hip_end = (roof == HIP_ROOF) & ((a - np.abs(u)) < (b - np.abs(v)))
        hu = np.where(hip_end, -su * t, hu)
        hv = np.where(hip_end, 0.0, hv)
        shed = roof == SHED_ROOF
        hu = np.where(shed, self.shed_u[k] * t, hu)
        hv = np.where(shed, self.shed_v[k] * t, hv)
        flat = roof == FLAT_ROOF
        hu = np.where(flat, 0.0, hu)
        hv = np.where(flat, 0.0, hv)
        c, s = self.cos[k], self.sin[k]
        return hu * c - hv * s, hu * s + hv * c

    def wall_normal(self, x: np.ndarray, y: np.ndarray, k: np.ndarray) -> np.ndarray:
        """Horizontal outward normal (n, 3) of building ``k``'s wall nearest (x, y)."""
        u, v = self.local_uv(x, y, k)
        a, b = self.a[k], self.b[k]
        end = (a - np.abs(u)) < (b - np.abs(v))
        nu = np.where(end, np.sign(u), 0.0)
        nv = np.where(end, 0.0, np.sign(v))
        return _rotate_to_map(nu, nv, self.cos[k], self.sin[k])

    def far_from(self, x: np.ndarray, y: np.ndarray, radius: np.ndarray, gap: float
                 ) -> np.ndarray:
        """Whether objects of ``radius`` at (x, y) stand ``gap`` metres off every building
        (those of their cell and the eight around it: farther ones cannot reach)."""
        g = self.grid
        ix = np.floor((x - g.x0) / g.cell).astype(np.int64)
        iy = np.floor((y - g.y0) / g.cell).astype(np.int64)
        ny, nx = g.shape
        clear = np.ones(x.size, dtype=bool)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                jx, jy = ix + dx, iy + dy
                valid = (jx >= 0) & (jx < nx) & (jy >= 0) & (jy < ny)
                j = np.clip(jy, 0, ny - 1) * nx + np.clip(jx, 0, nx - 1)
                near = valid & self.present[j]
                dist = np.hypot(x - self.cx[j], y - self.cy[j])
                clear &= ~near | (dist > self.half_diagonal[j] + radius + gap)
        return clear

    def footprints(self) -> Footprints:
        """Each building's centre, the half-side of the square that holds its rotated
        footprint, and its top (for
        :class:`~lidarcal_ros.core.simulation.object_tops.ObjectTops`)."""
        p = self.present
        ca, sa = np.abs(self.cos[p]), np.abs(self.sin[p])
        # half-extent of the rotated rectangle's bounding box (square box of the larger one)
        half = np.maximum(self.a[p] * ca + self.b[p] * sa, self.a[p] * sa + self.b[p] * ca)
        return self.cx[p], self.cy[p], half, self.top[p]

    def describe(self, origin: Sequence[float]) -> list[dict[str, Any]]:
        """Each building in map coordinates (``origin`` added)."""
        out: list[dict[str, Any]] = []
        for i in np.flatnonzero(self.present):
            out.append({
                "x": float(self.cx[i]) + origin[0],
                "y": float(self.cy[i]) + origin[1],
                "length": 2.0 * float(self.a[i]),
                "width": 2.0 * float(self.b[i]),
                "azimuth_rad": math.atan2(float(self.sin[i]), float(self.cos[i])),
                "roof": ROOF_TYPE_NAMES[int(self.roof[i])],
                "slope_deg": math.degrees(math.atan(float(self.tan_slope[i]))),
                "eave_height": float(self.eave[i]),
                "base": float(self.base[i]),
                "top": float(self.top[i]),
            })
        return out


@dataclass(frozen=True)
class Trees(_Objects):
    """Trees on a jittered grid (docs/internals.md), their azimuth that of the crown's first
    semi-axis.

    Attributes
    ----------
    (besides ``grid``, ``present``, ``cx``, ``cy``, ``cos``, ``sin`` and
    ``reflectance_factor`` of every kind of object; per-tree (n,) arrays)
    ra, rb : the crown's semi-axes, metres
    crown_base, crown_height : the crown's base above the ground and its height, metres
    base : ground under the centre, metres
    bump_amplitude, bump_k, bump_phase : the crown's bumps (relative amplitude; (3, n)
        wavenumbers, rad/m, and phases, rad)
    top : the highest point the crown may reach (absolute), metres
    """

    ra: np.ndarray
    rb: np.ndarray
    crown_base: np.ndarray
    crown_height: np.ndarray
    base: np.ndarray
    bump_amplitude: np.ndarray
    bump_k: np.ndarray
    bump_phase: np.ndarray
    top: np.ndarray

    @classmethod
    def draw(cls, rng: np.random.Generator, extent: Sequence[float], *, populated: bool,
             clear: ClearTest, ground: GroundHeight, buildings: Buildings) -> Trees:
        """Trees in 35% of the cells (none unless ``populated``) where ``clear`` allows them,
        4 m off every building, standing on ``ground``."""
        grid = _Grid.centred(extent, TREE_CELL)
        shape = grid.shape
        ra = rng.uniform(2.5, 6.0, shape)
        rb = ra * rng.uniform(0.7, 1.0, shape)
        rmax = 6.0
        cx, cy = grid.centres(rng, 0.5 * TREE_CELL - rmax - 0.5)
        az = rng.uniform(0.0, math.pi, shape)
        has = rng.uniform(0.0, 1.0, shape) < (0.35 if populated else 0.0)
        fx, fy, fr = cx.ravel(), cy.ravel(), ra.ravel()
        ok = has.ravel() & clear(fx, fy, fr, 1.0)
        cand = np.flatnonzero(ok)
        if cand.size and buildings.present.any():
            ok[cand] = buildings.far_from(fx[cand], fy[cand], fr[cand], 4.0)
        crown_base = rng.uniform(1.0, 4.0, shape).ravel()
        crown_height = rng.uniform(4.0, 12.0, shape).ravel()
        base = ground(fx, fy)
        amp = rng.uniform(0.05, 0.12, shape).ravel()
        bump_k = rng.uniform(2.0 * math.pi / 3.0, 2.0 * math.pi / 1.2, (3, *shape))
        bump_phase = rng.uniform(0.0, 2.0 * math.pi, (3, *shape))
        return cls(
            grid=grid, present=ok, cx=fx, cy=fy, cos=np.cos(az).ravel(), sin=np.sin(az).ravel(),
            ra=fr, rb=rb.ravel(), crown_base=crown_base, crown_height=crown_height, base=base,
            bump_amplitude=amp, bump_k=bump_k.reshape(3, -1),
            bump_phase=bump_phase.reshape(3, -1),
            top=base + crown_base + crown_height * (1.0 + 1.5 * amp),
            reflectance_factor=rng.uniform(0.9, 1.1, shape).ravel(),
        )

    def _inside(self, u: np.ndarray, v: np.ndarray, k: np.ndarray) -> np.ndarray:
        return (u / self.ra[k]) ** 2 + (v / self.rb[k]) ** 2 < 1.0

    def crown_surface(self, x: np.ndarray, y: np.ndarray, k: np.ndarray) -> np.ndarray:
        """Height of tree ``k``'s crown above (x, y), metres."""
        u, v = self.local_uv(x, y, k)
        q = (u / self.ra[k]) ** 2 + (v / self.rb[k]) ** 2
        kk = self.bump_k[:, k]
        ph = self.bump_phase[:, k]
        bump = (np.sin(kk[0] * u + ph[0]) * np.sin(kk[1] * v + ph[1])
                + 0.5 * np.sin(kk[2] * (u + v) + ph[2]))
        dome = np.sqrt(np.clip(1.0 - q, 0.0, None))
        return (self.base[k] + self.crown_base[k]
                + self.crown_height[k] * dome * (1.0 + self.bump_amplitude[k] * bump))

    def crown_gradient(self, x: np.ndarray, y: np.ndarray, k: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
        """d(height)/dx and d(height)/dy of tree ``k``'s crown, by central differences
        (1 cm)."""
        eps = 0.01
        gx = (self.crown_surface(x + eps, y, k) - self.crown_surface(x - eps, y, k)) / (2 * eps)
        gy = (self.crown_surface(x, y + eps, k) - self.crown_surface(x, y - eps, k)) / (2 * eps)
        return gx, gy

    def wall_normal(self, x: np.ndarray, y: np.ndarray, k: np.ndarray) -> np.ndarray:
        """Horizontal outward normal (n, 3) of tree ``k``'s crown wall at (x, y) ((0, 0, 1)
        at its centre)."""
        u, v = self.local_uv(x, y, k)
        nu = u / self.ra[k] ** 2
        nv = v / self.rb[k] ** 2
        w = _rotate_to_map(nu, nv, self.cos[k], self.sin[k])
        norm = np.linalg.norm(w, axis=-1, keepdims=True)
        return np.where(norm > 0, w / np.where(norm > 0, norm, 1.0), [[0.0, 0.0, 1.0]])

    def footprints(self) -> Footprints:
        """Each tree's centre, its larger semi-axis and its top (for
        :class:`~lidarcal_ros.core.simulation.object_tops.ObjectTops`)."""
        p = self.present
        return self.cx[p], self.cy[p], self.ra[p], self.top[p]


__all__ = ["BUILDING_CELL", "FLAT_ROOF", "GABLE_ROOF", "HIP_ROOF", "ROOF_TYPE_NAMES",
           "SHED_ROOF", "TREE_CELL", "Buildings", "ClearTest", "GroundHeight", "Trees"]
