"""An import's strips: which points make up which flight line (docs/import.md, "Strips")."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from lidarcal_ros.errors import InputError
from lidarcal_ros.pipeline.importing.points import PointsRead
from lidarcal_ros.pipeline.importing.time_bases import TimeRule


@dataclass
class StripSummary:
    """One strip of the imported mission (times on the bag's clock, seconds).

    Attributes
    ----------
    strip_id : int
    source : str
        ``"point_source_id N"`` or ``"split at GPS-time gaps"``.
    n_points : int
    t_first, t_last : float
    files : set of str
        Names of the files holding its points.
    """

    strip_id: int
    source: str
    n_points: int = 0
    t_first: float = math.inf
    t_last: float = -math.inf
    files: set[str] = field(default_factory=set)


class StripMap:
    """Raw (point_source_id, raw time) -> strip id (docs/import.md, "Strips").

    Parameters
    ----------
    occupancy : dict of int to set of int
        Point source id -> the time bins holding its points.
    bin_s : float
        Time bin, seconds.
    gap_s : float
        Gap in time that separates strips without point source ids, seconds.
    """

    def __init__(self, occupancy: dict[int, set[int]], bin_s: float, gap_s: float) -> None:
        ids = sorted(occupancy)
        self.by_gap_all = len(ids) == 1
        self.labelled = set() if self.by_gap_all else {i for i in ids if i != 0}
        unl: set[int] = set()
        for i in ids:
            if i not in self.labelled:
                unl |= occupancy[i]
        bins = np.array(sorted(unl), dtype=np.int64)
        gap_bins = max(1, int(math.ceil(gap_s / bin_s)))
        if bins.size:
            cut = np.flatnonzero(np.diff(bins) > gap_bins) + 1
            starts = bins[np.concatenate(([0], cut))]
        else:
            starts = np.empty(0, dtype=np.int64)
        self.segment_starts = starts.astype(np.float64) * bin_s  # raw times
        first_new = (max(self.labelled) + 1) if self.labelled else 1
        if self.by_gap_all and ids[0] != 0 and starts.size == 1:
            first_new = ids[0]  # one strip with one id: keep it
        self.segment_ids = np.arange(first_new, first_new + starts.size, dtype=np.int64)
        if self.segment_ids.size and self.segment_ids[-1] > 65535:
            raise InputError(f"{self.segment_ids.size} strips split at GPS-time gaps do not fit "
                             "UINT16 strip ids; raise --strip-gap")
        self.bin_s = bin_s

    def source_of(self, strip_id: int) -> str:
        """Where the strip comes from, in words (:attr:`StripSummary.source`)."""
        if strip_id in self.labelled or (self.by_gap_all and self.segment_ids.size == 1
                                         and strip_id == self.segment_ids[0] != 1):
            return f"point_source_id {strip_id}"
        return "split at GPS-time gaps"

    def map(self, psid: np.ndarray, t_raw: np.ndarray) -> np.ndarray:
        """Strip ids of points (their point source ids and raw times, seconds)."""
        out = psid.astype(np.int64)
        unl = np.ones(psid.shape, dtype=bool) if self.by_gap_all else psid == 0
        if unl.any():
            k = np.searchsorted(self.segment_starts, t_raw[unl], side="right") - 1
            out[unl] = self.segment_ids[np.clip(k, 0, self.segment_ids.size - 1)]
        return out


@dataclass
class StripAssembly:
    """The strips of an import before the bag is written.

    Attributes
    ----------
    map : StripMap
    summaries : dict of int to StripSummary
        Strip id -> summary; files and source known, counts and spans filled in while the
        bag is written.
    raw_spans : dict of int to (float, float)
        Strip id -> first and last raw time of its points, seconds, to the read pass's time
        bin (``gap_bin``) where the strip is split at gaps, else exact.
    gap_bin : float
        That time bin, seconds.
    split_at_gaps : bool
        Some strips come from gaps in time (not all from point source ids).
    """

    map: StripMap
    summaries: dict[int, StripSummary]
    raw_spans: dict[int, tuple[float, float]]
    gap_bin: float
    split_at_gaps: bool

    def spans(self, rule: TimeRule) -> dict[int, tuple[float, float]]:
        """Strip id -> first and last time on the bag's clock, seconds."""
        out = {}
        for sid, (lo, hi) in self.raw_spans.items():
            a, b = rule.points(np.array([lo, hi]))
            out[sid] = (float(a), float(b))
        return out

    def surely_inside(self, rule: TimeRule) -> list[StripSummary]:
        """Per strip, a span on the bag's clock its points surely reach (those split at gaps
        known to their time bin, shrunk by one bin): a trajectory must cover these."""
        inner = []
        for sid, (lo, hi) in self.raw_spans.items():
            exact = sid in self.map.labelled or not self.split_at_gaps
            pad = 0.0 if exact else self.gap_bin
            a, b = rule.points(np.array([lo + pad, max(lo + pad, hi - pad)]))
            inner.append(StripSummary(sid, "", 1, float(a), float(b)))
        return inner

    def leave_out(self, strip_ids: list[int]) -> None:
        """Drop strips (no trajectory for them): their points are not written."""
        for sid in strip_ids:
            self.summaries.pop(sid, None)


def assemble_strips(read: PointsRead, strip_gap_s: float) -> StripAssembly:
    """The strips of the points read (docs/import.md, "Strips")."""
    strip_map = StripMap(read.occupancy, read.gap_bin, strip_gap_s)
    summaries: dict[int, StripSummary] = {}
    for psid, source in read.sources.items():
        if strip_map.by_gap_all or psid == 0:  # every gap segment inside its span
            k0 = int(np.searchsorted(strip_map.segment_starts, source.t_first, side="right")) - 1
            k1 = int(np.searchsorted(strip_map.segment_starts, source.t_last, side="right")) - 1
            seg_ids = strip_map.segment_ids[max(k0, 0):k1 + 1].tolist()
        else:
            seg_ids = [psid]
        for sid in seg_ids:
            summary = summaries.setdefault(sid, StripSummary(sid, strip_map.source_of(sid)))
            summary.files |= source.files
    raw_spans: dict[int, tuple[float, float]] = {}
    gap_bin = read.gap_bin
    for psid, bins in read.occupancy.items():
        b = np.array(sorted(bins), dtype=np.float64)
        t_lo_b = b * gap_bin
        ids = strip_map.map(np.full(b.size, psid, dtype=np.uint16), t_lo_b + 0.5 * gap_bin)
        source = read.sources[psid]
        for sid in np.unique(ids):
            sel = ids == sid
            lo = max(float(t_lo_b[sel].min()), source.t_first)
            hi = min(float(t_lo_b[sel].max() + gap_bin), source.t_last)
            old_lo, old_hi = raw_spans.get(int(sid), (math.inf, -math.inf))
            raw_spans[int(sid)] = (min(old_lo, lo), max(old_hi, hi))
    return StripAssembly(strip_map, summaries, raw_spans, gap_bin,
                         split_at_gaps=strip_map.by_gap_all or 0 in read.sources)


__all__ = ["StripAssembly", "StripMap", "StripSummary", "assemble_strips"]
