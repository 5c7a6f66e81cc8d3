"""The columns lidarcal works on, read from the fields of a cloud's structured points.

Each field of an accepted type or refused in one line naming it. Metres in the cloud's
``header.frame_id``; times absolute seconds on the trajectory's clock.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from lidarcal_ros.core.mission import beyond_map
from lidarcal_ros.errors import CloudFormatError
from lidarcal_ros.io.cloud.pointcloud import (
    DATATYPE_NAMES,
    FLOAT32,
    FLOAT64,
    NUMPY_TO_DATATYPE,
    UINT8,
    UINT16,
    UINT32,
)

logger = logging.getLogger(__name__)

#: Names a driver may use for the firing-time field when ``t`` is absent.
TIME_ALIASES: tuple[str, ...] = ("time", "timestamp", "gps_time")

#: The coarsest rounding step of FLOAT32 ``x, y, z`` accepted when no tolerance is given (m):
#: the default range noise, ``sensor.range_noise_m``.
DEFAULT_COORDINATE_TOLERANCE_M = 0.03
#: FLOAT32 steps above this fraction of the tolerance are worth a warning (below: no effect
#: on any estimate worth a word).
COORDINATE_WARNING_FRACTION = 0.1


def float32_warning(step_m: float, tolerance_m: float) -> str | None:
    """A warning for FLOAT32 coordinates rounded to ``step_m`` (m) below the refusal
    ``tolerance_m`` but not negligibly (:data:`COORDINATE_WARNING_FRACTION`); None else."""
    if step_m <= COORDINATE_WARNING_FRACTION * tolerance_m:
        return None
    return (f"FLOAT32 x, y, z are rounded to steps of up to {step_m:.3g} m at these coordinates "
            f"(range noise {tolerance_m:g} m, sensor.range_noise_m); FLOAT64 keeps them exact")


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
    _without_beyond_map(xyz)
    _checked_float32_step(fields, xyz, source, coordinate_tolerance_m)
    return xyz


def _without_beyond_map(xyz: np.ndarray) -> bool:
    """Set to NaN, in place, the points of ``xyz`` (n, 3) with a coordinate beyond
    :data:`~lidarcal_ros.core.mission.MAX_COORDINATE_M` (a corrupt value, whose square
    would overflow): they are dropped and counted with the non-finite. Whether there were
    any."""
    beyond = beyond_map(xyz)
    if not beyond.any():
        return False
    xyz[beyond] = np.nan
    return True


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


def _stacked_xyz(fields: list[np.ndarray]) -> np.ndarray:
    """``(n, 3)`` float64 from the views of ``x, y, z``."""
    xyz = np.empty((fields[0].shape[0], 3), dtype=np.float64)
    if all(f.dtype.isnative for f in fields):
        # Imported here: the processes that only pass clouds on (the nodes' ROS side, a
        # replay) need not load numba.
        from lidarcal_ros.io.cloud.pointcloud_kernels import gather_xyz

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
        from lidarcal_ros.io.cloud.pointcloud_kernels import finite_range  # (here: see extract_xyz)

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
        from lidarcal_ros.io.cloud.pointcloud_kernels import (
            gather_columns,  # (here: see extract_xyz)
        )

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
    if _without_beyond_map(xyz):
        all_finite = False
    step = _checked_float32_step(fields, xyz, source, coordinate_tolerance_m)
    rn = nr = None
    if "return_number" in names:
        rn = _column(arr, "return_number", (UINT8, UINT16), np.uint8, source)
    if "number_of_returns" in names:
        nr = _column(arr, "number_of_returns", (UINT8, UINT16), np.uint8, source)
    return CloudColumns(xyz, t, intensity if intensity_field is not None else None,
                        strip_id if sid_field is not None else None, rn, nr, tname,
                        t_span=t_span, all_finite=all_finite, coordinate_step_m=step)


__all__ = ["COORDINATE_WARNING_FRACTION", "DEFAULT_COORDINATE_TOLERANCE_M", "TIME_ALIASES",
           "CloudColumns", "extract_columns", "extract_xyz", "float32_step", "float32_warning",
           "resolve_time_field", "time_span"]
