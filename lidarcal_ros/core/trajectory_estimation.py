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
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from lidarcal_ros.core.mission import Trajectory
from lidarcal_ros.errors import TrajectoryError

logger = logging.getLogger(__name__)


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
    """Keeps, per group and per ``bin_s`` seconds, the ``per_bin`` rays of largest separation.

    Memory grows with the mission's duration, not with its number of points.
    """

    def __init__(self, *, bin_s: float = 1.0, per_bin: int = 100) -> None:
        self.bin_s = float(bin_s)
        self.per_bin = int(per_bin)
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
            start = np.maximum.accumulate(np.where(new, np.arange(order.size), 0))
            rank = np.arange(order.size) - start
            rays = rays.take(np.sort(order[rank < self.per_bin]))
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
    sigma_m : float
        Largest a-posteriori standard deviation of a position coordinate over the segment, m.
    condition : float
        Condition number of the (column-scaled) normal matrix.
    height_m : float
        Sensor height above the median first return, metres.
    speed_mps : float
        Horizontal speed of the fitted path, m/s.
    level : ``"OK"``, ``"WARN"`` or ``"ERROR"``
    message : str
    """

    strip_id: int
    t_start: float
    t_end: float
    n_rays: int
    n_rejected: int = 0
    rms_m: float = math.nan
    sigma_m: float = math.nan
    condition: float = math.nan
    height_m: float = math.nan
    speed_mps: float = math.nan
    level: str = "ERROR"
    message: str = ""


@dataclass
class EstimatedTrajectory:
    """A rebuilt trajectory and its quality.

    Attributes
    ----------
    trajectory : Trajectory
        Samples of the usable segments, map frame, metres.
    segments : list of SegmentQuality
    failed_strips : list of int
        Strips none of whose segments could be rebuilt (no trajectory for them).
    """

    trajectory: Trajectory
    segments: list[SegmentQuality] = field(default_factory=list)
    failed_strips: list[int] = field(default_factory=list)


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
) -> tuple[np.ndarray, np.ndarray, SegmentQuality, float, float]:
    """Fit ``P(t)`` to the rays of one segment.

    Returns the coefficients ``(degree + 1, 3)``, their covariance ``(3(d+1), 3(d+1))``, the
    quality (level not set), and the centre and half-span of the normalised time.
    """
    tc = 0.5 * (t_start + t_end)
    half = max(0.5 * (t_end - t_start), 0.5)
    tau = (rays.t - tc) / half
    basis = _legendre(tau, degree)
    d = rays.direction
    proj = np.eye(3)[None, :, :] - d[:, :, None] * d[:, None, :]  # (n, 3, 3)
    ma = np.einsum("iab,ib->ia", proj, rays.anchor - rays.anchor.mean(axis=0))
    ref = rays.anchor.mean(axis=0)
    m = 3 * (degree + 1)
    use = np.ones(len(rays), dtype=bool)
    weights = rays.separation**2  # first pass: direction quality only
    coef = np.zeros((degree + 1, 3))
    normal = np.eye(m)
    dist = np.zeros(len(rays))
    for _ in range(iterations):
        w = weights * use
        normal = np.einsum("i,ik,il,iab->kalb", w, basis, basis, proj).reshape(m, m)
        rhs = np.einsum("i,ik,ia->ka", w, basis, ma).reshape(m)
        try:
            sol = np.linalg.solve(normal, rhs)
        except np.linalg.LinAlgError:
            raise TrajectoryError("singular ray geometry") from None
        coef = sol.reshape(degree + 1, 3)
        pos = basis @ coef  # relative to ref
        resid = np.einsum("iab,ib->ia", proj, pos - (rays.anchor - ref))
        dist = np.linalg.norm(resid, axis=1)
        rng = np.maximum(np.linalg.norm(pos - (rays.anchor - ref), axis=1), 1.0)
        weights = 1.0 / (point_sigma_m**2 * (1.0 + 2.0 * rng**2 / rays.separation**2))
        z = dist * np.sqrt(weights)
        scale = 1.4826 * float(np.median(z[use])) + 1e-12
        new_use = z <= robust_k * scale
        if new_use.sum() < m:
            break
        if np.array_equal(new_use, use):
            break
        use = new_use
    w = weights * use
    normal = np.einsum("i,ik,il,iab->kalb", w, basis, basis, proj).reshape(m, m)
    n_used = int(use.sum())
    redundancy = 2 * n_used - m
    sigma0_sq = float(np.sum(w * dist**2) / redundancy) if redundancy > 0 else math.nan
    try:
        cov = sigma0_sq * np.linalg.inv(normal)
    except np.linalg.LinAlgError:
        raise TrajectoryError("singular ray geometry") from None
    scale_n = np.sqrt(np.diag(normal))
    condition = float(np.linalg.cond(normal / np.outer(scale_n, scale_n)))
    # position covariance at the ends and the middle; keep the worst coordinate
    probe = _legendre(np.array([-1.0, 0.0, 1.0]), degree)
    sig = 0.0
    for b in probe:
        jac = np.kron(b, np.eye(3))  # (3, m) for coefficient order (k, a)
        sig = max(sig, float(np.sqrt(np.max(np.diag(jac @ cov @ jac.T)))))
    coef = coef.copy()
    coef[0] += ref
    vel = coef[1] / half if degree >= 1 else np.zeros(3)
    q = SegmentQuality(
        strip_id=int(rays.group[0]) if len(rays) else -1,
        t_start=float(t_start),
        t_end=float(t_end),
        n_rays=n_used,
        n_rejected=int(len(rays) - n_used),
        rms_m=float(np.sqrt(np.mean(dist[use] ** 2))) if n_used else math.nan,
        sigma_m=sig,
        condition=condition,
        height_m=float(coef[0, 2] - np.median(rays.anchor[use, 2])) if n_used else math.nan,
        speed_mps=float(np.hypot(vel[0], vel[1])),
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
) -> EstimatedTrajectory:
    """Rebuild the sensor path of each strip from its rays (module docstring).

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
        Fewest rays a segment needs.
    max_sigma_m : float, keyword-only
        A segment whose position sigma exceeds this is an ERROR (not used).

    Returns
    -------
    EstimatedTrajectory
        Strips without a usable segment are listed in ``failed_strips`` and get no samples.
    """
    if degree < 0 or degree > 5:
        raise TrajectoryError(f"trajectory estimate: degree {degree} outside 0..5")
    samples_t: list[np.ndarray] = []
    samples_xyz: list[np.ndarray] = []
    segments: list[SegmentQuality] = []
    failed: list[int] = []
    order = np.argsort(rays.group, kind="stable")
    g_sorted = rays.group[order]
    for sid, (t_first, t_last) in sorted(spans.items()):
        lo, hi = np.searchsorted(g_sorted, [sid, sid + 1])
        strip_rays = rays.take(order[lo:hi])
        edges = _segment_edges(strip_rays.t, t_first, t_last, segment_s, min_rays)
        usable = 0
        for k in range(len(edges) - 1):
            a, b = edges[k], edges[k + 1]
            last = k == len(edges) - 2
            inside = (strip_rays.t >= a) & ((strip_rays.t <= b) if last else (strip_rays.t < b))
            seg_rays = strip_rays.take(inside)
            need = max(min_rays, 3 * (degree + 1))
            if len(seg_rays) < need:
                segments.append(SegmentQuality(
                    sid, a, b, len(seg_rays),
                    message=f"{len(seg_rays)} multi-return pulses, need {need}"))
                continue
            try:
                coef, _, q, tc, half = _fit_segment(
                    seg_rays, a, b, degree=degree, point_sigma_m=point_sigma_m,
                    robust_k=robust_k)
            except TrajectoryError as exc:
                segments.append(SegmentQuality(sid, a, b, len(seg_rays), message=str(exc)))
                continue
            q.strip_id = sid
            _grade(q, max_sigma_m=max_sigma_m)
            segments.append(q)
            if q.level == "ERROR":
                continue
            usable += 1
            s0 = a - lead_s if k == 0 else a
            s1 = b + lead_s if last else b
            n = max(2, int(math.ceil((s1 - s0) * rate_hz)) + 1)
            ts = np.linspace(s0, s1, n)
            if not last:
                ts = ts[:-1]  # the next segment starts there
            samples_t.append(ts)
            samples_xyz.append(_legendre((ts - tc) / half, degree) @ coef)
        if not usable:
            failed.append(sid)
    if samples_t:
        traj = Trajectory.from_samples(np.concatenate(samples_t), np.concatenate(samples_xyz))
    else:
        traj = Trajectory(np.empty(0), np.empty((0, 3)))
    for q in segments:
        log = logger.warning if q.level != "OK" else logger.info
        log("trajectory estimate, strip %d %.1f-%.1f s: %s, %d rays, RMS %.2f m, sigma %.2f m, "
            "height %.0f m%s", q.strip_id, q.t_start, q.t_end, q.level, q.n_rays, q.rms_m,
            q.sigma_m, q.height_m, f" ({q.message})" if q.message else "")
    return EstimatedTrajectory(traj, segments, failed)


def _grade(q: SegmentQuality, *, max_sigma_m: float) -> None:
    problems = []
    if not (q.height_m > 0):
        problems.append(f"sensor not above the returns (height {q.height_m:.1f} m)")
    if not (q.speed_mps > 1.0):
        problems.append(f"horizontal speed {q.speed_mps:.2f} m/s: heading undefined")
    if not (q.sigma_m <= max_sigma_m):
        problems.append(f"position sigma {q.sigma_m:.1f} m > {max_sigma_m:g} m")
    if problems:
        q.level, q.message = "ERROR", "; ".join(problems)
    elif q.sigma_m > 1.0 or q.rms_m > 2.0 or q.condition > 1e8:
        q.level = "WARN"
        q.message = "weak ray geometry"
    else:
        q.level = "OK"
