"""Analytic digital surface models for simulated LiDAR missions, and a vectorised ray caster.

A :class:`Terrain` is a 2.5-D surface ``z = height(x, y)`` built from a seed over a rectangular
extent:

- gently undulating ground (a sum of a few long-wavelength sinusoids, a few metres over
  hundreds of metres; exactly ``z = 0`` for the ``flat`` kind);
- land cover on the ground: irregular patches (a jittered-grid Voronoi diagram) of soil, grass
  and asphalt, and straight asphalt roads;
- buildings on a jittered grid, at most one per cell (so a query is O(1): cell index -> that
  cell's building), of any azimuth, 10-40 m footprints, 4-20 m eaves and gable, hip, shed
  (mono-pitch) or flat roofs;
- trees (bumpy semi-ellipsoid crowns on a short "crown wall") on their own jittered grid,
  placed away from buildings and roads.

Surface classes: 0 ground-soil, 1 grass, 2 asphalt, 3 roof (buildings, walls included),
4 tree crown. Every public method takes map coordinates (the terrain's ``origin`` is
subtracted); the surface itself is generated in local coordinates around (0, 0).

:func:`cast_rays` intersects rays with the surface: Newton on the smooth ground, a conservative
max-height raster to find the stretch of each ray that may meet an object, a march of at most
0.5 m along the ray through that stretch, then bisection to below 1e-6 m. Rays that meet a
building or crown wall stop on the wall.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.ndimage import maximum_filter

from lidarcal_ros.errors import ConfigError

#: Surface class codes.
SOIL, GRASS, ASPHALT, ROOF, TREE = 0, 1, 2, 3, 4
CLASS_NAMES: dict[int, str] = {
    SOIL: "ground-soil", GRASS: "grass", ASPHALT: "asphalt", ROOF: "roof", TREE: "tree",
}
#: Nominal Lambertian reflectance of each class at 1064 nm (each object varies by +-10%).
CLASS_REFLECTANCE: dict[int, float] = {
    SOIL: 0.30, GRASS: 0.45, ASPHALT: 0.12, ROOF: 0.25, TREE: 0.50,
}

#: Roof type codes.
FLAT_ROOF, GABLE_ROOF, HIP_ROOF, SHED_ROOF = 0, 1, 2, 3
ROOF_TYPE_NAMES: dict[int, str] = {
    FLAT_ROOF: "flat", GABLE_ROOF: "gable", HIP_ROOF: "hip", SHED_ROOF: "shed",
}

TERRAIN_KINDS = ("built-up", "flat")

_NO_OBJECT = np.float32(-1.0e9)
_BUILDING_CELL = 56.0  # m, one building at most per cell
_TREE_CELL = 24.0  # m, one tree at most per cell
_PATCH_CELL = 70.0  # m, land-cover Voronoi seeds
_MAX_HALF_DIAGONAL = 0.5 * math.hypot(40.0, 24.0)


@dataclass
class RayHits:
    """Result of :func:`cast_rays` (all in the terrain's local frame).

    Attributes
    ----------
    t : (n,) float64
        Distance along each (unit) ray to the hit, metres.
    xyz : (n, 3) float64
        Hit points, local coordinates.
    on_wall : (n,) bool
        The ray stopped on a vertical face (building wall or crown edge).
    inside : (n, 3) float64
        A point within 1e-6 m of the hit on the object side (used to classify wall hits).
    """

    t: np.ndarray
    xyz: np.ndarray
    on_wall: np.ndarray
    inside: np.ndarray


class Terrain:
    """Vectorised analytic DSM (see the module docstring).

    Parameters
    ----------
    extent : (xmin, xmax, ymin, ymax)
        Area holding buildings, trees, roads and patches, local coordinates, metres. The ground
        continues outside it.
    seed : int
        Everything random derives from it.
    kind : ``"built-up"`` (default) or ``"flat"``
        ``flat`` is the plane ``z = 0`` with land-cover patches but no buildings or trees.
    keep_clear : sequence of (x, y), local coordinates
        Locations (control points) kept as open ground: no building or tree within
        ``clear_radius`` metres.
    clear_radius : float
    origin : (x0, y0)
        Added to local coordinates to give map coordinates; public methods take map coordinates.
    """

    def __init__(
        self,
        extent: Sequence[float] = (-600.0, 600.0, -600.0, 600.0),
        *,
        seed: int = 0,
        kind: str = "built-up",
        keep_clear: Iterable[Sequence[float]] = (),
        clear_radius: float = 15.0,
        origin: Sequence[float] = (0.0, 0.0),
    ) -> None:
        if kind not in TERRAIN_KINDS:
            raise ConfigError(f"terrain kind {kind!r} unknown; known: {', '.join(TERRAIN_KINDS)}")
        xmin, xmax, ymin, ymax = (float(v) for v in extent)
        if not (xmax > xmin and ymax > ymin):
            raise ConfigError(f"terrain extent {tuple(extent)} is empty")
        self.extent = (xmin, xmax, ymin, ymax)
        self.seed = int(seed)
        self.kind = kind
        self.origin = (float(origin[0]), float(origin[1]))
        self.clear_radius = float(clear_radius)
        self.keep_clear = np.asarray(list(keep_clear), dtype=np.float64).reshape(-1, 2)
        rng = np.random.default_rng([self.seed, 0x7E55A1])
        self._make_ground(rng)
        self._make_roads(rng)
        self._make_patches(rng)
        self._make_buildings(rng)
        self._make_trees(rng)
        self._make_rasters()

    # ------------------------------------------------------------------ generation

    def _make_ground(self, rng: np.random.Generator) -> None:
        if self.kind == "flat":
            self._g_amp = np.zeros(0)
            self._g_kx = np.zeros(0)
            self._g_ky = np.zeros(0)
            self._g_ph = np.zeros(0)
            self.ground_max_slope = 0.0
            return
        n = 4
        wavelength = rng.uniform(300.0, 900.0, n)
        azimuth = rng.uniform(0.0, math.pi, n)
        amp = rng.uniform(0.6, 1.4, n)
        k = 2.0 * math.pi / wavelength
        self._g_amp = amp
        self._g_kx = k * np.cos(azimuth)
        self._g_ky = k * np.sin(azimuth)
        self._g_ph = rng.uniform(0.0, 2.0 * math.pi, n)
        self.ground_max_slope = float(np.sum(amp * k))

    def _make_roads(self, rng: np.random.Generator) -> None:
        xmin, xmax, ymin, ymax = self.extent
        cx, cy = 0.5 * (xmin + xmax), 0.5 * (ymin + ymax)
        rows = []
        # two roughly north-south and two roughly east-west roads, never through the centre
        for base_az in (0.0, 0.0, 0.5 * math.pi, 0.5 * math.pi):
            az = base_az + rng.uniform(-0.35, 0.35)
            span = (xmax - xmin) if base_az == 0.0 else (ymax - ymin)
            off = rng.uniform(0.15, 0.45) * span * rng.choice([-1.0, 1.0])
            # unit normal to the road direction (road direction = (sin az, cos az))
            nx, ny = math.cos(az), -math.sin(az)
            c = nx * cx + ny * cy + off
            width = rng.uniform(6.0, 12.0)
            rows.append((nx, ny, c, 0.5 * width, rng.uniform(0.9, 1.1)))
        self._roads = np.array(rows, dtype=np.float64).reshape(-1, 5)

    def _road_distance(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """(n, n_roads) distance to each road's edge (negative inside the road)."""
        r = self._roads
        return np.abs(x[:, None] * r[:, 0] + y[:, None] * r[:, 1] - r[:, 2]) - r[:, 3]

    def _make_patches(self, rng: np.random.Generator) -> None:
        xmin, xmax, ymin, ymax = self.extent
        cs = _PATCH_CELL
        self._p_x0 = xmin - cs
        self._p_y0 = ymin - cs
        nx = int(math.ceil((xmax - xmin) / cs)) + 3
        ny = int(math.ceil((ymax - ymin) / cs)) + 3
        self._p_shape = (ny, nx)
        jx, jy = rng.uniform(0.1, 0.9, (2, ny, nx))
        ix = np.arange(nx)[None, :]
        iy = np.arange(ny)[:, None]
        self._p_sx = self._p_x0 + (ix + jx) * cs
        self._p_sy = self._p_y0 + (iy + jy) * cs
        self._p_cls = rng.choice(
            np.array([SOIL, GRASS, ASPHALT], dtype=np.int8), size=(ny, nx), p=[0.4, 0.45, 0.15]
        )
        self._p_fac = rng.uniform(0.9, 1.1, (ny, nx))

    def _make_buildings(self, rng: np.random.Generator) -> None:
        xmin, xmax, ymin, ymax = self.extent
        cs = _BUILDING_CELL
        nx = max(int((xmax - xmin) // cs), 1)
        ny = max(int((ymax - ymin) // cs), 1)
        self._b_x0 = xmin + 0.5 * ((xmax - xmin) - nx * cs)
        self._b_y0 = ymin + 0.5 * ((ymax - ymin) - ny * cs)
        self._b_shape = (ny, nx)
        shape = (ny, nx)
        long_side = rng.uniform(12.0, 40.0, shape)
        short_side = np.minimum(rng.uniform(10.0, 24.0, shape), long_side)
        a, b = 0.5 * long_side, 0.5 * short_side
        half_diag = np.hypot(a, b)
        slack = np.maximum(0.5 * cs - half_diag - 3.0, 0.0)
        ix = np.arange(nx)[None, :]
        iy = np.arange(ny)[:, None]
        cx = self._b_x0 + (ix + 0.5) * cs + rng.uniform(-1.0, 1.0, shape) * slack
        cy = self._b_y0 + (iy + 0.5) * cs + rng.uniform(-1.0, 1.0, shape) * slack
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
        has = (
            rng.uniform(0.0, 1.0, shape) < (0.0 if self.kind == "flat" else 0.85)
        )
        # keep roads, control points and the outside of the extent clear
        fx, fy = cx.ravel(), cy.ravel()
        hd = half_diag.ravel()
        ok = has.ravel().copy()
        if self._roads.size:
            ok &= (self._road_distance(fx, fy) > hd[:, None] + 3.0).all(axis=1)
        if self.keep_clear.size:
            d = np.hypot(fx[:, None] - self.keep_clear[:, 0], fy[:, None] - self.keep_clear[:, 1])
            ok &= (d > hd[:, None] + self.clear_radius + 1.0).all(axis=1)
        ok &= (fx - hd >= xmin) & (fx + hd <= xmax) & (fy - hd >= ymin) & (fy + hd <= ymax)
        has = ok.reshape(shape)
        base = self._ground_local(fx, fy).reshape(shape)
        ridge = np.where(
            roof == SHED_ROOF,
            (a * np.abs(np.cos(shed_aspect)) + b * np.abs(np.sin(shed_aspect))) * 2.0 * tan_slope,
            b * tan_slope,
        )
        self._b_has = has
        self._b_cx, self._b_cy = cx, cy
        self._b_cos, self._b_sin = np.cos(azimuth), np.sin(azimuth)
        self._b_a, self._b_b = a, b
        self._b_roof = roof
        self._b_tan = tan_slope
        # shed: uphill direction in the building's (u, v) frame and the offset to the low eave
        self._b_su, self._b_sv = np.cos(shed_aspect), np.sin(shed_aspect)
        self._b_soff = a * np.abs(self._b_su) + b * np.abs(self._b_sv)
        self._b_base = base
        self._b_eave = eave
        self._b_top = base + eave + ridge
        self._b_half_diag = half_diag
        self._b_fac = rng.uniform(0.9, 1.1, shape)

    def _make_trees(self, rng: np.random.Generator) -> None:
        xmin, xmax, ymin, ymax = self.extent
        cs = _TREE_CELL
        nx = max(int((xmax - xmin) // cs), 1)
        ny = max(int((ymax - ymin) // cs), 1)
        self._t_x0 = xmin + 0.5 * ((xmax - xmin) - nx * cs)
        self._t_y0 = ymin + 0.5 * ((ymax - ymin) - ny * cs)
        self._t_shape = (ny, nx)
        shape = (ny, nx)
        ra = rng.uniform(2.5, 6.0, shape)
        rb = ra * rng.uniform(0.7, 1.0, shape)
        rmax = 6.0
        ix = np.arange(nx)[None, :]
        iy = np.arange(ny)[:, None]
        slack = 0.5 * cs - rmax - 0.5
        cx = self._t_x0 + (ix + 0.5) * cs + rng.uniform(-1.0, 1.0, shape) * slack
        cy = self._t_y0 + (iy + 0.5) * cs + rng.uniform(-1.0, 1.0, shape) * slack
        az = rng.uniform(0.0, math.pi, shape)
        has = rng.uniform(0.0, 1.0, shape) < (0.0 if self.kind == "flat" else 0.35)
        fx, fy, fr = cx.ravel(), cy.ravel(), ra.ravel()
        ok = has.ravel().copy()
        if self._roads.size:
            ok &= (self._road_distance(fx, fy) > fr[:, None] + 1.0).all(axis=1)
        if self.keep_clear.size:
            d = np.hypot(fx[:, None] - self.keep_clear[:, 0], fy[:, None] - self.keep_clear[:, 1])
            ok &= (d > fr[:, None] + self.clear_radius + 1.0).all(axis=1)
        ok &= (fx - fr >= xmin) & (fx + fr <= xmax) & (fy - fr >= ymin) & (fy + fr <= ymax)
        # away from buildings: check the building cells around each candidate
        cand = np.flatnonzero(ok)
        if cand.size and self._b_has.any():
            bcx = np.floor((fx[cand] - self._b_x0) / _BUILDING_CELL).astype(np.int64)
            bcy = np.floor((fy[cand] - self._b_y0) / _BUILDING_CELL).astype(np.int64)
            bny, bnx = self._b_shape
            clear = np.ones(cand.size, dtype=bool)
            for dy in (-1, 0, 1):
                for dx in (-1, 0, 1):
                    jx, jy = bcx + dx, bcy + dy
                    valid = (jx >= 0) & (jx < bnx) & (jy >= 0) & (jy < bny)
                    jxc, jyc = np.clip(jx, 0, bnx - 1), np.clip(jy, 0, bny - 1)
                    present = valid & self._b_has[jyc, jxc]
                    dist = np.hypot(fx[cand] - self._b_cx[jyc, jxc],
                                    fy[cand] - self._b_cy[jyc, jxc])
                    clear &= ~present | (dist > self._b_half_diag[jyc, jxc] + fr[cand] + 4.0)
            ok[cand] = clear
        has = ok.reshape(shape)
        self._t_has = has
        self._t_cx, self._t_cy = cx, cy
        self._t_cos, self._t_sin = np.cos(az), np.sin(az)
        self._t_ra, self._t_rb = ra, rb
        self._t_hb = rng.uniform(1.0, 4.0, shape)  # crown base above the ground
        self._t_hc = rng.uniform(4.0, 12.0, shape)  # crown height
        self._t_base = self._ground_local(fx, fy).reshape(shape)
        self._t_amp = rng.uniform(0.05, 0.12, shape)
        self._t_k = rng.uniform(2.0 * math.pi / 3.0, 2.0 * math.pi / 1.2, (3, *shape))
        self._t_ph = rng.uniform(0.0, 2.0 * math.pi, (3, *shape))
        self._t_top = self._t_base + self._t_hb + self._t_hc * (1.0 + 1.5 * self._t_amp)
        self._t_fac = rng.uniform(0.9, 1.1, shape)

    def _make_rasters(self) -> None:
        """Conservative object-top rasters for the ray caster (objects only, no ground)."""
        xmin, xmax, ymin, ymax = self.extent
        area = (xmax - xmin) * (ymax - ymin)
        res = max(1.0, math.sqrt(area / 1.2e7))
        self._r_res = res
        self._r_x0, self._r_y0 = xmin - 2.0 * res, ymin - 2.0 * res
        nx = int(math.ceil((xmax - xmin) / res)) + 4
        ny = int(math.ceil((ymax - ymin) / res)) + 4
        m = np.full((ny, nx), _NO_OBJECT, dtype=np.float32)

        def paint(cx: np.ndarray, cy: np.ndarray, rad: np.ndarray, top: np.ndarray) -> None:
            for x, y, r, z in zip(cx, cy, rad, top):
                i0 = max(int((x - r - self._r_x0) // res), 0)
                i1 = min(int((x + r - self._r_x0) // res) + 1, nx)
                j0 = max(int((y - r - self._r_y0) // res), 0)
                j1 = min(int((y + r - self._r_y0) // res) + 1, ny)
                sub = m[j0:j1, i0:i1]
                np.maximum(sub, np.float32(z + 0.01), out=sub)

        hb = self._b_has
        ca, sa = np.abs(self._b_cos[hb]), np.abs(self._b_sin[hb])
        # half-extent of the rotated rectangle's bounding box (square box of the larger one)
        rad_b = np.maximum(self._b_a[hb] * ca + self._b_b[hb] * sa,
                           self._b_a[hb] * sa + self._b_b[hb] * ca)
        paint(self._b_cx[hb], self._b_cy[hb], rad_b + 0.01, self._b_top[hb])
        ht = self._t_has
        paint(self._t_cx[ht], self._t_cy[ht], self._t_ra[ht] + 0.01, self._t_top[ht])
        self._r_fine = maximum_filter(m, size=3, mode="constant", cval=_NO_OBJECT)
        # coarse raster: max over blocks of the fine (undilated) raster
        self._c_res = 32.0 * res
        f = 32
        cny, cnx = -(-ny // f), -(-nx // f)
        pad = np.full((cny * f, cnx * f), _NO_OBJECT, dtype=np.float32)
        pad[:ny, :nx] = m
        self._c_raw = pad.reshape(cny, f, cnx, f).max(axis=(1, 3))
        self._c_cache: dict[int, np.ndarray] = {}
        self.max_object_top = float(m.max()) if (hb.any() or ht.any()) else -math.inf

    # ------------------------------------------------------------------ ground and cover

    def _ground_local(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        z = np.zeros(np.broadcast(x, y).shape)
        for a, kx, ky, ph in zip(self._g_amp, self._g_kx, self._g_ky, self._g_ph):
            z += a * np.sin(kx * x + ky * y + ph)
        return z

    def _ground_grad_local(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        gx = np.zeros(np.broadcast(x, y).shape)
        gy = np.zeros_like(gx)
        for a, kx, ky, ph in zip(self._g_amp, self._g_kx, self._g_ky, self._g_ph):
            c = a * np.cos(kx * x + ky * y + ph)
            gx += c * kx
            gy += c * ky
        return gx, gy

    def _ground_cover_local(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Land-cover class and reflectance factor of the ground (ignoring objects)."""
        cs = _PATCH_CELL
        ny, nx = self._p_shape
        ix = np.floor((x - self._p_x0) / cs).astype(np.int64)
        iy = np.floor((y - self._p_y0) / cs).astype(np.int64)
        best = np.full(x.shape, np.inf)
        bx = np.clip(ix, 0, nx - 1)
        by = np.clip(iy, 0, ny - 1)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                jx = np.clip(ix + dx, 0, nx - 1)
                jy = np.clip(iy + dy, 0, ny - 1)
                d = (x - self._p_sx[jy, jx]) ** 2 + (y - self._p_sy[jy, jx]) ** 2
                closer = d < best
                best = np.where(closer, d, best)
                bx = np.where(closer, jx, bx)
                by = np.where(closer, jy, by)
        cls = self._p_cls[by, bx].astype(np.int8)
        fac = self._p_fac[by, bx]
        if self._roads.size:
            rd = self._road_distance(x, y)
            on_road = rd <= 0.0
            any_road = on_road.any(axis=1)
            cls = np.where(any_road, np.int8(ASPHALT), cls)
            road_fac = self._roads[np.argmax(on_road, axis=1), 4]
            fac = np.where(any_road, road_fac, fac)
        return cls, fac

    # ------------------------------------------------------------------ objects

    def _building_lookup(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Indices of the points inside a building footprint and the flat index of it."""
        ny, nx = self._b_shape
        ix = np.floor((x - self._b_x0) * (1.0 / _BUILDING_CELL)).astype(np.int64)
        iy = np.floor((y - self._b_y0) * (1.0 / _BUILDING_CELL)).astype(np.int64)
        valid = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
        flat = np.where(valid, iy * nx + ix, 0)
        sel = np.flatnonzero(valid & self._b_has.ravel()[flat])
        if sel.size == 0:
            return sel, sel
        k = flat[sel]
        dx = x[sel] - self._b_cx.ravel()[k]
        dy = y[sel] - self._b_cy.ravel()[k]
        c, s = self._b_cos.ravel()[k], self._b_sin.ravel()[k]
        u = dx * c + dy * s
        v = -dx * s + dy * c
        inside = (np.abs(u) <= self._b_a.ravel()[k]) & (np.abs(v) <= self._b_b.ravel()[k])
        return sel[inside], k[inside]

    def _building_local_uv(self, x: np.ndarray, y: np.ndarray, k: np.ndarray
                           ) -> tuple[np.ndarray, np.ndarray]:
        dx = x - self._b_cx.ravel()[k]
        dy = y - self._b_cy.ravel()[k]
        c, s = self._b_cos.ravel()[k], self._b_sin.ravel()[k]
        return dx * c + dy * s, -dx * s + dy * c

    def _roof_height(self, x: np.ndarray, y: np.ndarray, k: np.ndarray) -> np.ndarray:
        u, v = self._building_local_uv(x, y, k)
        a, b = self._b_a.ravel()[k], self._b_b.ravel()[k]
        t = self._b_tan.ravel()[k]
        roof = self._b_roof.ravel()[k]
        gable = b - np.abs(v)
        rise = np.where(roof == HIP_ROOF, np.minimum(gable, a - np.abs(u)), gable)
        shed = self._b_su.ravel()[k] * u + self._b_sv.ravel()[k] * v + self._b_soff.ravel()[k]
        rise = np.where(roof == SHED_ROOF, shed, rise)
        rise = np.where(roof == FLAT_ROOF, 0.0, rise)
        return self._b_base.ravel()[k] + self._b_eave.ravel()[k] + rise * t

    def _roof_gradient(self, x: np.ndarray, y: np.ndarray, k: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
        u, v = self._building_local_uv(x, y, k)
        a, b = self._b_a.ravel()[k], self._b_b.ravel()[k]
        t = self._b_tan.ravel()[k]
        roof = self._b_roof.ravel()[k]
        sv = np.where(v >= 0.0, 1.0, -1.0)
        su = np.where(u >= 0.0, 1.0, -1.0)
        hu = np.zeros_like(u)
        hv = -sv * t  # gable
        hip_end = (roof == HIP_ROOF) & ((a - np.abs(u)) < (b - np.abs(v)))
        hu = np.where(hip_end, -su * t, hu)
        hv = np.where(hip_end, 0.0, hv)
        shed = roof == SHED_ROOF
        hu = np.where(shed, self._b_su.ravel()[k] * t, hu)
        hv = np.where(shed, self._b_sv.ravel()[k] * t, hv)
        flat = roof == FLAT_ROOF
        hu = np.where(flat, 0.0, hu)
        hv = np.where(flat, 0.0, hv)
        c, s = self._b_cos.ravel()[k], self._b_sin.ravel()[k]
        return hu * c - hv * s, hu * s + hv * c

    def _tree_lookup(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ny, nx = self._t_shape
        ix = np.floor((x - self._t_x0) * (1.0 / _TREE_CELL)).astype(np.int64)
        iy = np.floor((y - self._t_y0) * (1.0 / _TREE_CELL)).astype(np.int64)
        valid = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
        flat = np.where(valid, iy * nx + ix, 0)
        sel = np.flatnonzero(valid & self._t_has.ravel()[flat])
        if sel.size == 0:
            return sel, sel
        k = flat[sel]
        q = self._tree_q(x[sel], y[sel], k)
        inside = q < 1.0
        return sel[inside], k[inside]

    def _tree_uv(self, x: np.ndarray, y: np.ndarray, k: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
        dx = x - self._t_cx.ravel()[k]
        dy = y - self._t_cy.ravel()[k]
        c, s = self._t_cos.ravel()[k], self._t_sin.ravel()[k]
        return dx * c + dy * s, -dx * s + dy * c

    def _tree_q(self, x: np.ndarray, y: np.ndarray, k: np.ndarray) -> np.ndarray:
        u, v = self._tree_uv(x, y, k)
        return (u / self._t_ra.ravel()[k]) ** 2 + (v / self._t_rb.ravel()[k]) ** 2

    def _crown_height(self, x: np.ndarray, y: np.ndarray, k: np.ndarray) -> np.ndarray:
        u, v = self._tree_uv(x, y, k)
        q = (u / self._t_ra.ravel()[k]) ** 2 + (v / self._t_rb.ravel()[k]) ** 2
        kk = self._t_k.reshape(3, -1)[:, k]
        ph = self._t_ph.reshape(3, -1)[:, k]
        bump = (np.sin(kk[0] * u + ph[0]) * np.sin(kk[1] * v + ph[1])
                + 0.5 * np.sin(kk[2] * (u + v) + ph[2]))
        dome = np.sqrt(np.clip(1.0 - q, 0.0, None))
        return (self._t_base.ravel()[k] + self._t_hb.ravel()[k]
                + self._t_hc.ravel()[k] * dome * (1.0 + self._t_amp.ravel()[k] * bump))

    # ------------------------------------------------------------------ local queries

    def _height_local(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        x = np.ascontiguousarray(x, dtype=np.float64)
        y = np.ascontiguousarray(y, dtype=np.float64)
        h = self._ground_local(x, y)
        if self.kind == "flat":
            return h
        sel, k = self._building_lookup(x, y)
        if sel.size:
            h[sel] = self._roof_height(x[sel], y[sel], k)
        sel, k = self._tree_lookup(x, y)
        if sel.size:
            h[sel] = self._crown_height(x[sel], y[sel], k)
        return h

    def _class_and_reflectance_local(self, x: np.ndarray, y: np.ndarray
                                     ) -> tuple[np.ndarray, np.ndarray]:
        x = np.ascontiguousarray(x, dtype=np.float64)
        y = np.ascontiguousarray(y, dtype=np.float64)
        cls, fac = self._ground_cover_local(x, y)
        sel, k = self._building_lookup(x, y)
        cls[sel] = ROOF
        fac[sel] = self._b_fac.ravel()[k]
        sel, k = self._tree_lookup(x, y)
        cls[sel] = TREE
        fac[sel] = self._t_fac.ravel()[k]
        base = np.array([CLASS_REFLECTANCE[i] for i in range(5)])
        return cls, base[cls] * fac

    def _normal_local(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        x = np.ascontiguousarray(x, dtype=np.float64)
        y = np.ascontiguousarray(y, dtype=np.float64)
        gx, gy = self._ground_grad_local(x, y)
        sel, k = self._building_lookup(x, y)
        if sel.size:
            gx[sel], gy[sel] = self._roof_gradient(x[sel], y[sel], k)
        sel, k = self._tree_lookup(x, y)
        if sel.size:
            eps = 0.01
            xs, ys = x[sel], y[sel]
            gx[sel] = (self._crown_height(xs + eps, ys, k)
                       - self._crown_height(xs - eps, ys, k)) / (2 * eps)
            gy[sel] = (self._crown_height(xs, ys + eps, k)
                       - self._crown_height(xs, ys - eps, k)) / (2 * eps)
        n = np.stack([-gx, -gy, np.ones_like(gx)], axis=-1)
        return n / np.linalg.norm(n, axis=-1, keepdims=True)

    def _wall_normal_local(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Horizontal outward normal of the nearest object edge (for points on or in objects).

        Points in no object get (0, 0, 1).
        """
        x = np.ascontiguousarray(x, dtype=np.float64)
        y = np.ascontiguousarray(y, dtype=np.float64)
        n = np.zeros((x.size, 3))
        n[:, 2] = 1.0
        sel, k = self._building_lookup(x, y)
        if sel.size:
            u, v = self._building_local_uv(x[sel], y[sel], k)
            a, b = self._b_a.ravel()[k], self._b_b.ravel()[k]
            end = (a - np.abs(u)) < (b - np.abs(v))
            nu = np.where(end, np.sign(u), 0.0)
            nv = np.where(end, 0.0, np.sign(v))
            c, s = self._b_cos.ravel()[k], self._b_sin.ravel()[k]
            n[sel] = np.stack([nu * c - nv * s, nu * s + nv * c, np.zeros_like(nu)], axis=-1)
        sel, k = self._tree_lookup(x, y)
        if sel.size:
            u, v = self._tree_uv(x[sel], y[sel], k)
            nu = u / self._t_ra.ravel()[k] ** 2
            nv = v / self._t_rb.ravel()[k] ** 2
            c, s = self._t_cos.ravel()[k], self._t_sin.ravel()[k]
            w = np.stack([nu * c - nv * s, nu * s + nv * c, np.zeros_like(nu)], axis=-1)
            norm = np.linalg.norm(w, axis=-1, keepdims=True)
            n[sel] = np.where(norm > 0, w / np.where(norm > 0, norm, 1.0), [[0.0, 0.0, 1.0]])
        return n

    # ------------------------------------------------------------------ public API (map frame)

    def _to_local(self, x: np.ndarray | float, y: np.ndarray | float
                  ) -> tuple[np.ndarray, np.ndarray, tuple[int, ...]]:
        xa = np.asarray(x, dtype=np.float64) - self.origin[0]
        ya = np.asarray(y, dtype=np.float64) - self.origin[1]
        xa, ya = np.broadcast_arrays(xa, ya)
        return xa.ravel(), ya.ravel(), xa.shape

    def height(self, x: np.ndarray | float, y: np.ndarray | float) -> np.ndarray:
        """Surface height (DSM: ground, roofs, crowns) at map coordinates, metres."""
        xl, yl, shape = self._to_local(x, y)
        return self._height_local(xl, yl).reshape(shape)

    def ground_height(self, x: np.ndarray | float, y: np.ndarray | float) -> np.ndarray:
        """Bare-ground height (ignores buildings and trees), metres."""
        xl, yl, shape = self._to_local(x, y)
        return self._ground_local(xl, yl).reshape(shape)

    def surface_class(self, x: np.ndarray | float, y: np.ndarray | float) -> np.ndarray:
        """Surface class codes (int8): 0 soil, 1 grass, 2 asphalt, 3 roof, 4 tree crown."""
        xl, yl, shape = self._to_local(x, y)
        return self._class_and_reflectance_local(xl, yl)[0].reshape(shape)

    def reflectance(self, x: np.ndarray | float, y: np.ndarray | float) -> np.ndarray:
        """True Lambertian reflectance of the surface (class value, +-10% per object/patch)."""
        xl, yl, shape = self._to_local(x, y)
        return self._class_and_reflectance_local(xl, yl)[1].reshape(shape)

    def normal(self, x: np.ndarray | float, y: np.ndarray | float) -> np.ndarray:
        """Upward unit normal of the surface, shape ``(*shape, 3)``.

        Analytic on the ground and roofs, central differences (1 cm) on tree crowns. Walls are
        not part of the height field: see :meth:`wall_normal`.
        """
        xl, yl, shape = self._to_local(x, y)
        return self._normal_local(xl, yl).reshape(*shape, 3)

    def wall_normal(self, x: np.ndarray | float, y: np.ndarray | float) -> np.ndarray:
        """Horizontal outward normal of the nearest wall of the object at (x, y)."""
        xl, yl, shape = self._to_local(x, y)
        return self._wall_normal_local(xl, yl).reshape(*shape, 3)

    def buildings(self) -> list[dict[str, Any]]:
        """Description of every building (map coordinates), for truth files and tests."""
        out: list[dict[str, Any]] = []
        for iy, ix in zip(*np.nonzero(self._b_has)):
            az = math.atan2(float(self._b_sin[iy, ix]), float(self._b_cos[iy, ix]))
            out.append({
                "x": float(self._b_cx[iy, ix]) + self.origin[0],
                "y": float(self._b_cy[iy, ix]) + self.origin[1],
                "length": 2.0 * float(self._b_a[iy, ix]),
                "width": 2.0 * float(self._b_b[iy, ix]),
                "azimuth_rad": az,
                "roof": ROOF_TYPE_NAMES[int(self._b_roof[iy, ix])],
                "slope_deg": math.degrees(math.atan(float(self._b_tan[iy, ix]))),
                "eave_height": float(self._b_eave[iy, ix]),
                "base": float(self._b_base[iy, ix]),
                "top": float(self._b_top[iy, ix]),
            })
        return out

    @property
    def n_buildings(self) -> int:
        return int(self._b_has.sum())

    @property
    def n_trees(self) -> int:
        return int(self._t_has.sum())

    def describe(self) -> dict[str, object]:
        """Summary for a truth file."""
        return {
            "kind": self.kind, "seed": self.seed, "extent_local": list(self.extent),
            "origin": list(self.origin), "n_buildings": self.n_buildings,
            "n_trees": self.n_trees, "n_roads": int(self._roads.shape[0]),
            "clear_radius": self.clear_radius,
            "keep_clear_local": self.keep_clear.tolist(),
        }

    # ------------------------------------------------------------------ rasters for ray casting

    def _fine_max(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        ny, nx = self._r_fine.shape
        ix = np.floor((x - self._r_x0) * (1.0 / self._r_res)).astype(np.int64)
        iy = np.floor((y - self._r_y0) * (1.0 / self._r_res)).astype(np.int64)
        valid = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
        m = self._r_fine[np.clip(iy, 0, ny - 1), np.clip(ix, 0, nx - 1)]
        return np.where(valid, m, _NO_OBJECT)

    def _coarse_max(self, x: np.ndarray, y: np.ndarray, reach: float) -> np.ndarray:
        """Max object top within at least ``reach`` metres (horizontally) of (x, y)."""
        cells = int(math.ceil(reach / self._c_res)) + 1
        if cells not in self._c_cache:
            self._c_cache[cells] = maximum_filter(self._c_raw, size=2 * cells + 1,
                                                  mode="constant", cval=_NO_OBJECT)
        grid = self._c_cache[cells]
        ny, nx = grid.shape
        ix = np.floor((x - self._r_x0) / self._c_res).astype(np.int64)
        iy = np.floor((y - self._r_y0) / self._c_res).astype(np.int64)
        # a point outside the grid may still be near objects on its edge: clip (conservative)
        return grid[np.clip(iy, 0, ny - 1), np.clip(ix, 0, nx - 1)]


class RasterTerrain(Terrain):
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
        self.seed = 0
        self.origin = (0.0, 0.0)
        self.extent = (self._west, self._west + cols * cell_m, self._north - rows * cell_m,
                       self._north)
        self.clear_radius = 0.0
        self.keep_clear = np.zeros((0, 2))
        self.max_object_top = -math.inf  # no objects: rays meet the height field directly
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

    def _ground_local(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
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

    def _height_local(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return self._ground_local(x, y)

    def _class_and_reflectance_local(self, x: np.ndarray, y: np.ndarray
                                     ) -> tuple[np.ndarray, np.ndarray]:
        n = np.asarray(x).size
        return np.full(n, SOIL, dtype=np.int8), np.full(n, CLASS_REFLECTANCE[SOIL])

    def _normal_local(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        gx, gy = self._ground_grad_local(x, y)
        n = np.stack([-gx, -gy, np.ones_like(gx)], axis=-1)
        return n / np.linalg.norm(n, axis=-1, keepdims=True)

    def _wall_normal_local(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        out = np.zeros((np.asarray(x).size, 3))
        out[:, 2] = 1.0
        return out

    @property
    def n_buildings(self) -> int:
        return 0

    @property
    def n_trees(self) -> int:
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

    def ray_hit(self, o: np.ndarray, d: np.ndarray, *, block: int = 32_768) -> np.ndarray:
        """Distance along each downward ray to the first crossing of the height field.

        The ray is sampled from the grid's highest to its lowest height at steps of half a
        cell horizontally (a bilinear surface has no feature narrower than a cell), and the
        first crossing found is refined by bisection.
        """
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
                     - self._ground_local(oo[:, 0, None] + ts * dd[:, 0, None],
                                          oo[:, 1, None] + ts * dd[:, 1, None])) > 0
            j = np.argmin(above, axis=1)  # first sample below the surface
            rows = np.arange(ts.shape[0])
            a, b = ts[rows, np.maximum(j - 1, 0)], ts[rows, j]
            for _ in range(48):
                mid = 0.5 * (a + b)
                f = (oo[:, 2] + mid * dd[:, 2]
                     - self._ground_local(oo[:, 0] + mid * dd[:, 0], oo[:, 1] + mid * dd[:, 1]))
                a = np.where(f > 0, mid, a)
                b = np.where(f > 0, b, mid)
            out[sl] = 0.5 * (a + b)
        return out


# ---------------------------------------------------------------------- ray casting


def _ground_hit(terrain: Terrain, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Distance along each ray to the smooth ground (Newton), or to a gridded DSM."""
    if isinstance(terrain, RasterTerrain):
        return terrain.ray_hit(o, d)
    t = (o[:, 2] - terrain._ground_local(o[:, 0], o[:, 1])) / -d[:, 2]
    if terrain.kind == "flat":
        return (o[:, 2] - 0.0) / -d[:, 2]
    for _ in range(30):
        x = o[:, 0] + t * d[:, 0]
        y = o[:, 1] + t * d[:, 1]
        g = terrain._ground_local(x, y)
        gx, gy = terrain._ground_grad_local(x, y)
        f = o[:, 2] + t * d[:, 2] - g
        fp = d[:, 2] - gx * d[:, 0] - gy * d[:, 1]
        step = f / fp
        t = t - step
        if np.max(np.abs(step)) < 1e-10:
            break
    return t


def cast_rays(
    terrain: Terrain,
    origins: np.ndarray,
    directions: np.ndarray,
    *,
    step: float = 0.5,
    tol: float = 1e-6,
    block: int = 262_144,
) -> RayHits:
    """First intersection of downward rays with the terrain surface (walls included).

    Parameters
    ----------
    terrain : Terrain
    origins : (n, 3) float64
        Ray origins, *local* coordinates (map minus ``terrain.origin``), above the surface.
    directions : (n, 3) float64
        Unit directions, pointing down (``d_z < 0``), at most ~60 deg off nadir.
    step : float
        Longest march step along a ray, metres (<= 0.5 m).
    tol : float
        Bisection stops when the bracket is shorter than this, metres.
    block : int
        Rays processed at a time (bounds memory).

    Returns
    -------
    RayHits
    """
    origins = np.ascontiguousarray(origins, dtype=np.float64).reshape(-1, 3)
    directions = np.ascontiguousarray(directions, dtype=np.float64).reshape(-1, 3)
    if origins.shape != directions.shape:
        raise ConfigError("cast_rays: origins and directions differ in shape")
    if np.any(directions[:, 2] >= -1e-3):
        raise ConfigError("cast_rays: every ray must point down")
    n = origins.shape[0]
    t_all = np.empty(n)
    wall_all = np.zeros(n, dtype=bool)
    inside_all = np.empty((n, 3))
    for i0 in range(0, n, block):
        i1 = min(i0 + block, n)
        t, wall, t_in = _cast_block(terrain, origins[i0:i1], directions[i0:i1], step, tol)
        t_all[i0:i1] = t
        wall_all[i0:i1] = wall
        inside_all[i0:i1] = origins[i0:i1] + t_in[:, None] * directions[i0:i1]
    xyz = origins + t_all[:, None] * directions
    return RayHits(t=t_all, xyz=xyz, on_wall=wall_all, inside=inside_all)


def _cast_block(
    terrain: Terrain, o: np.ndarray, d: np.ndarray, step: float, tol: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    n = o.shape[0]
    t_g = _ground_hit(terrain, o, d)
    t_hit = t_g.copy()
    t_in = t_g.copy()
    wall = np.zeros(n, dtype=bool)
    if terrain.kind == "flat" or not math.isfinite(terrain.max_object_top):
        return t_hit, wall, t_in
    step = min(step, 0.5)
    dxy = np.hypot(d[:, 0], d[:, 1])
    tan_max = float(np.max(dxy / -d[:, 2]))
    ground_min = float(np.min(o[:, 2] + t_g * d[:, 2]))
    reach = max(terrain.max_object_top - ground_min, 0.0) * tan_max + 1.0
    gx = o[:, 0] + t_g * d[:, 0]
    gy = o[:, 1] + t_g * d[:, 1]
    z_top = terrain._coarse_max(gx, gy, reach).astype(np.float64)
    t_top = np.maximum((o[:, 2] - z_top) / -d[:, 2], 0.0)
    cand = np.flatnonzero((z_top > _NO_OBJECT / 2) & (t_top < t_g))
    if cand.size == 0:
        return t_hit, wall, t_in
    # sample the stretch [t_top, t_g] at <= one raster cell horizontally; a segment whose lower
    # end is above the dilated max of its upper end's cell cannot meet an object
    res = terrain._r_res
    length_h = (t_g[cand] - t_top[cand]) * dxy[cand]
    k_need = np.ceil(length_h / (0.999 * res)).astype(np.int64) + 1
    k_bucket = np.maximum(2, 2 ** np.ceil(np.log2(np.maximum(k_need, 2))).astype(np.int64))
    t_start = np.full(cand.size, np.inf)
    for kb in np.unique(k_bucket):
        sel = np.flatnonzero(k_bucket == kb)
        idx = cand[sel]
        frac = np.linspace(0.0, 1.0, int(kb))
        ts = t_top[idx, None] + (t_g[idx] - t_top[idx])[:, None] * frac[None, :]
        xs = o[idx, 0, None] + ts * d[idx, 0, None]
        ys = o[idx, 1, None] + ts * d[idx, 1, None]
        zs = o[idx, 2, None] + ts * d[idx, 2, None]
        m = terrain._fine_max(xs[:, :-1].ravel(), ys[:, :-1].ravel()).reshape(len(idx), -1)
        unsafe = zs[:, 1:] <= m
        has = unsafe.any(axis=1)
        j = np.argmax(unsafe, axis=1)
        rows = np.arange(len(idx))
        mj = m[rows, j].astype(np.float64)
        t_m = (o[idx, 2] - mj) / -d[idx, 2]
        ts_j = ts[rows, j]
        t_start[sel] = np.where(has, np.maximum(ts_j, t_m), np.inf)
    march = np.isfinite(t_start)
    idx = cand[march]
    if idx.size == 0:
        return t_hit, wall, t_in
    lo = t_start[march]
    tg = t_g[idx]
    lo = np.minimum(lo, tg)
    hi = np.empty_like(lo)
    # march: find the first step whose end is below the surface (or reaches the ground hit)
    active = np.arange(idx.size)
    cur = lo.copy()
    while active.size:
        ii = idx[active]
        nxt = np.minimum(cur[active] + step, tg[active])
        x = o[ii, 0] + nxt * d[ii, 0]
        y = o[ii, 1] + nxt * d[ii, 1]
        z = o[ii, 2] + nxt * d[ii, 2]
        below = (z <= terrain._height_local(x, y)) | (nxt >= tg[active])
        done = active[below]
        lo[done] = cur[done]
        hi[done] = nxt[below]
        cur[active[~below]] = nxt[~below]
        active = active[~below]
    # bisection: lo above the surface, hi below it (or at the ground hit)
    n_iter = max(int(math.ceil(math.log2(max(step, tol) / tol))) + 1, 1)
    for _ in range(n_iter):
        mid = 0.5 * (lo + hi)
        x = o[idx, 0] + mid * d[idx, 0]
        y = o[idx, 1] + mid * d[idx, 1]
        z = o[idx, 2] + mid * d[idx, 2]
        below = z <= terrain._height_local(x, y)
        hi = np.where(below, mid, hi)
        lo = np.where(below, lo, mid)
    # a wall: the surface jumps across the final (sub-micrometre) bracket
    h_lo = terrain._height_local(o[idx, 0] + lo * d[idx, 0], o[idx, 1] + lo * d[idx, 1])
    h_hi = terrain._height_local(o[idx, 0] + hi * d[idx, 0], o[idx, 1] + hi * d[idx, 1])
    is_wall = (h_hi - h_lo) > 1e-3
    t_hit[idx] = 0.5 * (lo + hi)
    t_in[idx] = hi
    wall[idx] = is_wall
    return t_hit, wall, t_in
