"""The matching side of a calibration: strips, their pairs, TINs and point-to-patch matches.

:class:`PairMatcher` turns matches into the rows the adjustment takes (docs/method.md eq. [11]
for strip pairs, [12] for control points).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import replace
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from lidarcal_ros.core.adjustment.ins_noise import PoseLoading, side_loading
from lidarcal_ros.core.adjustment.least_squares import Observations
from lidarcal_ros.core.calibration.bounded import StripExtent, control_cells
from lidarcal_ros.core.calibration.control_surface import ControlSurface, fit_control_planes
from lidarcal_ros.core.calibration.pairs import (
    CorrectedStrips,
    Correction,
    FootprintGrid,
    PreparedStrip,
    StripPair,
    find_pair,
    footprint_keys,
    ground_speed,
    stratified_sample,
)
from lidarcal_ros.core.calibration.threads import StageClock, WorkerPool
from lidarcal_ros.core.calibration.tin import PatchMatches, Tin, match_to_tin
from lidarcal_ros.core.georeferencing.bias_model import (
    add_geometry_normal_rows,
    correct_points_exact,
    corrected_geometry,
    exact_correction,
)
from lidarcal_ros.core.georeferencing.laser_geometry import LaserGeometry, PositioningModel
from lidarcal_ros.core.georeferencing.rigorous import (
    LaserVectorQA,
    ModelChoice,
    laser_vector_qa,
    scan_qa,
    strip_geometry,
)
from lidarcal_ros.core.georeferencing.sensor_frame import point_rates
from lidarcal_ros.core.mission import ControlPoints, Strip, Trajectory
from lidarcal_ros.core.params import N_PARAMETERS
from lidarcal_ros.core.trajectory.strip_errors import (
    TrajectoryRows,
    TrajectoryState,
    strip_offset_sigmas,
)
from lidarcal_ros.errors import CalibrationError

if TYPE_CHECKING:  # (the options of calibrate(), which drives this module)
    from lidarcal_ros.core.calibration.calibrate import CalibrationSettings
    from lidarcal_ros.core.calibration.pair_work import PairWork



#: Points whose laser vectors the laser-vector QA of a strip makes at a time.
QA_BLOCK = 1 << 18


class SurfaceTerms(NamedTuple):
    """A surface's side of correspondences (:meth:`PairMatcher._surface_terms`): the observed
    normals (q, 3), ``n^T A_B`` at the foot (q, 8), the observed discrepancy (q,) m, the
    foot's time (q,) s, and the vertices' laser geometry (``geometry.take(where)``, where
    (q, K))."""

    normal: np.ndarray
    rows: np.ndarray
    y: np.ndarray
    t_foot: np.ndarray
    geometry: LaserGeometry
    where: np.ndarray


class PairMatcher:
    """The strips of a calibration, their pairs, and the matching of both.

    Parameters
    ----------
    settings : CalibrationSettings
    clock : StageClock
        Where the CPU time of each stage is summed.
    workers : WorkerPool
        The threads the per-strip and per-pair work runs in.

    Attributes
    ----------
    strips : list of PreparedStrip
        In the order added.
    pairs : list of StripPair
        In the order formed (``StripPair.index``).
    """

    def __init__(self, settings: CalibrationSettings, clock: StageClock,
                 workers: WorkerPool) -> None:
        self.settings = settings
        self.clock = clock
        self.workers = workers
        self.footprint = FootprintGrid(settings.overlap_cell_m)
        self.strips: list[PreparedStrip] = []
        self.pairs: list[StripPair] = []
        #: Every strip's trajectory error as estimated so far (docs/method.md section 11).
        self.trajectory = TrajectoryState(settings.trajectory.model,
                                          settings.trajectory.knot_interval_s)
        #: Where the per-pair matching runs instead of the threads (other processes), if set.
        self.remote: PairWork | None = None
        #: Build the TINs one at a time (a bounded-memory calibration: Triangle holds the
        #: interpreter lock anyway, and a second strip's temporaries beside its mesh raised
        #: the peak)
        self.tins_in_turn = False

    @property
    def n_points(self) -> int:
        """Points held (dropped strips excluded)."""
        return sum(len(ps.strip) for ps in self.strips if not ps.dropped)

    def add_strip(self, strip: Strip, trajectory: Trajectory, *,
                  whole: tuple[StripExtent, np.ndarray] | None = None
                  ) -> list[tuple[int, int]]:
        """Prepare a strip (local trajectory, footprint, sampling priority) and find its
        pairs with the strips already held. ``whole``: ``strip`` holds part of a strip's
        points only (a bounded-memory calibration), whose whole :class:`StripExtent` and
        the sampling priority of each point held are these (its footprint, density and
        span are then the whole strip's).

        Returns the ``(strip_id, strip_id)`` pairs it forms.

        Raises
        ------
        TrajectoryError
            The trajectory does not cover the strip's points.
        CalibrationError
            A strip with this id is already held.
        """
        with self.clock("local trajectories"):
            return self._add_strip(strip, trajectory, whole)

    def _add_strip(self, strip: Strip, trajectory: Trajectory,
                   whole: tuple[StripExtent, np.ndarray] | None) -> list[tuple[int, int]]:
        s = self.settings
        if any(ps.strip_id == strip.strip_id for ps in self.strips):
            raise CalibrationError(f"strip {strip.strip_id} added twice")
        geom, choice = strip_geometry(strip.t, strip.xyz, trajectory,
                                      window=s.window,
                                      source=f"strip {strip.strip_id}",
                                      heading_source=s.heading_source, model=s.model,
                                      scanner=s.scanner)
        if s.timing:  # dS's place holds the timing bias dt (docs/method.md section 12)
            geom.timing = point_rates(strip.t, strip.xyz, geom.origin, trajectory,
                                      source=f"strip {strip.strip_id}")
        if s.ins_noise.active and s.ins_noise.step_s is None and trajectory.t.size > 1:
            # the INS's errors on its samples' grid (the trajectory's median step); in the
            # settings, which the pair jobs of other processes carry
            self.settings = replace(s, ins_noise=replace(
                s.ins_noise, step_s=float(np.median(np.diff(trajectory.t)))))
        speed = ground_speed(trajectory, strip.t)
        qa = laser_vector_qa(geom, fov_deg=s.fov_deg, speed_mps=speed)
        # the laser vectors of the delivered points are not held (40-48 bytes a point):
        # every correction and design row computes those of the points it moves
        geom = geom.firing_frames()
        span: tuple[float, float] | None
        if whole is None:
            cells = np.unique(self.footprint.keys(strip.xyz[:, :2]))
            density = len(strip) / max(cells.size * s.overlap_cell_m**2, 1.0)
            priority = np.random.default_rng([s.seed, strip.strip_id]).random(len(strip))
            span = (float(np.nanmin(strip.t)), float(np.nanmax(strip.t))) if len(strip) \
                else None
        else:
            extent, priority = whole
            cells, density, span = extent.cells, extent.density, extent.span
            speed = ground_speed(trajectory, np.asarray(span))
        return self.add_prepared(PreparedStrip(
            strip, geom, density, cells, priority, choice, qa, speed,
            navigation_sigmas=None if span is None else strip_offset_sigmas(trajectory, *span),
            span=None if whole is None else span))

    def add_released(self, strip_id: int, t0: float, t1: float) -> PreparedStrip:
        """Hold a strip released before a restart, flown from ``t0`` to ``t1`` (s), for its
        trajectory error alone (a placeholder: no points, no pairs); returns it."""
        empty = np.empty(0, dtype=np.int64)
        ps = PreparedStrip(Strip(strip_id, np.empty((0, 3)), np.empty(0)), LaserGeometry.empty(),
                           0.0, empty, np.empty(0),
                           ModelChoice(PositioningModel.LEVEL, "released before a restart"),
                           LaserVectorQA(*(math.nan,) * 5), math.nan, dropped=True,
                           placeholder=True)
        self.add_prepared(ps, span=(t0, t1))
        return ps

    def add_prepared(self, ps: PreparedStrip, *,
                     span: tuple[float, float] | None = None) -> list[tuple[int, int]]:
        """Hold a strip another matcher of the same settings prepared (its TIN and geometry
        shared: a live ``auto`` calibration runs two trajectory models over the same strips)
        and find its pairs with the strips already held; :meth:`add_strip` says what it
        returns and raises. ``span``: the strip's first and last time (s), where its points
        are not held."""
        if any(held.strip_id == ps.strip_id for held in self.strips):
            raise CalibrationError(f"strip {ps.strip_id} added twice")
        s = self.settings
        strip = ps.strip
        self.strips.append(ps)
        if span is None:
            span = ps.span
        if span is None:
            span = ((float(np.nanmin(strip.t)), float(np.nanmax(strip.t))) if len(strip)
                    else (0.0, 0.0))
        self.trajectory.add_strip(*span, navigation_sigmas=ps.navigation_sigmas)
        new = len(self.strips) - 1
        formed = []
        for other in range(new):
            pair = find_pair(self.strips, other, new, index=len(self.pairs),
                             footprint=self.footprint, min_overlap_cells=s.min_overlap_cells,
                             max_candidates=s.max_candidates_per_pair)
            if pair is not None:
                self.pairs.append(pair)
                formed.append((self.strips[other].strip_id, strip.strip_id))
        return formed

    def drop_strip(self, strip_id: int, delta: np.ndarray) -> int:
        """Release a strip's points (memory budget); its pairs keep their last observations
        (none matched yet: no observation, at the current estimate ``delta``).

        Returns the number of points released.
        """
        for k, ps in enumerate(self.strips):
            if ps.strip_id == strip_id:
                for pair in self.pairs:
                    if k in (pair.a, pair.b) and pair.frozen is None:
                        pair.frozen_delta = pair.last_delta if pair.last_delta is not None \
                            else delta.copy()
                        pair.frozen = pair.last if pair.last is not None else \
                            Observations.empty()
                if ps.dropped:  # (released already through another matcher sharing it)
                    return 0
                n = len(ps.strip)
                ps.dropped = True
                ps.tin = None
                empty = np.empty((0, 3))
                ps.strip = Strip(ps.strip_id, empty, np.empty(0))
                ps.geometry0 = ps.geometry0.take(np.zeros(0, dtype=np.int64))
                ps.corrected = None
                ps.priority = np.empty(0)
                return n
        return 0

    def tin(self, k: int) -> Tin:
        """The TIN of strip ``k``, built at the first call."""
        ps = self.strips[k]
        if ps.tin is None:
            with self.clock("TINs"):
                ps.tin = Tin(ps.strip.xyz, self.settings.tin_quality(ps.density))
        return ps.tin

    def build_tins(self, strips: Iterable[int]) -> None:
        """Build the TINs of ``strips`` not built yet (largest first, in the threads)."""
        todo = sorted({k for k in strips if self.strips[k].tin is None and
                       not self.strips[k].dropped}, key=lambda k: -len(self.strips[k].strip))
        self.workers.map(self.tin, todo, "building TINs" if todo else None,
                         in_turn=self.tins_in_turn)

    def corrected(self, k: int, delta: np.ndarray, *, delivered: bool = False) -> np.ndarray:
        """Corrected coordinates of strip k ((n, 3), map frame, m): by the
        estimate ``delta`` and the strip's trajectory error as estimated, or with
        ``delivered`` by ``delta`` alone (the strips as delivered at ``delta`` zero: what a
        pair's sample points are chosen on, whatever the errors estimated by then).

        The strip's laser-frame geometry (x, z, beta) is then that of the corrected points
        (:meth:`geometry`): the design rows are the Jacobian at the current estimate.
        Evaluated at the delivered points instead, effects that cancel between opposite lines
        (dr, dS, dkappa) would appear not to cancel, and mimic dphi.
        """
        ps = self.strips[k]
        error = self.trajectory.strip_params(k) if self.trajectory.active and not delivered \
            else np.zeros(0)
        key = np.asarray(delta, dtype=np.float64).tobytes() + error.tobytes()
        if ps.corrected is None or ps.corrected.key != key:
            # the strip's last correction released first (unless a caller still holds it):
            # it and the new one held at once cost some 90 bytes a point more at the peak
            ps.corrected = None
            with self.clock("corrections"):
                geometry: LaserGeometry | None = None
                if ps.geometry0.timing is None:
                    # the geometry only where the design rows want it (:meth:`geometry`): 40
                    # to 48 bytes a held point less
                    corrected = correct_points_exact(ps.strip.xyz, ps.geometry0, delta)
                else:
                    corrected, _, geometry = exact_correction(ps.strip.xyz, ps.geometry0,
                                                              delta)
                removed = error.copy() if error.size and np.any(error) else None
                if removed is not None:
                    # docs/method.md section 11: X_corrected = X_b - A delta - e_s(t); the laser
                    # geometry stays that of the points before e_s (:meth:`geometry`)
                    corrected -= self.trajectory.error(k, ps.strip.t)
            ps.corrected = Correction(key, corrected, geometry, removed)
        return ps.corrected.corrected

    def release_corrections(self) -> None:
        """Forget every strip's latest correction (:meth:`corrected` makes it again)."""
        for ps in self.strips:
            ps.corrected = None

    def geometry(self, k: int, index: np.ndarray) -> tuple[LaserGeometry, np.ndarray]:
        """The laser geometry of strip ``k``'s points ``index`` (any shape) at its latest
        correction (:meth:`corrected`; before any, as delivered), and where each point of
        ``index`` is in it: ``geometry.take(where)`` are the points ``index``."""
        ps = self.strips[k]
        if ps.corrected is not None and ps.corrected.geometry is not None:
            return ps.corrected.geometry, index
        wanted, where = np.unique(index, return_inverse=True)
        return self._geometry_of(k, wanted), where.reshape(index.shape)

    def _geometry_of(self, k: int, index: np.ndarray) -> LaserGeometry:
        """The geometry of strip ``k``'s corrected points ``index`` (unique, sorted; before
        any correction, the delivered points'), from the points before the trajectory error
        where one was removed (``(X - e) + e``: within an ulp of them, not their bits)."""
        ps = self.strips[k]
        if ps.corrected is None:
            return corrected_geometry(ps.strip.xyz, ps.geometry0, index)
        error = ps.corrected.error
        if error is None or not len(index):
            return corrected_geometry(ps.corrected.corrected, ps.geometry0, index)
        before = ps.corrected.corrected[index] + \
            self.trajectory.bases[k].error(error, ps.strip.t[index])
        return corrected_geometry(before, ps.geometry0.take(index), np.arange(len(index)))

    def match_pair(
        self, pair: StripPair, points_idx: np.ndarray, delta: np.ndarray,
        corrected: CorrectedStrips, threshold: float,
    ) -> PatchMatches:
        """Match the points ``points_idx`` of the pair's strip ``a`` to the TIN of its strip
        ``b``, both corrected by the estimate ``delta`` (``corrected``: by strip, the
        corrected points), within ``threshold`` metres."""
        a_xyz, b_xyz = corrected[pair.a], corrected[pair.b]
        # The sample is matched every iteration: start each search at its last patch.
        on_sample = points_idx is pair.sample
        start = pair.last_triangle if on_sample else None
        tin = self.tin(pair.b)
        with self.clock("matching"):
            m = match_to_tin(a_xyz[points_idx], tin, b_xyz, max_normal_distance=threshold,
                             delivered=self._delivered_if_moved(pair.b, delta), start=start)
        if on_sample:
            pair.last_triangle = m.triangle
        return m

    def _delivered_if_moved(self, k: int, delta: np.ndarray) -> np.ndarray | None:
        """Strip ``k``'s delivered points where ``delta`` or its trajectory error moves
        them (its TIN's queries are then located in the delivered geometry), else None."""
        return self.strips[k].strip.xyz if np.any(delta) or self._moved(k) else None

    def _moved(self, k: int) -> bool:
        """Strip ``k``'s points are moved by a trajectory error estimated for it."""
        return self.trajectory.active and bool(np.any(self.trajectory.strip_params(k)))

    def _patch_terms(
        self, k: int, m: PatchMatches
    ) -> SurfaceTerms:
        """:meth:`_surface_terms` of the valid matches to strip ``k``'s TIN facets (the foot
        barycentric in its triangle)."""
        ok = m.valid
        tin = self.tin(k)
        return self._surface_terms(k, tin.simplices[m.triangle[ok]], m.weights[ok],
                                   m.normal[ok], m.distance[ok], tin.sloped[m.triangle[ok]])

    def _surface_terms(
        self, k: int, verts: np.ndarray, w: np.ndarray, normal: np.ndarray,
        distance: np.ndarray, sloped: np.ndarray,
    ) -> SurfaceTerms:
        """For correspondences with strip ``k``'s surface, its foot ``sum w_j X_j`` over the
        points ``verts`` (q, K) with weights ``w`` (q, K), its normal and signed distance (m):
        the observed normals (vertical unless ``sloped``), ``n^T A_B`` at the foot, the
        observed discrepancy (the distance along the observed normal), the time of the
        foot (s) and the vertices' laser geometry."""
        with self.clock("design rows"):
            n = self._observed_normal(normal, sloped)
            geometry, where = self.geometry(k, verts)
            rows = np.zeros((verts.shape[0], N_PARAMETERS))
            for v in range(verts.shape[1]):
                add_geometry_normal_rows(rows, n, geometry, where[:, v], w[:, v])
            y = distance * (n * normal).sum(axis=1)
            t_foot = (self.strips[k].strip.t[verts] * w).sum(axis=1)
        return SurfaceTerms(n, rows, y, t_foot, geometry, where)

    def _plane_terms(
        self, k: int, plane: ControlSurface
    ) -> SurfaceTerms:
        """:meth:`_surface_terms` of control points on the planes of strip ``k``'s points
        (the foot a least-squares combination of the plane's neighbours)."""
        flat = plane.normal[:, 2] >= math.cos(math.radians(self.settings.flat_slope_deg))
        return self._surface_terms(k, plane.neighbours, plane.weights, plane.normal,
                                   plane.distance, ~flat)

    def _control_surface(self, k: int, control: np.ndarray, xyz: np.ndarray,
                         threshold: float) -> ControlSurface:
        """The planes of strip ``k``'s points (``xyz``: corrected) under the ``control``
        points, valid only within ``threshold`` metres of them; none where
        ``control_plane_points`` is 0."""
        ps, k_points = self.strips[k], self.settings.control_plane_points
        if k_points == 0:
            return fit_control_planes(control, xyz, np.empty(0, np.int64), k=3, max_radius=0.0)
        cell = self.settings.overlap_cell_m
        near_cells = control_cells(control[:, :2], cell)
        candidates = np.flatnonzero(np.isin(self.footprint.keys(ps.strip.xyz[:, :2]),
                                            near_cells))
        # Twice the radius that holds k points at the strip's density: sparser than that
        # (a gap, the strip's edge) the neighbours would not surround the control point.
        radius = min(2.0 * math.sqrt(k_points / (math.pi * ps.density)), cell)
        surface = fit_control_planes(control, xyz, candidates, k=k_points, max_radius=radius)
        surface.valid[np.abs(surface.distance) > threshold] = False
        return surface

    def _trajectory_rows(self, a: int, t_a: np.ndarray, b: int, t_b: np.ndarray,
                         n: np.ndarray) -> TrajectoryRows | None:
        """The trajectory terms of correspondences of strip ``a``'s points at ``t_a`` (``a``
        -1: control points) against strip ``b``'s patches with feet at ``t_b``, normals ``n``;
        None where trajectory errors are not estimated."""
        if not self.trajectory.active:
            return None
        k = t_b.shape[0]
        rows = TrajectoryRows(np.full(k, a, np.int64), t_a, np.full(k, b, np.int64), t_b, n,
                              np.zeros(k))
        rows.applied = self.trajectory.projected(rows)
        return rows

    def pair_observations(
        self, pair: StripPair, points_idx: np.ndarray, m: PatchMatches
    ) -> Observations:
        """The correspondences (eq. [11]) of the valid matches ``m`` of the pair's points
        ``points_idx``."""
        sa = self.strips[pair.a]
        idx = points_idx[m.valid]
        # eq. [11]: the discrepancy n . (X_A - X_B) left by the current estimate; the
        # adjustment solves for the increment that removes it (Gauss-Newton).
        patch = self._patch_terms(pair.b, m)
        n = patch.normal
        with self.clock("design rows"):
            rows = np.zeros_like(patch.rows)
            geometry, where = self.geometry(pair.a, idx)
            add_geometry_normal_rows(rows, n, geometry, where)
            rows -= patch.rows
            cluster = self._cluster_of(sa.strip.xyz[idx])
        loading = None
        if self.settings.ins_noise.active and self.settings.ins_noise.step_s is not None:
            ok = m.valid
            with self.clock("design rows"):
                verts = self.tin(pair.b).simplices[m.triangle[ok]]
                loading = PoseLoading.of_sides(
                    self._side_loading(pair.a, idx, geometry, where, n, None),
                    [self._side_loading(pair.b, verts[:, j], patch.geometry,
                                        patch.where[:, j], n, m.weights[ok][:, j])
                     for j in range(verts.shape[1])])
        return Observations(rows, patch.y, np.ones(idx.size), np.full(idx.size, pair.index),
                            cluster, self._trajectory_rows(pair.a, sa.strip.t[idx], pair.b,
                                                           patch.t_foot, n), loading)

    def _side_loading(self, k: int, index: np.ndarray, geometry: LaserGeometry,
                      where: np.ndarray, n: np.ndarray, weight: np.ndarray | None
                      ) -> tuple[np.ndarray, np.ndarray]:
        """How strip ``k``'s points ``index`` (their laser geometry ``geometry.take(where)``)
        seen along ``n`` move with the INS's errors, each scaled by ``weight``
        (:func:`~lidarcal_ros.core.adjustment.ins_noise.side_loading`)."""
        step = self.settings.ins_noise.step_s
        assert step is not None
        strip = self.strips[k].strip
        frames = geometry.take(where)
        lever = frames.to_body(np.cross(strip.xyz[index] - frames.origin, n))
        return side_loading(strip.t[index], n, lever, step, weight)

    def _cluster_of(self, xyz: np.ndarray) -> np.ndarray:
        """Spatial cluster (cell of ``cluster_cell_m``) of observations at ``xyz``."""
        return footprint_keys(xyz[:, :2], self.settings.cluster_cell_m)

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

    def _select_sample(self, pair: StripPair, m: PatchMatches) -> np.ndarray:
        """Stratify matched candidates by patch slope and aspect; cap each class."""
        with self.clock("sample selection"):
            return stratified_sample(m, pair.candidates, self.strips[pair.a].priority,
                                     per_class_cap=self.settings.per_class_cap,
                                     flat_class_factor=self.settings.flat_class_factor)

    def control_observations(
        self, control: ControlPoints, delta: np.ndarray, threshold: float, *,
        corrected: CorrectedStrips | None = None, delivered: bool = False,
    ) -> tuple[Observations, list[tuple[int, int, float]]]:
        """Match the control points to the TINs of the strips whose footprint holds them,
        corrected by the estimate ``delta`` (with ``delivered``: by ``delta`` alone, as
        :meth:`corrected`), within ``threshold`` metres: their correspondences (eq. [12]),
        and (control index, strip index, normal distance in metres) of each match.
        ``corrected``: strips corrected so already (by strip)."""
        cp_cells = self.footprint.keys(control.xyz[:, :2])
        seen = {k: np.flatnonzero(np.isin(cp_cells, ps.cells))
                for k, ps in enumerate(self.strips) if not ps.dropped}
        seen = {k: cps for k, cps in seen.items() if cps.size}
        if self.remote is not None:
            return self.remote.control(self, control, seen, delta, threshold,
                                       delivered=delivered)
        self.build_tins(seen)
        given = corrected or {}
        corrected = {**given, **self.corrected_many((k for k in seen if k not in given), delta,
                                                    delivered=delivered)}
        parts: list[Observations] = []
        found: list[tuple[int, int, float]] = []
        for k, cps in seen.items():
            obs, matched = self.strip_control_observations(k, control, cps, delta,
                                                           corrected[k], threshold)
            parts.append(obs)
            found.extend(matched)
        return Observations.concatenate(parts), found

    def strip_control_observations(
        self, k: int, control: ControlPoints, cps: np.ndarray, delta: np.ndarray,
        xyz: np.ndarray, threshold: float,
    ) -> tuple[Observations, list[tuple[int, int, float]]]:
        """:meth:`control_observations` of the control points ``cps`` (indices) against strip
        ``k``, its points corrected by ``delta`` to ``xyz``."""
        parts = []
        found: list[tuple[int, int, float]] = []
        tin = self.tin(k)
        with self.clock("matching"):
            m = match_to_tin(control.xyz[cps], tin, xyz, max_normal_distance=threshold,
                             delivered=self._delivered_if_moved(k, delta))
        if not m.valid.any():
            return Observations.empty(), found
        # eq. [12]: n . (X_C - X_B), X_B corrected by the estimate: on the plane of the
        # control point's neighbours where they make one, else on the TIN facet.
        plane = self._control_surface(k, control.xyz[cps], xyz, threshold)
        on_plane = plane.valid & m.valid
        on_facet = m.valid & ~on_plane
        for ok, terms, distance in (
                (on_plane, self._plane_terms(k, plane.take(on_plane)), plane.distance),
                (on_facet, self._patch_terms(k, m.take(on_facet)), m.distance)):
            if not ok.any():
                continue
            weights = np.full(terms.y.size, self.settings.control_weight)
            parts.append(Observations(-terms.rows, terms.y, weights, -1 - cps[ok],
                                      self._cluster_of(control.xyz[cps[ok]]),
                                      self._trajectory_rows(-1, np.zeros(terms.y.size), k,
                                                            terms.t_foot, terms.normal)))
            found.extend((int(c), k, float(d)) for c, d in zip(cps[ok], distance[ok]))
        return Observations.concatenate(parts), found

    def laser_qa(self, delta: np.ndarray) -> dict[int, LaserVectorQA]:
        """By strip (index, those holding their points), what the laser vectors of its points
        corrected by ``delta`` say (one strip's geometry at a time)."""
        if self.remote is not None:
            return self.remote.laser_qa(self, delta)
        return {k: self.strip_laser_qa(k, delta) for k, ps in enumerate(self.strips)
                if not ps.dropped}

    def strip_laser_qa(self, k: int, delta: np.ndarray) -> LaserVectorQA:
        """:meth:`laser_qa` of strip ``k`` (the laser vectors of :data:`QA_BLOCK` points at a
        time: their scan angles and along-track parts held, 8-16 bytes a point, not all of
        them: 40-48)."""
        self.corrected(k, delta)
        ps = self.strips[k]
        if ps.corrected is not None and ps.corrected.geometry is not None:
            parts: Iterable[LaserGeometry] = [ps.corrected.geometry]
        else:
            n = len(ps.strip)
            parts = (self._geometry_of(k, np.arange(start, min(start + QA_BLOCK, n)))
                     for start in range(0, n, QA_BLOCK))
        beta, along = [], []
        for part in parts:
            beta.append(part.beta)
            if part.y is not None:
                along.append(part.y)
        g = ps.geometry0
        return scan_qa(np.concatenate([np.empty(0), *beta]),
                       np.concatenate(along) if along else None, scanner=g.scanner,
                       model=g.model, fov_deg=self.settings.fov_deg, speed_mps=ps.speed_mps)

    def choose_samples(self, pairs: Sequence[StripPair]) -> None:
        """Match pairs met for the first time once at zero correction: choose their sample
        points and keep their "before" discrepancies."""
        if not pairs:
            return
        if self.remote is not None:
            chosen = self.remote.choose(self, pairs)
        else:
            self.build_tins(p.b for p in pairs)
            delivered = self.corrected_many(self.used_strips(pairs), np.zeros(N_PARAMETERS),
                                            delivered=True)
            chosen = self.workers.map(lambda pair: self.choose_sample(pair, delivered), pairs,
                                      "choosing sample points")
        for pair, (sample, before) in zip(pairs, chosen, strict=True):
            pair.sample, pair.before = sample, before

    def choose_sample(self, pair: StripPair, delivered: CorrectedStrips
                      ) -> tuple[np.ndarray, np.ndarray]:
        """A pair's sample points (indices into its strip ``a``) and their normal distances
        (m) to strip ``b`` as delivered (its "before" QA): its candidates matched at zero
        correction (``delivered``: by strip, as :meth:`corrected` with ``delivered``)."""
        m = self.match_pair(pair, pair.candidates, np.zeros(N_PARAMETERS), delivered,
                            self.settings.max_normal_distance_m)
        sample = self._select_sample(pair, m)
        before = m.take(np.isin(pair.candidates, sample)).distance
        return sample, before[np.isfinite(before)]

    def sample_distances(self, pair: StripPair, delta: np.ndarray,
                         corrected: CorrectedStrips, threshold: float
                         ) -> np.ndarray:
        """The normal distances (m) of the pair's sample points matched at ``delta``
        (:meth:`match_pair`'s arguments), those matched only: its "after" QA."""
        assert pair.sample is not None
        m = self.match_pair(pair, pair.sample, delta, corrected, threshold)
        return m.distance[m.valid]

    def observe(self, pair: StripPair, delta: np.ndarray,
                corrected: CorrectedStrips, threshold: float
                ) -> tuple[Observations, np.ndarray]:
        """The pair's sample matched at ``delta`` (:meth:`match_pair`'s arguments): its
        correspondences and the patch of each sample point (-1: none)."""
        assert pair.sample is not None
        m = self.match_pair(pair, pair.sample, delta, corrected, threshold)
        return self.pair_observations(pair, pair.sample, m), np.where(m.valid, m.triangle, -1)

    def match_samples(
        self, delta: np.ndarray
    ) -> tuple[list[tuple[StripPair, PatchMatches]], CorrectedStrips]:
        """Match the sample points of every pair holding its points at the estimate ``delta``
        (first threshold), choosing the samples of pairs met for the first time.

        Returns the matches of each pair and the corrected strips (see :meth:`corrected`).
        """
        s = self.settings
        live = [p for p in self.pairs if p.frozen is None]
        # Samples first: choosing them leaves every strip's geometry at the delivered points.
        self.choose_samples([p for p in live if p.sample is None])
        corrected = self.corrected_all(delta)

        def match(pair: StripPair) -> PatchMatches:
            assert pair.sample is not None
            return self.match_pair(pair, pair.sample, delta, corrected, s.max_normal_distance_m)

        return list(zip(live, self.workers.map(match, live), strict=True)), corrected

    def corrected_all(self, delta: np.ndarray) -> CorrectedStrips:
        """:meth:`corrected` of every strip that holds its points."""
        return self.corrected_many((k for k in range(len(self.strips))
                                    if not self.strips[k].dropped), delta)

    def corrected_many(self, strips: Iterable[int], delta: np.ndarray, *,
                       delivered: bool = False) -> CorrectedStrips:
        """:meth:`corrected` of ``strips`` (in the threads)."""
        ks = sorted(set(strips))
        return dict(zip(ks, self.workers.map(
            lambda k: self.corrected(k, delta, delivered=delivered), ks), strict=True))

    def used_strips(self, pairs: Sequence[StripPair]) -> set[int]:
        """The strips (indices) of ``pairs``."""
        return {k for p in pairs for k in (p.a, p.b)}


__all__ = ["QA_BLOCK", "PairMatcher"]
