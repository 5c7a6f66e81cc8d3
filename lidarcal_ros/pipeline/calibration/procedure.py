"""Calibration procedure shared by `lidarcal calibrate` and the calibrator node.

Batch (``lidarcal calibrate``) and streaming (the calibrator node) call the same functions here,
which call :mod:`lidarcal_ros.core` for numerics and :mod:`lidarcal_ros.io` for data, so the two
cannot drift apart.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from lidarcal_ros.core.adjustment.least_squares import ParameterState
from lidarcal_ros.core.calibration.calibrate import Progress, calibrate
from lidarcal_ros.core.calibration.pairs import outside_strips
from lidarcal_ros.core.calibration.result import CalibrationResult
from lidarcal_ros.core.config import FlightConfig
from lidarcal_ros.core.georeferencing.heading import (
    HeadingSource,
    check_orientation,
    describe_heading_use,
)
from lidarcal_ros.core.georeferencing.laser_geometry import PositioningModel
from lidarcal_ros.core.georeferencing.rigorous import check_model_setting, describe_models
from lidarcal_ros.core.mission import Mission
from lidarcal_ros.core.params import PARAMETER_NAMES, format_value
from lidarcal_ros.core.simulation.trajectory_errors import (
    StripTrajectoryError,
    read_trajectory_errors,
)
from lidarcal_ros.core.units import LENGTH_UNITS, parse_quantity
from lidarcal_ros.errors import ConfigError
from lidarcal_ros.io.bag.mission_bag import read_mission
from lidarcal_ros.io.output_files import check_output, remove_quietly, write_text
from lidarcal_ros.io.survey.control import read_control_csv
from lidarcal_ros.io.yaml_file import read_yaml
from lidarcal_ros.pipeline.calibration.bounded import ReducedMission, load_reduced_mission
from lidarcal_ros.pipeline.calibration.parts import ExecutorPairWork
from lidarcal_ros.pipeline.executor import Executor, SerialExecutor

logger = logging.getLogger(__name__)


def load_mission(
    bag: str | Path, config: FlightConfig, *, control_csv: str | Path | None = None,
    box: tuple[float, float, float, float] | None = None,
) -> Mission:
    """Read a mission bag with the topics and time field of ``config``.

    Control points come from ``control_csv`` if given, else from the configuration's
    ``calibration.control_points_file`` if set, else from the bag's control topic. A
    ``matching.heading_source`` of ``attitude`` with poses that carry no orientation is
    refused here (ConfigError). ``box`` ``(xmin, ymin, xmax, ymax)``, map frame, m: only
    the points inside it.
    """
    mission = read_mission(
        bag,
        points_topic=config["topics.points"],
        trajectory_topic=config["topics.trajectory"],
        control_topic=config["topics.control_points"],
        time_field=config["time_field"],
        thinning_cell_m=config["calibration.thinning_cell_m"],
        box=box,
        coordinate_tolerance_m=config["sensor.range_noise_m"],
    )
    check_orientation(HeadingSource(config["matching.heading_source"]), mission.trajectory,
                      str(bag))
    check_model_setting(PositioningModel(config["matching.model"]), mission.trajectory, str(bag))
    csv = control_csv or config["calibration.control_points_file"] or None
    if csv:
        mission.control = read_control_csv(csv)
    return mission


def load_for_calibration(
    bag: str | Path, config: FlightConfig, *, control_csv: str | Path | None = None,
    progress: Progress | None = None, executor: Executor | None = None,
) -> Mission:
    """The mission of ``bag`` as ``calibration.memory`` says to hold it: every point
    (:func:`load_mission`) or the reduced mission of a bounded-memory calibration
    (:func:`~lidarcal_ros.pipeline.calibration.bounded.load_reduced_mission`, its samples
    chosen on the workers of ``executor`` if given)."""
    if config["calibration.memory"] == "bounded":
        return load_reduced_mission(bag, config, control_csv=control_csv, progress=progress,
                                    executor=executor)
    return load_mission(bag, config, control_csv=control_csv)


def calibrate_mission(
    mission: Mission,
    config: FlightConfig,
    *,
    solve_for: tuple[str, ...] | None = None,
    progress: Progress | None = None,
    executor: Executor | None = None,
) -> CalibrationResult:
    """Run the calibration of ``mission`` (a
    :class:`~lidarcal_ros.pipeline.calibration.bounded.ReducedMission` too) with the options
    of ``config``; its strip pairs matched on the workers of ``executor`` if given
    (:mod:`~lidarcal_ros.pipeline.calibration.parts`: the same estimate)."""
    settings = config.calibration_settings()
    if solve_for is not None:
        settings.solve_for = tuple(n for n in PARAMETER_NAMES if n in solve_for)
    reduced = mission if isinstance(mission, ReducedMission) else None
    result = calibrate(mission, settings, progress=progress,
                       whole=None if reduced is None else reduced.whole,
                       samples=None if reduced is None else reduced.samples,
                       pair_work=_pair_work(executor, bounded=reduced is not None))
    unused = unused_control(mission, result, config)
    if unused:
        logger.warning("%s", unused)
        result.solution.warnings.append(unused)
    return result


def _pair_work(executor: Executor | None, *, bounded: bool) -> ExecutorPairWork | None:
    """Where a calibration's strip pairs are matched: on ``executor``'s workers if given;
    else in this process's threads, or, calibrating in bounded memory, as tasks in this
    process, one strip's pairs after another (one strip corrected whole at a time, and of
    the others only the points matched: at 100M points a peak of 3591 MiB, not 3802)."""
    if executor is not None:
        return ExecutorPairWork(executor)
    return ExecutorPairWork(SerialExecutor()) if bounded else None


def unused_control(mission: Mission, result: CalibrationResult,
                   config: FlightConfig) -> str | None:
    """One line naming the control points that no strip's surface saw (outside every strip,
    or farther from its surface than ``matching.max_normal_distance_m``), which the
    adjustment therefore did not use; None when every one was used."""
    control = mission.control
    if control is None or not len(control):
        return None
    seen = {c.control_id for c in result.control}
    unused = [i for i, cid in enumerate(control.ids) if cid not in seen]
    if not unused:
        return None
    outside = outside_strips(mission.strips, control.xyz[unused],
                             config["matching.overlap_cell_m"])
    names = ", ".join(control.ids[i] for i in unused[:5]) + (", ..." if len(unused) > 5 else "")
    far = len(unused) - int(outside.sum())
    why = [f"{int(outside.sum())} outside every strip"] if outside.any() else []
    if far:
        why.append(f"{far} farther than {config['matching.max_normal_distance_m']:g} m from "
                   "the strips' surface (matching.max_normal_distance_m)")
    return (f"{len(unused)} of {len(control)} control points not used ({names}): "
            f"{' and '.join(why)}")


def convergence_warning(result: CalibrationResult, config: FlightConfig) -> str | None:
    """One line saying that the adjustment did not converge and why (the result's
    ``convergence``: how far from it the last iteration was, its largest step in sigmas of that
    parameter, against what re-matching alone moves it by); None when it converged (within
    the re-matching noise included)."""
    if result.converged:
        return None
    n = result.iterations
    why = result.convergence.removeprefix("not converged").lstrip(":, ")
    if not why:  # (a result from before the outcome was recorded)
        sol = result.solution
        history = result.history
        last = history[-1] - history[-2] if len(history) > 1 else \
            (history[-1] if history else np.zeros_like(sol.delta))
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = np.abs(last) / sol.sigma
        ratio[~np.isfinite(ratio)] = -1.0
        worst = int(np.argmax(ratio))
        why = (f"its last step moved {PARAMETER_NAMES[worst]} by {ratio[worst]:.3g} sigma"
               if ratio[worst] >= 0 else "")
    limit = config["calibration.max_iterations"]
    stopped = ("stopped early" if n < limit else
               f"calibration.max_iterations {limit}")
    rule = f"converged: every step below {config['calibration.convergence_fraction']:g} sigma"
    return (f"the adjustment did not converge in {n} iteration{'' if n == 1 else 's'} "
            f"({stopped}){'; ' + why if why else ''} ({rule}, or steps that stopped shrinking "
            "within the re-matching noise); the calibration is written with converged: false")


# ---------------------------------------------------------------------------- reports
@dataclass
class Truth:
    """Simulated truth kept beside a simulated bag: the biases and, where the file records
    them (``simulation.trajectory_errors``), each strip's trajectory error by strip id."""

    biases: dict[str, float]
    trajectory_errors: dict[int, StripTrajectoryError] = field(default_factory=dict)

    @classmethod
    def read(cls, path: str | Path) -> Truth:
        """The truth YAML at ``path`` (written by ``lidarcal simulate``; biases SI, 0 where not
        given); a ConfigError names what is wrong."""
        path = Path(path)
        doc = read_yaml(path, what="truth file")
        biases = doc.get("biases") if isinstance(doc, Mapping) else None
        if not isinstance(biases, Mapping):
            raise ConfigError(f"{path}: missing 'biases'")
        values = {}
        for name in PARAMETER_NAMES:
            value = biases.get(name, 0.0)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ConfigError(f"{path}: biases.{name} is not a number: {value!r}")
            values[name] = float(value)
        simulation = doc.get("simulation")
        block = simulation.get("trajectory_errors") if isinstance(simulation, Mapping) else None
        try:
            errors = {} if block is None else read_trajectory_errors(block)
        except ConfigError as exc:
            raise ConfigError(f"{path}: simulation.{exc}") from None
        return cls(values, errors)


def _fmt(name: str, value: float, sign: bool = True) -> str:
    return format_value(name, value, sign=sign, width=8 if sign and name != "dS" else 0)


def format_report(
    result: CalibrationResult,
    config: FlightConfig,
    *,
    title: str = "",
    truth: Truth | None = None,
) -> str:
    """A readable table: estimates with sigmas (arcsec, cm), correlations above 0.5, and per
    strip pair the RMS normal discrepancy before and after with its QA level."""
    sol = result.solution
    lines = []
    if title:
        lines.append(title)
    header = f"{'parameter':<9} {'estimate':>15} {'sigma':>17}"
    if truth is not None:
        header += f" {'truth':>15} {'error/sigma':>11}"
    lines.append(header)
    for i, name in enumerate(PARAMETER_NAMES):
        st = sol.status[name]
        if st.state == ParameterState.ESTIMATED:
            sigma = "+- " + _fmt(name, sol.sigma[i], False)
            row = f"{name:<9} {_fmt(name, sol.delta[i]):>15} {sigma:>17}"
            if truth is not None:
                err = (sol.delta[i] - truth.biases[name]) / sol.sigma[i]
                row += f" {_fmt(name, truth.biases[name]):>15} {err:>+11.2f}"
        elif st.state == ParameterState.FIXED:
            row = f"{name:<9} {'fixed at ' + _fmt(name, sol.delta[i]).strip():>33}"
            if truth is not None:
                row += f" {_fmt(name, truth.biases[name]):>15}"
        else:
            row = f"{name:<9} not estimable: {st.reason}"
        lines.append(row)
    lines.append(
        f"sigma0 {sol.sigma0 * 100:.2f} cm, redundancy {sol.redundancy}, "
        f"{result.iterations} iterations, {_converged_words(result)}; "
        f"{result.n_pair_correspondences} strip-pair and {result.n_control_correspondences} "
        "control correspondences"
    )
    if result.convergence and not result.convergence.startswith("converged: every step"):
        lines.append(f"convergence: {result.convergence}")  # (how, where not plain)
    pairs = sol.correlated_pairs(0.5)
    if pairs:
        lines.append("correlations above 0.5: " + ", ".join(f"{a}/{b} {r:+.2f}"
                                                             for a, b, r in pairs))
    for w in sol.warnings:
        lines.append(f"warning: {w}")
    if result.dropped_non_finite:
        lines.append(f"dropped {result.dropped_non_finite} points with non-finite values")
    if result.thinned_points:
        cell = config["calibration.thinning_cell_m"]
        lines.append(f"thinned to one point per {cell:g} m cell per strip and cloud: "
                     f"{result.thinned_points} points left out")
    if result.models:
        lines.append("model: " + describe_models(result.models))
    lines.extend(trajectory_lines(result))
    if not result.models or any(c.model != PositioningModel.RIGOROUS
                                for c in result.models.values()):
        heading = describe_heading_use(result.heading_from, result.crab_deg)
        if heading:
            lines.append(heading)
    for sid, qa in sorted(result.laser_qa.items()):
        lines.extend(f"warning: strip {sid}: {w}" for w in qa.warnings)
    lines.extend(_pair_lines(result, config))
    return "\n".join(lines)


def trajectory_lines(result: CalibrationResult) -> list[str]:
    """The trajectory model (and why, where ``auto`` chose it), then each strip's estimated
    error at its mid time and its drift (docs/method.md section 11), in cm and cm/s."""
    lines = [f"trajectory errors: {result.trajectory_choice}"]
    est = result.trajectory
    if est is None:
        return lines
    for sid in sorted(est.strips):
        se = est.strips[sid]
        row = (f"  strip {sid}: offset E {se.offset[0] * 100:+.1f} N {se.offset[1] * 100:+.1f} "
               f"U {se.offset[2] * 100:+.1f} cm (+- {se.offset_sigma[0] * 100:.1f} "
               f"{se.offset_sigma[1] * 100:.1f} {se.offset_sigma[2] * 100:.1f})")
        if se.drift is not None:
            row += (f", drift {se.drift[0] * 100:+.2f} {se.drift[1] * 100:+.2f} "
                    f"{se.drift[2] * 100:+.2f} cm/s")
        lines.append(row)
    return lines


def _converged_words(result: CalibrationResult) -> str:
    """``converged``, ``converged within the re-matching noise`` or ``NOT converged``."""
    if not result.converged:
        return "NOT converged"
    return ("converged within the re-matching noise"
            if result.convergence.startswith("converged within") else "converged")


def format_agreement(result: CalibrationResult, config: FlightConfig, *, title: str = "",
                     identity_written: Path | None = None) -> str:
    """What ``lidarcal calibrate`` prints when nothing could be estimated
    (:class:`~lidarcal_ros.core.calibration.result.NothingEstimated`): how well the strips
    agree as delivered (per strip pair the coverage, the sample points matched to a patch, RMS
    and 95th percentile of their normal discrepancy, the QA level), the control residuals, and
    what became of the calibration file."""
    lines = [title] if title else []
    lines.append(f"nothing estimated: {result.nothing_estimated}")
    if result.dropped_non_finite:
        lines.append(f"dropped {result.dropped_non_finite} points with non-finite values")
    if result.pairs:
        lines.append("how well the strips agree as delivered:")
    else:
        lines.append("no strip pair overlaps: there is no agreement between strips to report")
    lines.extend(_pair_lines(result, config, delivered=True))
    if result.height_agreement:
        warn, error = config["qa.rmsdz_warn_m"], config["qa.max_difference_m"]
        lines.append("heights of last returns on smooth cells both strips cover (median and "
                     "robust RMS of A - B):")
        for q in result.height_agreement:
            level = qa_level(q.rms_dz, warn_m=warn, error_m=error)
            lines.append(f"{q.strip_a:>3} & {q.strip_b:<3} {q.coverage * 100:>7.0f}% "
                         f"{q.n_cells:>6} cells, median {q.median_dz * 100:+6.1f} cm, RMS "
                         f"{q.rms_dz * 100:5.1f} cm  {level}")
    if identity_written is not None:
        lines.append(f"calibration that moves no point (every bias at its fixed value, none "
                     f"estimated) written to {identity_written}: lidarcal correct still gives "
                     "reflectance")
    else:
        lines.append("no calibration written (--write-identity writes one that moves no "
                     "point, for lidarcal correct)")
    return "\n".join(lines)


def _pair_lines(result: CalibrationResult, config: FlightConfig, *,
                delivered: bool = False) -> list[str]:
    """The strip-pair QA table and the control residuals; ``delivered``: of the strips as
    delivered (one set of figures, matches counting the sample points matched)."""
    warn = config["qa.rmsdz_warn_m"]
    error = config["qa.max_difference_m"]
    rule = f"QA (RMS: WARN > {warn * 100:.0f} cm, ERROR > {error * 100:.0f} cm)"
    lines = []
    if result.pairs and delivered:
        lines.append(f"{'strips':<8} {'coverage':>8} {'matches':>8} {'RMS':>8} "
                     f"{'95%':>8}  {rule}")
    elif result.pairs:
        lines.append(f"{'strips':<8} {'coverage':>8} {'matches':>8} {'RMS before':>11} "
                     f"{'RMS after':>10} {'95% after':>10}  {rule}")
    for p in result.pairs:
        head = f"{p.strip_a:>3} & {p.strip_b:<3} {p.coverage * 100:>7.0f}% {p.correspondences:>8}"
        if delivered and not p.n_after:
            lines.append(f"{head} {'n/a':>8} {'n/a':>8}  no point matched a usable patch "
                         "(a smooth, plane surface: ground, roofs)")
            continue
        level = qa_level(p.rms_after, warn_m=warn, error_m=error)
        if delivered:
            lines.append(f"{head} {p.rms_after * 100:>5.1f} cm {p.p95_after * 100:>5.1f} cm  "
                         f"{level}")
        else:
            lines.append(f"{head} {p.rms_before * 100:>8.1f} cm {p.rms_after * 100:>7.1f} cm "
                         f"{p.p95_after * 100:>7.1f} cm  {level}")
    if result.control:
        lines.append("control residuals (normal distance, before -> after):" if not delivered
                     else "control residuals (normal distance):")
        for c in result.control:
            after = "n/a" if math.isnan(c.after) else f"{c.after * 100:+.1f} cm"
            lines.append(f"  {c.control_id} in strip {c.strip_id}: {c.before * 100:+.1f} cm"
                         + ("" if delivered else f" -> {after}"))
    return lines


def qa_level(rms_m: float, *, warn_m: float, error_m: float) -> str:
    """OK / WARN / ERROR for a swath-to-swath RMS discrepancy (USGS LBS QL2: 8 cm, 16 cm)."""
    if not math.isfinite(rms_m) or rms_m > error_m:
        return "ERROR"
    return "WARN" if rms_m > warn_m else "OK"


#: The units of ``--biases`` values: SI per unit.
_BIAS_UNITS = {**LENGTH_UNITS, "arcsec": math.pi / 180 / 3600, "rad": 1.0, "ppm": 1e-6}


def parse_biases(text: str) -> dict[str, float]:
    """``"dX=0.05,domega=-29arcsec,dr=11.8cm"`` to SI values.

    Units accepted as suffixes: ``arcsec`` (angles), ``cm``, ``mm``, ``m``, ``rad``, ``ppm``.
    """
    out: dict[str, float] = {}
    for part in text.split(","):
        part = part.strip()
        if not part:
            continue
        if "=" not in part:
            raise ConfigError(f"--biases: expected NAME=VALUE, got '{part}'")
        name, raw = (s.strip() for s in part.split("=", 1))
        if name not in PARAMETER_NAMES:
            raise ConfigError(f"--biases: unknown parameter '{name}'")
        try:
            out[name] = parse_quantity(raw, _BIAS_UNITS)
        except ValueError:
            raise ConfigError(f"--biases: '{part}' is not a number") from None
    return out


def truth_document(biases: Mapping[str, float], config: Mapping[str, Any]) -> dict[str, Any]:
    """The truth file written beside a simulated bag."""
    return {
        "biases": {n: float(biases.get(n, 0.0)) for n in PARAMETER_NAMES},
        "simulation": {k: (v.tolist() if isinstance(v, np.ndarray) else v)
                       for k, v in config.items()},
    }


def simulation_paths(output: str | Path) -> dict[str, Path]:
    """Where ``lidarcal simulate -o OUT`` writes: the bag, ``OUT_control.csv``,
    ``OUT_truth.yaml``."""
    out = Path(output)
    stem = out.with_suffix("") if out.suffix == ".mcap" else out
    return {
        "bag": out,
        "control": stem.parent / f"{stem.name}_control.csv",
        "truth": stem.parent / f"{stem.name}_truth.yaml",
    }


def write_simulation(output: str | Path, sim: Any, *, overwrite: bool = False) -> dict[str, Path]:
    """Write a :class:`~lidarcal_ros.core.simulation.simulate.SimulatedMission` as the contract's
    files (all of them or, when one fails, none of the new ones).

    Raises
    ------
    OutputError
        One of the outputs exists and ``overwrite`` is False, or cannot be written.
    """
    from lidarcal_ros.io.bag.mission_bag import write_mission_bag

    def bag(path: Path) -> dict[str, Any]:
        write_mission_bag(path, sim.mission, overwrite=overwrite)
        return truth_document(sim.biases, sim.config)

    return write_simulation_files(output, sim.mission.control, bag, overwrite=overwrite)


def write_simulation_stream(output: str | Path, stream: Any, *, overwrite: bool = False
                            ) -> tuple[dict[str, Path], int]:
    """Write a :class:`~lidarcal_ros.core.simulation.simulate.MissionStream` as the contract's
    files, a block of points at a time (memory that does not grow with the mission), the same
    files :func:`write_simulation` writes of the same spec's mission; and the number of points.

    Raises
    ------
    OutputError
        As :func:`write_simulation`.
    """
    from lidarcal_ros.io.bag.mission_bag import write_mission_stream

    n_points = 0

    def bag(path: Path) -> dict[str, Any]:
        nonlocal n_points
        n_points = write_mission_stream(path, stream.lines(), control=stream.control,
                                        overwrite=overwrite)[1]
        return truth_document(stream.biases, stream.config)

    return write_simulation_files(output, stream.control, bag, overwrite=overwrite), n_points


def write_simulation_files(output: str | Path, control: Any,
                            write_bag: Callable[[Path], dict[str, Any]], *, overwrite: bool
                            ) -> dict[str, Path]:
    """The bag (``write_bag``, which returns the truth document), the control points and the
    truth file, all or none."""
    from lidarcal_ros.io.survey.control import write_control_csv

    paths = simulation_paths(output)
    for key in ("bag", "control", "truth"):
        check_output(paths[key], overwrite=overwrite, directory=key == "bag")
    if control is None or not len(control):
        paths.pop("control")
    written: list[Path] = []
    try:
        truth = write_bag(paths["bag"])
        written.append(paths["bag"])
        if "control" in paths:
            write_control_csv(paths["control"], control)
            written.append(paths["control"])
        write_text(paths["truth"], yaml.safe_dump(truth, sort_keys=False), what="truth file",
                   overwrite=overwrite)
    except BaseException:
        for path in written:
            remove_quietly(path)
        raise
    return paths


__all__ = [
    "Truth", "calibrate_mission", "convergence_warning", "format_agreement", "format_report",
    "load_for_calibration", "load_mission", "parse_biases", "qa_level", "simulation_paths",
    "trajectory_lines", "truth_document",
    "unused_control", "write_simulation", "write_simulation_files", "write_simulation_stream",
]
