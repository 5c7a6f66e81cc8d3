"""What the live calibration holds before a strip is complete, and the memory budget bounding it.

The strips being flown (:class:`OpenStrip`, as the chunks they arrived in) and the trajectory
samples; past the budget they are thinned (docs/nodes.md, "How the calibrator works").
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from lidarcal_ros.core.calibration.thinning import first_per_cell
from lidarcal_ros.core.mission import REORDER_S, Strip, Trajectory
from lidarcal_ros.errors import InputError

__all__ = [
    "BYTES_PER_HELD_POINT", "FIRST_AUTO_CELL_M", "MAX_AUTO_CELL_M", "OpenStrip", "OpenStrips",
    "TrajectorySamples", "default_point_budget",
]

#: What a point held by the calibration costs in memory once its strip is complete (its
#: triangles, their planes and neighbours; measured: 643 bytes on a 3.2M-point mission).
BYTES_PER_HELD_POINT = 700
#: Share of the machine's memory :func:`default_point_budget` gives the calibration.
_MEMORY_SHARE = 0.5
#: The first cell of the automatic thinning where no thinning was set, m (then doubled):
#: about the point spacing of a dense sensor.
FIRST_AUTO_CELL_M = 0.25
#: Coarsest automatic thinning cell, m: beyond it a strip hardly has patches left to match.
MAX_AUTO_CELL_M = 32.0


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
class OpenStrip:
    """The chunks of a strip still being flown (map frame, m; times in s)."""

    xyz: list[np.ndarray] = field(default_factory=list)
    t: list[np.ndarray] = field(default_factory=list)
    intensity: list[np.ndarray] = field(default_factory=list)
    has_intensity: bool = True
    #: Time of its newest point, s.
    last_t: float = -np.inf
    #: Points held.
    n: int = 0

    def add(self, xyz: np.ndarray, t: np.ndarray, intensity: np.ndarray | None) -> None:
        """Hold a chunk: points ``xyz`` (n, 3) (map frame, m), their times ``t`` (s) and
        intensities (None: the strip then keeps none)."""
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
        """The points held, in time order."""
        t = np.concatenate(self.t)
        order = np.argsort(t, kind="stable")
        inten = np.concatenate(self.intensity)[order] if self.has_intensity else None
        return Strip(strip_id, np.concatenate(self.xyz)[order], t[order], inten)


class OpenStrips:
    """The strips still being flown, by strip id."""

    def __init__(self) -> None:
        self._strips: dict[int, OpenStrip] = {}

    def __contains__(self, strip_id: int) -> bool:
        return strip_id in self._strips

    def __len__(self) -> int:
        return len(self._strips)

    @property
    def ids(self) -> list[int]:
        """Their strip ids, ascending."""
        return sorted(self._strips)

    @property
    def n_points(self) -> int:
        """Points held."""
        return sum(o.n for o in self._strips.values())

    def last_t(self, strip_id: int) -> float:
        """Time of the newest point of a strip, s."""
        return self._strips[strip_id].last_t

    def add(self, strip_id: int, xyz: np.ndarray, t: np.ndarray,
            intensity: np.ndarray | None) -> None:
        """Add a chunk of points of one strip (a new strip opens with its first chunk)."""
        self._strips.setdefault(strip_id, OpenStrip()).add(xyz, t, intensity)

    def strip(self, strip_id: int) -> Strip:
        """The points of a strip held so far, in time order."""
        return self._strips[strip_id].to_strip(strip_id)

    def pop(self, strip_id: int) -> Strip:
        """Take a strip out: it is complete."""
        return self._strips.pop(strip_id).to_strip(strip_id)

    def strips(self) -> Iterator[Strip]:
        """Every strip held, as :meth:`strip` gives it, in the order they opened."""
        return (o.to_strip(sid) for sid, o in self._strips.items())

    def ready(self, now_s: float, gap_s: float) -> list[int]:
        """Strips without a point for ``gap_s`` seconds before ``now_s``, oldest first."""
        idle = [sid for sid, o in self._strips.items() if now_s - o.last_t >= gap_s]
        return sorted(idle, key=self.last_t)

    def by_age(self) -> list[int]:
        """Every strip id, the one whose newest point is oldest first."""
        return sorted(self._strips, key=self.last_t)

    def thin_to(self, target: int, cell_m: float) -> tuple[float, int]:
        """Thin every cloud's part of every strip at twice ``cell_m`` (0: at
        :data:`FIRST_AUTO_CELL_M`), again and again, until at most ``target`` points are held
        or the cell reaches :data:`MAX_AUTO_CELL_M`; returns the cell (m) and the points let
        go."""
        cell = cell_m or FIRST_AUTO_CELL_M / 2.0
        removed = 0
        while self.n_points > target and cell < MAX_AUTO_CELL_M:
            cell *= 2.0
            for strip_id, strip in self._strips.items():
                removed += strip.thin(strip_id, cell)
        return cell, removed


class TrajectorySamples:
    """Trajectory samples as they arrive (IMU origin in the map frame, m; times in s; the
    orientation quaternions xyzw, NaN rows where not given)."""

    def __init__(self) -> None:
        self._t: list[np.ndarray] = []
        self._xyz: list[np.ndarray] = []
        self._q: list[np.ndarray] = []
        self._trajectory: Trajectory | None = None
        #: Samples left out of :attr:`trajectory`: a non-finite stamp or position, or a stamp
        #: already held (counted when the trajectory is formed), or dropped by a clock that
        #: stepped back.
        self.left_out = 0
        self._dropped = 0
        self._newest = -math.inf
        #: Times the stamps stepped back, and the latest in words.
        self.steps_back = 0
        self.last_step_back = ""

    def _cut(self, t_cut: float) -> None:
        """Drop the samples held from ``t_cut`` (s) on: the clock stepped back to it."""
        t, xyz, q = self.arrays()
        keep = ~(t >= t_cut)
        self.steps_back += 1
        self.last_step_back = (f"stamps went backwards at t={t_cut:.3f} s, "
                               f"{self._newest - t_cut:.3f} s back from t={self._newest:.3f} s")
        self._dropped += int(np.count_nonzero(~keep))
        self._t, self._xyz, self._q = [t[keep]], [xyz[keep]], [q[keep]]
        self._newest = float(t[keep].max()) if keep.any() else -math.inf

    def __bool__(self) -> bool:
        return bool(self._t)

    def add(self, t: np.ndarray, xyz: np.ndarray, orientation: np.ndarray | None) -> None:
        """Add samples: times (n,), positions (n, 3), quaternions (n, 4) or None.

        A stamp more than :data:`~lidarcal_ros.core.mission.REORDER_S` before the newest
        held is a clock that stepped back: the samples held from that stamp on are the old
        clock's and are dropped (counted in :attr:`left_out`, said in
        :attr:`last_step_back`), as the corrector's buffer does
        (:class:`~lidarcal_ros.core.trajectory.buffer.TrajectoryBuffer`).
        """
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        index = np.flatnonzero(np.isfinite(t))
        newest = np.maximum.accumulate(np.concatenate(([self._newest], t[index])))
        back = np.flatnonzero(t[index] < newest[:-1] - REORDER_S)
        if back.size:  # a late repeat of a stamp held (left out when formed) is no step
            held = np.concatenate([*self._t, t])
            first = np.array([np.flatnonzero(held == v)[0] for v in t[index[back]]])
            back = back[first >= len(held) - t.size + index[back]]
        q = None if orientation is None else np.asarray(orientation).reshape(-1, 4)
        if back.size:  # the first step back: held from its stamp on is the old clock's
            at = int(index[back[0]])
            self._append(t[:at], xyz[:at], None if q is None else q[:at])
            self._newest = float(newest[back[0]])
            self._cut(float(t[at]))
            self.add(t[at:], xyz[at:], None if q is None else q[at:])  # (later steps)
            return
        self._newest = float(newest[-1])
        self._append(t, xyz, q)

    @property
    def newest(self) -> float:
        """The newest stamp held, s (-inf: none)."""
        return self._newest

    def _append(self, t: np.ndarray, xyz: np.ndarray, orientation: np.ndarray | None) -> None:
        """Hold samples as given (no check)."""
        self._t.append(t)
        self._xyz.append(np.asarray(xyz, dtype=np.float64).reshape(-1, 3))
        self._q.append(np.full((t.shape[0], 4), np.nan) if orientation is None
                       else np.asarray(orientation, dtype=np.float64).reshape(-1, 4))
        self._trajectory = None

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every sample received, in the order received: times, positions, quaternions."""
        if not self._t:
            return np.empty(0), np.empty((0, 3)), np.empty((0, 4))
        return np.concatenate(self._t), np.concatenate(self._xyz), np.concatenate(self._q)

    @property
    def trajectory(self) -> Trajectory:
        """The trajectory of the samples received (screened: :attr:`left_out`).

        Raises
        ------
        InputError
            No sample received yet.
        """
        if self._trajectory is None:
            if not self._t:
                raise InputError("no trajectory received yet")
            t, xyz, q = self.arrays()
            self._trajectory = Trajectory.from_samples(t, xyz, q)
            self.left_out = self._dropped + int(t.shape[0]) - len(self._trajectory)
        return self._trajectory
