"""The quasi-rigorous calibration procedure (docs/method.md sections 4-7).

:func:`calibrate` a mission, or drive a :class:`Calibrator` strip by strip;
:class:`CalibrationSettings` are its options. Its parts are the modules beside it
(docs/internals.md, "The calibration").
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from lidarcal_ros.core.adjustment.ins_noise import InsNoise
from lidarcal_ros.core.adjustment.least_squares import (
    NormalEquations,
    ObservabilityLimits,
    Observations,
    ParameterState,
    ParameterStatus,
    Solution,
)
from lidarcal_ros.core.calibration.bounded import ChosenSamples, StripExtent
from lidarcal_ros.core.calibration.iteration import (
    Convergence,
    Iteration,
    MatchedSet,
    TrajectoryTerms,
    allow_for_held_biases,
    allow_for_ins_noise,
    allow_for_shared_errors,
    judge_convergence,
    next_threshold,
    reexpress_observations,
    rematching_noise,
    robust_solve,
)
from lidarcal_ros.core.calibration.matching import PairMatcher
from lidarcal_ros.core.calibration.pair_work import PairWork
from lidarcal_ros.core.calibration.pairs import (
    CorrectedStrips,
    PreparedStrip,
    StripPair,
    height_agreement,
    no_overlap_reason,
)
from lidarcal_ros.core.calibration.result import (
    CalibrationResult,
    ControlResidual,
    NothingEstimated,
    PairDiscrepancies,
    PairStats,
    robust_qa,
)
from lidarcal_ros.core.calibration.threads import StageClock, WorkerPool
from lidarcal_ros.core.calibration.tin import TinQuality
from lidarcal_ros.core.georeferencing.heading import HeadingSource
from lidarcal_ros.core.georeferencing.laser_geometry import PositioningModel, ScannerKind
from lidarcal_ros.core.georeferencing.local_trajectory import DEFAULT_WINDOW, TrajectoryWindow
from lidarcal_ros.core.mission import ControlPoints, Mission, Strip, Trajectory
from lidarcal_ros.core.params import N_PARAMETERS, PARAMETER_NAMES, display_value
from lidarcal_ros.core.trajectory.strip_errors import (
    AUTO_SIGMA0_RATIO,
    TrajectoryErrorSettings,
    TrajectoryEstimate,
    TrajectoryModel,
    TrajectoryState,
)
from lidarcal_ros.errors import CalibrationError, ConfigError

logger = logging.getLogger(__name__)

#: Progress callback: (stage description, fraction done in [0, 1]).
Progress = Callable[[str, float], None]
#: By strip id, a whole strip's extent and the sampling priority of each of its points held
#: (:func:`calibrate`).
WholeStrips = Mapping[int, tuple[StripExtent, np.ndarray]]


@dataclass
class CalibrationSettings:
    """Options of the adjustment (flight configuration ``calibration.*`` and ``matching.*``).

    Lengths in metres, angles in degrees unless stated.
    """

    #: The biases estimated (names of :data:`~lidarcal_ros.core.params.PARAMETER_NAMES`,
    #: kept in that order); the others are held at ``fixed``.
    solve_for: tuple[str, ...] = ("dX", "dY", "domega", "dphi", "dkappa", "dr", "dS")
    #: Value of each bias not estimated, SI units (0 where not given).
    fixed: dict[str, float] = field(default_factory=dict)
    #: How far a held bias's value may be off, 1 sigma SI, by name (e.g. a robot
    #: description's lever arm): the estimated biases' covariance allows for what it moves
    #: them by (:func:`~lidarcal_ros.core.calibration.iteration.allow_for_held_biases`).
    held_sigma: dict[str, float] = field(default_factory=dict)
    #: The INS's own errors (``ins.*``): the biases' covariance allows for what they move
    #: them by (:func:`~lidarcal_ros.core.calibration.iteration.allow_for_ins_noise`); all
    #: zero: the INS taken as exact.
    ins_noise: InsNoise = field(default_factory=InsNoise)
    #: The local-trajectory window (``matching.trajectory_window_s``;
    #: :mod:`lidarcal_ros.core.georeferencing.local_trajectory`).
    window: TrajectoryWindow = DEFAULT_WINDOW
    #: Heading of the local trajectory (``matching.heading_source``;
    #: :mod:`lidarcal_ros.core.georeferencing.heading`).
    heading_source: HeadingSource = HeadingSource.AUTO
    #: ``matching.model`` (:mod:`lidarcal_ros.core.georeferencing.rigorous`).
    model: PositioningModel = PositioningModel.AUTO
    #: The scanner's full field of view, deg (``sensor.fov_deg``): the laser-vector QA.
    fov_deg: float = 50.0
    #: What the laser vectors may be (docs/method.md section 12): ``GENERAL`` for clouds
    #: georeferenced from the sensor's frame (any scanner; the trajectory that of the
    #: sensor's origin), with ``model`` ``rigorous`` and no ``dS``.
    scanner: ScannerKind = ScannerKind.LINEAR
    #: A ``GENERAL`` scanner's eighth bias (``dS``'s place: it has no mirror scale) is the
    #: timing bias ``dt`` (delivered - true time, s; docs/method.md section 12), its column
    #: each point's rate ``v + w x (X - X_o)`` on the mission's trajectory (the sensor's
    #: origin's).
    timing: bool = False
    #: With ``timing``: the largest multiple correlation of a usable ``dt`` with the other
    #: biases estimated (``sensor_frame.timing_max_correlation``; a mounting's calibration
    #: holds ``dt`` at 0 beyond it: :func:`~lidarcal_ros.core.calibration.extrinsic.
    #: timing_unseen`, whose module gives the default and why).
    timing_max_correlation: float = 0.95
    #: Largest point-to-patch distance matched at the first iteration, m.
    max_normal_distance_m: float = 2.0
    #: Smallest matching threshold later iterations shrink to, m.
    min_normal_distance_m: float = 0.15
    #: Longest patch edge, in point spacings of its strip.
    max_edge_factor: float = 4.0
    #: Steepest usable patch, deg.
    max_slope_deg: float = 70.0
    #: Largest angle between a patch and its neighbours, deg.
    max_bend_deg: float = 10.0
    #: Patches (and all their neighbours) flatter than this observe vertical effects only, deg.
    flat_slope_deg: float = 5.0
    #: Cell of the spatial clusters of the cluster-robust sigmas, m.
    cluster_cell_m: float = 25.0
    #: Cell of the footprint grid the overlaps are found on, m.
    overlap_cell_m: float = 10.0
    #: Footprint cells two strips must share to form a pair.
    min_overlap_cells: int = 20
    #: Candidate points of a pair matched at the first iteration (at most).
    max_candidates_per_pair: int = 100_000
    #: Sample points kept per slope/aspect class and pair.
    per_class_cap: int = 3_000
    #: The flat class keeps this many times ``per_class_cap``.
    flat_class_factor: int = 4
    #: Most match-solve iterations.
    max_iterations: int = 10
    #: Converged when every step is below this fraction of its sigma.
    convergence_fraction: float = 0.01
    #: Strip-pair outliers rejected beyond this many robust sigmas.
    robust_k: float = 3.0
    #: Weight of a control observation relative to a strip-pair one.
    control_weight: float = 1.0
    #: Points of the plane a control point is compared with (0: the TIN facet under it).
    control_plane_points: int = 24
    #: Seed of the sampling priorities (with each strip's id).
    seed: int = 0
    #: Threads the calibration runs strips and strip pairs in (TINs, corrections, matching);
    #: the result does not depend on it.
    workers: int = 2
    #: When a parameter is reported as not separable or not observable.
    limits: ObservabilityLimits = field(default_factory=ObservabilityLimits)
    #: Per-strip trajectory errors estimated with the biases (docs/method.md section 11).
    trajectory: TrajectoryErrorSettings = field(
        default_factory=lambda: TrajectoryErrorSettings(TrajectoryModel.NONE))

    def __post_init__(self) -> None:
        self.solve_for = tuple(n for n in PARAMETER_NAMES if n in self.solve_for)
        if self.timing and self.scanner is not ScannerKind.GENERAL:
            raise ConfigError("calibration: a timing bias is a parameter of clouds in the "
                              "sensor's frame (a general scanner's) only")
        if self.scanner is ScannerKind.GENERAL and not self.timing and (
                "dS" in self.solve_for or self.fixed.get("dS", 0.0)):
            raise ConfigError("calibration: dS (a mirror's scale) is no parameter of a general "
                              "scanner; leave it out of solve_for and fixed")

    def held(self, delta: np.ndarray) -> np.ndarray:
        """A copy of the estimate ``delta`` (SI) with the biases not solved for at their
        ``fixed`` values, as a solve leaves them."""
        out = np.array(delta, dtype=np.float64)
        for k, name in enumerate(PARAMETER_NAMES):
            if name not in self.solve_for:
                out[k] = float(self.fixed.get(name, 0.0))
        return out

    def tin_quality(self, density: float) -> TinQuality:
        """Patch rules for a strip of ``density`` points per m^2 (edges up to
        ``max_edge_factor`` point spacings)."""
        spacing = 1.0 / np.sqrt(max(density, 1e-6))
        return TinQuality(max_edge_m=self.max_edge_factor * spacing,
                          max_slope_deg=self.max_slope_deg, max_bend_deg=self.max_bend_deg,
                          flat_slope_deg=self.flat_slope_deg)


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
        self.delta = np.zeros(N_PARAMETERS)
        self.threshold = settings.max_normal_distance_m
        self.dropped_non_finite = 0
        self.thinned_points = 0
        self.normal_equations = NormalEquations()
        self._restored = Observations.empty()
        self._restored_delta = np.zeros(N_PARAMETERS)
        self._control_before: list[tuple[int, int, float]] | None = None
        self.workers = WorkerPool(settings.workers, self._progress)
        self.clock = StageClock()
        self.matcher = PairMatcher(settings, self.clock, self.workers)
        #: Sigma of a correspondence of weight 1 (m) the trajectory priors are weighed with:
        #: the configured one, then each adjustment's own sigma0.
        self.unit_sigma = settings.trajectory.observation_sigma_m

    @classmethod
    def from_mission(
        cls, mission: Mission, settings: CalibrationSettings, *,
        progress: Progress | None = None, whole: WholeStrips | None = None,
        samples: ChosenSamples | None = None,
    ) -> Calibrator:
        """A calibrator holding every strip of ``mission`` (``whole`` and ``samples``: as
        :func:`calibrate`)."""
        if not mission.strips:
            raise CalibrationError("mission has no strips")
        cal = cls(settings, control=mission.control, progress=progress)
        cal.matcher.tins_in_turn = whole is not None
        cal.dropped_non_finite = mission.dropped_non_finite
        cal.thinned_points = mission.thinned_points
        for k, strip in enumerate(mission.strips):
            cal.add_strip(strip, mission.trajectory,
                          whole=None if whole is None else whole[strip.strip_id])
            cal._progress("local trajectories", (k + 1) / len(mission.strips))
        logger.info("%d overlapping strip pairs", len(cal.pairs))
        if samples is not None:
            cal.use_samples(samples)
        return cal

    def use_samples(self, samples: ChosenSamples) -> None:
        """Take the sample points (and "before" distances) of the pairs formed so far from
        ``samples`` (by the pair's strip ids: point strip, surface strip) instead of choosing
        them from candidates held (a bounded-memory calibration, whose strips hold little
        beyond the samples' surroundings)."""
        for pair in self.pairs:
            key = (self.strips[pair.a].strip_id, self.strips[pair.b].strip_id)
            if pair.sample is None and key in samples:
                pair.sample, before = samples[key]
                pair.candidates = pair.sample
                pair.before = before
        if all(pair.sample is not None for pair in self.pairs):
            # every sample chosen: the sampling priorities are not needed (8 bytes a point)
            for ps in self.strips:
                ps.priority = np.empty(0)

    # ------------------------------------------------------------------ strips
    @property
    def strips(self) -> list[PreparedStrip]:
        """The strips held, in the order added (:attr:`PairMatcher.strips`)."""
        return self.matcher.strips

    @property
    def pairs(self) -> list[StripPair]:
        """The strip pairs formed, in that order (:attr:`PairMatcher.pairs`)."""
        return self.matcher.pairs

    @property
    def n_points(self) -> int:
        """Points held (dropped strips excluded)."""
        return self.matcher.n_points

    def set_control(self, control: ControlPoints | None) -> None:
        """Control points for the runs from now on (their matches against the delivered
        strips are found again)."""
        self.control = control
        self._control_before = None

    def add_strip(self, strip: Strip, trajectory: Trajectory, *,
                  whole: tuple[StripExtent, np.ndarray] | None = None
                  ) -> list[tuple[int, int]]:
        """Prepare a strip and find its pairs with the strips already held; the
        ``(strip_id, strip_id)`` pairs it forms (:meth:`PairMatcher.add_strip`, which says
        what it raises and what ``whole`` is)."""
        return self.matcher.add_strip(strip, trajectory, whole=whole)

    def restart(self) -> None:
        """Back to where a new calibrator starts, the strips and pairs kept: the estimate at
        zero, the first matching threshold, every strip's trajectory error at zero and the
        priors weighed with the configured observation sigma (a full solve from scratch)."""
        self.delta = np.zeros(N_PARAMETERS)
        self.threshold = self.settings.max_normal_distance_m
        self.trajectory.params = np.zeros_like(self.trajectory.params)
        self.unit_sigma = self.settings.trajectory.observation_sigma_m

    def add_released_strip(self, strip_id: int, span: tuple[float, float]) -> PreparedStrip:
        """Hold a strip released before a restart, flown over ``span`` (first and last time,
        s), for its trajectory error alone (:meth:`PairMatcher.add_released`)."""
        return self.matcher.add_released(strip_id, *span)

    def add_prepared_strip(self, ps: PreparedStrip, *,
                           span: tuple[float, float] | None = None) -> list[tuple[int, int]]:
        """Hold a strip another calibrator of the same settings prepared, sharing its TIN
        and geometry (:meth:`PairMatcher.add_prepared`, ``span`` as there); the pairs it
        forms."""
        return self.matcher.add_prepared(ps, span=span)

    def drop_strip(self, strip_id: int) -> int:
        """Release a strip's points (memory budget); its pairs keep their last observations
        (:meth:`match_before_release` first).

        Returns the number of points released.
        """
        self.match_before_release(strip_id)
        return self.matcher.drop_strip(strip_id, self.delta)

    def match_before_release(self, strip_id: int) -> None:
        """Match the pairs of a strip about to be released that were never matched (their
        samples chosen, matched at the current estimate): released, they keep those
        correspondences instead of none (a calibrator whose runs have not come to them: the
        rival model of a live ``auto`` calibration)."""
        held = [k for k, ps in enumerate(self.strips) if ps.strip_id == strip_id and
                not ps.dropped]
        pending = [p for p in self.pairs if held and held[0] in (p.a, p.b) and
                   p.frozen is None and p.last is None]
        if not pending:
            return
        delta = self.delta.copy()
        with self.workers.threads():
            self.matcher.choose_samples([p for p in pending if p.sample is None])
            corrected = self.matcher.corrected_many(self.matcher.used_strips(pending), delta)
            for pair in pending:
                assert pair.sample is not None
                m = self.matcher.match_pair(pair, pair.sample, delta, corrected, self.threshold)
                pair.last = self.matcher.pair_observations(pair, pair.sample, m)
                pair.last_delta = delta

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
        return Observations.concatenate(
            reexpress_observations(obs, at, self.delta, self.matcher.trajectory)
            for obs, at in self._kept())

    def restore_frozen(self, obs: Observations) -> None:
        """Take frozen correspondences back from a checkpoint (expressed at ``self.delta``:
        set the estimate first)."""
        self._restored = obs
        self._restored_delta = self.delta.copy()

    # ------------------------------------------------------------------ adjustment
    def _robust_solve(self, obs: Observations, delta: np.ndarray,
                      trajectory: TrajectoryTerms | None) -> Solution:
        """Solve for the increment to ``delta`` (and the trajectory errors' in
        ``trajectory``), zeroing the weights of outliers (> robust_k robust sigmas) until
        they no longer change.

        Returns the solution with ``delta`` = current estimate + increment; parameters not
        solved for are moved to their fixed values.
        """
        s = self.settings
        # With the trajectory errors free, the lever arm (a shift of each strip) and dkappa
        # (an along-track one) are determined only through the navigation priors and changes
        # of attitude: kept with their wide sigmas, not held at a value the strips' errors
        # would then absorb (conclude() says so).
        limits = s.limits if trajectory is None else replace(s.limits, max_sigma={})
        with self.clock("normal equations"):
            return robust_solve(obs, delta, solve_for=s.solve_for, fixed=s.fixed,
                                limits=limits, robust_k=s.robust_k, trajectory=trajectory)

    def _trajectory_step(self, tau_step: np.ndarray, sigma0: float,
                         verdict: Convergence) -> Convergence:
        """Apply the trajectory errors' increment (all coefficients) and weigh it into
        ``verdict``: plainly converged only where every increment is below the convergence
        fraction of its prior sigma. The adjustment's ``sigma0`` (m) weighs the priors from
        now on."""
        s = self.settings
        if np.isfinite(sigma0) and sigma0 > 0:
            self.unit_sigma = sigma0
        self.trajectory.params = self.trajectory.params + tau_step
        ratio = np.abs(tau_step) / self.trajectory.prior_sigmas(s.trajectory)
        if verdict.converged and verdict.outcome.startswith("converged:") and \
                ratio.size and float(ratio.max()) > s.convergence_fraction:
            return Convergence(False, False, "not converged: a strip's trajectory error moved "
                               f"by {float(ratio.max()):.2g} of its prior sigma")
        return verdict

    @property
    def trajectory(self) -> TrajectoryState:
        """Every strip's trajectory error as estimated so far (docs/method.md section 11)."""
        return self.matcher.trajectory

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
        with self.workers.threads():
            iterations = self.iterate(new_pairs_only=new_pairs_only)
            while True:
                done = next(iterations)
                if done is not None and (done.ended or done.number >= limit):
                    return self.conclude(done)

    def _matched_pairs(
        self, live: Sequence[StripPair], delta: np.ndarray,
        corrected: CorrectedStrips, iteration: int,
    ) -> Iterator[tuple[StripPair, Observations, np.ndarray]]:
        """Each live pair's sample matched at ``delta``: the pair, its observations and the
        patch of each sample point (-1: none). Within :meth:`run` every pair is matched at
        once in the threads; otherwise one by one as the caller takes them, so that it can
        pause between pairs. ``corrected`` (by strip) gains the strips corrected on the way."""

        def observe(pair: StripPair) -> tuple[Observations, np.ndarray]:
            for k in (pair.a, pair.b):
                if k not in corrected:
                    corrected[k] = self.matcher.corrected(k, delta)
            return self.matcher.observe(pair, delta, corrected, self.threshold)

        label = f"iteration {iteration}: matching"
        remote = self.matcher.remote
        if remote is not None:  # (the strips corrected where the pairs are matched)
            self._progress(label, 0.0)
            for pair, (last, patches) in zip(live, remote.observe(self.matcher, live, delta,
                                                                  self.threshold), strict=True):
                yield pair, last, patches
            return
        if self.workers.running:
            # Every strip corrected first, so that the threads only read ``corrected``.
            corrected.update(self.matcher.corrected_many(self.matcher.used_strips(live), delta))
            for pair, (last, patches) in zip(live, self.workers.map(observe, live, label),
                                             strict=True):
                yield pair, last, patches
            return
        for p_i, pair in enumerate(live):
            self._progress(label, p_i / max(len(live), 1))
            yield (pair, *observe(pair))

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
        self.matcher.choose_samples(fresh)
        self._control_matches_before()
        iteration = 0
        history: list[np.ndarray] = []
        steps: list[np.ndarray] = []
        sigmas: list[np.ndarray] = []
        noises: list[np.ndarray] = []
        changed: list[int] = []
        matched_before: MatchedSet | None = None
        while True:
            iteration += 1
            delta = self.delta.copy()
            corrected: CorrectedStrips = {}
            # Kept correspondences re-expressed at the current estimate (Gauss-Newton form).
            parts = [reexpress_observations(obs, at, delta, self.trajectory)
                     for obs, at in frozen]
            # Each live pair's (index, first row, patch of each sample point or -1).
            layout: list[tuple[int, int, np.ndarray]] = []
            for pair, last, patches in self._matched_pairs(live, delta, corrected, iteration):
                pair.last = last
                pair.last_delta = delta.copy()
                layout.append((pair.index, sum(map(len, parts)), patches))
                parts.append(last)
                yield None
            if control is not None and len(control):
                parts.append(self.matcher.control_observations(
                    control, delta, s.max_normal_distance_m, corrected=corrected)[0])
            obs = Observations.concatenate(parts)
            # the strips corrected at this estimate are not held past the matching (24 bytes
            # a held point): the adjustment's normal equations and trajectory blocks peak
            # without them, and the next estimate corrects every strip anew anyway
            corrected.clear()
            self.matcher.release_corrections()
            if len(obs) == 0:
                raise CalibrationError(
                    "no point-to-patch correspondences: the overlaps hold no usable patches"
                )
            self._progress(f"iteration {iteration}: adjusting", 1.0)
            terms = TrajectoryTerms(self.trajectory, s.trajectory, self.unit_sigma) \
                if self.trajectory.active and obs.trajectory is not None else None
            try:
                sol = self._robust_solve(obs, delta, terms)
            except CalibrationError as exc:
                if not no_pairs:
                    raise
                n = len(control) if control is not None else 0
                raise CalibrationError(self._no_overlap(
                    f", and {n} control point{'' if n == 1 else 's'} alone cannot calibrate: "
                    f"{exc}")) from None
            step = sol.delta - delta
            if terms is not None:
                assert terms.blocks is not None and terms.step is not None
                residuals = terms.blocks.residuals(obs, step, terms.step)
            else:
                residuals = obs.residuals(step)
            self.threshold = next_threshold(obs, residuals, robust_k=s.robust_k,
                                            floor_m=s.min_normal_distance_m,
                                            current_m=self.threshold)
            self.delta = sol.delta.copy()
            history.append(self.delta.copy())
            # What re-matching alone moves the estimate by: the correspondences that changed.
            adjusted = MatchedSet.of(obs, layout)
            n_changed, changed_normal = adjusted.changes(matched_before) \
                if matched_before is not None else (len(obs), np.full((N_PARAMETERS,) * 2, np.nan))
            matched_before = adjusted
            steps.append(step)
            sigmas.append(sol.sigma.copy())
            noises.append(rematching_noise(sol, changed_normal))
            changed.append(n_changed)
            verdict = judge_convergence(history, steps, sigmas, noises, changed,
                                        s.convergence_fraction)
            if terms is not None and terms.step is not None:
                verdict = self._trajectory_step(terms.step, sol.sigma0, verdict)
            logger.info("iteration %d: sigma0 %.4f m, %d observations; %s", iteration,
                        sol.sigma0, len(obs), verdict.outcome)
            yield Iteration(iteration, sol, obs, step, verdict.converged, list(history),
                            ended=verdict.ended, outcome=verdict.outcome, noise=noises[-1],
                            trajectory=terms)

    def conclude(self, last: Iteration) -> CalibrationResult:
        """The result of the iterations of :meth:`iterate` that ended with ``last``: sigmas
        allowing for shared errors, and the QA of every pair at the estimate. Call once per
        iteration (it widens ``last``'s sigmas)."""
        terms = last.trajectory
        with self.clock("normal equations"):
            if terms is None or terms.blocks is None or terms.step is None:
                self.normal_equations = NormalEquations.from_observations(last.observations)
                allow_for_shared_errors(last.solution, last.observations, last.step)
                allow_for_ins_noise(last.solution, last.observations, self._ins_noise())
                allow_for_held_biases(last.solution, self.normal_equations.n,
                                      self.settings.held_sigma)
                trajectory = None
            else:
                # the biases' equations with the trajectory errors reduced out; the shared
                # errors' sigmas from the design rows with the errors partialled out
                blocks = terms.blocks
                self.normal_equations = blocks.reduced
                obs = last.observations
                reduced = blocks.reduced_rows(obs)
                v = blocks.residuals(obs, last.step, terms.step)
                rows_alone = Observations(reduced, v + reduced @ last.step, obs.weights,
                                          obs.group, obs.cluster,
                                          pose_loading=obs.pose_loading)
                allow_for_shared_errors(last.solution, rows_alone, last.step)
                allow_for_ins_noise(last.solution, rows_alone, self._ins_noise())
                allow_for_held_biases(last.solution, self.normal_equations.n,
                                      self.settings.held_sigma)
                trajectory = TrajectoryEstimate.from_state(
                    self.trajectory, [ps.strip_id for ps in self.strips],
                    blocks.tau_sigma(last.solution))
                self._weak_with_trajectory(last.solution)
        result = self._finish(last.solution, last.observations, last.solution.delta,
                              last.number, last.converged, last.history)
        result.trajectory = trajectory
        result.convergence = last.outcome
        return result

    def _ins_noise(self) -> InsNoise:
        """The INS's errors on the grid of the trajectory's samples (the matcher's settings
        hold its step once a strip is added)."""
        return self.matcher.settings.ins_noise

    def _weak_with_trajectory(self, sol: Solution) -> None:
        """Warn of the biases whose sigma exceeds what a calibration can use (the limits the
        trajectory errors' solve lifted), in words."""
        limits = self.settings.limits.max_sigma
        for i, name in enumerate(PARAMETER_NAMES):
            if name in sol.estimated and sol.sigma[i] > limits.get(name, np.inf):
                value, unit = display_value(name, sol.sigma[i])
                sol.warnings.append(
                    f"{name} determined only weakly (sigma {value:.3g} {unit}): with each "
                    "strip's trajectory error estimated, only through the navigation priors "
                    "and changes of attitude; hold it at its surveyed value if one is known")

    def unestimated_result(self, reason: str) -> CalibrationResult:
        """The result of a calibration that estimated nothing (``reason``): every bias at
        its fixed value (``settings.fixed``, 0 unless given), no sigma, not converged, and
        the QA of every strip pair as delivered (the sample points of :meth:`run`, matched
        at that value; ``correspondences`` counts the points matched, none of which was
        adjusted) and of the control points.
        """
        s = self.settings
        delta = np.array([float(s.fixed.get(name, 0.0)) for name in PARAMETER_NAMES])
        with self.workers.threads():
            self.matcher.choose_samples([p for p in self.pairs if p.frozen is None and
                                  p.sample is None])
        status = {name: ParameterStatus(ParameterState.NOT_ESTIMABLE, reason)
                  if name in s.solve_for else ParameterStatus(ParameterState.FIXED)
                  for name in PARAMETER_NAMES}
        sol = Solution(delta=delta, sigma=np.full(N_PARAMETERS, np.nan), estimated=(),
                       covariance=np.zeros((0, 0)), correlation=np.zeros((0, 0)),
                       sigma0=float("nan"), redundancy=0, status=status)
        with self.workers.threads():
            result = self._finish(sol, Observations.empty(), delta, 0, False, [])
        for p in result.pairs:
            p.correspondences = p.n_after
        result.nothing_estimated = reason
        result.height_agreement = height_agreement(self.strips)
        return result

    def _no_overlap(self, control: str) -> str:
        """Why no strip pair formed
        (:func:`~lidarcal_ros.core.calibration.pairs.no_overlap_reason`), then ``control``."""
        return no_overlap_reason(self.strips, control,
                                 overlap_cell_m=self.settings.overlap_cell_m,
                                 min_overlap_cells=self.settings.min_overlap_cells)

    def observations_at(self, delta: np.ndarray) -> Observations:
        """The correspondences of every pair (and control) at the estimate ``delta``, with
        no adjustment: what flight planning analyses."""
        with self.workers.threads():
            matched, corrected = self.matcher.match_samples(delta)
            parts = [self.matcher.pair_observations(pair, pair.sample, m) for pair, m in matched
                     if pair.sample is not None]
            if self.control is not None and len(self.control):
                parts.append(self.matcher.control_observations(
                    self.control, delta, self.settings.max_normal_distance_m,
                    corrected=corrected)[0])
        return Observations.concatenate(parts)

    def pair_discrepancies(self, delta: np.ndarray) -> list[PairDiscrepancies]:
        """Per strip pair holding its points, the normal discrepancy of every matched sample
        point after correcting both strips by ``delta`` (8 biases, SI, docs/method.md order):
        at zero the discrepancies "before" calibration, at the estimate those "after".

        The points and the matching threshold are those of the QA of :meth:`run`, so the
        statistics reproduce :class:`PairStats` (``rms_before`` at zero, ``rms_after`` at
        the estimate). Pairs sorted by strip ids.
        """
        floor = self.settings.min_normal_distance_m
        out = []
        with self.workers.threads():
            matched = self.matcher.match_samples(np.asarray(delta, dtype=np.float64))[0]
        for pair, m in matched:
            assert pair.sample is not None
            idx = pair.sample[m.valid]
            distance = m.distance[m.valid]
            rms, p95 = robust_qa(distance, floor)
            out.append(PairDiscrepancies(
                points_strip=self.strips[pair.a].strip_id,
                tin_strip=self.strips[pair.b].strip_id,
                xy=self.strips[pair.a].strip.xyz[idx, :2].copy(), distance=distance,
                rms=rms, p95=p95))
        out.sort(key=lambda d: d.strips)
        return out

    def control_residuals(
        self, delta: np.ndarray,
        corrected: CorrectedStrips | None = None,
    ) -> list[ControlResidual]:
        """Normal discrepancy of every control point against every strip that sees it, as
        delivered and after correcting the strips by ``delta`` (metres; NaN where the point
        no longer finds a patch). ``corrected``: the strips already corrected by ``delta``.
        """
        control = self.control
        if control is None or not len(control):
            return []
        before = self._control_matches_before()  # before ``corrected``: it resets geometries
        _, found_after = self.matcher.control_observations(
            control, delta, self.settings.max_normal_distance_m, corrected=corrected)
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
            self._control_before = self.matcher.control_observations(
                control, np.zeros(N_PARAMETERS), self.settings.max_normal_distance_m,
                delivered=True)[1]
        return self._control_before

    def _finish(
        self, sol: Solution, obs: Observations, delta: np.ndarray, iterations: int,
        converged: bool, history: list[np.ndarray],
    ) -> CalibrationResult:
        """QA: re-match the samples with the final estimate at the first threshold; the
        laser vectors of the points corrected by it."""
        s = self.settings
        remote = self.matcher.remote
        # (with remote matching the strips are corrected where they are held)
        corrected = self.matcher.corrected_all(delta) if remote is None else {}
        with self.clock("QA"):
            for k, qa in self.matcher.laser_qa(delta).items():
                self.strips[k].laser_qa = qa

        def after_of(pair: StripPair) -> np.ndarray:
            if pair.frozen is not None and pair.frozen_delta is not None:
                return pair.frozen.residuals(delta - pair.frozen_delta) if len(pair.frozen) \
                    else np.empty(0)
            return self.matcher.sample_distances(pair, delta, corrected,
                                                 s.max_normal_distance_m)

        if remote is None:
            afters = self.workers.map(after_of, self.pairs)
        else:
            matched = [p for p in self.pairs if p.frozen is None or p.frozen_delta is None]
            found = dict(zip((p.index for p in matched), remote.distances(
                self.matcher, matched, delta, s.max_normal_distance_m), strict=True))
            afters = [found[p.index] if p.index in found else after_of(p) for p in self.pairs]
        stats = []
        for pair, after in zip(self.pairs, afters, strict=True):
            assert pair.before is not None
            ids = sorted((self.strips[pair.a].strip_id, self.strips[pair.b].strip_id))
            rms_after, p95_after = robust_qa(after, s.min_normal_distance_m)
            stats.append(PairStats(
                strip_a=ids[0], strip_b=ids[1],
                coverage=float(pair.coverage),
                correspondences=int(np.count_nonzero(
                    (obs.group == pair.index) & (obs.weights > 0))),
                rms_before=robust_qa(pair.before, s.min_normal_distance_m)[0],
                rms_after=rms_after, p95_after=p95_after,
                n_before=int(pair.before.size), n_after=int(after.size),
            ))
        stats.sort(key=lambda p: (p.strip_a, p.strip_b))
        residuals = self.control_residuals(delta, corrected)
        n_ctrl = int(np.count_nonzero((obs.group < 0) & (obs.weights > 0)))
        held = [ps for ps in self.strips if not ps.placeholder]
        return CalibrationResult(
            solution=sol, iterations=iterations, converged=converged, pairs=stats,
            control=residuals, n_pair_correspondences=int(np.count_nonzero(
                (obs.group >= 0) & (obs.weights > 0))),
            n_control_correspondences=n_ctrl, history=history,
            dropped_non_finite=self.dropped_non_finite, thinned_points=self.thinned_points,
            heading_from={ps.strip_id: ps.geometry0.heading_from for ps in held},
            crab_deg={ps.strip_id: ps.geometry0.crab_deg for ps in held},
            models={ps.strip_id: ps.choice for ps in held},
            laser_qa={ps.strip_id: ps.laser_qa for ps in held},
            stage_seconds=dict(self.clock.seconds),
        )


def calibrate(
    mission: Mission,
    settings: CalibrationSettings | None = None,
    *,
    progress: Progress | None = None,
    whole: WholeStrips | None = None,
    samples: ChosenSamples | None = None,
    pair_work: PairWork | None = None,
) -> CalibrationResult:
    """Calibrate a mission: see :class:`Calibrator`.

    ``whole``: the mission's strips hold part of their points only (the reduced mission of
    a bounded-memory calibration, :mod:`~lidarcal_ros.core.calibration.bounded`); by strip
    id, each whole strip's extent and the sampling priority of each point held.
    ``samples``: the pairs' sample points chosen already (:meth:`Calibrator.use_samples`).
    ``pair_work``: where the strip pairs are matched, if not in this process's threads
    (:attr:`PairMatcher.remote <lidarcal_ros.core.calibration.matching.PairMatcher.remote>`;
    the same estimate).

    Raises
    ------
    NothingEstimated
        The mission holds strips but the adjustment could estimate nothing (a single strip,
        no overlap, no usable patches, nothing observable); it carries the QA of the strips
        as delivered.
    """
    settings = settings or CalibrationSettings()
    if settings.trajectory.model is not TrajectoryModel.AUTO:
        return _run(Calibrator.from_mission(mission, settings, progress=progress, whole=whole,
                                            samples=samples), pair_work)
    # auto: the trajectory as exact, then with each strip's spline over the same prepared
    # strips (their TINs and geometry shared, as the live calibration shares them); the
    # spline is kept where it fits clearly better (the strips disagree by more than their
    # noise)
    first = Calibrator.from_mission(mission, with_trajectory_model(settings,
                                                                   TrajectoryModel.NONE),
                                    progress=progress, whole=whole, samples=samples)
    exact = _run(first, pair_work)
    second = Calibrator(with_trajectory_model(settings, TrajectoryModel.SPLINE),
                        control=mission.control, progress=progress)
    second.dropped_non_finite, second.thinned_points = first.dropped_non_finite, \
        first.thinned_points
    second.matcher.tins_in_turn = first.matcher.tins_in_turn
    for ps in first.strips:
        second.add_prepared_strip(ps)
    if samples is not None:
        second.use_samples(samples)
    try:
        spline: CalibrationResult | CalibrationError = _run(second, pair_work)
    except CalibrationError as exc:  # (NothingEstimated too)
        spline = exc
    return choose_trajectory_model(exact, spline)


def with_trajectory_model(settings: CalibrationSettings,
                          model: TrajectoryModel) -> CalibrationSettings:
    """``settings`` with the trajectory errors modelled by ``model`` (the same priors)."""
    return replace(settings, trajectory=replace(settings.trajectory, model=model))


def choose_trajectory_model(exact: CalibrationResult,
                            spline: CalibrationResult | CalibrationError) -> CalibrationResult:
    """``auto``'s choice between the calibration with the trajectory as exact and that with
    each strip's spline (or why the latter failed): the spline where it leaves a sigma0
    :data:`~lidarcal_ros.core.trajectory.strip_errors.AUTO_SIGMA0_RATIO` times smaller (the strips
    disagree by more than their noise). The result chosen, its ``trajectory_choice`` saying
    which and why."""
    if isinstance(spline, CalibrationError):
        exact.trajectory_choice = (f"auto: none (with each strip's trajectory error the data "
                                   f"determine nothing: {spline})")
        return exact
    s_exact, s_spline = exact.solution.sigma0, spline.solution.sigma0
    better = bool(s_exact > AUTO_SIGMA0_RATIO * s_spline)
    chosen = spline if better else exact
    chosen.trajectory_choice = (
        f"auto: {'spline' if better else 'none'} (sigma0 {s_exact * 100:.2f} cm with the "
        f"trajectory as exact, {s_spline * 100:.2f} cm with each strip's spline"
        f"{'' if better else ': the trajectory fits within the noise'})")
    return chosen


def _run(cal: Calibrator, pair_work: PairWork | None = None) -> CalibrationResult:
    """:meth:`Calibrator.run`, its pairs matched by ``pair_work`` if given, its
    ``trajectory_choice`` its model (:func:`calibrate` says what it raises)."""
    cal.matcher.remote = pair_work
    try:
        result = cal.run()
    except NothingEstimated:
        raise
    except CalibrationError as exc:
        raise NothingEstimated(str(exc), cal.unestimated_result(str(exc))) from None
    result.trajectory_choice = cal.settings.trajectory.model.value
    return result


__all__ = ["CalibrationSettings", "Calibrator", "Progress", "WholeStrips", "calibrate",
           "choose_trajectory_model", "with_trajectory_model"]
