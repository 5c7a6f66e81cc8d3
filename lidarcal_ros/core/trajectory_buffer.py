"""A rolling buffer of trajectory samples as they arrive (the live nodes' trajectory)."""

from __future__ import annotations

import math
import threading
import time
from typing import Any

__all__ = ["TrajectoryBuffer"]

_NO_ORIENTATION = (math.nan, math.nan, math.nan, math.nan)


def _has_orientation(q: tuple[float, ...]) -> bool:
    """A quaternion that is finite and not the identity (module of
    :mod:`lidarcal_ros.core.attitude`: the identity means "not given")."""
    return all(math.isfinite(v) for v in q) and any(v != 0.0 for v in q[:3])

#: Samples added and not yet merged beyond which :meth:`TrajectoryBuffer.add` merges them
#: itself: a reader that rarely asks for the trajectory (the corrector node, which hands its
#: samples on and only reads the flags) must not keep them all as Python objects.
_MAX_PENDING = 20_000


class TrajectoryBuffer:
    """Rolling buffer of trajectory samples (thread-safe); samples may arrive out of order.

    ``keep_s`` seconds before the newest sample are kept. :meth:`trajectory` returns a
    :class:`~lidarcal_ros.core.mission.Trajectory` of the buffer (sorted, duplicates dropped),
    updated only when samples were added since the last call (appending in the common
    in-order case, re-sorting otherwise). Samples are merged, and old ones dropped, at the
    latest every ``_MAX_PENDING`` samples, whether or not anyone reads the trajectory.
    """

    def __init__(self, keep_s: float = 600.0) -> None:
        import numpy as np

        from lidarcal_ros.core.mission import Trajectory

        self._np = np
        self._Trajectory = Trajectory
        self.keep_s = float(keep_s)
        self._pending_t: list[float] = []
        self._pending_xyz: list[tuple[float, float, float]] = []
        # Orientation quaternions (x, y, z, w); NaN where not given.
        self._pending_q: list[tuple[float, ...]] = []
        self._traj = Trajectory(np.empty(0), np.empty((0, 3)))
        self._lock = threading.Lock()
        self._rebuild_lock = threading.Lock()
        self.frame_id: str | None = None
        self.end = -math.inf  # newest sample time
        self.last_arrival = -math.inf  # monotonic clock of the last sample received
        self.samples = 0
        self.oriented_samples = 0  # of them with an orientation (not the identity)
        #: Samples left out: a non-finite stamp or position, or a stamp already held.
        self.left_out = 0

    def add(self, t: float, xyz: tuple[float, float, float], frame_id: str | None = None,
            orientation: tuple[float, ...] = _NO_ORIENTATION) -> None:
        """Add one sample: time (s), position (m), and its orientation quaternion
        ``(x, y, z, w)`` (NaN or the identity: none)."""
        with self._lock:
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
        np = self._np
        t = np.asarray(t, dtype=np.float64).reshape(-1)
        if not t.size:
            return
        xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        finite = t[np.isfinite(t)]
        with self._lock:
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
            if finite.size and float(finite.max()) > self.end:
                self.end = float(finite.max())
            merge = len(self._pending_t) > _MAX_PENDING
        if merge:
            self.trajectory()

    def trajectory(self) -> Any:
        # One rebuild at a time: two threads rebuilding from the same old trajectory would
        # each drop the other's new samples.
        with self._rebuild_lock:
            return self._rebuild()

    def _rebuild(self) -> Any:
        np = self._np
        with self._lock:
            if not self._pending_t:
                return self._traj
            t_new = np.asarray(self._pending_t, dtype=np.float64)
            x_new = np.asarray(self._pending_xyz, dtype=np.float64).reshape(-1, 3)
            q_new = np.asarray(self._pending_q, dtype=np.float64).reshape(-1, 4)
            self._pending_t, self._pending_xyz, self._pending_q = [], [], []
        old = self._traj
        t = np.concatenate([old.t, t_new])
        xyz = np.concatenate([old.xyz, x_new])
        orientation = None
        if old.orientation is not None or not np.isnan(q_new).all():
            orientation = np.concatenate([old.orientation if old.orientation is not None
                                          else np.full((len(old), 4), np.nan), q_new])
        if (np.isfinite(t_new).all() and np.isfinite(x_new).all()
                and bool(np.all(np.diff(t_new) > 0))
                and (len(old) == 0 or t_new[0] > old.t[-1])):
            traj = self._Trajectory(t, xyz, orientation)
        else:
            traj = self._Trajectory.from_samples(t, xyz, orientation)
            self.left_out += int(t.shape[0]) - len(traj)
        if len(traj) and self.keep_s > 0 and traj.t[-1] - traj.t[0] > self.keep_s:
            start = int(np.searchsorted(traj.t, traj.t[-1] - self.keep_s))
            traj = traj.take(slice(start, None))
        with self._lock:
            self._traj = traj
        return traj

    def __len__(self) -> int:
        with self._lock:
            return len(self._traj) + len(self._pending_t)
