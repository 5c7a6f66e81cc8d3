"""The calibration file as ``lidarcal report`` shows it: biases, correlations, facts, coverage."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lidarcal_ros.core.adjustment.least_squares import ParameterState
from lidarcal_ros.core.calibration.extrinsic import timing_text
from lidarcal_ros.core.params import PARAMETER_NAMES
from lidarcal_ros.errors import ConfigError
from lidarcal_ros.io.calibration_file import (
    ROOT_KEY,
    CalibrationRecord,
    Extrinsic,
    read_calibration,
)
from lidarcal_ros.io.report.content import BiasEntry
from lidarcal_ros.io.yaml_file import read_yaml

__all__ = ["ReportCalibration", "extrinsic_facts", "read_report_calibration"]


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
        sigma0, redundancy, iterations, convergence, the mounting and timing bias of clouds
        in the sensor's frame (:func:`extrinsic_facts`), correspondences, as in the file.
    coverage : dict
        ``(strip, strip) -> overlap fraction`` of the pairs the file lists.
    warnings : list of str
    trajectory_model : str
        The file's ``trajectory_model``: how the trajectory errors were modelled and why
        ('' where the file does not say).
    """

    path: Path
    record: CalibrationRecord
    biases: list[BiasEntry]
    correlation_names: list[str]
    correlation: np.ndarray
    facts: list[tuple[str, str]]
    coverage: dict[tuple[int, int], float]
    warnings: list[str]
    trajectory_model: str = ""


def read_report_calibration(path: str | Path) -> ReportCalibration:
    """Read a calibration file (docs/interface.md) with the keys the report shows beyond the
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
            state = ParameterState.ESTIMATED
        elif reason:
            state = ParameterState.NOT_ESTIMABLE
        else:
            state = ParameterState.FIXED
        biases.append(BiasEntry(name, record.values[name],
                                record.sigmas[name] if state == ParameterState.ESTIMATED
                                else None,
                                state, str(reason) if reason else ""))
    names, matrix = _correlation_matrix(path, body.get("correlation"))
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
    if record.extrinsic is not None:
        facts.extend(extrinsic_facts(record.extrinsic))
    corr = body.get("correspondences")
    if isinstance(corr, Mapping):
        counts = [corr.get(k) if isinstance(corr.get(k), int) else "?"  # (not .nan, 1e400)
                  for k in ("strip_pairs", "control")]
        facts.append(("correspondences", f"{counts[0]} strip-pair, {counts[1]} control"))
    coverage = {}
    for k, pair in enumerate(body.get("strip_pairs") or []):
        strips = pair.get("strips") if isinstance(pair, Mapping) else None
        value = pair.get("coverage") if isinstance(pair, Mapping) else None
        if isinstance(strips, list) and len(strips) == 2 and isinstance(value, (int, float)):
            if not all(isinstance(s, int) and not isinstance(s, bool) for s in strips):
                raise ConfigError(f"{path}: strip_pairs[{k}].strips must be two strip ids, got "
                                  f"{strips!r}")
            if not 0.0 <= value <= 1.0:  # (NaN too)
                raise ConfigError(f"{path}: strip_pairs[{k}].coverage must be a fraction in "
                                  f"[0, 1], got {value!r}")
            a, b = sorted(strips)
            coverage[(a, b)] = float(value)
    warnings = [str(w) for w in body.get("warnings") or []]
    for strip in body.get("strips") or []:
        if isinstance(strip, Mapping):
            warnings.extend(f"strip {strip.get('id')}: {w}" for w in strip.get("warnings") or [])
    choice = body.get("trajectory_model")
    return ReportCalibration(path, record, biases, names, matrix, facts, coverage, warnings,
                             str(choice) if choice is not None else "")


def extrinsic_facts(extrinsic: Extrinsic) -> list[tuple[str, str]]:
    """The mounting of clouds in the sensor's frame as the report's facts: the calibrated
    transform against the nominal (mm, arcsec) and the timing bias ``dt`` (ms, with its
    sigma where estimated; held at 0 with the calibration's statement; no line where the
    calibration did not try)."""
    m, nominal = extrinsic.mounting, extrinsic.nominal
    shift_mm = float(np.linalg.norm(m.translation - nominal.translation)) * 1e3
    cos = (float(np.trace(nominal.rotation.T @ m.rotation)) - 1.0) / 2.0
    turn = math.degrees(math.acos(min(1.0, max(-1.0, cos)))) * 3600.0
    out = [("mounting", f"{extrinsic.parent} -> {extrinsic.child}: translation "
            + ", ".join(f"{v:+.4f}" for v in m.translation) + " m, rotation (qx, qy, qz, qw) "
            + ", ".join(f"{v:+.6f}" for v in m.quaternion)
            + f"; {shift_mm:.1f} mm and {turn:.1f} arcsec from the nominal")]
    # (a statement says it was held at 0, and why)
    text = extrinsic.time_offset_note or timing_text(
        extrinsic.time_offset_s, extrinsic.time_offset_sigma_s, "", plus_minus="\u00b1")
    if extrinsic.time_offset_sigma_s is not None and not extrinsic.time_offset_note:
        text += ", estimated with the mounting (the correction takes it off each point's time)"
    if text:
        out.append(("timing bias dt", text))
    return out


def _correlation_matrix(path: Path, doc: Any) -> tuple[list[str], np.ndarray]:
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
    if not names and matrix.size == 0:  # nothing estimated (--write-identity): [] is 0 x 0
        matrix = matrix.reshape(0, 0)
    if matrix.shape != (len(names), len(names)):
        raise ConfigError(f"{path}: correlation.matrix is {matrix.shape}, expected "
                          f"{len(names)} x {len(names)} for its names")
    # (a correlation is within [-1, 1]; round-off of the file's digits aside; NaN is not)
    if not (np.abs(matrix) <= 1.0 + 1e-9).all():
        raise ConfigError(f"{path}: correlation.matrix holds values outside [-1, 1] or not "
                          "finite")
    return [str(n) for n in names], matrix

