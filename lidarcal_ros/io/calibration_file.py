"""The calibration file of docs/interface.md (YAML, SI units)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from lidarcal_ros.core.adjustment.least_squares import ParameterState
from lidarcal_ros.core.calibration.result import CalibrationResult
from lidarcal_ros.core.georeferencing.laser_geometry import PositioningModel
from lidarcal_ros.core.georeferencing.rigorous import MIXED, describe_models, models_summary
from lidarcal_ros.core.georeferencing.sensor_frame import Mounting
from lidarcal_ros.core.params import PARAMETER_NAMES
from lidarcal_ros.core.trajectory.strip_errors import (
    SPLINE_INTERPOLATION,
    StripBasis,
    StripError,
    TrajectoryEstimate,
    TrajectoryModel,
)
from lidarcal_ros.core.units import finite_or_none
from lidarcal_ros.errors import ConfigError, OutputError
from lidarcal_ros.io.output_files import os_reason, write_together
from lidarcal_ros.io.yaml_file import read_yaml

ROOT_KEY = "lidarcal_calibration"
#: The largest timing bias of a file, s: beyond it the value is taken as written in other
#: units (ms).
MAX_TIME_OFFSET_S = 1.0
#: The file's ``model`` (plain strings: YAML writes no enum).
_LEVEL = PositioningModel.LEVEL.value
_FILE_MODELS = (_LEVEL, PositioningModel.RIGOROUS.value, MIXED)


@dataclass
class CalibrationRecord:
    """What a calibration file holds: values (SI) and which were estimated."""

    values: dict[str, float]
    sigmas: dict[str, float | None]
    estimated: dict[str, bool]
    sigma0: float | None = None
    #: The point-positioning model the biases were estimated with: ``level``, ``rigorous``,
    #: ``mixed`` (strips of both), or None where the file does not say.
    model: str | None = None
    #: Each strip's trajectory error (docs/method.md section 11), where the file holds one.
    trajectory: TrajectoryEstimate | None = None
    #: The calibrated mounting of clouds in the sensor's frame (docs/method.md section 12),
    #: where the file holds one.
    extrinsic: Extrinsic | None = None

    @property
    def delta(self) -> np.ndarray:
        """The values (8,) in ``PARAMETER_NAMES`` order, SI units."""
        return np.array([self.values[n] for n in PARAMETER_NAMES])


@dataclass(frozen=True)
class Extrinsic:
    """The calibration file's ``extrinsic`` block: the calibrated mounting ``parent ->
    child`` (REP-103; docs/interface.md) and the nominal one it was calibrated from, with the
    clouds' timing bias (the project's extension: ``time_offset_s``, delivered - true
    per-point time, s, which a correction takes off each point's time; absent from a file:
    0, not estimated)."""

    parent: str
    child: str
    mounting: Mounting
    nominal: Mounting
    time_offset_s: float = 0.0
    #: Its sigma, s; None: not estimated (held at ``time_offset_s``).
    time_offset_sigma_s: float | None = None
    #: Its correlation with each bias estimated with it (written where estimated).
    time_offset_correlation: Mapping[str, float] = field(default_factory=dict)
    #: Why it was held at 0 where it was asked for and the flight cannot see it ("": not so).
    time_offset_note: str = ""

    def document(self) -> dict[str, Any]:
        """The block as docs/interface.md writes it (translation m, rotation ``[qx, qy, qz,
        qw]``, the timing bias s)."""
        def transform(m: Mounting) -> dict[str, list[float]]:
            return {"translation": [float(v) for v in m.translation],
                    "rotation": [float(v) for v in m.quaternion]}

        doc: dict[str, Any] = {"parent": self.parent, "child": self.child,
                               **transform(self.mounting), "nominal": transform(self.nominal),
                               "time_offset_s": float(self.time_offset_s),
                               "time_offset_sigma_s": finite_or_none(self.time_offset_sigma_s)}
        if self.time_offset_correlation:
            doc["time_offset_correlation"] = {k: float(v) for k, v in
                                              self.time_offset_correlation.items()}
        if self.time_offset_note:
            doc["time_offset_not_estimable"] = self.time_offset_note
        return doc

    def urdf_joint(self) -> str:
        """The calibrated mounting as a URDF ``<joint>`` (fixed; ``origin`` xyz in m, rpy
        in rad: roll, pitch, yaw about the parent's fixed x, y, z axes)."""
        from scipy.spatial.transform import Rotation

        xyz = " ".join(f"{v:.6f}" for v in self.mounting.translation)
        rpy = " ".join(f"{v:.9f}" for v in
                       Rotation.from_matrix(self.mounting.rotation).as_euler("xyz"))
        return (f'<!-- lidarcal: the calibrated mounting {self.parent} -> {self.child} -->\n'
                f'<joint name="{self.parent}_to_{self.child}" type="fixed">\n'
                f'  <parent link="{self.parent}"/>\n'
                f'  <child link="{self.child}"/>\n'
                f'  <origin xyz="{xyz}" rpy="{rpy}"/>\n'
                f'</joint>\n')


def urdf_path(calibration: str | Path) -> Path:
    """Where the URDF joint of a calibration file goes: ``CAL.urdf.xml`` beside it."""
    path = Path(calibration)
    return path.with_name(f"{path.stem}.urdf.xml")


def calibration_document(result: CalibrationResult, *,
                         extrinsic: Extrinsic | None = None) -> dict[str, Any]:
    """The YAML document (a dict) for a calibration result (with the ``extrinsic`` block of
    clouds in the sensor's frame where given)."""
    sol = result.solution
    biases: dict[str, Any] = {}
    for i, name in enumerate(PARAMETER_NAMES):
        st = sol.status[name]
        entry: dict[str, Any] = {
            "value": float(sol.delta[i]),
            "sigma": finite_or_none(float(sol.sigma[i])),
            "estimated": st.state == ParameterState.ESTIMATED,
        }
        if st.state == ParameterState.NOT_ESTIMABLE:
            entry["not_estimable"] = st.reason
        biases[name] = entry
    doc: dict[str, Any] = {
        "biases": biases,
        "sigma0": finite_or_none(float(sol.sigma0)),
        "redundancy": int(sol.redundancy),
        "correlation": {
            "names": list(sol.estimated),
            "matrix": [[float(v) for v in row] for row in sol.correlation],
        },
        "iterations": int(result.iterations),
        "converged": bool(result.converged),
        "convergence": result.convergence,
        "model": models_summary(result.models) if result.models else _LEVEL,
        "model_detail": describe_models(result.models) if result.models else _LEVEL,
        "correspondences": {
            "strip_pairs": int(result.n_pair_correspondences),
            "control": int(result.n_control_correspondences),
        },
        "strip_pairs": [
            {"strips": [int(p.strip_a), int(p.strip_b)],
             "coverage": round(float(p.coverage), 4),
             "correspondences": int(p.correspondences),
             "rms_before_m": finite_or_none(p.rms_before),
             "rms_after_m": finite_or_none(p.rms_after),
             "p95_after_m": finite_or_none(p.p95_after)}
            for p in result.pairs
        ],
        "strips": [_strip_entry(sid, result) for sid in sorted(result.models)],
        "control_residuals": [
            {"id": c.control_id, "strip": c.strip_id, "before_m": finite_or_none(c.before),
             "after_m": finite_or_none(c.after)} for c in result.control
        ],
    }
    if not result.convergence:  # (no adjustment ran)
        del doc["convergence"]
    if result.nothing_estimated:
        doc["nothing_estimated"] = result.nothing_estimated
        doc["height_agreement"] = [
            {"strips": [int(q.strip_a), int(q.strip_b)], "coverage": round(float(q.coverage), 4),
             "cells": int(q.n_cells), "median_m": finite_or_none(q.median_dz),
             "rms_m": finite_or_none(q.rms_dz)}
            for q in result.height_agreement
        ]
    doc["trajectory_model"] = result.trajectory_choice
    if result.trajectory is not None:
        doc["trajectory"] = trajectory_document(result.trajectory)
    if result.partial_strips:
        doc["partial_strips"] = {str(sid): text for sid, text in
                                 sorted(result.partial_strips.items())}
    if result.dropped_non_finite:
        doc["dropped_non_finite_points"] = int(result.dropped_non_finite)
    if extrinsic is not None:
        doc["extrinsic"] = extrinsic.document()
    if sol.warnings:
        doc["warnings"] = list(sol.warnings)
    return {ROOT_KEY: doc}


def trajectory_document(estimate: TrajectoryEstimate) -> dict[str, Any]:
    """docs/interface.md's ``trajectory`` block: each strip's error ``e_s(t)`` (delivered -
    true, map frame, m; drift in m/s about ``t_ref``, s; a spline's knots, coefficients and
    interpolation) and its sigmas."""
    strips: dict[str, Any] = {}
    for sid in sorted(estimate.strips):
        se = estimate.strips[sid]
        entry: dict[str, Any] = {"t_ref": float(se.t_ref), "offset": _floats(se.offset),
                                 "offset_sigma": _floats(se.offset_sigma)}
        if se.drift is not None and se.drift_sigma is not None:
            entry["drift"] = _floats(se.drift)
            entry["drift_sigma"] = _floats(se.drift_sigma)
        if se.basis.knots is not None:
            entry["knots"] = _floats(se.basis.knots)
            entry["coefficients"] = [_floats(c) for c in se.coefficients]
            entry["coefficient_sigma"] = [_floats(c) for c in se.sigma]
            entry["interpolation"] = SPLINE_INTERPOLATION
        strips[str(sid)] = entry
    return {"model": estimate.model.value, "strips": strips}


def _floats(values: Any) -> list[float | None]:
    return [finite_or_none(float(v)) for v in np.asarray(values).ravel()]


def read_trajectory_block(path: Path, block: Any) -> TrajectoryEstimate:
    """The ``trajectory`` block of a calibration file (:func:`trajectory_document`).

    Raises
    ------
    ConfigError
        A model other than offset, drift or spline, a strip id that is not a whole number, a
        missing or non-finite ``t_ref``, ``offset``, ``drift``, ``knots`` or
        ``coefficients``, a negative or infinite sigma; one line naming the key. (A sigma
        that is null or absent is read as NaN: not known.)
    """
    if not isinstance(block, Mapping):
        raise ConfigError(f"{path}: trajectory must be a mapping with model and strips")
    try:
        model = TrajectoryModel(block.get("model"))
    except ValueError:
        model = TrajectoryModel.NONE
    if not model.estimated:
        raise ConfigError(f"{path}: trajectory.model must be offset, drift or spline, got "
                          f"{block.get('model')!r}")
    raw = block.get("strips")
    if not isinstance(raw, Mapping):
        raise ConfigError(f"{path}: trajectory.strips must be a mapping of strip ids")
    strips: dict[int, StripError] = {}
    for key, entry in raw.items():
        where = f"{path}: trajectory.strips.{key}"
        try:
            sid = int(str(key))
        except ValueError:
            raise ConfigError(f"{where}: the strip id is not a whole number") from None
        if not isinstance(entry, Mapping):
            raise ConfigError(f"{where} must be a mapping with t_ref and offset")

        def vector(name: str, size: int | None, entry: Mapping[str, Any] = entry,
                   where: str = where) -> np.ndarray:
            value = entry.get(name)
            try:
                out = np.array(value, dtype=np.float64).reshape(-1 if size is None else size)
            except (TypeError, ValueError):
                out = np.array([np.nan])
            if not out.size or not np.isfinite(out).all():
                raise ConfigError(f"{where}.{name} must be {size or 'a list of'} finite "
                                  f"numbers, got {value!r}")
            return out

        def sigmas(name: str, rows: int, entry: Mapping[str, Any] = entry,
                   where: str = where) -> np.ndarray:
            # (null: not known, NaN; absent as a whole: all NaN)
            value = entry.get(name)
            if value is None:
                return np.full((rows, 3), np.nan)
            try:
                out = np.array([np.nan if v is None else v for v in np.ravel(
                    np.array(value, dtype=object))], dtype=np.float64).reshape(rows, 3)
            except (TypeError, ValueError):
                raise ConfigError(f"{where}.{name} must be {3 * rows} numbers >= 0 or null, "
                                  f"got {value!r}") from None
            if (out < 0).any() or np.isinf(out).any():
                raise ConfigError(f"{where}.{name} must be {3 * rows} numbers >= 0 or null, "
                                  f"got {value!r}")
            return out

        t_ref = float(vector("t_ref", 1)[0])
        if model is TrajectoryModel.SPLINE:
            knots = vector("knots", None)
            coefficients = vector("coefficients", None).reshape(-1, 3)
            if knots.size < 5 or np.any(np.diff(knots) <= 0) or \
                    coefficients.shape[0] != knots.size - 4:
                raise ConfigError(f"{where}: a cubic spline of {knots.size} increasing knots "
                                  f"takes {3 * max(knots.size - 4, 0)} coefficients, got "
                                  f"{coefficients.size}")
            basis = StripBasis(model, t_ref, knots)
            sigma = sigmas("coefficient_sigma", coefficients.shape[0])
        else:
            coefficients = vector("offset", 3)[None, :]
            sigma = sigmas("offset_sigma", 1)
            if model is TrajectoryModel.DRIFT:
                coefficients = np.vstack([coefficients, vector("drift", 3)])
                sigma = np.vstack([sigma, sigmas("drift_sigma", 1)])
            basis = StripBasis(model, t_ref)
        strips[sid] = StripError(sid, basis, coefficients, sigma)
    return TrajectoryEstimate(model, strips)


def _strip_entry(strip_id: int, result: CalibrationResult) -> dict[str, Any]:
    """A strip's model, the reason for it, and its laser-vector QA."""
    choice = result.models[strip_id]
    entry: dict[str, Any] = {"id": int(strip_id), "model": choice.model.value,
                             "model_reason": choice.reason}
    qa = result.laser_qa.get(strip_id)
    if qa is not None:
        entry.update({
            "along_track_median_m": finite_or_none(qa.along_median_m),
            "along_track_spread_m": finite_or_none(qa.along_spread_m),
            "scan_angle_deg": [finite_or_none(qa.scan_min_deg), finite_or_none(qa.scan_max_deg)],
        })
        if qa.warnings:
            entry["warnings"] = list(qa.warnings)
    return entry


def write_calibration(path: str | Path, result: CalibrationResult, *,
                      overwrite: bool = True, extrinsic: Extrinsic | None = None) -> Path:
    """Write the calibration file (completely or not at all: a reader never sees half a
    file, a failure leaves a previous file untouched); returns its path. A missing parent
    directory is created (a node's ``calibration_file``). Without ``overwrite`` a file that
    appeared there while the command ran is refused, not replaced. With ``extrinsic`` the
    file holds its block and the URDF joint is written beside it (:func:`urdf_path`).

    Raises
    ------
    OutputError
        The file cannot be written; one line with the operating system's reason.
    """
    path = Path(path)
    text = yaml.safe_dump(calibration_document(result, extrinsic=extrinsic), sort_keys=False,
                          width=120)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{path}: cannot write calibration ({os_reason(exc)})") from None
    files = [(path, text.encode("utf-8"), "calibration")]
    if extrinsic is not None:  # both or neither: a joint beside no calibration misleads
        files.append((urdf_path(path), extrinsic.urdf_joint().encode("utf-8"), "URDF joint"))
    write_together(files, overwrite=overwrite)
    return path


def read_calibration(path: str | Path) -> CalibrationRecord:
    """Read a calibration file.

    Raises
    ------
    ConfigError
        Missing file or key, a non-numeric value, a negative or non-finite sigma, an
        ``estimated`` that is not a boolean; one line naming the key.
    """
    path = Path(path)
    doc = read_yaml(path, what="calibration")
    if not isinstance(doc, Mapping) or not isinstance(doc.get(ROOT_KEY), Mapping):
        raise ConfigError(f"{path}: missing top-level key '{ROOT_KEY}'")
    body = doc[ROOT_KEY]
    biases = body.get("biases")
    if not isinstance(biases, Mapping):
        raise ConfigError(f"{path}: missing '{ROOT_KEY}.biases'")
    values: dict[str, float] = {}
    sigmas: dict[str, float | None] = {}
    estimated: dict[str, bool] = {}
    for name in PARAMETER_NAMES:
        entry = biases.get(name)
        if not isinstance(entry, Mapping) or "value" not in entry:
            raise ConfigError(f"{path}: missing 'biases.{name}.value'")
        value = entry["value"]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or \
                not math.isfinite(value):
            raise ConfigError(f"{path}: biases.{name}.value is not a finite number: {value!r}")
        _check_units(path, name, float(value))
        values[name] = float(value)
        sigmas[name] = _sigma(path, f"biases.{name}.sigma", entry.get("sigma"))
        flag = entry.get("estimated", False)
        if not isinstance(flag, bool):
            raise ConfigError(f"{path}: biases.{name}.estimated is not true or false: {flag!r}")
        estimated[name] = flag
    model = body.get("model")
    if model is not None and model not in _FILE_MODELS:
        raise ConfigError(f"{path}: model {model!r} is not one of level, rigorous, mixed")
    trajectory = body.get("trajectory")
    extrinsic = body.get("extrinsic")
    return CalibrationRecord(values, sigmas, estimated,
                             _sigma(path, "sigma0", body.get("sigma0")), model,
                             None if trajectory is None else
                             read_trajectory_block(path, trajectory),
                             None if extrinsic is None else read_extrinsic(path, extrinsic))


def _transform(path: Path, key: str, block: Any) -> Mounting:
    """A ``{translation, rotation}`` mapping of the file as a Mounting."""
    if not isinstance(block, Mapping):
        raise ConfigError(f"{path}: {key} must be a mapping with translation and rotation")
    try:
        return Mounting.from_quaternion(np.asarray(block.get("translation"), dtype=np.float64),
                                        np.asarray(block.get("rotation"), dtype=np.float64))
    except (ConfigError, TypeError, ValueError) as exc:
        raise ConfigError(f"{path}: {key}: translation [x, y, z] (m) and rotation [qx, qy, qz, "
                          f"qw] expected ({exc})") from None


def read_extrinsic(path: Path, block: Any) -> Extrinsic:
    """The ``extrinsic`` block of a calibration file (:meth:`Extrinsic.document`)."""
    if not isinstance(block, Mapping) or not all(
            isinstance(block.get(k), str) and block.get(k) for k in ("parent", "child")):
        raise ConfigError(f"{path}: extrinsic must name its parent and child frames")
    offset = block.get("time_offset_s", 0.0)
    if isinstance(offset, bool) or not isinstance(offset, (int, float)) or \
            not math.isfinite(offset) or abs(offset) > MAX_TIME_OFFSET_S:
        raise ConfigError(f"{path}: extrinsic.time_offset_s must be a number of seconds within "
                          f"+-{MAX_TIME_OFFSET_S:g}, got {offset!r}")
    correlation = block.get("time_offset_correlation") or {}
    note = block.get("time_offset_not_estimable") or ""
    if not isinstance(correlation, Mapping) or not isinstance(note, str):
        raise ConfigError(f"{path}: extrinsic.time_offset_correlation must map bias names to "
                          "numbers, time_offset_not_estimable be a text")
    return Extrinsic(block["parent"], block["child"],
                     _transform(path, "extrinsic", block),
                     _transform(path, "extrinsic.nominal", block.get("nominal")),
                     float(offset),
                     _sigma(path, "extrinsic.time_offset_sigma_s",
                            block.get("time_offset_sigma_s")),
                     {str(k): float(v) for k, v in correlation.items()}, note)


def _sigma(path: Path, key: str, value: Any) -> float | None:
    """A standard deviation of the file: null (or NaN: not known), or a finite number not
    below zero."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or \
            not math.isfinite(value) or value < 0:
        raise ConfigError(f"{path}: {key} must be null or a finite number >= 0, got {value!r}")
    return float(value)


#: Plausibility bounds (SI) that catch values written in other units (arcsec, cm, ppm).
_PLAUSIBLE = {"dX": 5.0, "dY": 5.0, "dZ": 5.0, "domega": 0.05, "dphi": 0.05, "dkappa": 0.05,
              "dr": 5.0, "dS": 0.05}


def _check_units(path: Path, name: str, value: float) -> None:
    limit = _PLAUSIBLE[name]
    if abs(value) > limit:
        unit = "rad" if name in ("domega", "dphi", "dkappa") else ("m" if name != "dS" else "1")
        raise ConfigError(
            f"{path}: biases.{name}.value {value:g} is implausible in SI units ({unit}; "
            f"|value| <= {limit:g}); arcseconds or centimetres written by mistake?"
        )


__all__ = [
    "MAX_TIME_OFFSET_S",
    "ROOT_KEY",
    "CalibrationRecord",
    "Extrinsic",
    "calibration_document",
    "read_calibration",
    "read_extrinsic",
    "read_trajectory_block",
    "trajectory_document",
    "urdf_path",
    "write_calibration",
]
