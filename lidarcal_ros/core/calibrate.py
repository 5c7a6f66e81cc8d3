"""The quasi-rigorous calibration procedure (method.md sections 4-7), batch form.

``match -> solve -> correct -> match again`` until the corrections to the parameters are
negligible. What is computed once per mission: the laser-frame geometry of every point, one TIN
per strip, the overlap between strips and the candidate points of each overlap. What each
iteration does: correct vertex coordinates (a linear function of the estimate), re-match the
selected sample points to the corrected TINs, re-solve with robust weights.

Sample points are chosen so that slopes and aspects are well represented: every candidate in
an overlap is matched once, classed by its patch's slope and aspect, and each class is capped,
so flat ground (which sees only vertical effects) does not drown the sloped roofs that reveal
the horizontal parameters.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import TypeVar

import numpy as np

from lidarcal_ros.core.adjustment import (
    NormalEquations,
    ObservabilityLimits,
    Observations,
    ParameterStatus,
    Solution,
    cluster_robust_sigma,
    solve,
)
from lidarcal_ros.core.geometry import LaserGeometry
from lidarcal_ros.core.georeferencing import (
    LaserVectorQA,
    ModelChoice,
    laser_vector_qa,
    strip_geometry,
)
from lidarcal_ros.core.mission import ControlPoints, Mission, Strip, Trajectory
from lidarcal_ros.core.model import add_geometry_normal_rows, exact_correction
from lidarcal_ros.core.overlap_grid import OverlapGrid, PairQA
from lidarcal_ros.core.params import N_PARAMETERS, PARAMETER_NAMES
from lidarcal_ros.core.tin import PatchMatches, Tin, TinQuality, match_to_tin
from lidarcal_ros.errors import CalibrationError

logger = logging.getLogger(__name__)

#: Progress callback: (stage description, fraction done in [0, 1]).
Progress = Callable[[str, float], None]
_T = TypeVar("_T")
_R = TypeVar("_R")


@dataclass
class CalibrationSettings:
    """Options of the adjustment (flight configuration ``calibration.*`` and ``matching.*``).

    Lengths in metres, angles in degrees unless stated.
    """

    solve_for: tuple[str, ...] = ("dX", "dY", "domega", "dphi", "dkappa", "dr", "dS")
    fixed: dict[str, float] = field(default_factory=dict)
    trajectory_window_s: float = 0.5
    heading_source: str = "auto"
    #: ``matching.model``: ``auto``, ``level`` or ``rigorous``
    #: (:mod:`lidarcal_ros.core.georeferencing`).
    model: str = "auto"
    #: The scanner's full field of view, deg (``sensor.fov_deg``): the laser-vector QA.
    fov_deg: float = 50.0
    max_normal_distance_m: float = 2.0
    min_normal_distance_m: float = 0.15
    max_edge_factor: float = 4.0
    max_slope_deg: float = 70.0
    max_bend_deg: float = 10.0
    flat_slope_deg: float = 5.0
    cluster_cell_m: float = 25.0
    overlap_cell_m: float = 10.0
    min_overlap_cells: int = 20
    max_candidates_per_pair: int = 100_000
    per_class_cap: int = 3_000
    flat_class_factor: int = 4
    max_iterations: int = 10
    convergence_fraction: float = 0.01
    robust_k: float = 3.0
    control_weight: float = 1.0
    seed: int = 0
    #: Threads the calibration runs strips and strip pairs in (TINs, corrections, matching);
    #: the result does not depend on it.
    workers: int = 2
    limits: ObservabilityLimits = field(default_factory=ObservabilityLimits)

    def __post_init__(self) -> None:
        self.solve_for = tuple(n for n in PARAMETER_NAMES if n in self.solve_for)

    def tin_quality(self, density: float) -> TinQuality:
        """Patch rules for a strip of ``density`` points per m^2 (edges up to
        ``max_edge_factor`` point spacings)."""
        spacing = 1.0 / np.sqrt(max(density, 1e-6))
        return TinQuality(max_edge_m=self.max_edge_factor * spacing,
                          max_slope_deg=self.max_slope_deg, max_bend_deg=self.max_bend_deg,
                          flat_slope_deg=self.flat_slope_deg)


@dataclass
class PreparedStrip:
    """A strip with what the calibration computes once."""

    strip: Strip
    geometry0: LaserGeometry  # at the delivered points
    density: float  # points per m^2 over its footprint
    point_cells: np.ndarray  # footprint cell key of every point (int64)
    cells: np.ndarray  # sorted unique footprint cells
    priority: np.ndarray  # random rank of every point for sampling, fixed per strip
    choice: ModelChoice  # the point-positioning model it got, and why
    #: What its laser vectors say (as delivered; at the estimate once calibrated: what the
    #: biases do not explain).
    laser_qa: LaserVectorQA
    speed_mps: float  # ground speed over the strip, m/s
    tin: Tin | None = None
    geometry: LaserGeometry = field(init=False)  # at the points corrected by the estimate
    #: The latest correction (:meth:`Calibrator._corrected`): the estimate it is of (its
    #: bytes), the corrected points, ``delivered - corrected`` and their geometry.
    corrected: tuple[bytes, np.ndarray, np.ndarray, LaserGeometry] | None = None
    dropped: bool = False  # points released (memory budget); its pairs are frozen

    def __post_init__(self) -> None:
        self.geometry = self.geometry0

    @property
    def strip_id(self) -> int:
        return self.strip.strip_id


@dataclass
class PairStats:
    """QA of one strip pair: RMS normal discrepancy before and after calibration (metres)."""

    strip_a: int
    strip_b: int
    coverage: float
    correspondences: int
    rms_before: float
    rms_after: float
    n_before: int
    n_after: int
    p95_after: float = float("nan")  # 95th percentile of |discrepancy| after, metres


@dataclass
class PairDiscrepancies:
    """Normal discrepancies of one strip pair's sample points at one estimate (the QA of
    :class:`PairStats`, point by point).

    Attributes
    ----------
    points_strip, tin_strip : int
        Id of the strip whose points are matched, and of the strip whose TIN patches they are
        matched to.
    xy : (k, 2) float64
        Map-frame position of each matched point as delivered, metres.
    distance : (k,) float64
        Signed normal distance of each point from its patch, point minus patch along the
        patch's upward normal, after correcting both strips by the estimate; metres.
    rms, p95 : float
        RMS and 95th percentile of ``|distance|`` without gross mismatches, metres (the
        statistics of :class:`PairStats`).
    """

    points_strip: int
    tin_strip: int
    xy: np.ndarray
    distance: np.ndarray
    rms: float
    p95: float

    @property
    def strips(self) -> tuple[int, int]:
        """The two strip ids, smaller first (as in :class:`PairStats`)."""
        a, b = sorted((self.points_strip, self.tin_strip))
        return a, b


@dataclass
class ControlResidual:
    """Normal discrepancy of one control point against one strip, before and after (metres)."""

    control_id: str
    strip_id: int
    before: float
    after: float


@dataclass
class CalibrationResult:
    """Everything ``lidarcal calibrate`` reports and writes."""

    solution: Solution
    iterations: int
    converged: bool
    pairs: list[PairStats]
    control: list[ControlResidual]
    n_pair_correspondences: int
    n_control_correspondences: int
    history: list[np.ndarray]
    dropped_non_finite: int = 0
    thinned_points: int = 0  # left out by calibration.thinning_cell_m
    #: Where each strip's heading came from (``track`` or ``attitude``), and its median crab
    #: (attitude less track, deg; NaN without attitude), by strip id.
    heading_from: dict[int, str] = field(default_factory=dict)
    crab_deg: dict[int, float] = field(default_factory=dict)
    #: The point-positioning model of each strip and why (:mod:`~lidarcal_ros.core.
    #: georeferencing`), and the QA of its laser vectors, by strip id.
    models: dict[int, ModelChoice] = field(default_factory=dict)
    laser_qa: dict[int, LaserVectorQA] = field(default_factory=dict)
    #: Why nothing was estimated (:meth:`Calibrator.unestimated_result`), empty otherwise.
    nothing_estimated: str = ""
    #: Where nothing was estimated: the strip pairs' height agreement on smooth cells, which
    #: needs no patch (:mod:`lidarcal_ros.core.overlap_grid`).
    height_agreement: list[PairQA] = field(default_factory=list)
    #: CPU seconds of the calibration's threads in each of its stages (:class:`StageClock`).
    stage_seconds: dict[str, float] = field(default_factory=dict)


class StageClock:
    """CPU seconds spent in each stage of a calibration, summed over its threads (thread
    time: what the work costs, whatever else the machine runs). A stage entered within
    another pauses it, so the stages add up to the time spent in any of them."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self._lock = threading.Lock()
        self._local = threading.local()

    @contextmanager
    def __call__(self, stage: str) -> Iterator[None]:
        local = self._local
        outer: str | None = getattr(local, "stage", None)
        now = time.thread_time()
        if outer is not None:
            self._add(outer, now - local.since)
        local.stage, local.since = stage, now
        try:
            yield
        finally:
            now = time.thread_time()
            self._add(stage, now - local.since)
            local.stage, local.since = outer, now

    def _add(self, stage: str, seconds: float) -> None:
        with self._lock:
            self.seconds[stage] = self.seconds.get(stage, 0.0) + seconds


class NothingEstimated(CalibrationError):
    """The adjustment could estimate nothing; :attr:`result` still says how well the strips
    agree as delivered.

    Attributes
    ----------
    reason : str
        Why nothing could be estimated (the message of the adjustment's refusal).
    result : CalibrationResult
        The calibration that moves no point (:meth:`Calibrator.unestimated_result`): every
        bias at its fixed value, none estimated, not converged, with the strip pairs' QA.
    """

    def __init__(self, reason: str, result: CalibrationResult) -> None:
        super().__init__(reason)
        self.reason = reason
        self.result = result


@dataclass
class Iteration:
    """One match-and-adjust iteration of :meth:`Calibrator.iterate`.

    Attributes
    ----------
    number : int
        1 for the first iteration from the estimate the calibrator held.
    solution : Solution
        The adjustment (formal sigmas); ``solution.delta`` is the new estimate (SI).
    observations : Observations
        The correspondences adjusted, with their robust weights.
    step : (8,) float64
        Change of the estimate in this iteration (SI).
    converged : bool
        From the second iteration on: no estimated parameter moved by more than
        ``convergence_fraction`` of its sigma.
    history : list of (8,) float64
        The estimate after each iteration so far from the same start, this one's last.
    """

    number: int
    solution: Solution
    observations: Observations
    step: np.ndarray
    converged: bool
    history: list[np.ndarray]


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
class _Footprint:
    """Sparse footprint cells (overlap detection), keyed in absolute map coordinates so that
    strips arriving one by one share one grid."""

    cell: float

    def keys(self, xy: np.ndarray) -> np.ndarray:
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


@dataclass
class _PairWork:
    """Working state of one strip pair: points of ``a`` matched to the TIN of ``b``."""

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


class Calibrator:
    """Calibration of a mission, batch or strip by strip.

    Strips are added with :meth:`add_strip` (each is prepared once: local trajectory,
    footprint, pairs with the strips before it); :meth:`run` iterates matching and adjustment
    from the current estimate. Adding all strips and running once is the batch calibration;
    adding strips as they end and running after each is the live one, and both sample each
    pair the same way (seeded by the strip ids), so they agree.

    Parameters
    ----------
    settings : CalibrationSettings
    control : ControlPoints, optional
    progress : callable, optional
        Called with (stage, fraction) as work proceeds.
    """

    def __init__(
        self,
        settings: CalibrationSettings,
        *,
        control: ControlPoints | None = None,
        progress: Progress | None = None,
    ) -> None:
        self.settings = settings
        self.control = control
        self._progress = progress or (lambda stage, frac: None)
        self.footprint = _Footprint(settings.overlap_cell_m)
        self.strips: list[PreparedStrip] = []
        self.pairs: list[_PairWork] = []
        self.delta = np.zeros(N_PARAMETERS)
        self.threshold = settings.max_normal_distance_m
        self.dropped_non_finite = 0
        self.thinned_points = 0
        self.normal_equations = NormalEquations()
        self._restored = Observations.empty()
        self._restored_delta = np.zeros(N_PARAMETERS)
        self._control_before: list[tuple[int, int, float]] | None = None
        self._pool: ThreadPoolExecutor | None = None
        self.clock = StageClock()

    @classmethod
    def from_mission(
        cls, mission: Mission, settings: CalibrationSettings, *,
        progress: Progress | None = None,
    ) -> Calibrator:
        """A calibrator holding every strip of ``mission``."""
        if not mission.strips:
            raise CalibrationError("mission has no strips")
        cal = cls(settings, control=mission.control, progress=progress)
        cal.dropped_non_finite = mission.dropped_non_finite
        cal.thinned_points = mission.thinned_points
        for k, strip in enumerate(mission.strips):
            cal.add_strip(strip, mission.trajectory)
            cal._progress("local trajectories", (k + 1) / len(mission.strips))
        logger.info("%d overlapping strip pairs", len(cal.pairs))
        return cal

    # ------------------------------------------------------------------ preparation
    @property
    def n_points(self) -> int:
        """Points held (dropped strips excluded)."""
        return sum(len(ps.strip) for ps in self.strips if not ps.dropped)

    def set_control(self, control: ControlPoints | None) -> None:
        """Control points for the runs from now on (their matches against the delivered
        strips are found again)."""
        self.control = control
        self._control_before = None

    def add_strip(self, strip: Strip, trajectory: Trajectory) -> list[tuple[int, int]]:
        """Prepare a strip and find its pairs with the strips already held.

        Returns the ``(strip_id, strip_id)`` pairs it forms.

        Raises
        ------
        TrajectoryError
            The trajectory does not cover the strip's points.
        CalibrationError
            A strip with this id is already held.
        """
        with self.clock("local trajectories"):
            return self._add_strip(strip, trajectory)

    def _add_strip(self, strip: Strip, trajectory: Trajectory) -> list[tuple[int, int]]:
        s = self.settings
        if any(ps.strip_id == strip.strip_id for ps in self.strips):
            raise CalibrationError(f"strip {strip.strip_id} added twice")
        geom, choice = strip_geometry(strip.t, strip.xyz, trajectory,
                                      window_s=s.trajectory_window_s,
                                      source=f"strip {strip.strip_id}",
                                      heading_source=s.heading_source, model=s.model)
        speed = _ground_speed(trajectory, strip.t)
        qa = laser_vector_qa(geom, fov_deg=s.fov_deg, speed_mps=speed)
        keys = self.footprint.keys(strip.xyz[:, :2])
        cells = np.unique(keys)
        density = len(strip) / max(cells.size * s.overlap_cell_m**2, 1.0)
        priority = np.random.default_rng([s.seed, strip.strip_id]).random(len(strip))
        self.strips.append(PreparedStrip(strip, geom, density, keys, cells, priority, choice,
                                         qa, speed))
        new = len(self.strips) - 1
        formed = []
        for other in range(new):
            pair = self._make_pair(other, new)
            if pair is not None:
                self.pairs.append(pair)
                formed.append((self.strips[other].strip_id, strip.strip_id))
        return formed

    def _make_pair(self, i: int, j: int) -> _PairWork | None:
        s = self.settings
        si, sj = self.strips[i], self.strips[j]
        if si.dropped or sj.dropped:
            return None
        n_cells = int(np.intersect1d(si.cells, sj.cells, assume_unique=True).size)
        if n_cells < s.min_overlap_cells:
            return None
        coverage = float(n_cells) / float(min(si.cells.size, sj.cells.size))
        # Points come from the sparser strip, the TIN from the denser.
        a, b = (i, j) if si.density <= sj.density else (j, i)
        zone = np.intersect1d(self.strips[a].cells,
                              self.footprint.interior(self.strips[b].cells), assume_unique=True)
        cand = np.flatnonzero(np.isin(self.strips[a].point_cells, zone))
        if cand.size == 0:
            return None
        if cand.size > s.max_candidates_per_pair:
            prio = self.strips[a].priority[cand]
            cand = np.sort(cand[np.argpartition(prio, s.max_candidates_per_pair)
                                [:s.max_candidates_per_pair]])
        return _PairWork(len(self.pairs), a, b, coverage, cand)

    def _kept(self) -> list[tuple[Observations, np.ndarray]]:
        """Correspondences kept without re-matching, each with the estimate it was matched at."""
        kept = [(self._restored, self._restored_delta)] if len(self._restored) else []
        for p in self.pairs:
            if p.frozen is not None and p.frozen_delta is not None:
                kept.append((p.frozen, p.frozen_delta))
        return kept

    def frozen_observations(self) -> Observations:
        """Correspondences kept without their points (released strips, restored state),
        expressed at the current estimate."""
        return Observations.concatenate(_at(obs, at, self.delta) for obs, at in self._kept())

    def restore_frozen(self, obs: Observations) -> None:
        """Take frozen correspondences back from a checkpoint (expressed at ``self.delta``:
        set the estimate first)."""
        self._restored = obs
        self._restored_delta = self.delta.copy()

    def drop_strip(self, strip_id: int) -> int:
        """Release a strip's points (memory budget); its pairs keep their last observations.

        Returns the number of points released.
        """
        for ps in self.strips:
            if ps.strip_id == strip_id and not ps.dropped:
                k = self.strips.index(ps)
                for pair in self.pairs:
                    if k in (pair.a, pair.b) and pair.frozen is None:
                        pair.frozen_delta = pair.last_delta if pair.last_delta is not None \
                            else self.delta.copy()
                        pair.frozen = pair.last if pair.last is not None else \
                            Observations.empty()
                n = len(ps.strip)
                ps.dropped = True
                ps.tin = None
                empty = np.empty((0, 3))
                ps.strip = Strip(ps.strip_id, empty, np.empty(0))
                ps.geometry0 = ps.geometry = ps.geometry0.take(np.zeros(0, dtype=np.int64))
                ps.corrected = None
                ps.point_cells = np.empty(0, dtype=np.int64)
                ps.priority = np.empty(0)
                return n
        return 0

    def _tin(self, k: int) -> Tin:
        ps = self.strips[k]
        if ps.tin is None:
            with self.clock("TINs"):
                ps.tin = Tin(ps.strip.xyz, self.settings.tin_quality(ps.density))
        return ps.tin

    def _build_tins(self, strips: Iterable[int]) -> None:
        """Build the TINs of ``strips`` not built yet (largest first, in the threads)."""
        todo = sorted({k for k in strips if self.strips[k].tin is None and
                       not self.strips[k].dropped}, key=lambda k: -len(self.strips[k].strip))
        self._map(self._tin, todo, "building TINs" if todo else None)

    # ------------------------------------------------------------------ threads
    def _map(self, fn: Callable[[_T], _R], items: Sequence[_T], stage: str | None = None
             ) -> list[_R]:
        """``[fn(item) for item in items]``, in the worker threads while :meth:`run` holds
        them (``settings.workers``), reporting progress in ``stage``."""
        if stage:
            self._progress(stage, 0.0)
        if self._pool is None or len(items) < 2:
            out = []
            for i, item in enumerate(items):
                out.append(fn(item))
                if stage:
                    self._progress(stage, (i + 1) / len(items))
            return out
        futures = [self._pool.submit(fn, item) for item in items]
        results = []
        try:
            for i, future in enumerate(futures):
                results.append(future.result())
                if stage:
                    self._progress(stage, (i + 1) / len(items))
        finally:
            for future in futures:
                future.cancel()
        return results

    def _threads(self) -> _Threads:
        """The worker threads for the duration of a ``with`` block."""
        return _Threads(self)

    # ------------------------------------------------------------------ matching
    def _corrected(self, k: int, delta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Corrected coordinates of strip k and the shift ``delivered - corrected``.

        Also re-evaluates the strip's laser-frame geometry (x, z, beta) at the corrected
        points: the design rows are the Jacobian at the current estimate. Evaluated at the
        delivered points instead, effects that cancel between opposite lines (dr, dS, dkappa)
        would appear not to cancel, and mimic dphi.
        """
        ps = self.strips[k]
        key = np.asarray(delta, dtype=np.float64).tobytes()
        if ps.corrected is None or ps.corrected[0] != key:
            with self.clock("corrections"):
                corrected, shift, geometry = exact_correction(ps.strip.xyz, ps.geometry0,
                                                              delta)
            ps.corrected = (key, corrected, shift, geometry)
        _, corrected, shift, ps.geometry = ps.corrected
        return corrected, shift

    def _match_pair(
        self, pair: _PairWork, points_idx: np.ndarray, delta: np.ndarray,
        corrected: dict[int, tuple[np.ndarray, np.ndarray]], threshold: float,
    ) -> PatchMatches:
        a_xyz, _ = corrected[pair.a]
        b_xyz, b_shift = corrected[pair.b]
        shift = b_shift if np.any(delta) else None
        # The sample is matched every iteration: start each search at its last patch.
        on_sample = points_idx is pair.sample
        start = pair.last_triangle if on_sample else None
        tin = self._tin(pair.b)
        with self.clock("matching"):
            m = match_to_tin(a_xyz[points_idx], tin, b_xyz, max_normal_distance=threshold,
                             vertex_shift=shift, start=start)
        if on_sample:
            pair.last_triangle = m.triangle
        return m

    def _patch_terms(
        self, k: int, m: PatchMatches
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For the valid matches to strip ``k``'s patches: the observed normals, ``n^T A_B``
        interpolated at the foot of the normal (barycentric), and the observed discrepancy
        (the patch distance along the observed normal)."""
        ok = m.valid
        tin = self._tin(k)
        with self.clock("design rows"):
            n = self._observed_normal(m.normal[ok], tin.sloped[m.triangle[ok]])
            w = m.weights[ok]
            verts = tin.simplices[m.triangle[ok]]
            geometry = self.strips[k].geometry
            rows = np.zeros((int(ok.sum()), N_PARAMETERS))
            for v in range(3):
                add_geometry_normal_rows(rows, n, geometry, verts[:, v], w[:, v])
            y = m.distance[ok] * (n * m.normal[ok]).sum(axis=1)
        return n, rows, y

    def _pair_observations(
        self, pair: _PairWork, points_idx: np.ndarray, m: PatchMatches
    ) -> Observations:
        sa = self.strips[pair.a]
        idx = points_idx[m.valid]
        # eq. [11]: the discrepancy n . (X_A - X_B) left by the current estimate; the
        # adjustment solves for the increment that removes it (Gauss-Newton).
        n, patch_rows, y = self._patch_terms(pair.b, m)
        with self.clock("design rows"):
            rows = np.zeros_like(patch_rows)
            add_geometry_normal_rows(rows, n, sa.geometry, idx)
            rows -= patch_rows
            cluster = self._cluster_of(sa.strip.xyz[idx])
        return Observations(rows, y, np.ones(idx.size), np.full(idx.size, pair.index), cluster)

    def _cluster_of(self, xyz: np.ndarray) -> np.ndarray:
        """Spatial cluster (cell of ``cluster_cell_m``) of observations at ``xyz``."""
        return _Footprint(self.settings.cluster_cell_m).keys(xyz[:, :2])

    @staticmethod
    def _observed_normal(normal: np.ndarray, sloped: np.ndarray) -> np.ndarray:
        """Normals of patches that are not clearly sloped set exactly vertical.

        On flat ground a triangle tilts only by the noise of its vertices; that tilt would
        lend the horizontal parameters an information that is noise (and bias them toward
        zero), so such patches observe vertical effects only (see ``TinQuality``).
        """
        out = normal.copy()
        out[~sloped] = (0.0, 0.0, 1.0)
        return out

    def _select_sample(self, pair: _PairWork, m: PatchMatches) -> np.ndarray:
        """Stratify matched candidates by patch slope and aspect; cap each class."""
        with self.clock("sample selection"):
            return self._stratified_sample(pair, m)

    def _stratified_sample(self, pair: _PairWork, m: PatchMatches) -> np.ndarray:
        s = self.settings
        ok = np.flatnonzero(m.valid)
        n = m.normal[ok]
        slope = np.degrees(np.arccos(np.clip(n[:, 2], -1.0, 1.0)))
        aspect = np.degrees(np.arctan2(n[:, 0], n[:, 1])) % 360.0
        sector = np.floor(aspect / 45.0).astype(np.int64) % 8
        cls = np.where(slope < 5.0, 0, 1 + sector + 8 * (slope >= 25.0))
        # Lowest priority first: a point's priority is fixed per strip, so a few candidates
        # changing validity change the sample by a few points, not all of it.
        order = np.argsort(self.strips[pair.a].priority[pair.candidates[ok]], kind="stable")
        keep = np.zeros(ok.size, dtype=bool)
        for c in np.unique(cls):
            members = order[cls[order] == c]
            cap = s.per_class_cap * (s.flat_class_factor if c == 0 else 1)
            keep[members[:cap]] = True
        return np.sort(pair.candidates[ok[keep]])

    def _control_observations(
        self, control: ControlPoints, delta: np.ndarray,
        corrected: dict[int, tuple[np.ndarray, np.ndarray]], threshold: float,
    ) -> tuple[Observations, list[tuple[int, int, float]]]:
        parts = []
        found: list[tuple[int, int, float]] = []
        cp_cells = self.footprint.keys(control.xyz[:, :2])
        self._build_tins(k for k, ps in enumerate(self.strips)
                         if not ps.dropped and np.isin(cp_cells, ps.cells).any())
        for k, ps in enumerate(self.strips):
            if ps.dropped:
                continue
            inside = np.isin(cp_cells, ps.cells)
            if not inside.any():
                continue
            cps = np.flatnonzero(inside)
            xyz, shift = corrected[k]
            tin = self._tin(k)
            with self.clock("matching"):
                m = match_to_tin(control.xyz[cps], tin, xyz, max_normal_distance=threshold,
                                 vertex_shift=shift if np.any(delta) else None)
            if not m.valid.any():
                continue
            ok = m.valid
            # eq. [12]: n . (X_C - X_B), X_B corrected by the estimate
            _, patch_rows, y = self._patch_terms(k, m)
            rows = -patch_rows
            weights = np.full(y.size, self.settings.control_weight)
            parts.append(Observations(rows, y, weights, -1 - cps[ok],
                                      self._cluster_of(control.xyz[cps[ok]])))
            for c, d in zip(cps[ok], m.distance[ok]):
                found.append((int(c), k, float(d)))
        return Observations.concatenate(parts), found

    # ------------------------------------------------------------------ adjustment
    def _robust_solve(self, obs: Observations, delta: np.ndarray) -> Solution:
        """Solve for the increment to ``delta``, zeroing the weights of outliers
        (> robust_k robust sigmas) until they no longer change.

        Returns the solution with ``delta`` = current estimate + increment; parameters not
        solved for are moved to their fixed values.
        """
        with self.clock("normal equations"):
            return self._reweighted_solve(obs, delta)

    def _reweighted_solve(self, obs: Observations, delta: np.ndarray) -> Solution:
        s = self.settings
        fixed_step = {name: float(s.fixed.get(name, 0.0) - delta[i])
                      for i, name in enumerate(PARAMETER_NAMES)}
        base_w = obs.weights.copy()
        sol = None
        for _ in range(6):
            neq = NormalEquations.from_observations(obs)
            sol = solve(neq, solve_for=s.solve_for, fixed=fixed_step, limits=s.limits)
            v = obs.residuals(sol.delta)
            # Robust weights for strip pairs only: control points are surveyed and few, and
            # before dZ and dr are estimated their discrepancies are legitimately large.
            pairs = (obs.group >= 0) & (base_w > 0)
            scale = 1.4826 * np.median(np.abs(v[pairs])) if pairs.any() else 1.0
            outlier = pairs & (np.abs(v) > s.robust_k * max(scale, 1e-6))
            new_w = np.where(outlier, 0.0, base_w)
            if np.array_equal(new_w > 0, obs.weights > 0):
                break
            obs.weights = new_w
        assert sol is not None
        sol.delta = sol.delta + delta
        return sol

    def run(self, *, max_iterations: int | None = None,
            new_pairs_only: bool = False) -> CalibrationResult:
        """Iterate matching and adjustment from the current estimate to convergence (at most
        ``max_iterations``, default the settings'): :meth:`iterate` until an iteration
        converges, then :meth:`conclude`, with the worker threads (``settings.workers``)
        matching the strip pairs of each iteration at once.

        Pairs met for the first time are matched once at zero correction: that chooses their
        sample points and gives the "before" discrepancies. With ``new_pairs_only`` (a live
        update), pairs matched before keep their last correspondences instead of being
        re-matched; only pairs formed since are matched each iteration.
        """
        limit = max_iterations or self.settings.max_iterations
        with self._threads():
            iterations = self.iterate(new_pairs_only=new_pairs_only)
            while True:
                done = next(iterations)
                if done is not None and (done.converged or done.number >= limit):
                    return self.conclude(done)

    def iterate(self, *, new_pairs_only: bool = False) -> Iterator[Iteration | None]:
        """Match and adjust from the current estimate, iteration after iteration, for as long
        as the caller takes items (:meth:`run`'s options).

        Yields None after each strip pair matched (where the caller may pause, or stop:
        nothing is committed until the iteration's adjustment) and an :class:`Iteration`
        after each adjustment, whose estimate and matching threshold are from then on the
        calibrator's (:attr:`delta`, :attr:`threshold`). Strips, pairs and control points must
        not change while the iterations are under way; :meth:`conclude` turns the last one
        into a result. Within :meth:`run` (its threads started) the pairs of an iteration are
        matched together, in the threads, before their items are yielded.

        Raises
        ------
        CalibrationError
            Nothing to match (at the first item).
        """
        s = self.settings
        control = self.control
        live = [p for p in self.pairs if p.frozen is None]
        frozen = self._kept()
        no_pairs = not self.pairs and not frozen
        if no_pairs and (control is None or len(control) == 0):
            raise CalibrationError(self._no_overlap(", and no control points"))
        fresh = [p for p in live if p.sample is None]
        if new_pairs_only:
            kept = [p for p in live if p.last is not None and p.last_delta is not None]
            frozen.extend((p.last, p.last_delta) for p in kept
                          if p.last is not None and p.last_delta is not None)
            live = [p for p in live if p not in kept]
        self._choose_samples(fresh)
        self._control_matches_before()
        iteration = 0
        history: list[np.ndarray] = []
        while True:
            iteration += 1
            delta = self.delta.copy()
            corrected: dict[int, tuple[np.ndarray, np.ndarray]] = {}
            # Kept correspondences re-expressed at the current estimate (Gauss-Newton form).
            parts = [_at(obs, at, delta) for obs, at in frozen]
            if self._pool is not None:  # (run(): every pair at once, in the threads)
                corrected = self._corrected_many(self._used_strips(live), delta)

                def observe(pair: _PairWork, delta: np.ndarray = delta,
                            corrected: dict[int, tuple[np.ndarray, np.ndarray]] = corrected
                            ) -> Observations:
                    assert pair.sample is not None
                    m = self._match_pair(pair, pair.sample, delta, corrected, self.threshold)
                    return self._pair_observations(pair, pair.sample, m)

                matched = self._map(observe, live, f"iteration {iteration}: matching")
                for pair, last in zip(live, matched, strict=True):
                    pair.last = last
                    pair.last_delta = delta.copy()
                    parts.append(last)
                    yield None
            for p_i, pair in enumerate(live if self._pool is None else ()):
                self._progress(f"iteration {iteration}: matching", p_i / max(len(live), 1))
                assert pair.sample is not None
                for k in (pair.a, pair.b):
                    if k not in corrected:
                        corrected[k] = self._corrected(k, delta)
                m = self._match_pair(pair, pair.sample, delta, corrected, self.threshold)
                pair.last = self._pair_observations(pair, pair.sample, m)
                pair.last_delta = delta.copy()
                parts.append(pair.last)
                yield None
            if control is not None and len(control):
                corrected.update(self._corrected_many(
                    (k for k in range(len(self.strips))
                     if k not in corrected and not self.strips[k].dropped), delta))
                parts.append(self._control_observations(control, delta, corrected,
                                                        s.max_normal_distance_m)[0])
            obs = Observations.concatenate(parts)
            if len(obs) == 0:
                raise CalibrationError(
                    "no point-to-patch correspondences: the overlaps hold no usable patches"
                )
            self._progress(f"iteration {iteration}: adjusting", 1.0)
            try:
                sol = self._robust_solve(obs, delta)
            except CalibrationError as exc:
                if not no_pairs:
                    raise
                n = len(control) if control is not None else 0
                raise CalibrationError(self._no_overlap(
                    f", and {n} control point{'' if n == 1 else 's'} alone cannot calibrate: "
                    f"{exc}")) from None
            step = sol.delta - delta
            est = np.isfinite(sol.sigma)
            logger.info("iteration %d: sigma0 %.4f m, %d observations, max step/sigma %.3g",
                        iteration, sol.sigma0, len(obs),
                        float(np.max(np.abs(step[est]) / sol.sigma[est])) if est.any() else 0.0)
            inl = (obs.weights > 0) & (obs.group >= 0)
            scale = float(np.sqrt(np.mean(obs.residuals(step)[inl] ** 2))) if inl.any() else 0.0
            self.threshold = float(np.clip(2.0 * s.robust_k * scale, s.min_normal_distance_m,
                                           self.threshold))
            self.delta = sol.delta.copy()
            history.append(self.delta.copy())
            converged = iteration > 1 and bool(
                np.all(np.abs(step[est]) <= s.convergence_fraction * sol.sigma[est])
                or _matching_cycle(history, sol.sigma, est, s.convergence_fraction))
            yield Iteration(iteration, sol, obs, step, converged, list(history))

    def conclude(self, last: Iteration) -> CalibrationResult:
        """The result of the iterations of :meth:`iterate` that ended with ``last``: sigmas
        allowing for shared errors, and the QA of every pair at the estimate. Call once per
        iteration (it widens ``last``'s sigmas)."""
        with self.clock("normal equations"):
            self.normal_equations = NormalEquations.from_observations(last.observations)
            self._allow_for_shared_errors(last.solution, last.observations, last.step)
        return self._finish(last.solution, last.observations, last.solution.delta, last.number,
                            last.converged, last.history)

    def unestimated_result(self, reason: str) -> CalibrationResult:
        """The result of a calibration that estimated nothing (``reason``): every bias at
        its fixed value (``settings.fixed``, 0 unless given), no sigma, not converged, and
        the QA of every strip pair as delivered (the sample points of :meth:`run`, matched
        at that value; ``correspondences`` counts the points matched, none of which was
        adjusted) and of the control points.
        """
        s = self.settings
        delta = np.array([float(s.fixed.get(name, 0.0)) for name in PARAMETER_NAMES])
        with self._threads():
            self._choose_samples([p for p in self.pairs if p.frozen is None and
                                  p.sample is None])
        status = {name: ParameterStatus("not_estimable", reason) if name in s.solve_for
                  else ParameterStatus("fixed") for name in PARAMETER_NAMES}
        sol = Solution(delta=delta, sigma=np.full(N_PARAMETERS, np.nan), estimated=(),
                       covariance=np.zeros((0, 0)), correlation=np.zeros((0, 0)),
                       sigma0=float("nan"), redundancy=0, status=status)
        with self._threads():
            result = self._finish(sol, Observations.empty(), delta, 0, False, [])
        for p in result.pairs:
            p.correspondences = p.n_after
        result.nothing_estimated = reason
        result.height_agreement = self._height_agreement()
        return result

    def _height_agreement(self, *, points_per_cell: float = 4.0, min_cells: int = 10
                          ) -> list[PairQA]:
        """The strip pairs' height agreement on a grid (last returns where the strips say
        which they are), at cells of 2 m or wider, so that the sparsest strip holds about
        ``points_per_cell`` points a cell; pairs sharing ``min_cells`` smooth cells."""
        held = [ps for ps in self.strips if not ps.dropped and len(ps.strip)]
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

    def _no_overlap(self, control: str) -> str:
        """Why no strip pair formed, in words (one strip only, or how close the strips'
        footprints come: shared cells, else the gap between them), then ``control``."""
        held = [ps for ps in self.strips if not ps.dropped]
        ids = ", ".join(str(ps.strip_id) for ps in held)
        advice = "a calibration needs overlapping strips (two pairs of opposite lines at least)"
        if len(held) < 2:
            plural = "" if len(held) == 1 else "s"
            return (f"no overlap between strips: the mission has {len(held)} strip{plural}"
                    f"{f' (id {ids})' if held else ''}{control}; {advice}")
        s = self.settings
        shared = max(int(np.intersect1d(a.cells, b.cells, assume_unique=True).size)
                     for k, a in enumerate(held) for b in held[k + 1:])
        if shared:
            closest = (f"two strips share at most {shared} footprint cells of "
                       f"{s.overlap_cell_m:g} m, a pair needs {s.min_overlap_cells}")
        else:
            boxes = [(ps.strip.xyz[:, :2].min(axis=0), ps.strip.xyz[:, :2].max(axis=0))
                     for ps in held]
            gap = min(float(np.max(np.maximum(lo_b - hi_a, lo_a - hi_b).clip(0.0)))
                      for k, (lo_a, hi_a) in enumerate(boxes) for lo_b, hi_b in boxes[k + 1:])
            closest = (f"their footprints are {gap:.0f} m apart at the closest" if gap > 0
                       else "their footprints cross without sharing a cell")
        return (f"no overlap between strips: none of the {len(held)} strips ({ids}) overlaps "
                f"another ({closest}){control}; {advice}")

    def _choose_samples(self, pairs: Sequence[_PairWork]) -> None:
        """Match pairs met for the first time once at zero correction: choose their sample
        points and keep their "before" discrepancies."""
        if not pairs:
            return
        s = self.settings
        zero = np.zeros(N_PARAMETERS)
        self._build_tins(p.b for p in pairs)
        delivered = self._corrected_many(self._used_strips(pairs), zero)

        def choose(pair: _PairWork) -> None:
            m = self._match_pair(pair, pair.candidates, zero, delivered, s.max_normal_distance_m)
            pair.sample = self._select_sample(pair, m)
            before = m.take(np.isin(pair.candidates, pair.sample)).distance
            pair.before = before[np.isfinite(before)]

        self._map(choose, pairs, "choosing sample points")

    def _match_samples(
        self, delta: np.ndarray
    ) -> tuple[list[tuple[_PairWork, PatchMatches]], dict[int, tuple[np.ndarray, np.ndarray]]]:
        """Match the sample points of every pair holding its points at the estimate ``delta``
        (first threshold), choosing the samples of pairs met for the first time.

        Returns the matches of each pair and the corrected strips (see :meth:`_corrected`).
        """
        s = self.settings
        live = [p for p in self.pairs if p.frozen is None]
        # Samples first: choosing them leaves every strip's geometry at the delivered points.
        self._choose_samples([p for p in live if p.sample is None])
        corrected = self._corrected_all(delta)

        def match(pair: _PairWork) -> PatchMatches:
            assert pair.sample is not None
            return self._match_pair(pair, pair.sample, delta, corrected, s.max_normal_distance_m)

        return list(zip(live, self._map(match, live), strict=True)), corrected

    def _corrected_all(self, delta: np.ndarray) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """:meth:`_corrected` of every strip that holds its points."""
        return self._corrected_many((k for k in range(len(self.strips))
                                     if not self.strips[k].dropped), delta)

    def _corrected_many(self, strips: Iterable[int], delta: np.ndarray
                        ) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """:meth:`_corrected` of ``strips`` (in the threads)."""
        ks = sorted(set(strips))
        return dict(zip(ks, self._map(lambda k: self._corrected(k, delta), ks), strict=True))

    def observations_at(self, delta: np.ndarray) -> Observations:
        """The correspondences of every pair (and control) at the estimate ``delta``, with
        no adjustment: what flight planning analyses."""
        with self._threads():
            matched, corrected = self._match_samples(delta)
            parts = [self._pair_observations(pair, pair.sample, m) for pair, m in matched
                     if pair.sample is not None]
            if self.control is not None and len(self.control):
                parts.append(self._control_observations(self.control, delta, corrected,
                                                        self.settings.max_normal_distance_m)[0])
        return Observations.concatenate(parts)

    def pair_discrepancies(self, delta: np.ndarray) -> list[PairDiscrepancies]:
        """Per strip pair holding its points, the normal discrepancy of every matched sample
        point after correcting both strips by ``delta`` (8 biases, SI, method.md order):
        at zero the discrepancies "before" calibration, at the estimate those "after".

        The points and the matching threshold are those of the QA of :meth:`run`, so the
        statistics reproduce :class:`PairStats` (``rms_before`` at zero, ``rms_after`` at
        the estimate). Pairs sorted by strip ids.
        """
        floor = self.settings.min_normal_distance_m
        out = []
        with self._threads():
            matched = self._match_samples(np.asarray(delta, dtype=np.float64))[0]
        for pair, m in matched:
            assert pair.sample is not None
            idx = pair.sample[m.valid]
            distance = m.distance[m.valid]
            rms, p95 = _robust_qa(distance, floor)
            out.append(PairDiscrepancies(
                points_strip=self.strips[pair.a].strip_id,
                tin_strip=self.strips[pair.b].strip_id,
                xy=self.strips[pair.a].strip.xyz[idx, :2].copy(), distance=distance,
                rms=rms, p95=p95))
        out.sort(key=lambda d: d.strips)
        return out

    def control_residuals(
        self, delta: np.ndarray,
        corrected: dict[int, tuple[np.ndarray, np.ndarray]] | None = None,
    ) -> list[ControlResidual]:
        """Normal discrepancy of every control point against every strip that sees it, as
        delivered and after correcting the strips by ``delta`` (metres; NaN where the point
        no longer finds a patch). ``corrected``: the strips already corrected by ``delta``.
        """
        control = self.control
        if control is None or not len(control):
            return []
        before = self._control_matches_before()  # before ``corrected``: it resets geometries
        if corrected is None:
            corrected = self._corrected_all(delta)
        _, found_after = self._control_observations(
            control, delta, corrected, self.settings.max_normal_distance_m)
        after_map = {(c, k): d for c, k, d in found_after}
        return [ControlResidual(control.ids[c], self.strips[k].strip_id, d,
                                after_map.get((c, k), float("nan")))
                for c, k, d in before]

    def _control_matches_before(self) -> list[tuple[int, int, float]]:
        """(control index, strip index, normal distance) of every control point against the
        delivered strips; computed once."""
        if self._control_before is None:
            control = self.control
            if control is None or not len(control):
                return []
            zero = np.zeros(N_PARAMETERS)
            delivered = self._corrected_many(range(len(self.strips)), zero)
            self._control_before = self._control_observations(
                control, zero, delivered, self.settings.max_normal_distance_m)[1]
        return self._control_before

    def _used_strips(self, pairs: Sequence[_PairWork]) -> set[int]:
        return {k for p in pairs for k in (p.a, p.b)}

    @staticmethod
    def _allow_for_shared_errors(sol: Solution, obs: Observations, step: np.ndarray) -> None:
        """Widen each sigma to its cluster-robust value where that is larger.

        The formal covariance assumes independent observations, but the same patches and
        points serve several strip pairs. Correlations stay those of the formal covariance;
        only standard deviations grow (the covariance stays positive semi-definite).
        """
        robust = cluster_robust_sigma(sol, obs, step)
        idx = [PARAMETER_NAMES.index(n) for n in sol.estimated]
        formal = sol.sigma[idx]
        wider = np.where(np.isfinite(robust), np.maximum(formal, robust), formal)
        sol.sigma[idx] = wider
        sol.covariance = sol.correlation * wider[:, None] * wider[None, :]

    def _finish(
        self, sol: Solution, obs: Observations, delta: np.ndarray, iterations: int,
        converged: bool, history: list[np.ndarray],
    ) -> CalibrationResult:
        """QA: re-match the samples with the final estimate at the first threshold; the
        laser vectors of the points corrected by it."""
        s = self.settings
        corrected = self._corrected_all(delta)
        with self.clock("QA"):
            for ps in self.strips:
                if not ps.dropped:
                    ps.laser_qa = laser_vector_qa(ps.geometry, fov_deg=s.fov_deg,
                                                  speed_mps=ps.speed_mps)

        def after_of(pair: _PairWork) -> np.ndarray:
            assert pair.sample is not None
            if pair.frozen is not None and pair.frozen_delta is not None:
                return pair.frozen.residuals(delta - pair.frozen_delta) if len(pair.frozen) \
                    else np.empty(0)
            m = self._match_pair(pair, pair.sample, delta, corrected, s.max_normal_distance_m)
            return m.distance[m.valid]

        stats = []
        for pair, after in zip(self.pairs, self._map(after_of, self.pairs), strict=True):
            assert pair.before is not None
            ids = sorted((self.strips[pair.a].strip_id, self.strips[pair.b].strip_id))
            rms_after, p95_after = _robust_qa(after, s.min_normal_distance_m)
            stats.append(PairStats(
                strip_a=ids[0], strip_b=ids[1],
                coverage=float(pair.coverage),
                correspondences=int(np.count_nonzero(
                    (obs.group == pair.index) & (obs.weights > 0))),
                rms_before=_robust_qa(pair.before, s.min_normal_distance_m)[0],
                rms_after=rms_after, p95_after=p95_after,
                n_before=int(pair.before.size), n_after=int(after.size),
            ))
        stats.sort(key=lambda p: (p.strip_a, p.strip_b))
        residuals = self.control_residuals(delta, corrected)
        n_ctrl = int(np.count_nonzero((obs.group < 0) & (obs.weights > 0)))
        return CalibrationResult(
            solution=sol, iterations=iterations, converged=converged, pairs=stats,
            control=residuals, n_pair_correspondences=int(np.count_nonzero(
                (obs.group >= 0) & (obs.weights > 0))),
            n_control_correspondences=n_ctrl, history=history,
            dropped_non_finite=self.dropped_non_finite, thinned_points=self.thinned_points,
            heading_from={ps.strip.strip_id: ps.geometry0.heading_from for ps in self.strips},
            crab_deg={ps.strip.strip_id: ps.geometry0.crab_deg for ps in self.strips},
            models={ps.strip.strip_id: ps.choice for ps in self.strips},
            laser_qa={ps.strip.strip_id: ps.laser_qa for ps in self.strips},
            stage_seconds=dict(self.clock.seconds),
        )


class _Threads:
    """The worker threads of a :class:`Calibrator` (``settings.workers``) for a ``with``
    block; nested blocks share the outer one's."""

    def __init__(self, calibrator: Calibrator) -> None:
        self.calibrator = calibrator
        self.owner = False

    def __enter__(self) -> None:
        cal = self.calibrator
        if cal._pool is None and cal.settings.workers > 1:
            cal._pool = ThreadPoolExecutor(max_workers=cal.settings.workers,
                                           thread_name_prefix="lidarcal-calibrate")
            self.owner = True

    def __exit__(self, *exc: object) -> None:
        cal = self.calibrator
        if self.owner and cal._pool is not None:
            cal._pool.shutdown(wait=True, cancel_futures=True)
            cal._pool = None


def _at(obs: Observations, matched_at: np.ndarray, delta: np.ndarray) -> Observations:
    """Observations matched at ``matched_at`` re-expressed at ``delta``: the discrepancy left
    after the correction ``delta`` is ``y - a . (delta - matched_at)`` (linear in between)."""
    if not len(obs) or not np.any(delta - matched_at):
        return obs
    return Observations(obs.rows, obs.residuals(delta - matched_at), obs.weights, obs.group,
                        obs.cluster)


#: Largest step (in sigmas, times ``convergence_fraction``) of a cycle of the matching taken
#: for convergence: a correspondence entering and leaving the matched set at each iteration
#: moves the estimate back and forth by a few hundredths of its sigmas, for ever.
_CYCLE_FACTOR = 10.0


def _matching_cycle(history: list[np.ndarray], sigma: np.ndarray, est: np.ndarray,
                    fraction: float) -> bool:
    """The estimates of the last iterations repeat with a period of two or three (to 1e-6
    sigma), and their steps are below ``_CYCLE_FACTOR * fraction`` sigma: the iteration has
    settled into a cycle of the discrete matching, not drifting."""
    if len(history) < 4:
        return False
    last = history[-1][est]
    width = sigma[est]
    for period in (2, 3):
        if len(history) > period and np.all(
                np.abs(last - history[-1 - period][est]) <= 1e-6 * width):
            spread = np.ptp(np.stack([h[est] for h in history[-period - 1:]]), axis=0)
            return bool(np.all(spread <= _CYCLE_FACTOR * fraction * width))
    return False


def _ground_speed(trajectory: Trajectory, t: np.ndarray) -> float:
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


def _rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(values**2))) if values.size else float("nan")


def _robust_qa(distances: np.ndarray, floor_m: float) -> tuple[float, float]:
    """RMS and 95th percentile of |discrepancy| without gross mismatches (metres).

    Correspondences further than ``max(floor_m, 5 x 1.4826 x median |d|)`` from their patch are
    left out: points on walls or in trees matched to a neighbouring roof or ground patch. The
    scale is taken about zero, so a systematic offset between strips widens the cut and shows
    in full rather than being trimmed away.
    """
    d = np.abs(distances[np.isfinite(distances)])
    if not d.size:
        return float("nan"), float("nan")
    cut = max(floor_m, 5.0 * 1.4826 * float(np.median(d)))
    kept = d[d <= cut]
    return _rms(kept), float(np.percentile(kept, 95))


def calibrate(
    mission: Mission,
    settings: CalibrationSettings | None = None,
    *,
    progress: Progress | None = None,
) -> CalibrationResult:
    """Calibrate a mission: see :class:`Calibrator`.

    Raises
    ------
    NothingEstimated
        The mission holds strips but the adjustment could estimate nothing (a single strip,
        no overlap, no usable patches, nothing observable); it carries the QA of the strips
        as delivered.
    """
    cal = Calibrator.from_mission(mission, settings or CalibrationSettings(), progress=progress)
    try:
        return cal.run()
    except NothingEstimated:
        raise
    except CalibrationError as exc:
        raise NothingEstimated(str(exc), cal.unestimated_result(str(exc))) from None


__all__: Sequence[str] = (
    "CalibrationResult", "CalibrationSettings", "Calibrator", "ControlResidual", "Iteration",
    "NothingEstimated", "PairDiscrepancies", "PairStats", "calibrate", "footprint_keys",
    "outside_strips",
)
