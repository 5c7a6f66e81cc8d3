"""Trajectory files as delivered after a flight: Applanix SBET and ASCII ``time,x,y,z``.

Their records, columns and time bases: docs/import.md, "Trajectory files" and "GPS time". The
positions and attitude in the map's CRS: :mod:`lidarcal_ros.io.survey.trajectory_crs`.
"""

from __future__ import annotations

import enum
import io
import logging
import math
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from lidarcal_ros.errors import InputError, OutputError, TrajectoryError
from lidarcal_ros.io.survey.las_writer import (
    ADJUSTED_GPS_OFFSET,
    GPS_EPOCH_UNIX,
    adjusted_gps_to_unix,
)

if TYPE_CHECKING:
    from lidarcal_ros.core.mission import Trajectory

logger = logging.getLogger(__name__)


class TimeBase(enum.StrEnum):
    """What raw times count (docs/import.md, "GPS time"); ``--trajectory-time`` takes these
    or ``auto``."""

    #: GPS seconds of the week (an SBET's; a LAS header's global-encoding bit 0 clear).
    WEEK = "week"
    #: Adjusted standard GPS time: GPS seconds since the GPS epoch minus 1e9 (bit 0 set).
    ADJUSTED = "adjusted"
    #: GPS seconds since the GPS epoch (1980-01-06), no leap seconds.
    GPS = "gps"
    #: UNIX (UTC) seconds, leap seconds applied.
    UNIX = "unix"


class TrajectoryFileKind(enum.StrEnum):
    """The format of a trajectory file."""

    #: Applanix SBET: binary records of :data:`SBET_FIELDS`.
    SBET = "sbet"
    #: Text lines ``time,x,y,z[,...]``, with or without a header line.
    ASCII = "ascii"


WEEK_S = 604_800.0

SBET_FIELDS: tuple[str, ...] = (
    "time", "latitude", "longitude", "altitude",
    "x_velocity", "y_velocity", "z_velocity",
    "roll", "pitch", "heading", "wander_angle",
    "x_acceleration", "y_acceleration", "z_acceleration",
    "x_angular_rate", "y_angular_rate", "z_angular_rate",
)
SBET_DTYPE = np.dtype([(name, "<f8") for name in SBET_FIELDS])
SBET_RECORD_BYTES = SBET_DTYPE.itemsize  # 136
#: Most records an SBET or smrmsg may hold: 69 hours at 200 Hz (an SBET of 6.8 GB, some 3 GB
#: of columns once read). More is not a flight: a sparse file, or a file that is not one.
MAX_TRAJECTORY_RECORDS = 50_000_000

#: An Applanix ``smrmsg`` accuracy file's record: 10 little-endian float64 (the SBET's time,
#: position RMS north, east, down in m, velocity RMS m/s, roll, pitch, heading RMS arc-min).
SMRMSG_FIELDS: tuple[str, ...] = (
    "time", "north_position_rms", "east_position_rms", "down_position_rms",
    "north_velocity_rms", "east_velocity_rms", "down_velocity_rms",
    "roll_rms", "pitch_rms", "heading_rms",
)
SMRMSG_DTYPE = np.dtype([(name, "<f8") for name in SMRMSG_FIELDS])
SMRMSG_RECORD_BYTES = SMRMSG_DTYPE.itemsize  # 80

_SBET_SUFFIXES = {".out", ".sbet", ".bin", ".smrmsg"}
_ASCII_SUFFIXES = {".csv", ".txt", ".asc", ".pos", ".xyz", ".tsv", ".dat"}
_TIME_NAMES = {"time", "t", "gps_time", "gpstime", "timestamp", "sow", "seconds", "gps_seconds"}
_X_NAMES = {"x", "easting", "east", "e"}
_Y_NAMES = {"y", "northing", "north", "n"}
_Z_NAMES = {"z", "height", "h", "alt", "altitude", "elevation", "ellipsoidal_height", "up"}
_LAT_NAMES = {"lat", "latitude", "phi"}
_LON_NAMES = {"lon", "long", "longitude", "lambda"}
_HEADING_NAMES = {"heading", "heading_deg", "true_heading", "hdg"}
_ROLL_NAMES = {"roll", "roll_deg", "roll_angle", "bank"}
_PITCH_NAMES = {"pitch", "pitch_deg", "pitch_angle"}
#: Columns of roll, pitch and heading in a trajectory without a header:
#: ``time,x,y,z,roll,pitch,heading``.
_ROLL_COLUMN, _PITCH_COLUMN, _HEADING_COLUMN = 4, 5, 6
#: A unit of degrees after a header name: ``roll (deg)``, ``pitch[deg]``.
_DEGREE_UNIT = re.compile(r"\s*[\[(]\s*(deg|degrees|\u00b0)\s*[\])]$")


class TrajectoryFileError(TrajectoryError):
    """A trajectory file is missing, unreadable or malformed."""


@dataclass
class TrajectoryFile:
    """Samples of a trajectory file, as stored.

    Attributes
    ----------
    path : Path
    kind : TrajectoryFileKind
    t : (n,) float64
        Raw times, seconds, in the file's time base (SBET: week seconds).
    a, b, c : (n,) float64
        Geographic: longitude (deg), latitude (deg), ellipsoidal height (m).
        Projected: x, y, z in the file's CRS and unit.
    geographic : bool
    heading_deg : (n,) float64 or None
        Heading of the platform, degrees clockwise from north (true north for geographic
        positions, grid north for projected ones); None when the file has none.
    roll_deg, pitch_deg : (n,) float64 or None
        Roll (right wing down positive) and pitch (nose up positive), degrees; both None when
        the file has no heading or no usable roll and pitch (the heading alone then serves).
    """

    path: Path
    kind: TrajectoryFileKind
    t: np.ndarray
    a: np.ndarray
    b: np.ndarray
    c: np.ndarray
    geographic: bool
    heading_deg: np.ndarray | None = None
    roll_deg: np.ndarray | None = None
    pitch_deg: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.t.shape[0])

    @property
    def attitude(self) -> str:
        """What the file carries: ``"roll, pitch, heading"``, ``"heading"`` or ``"none"``."""
        if self.heading_deg is None:
            return "none"
        return "heading" if self.roll_deg is None else "roll, pitch, heading"

    def take(self, index: np.ndarray | slice) -> TrajectoryFile:
        """A subset of the samples."""
        def sub(values: np.ndarray | None) -> np.ndarray | None:
            return None if values is None else values[index]

        return TrajectoryFile(self.path, self.kind, self.t[index], self.a[index],
                              self.b[index], self.c[index], self.geographic,
                              sub(self.heading_deg), sub(self.roll_deg), sub(self.pitch_deg))


# ---------------------------------------------------------------------------- time bases
def gps_week_of_unix(unix_time: float) -> int:
    """GPS week number of a UNIX time (leap seconds ignored: a week is what matters)."""
    return int(math.floor((unix_time - GPS_EPOCH_UNIX) / WEEK_S))


def to_gps_seconds(values: np.ndarray, base: TimeBase, *, week: int | None = None
                   ) -> np.ndarray:
    """Times of ``base`` as GPS seconds since the GPS epoch.

    Parameters
    ----------
    values : (n,) float64
    base : TimeBase
    week : int, keyword-only
        GPS week of ``WEEK`` times (required for them).
    """
    v = np.asarray(values, dtype=np.float64)
    if base is TimeBase.WEEK:
        if week is None:
            raise ValueError("week times need the GPS week")
        return v + week * WEEK_S
    if base is TimeBase.ADJUSTED:
        return v + ADJUSTED_GPS_OFFSET
    if base is TimeBase.GPS:
        return v
    if base is TimeBase.UNIX:
        from lidarcal_ros.io.survey.las_writer import unix_to_adjusted_gps

        return np.asarray(unix_to_adjusted_gps(v)) + ADJUSTED_GPS_OFFSET
    raise ValueError(f"unknown time base {base!r}")


def gps_to_unix(gps_seconds: np.ndarray) -> np.ndarray:
    """GPS seconds since the GPS epoch to UNIX (UTC) seconds, leap seconds applied."""
    return np.asarray(adjusted_gps_to_unix(np.asarray(gps_seconds) - ADJUSTED_GPS_OFFSET))


# ---------------------------------------------------------------------------- SBET
def _check_record_count(p: Path, records: int, what: str) -> None:
    if records > MAX_TRAJECTORY_RECORDS:
        raise TrajectoryFileError(
            f"{p}: {records} {what} records, more than the {MAX_TRAJECTORY_RECORDS} of 69 hours "
            "at 200 Hz; refused (a sparse or foreign file?)")


def read_sbet(path: str | os.PathLike[str]) -> TrajectoryFile:
    """Read an Applanix SBET (docs/import.md, "Trajectory files").

    Returns
    -------
    TrajectoryFile
        ``t`` week seconds; ``a`` longitude and ``b`` latitude in degrees; ``c`` altitude (m).

    Raises
    ------
    TrajectoryFileError
        Missing file, a size that is not a whole number of 136-byte records, no records or
        more than :data:`MAX_TRAJECTORY_RECORDS`, records that are not SBET
        (latitude/longitude out of range, non-finite time), or records all at one time.
    """
    p = _check_file(path)
    size = p.stat().st_size
    if size == 0 or size % SBET_RECORD_BYTES:
        raise TrajectoryFileError(
            f"{p}: not an SBET: {size} bytes is not a whole number of {SBET_RECORD_BYTES}-byte "
            "records"
        )
    _check_record_count(p, size // SBET_RECORD_BYTES, "SBET")
    try:
        records = np.memmap(p, dtype=SBET_DTYPE, mode="r")
    except (OSError, ValueError) as exc:
        raise TrajectoryFileError(f"{p}: cannot read ({exc})") from None
    t = np.array(records["time"])
    lat = np.array(records["latitude"])
    lon = np.array(records["longitude"])
    alt = np.array(records["altitude"])
    platform_heading = np.array(records["heading"])
    wander = np.array(records["wander_angle"])
    roll = np.degrees(records["roll"])
    pitch = np.degrees(records["pitch"])
    del records
    bad = ~(np.isfinite(t) & np.isfinite(alt) & (np.abs(lat) <= math.pi / 2 + 1e-9)
            & (np.abs(lon) <= 2 * math.pi + 1e-9))
    if bad.any():
        k = int(np.argmax(bad))
        raise TrajectoryFileError(
            f"{p}: not an SBET: record {k} has time {float(t[k])!r}, latitude "
            f"{float(lat[k])!r} rad, longitude {float(lon[k])!r} rad"
        )
    _check_times(p, t)
    lon_deg = np.degrees(lon)
    lon_deg = np.where(lon_deg > 180.0, lon_deg - 360.0, lon_deg)
    heading = None
    if np.any(platform_heading != 0.0) or np.any(wander != 0.0):
        heading = np.degrees(platform_heading - wander)  # true heading (Applanix)
        heading[~np.isfinite(heading)] = np.nan
    roll_pitch = _roll_and_pitch(p, heading, roll, pitch, ("roll field", "pitch field"))
    return TrajectoryFile(p, TrajectoryFileKind.SBET, t, lon_deg, np.degrees(lat), alt, True,
                          heading, *roll_pitch)


def write_sbet(
    path: str | os.PathLike[str],
    t: np.ndarray,
    latitude_rad: np.ndarray,
    longitude_rad: np.ndarray,
    altitude_m: np.ndarray,
    **fields: np.ndarray,
) -> Path:
    """Write an SBET (docs/import.md); fields not given are zero.

    Parameters
    ----------
    path : path-like
    t : (n,) float64
        GPS seconds of the week.
    latitude_rad, longitude_rad : (n,) float64, radians
    altitude_m : (n,) float64, metres above the ellipsoid
    **fields : (n,) float64
        Further SBET fields by name (``roll``, ``heading``, ...).
    """
    return _write_records(path, SBET_DTYPE, "SBET", fields, time=t, latitude=latitude_rad,
                          longitude=longitude_rad, altitude=altitude_m)


def _write_records(path: str | os.PathLike[str], dtype: np.dtype, what: str,
                   fields: dict[str, np.ndarray], **columns: np.ndarray) -> Path:
    """Records of ``dtype`` from ``columns`` and the further ``fields`` (refused where
    ``dtype`` has no such field), the rest zero, written to ``path`` as they are."""
    unknown = [k for k in fields if k not in (dtype.names or ())]
    if unknown:
        raise InputError(f"{path}: unknown {what} field(s) {', '.join(unknown)}")
    rec = np.zeros(np.asarray(columns["time"]).shape[0], dtype=dtype)
    for name, values in {**columns, **fields}.items():
        rec[name] = values
    p = Path(path)
    rec.tofile(p)
    return p


# ---------------------------------------------------------------------------- smrmsg
@dataclass
class TrajectoryAccuracy:
    """An SBET's accuracy file (``smrmsg``): per epoch, the position RMS of the solution.

    Attributes
    ----------
    path : Path
    t : (n,) float64
        Times, seconds, the SBET's (GPS seconds of the week), increasing.
    position_rms : (n, 3) float64
        One-sigma position accuracy north, east, down, metres.
    """

    path: Path
    t: np.ndarray
    position_rms: np.ndarray

    def enu_at(self, t: np.ndarray, *, where: str) -> np.ndarray:
        """The position sigmas (n, 3) east, north, up (m) at times ``t`` (s, the file's time
        base), linear between epochs; within one epoch interval beyond the file's ends the
        end value held.

        Raises
        ------
        TrajectoryFileError
            ``t`` reaches further beyond the file's first or last epoch: one line naming
            ``where`` (the trajectory) and both spans.
        """
        t = np.asarray(t, dtype=np.float64)
        step = float(np.median(np.diff(self.t))) if self.t.size > 1 else 0.0
        lo, hi = float(np.nanmin(t)), float(np.nanmax(t))
        if lo < self.t[0] - step or hi > self.t[-1] + step:
            raise TrajectoryFileError(
                f"{self.path}: accuracy epochs span {self.t[0]:.3f}-{self.t[-1]:.3f} s but "
                f"{where} spans {lo:.3f}-{hi:.3f} s; it does not cover the trajectory")
        north, east, down = (np.interp(t, self.t, self.position_rms[:, k]) for k in range(3))
        return np.column_stack([east, north, down])


def read_smrmsg(path: str | os.PathLike[str]) -> TrajectoryAccuracy:
    """Read an Applanix ``smrmsg`` accuracy file (records of :data:`SMRMSG_FIELDS`).

    Raises
    ------
    TrajectoryFileError
        Missing file; a size that is not a whole number of 80-byte records (truncated, or
        not an smrmsg: an SBET's records are 136 bytes); no records; a time or position RMS
        not finite, or an RMS negative (with its record); times not increasing.
    """
    p = _check_file(path)
    size = p.stat().st_size
    if size == 0 or size % SMRMSG_RECORD_BYTES:
        raise TrajectoryFileError(
            f"{p}: not an smrmsg accuracy file: {size} bytes is not a whole number of "
            f"{SMRMSG_RECORD_BYTES}-byte records (truncated?)")
    _check_record_count(p, size // SMRMSG_RECORD_BYTES, "smrmsg")
    try:
        records = np.fromfile(p, dtype=SMRMSG_DTYPE)
    except (OSError, ValueError) as exc:
        raise TrajectoryFileError(f"{p}: cannot read ({exc})") from None
    t = np.array(records["time"])
    rms = np.column_stack([records[name] for name in SMRMSG_FIELDS[1:4]])
    bad = ~(np.isfinite(t) & np.isfinite(rms).all(axis=1) & (rms >= 0.0).all(axis=1))
    if bad.any():
        k = int(np.argmax(bad))
        raise TrajectoryFileError(
            f"{p}: smrmsg record {k} has time {float(t[k])!r} and position RMS north, east, "
            f"down {', '.join(repr(float(v)) for v in rms[k])} m; each must be a finite "
            "number, the RMS not negative")
    steps = np.diff(t)
    if (steps <= 0).any():
        k = int(np.argmax(steps <= 0)) + 1
        raise TrajectoryFileError(f"{p}: smrmsg record {k} at {float(t[k]):.3f} s does not "
                                  f"follow record {k - 1} at {float(t[k - 1]):.3f} s")
    return TrajectoryAccuracy(p, t, rms)


def write_smrmsg(path: str | os.PathLike[str], t: np.ndarray, north_m: np.ndarray,
                 east_m: np.ndarray, down_m: np.ndarray, **fields: np.ndarray) -> Path:
    """Write an ``smrmsg`` (:data:`SMRMSG_FIELDS`; times the SBET's, position RMS in m);
    fields not given are zero."""
    return _write_records(path, SMRMSG_DTYPE, "smrmsg", fields, time=t,
                          north_position_rms=north_m, east_position_rms=east_m,
                          down_position_rms=down_m)


def smrmsg_beside(trajectory: str | os.PathLike[str]) -> Path | None:
    """The accuracy file POSPac writes beside an SBET: ``smrmsg_NAME.out`` for
    ``sbet_NAME.out`` (the prefix in any case), where it exists; else None."""
    p = Path(trajectory)
    if not p.name.lower().startswith("sbet"):
        return None
    for prefix in ("smrmsg", "SMRMSG", "Smrmsg"):
        candidate = p.with_name(prefix + p.name[4:])
        if candidate.is_file():
            return candidate
    return None


# ---------------------------------------------------------------------------- ASCII
def _split(line: str) -> list[str]:
    for sep in (",", ";"):
        if sep in line:
            return [c.strip() for c in line.split(sep)]
    return line.split()


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def read_ascii_trajectory(path: str | os.PathLike[str]) -> TrajectoryFile:
    """Read an ASCII trajectory (docs/import.md, "Trajectory files").

    Raises
    ------
    TrajectoryFileError
        Missing file, no samples, fewer than four columns, a header without time and
        position columns, a value that is not a number (with its line), or samples all at
        one time.
    """
    p = _check_file(path)
    try:
        text = p.read_text(encoding="utf-8-sig", errors="strict")
    except UnicodeDecodeError:
        raise TrajectoryFileError(
            f"{p}: not a text trajectory (binary data; an SBET needs the .out suffix or "
            "a size that is a multiple of 136 bytes)"
        ) from None
    except OSError as exc:
        raise TrajectoryFileError(f"{p}: cannot read ({exc.strerror or exc})") from None
    rows = [(no, line) for no, line in enumerate(text.splitlines(), start=1)
            if line.strip() and not line.lstrip().startswith(("#", "%", "//"))]
    if not rows:
        raise TrajectoryFileError(f"{p}: empty trajectory file (expected time,x,y,z lines)")
    first = _split(rows[0][1])
    geographic = False
    cols: tuple[int | None, ...]
    if not all(_is_number(c) for c in first):
        header_no = rows[0][0]
        names = [_DEGREE_UNIT.sub("", c.strip().strip('"').lower()) for c in first]
        rows = rows[1:]
        col_t = _find(names, _TIME_NAMES)
        col_lat, col_lon = _find(names, _LAT_NAMES), _find(names, _LON_NAMES)
        col_z = _find(names, _Z_NAMES)
        col_a: int | None
        col_b: int | None
        if col_lat is not None and col_lon is not None:
            geographic = True
            col_a, col_b = col_lon, col_lat
        else:
            col_a, col_b = _find(names, _X_NAMES), _find(names, _Y_NAMES)
        missing = [label for label, col in (("time", col_t), ("x/lon", col_a), ("y/lat", col_b),
                                            ("z/height", col_z)) if col is None]
        if missing:
            raise TrajectoryFileError(
                f"{p}: line {header_no}: header lacks column(s) {', '.join(missing)} "
                f"(found: {', '.join(names)})"
            )
        col_heading = _find(names, _HEADING_NAMES)
        col_roll, col_pitch = _find(names, _ROLL_NAMES), _find(names, _PITCH_NAMES)
        cols = (col_t, col_a, col_b, col_z)
        width = len(names)
    else:
        cols = (0, 1, 2, 3)
        width = len(first)
        if width < 4:
            raise TrajectoryFileError(
                f"{p}: line {rows[0][0]}: {width} columns; expected time,x,y,z[,...]"
            )
        col_heading = _HEADING_COLUMN if width > _HEADING_COLUMN else None
        col_roll, col_pitch = ((_ROLL_COLUMN, _PITCH_COLUMN) if width > _PITCH_COLUMN
                               else (None, None))
    if not rows:
        raise TrajectoryFileError(f"{p}: no samples after the header line")
    body = "\n".join(",".join(_split(line)) for _, line in rows)
    try:
        data = np.loadtxt(io.StringIO(body), delimiter=",", ndmin=2,
                          usecols=[c for c in cols if c is not None])
    except ValueError as exc:
        raise TrajectoryFileError(f"{p}: {_locate_bad_row(rows, cols, width) or exc}") from None
    bad = ~np.isfinite(data).all(axis=1)
    if bad.any():
        k = int(np.argmax(bad))
        raise TrajectoryFileError(f"{p}: line {rows[k][0]}: non-finite value")
    _check_times(p, data[:, 0])
    heading = None
    if col_heading is not None:
        heading = _angle_column(p, body, col_heading, _column_label("heading", col_heading),
                                "headings from the track")
        if heading is not None and not np.any(heading != 0.0):
            heading = None  # a placeholder
        elif heading is not None:
            heading[~np.isfinite(heading)] = np.nan
    labels = (_column_label("roll", col_roll), _column_label("pitch", col_pitch))
    roll = pitch = None
    if col_roll is not None and col_pitch is not None:
        fallback = "heading only" if heading is not None else "positions only"
        roll = _angle_column(p, body, col_roll, labels[0], fallback)
        pitch = _angle_column(p, body, col_pitch, labels[1], fallback)
    elif heading is not None and (col_roll, col_pitch) != (None, None):
        logger.warning("%s: %s but %s: heading only", p, *labels)
    return TrajectoryFile(p, TrajectoryFileKind.ASCII, data[:, 0], data[:, 1], data[:, 2],
                          data[:, 3], geographic, heading,
                          *_roll_and_pitch(p, heading, roll, pitch, labels))


def _column_label(name: str, col: int | None) -> str:
    return f"{name} column {col + 1}" if col is not None else f"no {name} column"


def _angle_column(p: Path, body: str, col: int, label: str, fallback: str
                  ) -> np.ndarray | None:
    """A column of angles (degrees) of an ASCII trajectory (``body``: its sample lines,
    comma-separated); None, with a warning naming the ``label`` and the ``fallback``, where it
    is not numbers (a column of another meaning): the rest still serves."""
    try:
        return np.loadtxt(io.StringIO(body), delimiter=",", ndmin=1, usecols=[col])
    except (ValueError, IndexError):
        logger.warning("%s: %s is not numeric: %s", p, label, fallback)
        return None


def _roll_and_pitch(p: Path, heading: np.ndarray | None, roll: np.ndarray | None,
                    pitch: np.ndarray | None, labels: tuple[str, str]
                    ) -> tuple[np.ndarray, np.ndarray] | tuple[None, None]:
    """Roll and pitch (degrees) worth joining the heading, else ``(None, None)``.

    All zero: a converter that filled the heading only (the poses stay level, no warning).
    Any value not finite: the whole file keeps the heading alone (one trajectory is either
    levelled or measured, never both), with a warning naming the column. Without a heading
    roll and pitch cannot place the body: positions only, with a warning.
    """
    if roll is None or pitch is None:
        return None, None
    if not (np.any(roll != 0.0) or np.any(pitch != 0.0)):
        return None, None
    if heading is None:
        logger.warning("%s: %s and %s but no heading: positions only", p, *labels)
        return None, None
    for values, label in ((roll, labels[0]), (pitch, labels[1])):
        bad = int(np.count_nonzero(~np.isfinite(values)))
        if bad:
            logger.warning("%s: %s has %d of %d values not finite: heading only", p, label,
                           bad, values.size)
            return None, None
    return roll, pitch


def _find(names: list[str], wanted: set[str]) -> int | None:
    for i, name in enumerate(names):
        if name in wanted:
            return i
    return None


def _locate_bad_row(rows: list[tuple[int, str]], cols: tuple[int | None, ...], width: int) -> str:
    for no, line in rows:
        cells = _split(line)
        if len(cells) < width:
            return f"line {no}: {len(cells)} values, expected {width}"
        for c in cols:
            if c is not None and not _is_number(cells[c]):
                return f"line {no}: '{cells[c]}' is not a number"
    return ""


def _check_times(p: Path, t: np.ndarray) -> None:
    """Refuse samples that are all at one time (a column of another meaning, or times not
    written): they trace no path."""
    if t.size > 1 and float(t.min()) == float(t.max()):
        raise TrajectoryFileError(f"{p}: all {t.size} samples carry the same time {t[0]:.3f} s; "
                                  "a trajectory needs each sample at its own time")


def write_ascii_trajectory(path: str | os.PathLike[str], trajectory: Trajectory, *,
                           comments: Sequence[str] = (), overwrite: bool = False) -> Path:
    """Write ``trajectory`` as an ASCII trajectory that :func:`read_ascii_trajectory` (and
    ``lidarcal import``) reads: ``#`` comment lines, a header line, then one sample per line.

    Columns: ``time`` (the trajectory's clock, s: UNIX seconds for a bag's stamps), ``x``,
    ``y``, ``z`` (map frame, m); where the trajectory has an attitude, ``roll``, ``pitch``
    and ``heading`` in degrees (roll right wing down and pitch nose up positive, heading
    clockwise from the map's grid north, as an SBET's: the inverse of the import's
    conversion), or ``heading`` alone where its poses were levelled from a heading (``nan``
    for a sample without one). Atomic (:func:`~lidarcal_ros.io.output_files.write_text`).

    Raises
    ------
    OutputError
        ``path`` exists and ``overwrite`` is False, or it cannot be written (one line).
    """
    from lidarcal_ros.core.georeferencing.attitude import attitude_from_quaternions
    from lidarcal_ros.io.output_files import EXISTS, write_text

    p = Path(path)
    if (p.exists() or p.is_symlink()) and not overwrite:
        raise OutputError(f"{p}: {EXISTS}")
    columns = [trajectory.t, trajectory.xyz[:, 0], trajectory.xyz[:, 1], trajectory.xyz[:, 2]]
    names = ["time", "x", "y", "z"]
    formats = ["%.6f", "%.4f", "%.4f", "%.4f"]
    if trajectory.orientation is not None:
        roll, pitch, kappa = attitude_from_quaternions(trajectory.orientation)
        heading = np.mod(-np.degrees(kappa), 360.0)  # (kappa counter-clockwise from north)
        if trajectory.full_attitude:
            columns += [np.degrees(roll), np.degrees(pitch)]
            names += ["roll", "pitch"]
            formats += ["%.6f", "%.6f"]
        columns.append(heading)
        names.append("heading")
        formats.append("%.6f")
    buffer = io.StringIO()
    for line in comments:
        buffer.write(f"# {line}\n")
    buffer.write(",".join(names) + "\n")
    np.savetxt(buffer, np.column_stack(columns), fmt=formats, delimiter=",")
    return write_text(p, buffer.getvalue(), what="trajectory", overwrite=overwrite)


def _check_file(path: str | os.PathLike[str]) -> Path:
    p = Path(path)
    if not p.exists():
        raise TrajectoryFileError(f"{p}: trajectory file not found")
    if p.is_dir():
        raise TrajectoryFileError(f"{p}: is a directory, not a trajectory file")
    return p


def read_trajectory_file(
    path: str | os.PathLike[str], *, kind: TrajectoryFileKind | None = None
) -> TrajectoryFile:
    """Read an SBET or ASCII trajectory.

    ``kind`` None decides by suffix (``.out``, ``.sbet``, ``.bin``: SBET; ``.csv``,
    ``.txt``, ``.pos``, ...: ASCII), else by content (text or not).
    """
    p = _check_file(path)
    if kind is None:
        suffix = p.suffix.lower()
        if suffix in _SBET_SUFFIXES:
            kind = TrajectoryFileKind.SBET
        elif suffix in _ASCII_SUFFIXES:
            kind = TrajectoryFileKind.ASCII
        else:
            with p.open("rb") as fh:
                head = fh.read(4096)
            textual = bool(head) and all(b in b"\t\n\r" or 32 <= b < 127 for b in head)
            kind = TrajectoryFileKind.ASCII if textual else TrajectoryFileKind.SBET
    traj = read_sbet(p) if kind is TrajectoryFileKind.SBET else read_ascii_trajectory(p)
    if len(traj) < 2:
        raise TrajectoryFileError(f"{p}: {len(traj)} trajectory sample(s); need at least 2")
    return traj


__all__ = ["SBET_DTYPE", "SBET_FIELDS", "SBET_RECORD_BYTES", "SMRMSG_DTYPE", "SMRMSG_FIELDS",
           "SMRMSG_RECORD_BYTES", "WEEK_S", "TimeBase", "TrajectoryAccuracy", "TrajectoryFile",
           "TrajectoryFileError", "TrajectoryFileKind", "gps_to_unix", "gps_week_of_unix",
           "read_ascii_trajectory", "read_sbet", "read_smrmsg", "read_trajectory_file",
           "smrmsg_beside", "to_gps_seconds", "write_ascii_trajectory", "write_sbet",
           "write_smrmsg"]
