"""Per-point times of a lidar driver's cloud: its time field, units and reference, as seconds.

Velodyne ``time`` FLOAT32 s and Ouster ``t`` UINT32 ns after ``header.stamp``; Hesai and Livox
``timestamp`` FLOAT64, absolute or relative, s or ns (docs/interface.md). Times out are absolute
float64 seconds on the header stamps' clock.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lidarcal_ros.core.georeferencing.sensor_frame import TimeConvention
from lidarcal_ros.errors import CloudFormatError, ConfigError, InputError
from lidarcal_ros.io.cloud.columns import extract_xyz
from lidarcal_ros.io.cloud.pointcloud import (
    DATATYPE_NAMES,
    FLOAT32,
    FLOAT64,
    NUMPY_TO_DATATYPE,
    UINT32,
)

#: The drivers' time fields, looked for in this order where none is named.
SENSOR_TIME_FIELDS: tuple[str, ...] = ("time", "t", "timestamp", "offset_time")

#: A float time above this is nanoseconds (1e12 s are 31 700 years).
_NANOSECONDS_ABOVE = 1e12


@dataclass(frozen=True)
class TimeReading:
    """How a cloud's time field is read (:func:`time_reading`).

    Attributes
    ----------
    field : str
    datatype : int
        The field's PointField datatype.
    scale : float
        Seconds per unit of the field (1 or 1e-9).
    relative : bool
        The field is an offset from ``header.stamp``.
    assumed : bool
        Units and reference were detected (``auto``), not given.
    """

    field: str
    datatype: int
    scale: float
    relative: bool
    assumed: bool = False

    def describe(self) -> str:
        """One line of what the field is taken to be."""
        unit = "ns" if self.scale != 1.0 else "s"
        ref = "after header.stamp" if self.relative else "absolute"
        how = "assumed" if self.assumed else "as configured"
        return (f"per-point time from field '{self.field}' ({DATATYPE_NAMES[self.datatype]}): "
                f"{unit} {ref} ({how}; override with sensor_frame.time_convention)")

    def absolute(self, values: np.ndarray, stamp_s: float) -> np.ndarray:
        """Absolute seconds (float64) of the field's ``values`` in a cloud stamped
        ``stamp_s``."""
        t = values.astype(np.float64)
        if self.scale != 1.0:
            t *= self.scale
        if self.relative:
            t += stamp_s
        return t


def _datatype(points: np.ndarray, name: str) -> int:
    sub = points.dtype.fields[name][0]  # type: ignore[index]
    return -1 if sub.shape else NUMPY_TO_DATATYPE.get(f"{sub.kind}{sub.itemsize}", -1)


def time_reading(points: np.ndarray, stamp_s: float, *, field: str | None = None,
                 convention: TimeConvention | str = TimeConvention.AUTO,
                 source: str = "cloud") -> TimeReading:
    """How to read the per-point time of a driver's cloud (structured ``points``, stamped
    ``stamp_s`` s): the field (``field``, else the first of :data:`SENSOR_TIME_FIELDS`
    present), its units (UINT32: ns; FLOAT32: s; FLOAT64: s, or ns where its values exceed
    1e12) and reference (``convention``; ``auto``: absolute where the median value is nearer
    the stamp than zero, else relative).

    Raises
    ------
    CloudFormatError
        No time field, or one of a type no driver uses, or UINT32 taken as absolute (one
        line naming ``source`` and the fields present).
    """
    try:
        convention = TimeConvention(convention)
    except ValueError:
        raise ConfigError(f"sensor_frame.time_convention: '{convention}' is not one of "
                          f"{', '.join(c.value for c in TimeConvention)}") from None
    names = points.dtype.names or ()
    wanted = (field,) if field else SENSOR_TIME_FIELDS
    found = next((n for n in wanted if n in names), None)
    if found is None:
        raise CloudFormatError(
            f"{source}: no per-point time field ({', '.join(wanted)}); fields present: "
            f"{', '.join(names) or 'none'} (name it with --time-field)")
    code = _datatype(points, found)
    if code not in (FLOAT32, FLOAT64, UINT32):
        kind = DATATYPE_NAMES.get(code, str(points.dtype.fields[found][0]))  # type: ignore[index]
        raise CloudFormatError(f"{source}: time field '{found}' is {kind}; expected FLOAT32 "
                               "or FLOAT64 seconds or UINT32 nanoseconds")
    values = points[found]
    finite = values[np.isfinite(values)] if code != UINT32 else values
    median = float(np.median(finite)) if finite.size else 0.0
    scale = 1e-9 if code == UINT32 or (code == FLOAT64 and median > _NANOSECONDS_ABOVE) else 1.0
    if convention == TimeConvention.AUTO:
        relative = code == UINT32 or not median * scale > 0.5 * stamp_s
    else:
        relative = convention == TimeConvention.RELATIVE
    if code == UINT32 and not relative:
        raise CloudFormatError(f"{source}: time field '{found}' is UINT32 nanoseconds, which "
                               "cannot be absolute; set sensor_frame.time_convention to "
                               "relative or auto")
    return TimeReading(found, code, scale, relative, convention == TimeConvention.AUTO)


#: FLOAT32 ``x, y, z`` in the sensor's frame are rounded to well under a millimetre within
#: a driver's range; this tolerance only refuses map coordinates mistaken for them.
SENSOR_COORDINATE_TOLERANCE_M = 0.01


class SensorCloudDecoder:
    """A driver's clouds, one after the other, as points in the sensor's frame with absolute
    times: the time field read as the first non-empty cloud says (:func:`time_reading`). A
    bag's reader and the live calibrator decode with it alike.

    Parameters
    ----------
    field : str or None, keyword-only
        The per-point time field (None: found by name).
    convention : TimeConvention or str, keyword-only
    """

    def __init__(self, *, field: str | None = None,
                 convention: TimeConvention | str = TimeConvention.AUTO) -> None:
        self.field = field
        self.convention = convention
        #: How the time field is read (None until the first non-empty cloud).
        self.reading: TimeReading | None = None

    def decode(self, points: np.ndarray, stamp_s: float, *, source: str = "cloud"
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """One cloud (structured ``points`` stamped ``stamp_s`` s) as ``(xyz, t,
        intensity)``: (n, 3) float64 m in the sensor's frame, (n,) float64 absolute s,
        (n,) float32 or None.

        Raises
        ------
        CloudFormatError
            No usable time field or coordinates.
        InputError
            A cloud without the time field of the first.
        """
        names = points.dtype.names or ()
        if not len(points):
            return np.empty((0, 3)), np.empty(0), (np.empty(0, dtype=np.float32)
                                                   if "intensity" in names else None)
        if self.reading is None:
            self.reading = time_reading(points, stamp_s, field=self.field,
                                        convention=self.convention, source=source)
        elif self.reading.field not in names:
            raise InputError(f"{source}: a cloud at {stamp_s:.3f} s lacks the time field "
                             f"'{self.reading.field}' of the first")
        xyz = extract_xyz(points, source=source,
                          coordinate_tolerance_m=SENSOR_COORDINATE_TOLERANCE_M)
        t = self.reading.absolute(points[self.reading.field], stamp_s)
        intensity = points["intensity"].astype(np.float32) if "intensity" in names else None
        return xyz, t, intensity


__all__ = ["SENSOR_COORDINATE_TOLERANCE_M", "SENSOR_TIME_FIELDS", "SensorCloudDecoder",
           "TimeReading", "time_reading"]
