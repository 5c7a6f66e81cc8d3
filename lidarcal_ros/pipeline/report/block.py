"""The block pass of ``lidarcal report``: every strip once through the correction, what it keeps.

Each strip is a task of an executor (here, or a Dask worker: ``--dask``), sent in it; what
the tasks keep is summed here in the strips' order, as a serial pass sums it.
"""

from __future__ import annotations

import datetime
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from lidarcal_ros.core.calibration.calibrate import Progress
from lidarcal_ros.core.config import FlightConfig
from lidarcal_ros.core.flags import (
    FLAG_NO_INTENSITY,
    FLAG_NO_NORMAL,
    FLAG_NOT_CORRECTED,
    FLAG_ROUGH,
    FLAG_VOLUME,
)
from lidarcal_ros.core.mission import ControlPoints, Mission, Strip, Trajectory
from lidarcal_ros.core.normals.grid_normals import cell_size, finite_rows, grid_normals
from lidarcal_ros.core.qa.swath_differences import (
    SMOOTH_SLOPE_DEG,
    BlockGrid,
    CellHeights,
    cell_heights,
)
from lidarcal_ros.core.radiometry import volume_returns
from lidarcal_ros.io.report.content import FlightMap, MapRaster, StripRow
from lidarcal_ros.pipeline.correction.apply import (
    CorrectionSettings,
    correct_columns,
    surface_points,
    trajectory_heading,
)
from lidarcal_ros.pipeline.executor import (
    CommandTasks,
    Executor,
    SerialExecutor,
    results_in_turn,
)

__all__ = [
    "EXCLUDED_FLAGS", "FOOTPRINT_CELL_M", "MAP_MAX_CELLS", "MAP_STRIP_SPACINGS",
    "SWATH_CELL_SPACINGS", "SWATH_MAX_CELLS", "TRAJECTORY_MAP_POINTS", "BlockPass",
    "StripFootprint", "block_grids", "block_pass", "cell_sums", "flight_map", "time_text",
]

#: Most cells along the longer side of the intensity and reflectance maps.
MAP_MAX_CELLS = 600
#: Map cell in point spacings of the sparsest strip at least (so that where it flies alone,
#: at the block's edges, most cells hold a point or two).
MAP_STRIP_SPACINGS = 2.0
#: Points left out of the slope statistics: not corrected, no normal, no intensity, a
#: rough neighbourhood (edges, vegetation: slope and incidence uncertain) or a volume return
#: (canopy: no surface).
EXCLUDED_FLAGS = (FLAG_NOT_CORRECTED | FLAG_NO_NORMAL | FLAG_NO_INTENSITY | FLAG_ROUGH
                  | FLAG_VOLUME)
#: Cell of the strips' footprints (density, coverage), metres.
FOOTPRINT_CELL_M = 10.0
#: Cell of the swath differences in nominal pulse spacings (the LBS's "twice the NPS").
SWATH_CELL_SPACINGS = 2.0
#: Most cells along the longer side of the swath differences' grid.
SWATH_MAX_CELLS = 1500
#: Most trajectory samples drawn on the block map.
TRAJECTORY_MAP_POINTS = 4000
#: Times above this (s) are absolute (UNIX, after 1973) and shown as UTC dates.
_ABSOLUTE_TIME_S = 1e8


# ---------------------------------------------------------------------------- block pass
@dataclass
class StripFootprint:
    """Where a strip's points fall: its cells of :data:`FOOTPRINT_CELL_M` (sorted keys of a
    :class:`~lidarcal_ros.core.qa.swath_differences.BlockGrid`)."""

    strip_id: int
    keys: np.ndarray

    @property
    def area_m2(self) -> float:
        """The area of the strip's footprint cells, m^2."""
        return float(self.keys.size) * FOOTPRINT_CELL_M**2


@dataclass
class BlockPass:
    """What one correction pass over every strip gives the report (docs/internals.md).

    Attributes
    ----------
    surfaces : list of (int, float, CellHeights, CellHeights)
        Per strip: id, median time (s), its surface as delivered and as corrected.
    rows : list of StripRow
    footprints : list of StripFootprint
    slope, intensity, reflectance : (k,) float32
        The points of the slope statistics.
    map_sums : (3, ny * nx) float64
        Per map cell: sums of intensity and reflectance, and the number of points.
    n_radiometric : int
        Points with an intensity.
    """

    surfaces: list[tuple[int, float, CellHeights, CellHeights]] = field(default_factory=list)
    rows: list[StripRow] = field(default_factory=list)
    footprints: list[StripFootprint] = field(default_factory=list)
    slope: list[np.ndarray] = field(default_factory=list)
    intensity: list[np.ndarray] = field(default_factory=list)
    reflectance: list[np.ndarray] = field(default_factory=list)
    map_sums: np.ndarray = field(default_factory=lambda: np.zeros((3, 0)))
    n_radiometric: int = 0


def time_text(t: float) -> str:
    """A time as UTC (absolute) or seconds (relative)."""
    if t > _ABSOLUTE_TIME_S:
        stamp = datetime.datetime.fromtimestamp(t, tz=datetime.UTC)
        return stamp.strftime("%Y-%m-%d %H:%M:%S UTC")
    return f"{t:.1f} s"


def _strip_row(strip_id: int, t: np.ndarray, z: np.ndarray, trajectory: Trajectory,
               footprint: StripFootprint) -> StripRow:
    """The block table's row of a strip (:class:`StripRow`)."""
    t0, t1 = float(np.nanmin(t)), float(np.nanmax(t))
    inside = (trajectory.t >= t0) & (trajectory.t <= t1)
    path = trajectory.xyz[inside]
    if path.shape[0] >= 2:
        steps = np.diff(path[:, :2], axis=0)
        length = float(np.sum(np.hypot(steps[:, 0], steps[:, 1])))
        dx, dy = path[-1, :2] - path[0, :2]
        heading = math.degrees(math.atan2(dx, dy)) % 360.0
        height = float(np.median(path[:, 2]) - np.nanmedian(z))
    else:
        length = heading = height = math.nan
    duration = t1 - t0
    return StripRow(strip_id, int(t.size), time_text(t0), duration, length, heading,
                    length / duration if duration > 0 else math.nan, height,
                    t.size / footprint.area_m2 if footprint.area_m2 > 0 else math.nan)


@dataclass
class _BlockGrids:
    """The grids of a block pass (:func:`block_grids`)."""

    swath: BlockGrid
    footprint: BlockGrid
    map: BlockGrid


@dataclass
class _StripPass:
    """What the block pass keeps of one strip (a task's result; the fields of
    :class:`BlockPass` for one strip, the map's sums only in ``map_cells``: None without
    intensity)."""

    surface: tuple[int, float, CellHeights, CellHeights]
    footprint: StripFootprint
    row: StripRow
    map_cells: np.ndarray | None = None
    map_sums: np.ndarray | None = None
    slope: np.ndarray | None = None
    intensity: np.ndarray | None = None
    reflectance: np.ndarray | None = None


def _strip_pass(strip: Strip, trajectory: Trajectory, settings: CorrectionSettings,
                grids: _BlockGrids) -> _StripPass:
    """One strip through the correction, what the report keeps of it (a task)."""
    heading = trajectory_heading(trajectory, float(np.nanmedian(strip.t)))
    finite = finite_rows(strip.xyz) & np.isfinite(strip.t)
    # The normals of the last returns (volume returns: none, as lidarcal correct).
    volume = volume_returns(strip.extra.get("return_number"),
                            strip.extra.get("number_of_returns"))
    surface = surface_points(strip.xyz, volume)
    fitted = finite_rows(surface) & np.isfinite(strip.t)
    normals = grid_normals(surface, heading,
                           cell_m=cell_size(surface[fitted], heading, strip.t[fitted]))
    res = correct_columns(strip.xyz, strip.t, strip.intensity, trajectory,
                          settings, normals=normals, source=f"strip {strip.strip_id}",
                          volume=volume, strip_id=strip.strip_id)
    with np.errstate(invalid="ignore"):
        slope = np.degrees(np.arccos(np.clip(np.abs(normals.normals[:, 2]), 0.0, 1.0)))
    rough = normals.rough if normals.rough is not None else np.zeros(len(strip), bool)
    corrected = (res.flags & FLAG_NOT_CORRECTED) == 0
    smooth = normals.valid & ~rough & (slope < SMOOTH_SLOPE_DEG) & corrected
    keys = grids.footprint.keys(strip.xyz[finite, :2])
    footprint = StripFootprint(strip.strip_id, np.unique(keys[keys >= 0]))
    out = _StripPass((strip.strip_id, float(np.nanmedian(strip.t)),
                      cell_heights(grids.swath, strip.xyz, normals.normals, smooth),
                      cell_heights(grids.swath, res.xyz, normals.normals, smooth)),
                     footprint, _strip_row(strip.strip_id, strip.t[finite],
                                           res.xyz[finite, 2], trajectory, footprint))
    if strip.intensity is None:
        return out
    intensity = np.asarray(strip.intensity, dtype=np.float64)
    mapped = np.isfinite(res.reflectance) & np.isfinite(intensity)
    m = grids.map
    sums = np.array([cell_sums(res.xyz[mapped, :2], values, x0=m.x0, y0=m.y0, cell_m=m.cell_m,
                               shape=(m.ny, m.nx))[0]
                     for values in (intensity[mapped], res.reflectance[mapped],
                                    np.ones(int(mapped.sum())))])
    # (the cells holding points: the others' sums are zeros, which add nothing)
    out.map_cells = np.flatnonzero(sums[2])
    out.map_sums = sums[:, out.map_cells]
    usable = mapped & ((res.flags & EXCLUDED_FLAGS) == 0) & np.isfinite(slope)
    out.slope = slope[usable].astype(np.float32)
    out.intensity = intensity[usable].astype(np.float32)
    out.reflectance = res.reflectance[usable]
    return out


def block_pass(
    mission: Mission,
    settings: CorrectionSettings,
    *,
    swath_grid: BlockGrid,
    footprint_grid: BlockGrid,
    map_grid: BlockGrid,
    progress: Progress | None = None,
    executor: Executor | CommandTasks | None = None,
) -> BlockPass:
    """Correct every strip once and keep what the report needs of it (docs/internals.md).

    Parameters
    ----------
    mission : Mission
    settings : CorrectionSettings
        Biases and radiometric model (with the calibration constant, if any).
    swath_grid, footprint_grid : BlockGrid
        Grids of the swath differences and of the footprints.
    map_grid : BlockGrid
        The grid of the intensity and reflectance maps (:func:`block_grids`).
    progress : callable, optional
    executor : Executor or CommandTasks, optional
        Where each strip is corrected, a task a strip (default: here); what they keep is
        gathered here in the strips' order, so the pass is the serial one.
    """
    tasks = executor if isinstance(executor, CommandTasks) else \
        CommandTasks(executor or SerialExecutor(), "report")
    out = BlockPass(map_sums=np.zeros((3, map_grid.ny * map_grid.nx)))
    strips = [s for s in mission.strips if len(s)]
    trajectory = tasks.send(mission.trajectory, "trajectory")
    grids = _BlockGrids(swath_grid, footprint_grid, map_grid)
    futures = [tasks.submit(_strip_pass, tasks.send(strip, f"strip{strip.strip_id}"),
                            trajectory, settings, grids, key=f"pass{k}")
               for k, strip in enumerate(strips)]
    if progress is not None:
        progress("correcting strips", 0.0)
    for k, (strip, part) in enumerate(zip(strips, results_in_turn(futures), strict=True)):
        if progress is not None:
            progress("correcting strips", k / len(strips))
        out.surfaces.append(part.surface)
        out.footprints.append(part.footprint)
        out.rows.append(part.row)
        if part.map_cells is None:
            continue
        assert part.map_sums is not None and part.slope is not None and \
            part.intensity is not None and part.reflectance is not None
        out.n_radiometric += len(strip)
        out.map_sums[:, part.map_cells] += part.map_sums
        out.slope.append(part.slope)
        out.intensity.append(part.intensity)
        out.reflectance.append(part.reflectance)
    return out


def cell_sums(xy: np.ndarray, values: np.ndarray, *, x0: float, y0: float, cell_m: float,
               shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Sums of ``values`` and counts per cell, flat (points outside ignored)."""
    ny, nx = shape
    col = np.floor((xy[:, 0] - x0) / cell_m).astype(np.int64)
    row = np.floor((xy[:, 1] - y0) / cell_m).astype(np.int64)
    inside = (col >= 0) & (col < nx) & (row >= 0) & (row < ny)
    key = row[inside] * nx + col[inside]
    sums = np.bincount(key, weights=np.asarray(values, dtype=np.float64)[inside],
                       minlength=nx * ny)
    return sums, np.bincount(key, minlength=nx * ny)



# ---------------------------------------------------------------------------- block
def block_grids(mission: Mission, config: FlightConfig) -> tuple[BlockGrid, BlockGrid, BlockGrid]:
    """The grids of the footprints (:data:`FOOTPRINT_CELL_M`), of the swath differences (twice
    the nominal pulse spacing) and of the intensity and reflectance maps, over the block."""
    bounds = [(np.nanmin(s.xyz[:, :2], axis=0), np.nanmax(s.xyz[:, :2], axis=0))
              for s in mission.strips if len(s)]
    lo = np.min([b[0] for b in bounds], axis=0)
    hi = np.max([b[1] for b in bounds], axis=0)
    footprint = BlockGrid.covering(lo, hi, FOOTPRINT_CELL_M)
    # The nominal pulse spacing of single strips: their median density over their footprints.
    densities = []
    for s in mission.strips:
        keys = footprint.keys(s.xyz[:, :2])
        cells = np.unique(keys[keys >= 0]).size
        if cells:
            densities.append(len(s) / (cells * FOOTPRINT_CELL_M**2))
    spacing = 1.0 / math.sqrt(float(np.median(densities))) if densities else 1.0
    span = float(np.max(hi - lo))
    swath = BlockGrid.covering(lo, hi, max(SWATH_CELL_SPACINGS * spacing, 0.5,
                                           span / SWATH_MAX_CELLS))
    # Map cells hold points of the sparsest strip too (where it flies alone, at the edges).
    sparsest = 1.0 / math.sqrt(float(np.min(densities))) if densities else 1.0
    cell = max(span / MAP_MAX_CELLS, MAP_STRIP_SPACINGS * sparsest, 1e-3)
    shape = (int((hi[1] - lo[1]) // cell) + 1, int((hi[0] - lo[0]) // cell) + 1)
    return footprint, swath, BlockGrid(float(lo[0]), float(lo[1]), cell, nx=shape[1], ny=shape[0])


def flight_map(mission: Mission, footprints: Sequence[StripFootprint], grid: BlockGrid, *,
               check_points: ControlPoints | None = None,
               target: tuple[float, float, float, float] | None = None) -> FlightMap:
    """The block map's content (:class:`~lidarcal_ros.io.report.content.FlightMap`)."""
    traj = mission.trajectory
    step = max(1, len(traj) // TRAJECTORY_MAP_POINTS)
    drawn = traj.xyz[::step, :2].copy()
    # No line across a gap in the trajectory (turns not recorded).
    dt = np.diff(traj.t[::step])
    if dt.size:
        gaps = np.flatnonzero(dt > 10.0 * max(float(np.median(dt)), 1e-6)) + 1
        drawn = np.insert(drawn, gaps, np.nan, axis=0)
    lines = []
    for strip in mission.strips:
        if not len(strip):
            continue
        inside = (traj.t >= np.nanmin(strip.t)) & (traj.t <= np.nanmax(strip.t))
        xy = traj.xyz[inside, :2]
        lines.append((strip.strip_id, xy[::max(1, xy.shape[0] // 200)]))
    counts = np.zeros(grid.nx * grid.ny)
    for f in footprints:
        counts[f.keys] += 1
    coverage = MapRaster(counts.reshape(grid.ny, grid.nx), grid.x0, grid.y0, grid.cell_m)

    def named(points: ControlPoints | None) -> list[tuple[str, float, float]]:
        if points is None:
            return []
        return [(str(i), float(p[0]), float(p[1])) for i, p in zip(points.ids, points.xyz)]

    return FlightMap(drawn, lines, coverage, named(mission.control),
                     named(check_points), target)

