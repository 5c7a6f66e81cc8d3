"""Rebuilding the flight path from multiple returns, where no trajectory was delivered.

The first and the last return of one pulse lie on the laser ray, which starts at the sensor.
Rays of pulses fired close in time therefore pass near one point that moves slowly along the
flight line: the sensor. For each flight line (split into segments of at most ``segment_s``
seconds) the sensor position is modelled as a polynomial in time (a straight line by
default) and found by weighted least squares, minimising the perpendicular distances of the
model position at each ray's time to that ray::

    minimise  sum_i  w_i | (I - d_i d_i^T) (P(t_i) - a_i) |^2,   P(t) = sum_k c_k L_k(tau)

where ``a_i`` is the first return, ``d_i`` the unit ray direction (towards the sensor),
``L_k`` Legendre polynomials of the segment's normalised time ``tau`` in [-1, 1]. The
direction of a ray is known to about ``sqrt(2) sigma_p / s_i`` (``s_i`` the separation of the
two returns, ``sigma_p`` the point noise across the ray), so its distance to the sensor, at
range ``R_i``, to ``sqrt(2) sigma_p R_i / s_i``: ``w_i = 1 / (sigma_p^2 (1 + 2 R_i^2 / s_i^2))``,
iterated with ``R_i`` from the previous solution, and rays whose normalised residual exceeds
``robust_k`` robust standard deviations are dropped.

The position found is where the biased rays cross: the IMU origin plus the lever arm (and
its bias), a few centimetres to decimetres away, which the quasi-rigorous method, needing
positions to metres, tolerates (method.md section 4: the trajectory enters only the design
matrix). Along the track the position comes from where each ray's scan plane cuts the ground
track, across and up from the crossing of the fan: a linear scanner's fan of +-25 degrees
fixes the height about twice less well than the across-track position.

Quality per segment: rays used, RMS ray-to-sensor distance (m), condition number of the
normal matrix, a-posteriori standard deviation of the position (m, the largest over the
segment), and the sensor's height above the returns.

Weak segments: where the rays alone rebuild a segment poorly (few of them, or a fan only a
few degrees wide, as where a tile holds one edge of a line's swath: the rays then cross
nowhere in particular), the segment is fitted again as level flight, its height taken from
the segments rebuilt well (of its own line first, else of the other lines) and carried into
the stated sigma as a considered parameter; where its own fan is wide enough to fix its
height and that disagrees with theirs, its own is kept (a line flown at another altitude).
The quasi-rigorous method needs positions to metres only, so such a line, flagged, serves
better than its points left out (:func:`estimate_trajectory`).
"""

from __future__ import annotations

import copy
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lidarcal_ros.core.mission import Trajectory
from lidarcal_ros.errors import TrajectoryError

logger = logging.getLogger(__name__)

#: Spread of rays across the track (deg) below which they fix the sensor's height poorly.
_MIN_FAN_DEG = 10.0


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


class RayCollector:
    """Keeps, per group and per ``bin_s`` seconds, the rays of largest separation.

    How many a bin keeps follows a budget of ``max_rays`` over all the bins seen so far,
    between ``per_bin`` and ``max_per_bin``: a short flight (a tile cut from a few lines,
    seconds each) keeps up to ``max_per_bin`` rays a second and its lines are rebuilt from
    tens of times more rays than a fixed share would give them, while a long mission's
    memory stays bounded (``max_rays`` of 72 bytes, down to ``per_bin`` a bin and second).
    The rays a bin keeps are its best by separation whatever the cap, so lowering the cap as
    the mission grows leaves the same rays as a lower cap from the start.
    """

    def __init__(self, *, bin_s: float = 1.0, per_bin: int = 100, max_per_bin: int = 2_000,
                 max_rays: int = 500_000) -> None:
        self.bin_s = float(bin_s)
        self.per_bin = int(per_bin)
        self.max_per_bin = max(int(max_per_bin), self.per_bin)
        self.max_rays = int(max_rays)
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

    def rays(self) -> Rays:
        """The rays kept, in time order."""
        self._compact()
        rays = self._parts[0]
        return rays.take(np.argsort(rays.t, kind="stable"))


@dataclass
class SegmentQuality:
    """How well one segment of the flight path was rebuilt.

    Attributes
    ----------
    strip_id : int
    t_start, t_end : float
        Span of the segment (of its points), seconds.
    n_rays : int
        Rays used (after outlier rejection).
    n_rejected : int
    rms_m : float
        RMS perpendicular distance from the rays to the fitted sensor position, metres.
    sigma0 : float
        The same in units of what each ray's noise model expects (its weight): about 1
        where the rays meet as a point noise of ``point_sigma_m`` says they should.
    sigma_m : float
        Largest a-posteriori standard deviation of a position coordinate over the segment, m.
    horizontal_sigma_m : float
        The same of the horizontal coordinates alone, metres.
    condition : float
        Condition number of the (column-scaled) normal matrix.
    height_m : float
        Sensor height above the median first return, metres.
    speed_mps : float
        Horizontal speed of the fitted path, m/s.
    altitude_m, altitude_sigma_m : float
        Sensor height in the map frame at the segment's centre and its standard deviation, m.
    fan_deg : float
        Spread of the rays across the track (5th to 95th percentile of their angle from the
        vertical in the plane across the track), degrees: the crossing of the fan fixes the
        height, and a narrow fan (the tile holds one edge of the swath) fixes it poorly.
    model : ``"rays"`` or ``"level"``
        ``rays``: the polynomial fitted to the rays alone. ``level``: the fallback of a weak
        segment, level flight (one height), the height also drawn from ``altitude_from``.
    altitude_from : tuple of int
        Strips whose rebuilt altitude went into a ``level`` fit as a prior (the strip itself
        when its other segments were rebuilt well), empty when none was.
    weak : bool
        Kept although its position sigma exceeds the estimate's ``max_sigma_m``.
    fallback : str
        How a segment the rays alone rebuilt poorly was rebuilt instead (``message`` then
        says why it was poor); empty for a fit of the rays alone.
    level : ``"OK"``, ``"WARN"`` or ``"ERROR"``
        ERROR: not used (its strip has no trajectory there).
    message : str
    """

    strip_id: int
    t_start: float
    t_end: float
    n_rays: int
    n_rejected: int = 0
    rms_m: float = math.nan
    sigma0: float = math.nan
    sigma_m: float = math.nan
    horizontal_sigma_m: float = math.nan
    condition: float = math.nan
    height_m: float = math.nan
    speed_mps: float = math.nan
    altitude_m: float = math.nan
    altitude_sigma_m: float = math.nan
    fan_deg: float = math.nan
    model: str = "rays"
    altitude_from: tuple[int, ...] = ()
    weak: bool = False
    level: str = "ERROR"
    message: str = ""
    fallback: str = ""


@dataclass
class StripEstimate:
    """What became of one strip's trajectory.

    Attributes
    ----------
    strip_id : int
    kept : bool
        The strip has a trajectory (possibly weak); False: its points are left out.
    sigma_m : float
        Largest position sigma of its segments kept, metres (NaN when none was).
    fallback : bool
        Some of its segments were rebuilt as level flight (the rays alone rebuilt them
        poorly).
    summary : str
        One line saying how it was rebuilt, how well, and why it is weak or left out.
    """

    strip_id: int
    kept: bool
    sigma_m: float
    fallback: bool
    summary: str


@dataclass
class EstimatedTrajectory:
    """A rebuilt trajectory and its quality.

    Attributes
    ----------
    trajectory : Trajectory
        Samples of the usable segments, map frame, metres.
    segments : list of SegmentQuality
        Every segment as finally fitted (a weak one after its fallback).
    failed_strips : list of int
        Strips none of whose segments could be rebuilt (no trajectory for them).
    strips : list of StripEstimate
        Per strip, in id order, what happened.
    """

    trajectory: Trajectory
    segments: list[SegmentQuality] = field(default_factory=list)
    failed_strips: list[int] = field(default_factory=list)
    strips: list[StripEstimate] = field(default_factory=list)


def _legendre(tau: np.ndarray, degree: int) -> np.ndarray:
    """``(n, degree + 1)`` Legendre polynomials of ``tau``."""
    out = np.empty((tau.shape[0], degree + 1))
    out[:, 0] = 1.0
    if degree >= 1:
        out[:, 1] = tau
    for k in range(2, degree + 1):
        out[:, k] = ((2 * k - 1) * tau * out[:, k - 1] - (k - 1) * out[:, k - 2]) / k
    return out


def _fit_segment(
    rays: Rays,
    t_start: float,
    t_end: float,
    *,
    degree: int,
    point_sigma_m: float,
    robust_k: float,
    iterations: int = 6,
    level: bool = False,
    altitude: tuple[float, float] | None = None,
) -> tuple[np.ndarray, np.ndarray, SegmentQuality, float, float]:
    """Fit ``P(t)`` to the rays of one segment.

    ``level``: the height is one constant (level flight: no vertical term of degree 1 or
    more). ``altitude``: that height ``(value, sigma)`` (map frame, metres) taken from
    elsewhere instead of from the rays (with ``level`` only): the rays fix the rest of the
    path at that height, and the covariance adds what ``sigma`` moves it by (the height is a
    considered parameter, not adjusted).

    Returns the coefficients ``(degree + 1, 3)``, their covariance ``(3(d+1), 3(d+1))`` (zero
    for the vertical terms a level fit leaves out), the quality (level not set), and the
    centre and half-span of the normalised time.
    """
    if altitude is not None and not level:
        raise ValueError("a given altitude needs the level model")
    tc = 0.5 * (t_start + t_end)
    half = max(0.5 * (t_end - t_start), 0.5)
    tau = (rays.t - tc) / half
    basis = _legendre(tau, degree)
    d = rays.direction
    proj = np.eye(3)[None, :, :] - d[:, :, None] * d[:, None, :]  # (n, 3, 3)
    ref = rays.anchor.mean(axis=0)
    m = 3 * (degree + 1)
    # coefficient order (k, a): index 3 k + a; a level fit keeps the constant height only,
    # and with a given altitude not even that
    given = np.zeros(m)
    if altitude is not None:
        given[2] = altitude[0] - ref[2]
    free = np.array([i for i in range(m) if not (level and i % 3 == 2 and i >= 3)
                     and not (altitude is not None and i == 2)])
    ma = np.einsum("iab,ib->ia", proj, rays.anchor - ref)
    use = np.ones(len(rays), dtype=bool)
    weights = rays.separation**2  # first pass: direction quality only
    coef = np.zeros((degree + 1, 3))
    dist = np.zeros(len(rays))

    def normal_of(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        normal = np.einsum("i,ik,il,iab->kalb", w, basis, basis, proj).reshape(m, m)
        rhs = np.einsum("i,ik,ia->ka", w, basis, ma).reshape(m) - normal @ given
        return normal, rhs

    for _ in range(iterations):
        normal, rhs = normal_of(weights * use)
        try:
            sol = np.linalg.solve(normal[np.ix_(free, free)], rhs[free])
        except np.linalg.LinAlgError:
            raise TrajectoryError("singular ray geometry") from None
        full = given.copy()
        full[free] = sol
        coef = full.reshape(degree + 1, 3)
        pos = basis @ coef  # relative to ref
        resid = np.einsum("iab,ib->ia", proj, pos - (rays.anchor - ref))
        dist = np.linalg.norm(resid, axis=1)
        rng = np.maximum(np.linalg.norm(pos - (rays.anchor - ref), axis=1), 1.0)
        weights = 1.0 / (point_sigma_m**2 * (1.0 + 2.0 * rng**2 / rays.separation**2))
        z = dist * np.sqrt(weights)
        scale = 1.4826 * float(np.median(z[use])) + 1e-12
        new_use = z <= robust_k * scale
        if new_use.sum() < free.size:
            break
        if np.array_equal(new_use, use):
            break
        use = new_use
    w = weights * use
    full_normal, _ = normal_of(w)
    normal = full_normal[np.ix_(free, free)]
    n_used = int(use.sum())
    redundancy = 2 * n_used - free.size
    sigma0_sq = float(np.sum(w * dist**2) / redundancy) if redundancy > 0 else math.nan
    try:
        inverse = np.linalg.inv(normal)
    except np.linalg.LinAlgError:
        raise TrajectoryError("singular ray geometry") from None
    cov = np.zeros((m, m))
    cov[np.ix_(free, free)] = sigma0_sq * inverse
    if altitude is not None:
        # how the free coefficients follow the given height, and its variance through them
        follow = -inverse @ full_normal[free, 2]
        var = altitude[1] ** 2
        cov[np.ix_(free, free)] += var * np.outer(follow, follow)
        cov[free, 2] = cov[2, free] = var * follow
        cov[2, 2] = var
    scale_n = np.sqrt(np.diag(normal))
    condition = float(np.linalg.cond(normal / np.outer(scale_n, scale_n)))
    # position covariance at the ends and the middle; keep the worst coordinate
    probe = _legendre(np.array([-1.0, 0.0, 1.0]), degree)
    sig_xyz = np.zeros(3)
    for b in probe:
        jac = np.kron(b, np.eye(3))  # (3, m) for coefficient order (k, a)
        sig_xyz = np.maximum(sig_xyz, np.sqrt(np.diag(jac @ cov @ jac.T)))
    coef = coef.copy()
    coef[0] += ref
    vel = coef[1] / half if degree >= 1 else np.zeros(3)
    fan = math.nan
    if n_used and math.hypot(vel[0], vel[1]) > 1e-6:
        across = np.array([-vel[1], vel[0], 0.0]) / math.hypot(vel[0], vel[1])
        angle = np.degrees(np.arctan2(d[use] @ across, d[use, 2]))
        lo, hi = np.percentile(angle, [5.0, 95.0])
        fan = float(hi - lo)
    q = SegmentQuality(
        strip_id=int(rays.group[0]) if len(rays) else -1,
        t_start=float(t_start),
        t_end=float(t_end),
        n_rays=n_used,
        n_rejected=int(len(rays) - n_used),
        rms_m=float(np.sqrt(np.mean(dist[use] ** 2))) if n_used else math.nan,
        sigma0=math.sqrt(sigma0_sq),
        sigma_m=float(sig_xyz.max()),
        horizontal_sigma_m=float(sig_xyz[:2].max()),
        condition=condition,
        height_m=float(coef[0, 2] - np.median(rays.anchor[use, 2])) if n_used else math.nan,
        speed_mps=float(np.hypot(vel[0], vel[1])),
        altitude_m=float(coef[0, 2]),
        altitude_sigma_m=float(np.sqrt(cov[2, 2])),
        fan_deg=fan,
        model="level" if level else "rays",
    )
    return coef, cov, q, tc, half


def _segment_edges(t: np.ndarray, t_first: float, t_last: float, segment_s: float,
                   min_rays: int) -> list[float]:
    """Edges of segments of at most ``segment_s`` (merged until each holds ``min_rays``)."""
    n_seg = max(1, math.ceil((t_last - t_first) / segment_s - 1e-9))
    edges = list(np.linspace(t_first, t_last, n_seg + 1))
    while len(edges) > 2:
        counts = np.histogram(t, bins=edges)[0]
        k = int(np.argmin(counts))
        if counts[k] >= min_rays:
            break
        # merge the poorest segment with its poorer neighbour
        if k == 0:
            drop = 1
        elif k == len(counts) - 1:
            drop = k
        else:
            drop = k if counts[k - 1] <= counts[k + 1] else k + 1
        del edges[drop]
    return [float(e) for e in edges]


@dataclass
class _SegmentFit:
    """One segment's rays and fit (internal to :func:`estimate_trajectory`)."""

    rays: Rays
    first: bool  # the strip's first segment: its samples start ``lead_s`` early
    last: bool
    q: SegmentQuality
    coef: np.ndarray | None = None
    tc: float = 0.0
    half: float = 1.0


def estimate_trajectory(
    rays: Rays,
    spans: dict[int, tuple[float, float]],
    *,
    segment_s: float = 30.0,
    degree: int = 1,
    rate_hz: float = 10.0,
    lead_s: float = 1.0,
    point_sigma_m: float = 0.05,
    robust_k: float = 3.0,
    min_rays: int = 30,
    max_sigma_m: float = 5.0,
    min_weak_rays: int = 10,
    altitude_fraction: float = 0.05,
    max_weak_fraction: float = 0.25,
) -> EstimatedTrajectory:
    """Rebuild the sensor path of each strip from its rays (module docstring).

    A segment the rays alone rebuild poorly (position sigma over ``max_sigma_m``, too few
    rays, the sensor not above the returns, no speed) is not dropped: it is fitted again as
    level flight (one height over the segment), that height drawn also from the segments
    rebuilt well (those of its own strip if any, else those of the other strips: the lines
    of one flight are flown at about one altitude), with a standard deviation of
    ``altitude_fraction`` of their height above the returns, or their spread, or the
    disagreement with the segment's own rays where that is larger. It is kept with the
    sigma that fit states, as WARN (``weak`` where that sigma exceeds ``max_sigma_m``), and
    left out only where even that fails: fewer than ``min_weak_rays`` rays, no speed, or a
    sigma over ``max_weak_fraction`` of the height above the returns.

    Parameters
    ----------
    rays : Rays
        ``group`` holds the strip id.
    spans : dict of int to (float, float)
        Strip id -> first and last point time, seconds: the samples cover each span plus
        ``lead_s`` on both sides.
    segment_s : float, keyword-only
        Longest segment fitted with one polynomial, seconds.
    degree : int, keyword-only
        Polynomial degree in time (1: straight line at constant speed).
    rate_hz : float, keyword-only
        Rate of the trajectory samples written, Hz.
    point_sigma_m : float, keyword-only
        Noise of a return across the ray, metres (weights only).
    robust_k : float, keyword-only
        Rays beyond ``robust_k`` robust standard deviations are rejected.
    min_rays : int, keyword-only
        Fewest rays a segment needs for a fit from its rays alone.
    max_sigma_m : float, keyword-only
        Position sigma beyond which a segment's own fit is weak, metres.
    min_weak_rays : int, keyword-only
        Fewest rays the level fallback needs.
    altitude_fraction : float, keyword-only
        Standard deviation of the altitude lent by other segments, as a fraction of their
        height above the returns.
    max_weak_fraction : float, keyword-only
        Largest position sigma of a segment kept, as a fraction of its height.

    Returns
    -------
    EstimatedTrajectory
        Strips without a usable segment are listed in ``failed_strips`` and get no samples.
    """
    if degree < 0 or degree > 5:
        raise TrajectoryError(f"trajectory estimate: degree {degree} outside 0..5")
    fit_options: dict[str, Any] = {"degree": degree, "point_sigma_m": point_sigma_m,
                                   "robust_k": robust_k}
    need = max(min_rays, 3 * (degree + 1))
    order = np.argsort(rays.group, kind="stable")
    g_sorted = rays.group[order]
    fits: dict[int, list[_SegmentFit]] = {}
    for sid, (t_first, t_last) in sorted(spans.items()):
        lo, hi = np.searchsorted(g_sorted, [sid, sid + 1])
        strip_rays = rays.take(order[lo:hi])
        edges = _segment_edges(strip_rays.t, t_first, t_last, segment_s, min_rays)
        fits[sid] = []
        for k in range(len(edges) - 1):
            a, b = edges[k], edges[k + 1]
            last = k == len(edges) - 2
            inside = (strip_rays.t >= a) & ((strip_rays.t <= b) if last else (strip_rays.t < b))
            seg = _SegmentFit(strip_rays.take(inside), k == 0, last,
                              SegmentQuality(sid, a, b, int(inside.sum())))
            fits[sid].append(seg)
            if len(seg.rays) < need:
                seg.q.message = f"{len(seg.rays)} multi-return pulses, need {need}"
                continue
            _fit_into(seg, fit_options)
            if seg.coef is not None:
                _grade(seg.q, max_sigma_m=max_sigma_m)
    good = [f.q for strip in fits.values() for f in strip if f.q.level != "ERROR"]
    for strip in fits.values():
        for seg in strip:
            if seg.q.level == "ERROR":
                _level_fallback(seg, good, fit_options, need=need, min_rays=min_weak_rays,
                                max_sigma_m=max_sigma_m, altitude_fraction=altitude_fraction,
                                max_weak_fraction=max_weak_fraction)
    samples_t: list[np.ndarray] = []
    samples_xyz: list[np.ndarray] = []
    for strip in fits.values():
        for seg in strip:
            if seg.q.level == "ERROR" or seg.coef is None:
                continue
            a, b = seg.q.t_start, seg.q.t_end
            s0 = a - lead_s if seg.first else a
            s1 = b + lead_s if seg.last else b
            n = max(2, int(math.ceil((s1 - s0) * rate_hz)) + 1)
            ts = np.linspace(s0, s1, n)
            if not seg.last:
                ts = ts[:-1]  # the next segment starts there
            samples_t.append(ts)
            samples_xyz.append(_legendre((ts - seg.tc) / seg.half, degree) @ seg.coef)
    if samples_t:
        traj = Trajectory.from_samples(np.concatenate(samples_t), np.concatenate(samples_xyz))
    else:
        traj = Trajectory(np.empty(0), np.empty((0, 3)))
    segments = [f.q for strip in fits.values() for f in strip]
    for q in segments:
        log = logger.warning if q.level != "OK" else logger.info
        log("trajectory estimate, strip %d %.1f-%.1f s: %s, %d rays, RMS %.2f m, sigma %.2f m, "
            "height %.0f m%s", q.strip_id, q.t_start, q.t_end, q.level, q.n_rays, q.rms_m,
            q.sigma_m, q.height_m, f" ({q.message})" if q.message else "")
    outcomes = [_strip_outcome(sid, [f.q for f in strip]) for sid, strip in fits.items()]
    failed = [o.strip_id for o in outcomes if not o.kept]
    return EstimatedTrajectory(traj, segments, failed, outcomes)


def _fit_into(seg: _SegmentFit, options: dict[str, Any], **model: Any) -> None:
    """Fit ``seg`` (``model``: ``level``, ``altitude`` of :func:`_fit_segment`), keeping the
    fit; a singular geometry leaves it unfitted with the reason as its message."""
    q0 = seg.q
    try:
        coef, _, q, tc, half = _fit_segment(seg.rays, q0.t_start, q0.t_end, **options, **model)
    except TrajectoryError as exc:
        q0.message = str(exc)
        return
    q.strip_id = q0.strip_id
    seg.coef, seg.q, seg.tc, seg.half = coef, q, tc, half


def _grade(q: SegmentQuality, *, max_sigma_m: float) -> None:
    problems = _implausible(q)
    if not (q.sigma_m <= max_sigma_m):
        problems.append(f"position sigma {q.sigma_m:.1f} m > {max_sigma_m:g} m")
    if problems:
        q.level, q.message = "ERROR", "; ".join(problems)
    elif q.sigma_m > 1.0 or q.condition > 1e8:
        # (not the RMS in metres: rays of short separation, kept by the thousand where the
        # flight is short, miss the sensor by metres as their noise says; sigma weighs them)
        q.level = "WARN"
        q.message = "weak ray geometry"
    else:
        q.level = "OK"


def _implausible(q: SegmentQuality) -> list[str]:
    """What makes a fitted path no aircraft's."""
    problems = []
    if not (q.height_m > 0):
        problems.append(f"sensor not above the returns (height {q.height_m:.1f} m)")
    if not (q.speed_mps > 1.0):
        problems.append(f"horizontal speed {q.speed_mps:.2f} m/s: heading undefined")
    return problems


def _why_weak(q: SegmentQuality, need: int) -> str:
    """Why the rays alone rebuild a segment poorly, in words (from its first fit, ERROR;
    ``need``: the rays that fit needs)."""
    if q.n_rays == 0:
        return "no pulse with a first and a last return"
    if q.n_rays < need:
        return f"few multiple returns, {q.n_rays} rays"
    if not math.isfinite(q.sigma_m):  # not fitted: singular
        return q.message
    if _implausible(q):
        return q.message
    if math.isfinite(q.fan_deg) and q.fan_deg < _MIN_FAN_DEG:
        return f"{q.n_rays} rays spanning {q.fan_deg:.1f} deg across the track"
    if q.rms_m > 2.0:
        return f"{q.n_rays} rays scattered, RMS {q.rms_m:.1f} m from the sensor"
    return f"few multiple returns, {q.n_rays} rays"


def _altitude_prior(strip_id: int, good: list[SegmentQuality], fraction: float
                    ) -> tuple[float, float, tuple[int, ...]] | None:
    """Altitude (m), its standard deviation (m) and the strips it comes from, for a weak
    segment of ``strip_id``: its own strip's segments rebuilt well if any, else every
    other strip's (module docstring of :func:`estimate_trajectory`); None without any."""
    pool = [q for q in good if q.strip_id == strip_id] or good
    if not pool:
        return None
    ids = sorted({q.strip_id for q in pool})
    per_strip = [float(np.median([q.altitude_m for q in pool if q.strip_id == i]))
                 for i in ids]
    altitudes = np.array([q.altitude_m for q in pool])
    sigma = max(fraction * float(np.median([q.height_m for q in pool])),
                float(np.std(altitudes)), max(q.altitude_sigma_m for q in pool))
    return float(np.median(per_strip)), sigma, tuple(ids)


def _strip_names(ids: Sequence[int]) -> str:
    words = [str(i) for i in ids]
    return ("strip " if len(words) == 1 else "strips ") + (
        words[0] if len(words) == 1 else ", ".join(words[:-1]) + " and " + words[-1])


def _level_fallback(seg: _SegmentFit, good: list[SegmentQuality], options: dict[str, Any],
                    *, need: int, min_rays: int, max_sigma_m: float, altitude_fraction: float,
                    max_weak_fraction: float) -> None:
    """Refit a segment the rays alone rebuild poorly (``need``: the rays their fit needs)
    as level flight, its height drawn also from the segments rebuilt well
    (:func:`estimate_trajectory`)."""
    why = _why_weak(seg.q, need)
    if len(seg.rays) < min_rays:
        seg.q.message = f"{why}; the level fallback needs {min_rays}" if len(seg.rays) else why
        return
    own = _SegmentFit(seg.rays, seg.first, seg.last, copy.copy(seg.q))
    _fit_into(own, options, level=True)
    own_ok = own.coef is not None and math.isfinite(own.q.altitude_sigma_m) \
        and not _implausible(own.q)
    own_alt, own_sigma = own.q.altitude_m, own.q.altitude_sigma_m
    prior = _altitude_prior(seg.q.strip_id, good, altitude_fraction)
    given: tuple[float, float] | None = None
    ids: tuple[int, ...] = ()
    if prior is None:
        chosen, how = own, f"level flight at the altitude of its own rays, {own_alt:.0f} +- " \
                           f"{own_sigma:.0f} m"
    else:
        altitude, sigma, ids = prior
        names = _strip_names(ids)
        agree = own_ok and abs(own_alt - altitude) <= 3.0 * math.hypot(own_sigma, sigma)
        if own_ok and own.q.fan_deg >= _MIN_FAN_DEG:
            # a wide fan fixes its own height: the other strips' only adds to it
            if agree:
                weight = 1.0 / own_sigma**2 + 1.0 / sigma**2
                given = ((own_alt / own_sigma**2 + altitude / sigma**2) / weight,
                         weight**-0.5)
                how = (f"level flight at the altitude of its own rays and of {names}, "
                       f"{given[0]:.0f} +- {given[1]:.0f} m")
            else:
                chosen, ids = own, ()
                how = (f"level flight at the altitude of its own rays, {own_alt:.0f} +- "
                       f"{own_sigma:.0f} m ({names} at {altitude:.0f} m: another altitude)")
        else:
            given = (altitude, sigma)
            how = f"level flight at the altitude of {names}, {altitude:.0f} +- {sigma:.0f} m"
            if own_ok and not agree:
                how += f" (its own rays, across a narrow fan: {own_alt:.0f} m)"
    if given is not None:
        chosen = _SegmentFit(seg.rays, seg.first, seg.last, copy.copy(seg.q))
        _fit_into(chosen, options, level=True, altitude=given)
    chosen.q.altitude_from = ids
    q = chosen.q
    if chosen.coef is None:
        seg.q.message = f"{why}; level fallback: {q.message}"
        return
    problems = _implausible(q)
    if not (q.sigma_m <= max_weak_fraction * q.height_m):
        problems.append(f"position sigma {q.sigma_m:.0f} m, over "
                        f"{max_weak_fraction:.0%} of the height")
    if problems:
        seg.q.message = f"{why}; level fallback: {'; '.join(problems)}"
        return
    q.level, q.weak, q.message, q.fallback = "WARN", q.sigma_m > max_sigma_m, why, how
    seg.q, seg.coef, seg.tc, seg.half = q, chosen.coef, chosen.tc, chosen.half


def _strip_outcome(strip_id: int, segments: list[SegmentQuality]) -> StripEstimate:
    """One line on a strip's trajectory (its segments as finally fitted)."""
    failed = [q for q in segments if q.level == "ERROR"]
    if failed:
        return StripEstimate(strip_id, False, math.nan, False,
                             f"strip {strip_id}: left out, no trajectory could be rebuilt "
                             f"({failed[0].message})")
    sigma = max(q.sigma_m for q in segments)
    n_rays = sum(q.n_rays for q in segments)
    fallback = [q for q in segments if q.fallback]
    if not fallback:
        return StripEstimate(strip_id, True, sigma, False,
                             f"strip {strip_id}: rebuilt from {n_rays} rays, position sigma "
                             f"{sigma:.1f} m")
    q = fallback[0]
    weak = "weak: " if any(f.weak for f in fallback) else ""
    part = "" if len(fallback) == len(segments) else \
        f" in {len(fallback)} of its {len(segments)} segments"
    horizontal = max(f.horizontal_sigma_m for f in segments)
    return StripEstimate(strip_id, True, sigma, True,
                         f"strip {strip_id}: position sigma {sigma:.1f} m ({horizontal:.1f} m "
                         f"horizontally; {weak}{q.message}); kept{part}, {q.fallback}")
