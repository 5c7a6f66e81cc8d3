"""``sensor_msgs/PointCloud2`` bytes <-> numpy structured arrays, without ROS.

Works on any object with the attributes of a ``sensor_msgs/msg/PointCloud2`` (messages
deserialized by rosbags, rclpy or mcap-ros2, or a simple namespace) and on raw parts.
Points are in the cloud's ``header.frame_id`` (the map frame, metres); times are absolute
seconds on the trajectory's clock.
"""

from __future__ import annotations

import functools
import itertools
import logging
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace
from typing import Any, Literal

import numpy as np

from lidarcal_ros.errors import CloudFormatError

logger = logging.getLogger(__name__)

INT8 = 1
UINT8 = 2
INT16 = 3
UINT16 = 4
INT32 = 5
UINT32 = 6
FLOAT32 = 7
FLOAT64 = 8

#: PointField datatype code -> numpy scalar type (byte order chosen by the cloud).
DATATYPE_TO_NUMPY: dict[int, np.dtype[Any]] = {
    INT8: np.dtype(np.int8),
    UINT8: np.dtype(np.uint8),
    INT16: np.dtype(np.int16),
    UINT16: np.dtype(np.uint16),
    INT32: np.dtype(np.int32),
    UINT32: np.dtype(np.uint32),
    FLOAT32: np.dtype(np.float32),
    FLOAT64: np.dtype(np.float64),
}

#: numpy kind+size (e.g. ``'f8'``) -> PointField datatype code.
NUMPY_TO_DATATYPE: dict[str, int] = {
    f"{dt.kind}{dt.itemsize}": code for code, dt in DATATYPE_TO_NUMPY.items()
}

DATATYPE_NAMES: dict[int, str] = {
    INT8: "INT8",
    UINT8: "UINT8",
    INT16: "INT16",
    UINT16: "UINT16",
    INT32: "INT32",
    UINT32: "UINT32",
    FLOAT32: "FLOAT32",
    FLOAT64: "FLOAT64",
}

#: Names a driver may use for the firing-time field when ``t`` is absent.
TIME_ALIASES: tuple[str, ...] = ("time", "timestamp", "gps_time")

#: The coarsest rounding step of FLOAT32 ``x, y, z`` accepted when no tolerance is given (m):
#: the default range noise, ``sensor.range_noise_m``.
DEFAULT_COORDINATE_TOLERANCE_M = 0.03
#: FLOAT32 steps above this fraction of the tolerance are worth a warning (below: no effect
#: on any estimate worth a word).
COORDINATE_WARNING_FRACTION = 0.1

FieldTuple = tuple[str, int, int, int]


def _field_parts(field: Any) -> FieldTuple:
    """``(name, offset, datatype, count)`` of a PointField-like object or a tuple."""
    if isinstance(field, tuple):
        name, offset, datatype = field[0], field[1], field[2]
        count = field[3] if len(field) > 3 else 1
    else:
        name, offset, datatype = field.name, field.offset, field.datatype
        count = getattr(field, "count", 1)
    return str(name), int(offset), int(datatype), int(count)


def cloud_dtype(
    fields: Iterable[Any], point_step: int, *, is_bigendian: bool = False
) -> np.dtype[np.void]:
    """Structured dtype describing one point of a PointCloud2.

    Parameters
    ----------
    fields : iterable of PointField-like objects or ``(name, offset, datatype, count)`` tuples
        Field layout; order and padding are free. ``count > 1`` gives a subarray field.
    point_step : int
        Bytes per point; becomes the dtype's ``itemsize``.
    is_bigendian : bool, keyword-only
        Byte order of multi-byte fields.

    Returns
    -------
    numpy.dtype
        Structured dtype with explicit offsets and ``itemsize == point_step``.

    Raises
    ------
    CloudFormatError
        A field has an unknown datatype, reaches beyond ``point_step``, overlaps another
        field, or is named twice.
    """
    order: Literal[">", "<"] = ">" if is_bigendian else "<"
    names: list[str] = []
    formats: list[Any] = []
    offsets: list[int] = []
    spans: list[tuple[int, int, str]] = []
    if point_step <= 0:
        raise CloudFormatError(f"point_step must be positive, got {point_step}")
    for raw in fields:
        name, offset, datatype, count = _field_parts(raw)
        if not name:
            raise CloudFormatError(f"a PointField at offset {offset} has an empty name")
        if name in names:
            raise CloudFormatError(f"field '{name}' appears twice in the cloud")
        if datatype not in DATATYPE_TO_NUMPY:
            raise CloudFormatError(f"field '{name}' has unknown PointField datatype {datatype}")
        if count == 0:
            # Some drivers write count=0 for scalar fields; treat it as 1 as PCL does.
            count = 1
        if count < 0 or offset < 0:
            raise CloudFormatError(f"field '{name}' has offset {offset} and count {count}")
        base = DATATYPE_TO_NUMPY[datatype].newbyteorder(order)
        size = base.itemsize * count
        if offset + size > point_step:
            raise CloudFormatError(
                f"field '{name}' (offset {offset}, {size} bytes) reaches beyond "
                f"point_step {point_step}"
            )
        names.append(name)
        formats.append(base if count == 1 else (base, (count,)))
        offsets.append(offset)
        spans.append((offset, offset + size, name))
    spans.sort()
    for (_, end_a, name_a), (start_b, _, name_b) in itertools.pairwise(spans):
        if start_b < end_a:
            raise CloudFormatError(f"fields '{name_a}' and '{name_b}' overlap")
    return np.dtype(
        {"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step}
    )


@functools.lru_cache(maxsize=64)
def _cached_dtype(
    layout: tuple[FieldTuple, ...], point_step: int, is_bigendian: bool
) -> np.dtype[np.void]:
    """:func:`cloud_dtype` memoised on the layout (a bag repeats one layout per topic)."""
    return cloud_dtype(layout, point_step, is_bigendian=is_bigendian)


def _as_uint8(data: Any) -> np.ndarray:
    """Zero-copy uint8 view of a bytes-like buffer (copies only for plain sequences)."""
    if isinstance(data, np.ndarray):
        if data.dtype == np.uint8 and data.ndim == 1:
            return data
        return np.ascontiguousarray(data).reshape(-1).view(np.uint8)
    try:
        return np.frombuffer(data, dtype=np.uint8)
    except TypeError:
        return np.asarray(data, dtype=np.uint8)


def cloud_to_array(msg: Any, *, source: str = "cloud") -> np.ndarray:
    """Structured view of a PointCloud2's points.

    Parameters
    ----------
    msg : PointCloud2-like
        Needs ``fields``, ``point_step``, ``row_step``, ``width``, ``height``,
        ``is_bigendian`` and ``data``.
    source : str, keyword-only
        Topic or file named in error messages.

    Returns
    -------
    numpy.ndarray
        1-D structured array of ``width * height`` points (row-major). A view on
        ``msg.data`` (no copy) unless rows are padded (``row_step > width * point_step``),
        in which case the points are gathered into a new array.

    Raises
    ------
    CloudFormatError
        Bad field layout, or ``data`` length inconsistent with ``width``, ``height`` and
        ``row_step``.
    """
    point_step = int(msg.point_step)
    width, height, row_step = int(msg.width), int(msg.height), int(msg.row_step)
    try:
        layout = tuple(_field_parts(f) for f in msg.fields)
        dtype = _cached_dtype(layout, point_step, bool(msg.is_bigendian))
    except CloudFormatError as err:
        raise CloudFormatError(f"{source}: {err}") from None
    buf = _as_uint8(msg.data)
    n = width * height
    if n == 0:
        return np.empty(0, dtype=dtype)
    row_bytes = width * point_step
    if row_step < row_bytes:
        raise CloudFormatError(
            f"{source}: row_step {row_step} < width {width} * point_step {point_step}"
        )
    need = (height - 1) * row_step + row_bytes
    if not need <= buf.size <= height * row_step:
        raise CloudFormatError(
            f"{source}: data has {buf.size} bytes but width {width}, height {height}, "
            f"row_step {row_step} and point_step {point_step} need {height * row_step}"
        )
    if row_step == row_bytes or height == 1:
        return np.frombuffer(buf, dtype=dtype, count=n)
    rows = np.ndarray(
        shape=(height, width), dtype=dtype, buffer=buf, strides=(row_step, point_step)
    )
    return rows.reshape(n)


def point_fields(dtype: np.dtype[Any]) -> list[FieldTuple]:
    """The PointFields ``(name, offset, datatype, count)`` of a structured point dtype.

    Raises
    ------
    CloudFormatError
        ``dtype`` is not structured or a field has no PointField type.
    """
    if dtype.fields is None:
        raise CloudFormatError(f"array of dtype {dtype} is not a structured point array")
    fields: list[FieldTuple] = []
    for name, (fdt, offset, *_rest) in dtype.fields.items():
        base, shape = fdt.base, fdt.shape
        if len(shape) > 1 or base.fields is not None:
            raise CloudFormatError(f"field '{name}' has unsupported nested type {fdt}")
        code = NUMPY_TO_DATATYPE.get(f"{base.kind}{base.itemsize}")
        if code is None:
            raise CloudFormatError(f"field '{name}' has dtype {base}; no PointField type")
        fields.append((str(name), int(offset), code, int(shape[0]) if shape else 1))
    return fields


def array_to_cloud_parts(arr: np.ndarray) -> tuple[list[FieldTuple], int, np.ndarray]:
    """PointCloud2 parts for a structured array.

    Parameters
    ----------
    arr : numpy.ndarray
        Structured array of points (any shape; flattened). Fields must be scalar or 1-D
        subarrays of the eight PointField types. Big-endian fields are converted.

    Returns
    -------
    fields : list of ``(name, offset, datatype, count)``
    point_step : int
        ``arr.dtype.itemsize``.
    data : (n * point_step,) uint8 numpy.ndarray
        Little-endian point bytes; a view on ``arr`` when it is already C-contiguous and
        little-endian.

    Raises
    ------
    CloudFormatError
        ``arr`` is not structured or a field has an unsupported type.
    """
    dtype = arr.dtype
    fields = point_fields(dtype)
    swap = any(base.byteorder == ">" or (base.byteorder == "=" and not np.little_endian)
               for base in (fdt.base for fdt, *_rest in (dtype.fields or {}).values()))
    flat = np.ascontiguousarray(arr).reshape(-1)
    if swap:
        logger.debug("converting big-endian point array to little-endian")
        flat = flat.astype(dtype.newbyteorder("<"))
    return fields, int(dtype.itemsize), flat.view(np.uint8).reshape(-1)


@dataclass
class CloudColumns:
    """Per-point columns of one cloud, in native byte order.

    Attributes
    ----------
    xyz : (n, 3) float64
        Coordinates in the cloud's frame, metres.
    t : (n,) float64
        Firing times, absolute seconds.
    intensity : (n,) float32 or None
    strip_id : (n,) uint32 or None
        From ``strip_id`` or ``point_source_id``.
    return_number, number_of_returns : (n,) uint8 or None
    time_field : str
        Name of the field ``t`` came from.
    t_span : (float, float) or None
        :func:`time_span` of ``t`` when known (found while the columns were extracted).
    all_finite : bool or None
        Every ``x, y, z, t`` finite, when known.
    coordinate_step_m : float
        The rounding step of FLOAT32 ``x, y, z`` at the cloud's largest coordinate (m; 0 for
        FLOAT64): :func:`float32_step`.
    """

    xyz: np.ndarray
    t: np.ndarray
    intensity: np.ndarray | None = None
    strip_id: np.ndarray | None = None
    return_number: np.ndarray | None = None
    number_of_returns: np.ndarray | None = None
    time_field: str = "t"
    t_span: tuple[float, float] | None = None
    all_finite: bool | None = None
    coordinate_step_m: float = 0.0

    def __len__(self) -> int:
        return int(self.t.shape[0])

    def finite(self) -> np.ndarray:
        """(n,) bool: the points whose ``x, y, z`` and ``t`` are all finite (without a pass
        over them when the extraction found every one so)."""
        if self.all_finite:
            return np.ones(len(self), dtype=bool)
        return np.isfinite(self.xyz).all(axis=1) & np.isfinite(self.t)

    def take(self, keep: np.ndarray) -> CloudColumns:
        """The columns of the points ``keep`` (a mask or indices), each per-point column
        taken alike."""
        def part(column: np.ndarray | None) -> np.ndarray | None:
            return None if column is None else column[keep]

        return replace(self, xyz=self.xyz[keep], t=self.t[keep], intensity=part(self.intensity),
                       strip_id=part(self.strip_id), return_number=part(self.return_number),
                       number_of_returns=part(self.number_of_returns), t_span=None,
                       all_finite=True if self.all_finite else None)


def _code_of(arr: np.ndarray, name: str) -> int:
    sub = arr.dtype.fields[name][0] if arr.dtype.fields else arr.dtype
    if sub.shape:
        return -1
    return NUMPY_TO_DATATYPE.get(f"{sub.kind}{sub.itemsize}", -1)


def _type_name(arr: np.ndarray, name: str) -> str:
    code = _code_of(arr, name)
    return DATATYPE_NAMES.get(code, str(arr.dtype.fields[name][0]))  # type: ignore[index]


def _present(arr: np.ndarray) -> str:
    return ", ".join(arr.dtype.names or ()) or "none"


def _field(arr: np.ndarray, name: str, accepted: Sequence[int], source: str) -> np.ndarray:
    """The view of field ``name``, whose type must be one of ``accepted``."""
    if _code_of(arr, name) not in accepted:
        want = "/".join(DATATYPE_NAMES[c] for c in accepted)
        raise CloudFormatError(
            f"{source}: field '{name}' is {_type_name(arr, name)}; expected {want}"
        )
    return arr[name]


def _column(
    arr: np.ndarray, name: str, accepted: Sequence[int], out: type[np.generic], source: str
) -> np.ndarray:
    return _field(arr, name, accepted, source).astype(out)


def _xyz_fields(arr: np.ndarray, source: str) -> list[np.ndarray]:
    """The views of ``x, y, z``, which must be present and FLOAT64 or FLOAT32."""
    names = arr.dtype.names or ()
    missing = [c for c in ("x", "y", "z") if c not in names]
    if missing:
        raise CloudFormatError(
            f"{source}: cloud lacks field(s) {', '.join(missing)}; fields present: "
            f"{_present(arr)}"
        )
    return [_field(arr, c, (FLOAT64, FLOAT32), source) for c in ("x", "y", "z")]


def extract_xyz(arr: np.ndarray, *, source: str = "cloud",
                coordinate_tolerance_m: float = DEFAULT_COORDINATE_TOLERANCE_M) -> np.ndarray:
    """``(n, 3)`` float64 coordinates from fields ``x, y, z`` (FLOAT64 or FLOAT32).

    Raises
    ------
    CloudFormatError
        A coordinate field is missing or not floating point, or FLOAT32 coordinates are too
        large for it (:func:`float32_step`).
    """
    fields = _xyz_fields(arr, source)
    xyz = _stacked_xyz(fields)
    _checked_float32_step(fields, xyz, source, coordinate_tolerance_m)
    return xyz


def float32_step(xyz: np.ndarray) -> tuple[float, int, float]:
    """The rounding step of FLOAT32 at the largest finite coordinate of each column.

    Parameters
    ----------
    xyz : (n, 3) float64
        Coordinates that were FLOAT32 (metres).

    Returns
    -------
    step : float
        The spacing of FLOAT32 numbers (its unit in the last place) at the largest magnitude
        of the worst column, metres: a FLOAT32 coordinate is off by up to half of it. 0 for
        no finite coordinate.
    column : int
        The column (0: x, 1: y, 2: z) of that magnitude.
    magnitude : float
        That magnitude, metres.
    """
    worst = (0.0, 0, 0.0)
    for column in range(xyz.shape[1] if xyz.ndim == 2 else 0):
        values = np.abs(xyz[:, column])
        values = values[np.isfinite(values)]
        if values.size:
            magnitude = float(values.max())
            step = float(np.spacing(np.float32(magnitude)))
            if step > worst[0]:
                worst = (step, column, magnitude)
    return worst


def _checked_float32_step(fields: list[np.ndarray], xyz: np.ndarray, source: str,
                          tolerance_m: float) -> float:
    """:func:`float32_step` of the FLOAT32 coordinate fields among ``fields`` (0 if none);
    a step coarser than ``tolerance_m`` is refused."""
    is32 = [f.dtype.itemsize == 4 for f in fields]
    if not any(is32) or not xyz.shape[0]:
        return 0.0
    step, column, magnitude = float32_step(xyz[:, np.flatnonzero(is32)])
    name = "xyz"[np.flatnonzero(is32)[column]]
    if step > tolerance_m:
        raise CloudFormatError(
            f"{source}: FLOAT32 field '{name}' holds coordinates up to {magnitude:.0f} m, where "
            f"FLOAT32 has {step:.3g} m steps, coarser than the {tolerance_m:g} m range noise "
            f"(sensor.range_noise_m): points would be off by up to {step / 2:.3g} m; projected "
            "coordinates need FLOAT64"
        )
    return step


def float32_warning(step_m: float, tolerance_m: float) -> str | None:
    """A warning for FLOAT32 coordinates rounded to ``step_m`` (m) below the refusal
    ``tolerance_m`` but not negligibly (:data:`COORDINATE_WARNING_FRACTION`); None else."""
    if step_m <= COORDINATE_WARNING_FRACTION * tolerance_m:
        return None
    return (f"FLOAT32 x, y, z are rounded to steps of up to {step_m:.3g} m at these coordinates "
            f"(range noise {tolerance_m:g} m, sensor.range_noise_m); FLOAT64 keeps them exact")


def _stacked_xyz(fields: list[np.ndarray]) -> np.ndarray:
    """``(n, 3)`` float64 from the views of ``x, y, z``."""
    xyz = np.empty((fields[0].shape[0], 3), dtype=np.float64)
    if all(f.dtype.isnative for f in fields):
        # Imported here: the processes that only pass clouds on (the nodes' ROS side, a
        # replay) need not load numba.
        from lidarcal_ros.io.pointcloud_kernels import gather_xyz

        gather_xyz(fields[0], fields[1], fields[2], xyz)  # one pass over the rows
    else:  # a big-endian cloud (the compiled loop takes native byte order only)
        for i, f in enumerate(fields):
            xyz[:, i] = f
    return xyz


def resolve_time_field(arr: np.ndarray, time_field: str = "t", *, source: str = "cloud") -> str:
    """Name of the firing-time field of ``arr``.

    ``time_field`` is used as given, except that for the default ``'t'`` a cloud without
    ``t`` but with exactly one of ``time``, ``timestamp``, ``gps_time`` uses that one.

    Raises
    ------
    CloudFormatError
        No usable time field.
    """
    names = arr.dtype.names or ()
    if time_field in names:
        return time_field
    if time_field == "t":
        found = [a for a in TIME_ALIASES if a in names]
        if len(found) == 1:
            logger.debug("%s: using field '%s' as the time field", source, found[0])
            return found[0]
        if len(found) > 1:
            raise CloudFormatError(
                f"{source}: no field 't' and several time aliases ({', '.join(found)}); "
                "choose one with the time_field parameter"
            )
    raise CloudFormatError(
        f"{source}: cloud lacks time field '{time_field}'; fields present: {_present(arr)}"
    )


def time_span(t: np.ndarray) -> tuple[float, float]:
    """Earliest and latest time among ``t`` ignoring NaN (s); ``(nan, nan)`` when there is
    none (an empty cloud, or times all NaN)."""
    if t.size == 0:
        return float("nan"), float("nan")
    if t.ndim == 1 and t.dtype.kind == "f" and t.dtype.isnative:
        from lidarcal_ros.io.pointcloud_kernels import finite_range  # (here: see extract_xyz)

        return finite_range(t)  # one pass (the field is strided in the cloud's rows)
    # fmin/fmax skip NaN, and give NaN (without a warning) only when all are.
    return float(np.fmin.reduce(t)), float(np.fmax.reduce(t))


def extract_columns(
    arr: np.ndarray, *, time_field: str = "t", source: str = "cloud",
    coordinate_tolerance_m: float = DEFAULT_COORDINATE_TOLERANCE_M,
) -> CloudColumns:
    """Interpret a structured point array as lidarcal columns.

    Parameters
    ----------
    arr : numpy.ndarray
        Structured array, e.g. from :func:`cloud_to_array`.
    time_field : str, keyword-only
        Name of the FLOAT64 firing-time field (absolute seconds). With the default ``'t'``,
        a cloud without ``t`` but with exactly one of ``time``, ``timestamp``, ``gps_time``
        uses that field.
    source : str, keyword-only
        Topic or file named in error messages.
    coordinate_tolerance_m : float, keyword-only
        The coarsest rounding step of FLOAT32 ``x, y, z`` accepted (m; the range noise,
        ``sensor.range_noise_m``). FLOAT32 has a step of 0.5 m at a UTM northing of 5000 km:
        such coordinates are refused, not rounded silently (:func:`float32_step`).

    Returns
    -------
    CloudColumns
        New arrays (copies) in native byte order.

    Raises
    ------
    CloudFormatError
        Missing ``x``, ``y``, ``z`` or time field, a field of an unsupported type, or FLOAT32
        coordinates whose step exceeds ``coordinate_tolerance_m``: one line naming the field,
        the magnitude and the step.
    """
    names = arr.dtype.names or ()
    fields = _xyz_fields(arr, source)
    tname = resolve_time_field(arr, time_field, source=source)
    t_field = _field(arr, tname, (FLOAT64,), source)
    intensity_field = (_field(arr, "intensity", (FLOAT32, UINT16, UINT8), source)
                       if "intensity" in names else None)
    sid_name = "strip_id" if "strip_id" in names else (
        "point_source_id" if "point_source_id" in names else None
    )
    sid_field = (_field(arr, sid_name, (UINT16, UINT32, UINT8), source)
                 if sid_name is not None else None)
    wanted = [*fields, t_field, intensity_field, sid_field]
    n = arr.shape[0]
    t_span: tuple[float, float] | None = None
    all_finite: bool | None = None
    if all(f is None or f.dtype.isnative for f in wanted):
        from lidarcal_ros.io.pointcloud_kernels import gather_columns  # (here: see extract_xyz)

        xyz, t = np.empty((n, 3)), np.empty(n)
        intensity = np.empty(n if intensity_field is not None else 0, dtype=np.float32)
        strip_id = np.empty(n if sid_field is not None else 0, dtype=np.uint32)
        t_lo, t_hi, non_finite = gather_columns(  # one pass over the rows
            fields[0], fields[1], fields[2], t_field,
            intensity_field if intensity_field is not None else intensity,
            sid_field if sid_field is not None else strip_id, xyz, t, intensity, strip_id)
        t_span, all_finite = (t_lo, t_hi), non_finite == 0
    else:  # a big-endian cloud (the compiled loop takes native byte order only)
        xyz = _stacked_xyz(fields)
        t = t_field.astype(np.float64)
        intensity = (intensity_field.astype(np.float32) if intensity_field is not None
                     else np.empty(0, dtype=np.float32))
        strip_id = (sid_field.astype(np.uint32) if sid_field is not None
                    else np.empty(0, dtype=np.uint32))
    step = _checked_float32_step(fields, xyz, source, coordinate_tolerance_m)
    rn = nr = None
    if "return_number" in names:
        rn = _column(arr, "return_number", (UINT8, UINT16), np.uint8, source)
    if "number_of_returns" in names:
        nr = _column(arr, "number_of_returns", (UINT8, UINT16), np.uint8, source)
    return CloudColumns(xyz, t, intensity if intensity_field is not None else None,
                        strip_id if sid_field is not None else None, rn, nr, tname,
                        t_span=t_span, all_finite=all_finite, coordinate_step_m=step)


def make_point_dtype(
    extra_float32_fields: Sequence[str] = (), *, intensity: bool = True
) -> np.dtype[np.void]:
    """The point layout lidarcal writes.

    Parameters
    ----------
    extra_float32_fields : sequence of str
        Further FLOAT32 fields appended after the core ones, e.g. ``reflectance``,
        ``range`` (m), ``incidence`` (rad), ``scan_angle`` (rad).
    intensity : bool, keyword-only
        Include the FLOAT32 ``intensity`` field.

    Returns
    -------
    numpy.dtype
        Aligned little-endian structured dtype: ``x, y, z, t`` float64 (metres, seconds),
        ``intensity`` float32, ``strip_id`` uint16, extras float32.
    """
    spec: list[tuple[str, str]] = [("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("t", "<f8")]
    if intensity:
        spec.append(("intensity", "<f4"))
    spec.append(("strip_id", "<u2"))
    for name in extra_float32_fields:
        if name in {n for n, _ in spec}:
            raise CloudFormatError(f"extra field '{name}' clashes with a core field")
        spec.append((name, "<f4"))
    return np.dtype(spec, align=True)
