"""A rolling buffer of trajectory samples as they arrive (the live nodes' trajectory)."""

from __future__ import annotations

import math
import threading
import time
from typing import Any

import numpy as np

from lidarcal_ros.core.georeferencing.attitude import (
    headings_from_quaternions,
    normalise_quaternions,
)
from lidarcal_ros.core.mission import REORDER_S, Trajectory

__all__ = ["TrajectoryBuffer"]

_NO_ORIENTATION = (math.nan, math.nan, math.nan, math.nan)


def _has_orientation(q: tuple[float, ...]) -> bool:
    """A quaternion that is finite and not the identity (the identity of every pose means "not
    given", :mod:`lidarcal_ros.core.georeferencing.attitude`)."""
    return all(math.isfinite(v) for v in q) and any(v != 0.0 for v in q[:3])

#: Samples added and not yet merged beyond which :meth:`TrajectoryBuffer.add` merges them
#: itself: a reader that rarely asks for the trajectory (the corrector node, which hands its
#: samples on and only reads the flags) must not keep them all as Python objects.
_MAX_PENDING = 20_000
#: Least room (samples) of the buffer's arrays.
_MIN_CAPACITY = 1024


class _Rows:
    """The merged samples in time order, rows ``lo:hi`` of arrays that grow by doubling,
    with what a :class:`~lidarcal_ros.core.mission.Trajectory` derives from each sample
    computed once, as the sample arrives: its unit quaternion (in the hemisphere of the row
    before, :func:`~lidarcal_ros.core.georeferencing.attitude.normalise_quaternions`), heading, tilt
    and uprightness. Rows handed out in a trajectory are never written again (new samples go
    past ``hi``, a full array is copied into a new one), so a trajectory taken earlier stays
    valid in another thread."""

    def __init__(self, trajectory: Trajectory) -> None:
        n = len(trajectory)
        cap = max(_MIN_CAPACITY, 2 * n)
        self.t = np.empty(cap)
        self.xyz = np.empty((cap, 3))
        self.q = np.full((cap, 4), np.nan)
        self.heading = np.full(cap, np.nan)
        self.tilt = np.full(cap, np.nan)
        self.upright = np.full(cap, np.nan)
        self.lo, self.hi = 0, n
        self.oriented = trajectory.orientation is not None  # some row has an orientation
        self.t[:n], self.xyz[:n] = trajectory.t, trajectory.xyz
        if trajectory.orientation is not None:
            self._derive(0, trajectory.orientation)

    def _derive(self, at: int, q: np.ndarray) -> None:
        """Store unit quaternions ``q`` (already in their hemispheres) from row ``at``, with
        their heading, tilt and uprightness (the terms of Trajectory's ``full_attitude``)."""
        end = at + q.shape[0]
        self.q[at:end] = q
        self.heading[at:end] = headings_from_quaternions(q)
        x, y, z, w = q.T
        self.tilt[at:end] = np.maximum(np.abs(x * z - y * w), np.abs(y * z + x * w))
        self.upright[at:end] = 1.0 - 2.0 * (x * x + y * y)

    def append(self, t: np.ndarray, xyz: np.ndarray, q: np.ndarray) -> None:
        """Samples later than every row, in time order (``q`` as given: NaN rows or the
        identity where none)."""
        n = t.shape[0]
        if self.hi + n > self.t.shape[0]:
            self._grow(n)
        at = self.hi
        self.t[at:at + n], self.xyz[at:at + n] = t, xyz
        if self.oriented or not np.isnan(q).all():
            if at > self.lo:
                # The previous row first: the new rows take its hemisphere, as when the
                # whole trajectory is normalised at once.
                unit = normalise_quaternions(np.concatenate([self.q[at - 1:at], q]),
                                             oriented=self.oriented)[1:]
            else:
                unit = normalise_quaternions(q, oriented=self.oriented)
            self._derive(at, unit)
            self.oriented = self.oriented or not np.isnan(unit[:, 0]).all()
        self.hi = at + n

    def _grow(self, n: int) -> None:
        """Room for ``n`` more rows: the kept rows copied into new arrays (never moved in
        place: trajectories handed out may still read them)."""
        kept = self.hi - self.lo
        cap = max(_MIN_CAPACITY, 2 * (kept + n))
        for name in ("t", "xyz", "q", "heading", "tilt", "upright"):
            old = getattr(self, name)
            new = np.full((cap, *old.shape[1:]), np.nan)  # (rows without attitude: NaN)
            new[:kept] = old[self.lo:self.hi]
            setattr(self, name, new)
        self.lo, self.hi = 0, kept

    def trim(self, keep_s: float) -> None:
        """Drop the rows more than ``keep_s`` before the newest."""
        if self.hi - self.lo and keep_s > 0 and self.t[self.hi - 1] - self.t[self.lo] > keep_s:
            self.lo += int(np.searchsorted(self.t[self.lo:self.hi],
                                           self.t[self.hi - 1] - keep_s))

    @property
    def last_t(self) -> float:
        return float(self.t[self.hi - 1]) if self.hi > self.lo else -math.inf

    def trajectory(self) -> Trajectory:
        """The rows as a Trajectory (views, nothing recomputed)."""
        sl = slice(self.lo, self.hi)
        q = self.q[sl] if self.oriented else None
        if q is not None and np.isnan(q[:, 0]).all():
            q = None  # (the rows with an orientation were dropped)
        full = True
        if q is not None:
            with np.errstate(invalid="ignore"):
                full = not bool(np.nanmax(self.tilt[sl]) < 0.5e-9
                                and np.nanmin(self.upright[sl]) > 0.0)
        return Trajectory.of_normalised(self.t[sl], self.xyz[sl], q, full,
                                        None if q is None else self.heading[sl])


class TrajectoryBuffer:
    """Rolling buffer of trajectory samples (thread-safe); samples may arrive out of order.

    ``keep_s`` seconds before the newest sample are kept. :meth:`trajectory` returns a
    :class:`~lidarcal_ros.core.mission.Trajectory` of the buffer (sorted, duplicates dropped),
    updated only when samples were added since the last call: in the common in-order case
    the new samples are appended and only they are normalised (a 200 Hz attitude kept for 600
    s is 120 000 samples, which a corrector asks for 20 times a second), otherwise all are
    sorted again. Samples are merged, and old ones dropped, at the latest every
    ``_MAX_PENDING`` samples, whether or not anyone reads the trajectory.

    A sample more than :data:`~lidarcal_ros.core.mission.REORDER_S` older than the newest is
    a clock that stepped back (a reset, a replay looping): the samples held from its stamp on
    belong to the old clock and are dropped, so that the points of the new clock are
    georeferenced by its own samples, never by the flight the old clock saw at those times
    (:attr:`steps_back` counts the steps, :attr:`last_step_back` says the latest).
    """

    def __init__(self, keep_s: float = 600.0) -> None:
        self.keep_s = float(keep_s)
        self._pending_t: list[float] = []
        self._pending_xyz: list[tuple[float, float, float]] = []
        # Orientation quaternions (x, y, z, w); NaN where not given.
        self._pending_q: list[tuple[float, ...]] = []
        self._rows = _Rows(Trajectory(np.empty(0), np.empty((0, 3))))
        self._traj = self._rows.trajectory()
        self._lock = threading.Lock()
        self._rebuild_lock = threading.Lock()
        self.frame_id: str | None = None
        self.end = -math.inf  # newest sample time
        self.last_arrival = -math.inf  # monotonic clock of the last sample received
        self.samples = 0
        self.oriented_samples = 0  # of them with an orientation (not the identity)
        #: Samples left out: a non-finite stamp or position, a stamp already held, or a
        #: stamp the clock stepped back over.
        self.left_out = 0
        #: Times the stamps stepped back by more than REORDER_S, and the latest as words.
        self.steps_back = 0
        self.last_step_back = ""
        # (index in the pending samples, stamp): held samples from the stamp on are dropped
        self._cuts: list[tuple[int, float]] = []

    def _held(self, t: float) -> bool:
        """A sample at stamp ``t`` is held (merged or pending; lock held): a late repeat,
        left out when merged, is no step back."""
        rows = self._rows
        k = int(np.searchsorted(rows.t[rows.lo:rows.hi], t))
        return (k < rows.hi - rows.lo and rows.t[rows.lo + k] == t) or t in self._pending_t

    def _step_back(self, at: int, t: float) -> None:
        """Note a clock stepping back to ``t`` (s) at pending sample ``at`` (lock held)."""
        self.steps_back += 1
        self.last_step_back = (f"stamps went backwards at t={t:.3f} s, {self.end - t:.3f} s "
                               f"back from t={self.end:.3f} s")
        self._cuts.append((at, t))
        self.end = t

    def add(self, t: float, xyz: tuple[float, float, float], frame_id: str | None = None,
            orientation: tuple[float, ...] = _NO_ORIENTATION) -> None:
        """Add one sample: time (s), position (m), and its orientation quaternion
        ``(x, y, z, w)`` (NaN or the identity: none)."""
        with self._lock:
            if t < self.end - REORDER_S and not self._held(t):
                self._step_back(len(self._pending_t), t)
            self._pending_t.append(t)
            self._pending_xyz.append(xyz)
            self._pending_q.append(orientation)
            if _has_orientation(orientation):
                self.oriented_samples += 1
            self.samples += 1
            self.last_arrival = time.monotonic()
            if t > self.end:
                self.end = t
            if frame_id is not None:
                self.frame_id = frame_id
            merge = len(self._pending_t) > _MAX_PENDING
        if merge:
            self.trajectory()

    def add_many(self, t: Any, xyz: Any, orientation: Any = None) -> None:
        """Add samples given as arrays: times (n,), s, positions (n, 3), m, and optionally
        orientation quaternions (n, 4) xyzw (NaN rows, the identity or None: none)."""
        t = np.asarray(t, dtype=np.float64).reshape(-1)
        if not t.size:
            return
        xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        finite = t[np.isfinite(t)]
        with self._lock:
            newest = np.maximum.accumulate(np.concatenate(([self.end], finite)))
            if np.any(finite < newest[:-1] - REORDER_S):
                base = len(self._pending_t)
                for k in np.flatnonzero(np.isfinite(t)).tolist():  # each step, in order
                    tk = float(t[k])
                    if tk < self.end - REORDER_S and not self._held(tk):
                        self._step_back(base + k, tk)
                    self.end = max(self.end, tk)
            else:
                self.end = float(newest[-1])
            self._pending_t.extend(t.tolist())
            self._pending_xyz.extend(xyz.tolist())
            if orientation is None:
                self._pending_q.extend([_NO_ORIENTATION] * int(t.size))
            else:
                q = np.asarray(orientation, dtype=np.float64).reshape(-1, 4)
                self._pending_q.extend(map(tuple, q.tolist()))
                self.oriented_samples += int(np.count_nonzero(
                    np.isfinite(q).all(axis=1) & np.any(q[:, :3] != 0.0, axis=1)))
            self.samples += int(t.size)
            self.last_arrival = time.monotonic()
            merge = len(self._pending_t) > _MAX_PENDING
        if merge:
            self.trajectory()

    def trajectory(self) -> Trajectory:
        """The trajectory of every sample received so far (the pending ones merged in)."""
        # One rebuild at a time: two threads rebuilding from the same old trajectory would
        # each drop the other's new samples.
        with self._rebuild_lock:
            return self._rebuild()

    def _rebuild(self) -> Trajectory:
        with self._lock:
            if not self._pending_t:
                return self._traj
            t_new = np.asarray(self._pending_t, dtype=np.float64)
            x_new = np.asarray(self._pending_xyz, dtype=np.float64).reshape(-1, 3)
            q_new = np.asarray(self._pending_q, dtype=np.float64).reshape(-1, 4)
            self._pending_t, self._pending_xyz, self._pending_q = [], [], []
            cuts, self._cuts = self._cuts, []
        rows = self._rows
        if cuts:  # the samples of the old clock from each step's stamp on are dropped
            keep_old, keep_new = np.ones(len(self._traj), bool), np.ones(t_new.shape[0], bool)
            for at, t_cut in cuts:
                keep_old &= self._traj.t < t_cut
                keep_new[:at] &= ~(t_new[:at] >= t_cut)
            old = self._traj.take(np.flatnonzero(keep_old))
            self.left_out += int(np.count_nonzero(~keep_old) + np.count_nonzero(~keep_new))
            t_new, x_new, q_new = t_new[keep_new], x_new[keep_new], q_new[keep_new]
            rows = self._rows = _Rows(old)
            self._traj = old
        if (np.isfinite(t_new).all() and np.isfinite(x_new).all()
                and bool(np.all(np.diff(t_new) > 0)) and t_new[0] > rows.last_t):
            rows.append(t_new, x_new, q_new)
        else:  # out of order, repeated or not finite: everything sorted again
            old = self._traj
            orientation = None
            if old.orientation is not None or not np.isnan(q_new).all():
                orientation = np.concatenate([old.orientation if old.orientation is not None
                                              else np.full((len(old), 4), np.nan), q_new])
            merged = Trajectory.from_samples(np.concatenate([old.t, t_new]),
                                             np.concatenate([old.xyz, x_new]), orientation)
            self.left_out += len(old) + int(t_new.shape[0]) - len(merged)
            rows = self._rows = _Rows(merged)
        rows.trim(self.keep_s)
        traj = rows.trajectory()
        with self._lock:
            self._traj = traj
        return traj

    def __len__(self) -> int:
        with self._lock:
            return len(self._traj) + len(self._pending_t)
