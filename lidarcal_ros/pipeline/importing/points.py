"""An import's points: the LAS headers' CRS and units, the read pass, the time-sorted runs.

Coordinates are converted to metres on reading; past ``memory_points`` the runs are spilled to
files beside the output (docs/import.md, "Memory").
"""

from __future__ import annotations

import logging
import math
import shutil
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lidarcal_ros.core.trajectory.rays import RayCollector, rays_from_returns
from lidarcal_ros.errors import InputError
from lidarcal_ros.io.survey.las_reader import (
    GpsTimeType,
    LasChunk,
    LasFileInfo,
    crs_units,
    iter_las_chunks,
)
from lidarcal_ros.pipeline.importing.options import ImportOptions, Returns

logger = logging.getLogger(__name__)

#: ``(stage, fraction done)`` callback.
Progress = Callable[[str, float], None]

#: Point layout of the bag (aligned, little-endian).
POINT_DTYPE = np.dtype(
    [("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("t", "<f8"), ("intensity", "<f4"),
     ("strip_id", "<u2"), ("return_number", "u1"), ("number_of_returns", "u1"),
     ("classification", "u1")],
    align=True,
)
#: Longest time bin of the strip occupancy, seconds (a quarter of the strip gap if shorter).
_GAP_BIN_MAX_S = 0.5


# ---------------------------------------------------------------------------- headers
def header_time_base(infos: list[LasFileInfo]) -> GpsTimeType:
    """The GPS time type all the files share.

    Raises
    ------
    InputError
        The files mix both.
    """
    bases = {i.gps_time_type for i in infos}
    if len(bases) > 1:
        adj = next(i.path for i in infos if i.gps_time_type is GpsTimeType.ADJUSTED)
        week = next(i.path for i in infos if i.gps_time_type is GpsTimeType.WEEK)
        raise InputError(f"{week}: GPS week time, but {adj} holds adjusted standard GPS time; "
                         "import them separately or convert one")
    return bases.pop()


@dataclass(frozen=True)
class PointsFrame:
    """The points' map frame: their CRS and the factors that take them to metres.

    Attributes
    ----------
    crs : pyproj.CRS or None
        None: unknown (no CRS in the headers, none given).
    unit_factors : (float, float)
        Factors of the horizontal coordinates and of the heights to metres.
    """

    crs: Any
    unit_factors: tuple[float, float]

    @property
    def name(self) -> str:
        """The CRS's name, or what its absence means."""
        return self.crs.name if self.crs is not None else "unknown (coordinates as stored)"


def points_frame(infos: list[LasFileInfo], crs: str | None) -> PointsFrame:
    """The points' CRS (``crs`` or the headers') and their units ((1, 1) without a CRS).

    Raises
    ------
    InputError
        The headers' CRSs differ (without ``crs``), or the CRS is not projected.
    """
    points_crs = _resolve_crs(infos, crs)
    if points_crs is not None and not points_crs.is_projected and not (
            points_crs.is_compound and points_crs.sub_crs_list[0].is_projected):
        where = crs or str(next(i.path for i in infos if i.crs is not None))
        raise InputError(f"{where}: CRS '{points_crs.name}' is not projected; lidarcal needs "
                         "a projected map frame in metres (reproject the points, or --crs)")
    factors = crs_units(points_crs) if points_crs is not None else (1.0, 1.0)
    if factors != (1.0, 1.0):
        logger.warning("coordinates in %s are converted to metres (x%g, heights x%g)",
                       points_crs.name, factors[0], factors[1])
    return PointsFrame(points_crs, factors)


def _resolve_crs(infos: list[LasFileInfo], crs: str | None) -> Any:
    from lidarcal_ros.io.survey.las_writer import parse_crs

    if crs:
        return parse_crs(crs)
    found = [(i.path, i.crs) for i in infos if i.crs is not None]
    if not found:
        return None
    first_path, first = found[0]
    for path, other in found[1:]:
        if not other.equals(first, ignore_axis_order=True):
            raise InputError(f"{path}: CRS '{other.name}' differs from '{first.name}' of "
                             f"{first_path}; give --crs to choose")
    return first


# ---------------------------------------------------------------------------- spilling
class RunStore:
    """Points buffered in memory, spilled as time-sorted runs past a limit.

    Parameters
    ----------
    limit : int
        Points buffered before a run is spilled (at least 1000).
    directory : Path
        Where the runs' temporary directory is made (beside the output).
    """

    def __init__(self, limit: int, directory: Path) -> None:
        self.limit = max(1000, int(limit))
        self.directory = directory
        self._buffer: list[np.ndarray] = []
        self._buffered = 0
        self.runs: list[Path] = []
        self._tmp: Path | None = None
        self._also: list[Path] = []

    def also_remove(self, folder: Path) -> None:
        """Remove ``folder`` (runs other stores spill there) with this store's runs."""
        self._also.append(folder)

    def add(self, points: np.ndarray) -> None:
        """Buffer :data:`POINT_DTYPE` rows (spilling a sorted run when the buffer is full)."""
        if not len(points):
            return
        self._buffer.append(points)
        self._buffered += len(points)
        if self._buffered >= self.limit:
            self._spill()

    def _sorted_buffer(self) -> np.ndarray:
        arr = np.concatenate(self._buffer) if self._buffer else np.empty(0, POINT_DTYPE)
        self._buffer, self._buffered = [], 0
        return arr[np.argsort(arr["t"], kind="stable")]

    def _spill(self) -> None:
        if self._tmp is None:
            self._tmp = Path(tempfile.mkdtemp(prefix=".lidarcal-import-", dir=self.directory))
        path = self._tmp / f"run{len(self.runs):05d}.npy"
        try:
            np.save(path, self._sorted_buffer())
        except OSError as exc:
            raise InputError(f"{path}: cannot spill points ({exc.strerror or exc})") from None
        self.runs.append(path)

    def spill_all(self) -> None:
        """Spill what is buffered too: every point is then in :attr:`runs`."""
        if self._buffered:
            self._spill()

    def adopt(self, runs: list[Path]) -> None:
        """Take ``runs`` spilled by another store (points read after this one's), in order,
        after this one's spilled so far; whoever made them removes them."""
        self.spill_all()
        self.runs.extend(runs)

    def sources(self) -> list[np.ndarray]:
        """The sorted runs (memory-mapped) and the sorted in-memory rest."""
        rest = self._sorted_buffer()
        out = [np.load(p, mmap_mode="r") for p in self.runs]
        if len(rest):
            out.append(rest)
        return out

    def cleanup(self) -> None:
        """Remove the spilled runs."""
        for folder in [self._tmp, *self._also] if self._tmp is not None else self._also:
            shutil.rmtree(folder, ignore_errors=True)
        self._tmp, self._also = None, []


def merged_windows(
    sources: list[np.ndarray], t_start: float, step: float, limit: int
) -> Iterator[np.ndarray]:
    """Points of time-sorted ``sources`` in time order, in windows of whole ``step`` cells
    from ``t_start`` holding about ``limit`` points (at least one cell)."""
    pos = [0] * len(sources)
    times = [s["t"] for s in sources]
    ends = [len(s) for s in sources]
    while True:
        live = [i for i in range(len(sources)) if pos[i] < ends[i]]
        if not live:
            return
        t_min = min(float(times[i][pos[i]]) for i in live)
        t_max = max(float(times[i][ends[i] - 1]) for i in live)
        k0 = math.floor((t_min - t_start) / step)
        k_last = math.floor((t_max - t_start) / step)

        def count(k: int, live: list[int] = live) -> int:
            edge = t_start + (k + 1) * step
            return sum(int(np.searchsorted(times[i], edge, side="left")) - pos[i] for i in live)

        lo, hi = k0, k_last
        if count(hi) > limit:
            while lo < hi:  # largest k with count(k) <= limit, at least k0
                mid = (lo + hi + 1) // 2
                if count(mid) <= limit:
                    lo = mid
                else:
                    hi = mid - 1
            k = lo
        else:
            k = k_last
        edge = t_start + (k + 1) * step
        parts = []
        for i in live:
            stop = int(np.searchsorted(times[i], edge, side="left")) if k < k_last else ends[i]
            if stop > pos[i]:
                parts.append(np.asarray(sources[i][pos[i]:stop]))
                pos[i] = stop
        if not parts:
            continue
        window = np.concatenate(parts) if len(parts) > 1 else parts[0].copy()
        yield window[np.argsort(window["t"], kind="stable")]


# ---------------------------------------------------------------------------- the read pass
@dataclass
class SourceSpan:
    """The points of one ``point_source_id`` as read (raw GPS times, seconds)."""

    count: int = 0
    t_first: float = math.inf
    t_last: float = -math.inf
    files: set[str] = field(default_factory=set)


@dataclass
class PointsRead:
    """What the read pass gathered.

    Attributes
    ----------
    infos : list of LasFileInfo
        The files, in the order read.
    store : RunStore
        The points kept, :data:`POINT_DTYPE`, coordinates in metres, raw times.
    frame : PointsFrame
        Their CRS and the factors applied to reach metres.
    gap_bin : float
        Time bin of ``occupancy``, seconds.
    occupancy : dict of int to set of int
        Point source id -> the time bins (raw time // ``gap_bin``) holding its points.
    sources : dict of int to SourceSpan
        Point source id -> its points' count, span and files.
    rays : RayCollector or None
        Rays of multi-return pulses, for a trajectory estimate (else None).
    n_read, n_kept : int
        Points read, and kept for the bag (``returns``).
    returns_seen : (int, int)
        First and last returns of multi-return pulses read (while collecting rays).
    """

    infos: list[LasFileInfo]
    store: RunStore
    frame: PointsFrame
    gap_bin: float
    occupancy: dict[int, set[int]] = field(default_factory=dict)
    sources: dict[int, SourceSpan] = field(default_factory=dict)
    rays: RayCollector | None = None
    n_read: int = 0
    n_kept: int = 0
    returns_seen: tuple[int, int] = (0, 0)

    @property
    def time_range(self) -> tuple[float, float]:
        """First and last raw point time, seconds."""
        return (min(s.t_first for s in self.sources.values()),
                max(s.t_last for s in self.sources.values()))

    @property
    def where(self) -> str:
        """The files, for messages: the first, and how many more."""
        paths = [i.path for i in self.infos]
        return str(paths[0]) if len(paths) == 1 else f"{paths[0]} (and {len(paths) - 1} more)"


def read_points(infos: list[LasFileInfo], store: RunStore, frame: PointsFrame,
                options: ImportOptions, progress: Progress) -> PointsRead:
    """Read every point once into ``store`` and gather :class:`PointsRead` (docs/import.md).

    Raises
    ------
    InputError
        A non-finite GPS time, or no point to import.
    """
    read = new_read(infos, store, frame, options)
    total = sum(i.point_count for i in infos)
    for info in infos:
        if info.point_count == 0 and len(infos) > 1:
            logger.warning("%s: no points", info.path)
        read_file(read, info, options, lambda n: progress("reading", n / max(total, 1)))
    check_points_read(read, options)
    return read


def new_read(infos: list[LasFileInfo], store: RunStore, frame: PointsFrame,
             options: ImportOptions) -> PointsRead:
    """An empty :class:`PointsRead` of ``infos`` into ``store``, as ``options`` gather it."""
    return PointsRead(infos, store, frame,
                      gap_bin=min(_GAP_BIN_MAX_S, options.strip_gap_s / 4.0),
                      rays=RayCollector(options.ray_budget)
                      if options.estimates_trajectory else None)


def read_file(read: PointsRead, info: LasFileInfo, options: ImportOptions,
              progress: Callable[[int], None]) -> None:
    """Read every point of one file into ``read`` (its store, counts, sources, rays);
    ``progress(points read so far)`` after each chunk.

    Raises
    ------
    InputError
        A non-finite GPS time.
    """
    hfac, vfac = read.frame.unit_factors
    scale = np.array([hfac, hfac, vfac])
    for chunk in iter_las_chunks(info.path, chunk_points=options.chunk_points):
        xyz = chunk.xyz * scale
        if not np.isfinite(chunk.gps_time).all():
            raise InputError(f"{info.path}: non-finite GPS time")
        read.n_read += len(chunk)
        if read.rays is not None:
            _collect_rays(read, chunk, xyz)
        _note_sources(read, chunk, info.path.name)
        keep = _returns_kept(chunk, options.returns)
        read.store.add(_bag_rows(chunk, xyz, keep))
        read.n_kept += int(keep.sum())
        progress(read.n_read)


def merge_read(read: PointsRead, part: PointsRead) -> None:
    """Add ``part`` (the read of later files, its store's runs all spilled) to ``read``: as
    if ``read`` had read them (the runs adopted, the rays offered in the order read)."""
    read.store.adopt(part.store.runs)
    read.n_read += part.n_read
    read.n_kept += part.n_kept
    read.returns_seen = (read.returns_seen[0] + part.returns_seen[0],
                         read.returns_seen[1] + part.returns_seen[1])
    for value, span in part.sources.items():
        mine = read.sources.setdefault(value, SourceSpan())
        mine.count += span.count
        mine.t_first = min(mine.t_first, span.t_first)
        mine.t_last = max(mine.t_last, span.t_last)
        mine.files |= span.files
    for value, bins in part.occupancy.items():
        read.occupancy.setdefault(value, set()).update(bins)
    if read.rays is not None and part.rays is not None:
        read.rays.merge(part.rays)


def check_points_read(read: PointsRead, options: ImportOptions) -> None:
    """Refuse a read without a point to import."""
    if read.n_kept == 0:
        paths = [i.path for i in read.infos]
        raise InputError(f"{read.where}: no points to import (--returns {options.returns})"
                         if read.n_read else f"{read.where}: no points in the "
                         f"{'file' if len(paths) == 1 else 'files'}")


def _collect_rays(read: PointsRead, chunk: LasChunk, xyz: np.ndarray) -> None:
    """Offer the chunk's rays to the collector; count first and last returns of multi-return
    pulses (to say why no ray was found)."""
    assert read.rays is not None
    read.rays.add(rays_from_returns(xyz, chunk.gps_time, chunk.point_source_id,
                                    chunk.return_number, chunk.number_of_returns))
    multi = chunk.number_of_returns >= 2
    first, last = read.returns_seen
    read.returns_seen = (
        first + int(np.count_nonzero(multi & (chunk.return_number == 1))),
        last + int(np.count_nonzero(multi & (chunk.return_number == chunk.number_of_returns))))


def _note_sources(read: PointsRead, chunk: LasChunk, file_name: str) -> None:
    """Count, span, file and time bins of each point source id in the chunk."""
    psid, t = chunk.point_source_id, chunk.gps_time
    for value in np.unique(psid):
        sel = psid == value
        ts = t[sel]
        span = read.sources.setdefault(int(value), SourceSpan())
        span.count += int(sel.sum())
        span.t_first = min(span.t_first, float(ts.min()))
        span.t_last = max(span.t_last, float(ts.max()))
        span.files.add(file_name)
        read.occupancy.setdefault(int(value), set()).update(
            np.unique(np.floor(ts / read.gap_bin).astype(np.int64)).tolist())


def _returns_kept(chunk: LasChunk, returns: Returns) -> np.ndarray:
    """Which points of the chunk the bag gets."""
    rn = chunk.return_number.astype(np.int16)
    nr = chunk.number_of_returns.astype(np.int16)
    if returns is Returns.FIRST:
        return rn <= 1
    if returns is Returns.LAST:
        return (rn >= nr) | (nr <= 1)
    return np.ones(len(chunk), dtype=bool)


def _bag_rows(chunk: LasChunk, xyz: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """The kept points as :data:`POINT_DTYPE` rows (raw times, point source id as strip)."""
    pts = np.empty(int(keep.sum()), dtype=POINT_DTYPE)
    pts["x"], pts["y"], pts["z"] = xyz[keep, 0], xyz[keep, 1], xyz[keep, 2]
    pts["t"] = chunk.gps_time[keep]
    pts["intensity"] = chunk.intensity[keep]
    pts["strip_id"] = chunk.point_source_id[keep]
    pts["return_number"] = chunk.return_number[keep]
    pts["number_of_returns"] = chunk.number_of_returns[keep]
    pts["classification"] = chunk.classification[keep]
    return pts


__all__ = ["POINT_DTYPE", "PointsFrame", "PointsRead", "Progress", "RunStore", "SourceSpan",
           "check_points_read", "header_time_base", "merge_read", "merged_windows", "new_read",
           "points_frame", "read_file", "read_points"]
