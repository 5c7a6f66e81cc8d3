"""What ``lidarcal report`` shows, computed from a mission bag, a calibration file and the
flight configuration with the procedures calibration and correction use themselves.

- Geometry: a :class:`~lidarcal_ros.core.calibrate.Calibrator` over the mission chooses the
  same sample points as ``lidarcal calibrate`` (same configuration, same seeds) and matches them
  at zero biases ("before") and at the calibration file's estimate ("after"): per strip pair,
  the signed normal discrepancy of every matched point with its map position, whose robust RMS
  is the calibration's own pair QA; and the control-point residuals.
- Radiometry: every strip with intensity goes through
  :func:`~lidarcal_ros.pipeline.correction.correct_columns` (the correction ``lidarcal
  correct`` applies), and the terrain slope of each point comes from the same grid normals
  (:func:`~lidarcal_ros.core.normals.grid_normals`, same heading and cell). Per slope class,
  the variance-to-mean ratio of the recorded intensity (before) and of the reflectance
  (after); and maps of both on one grid.

Everything stays in memory; the cost is one matching pass more than a calibration iteration
plus one correction pass (a 579k-point mission reports in a few seconds).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lidarcal_ros import __version__
from lidarcal_ros.core.calibrate import Calibrator, ControlResidual, Progress
from lidarcal_ros.core.config import FlightConfig
from lidarcal_ros.core.heading import describe_heading_policy
from lidarcal_ros.core.mission import Mission
from lidarcal_ros.core.normals import grid_normals
from lidarcal_ros.core.params import N_PARAMETERS, PARAMETER_NAMES
from lidarcal_ros.core.radiometry import describe_alpha
from lidarcal_ros.errors import ConfigError
from lidarcal_ros.io.calibration_file import ROOT_KEY, CalibrationRecord, read_calibration
from lidarcal_ros.io.html_report import (
    BiasEntry,
    MapRaster,
    PairSection,
    RadiometrySection,
    ReportContent,
    SlopeClass,
)
from lidarcal_ros.io.yaml_file import read_yaml
from lidarcal_ros.pipeline.calibration import load_mission, qa_level
from lidarcal_ros.pipeline.correction import (
    FLAG_NO_INTENSITY,
    FLAG_NO_NORMAL,
    FLAG_NOT_CORRECTED,
    FLAG_ROUGH,
    CorrectionSettings,
    correct_columns,
    trajectory_heading,
)

logger = logging.getLogger(__name__)

#: Bounds of the terrain-slope classes of the variance-to-mean ratio, degrees.
SLOPE_CLASS_EDGES_DEG: tuple[float, ...] = (0.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0, 90.0)
#: Fewest points for a class's statistics (NaN below).
MIN_CLASS_POINTS = 30
#: Most cells along the longer side of the intensity and reflectance maps.
MAP_MAX_CELLS = 600
#: Map cell in mean point spacings at least (so most cells hold a few points).
MAP_CELL_SPACINGS = 1.5
#: Points left out of the slope statistics: not corrected, no normal, no intensity, or a
#: rough neighbourhood (edges, vegetation: slope and incidence uncertain).
EXCLUDED_FLAGS = FLAG_NOT_CORRECTED | FLAG_NO_NORMAL | FLAG_NO_INTENSITY | FLAG_ROUGH


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
        sigma0, redundancy, iterations, correspondences, as in the file.
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
    facts = []
    if record.sigma0 is not None:
        facts.append(("sigma0 (a posteriori)", f"{record.sigma0 * 100:.2f} cm"))
    for key, label in (("redundancy", "redundancy"), ("iterations", "iterations")):
        if isinstance(body.get(key), int):
            facts.append((label, str(body[key])))
    if isinstance(body.get("converged"), bool):
        facts.append(("converged", "yes" if body["converged"] else "NO"))
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

    Parameters
    ----------
    slope_deg : (n,) float
        Terrain slope of each point, degrees from horizontal.
    intensity, reflectance : (n,) float
        Recorded intensity and reflectance (intensity units) of the same points, finite.
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
    out = []
    for k in range(edges.size - 1):
        members = which == k
        n = int(np.count_nonzero(members))
        stats = [math.nan] * 4
        if n >= min_points:
            inten = np.asarray(intensity[members], dtype=np.float64)
            refl = np.asarray(reflectance[members], dtype=np.float64)
            stats = [_vmr(inten), _vmr(refl), float(inten.mean()), float(refl.mean())]
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
    ny, nx = shape
    col = np.floor((xy[:, 0] - x0) / cell_m).astype(np.int64)
    row = np.floor((xy[:, 1] - y0) / cell_m).astype(np.int64)
    inside = (col >= 0) & (col < nx) & (row >= 0) & (row < ny)
    key = row[inside] * nx + col[inside]
    sums = np.bincount(key, weights=np.asarray(values, dtype=np.float64)[inside],
                       minlength=nx * ny)
    counts = np.bincount(key, minlength=nx * ny)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(counts > 0, sums / counts, np.nan)
    return MapRaster(mean.reshape(ny, nx), x0, y0, cell_m)


def map_grid(xy: np.ndarray, *, max_cells: int = MAP_MAX_CELLS) -> tuple[float, float, float,
                                                                           tuple[int, int]]:
    """A grid over the points: ``(x0, y0, cell_m, (rows, columns))``.

    The cell is the larger of the extent over ``max_cells`` and :data:`MAP_CELL_SPACINGS`
    mean point spacings over the bounding box (metres).
    """
    lo = xy.min(axis=0)
    hi = xy.max(axis=0)
    size = np.maximum(hi - lo, 1e-3)
    spacing = math.sqrt(float(size[0] * size[1]) / max(xy.shape[0], 1))
    cell = max(float(size.max()) / max_cells, MAP_CELL_SPACINGS * spacing, 1e-3)
    nx = int(math.floor(size[0] / cell)) + 1
    ny = int(math.floor(size[1] / cell)) + 1
    return float(lo[0]), float(lo[1]), cell, (ny, nx)


def radiometry_section(
    mission: Mission,
    delta: np.ndarray,
    config: FlightConfig,
    *,
    progress: Progress | None = None,
) -> RadiometrySection | None:
    """Slope statistics of intensity and reflectance, and their maps (module docstring).

    Parameters
    ----------
    mission : Mission
    delta : (8,) float64
        Biases to remove, SI, method.md order.
    config : FlightConfig
        Radiometric model, atmosphere, trajectory window.
    progress : callable, optional

    Returns
    -------
    RadiometrySection or None
        None where no strip carries intensity.
    """
    settings = CorrectionSettings.from_config(config, delta)
    strips = [s for s in mission.strips if s.intensity is not None and len(s)]
    if not strips:
        return None
    xy, inten, refl, slope, usable = [], [], [], [], []
    n_points = 0
    for k, strip in enumerate(strips):
        if progress is not None:
            progress("radiometric correction", k / len(strips))
        heading = trajectory_heading(mission.trajectory, float(np.nanmedian(strip.t)))
        res = correct_columns(strip.xyz, strip.t, strip.intensity, mission.trajectory, settings,
                              heading=heading, source=f"strip {strip.strip_id}")
        # The normals correct_columns fitted (same points, heading and cell): their slope.
        normals = grid_normals(strip.xyz, heading, cell_m=res.cell_m).normals
        with np.errstate(invalid="ignore"):
            slope_deg = np.degrees(np.arccos(np.clip(normals[:, 2], 0.0, 1.0)))
        intensity = np.asarray(strip.intensity, dtype=np.float64)
        ok = ((res.flags & EXCLUDED_FLAGS) == 0) & np.isfinite(res.reflectance) \
            & np.isfinite(intensity) & np.isfinite(slope_deg)
        mapped = np.isfinite(res.reflectance) & np.isfinite(intensity)
        n_points += len(strip)
        xy.append(res.xyz[mapped, :2])
        inten.append(intensity[mapped])
        refl.append(res.reflectance[mapped].astype(np.float64))
        slope.append(slope_deg[mapped])
        usable.append(ok[mapped])
    all_xy = np.concatenate(xy)
    if not all_xy.shape[0]:
        return None
    all_inten, all_refl = np.concatenate(inten), np.concatenate(refl)
    all_slope, all_usable = np.concatenate(slope), np.concatenate(usable)
    classes = slope_class_statistics(all_slope[all_usable], all_inten[all_usable],
                                     all_refl[all_usable])
    x0, y0, cell, shape = map_grid(all_xy)
    model = settings.radiometry
    notes = [
        f"Reflectance: intensity normalised to {model.reference_range_m:g} m range, normal "
        f"incidence and clear air ({describe_alpha(model)}); it reads in intensity units.",
        "Left out of the slope statistics: points not corrected, without a surface normal "
        "or intensity, and rough neighbourhoods (edges, vegetation), whose slope and incidence "
        "are uncertain. Terrain slope from the grid normals of the radiometric correction.",
    ]
    return RadiometrySection(
        slope_classes=classes,
        intensity=mean_raster(all_xy, all_inten, x0=x0, y0=y0, cell_m=cell, shape=shape),
        reflectance=mean_raster(all_xy, all_refl, x0=x0, y0=y0, cell_m=cell, shape=shape),
        n_points=n_points, n_used=int(all_usable.sum()), notes=notes)


# ---------------------------------------------------------------------------- report
def report_mission(
    mission: Mission,
    calibration: ReportCalibration,
    config: FlightConfig,
    *,
    title: str = "LiDAR calibration report",
    facts: Sequence[tuple[str, str]] = (),
    progress: Progress | None = None,
) -> ReportContent:
    """The report of a mission under a calibration (module docstring).

    ``facts`` (label, value) lead the summary, before the mission's and the calibration's.
    """
    delta = calibration.record.delta
    pairs, control = geometric_sections(mission, delta, config, coverage=calibration.coverage,
                                        progress=progress)
    radiometry = radiometry_section(mission, delta, config, progress=progress)
    n_ctrl = len(mission.control) if mission.control is not None else 0
    summary = [
        *facts,
        ("mission", f"{len(mission.strips)} strips, {mission.n_points} points, {len(pairs)} "
                    f"overlapping pairs, {n_ctrl} control point{'' if n_ctrl == 1 else 's'}"),
        ("calibration file", str(calibration.path)),
        ("heading", describe_heading_policy(str(config["matching.heading_source"]),
                                            mission.trajectory.heading is not None)),
        *calibration.facts,
        ("generated by", f"lidarcal {__version__}"),
    ]
    if mission.dropped_non_finite:
        summary.append(("points dropped", f"{mission.dropped_non_finite} with non-finite "
                                          "values"))
    if mission.thinned_points:
        summary.append(("points thinned", (
            f"{mission.thinned_points} left out: one point per "
            f"{config['calibration.thinning_cell_m']:g} m cell per strip and cloud, as the "
            "calibration")))
    starts = [np.nanmin(s.xyz[:, :2], axis=0) for s in mission.strips if len(s)]
    corner = np.nanmin(starts, axis=0) if starts else np.zeros(2)
    origin = (float(np.floor(corner[0] / 100.0) * 100.0),
              float(np.floor(corner[1] / 100.0) * 100.0))
    return ReportContent(
        title=title, facts=summary, biases=calibration.biases,
        correlation_names=calibration.correlation_names,
        correlation=calibration.correlation, pairs=pairs, control=control,
        radiometry=radiometry, origin=origin,
        qa_warn_m=float(config["qa.rmsdz_warn_m"]),
        qa_error_m=float(config["qa.max_difference_m"]),
        warnings=calibration.warnings)


def build_report(
    bag: str | Path,
    calibration_path: str | Path,
    config: FlightConfig,
    *,
    control_csv: str | Path | None = None,
    config_source: str | Path | None = None,
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
    progress : callable, optional
    """
    calibration = read_report_calibration(calibration_path)
    mission = load_mission(bag, config, control_csv=control_csv)
    facts = [("bag", str(bag)),
             ("flight configuration", str(config_source) if config_source else "defaults")]
    return report_mission(mission, calibration, config, title=f"Calibration report: "
                          f"{Path(bag).name}", facts=facts, progress=progress)
