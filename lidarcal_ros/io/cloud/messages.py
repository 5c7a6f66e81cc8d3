"""ROS 2 messages of the node suite as raw CDR and plain Python, without rclpy.

Clouds parsed into zero-copy numpy views and serialised with one copy; the estimate message
(docs/interface.md, "The estimate message"); the calibrator's QA statuses (docs/nodes.md).
"""

from __future__ import annotations

import math
import struct
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import yaml

from lidarcal_ros.core.adjustment.least_squares import ParameterState
from lidarcal_ros.core.georeferencing.heading import HeadingSource, describe_heading_use
from lidarcal_ros.core.georeferencing.rigorous import describe_models
from lidarcal_ros.core.params import (
    N_PARAMETERS,
    PARAMETER_NAMES,
    format_estimate,
    format_value,
)
from lidarcal_ros.core.units import format_cm, format_percent, status_value
from lidarcal_ros.errors import CloudFormatError, one_line
from lidarcal_ros.io.bag.format import POINTCLOUD2
from lidarcal_ros.io.cloud.pointcloud import array_to_cloud_parts, cloud_to_array

#: Diagnostic levels (diagnostic_msgs/DiagnosticStatus).
OK, WARN, ERROR, STALE = 0, 1, 2, 3
LEVEL_NAMES = {OK: "OK", WARN: "WARN", ERROR: "ERROR", STALE: "STALE"}

#: Rows of the estimate matrix.
ESTIMATE_ROWS = ("value", "sigma", *(f"covariance_{n}" for n in PARAMETER_NAMES))
ESTIMATE_ROW_LABEL = "value,sigma,covariance[" + ",".join(PARAMETER_NAMES) + "]"
_CONVERGED_TAG = ";converged="
ESTIMATE_COLUMN_LABEL = ",".join(PARAMETER_NAMES)

_NS = 1_000_000_000
_ENCAPSULATION_LE = b"\x00\x01\x00\x00"

_typestore: Any = None


def typestore() -> Any:
    """The rosbags typestore of the standard ROS 2 messages (created once)."""
    global _typestore
    if _typestore is None:
        from rosbags.typesys import Stores, get_typestore

        _typestore = get_typestore(getattr(Stores, "ROS2_JAZZY", Stores.ROS2_HUMBLE))
    return _typestore


def deserialize(raw: bytes | memoryview, msgtype: str) -> Any:
    """A rosbags message object from CDR bytes; arrays are views on ``raw``."""
    return typestore().deserialize_cdr(raw, msgtype)


def serialize(msg: Any, msgtype: str) -> bytes:
    """CDR bytes of a rosbags message object."""
    return bytes(typestore().serialize_cdr(msg, msgtype))


def stamp_ns(stamp: Any) -> int:
    """A builtin_interfaces/Time as integer nanoseconds."""
    return int(stamp.sec) * _NS + int(stamp.nanosec)


# ---------------------------------------------------------------------------- clouds
@dataclass
class CloudMessage:
    """A PointCloud2 read from CDR bytes.

    Attributes
    ----------
    stamp_ns : int
        ``header.stamp``, nanoseconds.
    frame_id : str
    points : numpy.ndarray
        Structured view of the points (no copy unless rows are padded).
    msg : object
        The rosbags message object (``data`` is a view on the CDR bytes).
    """

    stamp_ns: int
    frame_id: str
    points: np.ndarray
    msg: Any

    def __len__(self) -> int:
        return int(self.points.shape[0])


def parse_cloud(raw: bytes | memoryview, *, source: str = "cloud") -> CloudMessage:
    """Parse a serialised ``sensor_msgs/PointCloud2``.

    Raises
    ------
    CloudFormatError
        Undecodable bytes, or a field layout / data size that does not add up (one line
        naming ``source``).
    """
    try:
        # Through a memoryview: rosbags slices off the encapsulation header, which for bytes
        # would copy the whole message (10 MB for 200k points) while holding the GIL.
        msg = deserialize(memoryview(raw), POINTCLOUD2)
    except Exception as err:  # truncated or garbage bytes
        raise CloudFormatError(f"{source}: undecodable PointCloud2 ({one_line(err)})") from None
    points = cloud_to_array(msg, source=source)
    return CloudMessage(stamp_ns(msg.header.stamp), str(msg.header.frame_id), points, msg)


def _cdr_string(out: bytearray, text: str) -> None:
    data = text.encode("utf-8") + b"\x00"
    _align(out, 4)
    out += struct.pack("<I", len(data))
    out += data


def _align(out: bytearray, n: int) -> None:
    # Alignment is relative to the start of the payload (after the 4-byte encapsulation).
    pad = (-(len(out) - 4)) % n
    if pad:
        out += b"\x00" * pad


def cloud_header_cdr(
    stamp: int, frame_id: str, fields: Sequence[tuple[str, int, int, int]], point_step: int,
    n: int,
) -> bytes:
    """CDR bytes of a one-row PointCloud2 up to and including the length of ``data``."""
    out = bytearray(_ENCAPSULATION_LE)
    sec, nsec = divmod(int(stamp), _NS)
    out += struct.pack("<iI", sec, nsec)
    _cdr_string(out, frame_id)
    _align(out, 4)
    out += struct.pack("<III", 1, n, len(fields))
    for name, offset, datatype, count in fields:
        _cdr_string(out, name)
        _align(out, 4)
        out += struct.pack("<IB", offset, datatype)
        _align(out, 4)
        out += struct.pack("<I", count)
    out += b"\x00"  # is_bigendian
    _align(out, 4)
    out += struct.pack("<III", point_step, n * point_step, n * point_step)
    return bytes(out)


def warm_up_cloud_codec() -> None:
    """Write and parse one tiny PointCloud2 and take its time span, so that rosbags
    generates its (de)serialisers and the compiled loops of the codec load now: done by the
    first real cloud, that is some 70 ms in its path (a node calls this before it
    subscribes)."""
    from lidarcal_ros.io.cloud.columns import time_span
    from lidarcal_ros.io.cloud.pointcloud import make_point_dtype

    # Two points, not one: the field views of a one-point cloud are contiguous, a type the
    # compiled loops then load for nothing (every real cloud's fields are strided).
    cloud = parse_cloud(cloud_cdr(0, "warm-up", np.zeros(2, dtype=make_point_dtype())),
                        source="warm-up")
    time_span(cloud.points["t"])


def cloud_cdr(
    stamp: int, frame_id: str, points: np.ndarray, *, is_dense: bool | None = None
) -> bytes:
    """Serialise a structured point array as a one-row ``sensor_msgs/PointCloud2``.

    Parameters
    ----------
    stamp : int
        ``header.stamp``, nanoseconds.
    frame_id : str
    points : structured numpy array
        Fields of the eight PointField types (see
        :func:`~lidarcal_ros.io.cloud.pointcloud.array_to_cloud_parts`).
    is_dense : bool, optional
        Default: whether ``x, y, z`` (those present) are all finite.

    Returns
    -------
    bytes
        CDR (little-endian) bytes, identical to rosbags' and rclpy's serialisation; the point
        bytes are copied once, straight into the result.
    """
    return b"".join(cloud_cdr_parts(stamp, frame_id, points, is_dense=is_dense))


def cloud_cdr_parts(
    stamp: int, frame_id: str, points: np.ndarray, *, is_dense: bool | None = None
) -> tuple[bytes, memoryview, bytes]:
    """The CDR bytes of :func:`cloud_cdr` in three parts, the point bytes not copied: the
    header up to the length of ``data``, the point bytes, and ``is_dense``. Joined, they are
    the message; a caller can also copy them straight into a buffer of its own."""
    fields, point_step, data = array_to_cloud_parts(points)
    n = data.size // point_step if point_step else 0
    head = cloud_header_cdr(stamp, frame_id, fields, point_step, n)
    return head, data.data, is_dense_byte(points) if is_dense is None else bytes([is_dense])


def is_dense_byte(points: np.ndarray) -> bytes:
    r"""PointCloud2's ``is_dense`` as it is serialised: ``b"\x01"`` when every ``x, y, z``
    of ``points`` (those present) is finite, else ``b"\x00"``."""
    names = points.dtype.names or ()
    present = [points[c] for c in "xyz" if c in names]
    if len(present) == 3 and all(p.dtype.kind == "f" and p.dtype.isnative for p in present):
        # (Imported here: see io.cloud_columns.extract_xyz.)
        from lidarcal_ros.io.cloud.pointcloud_kernels import all_finite_xyz

        dense = all_finite_xyz(*present)  # one pass over the rows
    else:
        dense = all(bool(np.isfinite(p).all()) for p in present)
    return b"\x01" if dense else b"\x00"


# ---------------------------------------------------------------------------- estimate
def estimate_matrix(result: Any) -> np.ndarray:
    """The 10 x 8 estimate matrix of a CalibrationResult (docs/interface.md)."""
    sol = result.solution
    out = np.zeros((len(ESTIMATE_ROWS), N_PARAMETERS), dtype=np.float64)
    out[0] = np.asarray(sol.delta, dtype=np.float64)
    sigma = np.full(N_PARAMETERS, np.nan)
    index = [PARAMETER_NAMES.index(n) for n in sol.estimated]
    for k, i in enumerate(index):
        sigma[i] = float(sol.sigma[i])
        for kk, j in enumerate(index):
            out[2 + i, j] = float(sol.covariance[k, kk])
    out[1] = sigma
    return out


def estimate_row_label(converged: bool) -> str:
    """The label of the estimate's rows (``layout.dim[0]``), which also says whether the
    estimate is converged (the shape and the other fields stay as they are)."""
    return f"{ESTIMATE_ROW_LABEL}{_CONVERGED_TAG}{'true' if converged else 'false'}"


@dataclass
class Estimate:
    """The estimate message read back (SI units)."""

    values: dict[str, float]
    sigmas: dict[str, float | None]
    covariance: np.ndarray  # (8, 8), zero for parameters not estimated
    #: Whether the estimate is converged (the row label's flag); None where not said.
    converged: bool | None = None

    @property
    def delta(self) -> np.ndarray:
        """The values (8,) in ``PARAMETER_NAMES`` order, SI units."""
        return np.array([self.values[n] for n in PARAMETER_NAMES])

    @property
    def estimated(self) -> tuple[str, ...]:
        """The names of the parameters estimated (those with a sigma), in ``PARAMETER_NAMES``
        order."""
        return tuple(n for n in PARAMETER_NAMES if self.sigmas[n] is not None)


def parse_estimate(data: Sequence[float] | np.ndarray, labels: Sequence[str] = ()) -> Estimate:
    """Read the estimate matrix (``Float64MultiArray.data``, and optionally the dim labels,
    whose first says whether the estimate is converged).

    Raises
    ------
    ValueError
        Wrong size, or column labels that are not the eight parameters in order.
    """
    arr = np.asarray(data, dtype=np.float64)
    if arr.size != len(ESTIMATE_ROWS) * N_PARAMETERS:
        raise ValueError(f"estimate has {arr.size} values, expected "
                         f"{len(ESTIMATE_ROWS) * N_PARAMETERS} (10 x 8)")
    if len(labels) >= 2 and labels[1] != ESTIMATE_COLUMN_LABEL:
        raise ValueError(f"estimate columns are '{labels[1]}', expected "
                         f"'{ESTIMATE_COLUMN_LABEL}'")
    m = arr.reshape(len(ESTIMATE_ROWS), N_PARAMETERS)
    values = {n: float(m[0, i]) for i, n in enumerate(PARAMETER_NAMES)}
    sigmas = {n: (float(m[1, i]) if math.isfinite(m[1, i]) else None)
              for i, n in enumerate(PARAMETER_NAMES)}
    converged = None
    if labels:
        _, tagged, flag = labels[0].partition(_CONVERGED_TAG)
        converged = flag == "true" if tagged else None
    return Estimate(values, sigmas, m[2:].copy(), converged)


def calibration_yaml(result: Any, *, extrinsic: Any = None) -> str:
    """The calibration file of docs/interface.md as YAML text (with the ``extrinsic`` block
    of clouds in the sensor's frame where given)."""
    from lidarcal_ros.io.calibration_file import calibration_document

    return yaml.safe_dump(calibration_document(result, extrinsic=extrinsic), sort_keys=False,
                          width=120)


# ---------------------------------------------------------------------------- diagnostics
@dataclass
class StatusSpec:
    """Contents of one ``diagnostic_msgs/DiagnosticStatus``."""

    level: int
    name: str
    message: str
    values: dict[str, str] = field(default_factory=dict)


def estimate_status(solution: Any, heading_from: dict[int, HeadingSource] | None = None,
                    crab_deg: dict[int, float] | None = None,
                    models: dict[int, Any] | None = None) -> StatusSpec:
    """The biases as a crew reads them (``lidarcal: estimate``): the message lists the
    estimated ones with their standard deviations (``dphi -90.98 +- 0.04 arcsec``); the values
    give every parameter, fixed and not estimable ones with what was used or why, and (given
    ``heading_from``, strip id -> ``track`` or ``attitude``) under ``heading`` where the
    strips' headings came from, and (given ``models``, strip id ->
    :class:`~lidarcal_ros.core.georeferencing.rigorous.ModelChoice`) under ``model`` the
    point-positioning model of the strips and why."""
    values: dict[str, str] = {}
    estimated: list[str] = []
    for i, name in enumerate(PARAMETER_NAMES):
        status = solution.status[name]
        value = float(solution.delta[i])
        if status.state == ParameterState.ESTIMATED:
            text = format_estimate(name, value, float(solution.sigma[i]))
            estimated.append(f"{name} {text}")
        elif status.state == ParameterState.FIXED:
            text = f"fixed at {format_value(name, value)}"
        else:
            text = f"not estimable: {status.reason}"
        values[name] = text
    if heading_from is not None:
        values["heading"] = describe_heading_use(heading_from, crab_deg) or "from the track"
    if models:
        values["model"] = describe_models(models)
    return StatusSpec(OK, "lidarcal: estimate", ", ".join(estimated) or "nothing estimated",
                      values)


def geometry_status(models: dict[int, Any], laser_qa: dict[int, Any]) -> StatusSpec:
    """``lidarcal: geometry``: the point-positioning model of the strips and what their
    laser vectors say (:class:`~lidarcal_ros.core.georeferencing.rigorous.LaserVectorQA`): WARN with
    the first warning where one strip has one."""
    warnings = [f"strip {sid}: {w}" for sid, qa in sorted(laser_qa.items())
                for w in qa.warnings]
    values = {"model": describe_models(models)}
    for sid, qa in sorted(laser_qa.items()):
        values[f"strip {sid}"] = (
            f"along track {status_value(qa.along_median_m)} m "
            f"(+-{status_value(qa.along_spread_m)}), scan "
            f"{status_value(qa.scan_min_deg)}..{status_value(qa.scan_max_deg)} deg")
    message = warnings[0] if warnings else describe_models(models)
    if len(warnings) > 1:
        message += f" (and {len(warnings) - 1} more)"
    return StatusSpec(WARN if warnings else OK, "lidarcal: geometry", message, values)


def pair_level(rms_after: float, p95_after: float, *, warn_m: float, error_m: float) -> int:
    """QA level of a strip pair: ERROR when the RMS after calibration exceeds ``error_m`` (or
    is unknown), WARN when it exceeds ``warn_m`` or when the 95th percentile of the
    discrepancies exceeds ``error_m`` ("no difference beyond 16 cm"), else OK."""
    if not math.isfinite(rms_after) or rms_after > error_m:
        return ERROR
    if rms_after > warn_m or (math.isfinite(p95_after) and p95_after > error_m):
        return WARN
    return OK


def qa_statuses(
    result: Any, *, warn_m: float, error_m: float, solve_for: Iterable[str] = (),
) -> list[StatusSpec]:
    """The estimate, per-pair, convergence and observability statuses of a
    CalibrationResult."""
    out = [estimate_status(result.solution, result.heading_from, result.crab_deg,
                           result.models)]
    if result.laser_qa:
        out.append(geometry_status(result.models, result.laser_qa))
    for p in result.pairs:
        level = pair_level(p.rms_after, p.p95_after, warn_m=warn_m, error_m=error_m)
        out.append(StatusSpec(
            level, f"lidarcal: strips {p.strip_a}&{p.strip_b}",
            f"RMS {format_cm(p.rms_after, unit='cm')} "
            f"(before {format_cm(p.rms_before, unit='cm')}), coverage "
            f"{format_percent(p.coverage)}: {LEVEL_NAMES[level]}",
            {"coverage": status_value(float(p.coverage)),
             "rms_before": status_value(float(p.rms_before)),
             "rms_after": status_value(float(p.rms_after)),
             "p95_after": status_value(float(p.p95_after)),
             "correspondences": str(int(p.correspondences)),
             "rms_warn_threshold": status_value(float(warn_m)),
             "max_difference_threshold": status_value(float(error_m))}))
    sol = result.solution
    conv_level = OK if result.converged else WARN
    out.append(StatusSpec(
        conv_level, "lidarcal: convergence",
        (f"converged in {result.iterations} iterations" if result.converged else
         f"NOT converged after {result.iterations} iterations")
        + f", sigma0 {format_cm(float(sol.sigma0), unit='cm')}",
        {"iterations": str(int(result.iterations)), "converged": str(bool(result.converged)),
         "sigma0": status_value(float(sol.sigma0)), "redundancy": str(int(sol.redundancy)),
         "strip_pair_correspondences": str(int(result.n_pair_correspondences)),
         "control_correspondences": str(int(result.n_control_correspondences))}))
    wanted = set(solve_for) or set(PARAMETER_NAMES)
    missing = {n: st.reason for n, st in sol.status.items()
               if st.state == ParameterState.NOT_ESTIMABLE and n in wanted}
    values = {n: (str(st.state) if st.state != ParameterState.NOT_ESTIMABLE
                  else f"not estimable: {st.reason}")
              for n, st in sol.status.items()}
    for a, b, r in sol.correlated_pairs(0.9):
        values[f"correlation {a}/{b}"] = f"{r:+.3f}"
    if missing:
        text = "; ".join(f"{n} not estimable: {why}" for n, why in missing.items())
        out.append(StatusSpec(WARN, "lidarcal: observability", text, values))
    else:
        out.append(StatusSpec(OK, "lidarcal: observability",
                              f"all {len(sol.estimated)} parameters asked for are estimable",
                              values))
    return out


def qa_summary(statuses: Sequence[StatusSpec]) -> str:
    """One line for a log from :func:`qa_statuses`: the estimate and the worst strip pair,
    e.g. ``dphi -90.98 +- 0.04 arcsec, ...; strips 5&6: RMS 9.0 cm (before 26.4 cm),
    coverage 44%: WARN (worst of 15 pairs)``."""
    estimate = next((s.message for s in statuses if s.name == "lidarcal: estimate"), "")
    pairs = [s for s in statuses if s.name.startswith("lidarcal: strips ")]
    if not pairs:
        return estimate or "no estimate"

    def severity(s: StatusSpec) -> tuple[int, float]:
        rms = float(s.values.get("rms_after", "nan"))
        return s.level, rms if math.isfinite(rms) else math.inf

    worst = max(pairs, key=severity)
    where = worst.name.removeprefix("lidarcal: ")
    return f"{estimate}; {where}: {worst.message} (worst of {len(pairs)} pairs)"


def worst_level(statuses: Iterable[StatusSpec]) -> int:
    """The highest level among ``statuses`` (OK for none)."""
    return max((s.level for s in statuses if s.level != STALE), default=OK)


def flatten_values(values: Mapping[str, Any]) -> dict[str, str]:
    """Key-values as strings (numbers formatted compactly)."""
    return {str(k): status_value(v) for k, v in values.items()}


__all__ = [
    "ESTIMATE_COLUMN_LABEL",
    "ESTIMATE_ROWS",
    "ESTIMATE_ROW_LABEL",
    "LEVEL_NAMES",
    "CloudMessage",
    "Estimate",
    "StatusSpec",
    "calibration_yaml",
    "cloud_cdr",
    "cloud_cdr_parts",
    "cloud_header_cdr",
    "deserialize",
    "estimate_matrix",
    "estimate_row_label",
    "estimate_status",
    "flatten_values",
    "geometry_status",
    "is_dense_byte",
    "pair_level",
    "parse_cloud",
    "parse_estimate",
    "qa_statuses",
    "qa_summary",
    "serialize",
    "stamp_ns",
    "typestore",
    "warm_up_cloud_codec",
    "worst_level",
]
