"""Live calibration: a mission fed message by message (the calibrator node's core).

Clouds arrive as chunks; a strip is complete once no point of it has arrived for
``strip_gap_s`` seconds of point time (and the trajectory covers its end). Each completed strip
is prepared once (local trajectory, footprint), paired with the strips before it, and the
adjustment is re-run from the current estimate: the new correspondences join the normal
equations without re-preparing anything older. That quick update re-matches only the new
strip's pairs, two iterations, so its estimate is not converged.

Convergence goes on in the background (:meth:`StreamingCalibration.refine_step`, called
whenever the caller has nothing else to do): from the current estimate and matching threshold,
every pair is re-matched and the adjustment re-solved, iteration after iteration, until an
iteration moves no parameter by more than ``calibration.convergence_fraction`` of its sigma
(from the second on, as ``lidarcal calibrate`` decides) or ``calibration.max_iterations`` pass.
Each step is one strip pair's matching or one adjustment, so the caller can take input between
them. Whatever changes the data (a strip closed, a strip released under the memory budget,
control points, the configuration) makes the estimate not converged and starts the refinement
afresh from the estimate reached. The converged estimate is the one ``lidarcal calibrate``
gives on the same strips: the same sample points, thresholds and control, converged to the same
fixed point. :meth:`StreamingCalibration.solve` runs the full adjustment from zero exactly as
``lidarcal calibrate`` does. Checkpoints keep whether the estimate was converged and the
matching threshold; a calibration resumed from one converges again before its first result.

Memory: points are held under a budget; past it the oldest complete strip is released first,
its strip pairs keeping their last correspondences (frozen), and the count is reported. Where
the strips still being flown hold more than the budget on their own (a dense sensor on a long
line, without ``calibration.thinning_cell_m``), their points are thinned as that setting
does, at the coarsest of twice the cell in force until they hold at most half the budget, and
every later cloud at that cell: the calibration goes on with fewer points instead of running
out of memory (:attr:`StreamingCalibration.auto_thinning_cell_m`, reported).
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lidarcal_ros.core.adjustment import NormalEquations, Observations
from lidarcal_ros.core.calibrate import CalibrationResult, Calibrator, Iteration
from lidarcal_ros.core.config import FlightConfig
from lidarcal_ros.core.local_trajectory import served_by_trajectory
from lidarcal_ros.core.mission import ControlPoints, Strip, Trajectory
from lidarcal_ros.core.thinning import first_per_cell
from lidarcal_ros.errors import CalibrationError, InputError, TrajectoryError
from lidarcal_ros.io.pointcloud import CloudColumns

logger = logging.getLogger(__name__)

CHECKPOINT_VERSION = 2
#: What a point held by the calibration costs in memory once its strip is complete (its
#: triangles, their planes and neighbours; measured: 643 bytes on a 3.2M-point mission).
BYTES_PER_HELD_POINT = 700
#: Share of the machine's memory :func:`default_point_budget` gives the calibration.
_MEMORY_SHARE = 0.5
#: The first cell of the automatic thinning where no thinning was set, m (then doubled):
#: about the point spacing of a dense sensor.
_FIRST_AUTO_CELL_M = 0.25
#: Coarsest automatic thinning cell, m: beyond it a strip hardly has patches left to match.
_MAX_AUTO_CELL_M = 32.0


def default_point_budget(memory_bytes: int | None = None) -> int:
    """Points the calibration may hold on this machine: about half of its memory
    (``memory_bytes``, default the physical memory) at :data:`BYTES_PER_HELD_POINT`; 10M
    where the memory cannot be read."""
    if memory_bytes is None:
        try:
            memory_bytes = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (AttributeError, ValueError, OSError):
            return 10_000_000
    return max(int(_MEMORY_SHARE * memory_bytes / BYTES_PER_HELD_POINT), 1)


@dataclass
class _OpenStrip:
    """Chunks of a strip still being flown."""

    xyz: list[np.ndarray] = field(default_factory=list)
    t: list[np.ndarray] = field(default_factory=list)
    intensity: list[np.ndarray] = field(default_factory=list)
    has_intensity: bool = True
    last_t: float = -np.inf
    n: int = 0

    def add(self, xyz: np.ndarray, t: np.ndarray, intensity: np.ndarray | None) -> None:
        self.xyz.append(np.ascontiguousarray(xyz, dtype=np.float64))
        self.t.append(np.ascontiguousarray(t, dtype=np.float64))
        if intensity is None:
            self.has_intensity = False
        elif self.has_intensity:
            self.intensity.append(np.asarray(intensity, dtype=np.float32))
        self.last_t = max(self.last_t, float(t.max()))
        self.n += int(t.shape[0])

    def thin(self, strip_id: int, cell_m: float) -> int:
        """Keep the first point of each ``cell_m`` cell of every cloud's part held (as
        ``calibration.thinning_cell_m`` thins each cloud); returns the points let go."""
        removed = 0
        for k, xyz in enumerate(self.xyz):
            keep = first_per_cell(xyz, np.full(xyz.shape[0], strip_id, dtype=np.int64), cell_m)
            gone = int(keep.size - np.count_nonzero(keep))
            if not gone:
                continue
            removed += gone
            self.xyz[k], self.t[k] = xyz[keep], self.t[k][keep]
            if self.has_intensity:
                self.intensity[k] = self.intensity[k][keep]
        self.n -= removed
        return removed

    def to_strip(self, strip_id: int) -> Strip:
        t = np.concatenate(self.t)
        order = np.argsort(t, kind="stable")
        inten = np.concatenate(self.intensity)[order] if self.has_intensity else None
        return Strip(strip_id, np.concatenate(self.xyz)[order], t[order], inten)


@dataclass
class _Refinement:
    """A background convergence under way (module docstring)."""

    iterations: Iterator[Iteration | None]
    completed: int = 0  # iterations
    seconds: float = 0.0  # spent in its steps, s


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
    """

    def __init__(
        self,
        config: FlightConfig,
        *,
        control: ControlPoints | None = None,
        max_points: int | None = None,
        strip_gap_s: float = 2.0,
    ) -> None:
        if max_points is None:
            max_points = default_point_budget()
        if max_points <= 0:
            raise CalibrationError(f"max_points must be positive, got {max_points}")
        self.config = config
        self.max_points = int(max_points)
        self.strip_gap_s = float(strip_gap_s)
        self.frame_id: str | None = None
        self.dropped_points = 0
        self.dropped_strips: list[int] = []
        self.dropped_non_finite = 0
        #: Points left out by the thinning of ``calibration.thinning_cell_m`` (and the
        #: automatic one).
        self.thinned_points = 0
        #: Thinning cell (m) the budget forced because the open strips alone held more than
        #: it (module docstring); 0 while it did not.
        self.auto_thinning_cell_m = 0.0
        self.latest: CalibrationResult | None = None
        #: Whether the estimate held is converged on the strips held (module docstring).
        self.converged = False
        #: Seconds the last refinement concluded took in its steps (NaN: none yet).
        self.refinement_seconds = float("nan")
        self._refinement: _Refinement | None = None
        self._refinement_wanted = False
        self.waiting_for = "no strip complete yet"
        self.normal_equations = NormalEquations()
        self._traj_t: list[np.ndarray] = []
        self._traj_xyz: list[np.ndarray] = []
        self._traj_q: list[np.ndarray] = []  # orientation quaternions xyzw; NaN: none
        #: Poses left out of the trajectory: a non-finite stamp or position, or a stamp
        #: already held.
        self.poses_left_out = 0
        self._trajectory: Trajectory | None = None
        self._open: dict[int, _OpenStrip] = {}
        self._closed: list[Strip] = []
        self._control = control
        self._now = -np.inf
        self._late_strips: set[int] = set()
        self.late_points = 0
        #: Points of complete strips the trajectory did not serve (left out), and the strips
        #: left out whole for that reason.
        self.uncovered_points = 0
        self.uncovered_strips: list[int] = []
        #: Complete strips the calibration refused, with the reason (left out).
        self.rejected_strips: list[tuple[int, str]] = []
        self._calibrator = self._new_calibrator()

    # ------------------------------------------------------------------ inputs
    def _new_calibrator(self) -> Calibrator:
        return Calibrator(self.config.calibration_settings(), control=self._control)

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
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        self._traj_t.append(t)
        self._traj_xyz.append(np.asarray(xyz, dtype=np.float64).reshape(-1, 3))
        self._traj_q.append(np.full((t.shape[0], 4), np.nan) if orientation is None
                            else np.asarray(orientation, dtype=np.float64).reshape(-1, 4))
        self._trajectory = None

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
            self._open.setdefault(key, _OpenStrip()).add(
                xyz[sel], t[sel], inten[sel] if inten is not None else None)
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
        self._calibrator.control = control
        self._calibrator._control_before = None
        self._data_changed()

    def update_config(self, config: FlightConfig) -> None:
        """New configuration: where it changes the calibration's settings, the strips are
        re-prepared with it and the estimate converged again."""
        changed = config.calibration_settings() != self.config.calibration_settings()
        self.config = config
        if changed:
            self._rebuild()

    # ------------------------------------------------------------------ state
    @property
    def trajectory(self) -> Trajectory:
        if self._trajectory is None:
            if not self._traj_t:
                raise InputError("no trajectory received yet")
            t = np.concatenate(self._traj_t)
            self._trajectory = Trajectory.from_samples(t, np.concatenate(self._traj_xyz),
                                                       np.concatenate(self._traj_q))
            self.poses_left_out = int(t.shape[0]) - len(self._trajectory)
        return self._trajectory

    @property
    def n_points(self) -> int:
        return self._calibrator.n_points + sum(o.n for o in self._open.values())

    @property
    def strip_ids(self) -> list[int]:
        return [s.strip_id for s in self._closed] + sorted(self._open)

    @property
    def open_strip_ids(self) -> list[int]:
        return sorted(self._open)

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
            n = self._calibrator.drop_strip(oldest)
            self.dropped_points += n
            self.dropped_strips.append(oldest)
            self._closed = [s for s in self._closed if s.strip_id != oldest]
            self._data_changed()
            logger.warning("memory budget: released strip %d (%d points); its pairs keep their "
                           "last correspondences", oldest, n)

    def _thin_open_strips(self) -> None:
        """The open strips alone hold more than the budget: thin them, and what comes later,
        at twice the cell in force until they hold at most half of it (module docstring)."""
        target = self.max_points // 2
        cell = self.thinning_cell_m or _FIRST_AUTO_CELL_M / 2.0
        before = self.n_points
        while self.n_points > target and cell < _MAX_AUTO_CELL_M:
            cell *= 2.0
            for key, strip in self._open.items():
                self.thinned_points += strip.thin(key, cell)
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
        strip = self._open.pop(strip_id).to_strip(strip_id)
        served = served_by_trajectory(
            strip.t, strip.xyz, self.trajectory,
            window_s=self._calibrator.settings.trajectory_window_s)
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
            formed = self._calibrator.add_strip(strip, self.trajectory)
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
        if not self._traj_t:
            self.waiting_for = "no trajectory received yet"
            return None
        ready = [sid for sid, o in self._open.items()
                 if now - o.last_t >= self.strip_gap_s and self._covered(o.last_t)]
        if not ready:
            return None
        # Not converged from the moment a strip joins (whoever looks meanwhile: diagnostics).
        self._data_changed(refine=True)
        for sid in sorted(ready, key=lambda k: self._open[k].last_t):
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
        for sid in sorted(self._open, key=lambda k: self._open[k].last_t):
            if self._covered(self._open[sid].last_t):
                self._close(sid)
        self._data_changed(refine=False)
        self._calibrator.delta = np.zeros_like(self._calibrator.delta)
        self._calibrator.threshold = self._calibrator.settings.max_normal_distance_m
        result = self._solve(max_iterations=None)
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
        self._calibrator.dropped_non_finite = self.dropped_non_finite
        self._calibrator.thinned_points = self.thinned_points

    def _adopt(self, result: CalibrationResult) -> CalibrationResult:
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
        """Take the background convergence one step further (module docstring): one strip
        pair's matching or one adjustment, from the estimate reached.

        Returns the result once an iteration converged (:attr:`converged` then True) or
        ``calibration.max_iterations`` passed without (False); None while under way or with
        nothing to do (:attr:`refinement_pending`). Too little data to solve ends it quietly
        (:attr:`waiting_for` says why).
        """
        if not self._refinement_wanted:
            return None
        started = time.perf_counter()
        refinement = self._refinement
        if refinement is None:
            refinement = self._refinement = _Refinement(self._calibrator.iterate())
        try:
            done = next(refinement.iterations)
        except CalibrationError as exc:
            self._data_changed(refine=False)
            self.waiting_for = str(exc)
            logger.info("not refined: %s", exc)
            return None
        except Exception:  # (a failure is reported once, not at every step after)
            self._data_changed(refine=False)
            raise
        if done is not None:
            refinement.completed = done.number
        if done is None or not (done.converged or
                                done.number >= self._calibrator.settings.max_iterations):
            refinement.seconds += time.perf_counter() - started
            return None
        self._pass_counters()
        result = self._adopt(self._calibrator.conclude(done))
        self.converged = done.converged
        self._refinement, self._refinement_wanted = None, False
        self.refinement_seconds = refinement.seconds + time.perf_counter() - started
        logger.info("refined: %s after %d iterations (%.2f s)",
                    "converged" if done.converged else "NOT converged", done.number,
                    self.refinement_seconds)
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
        self._data_changed(refine=False)
        self.normal_equations = NormalEquations()
        self._traj_t, self._traj_xyz, self._traj_q = [], [], []
        self._trajectory = None
        self._open, self._closed = {}, []
        self._now = -np.inf
        self._late_strips = set()
        self.late_points = 0
        self.uncovered_points = 0
        self.uncovered_strips = []
        self.rejected_strips = []
        self._calibrator = self._new_calibrator()

    def _rebuild(self) -> None:
        cal = self._new_calibrator()
        for strip in self._closed:
            cal.add_strip(strip, self.trajectory)
        cal.delta = self._calibrator.delta
        self._calibrator = cal
        self._data_changed()

    # ------------------------------------------------------------------ checkpoints
    def save_checkpoint(self, path: str | Path) -> Path:
        """Write everything needed to resume (atomic ``.npz``)."""
        path = Path(path)
        arrays: dict[str, np.ndarray] = {
            "version": np.array(CHECKPOINT_VERSION),
            "traj_t": np.concatenate(self._traj_t) if self._traj_t else np.empty(0),
            "traj_xyz": np.concatenate(self._traj_xyz) if self._traj_xyz else np.empty((0, 3)),
            "traj_orientation": (np.concatenate(self._traj_q) if self._traj_q
                                 else np.empty((0, 4))),
            "delta": self._calibrator.delta,
            "threshold": np.array(self._calibrator.threshold),
            "converged": np.array(self.converged),
            "counters": np.array([self.dropped_points, self.dropped_non_finite,
                                  self.thinned_points]),
            "auto_thinning_cell_m": np.array(self.auto_thinning_cell_m),
            "uncovered_points": np.array(self.uncovered_points),
            "uncovered_strips": np.array(self.uncovered_strips, dtype=np.int64),
            "rejected_ids": np.array([i for i, _ in self.rejected_strips], dtype=np.int64),
            "rejected_reasons": np.array([r for _, r in self.rejected_strips], dtype=np.str_),
            "dropped_strips": np.array(self.dropped_strips, dtype=np.int64),
            "neq_n": self.normal_equations.n, "neq_u": self.normal_equations.u,
            "neq_yy": np.array(self.normal_equations.yy),
            "neq_count": np.array(self.normal_equations.count),
            "frame_id": np.array(self.frame_id or ""),
        }
        closed_ids = []
        for strip in self._closed:
            closed_ids.append(strip.strip_id)
            arrays[f"closed_{strip.strip_id}_xyz"] = strip.xyz
            arrays[f"closed_{strip.strip_id}_t"] = strip.t
            if strip.intensity is not None:
                arrays[f"closed_{strip.strip_id}_i"] = strip.intensity
        arrays["closed_ids"] = np.array(closed_ids, dtype=np.int64)
        open_ids = []
        for sid, o in self._open.items():
            open_ids.append(sid)
            s = o.to_strip(sid)
            arrays[f"open_{sid}_xyz"] = s.xyz
            arrays[f"open_{sid}_t"] = s.t
            if s.intensity is not None:
                arrays[f"open_{sid}_i"] = s.intensity
        arrays["open_ids"] = np.array(open_ids, dtype=np.int64)
        frozen = self._calibrator.frozen_observations()
        for name in ("rows", "y", "weights", "group", "cluster"):
            arrays[f"frozen_{name}"] = getattr(frozen, name)
        if self._control is not None:
            arrays["control_xyz"] = self._control.xyz
            arrays["control_ids"] = np.array(self._control.ids)
        tmp = path.with_name(path.name + ".tmp.npz")
        with tmp.open("wb") as fh:
            np.savez(fh, allow_pickle=False, **arrays)
        tmp.replace(path)
        return path

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
        path = Path(path)
        try:
            data = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise InputError(f"{path}: cannot read checkpoint ({exc})") from None
        with data:
            if int(data["version"]) != CHECKPOINT_VERSION:
                raise InputError(f"{path}: checkpoint version {int(data['version'])} unknown")
            control = None
            if "control_xyz" in data:
                control = ControlPoints([str(i) for i in data["control_ids"]],
                                        data["control_xyz"])
            self = cls(config, control=control, max_points=max_points, strip_gap_s=strip_gap_s)
            frame = str(data["frame_id"])
            self.frame_id = frame or None
            if data["traj_t"].size:
                self._traj_t = [data["traj_t"]]
                self._traj_xyz = [data["traj_xyz"]]
                self._traj_q = [data["traj_orientation"]]
            counters = [int(v) for v in data["counters"]]
            self.dropped_points, self.dropped_non_finite = counters[:2]
            if len(counters) > 2:  # (checkpoints of earlier versions lack it)
                self.thinned_points = counters[2]
            if "auto_thinning_cell_m" in data:  # (nor this)
                self.auto_thinning_cell_m = float(data["auto_thinning_cell_m"])
            if "uncovered_points" in data:  # (checkpoints of earlier versions lack them)
                self.uncovered_points = int(data["uncovered_points"])
                self.uncovered_strips = [int(v) for v in data["uncovered_strips"]]
            if "rejected_ids" in data:
                self.rejected_strips = [(int(i), str(r)) for i, r in
                                        zip(data["rejected_ids"], data["rejected_reasons"],
                                            strict=True)]
            self.dropped_strips = [int(v) for v in data["dropped_strips"]]
            for sid in data["closed_ids"]:
                key = f"closed_{int(sid)}"
                inten = data[f"{key}_i"] if f"{key}_i" in data else None
                strip = Strip(int(sid), data[f"{key}_xyz"], data[f"{key}_t"], inten)
                self._closed.append(strip)
                self._calibrator.add_strip(strip, self.trajectory)
            for sid in data["open_ids"]:
                key = f"open_{int(sid)}"
                o = _OpenStrip()
                inten = data[f"{key}_i"] if f"{key}_i" in data else None
                o.add(data[f"{key}_xyz"], data[f"{key}_t"], inten)
                self._open[int(sid)] = o
            frozen = Observations(data["frozen_rows"], data["frozen_y"], data["frozen_weights"],
                                  data["frozen_group"], data["frozen_cluster"])
            self._calibrator.delta = np.array(data["delta"])
            self._calibrator.restore_frozen(frozen)  # expressed at the saved estimate
            self._calibrator.threshold = float(data["threshold"])
            # (checkpoints of earlier versions lack it: not known to be converged)
            self.converged = bool(data["converged"]) if "converged" in data else False
            # No result survives a restart: converge again (at once where it was converged)
            # for one to publish.
            self._refinement_wanted = bool(self._closed) or len(frozen) > 0
            self.normal_equations = NormalEquations(
                np.array(data["neq_n"]), np.array(data["neq_u"]), float(data["neq_yy"]),
                int(data["neq_count"]))
            if self._closed:
                self._now = max(float(s.t[-1]) for s in self._closed)
            for o in self._open.values():
                self._now = max(self._now, o.last_t)
        return self
