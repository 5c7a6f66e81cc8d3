"""``sensor_msgs/PointCloud2`` bytes <-> numpy structured arrays, without ROS.

Any object with a PointCloud2's attributes; layouts checked; zero-copy views. Points in the
cloud's ``header.frame_id`` (map frame, metres).
"""

from __future__ import annotations

import functools
import itertools
import logging
from collections.abc import Iterable, Sequence
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

FieldTuple = tuple[str, int, int, int]

#: Largest point_step taken, bytes: a driver's point is some 16-100 bytes, and numpy's dtypes
#: stop at 2**31 (a point_step of 2**32 - 1 was an internal error, found by the fuzzer).
MAX_POINT_STEP = 1 << 20


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
    if not 0 < point_step <= MAX_POINT_STEP:
        raise CloudFormatError(f"point_step must be 1 to {MAX_POINT_STEP} bytes, got "
                               f"{point_step}")
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


def without_padding_garbage(arr: np.ndarray) -> np.ndarray:
    """``arr`` itself where its structured layout has no padding; else a copy with the
    padding zero. numpy's copies of an aligned layout (concatenate, take, copy) move field by
    field and leave the padding with whatever memory was there: a file written from it would
    differ from run to run and carry the process's memory."""
    dtype = arr.dtype
    if sum(f[0].itemsize for f in (dtype.fields or {}).values()) >= dtype.itemsize:
        return arr
    clean = np.zeros(arr.shape, dtype=dtype)
    clean[...] = arr
    return clean


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


__all__ = ["DATATYPE_NAMES", "DATATYPE_TO_NUMPY", "FLOAT32", "FLOAT64", "INT8", "INT16", "INT32",
           "NUMPY_TO_DATATYPE", "UINT8", "UINT16", "UINT32", "FieldTuple", "array_to_cloud_parts",
           "cloud_dtype", "cloud_to_array", "make_point_dtype", "point_fields",
           "without_padding_garbage"]
