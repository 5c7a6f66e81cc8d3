"""Reading LAS 1.0-1.4 and LAZ flight lines, chunk by chunk (laspy with the lazrs backend).

Coordinates are returned as stored, in the file's CRS and linear unit (:func:`crs_units` gives
the factors to metres); GPS times raw, in the base the header names (docs/import.md).
"""

from __future__ import annotations

import datetime
import enum
import logging
import os
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lidarcal_ros.errors import InputError, one_line
from lidarcal_ros.io.url_cache import local_source

logger = logging.getLogger(__name__)


def _not_an_error(record: logging.LogRecord) -> bool:
    return record.levelno < logging.ERROR


def quiet_laspy_errors(module: str) -> None:
    """Drop the ERROR records of a laspy module: laspy logs a LAZ failure and then raises
    it, and lidarcal reports what it raises in one line of its own (warnings pass)."""
    logger_ = logging.getLogger(module)
    if _not_an_error not in logger_.filters:
        logger_.addFilter(_not_an_error)


quiet_laspy_errors("laspy.lasreader")

#: Points decoded per chunk (about 60 MB of columns).
CHUNK_POINTS = 1_000_000


class GpsTimeType(enum.StrEnum):
    """What a LAS header's GPS times count: its global-encoding bit 0."""

    #: Bit 0 clear: GPS seconds of the week.
    WEEK = "week"
    #: Bit 0 set: Adjusted Standard GPS Time (GPS seconds since the GPS epoch minus 1e9).
    ADJUSTED = "adjusted"


class LasFileError(InputError):
    """A LAS/LAZ file is missing, unreadable, corrupt or lacks what lidarcal needs."""


@dataclass
class LasFileInfo:
    """Header facts of one LAS/LAZ file.

    Attributes
    ----------
    path : Path
    version : str
        ``"1.2"``, ``"1.4"``, ...
    point_format : int
    point_count : int
    compressed : bool
        LAZ.
    gps_time_type : GpsTimeType
        Global encoding bit 0: clear = GPS week seconds, set = Adjusted Standard GPS Time.
    creation_date : datetime.date or None
        Header creation date (processing date, usually on or after the flight).
    crs : pyproj.CRS or None
        From the WKT or GeoTIFF VLRs.
    mins, maxs : (3,) float64
        Header bounds, file units.
    """

    path: Path
    version: str
    point_format: int
    point_count: int
    compressed: bool
    gps_time_type: GpsTimeType
    creation_date: datetime.date | None
    crs: Any
    mins: np.ndarray
    maxs: np.ndarray


@dataclass
class LasChunk:
    """Columns of consecutive points of one file (all (n,) unless stated).

    Attributes
    ----------
    xyz : (n, 3) float64
        Coordinates in the file's CRS and units.
    gps_time : float64
        Raw GPS time (see :attr:`LasFileInfo.gps_time_type`), seconds.
    intensity : uint16
    point_source_id : uint16
    return_number, number_of_returns, classification : uint8
    """

    xyz: np.ndarray
    gps_time: np.ndarray
    intensity: np.ndarray
    point_source_id: np.ndarray
    return_number: np.ndarray
    number_of_returns: np.ndarray
    classification: np.ndarray

    def __len__(self) -> int:
        return int(self.gps_time.shape[0])

    def take(self, index: np.ndarray) -> LasChunk:
        """A subset of the points (boolean or fancy index)."""
        return LasChunk(self.xyz[index], self.gps_time[index], self.intensity[index],
                        self.point_source_id[index], self.return_number[index],
                        self.number_of_returns[index], self.classification[index])


#: Smallest VLR and EVLR (their headers), bytes.
_VLR_BYTES, _EVLR_BYTES = 54, 60


def _check_path(path: Path) -> None:
    if not path.exists():
        raise LasFileError(f"{path}: LAS/LAZ file not found")
    if path.is_dir():
        raise LasFileError(f"{path}: is a directory, not a LAS/LAZ file")
    _check_counts(path)


def _check_counts(path: Path) -> None:
    """Refuse a header whose counts of VLRs, EVLRs or (uncompressed) points claim more than
    the file holds, before laspy loops over them (4,294,967,295 VLRs took minutes) or
    streams a point count the file cannot hold. Files that are not LAS are left to laspy."""
    try:
        with path.open("rb") as f:
            head = f.read(375)
            size = os.fstat(f.fileno()).st_size
    except OSError as exc:
        raise LasFileError(f"{path}: cannot read ({exc.strerror or one_line(exc)})") from None
    if len(head) < 227 or head[:4] != b"LASF":
        return
    minor = head[25]
    header_size, points_at, vlrs = struct.unpack_from("<HII", head, 94)
    record_format, record_bytes, legacy_count = struct.unpack_from("<BHI", head, 104)
    if points_at > size:
        raise LasFileError(f"{path}: the header places the points at byte {points_at}, beyond "
                           f"the file's {size} bytes (truncated?)")
    room = points_at - header_size
    if vlrs * _VLR_BYTES > max(room, 0):
        raise LasFileError(f"{path}: the header claims {vlrs} VLRs; the {max(room, 0)} bytes "
                           f"between the header and the points hold at most "
                           f"{max(room, 0) // _VLR_BYTES}; refused")
    count = legacy_count
    if minor >= 4 and len(head) >= 255:
        evlr_at, evlrs, count = struct.unpack_from("<QIQ", head, 235)
        if evlrs and (evlr_at > size or evlrs * _EVLR_BYTES > size - evlr_at):
            raise LasFileError(f"{path}: the header claims {evlrs} extended VLRs from byte "
                               f"{evlr_at}; the file's {size} bytes hold at most "
                               f"{max(size - evlr_at, 0) // _EVLR_BYTES}; refused")
    compressed = bool(record_format & 0xC0)  # LAZ sets bit 7 (some writers bit 6)
    if not compressed and count * record_bytes > size - points_at:
        raise LasFileError(f"{path}: truncated: the header claims {count} points of "
                           f"{record_bytes} bytes, the file holds {size - points_at} bytes of "
                           f"points ({(size - points_at) // max(record_bytes, 1)} points)")


def inspect_las(path: str | os.PathLike[str]) -> LasFileInfo:
    """Read and check the header of a LAS/LAZ file.

    Raises
    ------
    LasFileError
        Missing or unreadable file, not LAS, scale factors that are zero or not finite, offsets
        that are not finite, no GPS time in its point format.
    """
    import laspy

    p = local_source(path, what="LAS file")
    _check_path(p)
    try:
        with laspy.open(str(p)) as reader:
            header = reader.header
            compressed = bool(header.are_points_compressed)
    except OSError as exc:
        raise LasFileError(f"{p}: cannot read ({exc.strerror or one_line(exc)})") from None
    except Exception as exc:  # laspy/lazrs raise various types for a bad header
        raise LasFileError(f"{p}: not a readable LAS/LAZ file ({one_line(exc)})") from None
    scales = np.asarray(header.scales, dtype=np.float64)
    offsets = np.asarray(header.offsets, dtype=np.float64)
    if not (np.isfinite(scales).all() and (scales != 0).all() and np.isfinite(offsets).all()):
        raise LasFileError(
            f"{p}: header scale factors {scales.tolist()} and offsets {offsets.tolist()} do "
            "not give coordinates (scales must be non-zero, both finite)"
        )
    dims = set(header.point_format.dimension_names)
    if "gps_time" not in dims:
        raise LasFileError(
            f"{p}: point format {header.point_format.id} has no GPS time; lidarcal needs "
            "the firing time of every point (point formats 1, 3-10)"
        )
    crs = None
    try:
        crs = header.parse_crs()
    except Exception as exc:  # a malformed CRS VLR: usable with --crs
        logger.warning("%s: cannot parse the CRS VLR (%s)", p, one_line(exc))
    encoding = header.global_encoding.gps_time_type
    gps_type = GpsTimeType.ADJUSTED if int(encoding) == 1 else GpsTimeType.WEEK
    return LasFileInfo(
        path=p,
        version=f"{header.version.major}.{header.version.minor}",
        point_format=int(header.point_format.id),
        point_count=int(header.point_count),
        compressed=compressed,
        gps_time_type=gps_type,
        creation_date=header.creation_date,
        crs=crs,
        mins=np.asarray(header.mins, dtype=np.float64),
        maxs=np.asarray(header.maxs, dtype=np.float64),
    )


def iter_las_chunks(
    path: str | os.PathLike[str], *, chunk_points: int = CHUNK_POINTS
) -> Iterator[LasChunk]:
    """Stream the points of a LAS/LAZ file.

    Parameters
    ----------
    path : path-like
    chunk_points : int, keyword-only
        Points per chunk; memory is bounded by it, whatever the file's size.

    Yields
    ------
    LasChunk

    Raises
    ------
    LasFileError
        Unreadable, corrupt or truncated point data (names the file and the point reached),
        or a point format without GPS time.
    """
    import laspy

    p = local_source(path, what="LAS file")
    _check_path(p)
    done = 0
    expected = -1
    try:
        with laspy.open(str(p)) as reader:
            header = reader.header
            expected = int(header.point_count)
            if "gps_time" not in set(header.point_format.dimension_names):
                raise LasFileError(f"{p}: point format {header.point_format.id} has no GPS time")
            for pts in reader.chunk_iterator(max(1, int(chunk_points))):
                n = len(pts)
                if n == 0:
                    break
                xyz = np.empty((n, 3), dtype=np.float64)
                xyz[:, 0] = pts.x
                xyz[:, 1] = pts.y
                xyz[:, 2] = pts.z
                chunk = LasChunk(
                    xyz=xyz,
                    gps_time=np.array(pts.gps_time, dtype=np.float64),
                    intensity=np.array(pts.intensity, dtype=np.uint16),
                    point_source_id=np.array(pts.point_source_id, dtype=np.uint16),
                    return_number=np.array(pts.return_number, dtype=np.uint8),
                    number_of_returns=np.array(pts.number_of_returns, dtype=np.uint8),
                    classification=np.array(pts.classification, dtype=np.uint8),
                )
                done += n
                yield chunk
    except LasFileError:
        raise
    except OSError as exc:
        raise LasFileError(
            f"{p}: cannot read point data after {done} points ({exc.strerror or one_line(exc)})"
        ) from None
    except Exception as exc:  # lazrs / laspy decoding errors: corrupt or truncated data
        raise LasFileError(
            f"{p}: corrupt or truncated point data after {done} of {expected} points "
            f"({one_line(exc)})"
        ) from None
    if expected >= 0 and done != expected:
        raise LasFileError(f"{p}: truncated: header says {expected} points, read {done}")


def crs_units(crs: Any) -> tuple[float, float]:
    """Factors from a projected CRS's horizontal and vertical units to metres.

    The vertical factor comes from the vertical axis of a compound (or 3-D) CRS; for a 2-D
    CRS the heights are taken to be in the horizontal unit (the ASPRS convention when no
    vertical CRS is declared).
    """
    horizontal = crs
    vertical = None
    if crs.is_compound:
        subs = crs.sub_crs_list
        horizontal = subs[0]
        vertical = subs[1] if len(subs) > 1 else None
    axes = horizontal.axis_info
    hfac = float(axes[0].unit_conversion_factor) if axes else 1.0
    vfac = hfac
    if vertical is not None and vertical.axis_info:
        vfac = float(vertical.axis_info[0].unit_conversion_factor)
    elif len(axes) >= 3:
        vfac = float(axes[2].unit_conversion_factor)
    return hfac, vfac


__all__ = ["CHUNK_POINTS", "GpsTimeType", "LasChunk", "LasFileError", "LasFileInfo", "crs_units",
           "inspect_las", "iter_las_chunks", "quiet_laspy_errors"]
