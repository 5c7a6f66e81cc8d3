"""The strips of a calibration and the overlapping pairs they form (docs/method.md section 5).

Footprints are sparse square cells keyed in absolute map coordinates, so that strips arriving
one by one share one grid.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from lidarcal_ros.core.adjustment.least_squares import Observations
from lidarcal_ros.core.calibration.tin import PatchMatches, Tin
from lidarcal_ros.core.georeferencing.laser_geometry import LaserGeometry
from lidarcal_ros.core.georeferencing.rigorous import LaserVectorQA, ModelChoice
from lidarcal_ros.core.mission import Strip, Trajectory
from lidarcal_ros.core.qa.overlap_grid import OverlapGrid, PairQA


def footprint_keys(xy: np.ndarray, cell: float) -> np.ndarray:
    """Key (int64) of the square ``cell``-metre cell holding each map position (columns x, y;
    further columns ignored), absolute in the map frame so that any two strips share one
    grid."""
    ix = np.floor(xy[:, 0] / cell).astype(np.int64)
    iy = np.floor(xy[:, 1] / cell).astype(np.int64)
    return ix * (1 << 32) + (iy + (1 << 31))


def outside_strips(strips: Sequence[Strip], xy: np.ndarray, cell: float) -> np.ndarray:
    """Which map positions ``xy`` (columns x, y; further columns ignored) lie in no strip's
    footprint (no point of any strip in their ``cell``-metre cell): a control point there is
    seen by no strip."""
    xy = np.asarray(xy, dtype=np.float64).reshape(len(xy), -1)
    if not strips:
        return np.ones(len(xy), dtype=bool)
    covered = np.unique(np.concatenate([footprint_keys(s.xyz, cell) for s in strips]))
    return ~np.isin(footprint_keys(xy, cell), covered)


@dataclass(frozen=True)
class FootprintGrid:
    """Sparse footprint cells of ``cell`` metres (overlap detection), keyed in absolute map
    coordinates (:func:`footprint_keys`)."""

    cell: float

    def keys(self, xy: np.ndarray) -> np.ndarray:
        """:func:`footprint_keys` of map positions ``xy`` (columns x, y)."""
        return footprint_keys(xy, self.cell)

    @staticmethod
    def interior(cells: np.ndarray) -> np.ndarray:
        """Cells whose eight neighbours are all in ``cells`` (a one-cell erosion)."""
        keep = np.ones(cells.size, dtype=bool)
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                if dx or dy:
                    keep &= np.isin(cells + dx * (1 << 32) + dy, cells, assume_unique=True)
        return cells[keep]


class Correction(NamedTuple):
    """A strip corrected by an estimate (:meth:`~lidarcal_ros.core.calibration.matching.
    PairMatcher.corrected`)."""

    key: bytes  # the estimate and trajectory error it is of (their bytes)
    #: (n, 3) the corrected points, map frame, m (their shift, delivered - corrected, is
    #: computed where used: 24 bytes a point)
    corrected: np.ndarray
    #: Their laser geometry where a timing bias is estimated; else None: the geometry of
    #: the points wanted is computed from them (:meth:`~lidarcal_ros.core.calibration.
    #: matching.PairMatcher.geometry`).
    geometry: LaserGeometry | None
    #: The coefficients of the strip's trajectory error removed after the biases (a copy;
    #: None: none): the geometry is that of the points before it (docs/method.md section 11).
    error: np.ndarray | None


#: By strip index, the strip's points corrected by an estimate ((n, 3), map frame, m:
#: :meth:`~lidarcal_ros.core.calibration.matching.PairMatcher.corrected`).
CorrectedStrips = dict[int, np.ndarray]


@dataclass
class PreparedStrip:
    """A strip with what the calibration computes once."""

    strip: Strip
    #: The firing frames of the delivered points (:meth:`LaserGeometry.firing_frames`).
    geometry0: LaserGeometry
    density: float  # points per m^2 over its footprint
    #: Its sorted unique footprint cells (those of its points: ``FootprintGrid.keys``, not
    #: held: 8 bytes a point)
    cells: np.ndarray
    #: Random rank of every point for sampling, fixed per strip (empty once every sample is
    #: chosen: :meth:`~lidarcal_ros.core.calibration.calibrate.Calibrator.use_samples`)
    priority: np.ndarray
    choice: ModelChoice  # the point-positioning model it got, and why
    #: What its laser vectors say (as delivered; at the estimate once calibrated: what the
    #: biases do not explain).
    laser_qa: LaserVectorQA
    speed_mps: float  # ground speed over the strip, m/s
    tin: Tin | None = None
    #: The latest correction (:meth:`~lidarcal_ros.core.calibration.matching.PairMatcher.
    #: corrected`).
    corrected: Correction | None = None
    dropped: bool = False  # points released (memory budget); its pairs are frozen
    #: Released before a restart: held for its trajectory error alone (no points, no pairs,
    #: not in a result's strips).
    placeholder: bool = False
    #: Sigmas (m, x y z) of its trajectory offset from the navigation solution's accuracy
    #: over its span (docs/method.md section 11), None where the trajectory has none.
    navigation_sigmas: np.ndarray | None = None
    #: First and last time (s) of the whole strip where ``strip`` holds part of its points
    #: (a bounded-memory calibration); None: those of ``strip``.
    span: tuple[float, float] | None = None

    @property
    def strip_id(self) -> int:
        """The strip's id."""
        return self.strip.strip_id


@dataclass
class StripPair:
    """Working state of one strip pair: points of strip ``a`` matched to the TIN of strip
    ``b`` (indices into the calibration's strips)."""

    index: int
    a: int
    b: int
    coverage: float
    candidates: np.ndarray
    sample: np.ndarray | None = None
    before: np.ndarray | None = None
    frozen: Observations | None = None  # last observations, kept when a strip is dropped
    frozen_delta: np.ndarray | None = None  # the estimate ``frozen`` was matched at
    last_delta: np.ndarray | None = None  # the estimate ``last`` was matched at
    last: Observations | None = None  # observations of the latest matching
    last_triangle: np.ndarray | None = None  # patch of each sample point at the last matching


def find_pair(
    strips: Sequence[PreparedStrip], i: int, j: int, *, index: int, footprint: FootprintGrid,
    min_overlap_cells: int, max_candidates: int,
) -> StripPair | None:
    """The pair (number ``index``) strips ``i`` and ``j`` form, or None: neither dropped, at
    least ``min_overlap_cells`` shared footprint cells and a candidate point.

    The points come from the sparser strip, the TIN from the denser; the candidates are the
    sparser strip's points in the denser one's interior cells, at most ``max_candidates`` of
    them (those of lowest sampling priority).
    """
    si, sj = strips[i], strips[j]
    if si.dropped or sj.dropped:
        return None
    n_cells = int(np.intersect1d(si.cells, sj.cells, assume_unique=True).size)
    if n_cells < min_overlap_cells:
        return None
    coverage = float(n_cells) / float(min(si.cells.size, sj.cells.size))
    # Points come from the sparser strip, the TIN from the denser.
    a, b = (i, j) if si.density <= sj.density else (j, i)
    zone = np.intersect1d(strips[a].cells, footprint.interior(strips[b].cells),
                          assume_unique=True)
    cand = np.flatnonzero(np.isin(footprint.keys(strips[a].strip.xyz[:, :2]), zone))
    if cand.size == 0:
        return None
    if cand.size > max_candidates:
        if strips[a].priority.size == len(strips[a].strip):
            prio = strips[a].priority[cand]
            cand = np.sort(cand[np.argpartition(prio, max_candidates)[:max_candidates]])
        else:  # (released: the samples are given, replacing the candidates)
            cand = cand[:max_candidates]
    return StripPair(index, a, b, coverage, cand)


def stratified_sample(
    matches: PatchMatches, candidates: np.ndarray, priority: np.ndarray, *,
    per_class_cap: int, flat_class_factor: int,
) -> np.ndarray:
    """The sample points of a pair: its matched ``candidates`` (indices into the point strip,
    ``matches`` over them) classed by their patch's slope (flat below 5 deg, moderate, steep
    from 25 deg) and aspect (eight 45 deg sectors), each class capped at ``per_class_cap``
    points of lowest ``priority`` (the flat class at ``flat_class_factor`` times that), so
    that flat ground, which sees only vertical effects, does not drown the sloped roofs that
    reveal the horizontal parameters. Sorted point indices."""
    ok = np.flatnonzero(matches.valid)
    n = matches.normal[ok]
    slope = np.degrees(np.arccos(np.clip(n[:, 2], -1.0, 1.0)))
    aspect = np.degrees(np.arctan2(n[:, 0], n[:, 1])) % 360.0
    sector = np.floor(aspect / 45.0).astype(np.int64) % 8
    cls = np.where(slope < 5.0, 0, 1 + sector + 8 * (slope >= 25.0))
    # Lowest priority first: a point's priority is fixed per strip, so a few candidates
    # changing validity change the sample by a few points, not all of it.
    order = np.argsort(priority[candidates[ok]], kind="stable")
    keep = np.zeros(ok.size, dtype=bool)
    for c in np.unique(cls):
        members = order[cls[order] == c]
        cap = per_class_cap * (flat_class_factor if c == 0 else 1)
        keep[members[:cap]] = True
    return np.sort(candidates[ok[keep]])


def ground_speed(trajectory: Trajectory, t: np.ndarray) -> float:
    """Median horizontal speed of the trajectory over the times ``t`` (m/s; NaN if
    unknown)."""
    if len(trajectory) < 2 or not t.size:
        return float("nan")
    i0 = int(np.searchsorted(trajectory.t, float(np.min(t))))
    i1 = int(np.searchsorted(trajectory.t, float(np.max(t)), side="right"))
    i0, i1 = max(i0 - 1, 0), min(i1 + 1, len(trajectory))
    if i1 - i0 < 2:
        return float("nan")
    step = np.diff(trajectory.xyz[i0:i1, :2], axis=0)
    dt = np.diff(trajectory.t[i0:i1])
    return float(np.median(np.hypot(step[:, 0], step[:, 1]) / dt))


def no_overlap_reason(
    strips: Sequence[PreparedStrip], control: str, *, overlap_cell_m: float,
    min_overlap_cells: int,
) -> str:
    """Why no strip pair formed among the ``strips`` held, in words (one strip only, or how
    close the strips' footprints of ``overlap_cell_m`` cells come: shared cells, else the gap
    between them, metres), then ``control``."""
    held = [ps for ps in strips if not ps.dropped]
    ids = ", ".join(str(ps.strip_id) for ps in held)
    advice = "a calibration needs overlapping strips (two pairs of opposite lines at least)"
    if len(held) < 2:
        plural = "" if len(held) == 1 else "s"
        return (f"no overlap between strips: the mission has {len(held)} strip{plural}"
                f"{f' (id {ids})' if held else ''}{control}; {advice}")
    shared = max(int(np.intersect1d(a.cells, b.cells, assume_unique=True).size)
                 for k, a in enumerate(held) for b in held[k + 1:])
    if shared:
        closest = (f"two strips share at most {shared} footprint cells of "
                   f"{overlap_cell_m:g} m, a pair needs {min_overlap_cells}")
    else:
        boxes = [(ps.strip.xyz[:, :2].min(axis=0), ps.strip.xyz[:, :2].max(axis=0))
                 for ps in held]
        gap = min(float(np.max(np.maximum(lo_b - hi_a, lo_a - hi_b).clip(0.0)))
                  for k, (lo_a, hi_a) in enumerate(boxes) for lo_b, hi_b in boxes[k + 1:])
        closest = (f"their footprints are {gap:.0f} m apart at the closest" if gap > 0
                   else "their footprints cross without sharing a cell")
    return (f"no overlap between strips: none of the {len(held)} strips ({ids}) overlaps "
            f"another ({closest}){control}; {advice}")


def height_agreement(strips: Sequence[PreparedStrip], *, points_per_cell: float = 4.0,
                     min_cells: int = 10) -> list[PairQA]:
    """The strip pairs' height agreement on a grid (last returns where the strips say
    which they are), at cells of 2 m or wider, so that the sparsest strip holds about
    ``points_per_cell`` points a cell; pairs sharing ``min_cells`` smooth cells."""
    held = [ps for ps in strips if not ps.dropped and len(ps.strip)]
    if len(held) < 2:
        return []
    cell = max(2.0, max(float(np.sqrt(points_per_cell / max(ps.density, 1e-6)))
                        for ps in held))
    origin = held[0].strip.xyz[0, :2]
    grid = OverlapGrid(cell, (float(origin[0]), float(origin[1])))
    for ps in held:
        extra = ps.strip.extra
        rn, nr = extra.get("return_number"), extra.get("number_of_returns")
        last = slice(None) if rn is None or nr is None else \
            (np.asarray(rn) >= np.asarray(nr)) | (np.asarray(nr) <= 1)
        xyz = ps.strip.xyz[last]
        grid.add(np.full(len(xyz), ps.strip_id, dtype=np.int64), xyz)
    return grid.pairs(min_cells=min_cells)


__all__ = [
    "CorrectedStrips", "Correction", "FootprintGrid", "PreparedStrip", "StripPair", "find_pair",
    "footprint_keys", "ground_speed", "height_agreement", "no_overlap_reason", "outside_strips",
    "stratified_sample",
]
