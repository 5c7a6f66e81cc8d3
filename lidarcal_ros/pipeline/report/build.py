"""What ``lidarcal report`` shows, computed from a mission bag, a calibration and a configuration.

With the procedures calibration, correction and evaluation use themselves (docs/internals.md,
"The HTML report").
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
from lidarcal_ros.core.calibration.calibrate import Calibrator, Progress
from lidarcal_ros.core.calibration.result import ControlResidual
from lidarcal_ros.core.config import FlightConfig
from lidarcal_ros.core.georeferencing.heading import HeadingSource, describe_heading_policy
from lidarcal_ros.core.mission import ControlPoints, Mission
from lidarcal_ros.core.params import N_PARAMETERS
from lidarcal_ros.core.qa.quality_level import QualityAssessment, assess
from lidarcal_ros.core.qa.swath_differences import (
    SMOOTH_SLOPE_DEG,
    SwathDifferences,
    swath_differences,
)
from lidarcal_ros.errors import ConfigError
from lidarcal_ros.io.report.content import (
    EvaluationSection,
    PairSection,
    Provenance,
    ReportContent,
    TrajectorySection,
)
from lidarcal_ros.pipeline.calibration.procedure import load_mission, qa_level
from lidarcal_ros.pipeline.correction.apply import CorrectionSettings
from lidarcal_ros.pipeline.correction.reflectance import (
    measure_target_on_mission,
    target_of,
    with_constant,
)
from lidarcal_ros.pipeline.evaluation import Evaluation, evaluate_mission
from lidarcal_ros.pipeline.executor import CommandTasks, Executor, SerialExecutor
from lidarcal_ros.pipeline.report.block import (
    FOOTPRINT_CELL_M,
    StripFootprint,
    block_grids,
    block_pass,
    flight_map,
    time_text,
)
from lidarcal_ros.pipeline.report.calibration import ReportCalibration, read_report_calibration
from lidarcal_ros.pipeline.report.provenance import configuration_table, describe_inputs
from lidarcal_ros.pipeline.report.radiometry import radiometry_section

__all__ = [
    "ReportInputs", "build_report", "evaluation_section", "geometric_sections",
    "quality_assessment", "read_evaluation", "report_mission", "trajectory_section",
]

logger = logging.getLogger(__name__)


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
        The calibration's biases, SI, docs/method.md order.
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


def evaluation_section(evaluation: Evaluation, source: str) -> EvaluationSection:
    """``lidarcal evaluate``'s results as the report shows them."""
    return EvaluationSection(
        [(p.strip_a, p.strip_b, p.before, p.after) for p in evaluation.pairs],
        [(c.point_id, c.strips, c.before, c.after) for c in evaluation.check_points], source)


def quality_assessment(swath: SwathDifferences, footprints: Sequence[StripFootprint],
                       n_points: int, evaluation: EvaluationSection | None
                       ) -> QualityAssessment:
    """The LBS measures after calibration (:mod:`lidarcal_ros.core.qa.quality_level`)."""
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


def trajectory_section(mission: Mission, calibration: ReportCalibration
                       ) -> TrajectorySection | None:
    """Each strip's estimated trajectory error over the times its points were flown; None
    where the calibration holds no trajectory errors."""
    estimate = calibration.record.trajectory
    if estimate is None:
        return None
    spans: dict[int, tuple[float, float]] = {}
    for strip in mission.strips:
        t = strip.t[np.isfinite(strip.t)]
        if t.size:
            lo, hi = spans.get(strip.strip_id, (math.inf, -math.inf))
            spans[strip.strip_id] = (min(lo, float(t.min())), max(hi, float(t.max())))
    starts = [a for a, _ in spans.values()] or [se.t_ref for se in estimate.strips.values()]
    t0 = min(starts) if starts else 0.0
    return TrajectorySection(estimate, calibration.trajectory_model or estimate.model.value,
                             spans, t0, time_text(t0))


def report_mission(
    mission: Mission,
    calibration: ReportCalibration,
    config: FlightConfig,
    inputs: ReportInputs | None = None,
    *,
    progress: Progress | None = None,
    executor: Executor | None = None,
) -> ReportContent:
    """The report of a mission under a calibration (docs/internals.md, "The HTML report");
    the block pass and the evaluation as tasks of ``executor`` (default: here), each strip
    sent to it once."""
    inputs = inputs or ReportInputs()
    tasks = CommandTasks(executor or SerialExecutor(), "report")
    delta = calibration.record.delta
    pairs, control = geometric_sections(mission, delta, config, coverage=calibration.coverage,
                                        progress=progress)
    settings = CorrectionSettings.from_config(config, calibration.record)
    target = target_of(config)
    measured = None
    if target is not None and not settings.radiometry.absolute:
        measured = measure_target_on_mission(mission, settings, target)
        settings = with_constant(settings, measured.constant)
    footprint_grid, swath_grid, map_grid = block_grids(mission, config)
    passed = block_pass(mission, settings, swath_grid=swath_grid,
                        footprint_grid=footprint_grid, map_grid=map_grid, progress=progress,
                        executor=tasks)
    if progress is not None:
        progress("swath differences", 0.0)
    swath = swath_differences(swath_grid, passed.surfaces)
    radiometry = radiometry_section(passed, settings, map_grid, measured)
    evaluation = inputs.evaluation
    source = inputs.evaluation_source
    if evaluation is None:
        evaluation = evaluate_mission(mission, delta, config.calibration_settings(),
                                      check_points=inputs.check_points, progress=progress,
                                      executor=tasks)
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
        ("heading", describe_heading_policy(HeadingSource(config["matching.heading_source"]),
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
        smooth_slope_deg=SMOOTH_SLOPE_DEG, warnings=calibration.warnings,
        trajectory=trajectory_section(mission, calibration))


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
    executor: Executor | None = None,
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
    executor : Executor, optional
        Where the strips are corrected and evaluated (:func:`report_mission`).
    """
    from lidarcal_ros.io.survey.control import read_control_csv

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
    return report_mission(mission, calibration, config, inputs, progress=progress,
                          executor=executor)
