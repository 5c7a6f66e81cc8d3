"""Writing corrected clouds as LAS 1.4 / LAZ (point format 6), chunk by chunk.

The record's fields and the conventions of scan angle, GPS time and intensity: docs/correction.md,
"LAS and LAZ".
"""

from __future__ import annotations

import calendar
import io
import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, Literal

import numpy as np

from lidarcal_ros.core.flags import FLAG_NOT_CORRECTED
from lidarcal_ros.errors import ConfigError, OutputError
from lidarcal_ros.io.output_files import (
    APPEARED,
    EXISTS,
    install,
    os_reason,
    remove_quietly,
    temporary_beside,
)
from lidarcal_ros.io.survey import las_kernels
from lidarcal_ros.io.survey.las_reader import quiet_laspy_errors

logger = logging.getLogger(__name__)
quiet_laspy_errors("laspy.laswriter")

#: Coordinate resolution, metres.
SCALE_M = 0.001
#: LAS stores coordinates as 32-bit integers of the scale from the offsets.
_MAX_SCALED = 2.0**31 - 1.0
#: UNIX time of the GPS epoch, 1980-01-06T00:00:00Z.
GPS_EPOCH_UNIX = 315_964_800
#: Offset of Adjusted Standard GPS Time.
ADJUSTED_GPS_OFFSET = 1.0e9
#: (UNIX time from which it applies, GPS - UTC in seconds).
_LEAP_SECONDS: tuple[tuple[int, int], ...] = tuple(
    (calendar.timegm((y, m, 1, 0, 0, 0)), n)
    for (y, m), n in zip(
        ((1981, 7), (1982, 7), (1983, 7), (1985, 7), (1988, 1), (1990, 1), (1991, 1),
         (1992, 7), (1993, 7), (1994, 7), (1996, 1), (1997, 7), (1999, 1), (2006, 1),
         (2009, 1), (2012, 7), (2015, 7), (2017, 1)),
        range(1, 19),
    )
)
_LEAP_T = np.array([t for t, _ in _LEAP_SECONDS], dtype=np.float64)
_LEAP_N = np.array([0] + [n for _, n in _LEAP_SECONDS], dtype=np.float64)

#: Extra-bytes dimensions written: name, numpy type, description (LAS allows 32 characters;
#: the reflectance's is the writer's ``reflectance_description``).
EXTRA_DIMENSIONS: tuple[tuple[str, str, str], ...] = (
    ("reflectance", "f4", "I at 1000 m, 0 deg incidence"),
    ("range", "f4", "sensor to point, m"),
    ("incidence", "f4", "incidence angle, rad"),
    ("correction_flags", "u1", "lidarcal correction flags"),
)


def leap_seconds(unix_time: np.ndarray) -> np.ndarray:
    """GPS - UTC (s) in force at each UNIX time (table up to the 2017 leap second)."""
    return _LEAP_N[np.searchsorted(_LEAP_T, np.asarray(unix_time, dtype=np.float64),
                                   side="right")]


def unix_to_adjusted_gps(unix_time: np.ndarray) -> np.ndarray:
    """UNIX (UTC) seconds to Adjusted Standard GPS Time (GPS seconds - 1e9)."""
    t = np.asarray(unix_time, dtype=np.float64)
    return (t - (GPS_EPOCH_UNIX + ADJUSTED_GPS_OFFSET)) + leap_seconds(t)


def adjusted_gps_to_unix(gps_time: np.ndarray) -> np.ndarray:
    """Adjusted Standard GPS Time to UNIX (UTC) seconds (inverse of
    :func:`unix_to_adjusted_gps`, exact away from the second of a leap)."""
    g = np.asarray(gps_time, dtype=np.float64)
    approx = g + (GPS_EPOCH_UNIX + ADJUSTED_GPS_OFFSET)
    return approx - leap_seconds(approx - leap_seconds(approx))


def parse_crs(text: str) -> Any:
    """A ``pyproj.CRS`` from ``EPSG:N`` (or anything pyproj accepts).

    Raises
    ------
    ConfigError
        pyproj does not know it.
    """
    import pyproj

    try:
        return pyproj.CRS.from_user_input(text)
    except pyproj.exceptions.CRSError as exc:
        raise ConfigError(f"--crs: '{text}' is not a known CRS ({' '.join(str(exc).split())})"
                          ) from None


@dataclass
class LasStats:
    """What a :class:`LasChunkWriter` wrote."""

    points: int = 0
    skipped_non_finite: int = 0
    #: Points too far from the file's offsets for LAS's 32-bit coordinates (about 2147 km
    #: at the 1 mm scale): a glitch, not a point of the survey.
    skipped_out_of_range: int = 0
    clipped_intensity: int = 0
    withheld: int = 0


class _OutputFile(io.BufferedRandom):
    """The file being written, keeping the first ``OSError`` of its writes: lazrs reports a
    failed write as a bare ``IoError``, without the operating system's reason (disk full)."""

    def __init__(self, path: Path) -> None:
        super().__init__(io.FileIO(path, "w+"))
        self.error: OSError | None = None

    def _kept(self, exc: OSError) -> OSError:
        if self.error is None:
            self.error = exc
        return exc

    def write(self, data: Any) -> int:
        try:
            return super().write(data)
        except OSError as exc:
            raise self._kept(exc) from None

    def flush(self) -> None:
        try:
            super().flush()
        except OSError as exc:
            raise self._kept(exc) from None


def _column(values: np.ndarray | None, kind: str = "f4") -> np.ndarray:
    """An optional column of :func:`~lidarcal_ros.io.survey.las_kernels.fill_records`: empty (of
    the type it would have) when the cloud lacks it."""
    return np.zeros(0, dtype=kind) if values is None else values


def _field(arr: np.ndarray, *names: str) -> np.ndarray | None:
    present = arr.dtype.names or ()
    for name in names:
        if name in present:
            return arr[name]
    return None


class LasChunkWriter:
    """Stream corrected point arrays into a LAS 1.4 / LAZ file; use as a context manager.

    Parameters
    ----------
    path : path-like
        ``.las`` or ``.laz`` (compressed with lazrs).
    time_field : str
        Field of the arrays holding the firing time (absolute seconds).
    crs : pyproj.CRS, optional
        Written as an OGC WKT VLR.
    overwrite : bool
        Replace an existing file.
    reflectance_description : str, optional
        Description of the ``reflectance`` dimension (at most 32 characters:
        :attr:`~lidarcal_ros.core.radiometry.RadiometricModel.las_description`); default
        that of :data:`EXTRA_DIMENSIONS`.

    Notes
    -----
    The header (offsets) is made when the first chunk arrives; bounds and point counts are
    updated as chunks are written and rewritten on close. Memory does not grow with the number
    of points. The file is written under a hidden name beside ``path`` and moved into place
    when complete: if the ``with`` block or a write fails (disk full), nothing partial is left
    and a previous file is untouched.

    Raises
    ------
    OutputError
        The output exists (without ``overwrite``), its directory is missing, or a write
        fails: one line naming the file and the operating system's reason.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        time_field: str = "t",
        crs: Any = None,
        overwrite: bool = False,
        reflectance_description: str | None = None,
    ) -> None:
        self.path = Path(path)
        if reflectance_description is not None and len(reflectance_description) > 32:
            raise ConfigError(f"LAS extra-bytes descriptions hold 32 characters: "
                              f"{reflectance_description!r} is longer")
        self.descriptions = {name: desc for name, _, desc in EXTRA_DIMENSIONS}
        if reflectance_description is not None:
            self.descriptions["reflectance"] = reflectance_description
        suffix = self.path.suffix.lower()
        if suffix not in (".las", ".laz"):
            raise ConfigError(f"{self.path}: a LAS output must end in .las or .laz")
        if (self.path.exists() or self.path.is_symlink()) and not overwrite:
            raise OutputError(f"{self.path}: {EXISTS}")
        if not self.path.parent.is_dir():
            raise OutputError(f"{self.path}: directory {self.path.parent} does not exist")
        self._overwrite = overwrite
        self.compress = suffix == ".laz"
        self.time_field = time_field
        self.crs = crs
        self.stats = LasStats()
        self._writer: Any = None
        self._header: Any = None
        self._gps_standard: bool | None = None
        self._tmp = temporary_beside(self.path)
        self._file: _OutputFile | None = None

    @property
    def header(self) -> Any:
        """The laspy header of the file (scales, offsets, point format), made from the first
        chunk written; None before it."""
        return self._header

    @property
    def gps_standard(self) -> bool | None:
        """Whether the GPS times are written as adjusted standard GPS time (True) or as they
        came (False: times before the GPS epoch, e.g. GPS week seconds); None before the first
        chunk."""
        return self._gps_standard

    # -- life cycle ----------------------------------------------------------------------

    def __enter__(self) -> LasChunkWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> Literal[False]:
        if exc_type is None:
            self.close()
        else:
            self.abort()
        return False

    def _open(self, xyz: np.ndarray, t: np.ndarray) -> None:
        import laspy

        header = laspy.LasHeader(version="1.4", point_format=6)
        header.add_extra_dims([laspy.ExtraBytesParams(name=name, type=np.dtype(kind),
                                                      description=self.descriptions[name])
                               for name, kind, _ in EXTRA_DIMENSIONS])
        header.scales = np.array([SCALE_M, SCALE_M, SCALE_M])
        if xyz.shape[0]:
            # the median: a glitch point far away must not move the offsets off the survey
            mid = np.median(xyz, axis=0)
            header.offsets = np.array([math.floor(mid[0] / 1000.0) * 1000.0,
                                       math.floor(mid[1] / 1000.0) * 1000.0, 0.0])
        else:
            header.offsets = np.zeros(3)
        finite_t = t[np.isfinite(t)]
        self._gps_standard = bool(finite_t.size == 0 or finite_t.min() >= GPS_EPOCH_UNIX)
        header.global_encoding.gps_time_type = (
            laspy.header.GpsTimeType.STANDARD if self._gps_standard
            else laspy.header.GpsTimeType.WEEK_TIME)
        if not self._gps_standard:
            logger.warning("%s: point times are before 1980 (not UNIX/ROS times?); written "
                           "unchanged as GPS week time", self.path)
        header.global_encoding.wkt = True  # required for point formats 6-10 (LAS 1.4 R15)
        header.system_identifier = "lidarcal_ros"
        header.generating_software = "lidarcal correct"
        if self.crs is not None:
            header.add_crs(self.crs)
        self._header = header
        try:
            self._file = _OutputFile(self._tmp)
            self._writer = laspy.open(self._file, mode="w", header=header,
                                      do_compress=self.compress, closefd=True)
        except Exception as exc:
            raise self._failure("cannot create", exc) from None
        except BaseException:  # Ctrl-C, SIGTERM: leave nothing behind either
            self.abort()
            raise

    def _failure(self, what: str, exc: BaseException) -> OutputError:
        """The one-line error of a failed write (the operating system's reason where the LAZ
        compressor hid it); the partial file is removed."""
        cause = self._file.error if self._file is not None and self._file.error else exc
        self.abort()
        return OutputError(f"{self.path}: {what} ({os_reason(cause)})")

    def close(self) -> None:
        """Finish the file (header with bounds and counts) and move it into place."""
        if self._writer is None:
            # No chunk at all: still write a valid, empty file.
            self._open(np.empty((0, 3)), np.empty(0))
        writer, self._writer = self._writer, None
        try:
            writer.close()
            install(self._tmp, self.path, overwrite=self._overwrite)
        except FileExistsError:
            self._discard()
            raise OutputError(f"{self.path}: {APPEARED}") from None
        except Exception as exc:
            raise self._failure("cannot finish", exc) from None
        except BaseException:  # Ctrl-C, SIGTERM
            self._discard()
            raise

    def abort(self) -> None:
        """Stop writing and remove the partial file."""
        writer, self._writer = self._writer, None
        if writer is not None:
            try:
                writer.close()
            except Exception:  # best effort
                logger.debug("error closing %s", self._tmp, exc_info=True)
        self._discard()

    def _discard(self) -> None:
        if self._file is not None and not self._file.closed:
            try:
                self._file.close()
            except OSError:  # the write that failed, again
                pass
        remove_quietly(self._tmp)

    # -- writing -------------------------------------------------------------------------

    def write(self, points: np.ndarray) -> int:
        """Append a chunk of corrected points (a structured array with ``x, y, z``, the time
        field and optionally ``intensity``, ``strip_id``/``point_source_id``,
        ``return_number``, ``number_of_returns``, ``scan_angle``, ``reflectance``, ``range``,
        ``incidence``, ``correction_flags``). Returns the number of points written."""
        import laspy

        x, y, z = (np.asarray(points[c], dtype=np.float64) for c in "xyz")
        t = np.asarray(points[self.time_field], dtype=np.float64)
        if self._writer is None:
            finite = np.isfinite(x) & np.isfinite(y) & np.isfinite(z)
            self._open(np.column_stack([x[finite], y[finite], z[finite]]), t[finite])
        header = self._header
        offsets = np.asarray(header.offsets, dtype=np.float64)
        scales = np.asarray(header.scales, dtype=np.float64)
        rows, non_finite, out_of_range = las_kernels.rows_to_write(x, y, z, offsets, scales,
                                                                   _MAX_SCALED)
        self.stats.skipped_non_finite += non_finite
        self.stats.skipped_out_of_range += out_of_range
        n = len(rows)
        if n == 0:
            return 0
        rec = laspy.ScaleAwarePointRecord.zeros(n, header=header)
        out = rec.array
        inten = _field(points, "intensity")
        mode = las_kernels.INTENSITY_NONE if inten is None else (
            las_kernels.INTENSITY_U16 if inten.dtype == np.uint16 else
            las_kernels.INTENSITY_U8 if inten.dtype == np.uint8 else
            las_kernels.INTENSITY_FLOAT)
        extra = [name for name, _, _ in EXTRA_DIMENSIONS]  # reflectance, range, incidence, flags
        clipped, withheld = las_kernels.fill_records(
            rows, x, y, z, t, bool(self._gps_standard),
            GPS_EPOCH_UNIX + ADJUSTED_GPS_OFFSET, _LEAP_T, _LEAP_N,
            _column(inten, "u2"), mode,
            _column(_field(points, "strip_id", "point_source_id"), "u2"),
            _column(_field(points, "return_number"), "u1"),
            _column(_field(points, "number_of_returns"), "u1"),
            _column(_field(points, "scan_angle")),
            _column(_field(points, extra[0])), _column(_field(points, extra[1])),
            _column(_field(points, extra[2])), _column(_field(points, extra[3]), "u1"),
            FLAG_NOT_CORRECTED, offsets, scales, out["X"], out["Y"], out["Z"],
            out["intensity"], out["bit_fields"], out["classification_flags"],
            out["scan_angle"], out["point_source_id"], out["gps_time"], out[extra[0]],
            out[extra[1]], out[extra[2]], out[extra[3]])
        if clipped:
            if self.stats.clipped_intensity == 0:
                logger.warning("%s: intensities outside 0..65535 are clipped to the LAS range",
                               self.path)
            self.stats.clipped_intensity += clipped
        self.stats.withheld += withheld
        try:
            self._writer.write_points(rec)
        except Exception as exc:  # lazrs wraps a failed write in its own error type
            raise self._failure("cannot write", exc) from None
        self.stats.points += n
        return n


__all__ = [
    "ADJUSTED_GPS_OFFSET",
    "EXTRA_DIMENSIONS",
    "GPS_EPOCH_UNIX",
    "SCALE_M",
    "LasChunkWriter",
    "LasStats",
    "adjusted_gps_to_unix",
    "leap_seconds",
    "parse_crs",
    "unix_to_adjusted_gps",
]
