"""What ``lidarcal report`` shows, computed from a mission bag, a calibration file and the
flight configuration with the procedures calibration, correction and evaluation use
themselves.

- Pairs: a :class:`~lidarcal_ros.core.calibrate.Calibrator` over the mission chooses the
  same sample points as ``lidarcal calibrate`` (same configuration, same seeds) and matches
  them at zero biases ("before") and at the calibration file's estimate ("after"): per strip
  pair, the signed normal discrepancy of every matched point with its map position, whose
  robust RMS is the calibration's own pair QA; and the control-point residuals.
- The block pass: every strip once through
  :func:`~lidarcal_ros.pipeline.correction.correct_columns` (the correction ``lidarcal
  correct`` applies) with the surface normals it needs fitted once
  (:func:`~lidarcal_ros.core.normals.grid_normals`). From it: the strip's surface on the
  block's grid as delivered and as corrected, whose differences between strips are the
  swath-to-swath height differences (:mod:`lidarcal_ros.core.swath_differences`); the
  terrain slope of each point, with which the variance-to-mean ratio of the recorded
  intensity (before) and of the reflectance (after) per slope class; maps of both on one
  grid; and the strip's row of the block table.
- Accuracy: ``lidarcal evaluate``'s co-alignment of each pair and check-point residuals
  (:func:`~lidarcal_ros.pipeline.evaluation.evaluate_mission`), or its saved JSON.
- The USGS LBS quality level (:mod:`lidarcal_ros.core.quality_level`) from the swath
  differences after calibration, the aggregate density and the check points.
- Provenance: version, date, command, inputs with size and SHA-256, the configuration.

Everything stays in memory beside the mission: per strip the cells of its surface, the
points of the slope statistics and the sums of the maps.
"""

from __future__ import annotations

import datetime
import json
import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lidarcal_ros import __version__
from lidarcal_ros.core.calibrate import Calibrator, Progress
from lidarcal_ros.core.calibration_result import ControlResidual
from lidarcal_ros.core.config import SCHEMA, FlightConfig
from lidarcal_ros.core.flags import (
    FLAG_NO_INTENSITY,
    FLAG_NO_NORMAL,
    FLAG_NOT_CORRECTED,
    FLAG_ROUGH,
)
from lidarcal_ros.core.heading import describe_heading_policy
from lidarcal_ros.core.mission import ControlPoints, Mission, Trajectory
from lidarcal_ros.core.normals import cell_size, finite_rows, grid_normals
from lidarcal_ros.core.params import N_PARAMETERS, PARAMETER_NAMES
from lidarcal_ros.core.quality_level import QualityAssessment, assess
from lidarcal_ros.core.radiometry import describe_alpha
from lidarcal_ros.core.swath_differences import (
    SMOOTH_SLOPE_DEG,
    BlockGrid,
    CellHeights,
    SwathDifferences,
    cell_heights,
    swath_differences,
)
from lidarcal_ros.errors import ConfigError
from lidarcal_ros.io.calibration_file import ROOT_KEY, CalibrationRecord, read_calibration
from lidarcal_ros.io.digest import digest
from lidarcal_ros.io.html_report import (
    BiasEntry,
    EvaluationSection,
    FlightMap,
    InputFile,
    MapRaster,
    PairSection,
    Provenance,
    RadiometrySection,
    ReportContent,
    SlopeClass,
    StripRow,
)
from lidarcal_ros.io.yaml_file import read_yaml
from lidarcal_ros.pipeline.calibration import load_mission, qa_level
from lidarcal_ros.pipeline.correction import (
    CorrectionSettings,
    correct_columns,
    trajectory_heading,
)
from lidarcal_ros.pipeline.evaluation import Evaluation, evaluate_mission
from lidarcal_ros.pipeline.reflectance import (
    TargetMeasurement,
    measure_target_on_mission,
    target_of,
    with_constant,
)

logger = logging.getLogger(__name__)

#: Bounds of the terrain-slope classes of the variance-to-mean ratio, degrees.
SLOPE_CLASS_EDGES_DEG: tuple[float, ...] = (0.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0, 90.0)
#: Fewest points for a class's statistics (NaN below).
MIN_CLASS_POINTS = 30
#: Most cells along the longer side of the intensity and reflectance maps.
MAP_MAX_CELLS = 600
#: Map cell in point spacings of the sparsest strip at least (so that where it flies alone,
#: at the block's edges, most cells hold a point or two).
MAP_STRIP_SPACINGS = 2.0
#: Points left out of the slope statistics: not corrected, no normal, no intensity, or a
#: rough neighbourhood (edges, vegetation: slope and incidence uncertain).
EXCLUDED_FLAGS = FLAG_NOT_CORRECTED | FLAG_NO_NORMAL | FLAG_NO_INTENSITY | FLAG_ROUGH
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


# ---------------------------------------------------------------------------- calibration file
@dataclass
class ReportCalibration:
    """A calibration file as the report shows it.

    Attributes
    ----------
    path : Path
    record : CalibrationRecord
        The biases (SI) as ``lidarcal correct`` reads them.
    biases : list of BiasEntry
        The eight parameters with their state and, where not estimable, the reason.
    correlation_names : list of str
    correlation : (m, m) float64
        Correlations of the estimated parameters (empty when the file has none).
    facts : list of (str, str)
        sigma0, redundancy, iterations, convergence, correspondences, as in the file.
    coverage : dict
        ``(strip, strip) -> overlap fraction`` of the pairs the file lists.
    warnings : list of str
    """

    path: Path
    record: CalibrationRecord
    biases: list[BiasEntry]
    correlation_names: list[str]
    correlation: np.ndarray
    facts: list[tuple[str, str]]
    coverage: dict[tuple[int, int], float]
    warnings: list[str]


def read_report_calibration(path: str | Path) -> ReportCalibration:
    """Read a calibration file (interface.md) with the keys the report shows beyond the
    biases: correlation matrix, reasons for parameters not estimable, pair coverage.

    Raises
    ------
    ConfigError
        A required key is missing or malformed (see
        :func:`~lidarcal_ros.io.calibration_file.read_calibration`), or the correlation
        matrix does not match its names.
    """
    path = Path(path)
    record = read_calibration(path)
    body = read_yaml(path, what="calibration")[ROOT_KEY]
    entries = body["biases"]
    biases = []
    for name in PARAMETER_NAMES:
        entry = entries[name]
        reason = entry.get("not_estimable")
        if record.estimated[name]:
            state = "estimated"
        elif reason:
            state = "not_estimable"
        else:
            state = "fixed"
        biases.append(BiasEntry(name, record.values[name],
                                record.sigmas[name] if state == "estimated" else None,
                                state, str(reason) if reason else ""))
    names, matrix = _correlation(path, body.get("correlation"))
    facts = [("calibration file", str(path))]
    if record.sigma0 is not None:
        facts.append(("sigma0 (a posteriori)", f"{record.sigma0 * 100:.2f} cm"))
    for key, label in (("redundancy", "redundancy"), ("iterations", "iterations")):
        if isinstance(body.get(key), int):
            facts.append((label, str(body[key])))
    if isinstance(body.get("converged"), bool):
        facts.append(("converged", "yes" if body["converged"] else "NO"))
    if body.get("model_detail"):
        facts.append(("point-positioning model", str(body["model_detail"])))
    corr = body.get("correspondences")
    if isinstance(corr, Mapping):
        facts.append(("correspondences", f"{corr.get('strip_pairs', '?')} strip-pair, "
                                         f"{corr.get('control', '?')} control"))
    coverage = {}
    for pair in body.get("strip_pairs") or []:
        strips = pair.get("strips") if isinstance(pair, Mapping) else None
        value = pair.get("coverage") if isinstance(pair, Mapping) else None
        if isinstance(strips, list) and len(strips) == 2 and isinstance(value, (int, float)):
            a, b = sorted(int(s) for s in strips)
            coverage[(a, b)] = float(value)
    warnings = [str(w) for w in body.get("warnings") or []]
    for strip in body.get("strips") or []:
        if isinstance(strip, Mapping):
            warnings.extend(f"strip {strip.get('id')}: {w}" for w in strip.get("warnings") or [])
    return ReportCalibration(path, record, biases, names, matrix, facts, coverage, warnings)


def _correlation(path: Path, doc: Any) -> tuple[list[str], np.ndarray]:
    """Names and matrix of the file's ``correlation`` (empty if absent)."""
    if doc is None:
        return [], np.zeros((0, 0))
    names = doc.get("names") if isinstance(doc, Mapping) else None
    rows = doc.get("matrix") if isinstance(doc, Mapping) else None
    if not isinstance(names, list) or not all(n in PARAMETER_NAMES for n in names):
        raise ConfigError(f"{path}: correlation.names must list parameter names, got {names!r}")
    try:
        matrix = np.array(rows, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(f"{path}: correlation.matrix is not a matrix of numbers") from None
    if matrix.shape != (len(names), len(names)):
        raise ConfigError(f"{path}: correlation.matrix is {matrix.shape}, expected "
                          f"{len(names)} x {len(names)} for its names")
    return [str(n) for n in names], matrix


# ---------------------------------------------------------------------------- geometry
def geometric_sections(
    mission: Mission,
    delta: np.ndarray,
    config: FlightConfig,
    *,
    coverage: Mapping[tuple[int, int], float] | None = None,
    progress: Progress | None = None,
) -> tuple[list[PairSection], list[ControlResidual]]:
    """Per strip pair the normal discrepancies before (zero biases) and after ``delta``, and
    the control residuals.

    Parameters
    ----------
    mission : Mission
    delta : (8,) float64
        The calibration's biases, SI, method.md order.
    config : FlightConfig
        Matching options and QA thresholds (those of the calibration for the same sample).
    coverage : mapping, optional
        Overlap fraction per ``(strip, strip)``, shown beside each pair.
    progress : callable, optional

    Returns
    -------
    pairs : list of PairSection
        Sorted by strip ids.
    control : list of ControlResidual
        Metres.
    """
    calibrator = Calibrator.from_mission(mission, config.calibration_settings(),
                                         progress=progress)
    before = calibrator.pair_discrepancies(np.zeros(N_PARAMETERS))
    if progress is not None:
        progress("matching at the estimate", 0.0)
    after = calibrator.pair_discrepancies(delta)
    control = calibrator.control_residuals(delta)
    warn, error = config["qa.rmsdz_warn_m"], config["qa.max_difference_m"]
    coverage = coverage or {}
    pairs = []
    for b, a in zip(before, after):
        assert b.strips == a.strips
        pairs.append(PairSection(b, a, qa_level(a.rms, warn_m=warn, error_m=error),
                                 coverage.get(a.strips)))
    return pairs, control


# ---------------------------------------------------------------------------- radiometry
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
            stats = [_vmr(inten), _vmr(refl * scale), float(inten.mean()), float(refl.mean())]
        out.append(SlopeClass(float(edges[k]), float(edges[k + 1]), n, *stats))
    return out


def _vmr(values: np.ndarray) -> float:
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
    sums, counts = _cell_sums(xy, values, x0=x0, y0=y0, cell_m=cell_m, shape=shape)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(counts > 0, sums / counts, np.nan)
    return MapRaster(mean.reshape(shape), x0, y0, cell_m)


def _cell_sums(xy: np.ndarray, values: np.ndarray, *, x0: float, y0: float, cell_m: float,
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


# ---------------------------------------------------------------------------- block pass
@dataclass
class StripFootprint:
    """Where a strip's points fall: its cells of :data:`FOOTPRINT_CELL_M` (sorted keys of a
    :class:`~lidarcal_ros.core.swath_differences.BlockGrid`)."""

    strip_id: int
    keys: np.ndarray

    @property
    def area_m2(self) -> float:
        return float(self.keys.size) * FOOTPRINT_CELL_M**2


@dataclass
class BlockPass:
    """What one correction pass over every strip gives the report (module docstring).

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


def _time_text(t: float) -> str:
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
    return StripRow(strip_id, int(t.size), _time_text(t0), duration, length, heading,
                    length / duration if duration > 0 else math.nan, height,
                    t.size / footprint.area_m2 if footprint.area_m2 > 0 else math.nan)


def block_pass(
    mission: Mission,
    settings: CorrectionSettings,
    *,
    swath_grid: BlockGrid,
    footprint_grid: BlockGrid,
    map_shape: tuple[float, float, float, tuple[int, int]],
    progress: Progress | None = None,
) -> BlockPass:
    """Correct every strip once and keep what the report needs of it (module docstring).

    Parameters
    ----------
    mission : Mission
    settings : CorrectionSettings
        Biases and radiometric model (with the calibration constant, if any).
    swath_grid, footprint_grid : BlockGrid
        Grids of the swath differences and of the footprints.
    map_shape : (x0, y0, cell_m, (rows, columns))
        The grid of the intensity and reflectance maps (:func:`block_grids`).
    progress : callable, optional
    """
    x0, y0, cell, shape = map_shape
    out = BlockPass(map_sums=np.zeros((3, shape[0] * shape[1])))
    strips = [s for s in mission.strips if len(s)]
    for k, strip in enumerate(strips):
        if progress is not None:
            progress("correcting strips", k / len(strips))
        heading = trajectory_heading(mission.trajectory, float(np.nanmedian(strip.t)))
        finite = finite_rows(strip.xyz) & np.isfinite(strip.t)
        normals = grid_normals(strip.xyz, heading,
                               cell_m=cell_size(strip.xyz[finite], heading, strip.t[finite]))
        res = correct_columns(strip.xyz, strip.t, strip.intensity, mission.trajectory,
                              settings, normals=normals, source=f"strip {strip.strip_id}")
        with np.errstate(invalid="ignore"):
            slope = np.degrees(np.arccos(np.clip(np.abs(normals.normals[:, 2]), 0.0, 1.0)))
        rough = normals.rough if normals.rough is not None else np.zeros(len(strip), bool)
        corrected = (res.flags & FLAG_NOT_CORRECTED) == 0
        smooth = normals.valid & ~rough & (slope < SMOOTH_SLOPE_DEG) & corrected
        out.surfaces.append((strip.strip_id, float(np.nanmedian(strip.t)),
                             cell_heights(swath_grid, strip.xyz, normals.normals, smooth),
                             cell_heights(swath_grid, res.xyz, normals.normals, smooth)))
        keys = footprint_grid.keys(strip.xyz[finite, :2])
        footprint = StripFootprint(strip.strip_id, np.unique(keys[keys >= 0]))
        out.footprints.append(footprint)
        out.rows.append(_strip_row(strip.strip_id, strip.t[finite], res.xyz[finite, 2],
                                   mission.trajectory, footprint))
        if strip.intensity is None:
            continue
        intensity = np.asarray(strip.intensity, dtype=np.float64)
        mapped = np.isfinite(res.reflectance) & np.isfinite(intensity)
        out.n_radiometric += len(strip)
        for row, values in enumerate((intensity[mapped], res.reflectance[mapped],
                                      np.ones(int(mapped.sum())))):
            sums, _ = _cell_sums(res.xyz[mapped, :2], values, x0=x0, y0=y0, cell_m=cell,
                                 shape=shape)
            out.map_sums[row] += sums
        usable = mapped & ((res.flags & EXCLUDED_FLAGS) == 0) & np.isfinite(slope)
        out.slope.append(slope[usable].astype(np.float32))
        out.intensity.append(intensity[usable].astype(np.float32))
        out.reflectance.append(res.reflectance[usable])
    return out


def radiometry_section(
    passed: BlockPass,
    settings: CorrectionSettings,
    map_shape: tuple[float, float, float, tuple[int, int]],
    target: TargetMeasurement | None = None,
) -> RadiometrySection | None:
    """Slope statistics of intensity and reflectance, and their maps (None where no strip
    carries intensity)."""
    if not passed.n_radiometric or not passed.map_sums[2].any():
        return None
    x0, y0, cell, shape = map_shape
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


# ---------------------------------------------------------------------------- block
def block_grids(mission: Mission, config: FlightConfig) -> tuple[BlockGrid, BlockGrid,
                                                                   tuple[float, float, float,
                                                                         tuple[int, int]]]:
    """The grids of the footprints, of the swath differences and of the maps."""
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
    return footprint, swath, (float(lo[0]), float(lo[1]), cell, shape)


def flight_map(mission: Mission, footprints: Sequence[StripFootprint], grid: BlockGrid, *,
               check_points: ControlPoints | None = None,
               target: tuple[float, float, float, float] | None = None) -> FlightMap:
    """The block map's content (:class:`~lidarcal_ros.io.html_report.FlightMap`)."""
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


def evaluation_section(evaluation: Evaluation, source: str) -> EvaluationSection:
    """``lidarcal evaluate``'s results as the report shows them."""
    return EvaluationSection(
        [(p.strip_a, p.strip_b, p.before, p.after) for p in evaluation.pairs],
        [(c.point_id, c.strips, c.before, c.after) for c in evaluation.check_points], source)


def quality_assessment(swath: SwathDifferences, footprints: Sequence[StripFootprint],
                       n_points: int, evaluation: EvaluationSection | None
                       ) -> QualityAssessment:
    """The LBS measures after calibration (:mod:`lidarcal_ros.core.quality_level`)."""
    after = swath.statistics("after")
    union = np.unique(np.concatenate([f.keys for f in footprints])) if footprints \
        else np.zeros(0)
    area = union.size * FOOTPRINT_CELL_M**2
    nva, n_check = math.nan, 0
    if evaluation is not None and evaluation.check:
        summary = evaluation.summary("after")
        nva, n_check = summary.rmse, summary.n
    return assess(rmsdz_m=after.rmsdz, max_dz_m=after.max_abs,
                  anpd_per_m2=n_points / area if area > 0 else math.nan, nva_rmse_m=nva,
                  n_check_points=n_check,
                  dz_note=f"{after.n_cells} cells of {swath.grid.cell_m:.1f} m, smooth ground, "
                          f"{len(swath.pairs)} strip pairs")


# ---------------------------------------------------------------------------- report
@dataclass
class ReportInputs:
    """What the report says of its inputs beyond the mission and the calibration.

    Attributes
    ----------
    title : str
    facts : list of (str, str)
        Leading lines of the summary (bag, configuration).
    check_points : ControlPoints, optional
        Surveyed points not used by the calibration (``lidarcal evaluate --check-points``).
    evaluation : Evaluation, optional
        ``lidarcal evaluate``'s results to show instead of computing them; with
        ``evaluation_source`` naming where they came from.
    crs : str
        The map frame's CRS as named on the maps ('' where not known).
    provenance : Provenance, optional
    """

    title: str = "LiDAR calibration report"
    facts: list[tuple[str, str]] = field(default_factory=list)
    check_points: ControlPoints | None = None
    evaluation: Evaluation | None = None
    evaluation_source: str = ""
    crs: str = ""
    provenance: Provenance | None = None


def report_mission(
    mission: Mission,
    calibration: ReportCalibration,
    config: FlightConfig,
    inputs: ReportInputs | None = None,
    *,
    progress: Progress | None = None,
) -> ReportContent:
    """The report of a mission under a calibration (module docstring)."""
    inputs = inputs or ReportInputs()
    delta = calibration.record.delta
    pairs, control = geometric_sections(mission, delta, config, coverage=calibration.coverage,
                                        progress=progress)
    settings = CorrectionSettings.from_config(config, calibration.record)
    target = target_of(config)
    measured = None
    if target is not None and not settings.radiometry.absolute:
        measured = measure_target_on_mission(mission, settings, target)
        settings = with_constant(settings, measured.constant)
    footprint_grid, swath_grid, map_shape = block_grids(mission, config)
    passed = block_pass(mission, settings, swath_grid=swath_grid,
                        footprint_grid=footprint_grid, map_shape=map_shape, progress=progress)
    if progress is not None:
        progress("swath differences", 0.0)
    swath = swath_differences(swath_grid, passed.surfaces)
    radiometry = radiometry_section(passed, settings, map_shape, measured)
    evaluation = inputs.evaluation
    source = inputs.evaluation_source
    if evaluation is None:
        evaluation = evaluate_mission(mission, delta, config.calibration_settings(),
                                      check_points=inputs.check_points, progress=progress)
        source = "Computed for this report as lidarcal evaluate does (100000 points per pair)."
    evaluated = evaluation_section(evaluation, source)
    quality = quality_assessment(swath, passed.footprints, mission.n_points, evaluated)
    n_ctrl = len(mission.control) if mission.control is not None else 0
    n_check = len(inputs.check_points) if inputs.check_points is not None else 0
    starts = [r.start for r in passed.rows]
    summary = [
        *inputs.facts,
        ("mission", f"{len(mission.strips)} strips, {mission.n_points} points, {len(pairs)} "
                    f"overlapping pairs, {n_ctrl} control point{'' if n_ctrl == 1 else 's'}, "
                    f"{n_check} check point{'' if n_check == 1 else 's'}"),
        ("flown", f"{min(starts)} (first point)" if starts else "n/a"),
        ("map frame", f"'{mission.frame_id}', " + (inputs.crs or "CRS not given")),
        ("heading", describe_heading_policy(str(config["matching.heading_source"]),
                                            mission.trajectory.heading is not None)),
        ("reflectance", settings.radiometry.meaning),
    ]
    if mission.dropped_non_finite:
        summary.append(("points dropped", f"{mission.dropped_non_finite} with non-finite "
                                          "values"))
    if mission.thinned_points:
        summary.append(("points thinned", (
            f"{mission.thinned_points} left out: one point per "
            f"{config['calibration.thinning_cell_m']:g} m cell per strip and cloud, as the "
            "calibration")))
    if inputs.provenance is not None:
        summary.append(("generated", f"{inputs.provenance.generated} by lidarcal "
                                     f"{inputs.provenance.version}"))
    return ReportContent(
        title=inputs.title, facts=summary, calibration_facts=calibration.facts,
        biases=calibration.biases, correlation_names=calibration.correlation_names,
        correlation=calibration.correlation, pairs=pairs, control=control,
        radiometry=radiometry, strips=passed.rows,
        flight=flight_map(mission, passed.footprints, footprint_grid,
                          check_points=inputs.check_points,
                          target=target[0] if target is not None else None),
        swath=swath, swath_limit_m=float(config["qa.max_difference_m"]), quality=quality,
        evaluation=evaluated, provenance=inputs.provenance, crs=inputs.crs,
        qa_warn_m=float(config["qa.rmsdz_warn_m"]),
        qa_error_m=float(config["qa.max_difference_m"]),
        smooth_slope_deg=SMOOTH_SLOPE_DEG, warnings=calibration.warnings)


def read_evaluation(path: str | Path, delta: np.ndarray) -> Evaluation:
    """``lidarcal evaluate --json`` output, checked to be of the calibration's biases.

    Raises
    ------
    ConfigError
        Not JSON, not an evaluation, or of other biases.
    """
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read the evaluation ({exc})") from None
    evaluation = Evaluation.from_dict(doc, source=str(path))
    if evaluation.delta is None:
        raise ConfigError(f"{path}: the evaluation does not say which biases it evaluated "
                          "(no 'biases'); run lidarcal evaluate --json again")
    if not np.allclose(evaluation.delta, delta, rtol=0.0, atol=1e-12):
        raise ConfigError(f"{path}: the evaluation is of other biases than the calibration "
                          "file's (a different calibration)")
    return evaluation


def configuration_table(config: FlightConfig) -> list[tuple[str, str, bool]]:
    """Every parameter of ``config``: name, value, whether it differs from the default."""
    return [(name, _config_text(config[name]), config[name] != spec.default)
            for name, spec in SCHEMA.items()]


def _config_text(value: Any) -> str:
    return ", ".join(value) if isinstance(value, list) else str(value)


def describe_inputs(files: Sequence[tuple[str, str | Path | None]], *,
                    progress: Progress | None = None) -> list[InputFile]:
    """Size and SHA-256 of each input (role, path); None paths are left out."""
    present = [(role, Path(path)) for role, path in files if path is not None]
    out = []
    for k, (role, path) in enumerate(present):
        if progress is not None:
            progress(f"hashing {role}", k / max(len(present), 1))
        size, sha = digest(path)
        out.append(InputFile(role, str(path), size, sha))
    return out


def build_report(
    bag: str | Path,
    calibration_path: str | Path,
    config: FlightConfig,
    *,
    control_csv: str | Path | None = None,
    config_source: str | Path | None = None,
    check_points_csv: str | Path | None = None,
    evaluation_json: str | Path | None = None,
    crs: Any = None,
    command: str = "",
    progress: Progress | None = None,
) -> ReportContent:
    """Read a mission bag and a calibration file and compute the report.

    Parameters
    ----------
    bag : path
        rosbag2 directory or ``.mcap`` file.
    calibration_path : path
        Calibration YAML (``lidarcal calibrate``).
    config : FlightConfig
        The flight configuration the calibration ran with (same sample points and QA).
    control_csv : path, optional
        Control points ``id,x,y,z`` (else the configuration's file, else the bag's topic).
    config_source : path, optional
        Where ``config`` came from, shown in the report.
    check_points_csv : path, optional
        Surveyed check points ``id,x,y,z`` not used by the calibration.
    evaluation_json : path, optional
        ``lidarcal evaluate --json`` output of the same mission and calibration, shown instead
        of evaluating again.
    crs : pyproj.CRS, optional
        The map frame's CRS, named on the maps.
    command : str
        The command line, recorded in the provenance.
    progress : callable, optional
    """
    from lidarcal_ros.io.control import read_control_csv

    calibration = read_report_calibration(calibration_path)
    check = read_control_csv(check_points_csv) if check_points_csv else None
    evaluation = (read_evaluation(evaluation_json, calibration.record.delta)
                  if evaluation_json else None)
    if progress is not None:
        progress("reading the bag", 0.0)
    mission = load_mission(bag, config, control_csv=control_csv)
    control_file = control_csv or config["calibration.control_points_file"] or None
    files = describe_inputs([("bag", bag), ("calibration", calibration_path),
                             ("flight configuration", config_source),
                             ("control points", control_file),
                             ("check points", check_points_csv),
                             ("evaluation", evaluation_json)], progress=progress)
    generated = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M:%S UTC")
    provenance = Provenance(__version__, generated, command, files,
                            configuration_table(config),
                            str(config_source) if config_source else "defaults")
    crs_name = f"{crs.to_string()} ({crs.name})" if crs is not None else ""
    inputs = ReportInputs(
        title=f"Calibration report: {Path(bag).name}",
        facts=[("bag", str(bag)),
               ("flight configuration", str(config_source) if config_source else "defaults")],
        check_points=check, evaluation=evaluation,
        evaluation_source=f"Read from {evaluation_json} (lidarcal evaluate --json)."
        if evaluation_json else "", crs=crs_name, provenance=provenance)
    return report_mission(mission, calibration, config, inputs, progress=progress)
