"""Control points as CSV: ``id,x,y,z`` with a header line, map frame, metres."""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from lidarcal_ros.core.mission import ControlPoints
from lidarcal_ros.errors import InputError
from lidarcal_ros.io.output_files import write_text

logger = logging.getLogger(__name__)

COLUMNS: tuple[str, ...] = ("id", "x", "y", "z")
#: Larger coordinates are no map coordinates (metres; UTM northings reach 1e7).
MAX_COORDINATE_M = 1e8


#: Most control points a file may hold: control fixes a datum with tens to thousands of
#: points; beyond this it is a surface, and every iteration would match all of it.
MAX_CONTROL_POINTS = 100_000


def read_control_csv(path: str | os.PathLike[str]) -> ControlPoints:
    """Read control points.

    Parameters
    ----------
    path : path-like
        CSV file whose first non-blank line is a header naming ``id, x, y, z`` (any order,
        case-insensitive, further columns ignored); blank lines and lines starting with ``#``
        are skipped; whitespace around values is ignored.

    Returns
    -------
    ControlPoints
        Ids as strings, coordinates (n, 3) float64 in the map frame, metres.

    Raises
    ------
    InputError
        Missing or unreadable file, missing columns, a non-numeric, non-finite or
        implausibly large value (with its line number), a duplicate id, or no rows.
    """
    p = Path(path)
    try:
        with open(p, encoding="utf-8-sig", newline=None) as stream:
            return _read_rows(p, stream)
    except FileNotFoundError:
        raise InputError(f"{p}: control point file not found") from None
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(f"{p}: cannot read control point file ({err})") from None


def _read_rows(p: Path, stream: Iterable[str]) -> ControlPoints:
    """The control points of the lines of an open file, read one at a time: a file of more
    than :data:`MAX_CONTROL_POINTS` rows is counted, not held (a million rows: some 30 MB
    of text, 450 MB as a list of lines)."""
    lines = ((no, line) for no, line in enumerate(stream, start=1)
             if line.strip() and not line.lstrip().startswith("#"))
    first = next(lines, None)
    if first is None:
        raise InputError(f"{p}: empty control point file (expected header id,x,y,z)")
    header_no, header = first
    names = [c.strip().lower() for c in header.split(",")]
    missing = [c for c in COLUMNS if c not in names]
    if missing:
        raise InputError(
            f"{p}: line {header_no}: header lacks column(s) {', '.join(missing)} "
            f"(found: {header.strip()})"
        )
    col = {c: names.index(c) for c in COLUMNS}
    ids: list[str] = []
    seen: set[str] = set()
    xyz: list[tuple[float, float, float]] = []
    for no, line in lines:
        if len(ids) == MAX_CONTROL_POINTS:
            rows = len(ids) + 1 + sum(1 for _ in lines)
            raise InputError(f"{p}: {rows:,} control points; at most "
                             f"{MAX_CONTROL_POINTS:,} are taken (thin the file, or give check "
                             "points to lidarcal evaluate)")
        cells = [c.strip() for c in line.split(",")]
        if len(cells) < len(names):
            raise InputError(
                f"{p}: line {no}: {len(cells)} values, expected {len(names)}"
            )
        pid = cells[col["id"]]
        if not pid:
            raise InputError(f"{p}: line {no}: empty id")
        if pid in seen:
            raise InputError(f"{p}: line {no}: duplicate id '{pid}'")
        seen.add(pid)
        coords = []
        for c in ("x", "y", "z"):
            value = cells[col[c]]
            try:
                v = float(value)
            except ValueError:
                raise InputError(
                    f"{p}: line {no}: {c} value '{value}' is not a number"
                ) from None
            if not math.isfinite(v):
                raise InputError(f"{p}: line {no}: {c} value '{value}' is not finite")
            if abs(v) > MAX_COORDINATE_M:
                raise InputError(f"{p}: line {no}: {c} value '{value}' is not a map "
                                 f"coordinate (|{c}| > {MAX_COORDINATE_M:g} m)")
            coords.append(v)
        ids.append(pid)
        xyz.append((coords[0], coords[1], coords[2]))
    if not ids:
        raise InputError(f"{p}: no control points after the header line")
    logger.debug("%s: read %d control points", p, len(ids))
    return ControlPoints(ids, np.asarray(xyz, dtype=np.float64).reshape(-1, 3))


def write_control_csv(path: str | os.PathLike[str], control: ControlPoints) -> None:
    """Write control points as ``id,x,y,z`` with a header line.

    Coordinates are written with ``repr`` precision, so reading back gives identical
    float64 values.

    Raises
    ------
    InputError
        Ids and coordinates disagree in number, or an id contains a comma or newline.
    OutputError
        The file cannot be written.
    """
    p = Path(path)
    xyz = np.asarray(control.xyz, dtype=np.float64).reshape(-1, 3)
    if len(control.ids) != len(xyz):
        raise InputError(
            f"{p}: {len(control.ids)} control ids but {len(xyz)} coordinates"
        )
    rows = ["id,x,y,z"]
    for pid, (x, y, z) in zip(control.ids, xyz, strict=True):
        if any(ch in str(pid) for ch in ",\n\r"):
            raise InputError(f"{p}: control id {pid!r} contains a comma or newline")
        rows.append(f"{pid},{float(x)!r},{float(y)!r},{float(z)!r}")
    write_text(p, "\n".join(rows) + "\n", what="control point file")


__all__ = ["COLUMNS", "MAX_COORDINATE_M", "read_control_csv", "write_control_csv"]
