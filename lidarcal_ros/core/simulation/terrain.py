"""The analytic terrain of simulated LiDAR missions: a built-up or flat area from a seed.

Ground, land cover, buildings and trees in local coordinates around (0, 0)
(docs/internals.md, "The simulator").
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from lidarcal_ros.core.simulation.object_tops import ObjectTops
from lidarcal_ros.core.simulation.surface import (
    ASPHALT,
    CLASS_REFLECTANCE,
    GRASS,
    ROOF,
    SOIL,
    TREE,
    Surface,
)
from lidarcal_ros.core.simulation.terrain_objects import Buildings, Trees
from lidarcal_ros.errors import ConfigError

TERRAIN_KINDS = ("built-up", "flat")
PATCH_CELL = 70.0  # m, land-cover Voronoi seeds


@dataclass(frozen=True)
class Ground:
    """The bare ground: ``z = sum_i amplitude_i sin(kx_i x + ky_i y + phase_i)`` (metres,
    local coordinates); no term at all for flat ground."""

    amplitude: np.ndarray
    kx: np.ndarray
    ky: np.ndarray
    phase: np.ndarray
    #: Steepest slope the terms could add up to (dz/dxy).
    max_slope: float

    @classmethod
    def draw(cls, rng: np.random.Generator, *, undulating: bool) -> Ground:
        """Four waves of 300-900 m and 0.6-1.4 m amplitude in any direction, or flat ground
        (drawing nothing)."""
        if not undulating:
            none = np.zeros(0)
            return cls(none, none, none, none, 0.0)
        n = 4
        wavelength = rng.uniform(300.0, 900.0, n)
        azimuth = rng.uniform(0.0, math.pi, n)
        amp = rng.uniform(0.6, 1.4, n)
        k = 2.0 * math.pi / wavelength
        return cls(amp, k * np.cos(azimuth), k * np.sin(azimuth),
                   rng.uniform(0.0, 2.0 * math.pi, n), float(np.sum(amp * k)))

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """The ground's height at (x, y), metres."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        z = np.zeros(np.broadcast(x, y).shape)
        for a, kx, ky, ph in zip(self.amplitude, self.kx, self.ky, self.phase):
            z += a * np.sin(kx * x + ky * y + ph)
        return z

    def gradient(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """dz/dx and dz/dy of the ground at (x, y)."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        gx = np.zeros(np.broadcast(x, y).shape)
        gy = np.zeros_like(gx)
        for a, kx, ky, ph in zip(self.amplitude, self.kx, self.ky, self.phase):
            c = a * np.cos(kx * x + ky * y + ph)
            gx += c * kx
            gy += c * ky
        return gx, gy

    def ray_hit(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Distance along each downward unit ray to the ground (Newton from the height
        below its origin, to steps below 1e-10 m)."""
        t = (o[:, 2] - self.height(o[:, 0], o[:, 1])) / -d[:, 2]
        for _ in range(30):
            x = o[:, 0] + t * d[:, 0]
            y = o[:, 1] + t * d[:, 1]
            g = self.height(x, y)
            gx, gy = self.gradient(x, y)
            f = o[:, 2] + t * d[:, 2] - g
            fp = d[:, 2] - gx * d[:, 0] - gy * d[:, 1]
            step = f / fp
            t = t - step
            if np.max(np.abs(step)) < 1e-10:
                break
        return t


@dataclass(frozen=True)
class LandCover:
    """What covers the ground: Voronoi patches of soil, grass and asphalt, and roads.

    Attributes
    ----------
    roads : (4, 5) float64
        Per road: the unit normal (nx, ny) to its direction, ``c`` of its centre line
        ``nx x + ny y = c``, its half width (m) and its reflectance factor.
    patch_x0, patch_y0 : float
        Lower-left corner of the patch grid, metres.
    seed_x, seed_y : (rows, cols) float64
        Each patch's Voronoi seed, metres.
    patch_class : (rows, cols) int8
        Each patch's class (soil, grass or asphalt).
    patch_factor : (rows, cols) float64
        Each patch's departure from its class reflectance (0.9-1.1).
    """

    roads: np.ndarray
    patch_x0: float
    patch_y0: float
    seed_x: np.ndarray
    seed_y: np.ndarray
    patch_class: np.ndarray
    patch_factor: np.ndarray

    @classmethod
    def draw(cls, rng: np.random.Generator, extent: Sequence[float]) -> LandCover:
        """Two roughly north-south and two roughly east-west roads, 6-12 m wide, never through
        the centre; then patches on a 70 m jittered grid over the extent and a cell beyond."""
        xmin, xmax, ymin, ymax = extent
        cx, cy = 0.5 * (xmin + xmax), 0.5 * (ymin + ymax)
        rows = []
        for base_az in (0.0, 0.0, 0.5 * math.pi, 0.5 * math.pi):
            az = base_az + rng.uniform(-0.35, 0.35)
            span = (xmax - xmin) if base_az == 0.0 else (ymax - ymin)
            off = rng.uniform(0.15, 0.45) * span * rng.choice([-1.0, 1.0])
            # unit normal to the road direction (road direction = (sin az, cos az))
            nx, ny = math.cos(az), -math.sin(az)
            c = nx * cx + ny * cy + off
            width = rng.uniform(6.0, 12.0)
            rows.append((nx, ny, c, 0.5 * width, rng.uniform(0.9, 1.1)))
        roads = np.array(rows, dtype=np.float64).reshape(-1, 5)
        cs = PATCH_CELL
        x0, y0 = xmin - cs, ymin - cs
        nx = int(math.ceil((xmax - xmin) / cs)) + 3
        ny = int(math.ceil((ymax - ymin) / cs)) + 3
        jx, jy = rng.uniform(0.1, 0.9, (2, ny, nx))
        ix = np.arange(nx)[None, :]
        iy = np.arange(ny)[:, None]
        patch_class = rng.choice(
            np.array([SOIL, GRASS, ASPHALT], dtype=np.int8), size=(ny, nx), p=[0.4, 0.45, 0.15]
        )
        return cls(roads, x0, y0, x0 + (ix + jx) * cs, y0 + (iy + jy) * cs, patch_class,
                   rng.uniform(0.9, 1.1, (ny, nx)))

    def road_distance(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """(n, n_roads) distance to each road's edge (negative inside the road), metres."""
        r = self.roads
        return np.abs(x[:, None] * r[:, 0] + y[:, None] * r[:, 1] - r[:, 2]) - r[:, 3]

    def cover(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Class (int8) and reflectance factor of the ground at (x, y), objects ignored."""
        cs = PATCH_CELL
        ny, nx = self.seed_x.shape
        ix = np.floor((x - self.patch_x0) / cs).astype(np.int64)
        iy = np.floor((y - self.patch_y0) / cs).astype(np.int64)
        best = np.full(x.shape, np.inf)
        bx = np.clip(ix, 0, nx - 1)
        by = np.clip(iy, 0, ny - 1)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                jx = np.clip(ix + dx, 0, nx - 1)
                jy = np.clip(iy + dy, 0, ny - 1)
                d = (x - self.seed_x[jy, jx]) ** 2 + (y - self.seed_y[jy, jx]) ** 2
                closer = d < best
                best = np.where(closer, d, best)
                bx = np.where(closer, jx, bx)
                by = np.where(closer, jy, by)
        cls = self.patch_class[by, bx].astype(np.int8)
        fac = self.patch_factor[by, bx]
        if self.roads.size:
            on_road = self.road_distance(x, y) <= 0.0
            any_road = on_road.any(axis=1)
            cls = np.where(any_road, np.int8(ASPHALT), cls)
            road_fac = self.roads[np.argmax(on_road, axis=1), 4]
            fac = np.where(any_road, road_fac, fac)
        return cls, fac


class Terrain(Surface):
    """The analytic surface: undulating ground, land cover, buildings and trees from a seed.

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
        # The order of the draws is the terrain's: the same seed, the same terrain.
        rng = np.random.default_rng([self.seed, 0x7E55A1])
        populated = kind != "flat"
        self._ground = Ground.draw(rng, undulating=populated)
        self.ground_max_slope = self._ground.max_slope
        self._cover = LandCover.draw(rng, self.extent)
        self._buildings = Buildings.draw(rng, self.extent, populated=populated,
                                         clear=self._clear, ground=self._ground.height)
        self._trees = Trees.draw(rng, self.extent, populated=populated, clear=self._clear,
                                 ground=self._ground.height, buildings=self._buildings)
        self.object_tops = (
            ObjectTops(self.extent, [self._buildings.footprints(), self._trees.footprints()])
            if self.n_buildings or self.n_trees else None)

    def _clear(self, x: np.ndarray, y: np.ndarray, radius: np.ndarray, road_gap: float
               ) -> np.ndarray:
        """Whether objects of ``radius`` at (x, y) stand ``road_gap`` metres off every road,
        ``clear_radius`` + 1 m from every place kept clear, and inside the extent."""
        ok = np.ones(x.shape, dtype=bool)
        if self._cover.roads.size:
            ok &= (self._cover.road_distance(x, y) > radius[:, None] + road_gap).all(axis=1)
        if self.keep_clear.size:
            d = np.hypot(x[:, None] - self.keep_clear[:, 0], y[:, None] - self.keep_clear[:, 1])
            ok &= (d > radius[:, None] + self.clear_radius + 1.0).all(axis=1)
        xmin, xmax, ymin, ymax = self.extent
        ok &= (x - radius >= xmin) & (x + radius <= xmax) & (y - radius >= ymin) & (
            y + radius <= ymax)
        return ok

    # ------------------------------------------------------------------ local queries

    def height_local(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Surface height (ground, roofs, crowns) at local (x, y) (n,), metres."""
        x = np.ascontiguousarray(x, dtype=np.float64)
        y = np.ascontiguousarray(y, dtype=np.float64)
        h = self._ground.height(x, y)
        if self.kind == "flat":
            return h
        sel, k = self._buildings.lookup(x, y)
        if sel.size:
            h[sel] = self._buildings.roof_height(x[sel], y[sel], k)
        sel, k = self._trees.lookup(x, y)
        if sel.size:
            h[sel] = self._trees.crown_surface(x[sel], y[sel], k)
        return h

    def ground_local(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Bare-ground height (buildings and trees ignored) at local (x, y) (n,), metres."""
        return self._ground.height(x, y)

    def class_and_reflectance_local(self, x: np.ndarray, y: np.ndarray
                                    ) -> tuple[np.ndarray, np.ndarray]:
        """Class code (int8) and Lambertian reflectance (the class's, times the object's or
        patch's factor) at local (x, y) (n,)."""
        x = np.ascontiguousarray(x, dtype=np.float64)
        y = np.ascontiguousarray(y, dtype=np.float64)
        cls, fac = self._cover.cover(x, y)
        sel, k = self._buildings.lookup(x, y)
        cls[sel] = ROOF
        fac[sel] = self._buildings.reflectance_factor[k]
        sel, k = self._trees.lookup(x, y)
        cls[sel] = TREE
        fac[sel] = self._trees.reflectance_factor[k]
        base = np.array([CLASS_REFLECTANCE[i] for i in range(5)])
        return cls, base[cls] * fac

    def normal_local(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Analytic on the ground and roofs, central differences (1 cm) on tree crowns."""
        x = np.ascontiguousarray(x, dtype=np.float64)
        y = np.ascontiguousarray(y, dtype=np.float64)
        gx, gy = self._ground.gradient(x, y)
        sel, k = self._buildings.lookup(x, y)
        if sel.size:
            gx[sel], gy[sel] = self._buildings.roof_gradient(x[sel], y[sel], k)
        sel, k = self._trees.lookup(x, y)
        if sel.size:
            gx[sel], gy[sel] = self._trees.crown_gradient(x[sel], y[sel], k)
        n = np.stack([-gx, -gy, np.ones_like(gx)], axis=-1)
        return n / np.linalg.norm(n, axis=-1, keepdims=True)

    def wall_normal_local(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Horizontal outward normal (n, 3) of the nearest wall of the building or tree at local
        (x, y) (n,); (0, 0, 1) where there is none."""
        x = np.ascontiguousarray(x, dtype=np.float64)
        y = np.ascontiguousarray(y, dtype=np.float64)
        n = np.zeros((x.size, 3))
        n[:, 2] = 1.0
        sel, k = self._buildings.lookup(x, y)
        if sel.size:
            n[sel] = self._buildings.wall_normal(x[sel], y[sel], k)
        sel, k = self._trees.lookup(x, y)
        if sel.size:
            n[sel] = self._trees.wall_normal(x[sel], y[sel], k)
        return n

    def ground_hit(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Distance (n,) along each downward unit ray (origins and directions (n, 3), local) to
        the ground, objects ignored, metres."""
        if self.kind == "flat":
            return (origins[:, 2] - 0.0) / -directions[:, 2]
        return self._ground.ray_hit(origins, directions)

    # ------------------------------------------------------------------ the whole terrain

    def buildings(self) -> list[dict[str, Any]]:
        """Description of every building (map coordinates), for truth files and tests."""
        return self._buildings.describe(self.origin)

    @property
    def n_buildings(self) -> int:
        """How many buildings stand on the terrain."""
        return self._buildings.count

    @property
    def n_trees(self) -> int:
        """How many trees stand on the terrain."""
        return self._trees.count

    def describe(self) -> dict[str, object]:
        """Summary for a truth file: kind, seed, extent and places kept clear (local), origin,
        object and road counts; metres."""
        return {
            "kind": self.kind, "seed": self.seed, "extent_local": list(self.extent),
            "origin": list(self.origin), "n_buildings": self.n_buildings,
            "n_trees": self.n_trees, "n_roads": int(self._cover.roads.shape[0]),
            "clear_radius": self.clear_radius,
            "keep_clear_local": self.keep_clear.tolist(),
        }


__all__ = ["PATCH_CELL", "TERRAIN_KINDS", "Ground", "LandCover", "Terrain"]
