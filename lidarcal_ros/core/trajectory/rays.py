"""Laser rays from multiple returns, and the bounded set of them a trajectory estimate keeps.

The first and the last return of one pulse lie on its laser ray, which starts at the sensor:
:func:`rays_from_returns` pairs them into :class:`Rays` (anchor at the first return, unit
direction up towards the sensor), and :class:`RayCollector` keeps, as LAS chunks stream past,
the rays of largest separation per strip and second within a :class:`RayBudget`. What the rays
are for: :mod:`lidarcal_ros.core.trajectory.estimation`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass
class Rays:
    """Laser rays from pulses with several returns (all arrays have n rows).

    Attributes
    ----------
    t : (n,) float64
        Firing time, seconds.
    anchor : (n, 3) float64
        First return, map frame, metres.
    direction : (n, 3) float64
        Unit vector from the last towards the first return (up, towards the sensor).
    separation : (n,) float64
        Distance between first and last return, metres.
    group : (n,) int64
        Flight-line (strip) key.
    """

    t: np.ndarray
    anchor: np.ndarray
    direction: np.ndarray
    separation: np.ndarray
    group: np.ndarray

    def __len__(self) -> int:
        return int(self.t.shape[0])

    def take(self, index: np.ndarray) -> Rays:
        """A subset of the rays."""
        return Rays(self.t[index], self.anchor[index], self.direction[index],
                    self.separation[index], self.group[index])

    @classmethod
    def empty(cls) -> Rays:
        """No rays."""
        return cls(np.empty(0), np.empty((0, 3)), np.empty((0, 3)), np.empty(0),
                   np.empty(0, dtype=np.int64))

    @classmethod
    def concatenate(cls, parts: list[Rays]) -> Rays:
        """Rays of several parts, in order."""
        parts = [p for p in parts if len(p)]
        if not parts:
            return cls.empty()
        return cls(np.concatenate([p.t for p in parts]),
                   np.concatenate([p.anchor for p in parts]),
                   np.concatenate([p.direction for p in parts]),
                   np.concatenate([p.separation for p in parts]),
                   np.concatenate([p.group for p in parts]))


def rays_from_returns(
    xyz: np.ndarray,
    t: np.ndarray,
    group: np.ndarray,
    return_number: np.ndarray,
    number_of_returns: np.ndarray,
    *,
    min_separation_m: float = 2.0,
    max_off_nadir_deg: float = 60.0,
) -> Rays:
    """Rays from the first and last returns of each pulse among the given points.

    A pulse is the set of points sharing one time and one group key; it gives a ray if it
    holds its first return (return number 1) and its last (return number = number of
    returns >= 2), at least ``min_separation_m`` apart, the ray within ``max_off_nadir_deg``
    of the vertical. Returns of one pulse split between two calls are lost (a few, at file
    and chunk edges).

    Parameters
    ----------
    xyz : (n, 3) float64
        Points, map frame, metres.
    t : (n,) float64
        Times, seconds (the returns of one pulse share it exactly).
    group : (n,) int
        Strip key of each point.
    return_number, number_of_returns : (n,) int
    min_separation_m, max_off_nadir_deg : float, keyword-only
    """
    rn = np.asarray(return_number, dtype=np.int64)
    nr = np.asarray(number_of_returns, dtype=np.int64)
    keep = (nr >= 2) & ((rn == 1) | (rn == nr))
    if not keep.any():
        return Rays.empty()
    idx = np.flatnonzero(keep)
    tt, gg, rr = np.asarray(t)[idx], np.asarray(group, dtype=np.int64)[idx], rn[idx]
    order = np.lexsort((rr, gg, tt))
    idx, tt, gg, rr = idx[order], tt[order], gg[order], rr[order]
    nrr = nr[idx]
    new = np.ones(idx.size, dtype=bool)
    new[1:] = (tt[1:] != tt[:-1]) | (gg[1:] != gg[:-1])
    starts = np.flatnonzero(new)
    stops = np.append(starts[1:], idx.size)
    first, last = starts, stops - 1
    ok = (stops - starts >= 2) & (rr[first] == 1) & (rr[last] == nrr[last])
    first, last = first[ok], last[ok]
    p1 = np.asarray(xyz, dtype=np.float64)[idx[first]]
    p2 = np.asarray(xyz, dtype=np.float64)[idx[last]]
    vec = p1 - p2
    sep = np.linalg.norm(vec, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        direction = vec / sep[:, None]
    min_up = math.cos(math.radians(max_off_nadir_deg))
    good = (sep >= min_separation_m) & (direction[:, 2] >= min_up)
    return Rays(tt[first][good], p1[good], direction[good], sep[good], gg[first][good])


@dataclass(frozen=True)
class RayBudget:
    """How many rays a :class:`RayCollector` keeps.

    How many a bin keeps follows a budget of ``max_rays`` over all the bins seen so far,
    between ``per_bin`` and ``max_per_bin``: a short flight (a tile cut from a few lines,
    seconds each) keeps up to ``max_per_bin`` rays a second and its lines are rebuilt from
    tens of times more rays than a fixed share would give them, while a long mission's
    memory stays bounded (``max_rays`` of 72 bytes, down to ``per_bin`` a bin and second).

    Attributes
    ----------
    bin_s : float
        Time bin, seconds.
    per_bin : int
        Rays a bin keeps at the least (while it has them).
    max_per_bin : int
        Rays a bin keeps at the most (raised to ``per_bin`` if below it).
    max_rays : int
        Rays kept over all bins, beyond which each bin keeps fewer (down to ``per_bin``).
    """

    bin_s: float = 1.0
    per_bin: int = 100
    max_per_bin: int = 2_000
    max_rays: int = 500_000


class RayCollector:
    """Keeps, per group and per time bin, the rays of largest separation (:class:`RayBudget`).

    The rays a bin keeps are its best by separation whatever the cap, so lowering the cap as
    the mission grows leaves the same rays as a lower cap from the start.
    """

    def __init__(self, budget: RayBudget = RayBudget()) -> None:
        self.bin_s = float(budget.bin_s)
        self.per_bin = int(budget.per_bin)
        self.max_per_bin = max(int(budget.max_per_bin), self.per_bin)
        self.max_rays = int(budget.max_rays)
        self._parts: list[Rays] = []
        self._pending = 0
        self._kept = 0

    def add(self, rays: Rays) -> None:
        """Offer rays; the best are kept."""
        if not len(rays):
            return
        self._parts.append(rays)
        self._pending += len(rays)
        if self._pending > max(200_000, 2 * self._kept):
            self._compact()

    def _compact(self) -> None:
        rays = Rays.concatenate(self._parts)
        if len(rays):
            bins = np.floor(rays.t / self.bin_s).astype(np.int64)
            order = np.lexsort((-rays.separation, bins, rays.group))
            g, b = rays.group[order], bins[order]
            new = np.ones(order.size, dtype=bool)
            new[1:] = (g[1:] != g[:-1]) | (b[1:] != b[:-1])
            cap = min(self.max_per_bin, max(self.per_bin,
                                            self.max_rays // max(int(new.sum()), 1)))
            start = np.maximum.accumulate(np.where(new, np.arange(order.size), 0))
            rank = np.arange(order.size) - start
            rays = rays.take(np.sort(order[rank < cap]))
        self._parts = [rays]
        self._kept = len(rays)
        self._pending = 0

    def merge(self, other: RayCollector) -> None:
        """Offer the rays ``other`` kept (offered after this one's, the same budget): the
        best of each bin are kept whether they came through one collector or two, since a
        collector of fewer bins keeps at least as many per bin."""
        for part in other._parts:
            self.add(part)

    def rays(self) -> Rays:
        """The rays kept, in time order."""
        self._compact()
        rays = self._parts[0]
        return rays.take(np.argsort(rays.t, kind="stable"))


__all__ = ["RayBudget", "RayCollector", "Rays", "rays_from_returns"]
