"""Live calibration: a mission fed message by message (the calibrator node's core).

:class:`StreamingCalibration`: strips completed as they end, quick updates, convergence in the
background, the memory budget, strips seen in part (docs/nodes.md, "How the calibrator works").
Trajectory errors: docs/method.md section 11.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lidarcal_ros.core.adjustment.least_squares import NormalEquations
from lidarcal_ros.core.calibration.calibrate import CalibrationSettings, Calibrator
from lidarcal_ros.core.calibration.iteration import Iteration
from lidarcal_ros.core.calibration.result import CalibrationResult
from lidarcal_ros.core.calibration.thinning import first_per_cell
from lidarcal_ros.core.config import FlightConfig
from lidarcal_ros.core.georeferencing.local_trajectory import served_by_trajectory
from lidarcal_ros.core.mission import ControlPoints, Strip, Trajectory
from lidarcal_ros.errors import CalibrationError, InputError, TrajectoryError
from lidarcal_ros.io.cloud.columns import CloudColumns
from lidarcal_ros.pipeline.calibration.checkpoint import (
    SensorFrameState,
    StreamCheckpoint,
    read_checkpoint,
    write_checkpoint,
)
from lidarcal_ros.pipeline.calibration.stream_inputs import (
    OpenStrips,
    TrajectorySamples,
    default_point_budget,
)
from lidarcal_ros.pipeline.calibration.stream_models import ModelCalibrators
from lidarcal_ros.pipeline.calibration.strip_coverage import StripCoverage

__all__ = ["StreamingCalibration"]

logger = logging.getLogger(__name__)


@dataclass
class _Refinement:
    """A background convergence under way (docs/nodes.md)."""

    iterations: Iterator[Iteration | None]
    completed: int = 0  # iterations
    seconds: float = 0.0  # spent in its steps, s
    #: ``auto``: the active calibrator's result and whether it converged, once concluded,
    #: while the rival model's iterations run.
    first: tuple[CalibrationResult, bool] | None = None


class StreamingCalibration:
    """Accumulate clouds, trajectory and control; calibrate strip by strip.

    Parameters
    ----------
    config : FlightConfig
    control : ControlPoints, optional
    max_points : int, optional
        Memory budget in points held (open and complete strips); default
        :func:`default_point_budget`.
    strip_gap_s : float
        Seconds of point time without a point of a strip after which it is complete.
    settings_of : callable, optional
        The calibration's settings of a configuration (default
        :meth:`FlightConfig.calibration_settings`; clouds in the sensor's frame: the
        mounting's, as ``lidarcal calibrate`` sets them).
    """

    #: The map frame of the points and the trajectory (None until the first message).
    frame_id: str | None
    #: Points and strips released under the memory budget (docs/nodes.md).
    dropped_points: int
    dropped_strips: list[int]
    #: Points left out for a non-finite coordinate or time.
    dropped_non_finite: int
    #: Points left out by the thinning of ``calibration.thinning_cell_m`` (and the
    #: automatic one).
    thinned_points: int
    #: Thinning cell (m) the budget forced because the open strips alone held more than it
    #: (docs/nodes.md); 0 while it did not.
    auto_thinning_cell_m: float
    #: The latest estimate (None: none yet).
    latest: CalibrationResult | None
    #: Whether :attr:`latest` is converged on the strips held (docs/nodes.md).
    converged: bool
    #: The normal equations of :attr:`latest`.
    normal_equations: NormalEquations
    #: Points of strips already complete that arrived later (ignored).
    late_points: int
    #: Points of complete strips the trajectory did not serve (left out), and the strips left
    #: out whole for that reason.
    uncovered_points: int
    uncovered_strips: list[int]
    #: Complete strips the calibration refused, with the reason (left out).
    rejected_strips: list[tuple[int, str]]
    _refinement: _Refinement | None
    _refinement_wanted: bool
    _samples: TrajectorySamples
    _open: OpenStrips
    _closed: list[Strip]
    _now: float  # newest point time, s
    _late_strips: set[int]
    _coverage: StripCoverage
    _models: ModelCalibrators
    _settings: CalibrationSettings  # the settings of ``_models``

    def __init__(
        self,
        config: FlightConfig,
        *,
        control: ControlPoints | None = None,
        max_points: int | None = None,
        strip_gap_s: float = 2.0,
        settings_of: Callable[[FlightConfig], CalibrationSettings] | None = None,
    ) -> None:
        self._settings_of = settings_of or FlightConfig.calibration_settings
        if max_points is None:
            max_points = default_point_budget()
        if max_points <= 0:
            raise CalibrationError(f"max_points must be positive, got {max_points}")
        self.config = config
        self.max_points = int(max_points)
        self.strip_gap_s = float(strip_gap_s)
        self._control = control
        #: Seconds the last refinement concluded took in its steps (NaN: none yet).
        self.refinement_seconds = float("nan")
        #: Why there is no estimate yet ('' once there is one).
        self.waiting_for = "no strip complete yet"
        self.reset()

    # ------------------------------------------------------------------ inputs
    def _new_models(self) -> ModelCalibrators:
        self._settings = self._settings_of(self.config)
        return ModelCalibrators(self._settings, control=self._control)

    @property
    def _calibrator(self) -> Calibrator:
        """The calibrator whose estimate is published (:class:`ModelCalibrators`)."""
        return self._models.active

    def _check_frame(self, frame_id: str, what: str) -> None:
        if self.frame_id is None:
            self.frame_id = frame_id
        elif frame_id != self.frame_id:
            raise InputError(f"{what} in frame '{frame_id}' but the mission is in "
                             f"'{self.frame_id}'")

    def add_trajectory(self, t: np.ndarray, xyz: np.ndarray, frame_id: str,
                       orientation: np.ndarray | None = None) -> None:
        """Add trajectory samples (seconds; IMU origin, map frame, metres; the orientation
        quaternions (n, 4) xyzw, NaN rows, the identity or None where not given)."""
        self._check_frame(frame_id, "trajectory")
        self._samples.add(t, xyz, orientation)
        self._coverage.add_poses(t)

    def add_cloud(self, columns: CloudColumns, frame_id: str) -> None:
        """Add one PointCloud2 chunk (already decoded to columns).

        Raises
        ------
        InputError
            Frame mismatch or no strip id.
        """
        self._check_frame(frame_id, "cloud")
        if columns.strip_id is None:
            raise InputError("cloud has no strip_id / point_source_id field")
        ok = columns.finite()
        self.dropped_non_finite += int((~ok).sum())
        if not ok.any():
            return
        received_ids, received_t = columns.strip_id[ok], columns.t[ok]
        for sid in np.unique(received_ids):  # (all it received: before any thinning)
            self._coverage.add_cloud(int(sid), received_t[received_ids == sid])
        cell = self.thinning_cell_m
        if cell > 0:  # (among the finite points, in order: as lidarcal calibrate reads a bag)
            thin = first_per_cell(columns.xyz[ok], columns.strip_id[ok], cell)
            self.thinned_points += int(thin.size - np.count_nonzero(thin))
            ok[ok] = thin
        ids = columns.strip_id[ok]
        xyz, t = columns.xyz[ok], columns.t[ok]
        inten = columns.intensity[ok] if columns.intensity is not None else None
        closed_ids = {s.strip_id for s in self._closed}
        for sid in np.unique(ids):
            sel = ids == sid
            key = int(sid)
            if key in closed_ids:
                if key not in self._late_strips:  # say it once per strip, not per chunk
                    logger.warning("points of strip %d arrived after it was closed: ignored",
                                   key)
                self._late_strips.add(key)
                self.late_points += int(sel.sum())
                continue
            self._open.add(key, xyz[sel], t[sel], inten[sel] if inten is not None else None)
        self._now = max(self._now, float(t.max()))
        self._enforce_budget()

    def set_control(self, control: ControlPoints) -> None:
        """Control points for the next solves (the same again changes nothing: a restart
        reads its control file again after the checkpoint)."""
        held = self._control
        if held is not None and held.ids == control.ids and np.array_equal(held.xyz,
                                                                            control.xyz):
            return
        self._control = control
        self._models.set_control(control)
        self._data_changed()

    def update_config(self, config: FlightConfig) -> None:
        """New configuration: where it changes the calibration's settings (``settings_of``
        may look beyond it, e.g. at the control points), the strips are re-prepared with it
        and the estimate converged again."""
        changed = self._settings_of(config) != self._settings
        self.config = config
        if changed:
            self._rebuild()

    # ------------------------------------------------------------------ state
    @property
    def trajectory(self) -> Trajectory:
        """The trajectory of the samples received (:attr:`TrajectorySamples.trajectory`:
        InputError before the first)."""
        return self._samples.trajectory

    @property
    def control(self) -> ControlPoints | None:
        """The control points held (None: none)."""
        return self._control

    def held_strips(self) -> list[Strip] | None:
        """The strips of the calibration with every point held (thinned where the budget
        thinned them), in order; None where a strip was released or one is still open."""
        if any(ps.dropped for ps in self._calibrator.strips) or self._open.n_points:
            return None
        return [ps.strip for ps in self._calibrator.strips]

    @property
    def poses_left_out(self) -> int:
        """Poses left out of the trajectory: a non-finite stamp or position, or a stamp
        already held."""
        return self._samples.left_out

    @property
    def clock_steps(self) -> tuple[int, str]:
        """How often the pose stamps stepped back (the old clock's samples dropped), and the
        latest in words."""
        return self._samples.steps_back, self._samples.last_step_back

    @property
    def newest_pose(self) -> float:
        """The newest pose stamp held, s (-inf: none)."""
        return self._samples.newest

    @property
    def partial_strips(self) -> dict[int, str]:
        """The strips received only in part, with what is missing (docs/nodes.md)."""
        return self._coverage.partial_strips

    @property
    def n_points(self) -> int:
        """Points held, in complete strips and in strips being flown."""
        return self._calibrator.n_points + self._open.n_points

    @property
    def strip_ids(self) -> list[int]:
        """The complete strips held (in the order they were completed), then those being
        flown."""
        return [s.strip_id for s in self._closed] + self._open.ids

    @property
    def open_strip_ids(self) -> list[int]:
        """The strips being flown."""
        return self._open.ids

    @property
    def closed_strips(self) -> tuple[Strip, ...]:
        """The complete strips the calibration holds (points as it holds them)."""
        return tuple(self._closed)

    def open_strip(self, strip_id: int) -> Strip:
        """The points of a strip being flown held so far, in time order."""
        return self._open.strip(strip_id)

    @property
    def delta(self) -> np.ndarray:
        """The current estimate (``PARAMETER_NAMES`` order, SI units), read-only."""
        view = self._calibrator.delta.view()
        view.flags.writeable = False
        return view

    @property
    def threshold(self) -> float:
        """The matching threshold the next matching uses, m."""
        return float(self._calibrator.threshold)

    @property
    def thinning_cell_m(self) -> float:
        """The thinning in force, m: ``calibration.thinning_cell_m`` or the automatic one,
        the coarser (0: none)."""
        return max(float(self.config["calibration.thinning_cell_m"]), self.auto_thinning_cell_m)

    def _enforce_budget(self) -> None:
        while self.n_points > self.max_points:
            held = [ps for ps in self._calibrator.strips if not ps.dropped]
            if not held:
                self._thin_open_strips()
                return
            oldest = held[0].strip_id
            n = self._models.drop_strip(oldest)
            self.dropped_points += n
            self.dropped_strips.append(oldest)
            self._closed = [s for s in self._closed if s.strip_id != oldest]
            self._data_changed()
            logger.warning("memory budget: released strip %d (%d points); its pairs keep their "
                           "last correspondences", oldest, n)

    def _thin_open_strips(self) -> None:
        """The open strips alone hold more than the budget: thin them, and what comes later,
        at twice the cell in force until they hold at most half of it (docs/nodes.md)."""
        before = self.n_points
        cell, removed = self._open.thin_to(self.max_points // 2 - self._calibrator.n_points,
                                           self.thinning_cell_m)
        self.thinned_points += removed
        self.auto_thinning_cell_m = cell
        logger.warning("memory budget: the strips being flown held %d points of a budget of %d;"
                       " thinned to one point per %g m cell per strip and cloud (%d held)",
                       before, self.max_points, cell, self.n_points)

    def _close(self, strip_id: int) -> list[tuple[int, int]]:
        """Hand a complete strip to the calibration; returns the pairs it forms.

        Points the trajectory does not serve (it started after the strip did, has a gap, or
        a point lies above it) are left out and counted, not the strip: live, a trajectory
        joined late or one spurious return must not cost the whole strip (offline,
        ``lidarcal calibrate`` refuses such a mission). A strip the calibration still
        refuses is left out with its reason (:attr:`rejected_strips`), and the others go on.
        """
        strip = self._open.pop(strip_id)
        missing = self._coverage.describe(strip_id)
        if missing:
            logger.warning("strip %d seen in part: %s", strip_id, missing)
        served = served_by_trajectory(
            strip.t, strip.xyz, self.trajectory,
            window=self._calibrator.settings.window)
        if not served.all():
            n_out = int((~served).sum())
            self.uncovered_points += n_out
            if not served.any():
                self.uncovered_strips.append(strip_id)
                logger.warning("strip %d left out: the trajectory serves none of its %d "
                               "points", strip_id, n_out)
                return []
            logger.warning("strip %d: %d of %d points not served by the trajectory (outside "
                           "it, in a gap, or not below it), left out", strip_id, n_out,
                           len(strip))
            strip = Strip(strip_id, strip.xyz[served], strip.t[served],
                          None if strip.intensity is None else strip.intensity[served])
        if any(ps.strip_id == strip_id for ps in self._calibrator.strips):
            return self._reject(strip, f"strip {strip_id} continued after it was closed (no "
                                f"point of it for strip_gap_s = {self.strip_gap_s:g} s); "
                                "its later points are left out")
        try:
            formed = self._models.add_strip(strip, self.trajectory)
        except (TrajectoryError, CalibrationError) as exc:
            return self._reject(strip, str(exc))
        self._closed.append(strip)
        return formed

    def _reject(self, strip: Strip, reason: str) -> list[tuple[int, int]]:
        self.rejected_strips.append((strip.strip_id, reason))
        logger.error("strip %d left out (%d points): %s", strip.strip_id, len(strip), reason)
        return []

    def _covered(self, t_end: float) -> bool:
        traj = self.trajectory
        return bool(len(traj) and traj.t[-1] >= t_end + self.config["matching.trajectory_window_s"])

    # ------------------------------------------------------------------ solving
    def update(self, now_s: float | None = None) -> CalibrationResult | None:
        """Close the strips idle for ``strip_gap_s`` (point time, or ``now_s``), pair them
        with the earlier strips and re-solve from the current estimate.

        Returns the new result, or None if no strip was closed.
        """
        now = self._now if now_s is None else max(self._now, float(now_s))
        if not self._samples:
            self.waiting_for = "no trajectory received yet"
            return None
        ready = [sid for sid in self._open.ready(now, self.strip_gap_s)
                 if self._covered(self._open.last_t(sid))]
        if not ready:
            return None
        # Not converged from the moment a strip joins (whoever looks meanwhile: diagnostics).
        self._data_changed(refine=True)
        for sid in ready:
            formed = self._close(sid)
            logger.info("strip %d complete: overlaps %s", sid,
                        ", ".join(str(a) for a, _ in formed) or "no earlier strip")
        try:
            # Two iterations from the current estimate, re-matching only the new strip's pairs
            # (the others keep their last correspondences): the estimate carries over from
            # strip to strip, and the refinement re-matches everything to convergence.
            result = self._solve(max_iterations=2, new_pairs_only=True)
        except CalibrationError as exc:
            # Too little data so far (one strip, no overlap yet): keep accumulating.
            self._data_changed(refine=False)
            self.waiting_for = str(exc)
            logger.info("not solved yet: %s", exc)
            return None
        result.converged = False  # (the pairs kept were not re-matched)
        return result

    def solve(self) -> CalibrationResult:
        """Close every open strip the trajectory covers and run the full adjustment, as
        ``lidarcal calibrate`` does on the same data."""
        for sid in self._open.by_age():
            if self._covered(self._open.last_t(sid)):
                self._close(sid)
        self._data_changed(refine=False)
        self._pass_counters()
        for cal in self._models.calibrators:
            cal.restart()
        result = self._calibrator.run()
        rival = self._models.rival
        if rival is not None:  # auto: both models from scratch, chosen as batch chooses
            try:
                other: CalibrationResult | CalibrationError = rival.run()
            except CalibrationError as exc:
                other = exc
            result = self._models.choose(result, other)
        result = self._adopt(result)
        # Not converged within calibration.max_iterations: the refinement may go on.
        self.converged = result.converged
        self._refinement_wanted = not result.converged
        return result

    def _solve(self, *, max_iterations: int | None,
               new_pairs_only: bool = False) -> CalibrationResult:
        self._pass_counters()
        return self._adopt(self._calibrator.run(max_iterations=max_iterations,
                                                new_pairs_only=new_pairs_only))

    def _pass_counters(self) -> None:
        """The input counters the calibration's results report."""
        for cal in self._models.calibrators:
            cal.dropped_non_finite = self.dropped_non_finite
            cal.thinned_points = self.thinned_points

    def _adopt(self, result: CalibrationResult) -> CalibrationResult:
        """``result`` (the active calibrator's) becomes the latest, its trajectory model
        said."""
        self._models.label(result)
        result.partial_strips = self.partial_strips
        self.latest = result
        self.waiting_for = ""
        self.normal_equations = self._calibrator.normal_equations
        return result

    # ------------------------------------------------------------------ refinement
    @property
    def refinement_pending(self) -> bool:
        """Whether :meth:`refine_step` has work: an estimate not yet converged on the strips
        held (and not given up after ``calibration.max_iterations``)."""
        return self._refinement_wanted

    @property
    def refinement_iteration(self) -> int:
        """Iterations the refinement under way has completed (0: none under way)."""
        return self._refinement.completed if self._refinement is not None else 0

    def _data_changed(self, *, refine: bool | None = None) -> None:
        """The strips, pairs or control points held changed: the estimate is no longer known
        to be converged, and a refinement under way (on the data before) is dropped. The
        refinement starts afresh if ``refine`` (default: if one was wanted or there is an
        estimate)."""
        if refine is None:
            refine = self._refinement_wanted or self.latest is not None
        self.converged = False
        self._refinement = None
        self._refinement_wanted = refine

    def refine_step(self) -> CalibrationResult | None:
        """Take the background convergence one step further (docs/nodes.md): one strip
        pair's matching or one adjustment, from the estimate reached.

        Returns the result once an iteration ended (converged: :attr:`converged` then True;
        or said that more iterations cannot converge it) or ``calibration.max_iterations``
        passed without (False); None while under way or with
        nothing to do (:attr:`refinement_pending`). Too little data to solve ends it quietly
        (:attr:`waiting_for` says why).
        """
        if not self._refinement_wanted:
            return None
        started = time.perf_counter()
        refinement = self._refinement
        if refinement is None:
            refinement = self._refinement = _Refinement(self._calibrator.iterate())
        rival = refinement.first is not None
        calibrator = self._models.rival if rival else self._calibrator
        assert calibrator is not None
        try:
            done = next(refinement.iterations)
        except CalibrationError as exc:
            if refinement.first is not None:  # the rival model determines nothing
                first, converged = refinement.first
                return self._refined(refinement, self._models.choose(first, exc), converged,
                                     started)
            self._data_changed(refine=False)
            self.waiting_for = str(exc)
            logger.info("not refined: %s", exc)
            return None
        except Exception:  # (a failure is reported once, not at every step after)
            self._data_changed(refine=False)
            raise
        if done is not None:
            refinement.completed = done.number
        if done is None or not (done.ended or
                                done.number >= self._calibrator.settings.max_iterations):
            refinement.seconds += time.perf_counter() - started
            return None
        self._pass_counters()
        result = calibrator.conclude(done)
        if refinement.first is None and self._models.rival is not None:
            # auto: the other model converges next, on the same strips, for the comparison
            refinement.first = (result, done.converged)
            refinement.iterations = self._models.rival.iterate()
            refinement.completed = 0
            refinement.seconds += time.perf_counter() - started
            return None
        converged = done.converged
        if refinement.first is not None:
            first, first_converged = refinement.first
            result = self._models.choose(first, result)
            converged = first_converged if result is first else done.converged
        return self._refined(refinement, result, converged, started)

    def _refined(self, refinement: _Refinement, result: CalibrationResult, converged: bool,
                 started: float) -> CalibrationResult:
        """The refinement ended with ``result`` (the active calibrator's): adopt it."""
        result = self._adopt(result)
        self.converged = converged
        self._refinement, self._refinement_wanted = None, False
        self.refinement_seconds = refinement.seconds + time.perf_counter() - started
        logger.info("refined: %s after %d iterations (%.2f s); trajectory errors: %s",
                    "converged" if converged else "NOT converged", result.iterations,
                    self.refinement_seconds, result.trajectory_choice)
        return result

    def converge(self, timeout_s: float = np.inf) -> CalibrationResult | None:
        """:meth:`refine_step` until the refinement ends or ``timeout_s`` seconds passed;
        returns its result, None if it did not end (:attr:`refinement_pending` says whether
        it was cut short) or there was nothing to refine."""
        deadline = time.monotonic() + timeout_s
        while self._refinement_wanted and time.monotonic() < deadline:
            result = self.refine_step()
            if result is not None:
                return result
        return None

    def reset(self) -> None:
        """Forget everything accumulated (data, estimate, correspondences); keep the
        configuration and control points."""
        self.frame_id = None
        self.dropped_points = 0
        self.dropped_strips = []
        self.dropped_non_finite = 0
        self.thinned_points = 0
        self.auto_thinning_cell_m = 0.0
        self.latest = None
        self.converged = False
        self._refinement = None
        self._refinement_wanted = False
        self.normal_equations = NormalEquations()
        self._samples = TrajectorySamples()
        self._open = OpenStrips()
        self._closed = []
        self._now = -np.inf
        self._late_strips = set()
        self._coverage = StripCoverage()
        self.late_points = 0
        self.uncovered_points = 0
        self.uncovered_strips = []
        self.rejected_strips = []
        self._models = self._new_models()

    def _rebuild(self) -> None:
        models = self._new_models()
        for strip in self._closed:
            models.add_strip(strip, self.trajectory)
        for cal in models.calibrators:
            # (a bias no longer solved for goes to its held value, as a new calibration's)
            cal.delta = cal.settings.held(self._calibrator.delta)
        self._models = models
        self._data_changed()

    # ------------------------------------------------------------------ checkpoints
    def save_checkpoint(self, path: str | Path, *,
                        sensor: SensorFrameState | None = None) -> Path:
        """Write everything needed to resume (:mod:`.checkpoint`), with the state of the
        clouds in the sensor's frame that feed it (``sensor``) where they do."""
        return write_checkpoint(path, self.checkpoint(sensor=sensor))

    def checkpoint(self, *, sensor: SensorFrameState | None = None) -> StreamCheckpoint:
        """:meth:`save_checkpoint`'s state, in memory (the strips shared, not copied):
        :meth:`from_checkpoint` resumes from it."""
        return StreamCheckpoint(
            sensor=sensor,
            frame_id=self.frame_id, trajectory=self._samples.arrays(),
            closed=list(self._closed), open=list(self._open.strips()),
            models=self._models.states(), trajectory_choice=self._models.choice,
            converged=self.converged, normal_equations=self.normal_equations, control=self._control,
            dropped_points=self.dropped_points, dropped_non_finite=self.dropped_non_finite,
            thinned_points=self.thinned_points, auto_thinning_cell_m=self.auto_thinning_cell_m,
            uncovered_points=self.uncovered_points,
            uncovered_strips=list(self.uncovered_strips),
            rejected_strips=list(self.rejected_strips), dropped_strips=list(self.dropped_strips))

    @classmethod
    def load_checkpoint(
        cls, path: str | Path, config: FlightConfig, *, max_points: int | None = None,
        strip_gap_s: float = 2.0,
    ) -> StreamingCalibration:
        """Resume from :meth:`save_checkpoint`.

        Raises
        ------
        InputError
            Unreadable or incompatible checkpoint.
        """
        return cls.from_checkpoint(read_checkpoint(path), config, max_points=max_points,
                                   strip_gap_s=strip_gap_s)

    @classmethod
    def from_checkpoint(
        cls, state: StreamCheckpoint, config: FlightConfig, *, max_points: int | None = None,
        strip_gap_s: float = 2.0,
        settings_of: Callable[[FlightConfig], CalibrationSettings] | None = None,
    ) -> StreamingCalibration:
        """Resume from a checkpoint read (:func:`~.checkpoint.read_checkpoint`);
        ``settings_of`` as the constructor's (a mounting's calibration: its own)."""
        self = cls(config, control=state.control, max_points=max_points,
                   strip_gap_s=strip_gap_s, settings_of=settings_of)
        self.frame_id = state.frame_id
        t, xyz, orientation = state.trajectory
        if t.size:
            self._samples.add(t, xyz, orientation)
        self.dropped_points = state.dropped_points
        self.dropped_non_finite = state.dropped_non_finite
        self.thinned_points = state.thinned_points
        self.auto_thinning_cell_m = state.auto_thinning_cell_m
        self.uncovered_points = state.uncovered_points
        self.uncovered_strips = list(state.uncovered_strips)
        self.rejected_strips = list(state.rejected_strips)
        self.dropped_strips = list(state.dropped_strips)
        # in the calibration's order, strips released before in their places (their
        # trajectory errors' frozen correspondences name them)
        closed = {strip.strip_id: strip for strip in state.closed}
        order = [int(i) for i in state.models[0].trajectory_ids] if state.models else []
        spans = {sid: (float(a), float(b)) for sid, (a, b) in
                 zip(order, state.models[0].spans, strict=True)} if state.models else {}
        for sid in order + [s.strip_id for s in state.closed if s.strip_id not in order]:
            if sid not in closed:
                self._models.add_released(sid, spans[sid])
                continue
            self._closed.append(closed[sid])
            self._models.add_strip(closed[sid], self.trajectory)
        for strip in state.open:
            self._open.add(strip.strip_id, strip.xyz, strip.t, strip.intensity)
        # estimates, thresholds, trajectory errors, frozen correspondences
        self._models.restore(state.models, state.trajectory_choice)
        self.converged = state.converged
        # No result survives a restart: converge again (at once where it was converged) for
        # one to publish.
        self._refinement_wanted = bool(self._closed) or any(len(m.frozen) for m in state.models)
        self.normal_equations = state.normal_equations
        if self._closed:
            self._now = max(float(s.t[-1]) for s in self._closed)
        for sid in self._open.ids:
            self._now = max(self._now, self._open.last_t(sid))
        return self
