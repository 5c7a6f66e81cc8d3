"""One segment of a flight line rebuilt from its rays: the least-squares fit and its grade.

``P(t) = sum_k c_k L_k(tau)`` (Legendre polynomials of the segment's normalised time), map
frame, metres (docs/import.md, "Without a trajectory").
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np

from lidarcal_ros.core.trajectory.rays import Rays
from lidarcal_ros.errors import TrajectoryError

#: Iterations of the reweighting and outlier rejection of one fit.
_ITERATIONS = 6


@dataclass(frozen=True)
class EstimateSettings:
    """How a trajectory is rebuilt from rays
    (:func:`~lidarcal_ros.core.trajectory.estimation.estimate_trajectory`).

    Attributes
    ----------
    segment_s : float
        Longest segment fitted with one polynomial, seconds.
    degree : int
        Polynomial degree in time (1: straight line at constant speed), 0 to 5.
    rate_hz : float
        Rate of the trajectory samples written, Hz.
    lead_s : float
        Samples reach this far before a strip's first and after its last point, seconds.
    point_sigma_m : float
        Noise of a return across the ray, metres (weights only).
    robust_k : float
        Rays beyond ``robust_k`` robust standard deviations are rejected.
    min_rays : int
        Fewest rays a segment needs for a fit from its rays alone (at least three per
        coefficient: :attr:`rays_needed`).
    max_sigma_m : float
        Position sigma beyond which a segment's own fit is weak, metres.
    min_weak_rays : int
        Fewest rays the level fallback needs.
    altitude_fraction : float
        Standard deviation of the altitude lent by other segments, as a fraction of their
        height above the returns.
    max_weak_fraction : float
        Largest position sigma of a segment kept, as a fraction of its height.
    """

    segment_s: float = 30.0
    degree: int = 1
    rate_hz: float = 10.0
    lead_s: float = 1.0
    point_sigma_m: float = 0.05
    robust_k: float = 3.0
    min_rays: int = 30
    max_sigma_m: float = 5.0
    min_weak_rays: int = 10
    altitude_fraction: float = 0.05
    max_weak_fraction: float = 0.25

    @property
    def rays_needed(self) -> int:
        """Fewest rays a fit from the rays alone takes."""
        return max(self.min_rays, 3 * (self.degree + 1))


class SegmentModel(enum.StrEnum):
    """How a segment's sensor path was fitted (:attr:`SegmentQuality.model`)."""

    #: The polynomial fitted to the rays alone.
    RAYS = "rays"
    #: Level flight (one height), the fallback of a weak segment.
    LEVEL = "level"


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
    model : SegmentModel
        ``RAYS``: the polynomial fitted to the rays alone. ``LEVEL``: the fallback of a weak
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
    model: SegmentModel = SegmentModel.RAYS
    altitude_from: tuple[int, ...] = ()
    weak: bool = False
    level: str = "ERROR"
    message: str = ""
    fallback: str = ""


@dataclass
class SegmentFit:
    """One segment's rays and its fit as it stands.

    Attributes
    ----------
    rays : Rays
    first, last : bool
        The strip's first (last) segment: its samples start (end) ``lead_s`` beyond it.
    q : SegmentQuality
    coef : (degree + 1, 3) float64 or None
        Legendre coefficients of the sensor position, map frame, metres; None: not fitted.
    tc, half : float
        Centre and half-span of the segment's normalised time, seconds.
    """

    rays: Rays
    first: bool
    last: bool
    q: SegmentQuality
    coef: np.ndarray | None = None
    tc: float = 0.0
    half: float = 1.0

    def fit(self, settings: EstimateSettings, *, level: bool = False,
            altitude: tuple[float, float] | None = None) -> None:
        """Fit the segment (``level``, ``altitude``: :func:`fit_segment`), keeping the fit; a
        singular geometry leaves it unfitted with the reason as its message."""
        q0 = self.q
        try:
            coef, _, q, tc, half = fit_segment(self.rays, q0.t_start, q0.t_end, settings,
                                               level=level, altitude=altitude)
        except TrajectoryError as exc:
            q0.message = str(exc)
            return
        q.strip_id = q0.strip_id
        self.coef, self.q, self.tc, self.half = coef, q, tc, half

    def positions(self, t: np.ndarray) -> np.ndarray:
        """``(n, 3)`` sensor positions of the fit at times ``t`` (seconds), map frame, metres."""
        assert self.coef is not None
        return legendre((t - self.tc) / self.half, self.coef.shape[0] - 1) @ self.coef


def legendre(tau: np.ndarray, degree: int) -> np.ndarray:
    """``(n, degree + 1)`` Legendre polynomials of ``tau``."""
    out = np.empty((tau.shape[0], degree + 1))
    out[:, 0] = 1.0
    if degree >= 1:
        out[:, 1] = tau
    for k in range(2, degree + 1):
        out[:, k] = ((2 * k - 1) * tau * out[:, k - 1] - (k - 1) * out[:, k - 2]) / k
    return out


def fit_segment(
    rays: Rays,
    t_start: float,
    t_end: float,
    settings: EstimateSettings,
    *,
    level: bool = False,
    altitude: tuple[float, float] | None = None,
) -> tuple[np.ndarray, np.ndarray, SegmentQuality, float, float]:
    """Fit ``P(t)`` to the rays of one segment (``settings``: its degree, point noise and
    robust cut).

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
    degree, point_sigma_m, robust_k = settings.degree, settings.point_sigma_m, settings.robust_k
    tc = 0.5 * (t_start + t_end)
    half = max(0.5 * (t_end - t_start), 0.5)
    tau = (rays.t - tc) / half
    basis = legendre(tau, degree)
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

    for _ in range(_ITERATIONS):
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
    probe = legendre(np.array([-1.0, 0.0, 1.0]), degree)
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
        model=SegmentModel.LEVEL if level else SegmentModel.RAYS,
    )
    return coef, cov, q, tc, half


def segment_edges(t: np.ndarray, t_first: float, t_last: float, segment_s: float,
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


def grade(q: SegmentQuality, *, max_sigma_m: float) -> None:
    """Set the level and message of a segment fitted from its rays alone: ERROR where it is
    no aircraft's path or its position sigma exceeds ``max_sigma_m`` (metres), WARN where
    the ray geometry is weak, else OK."""
    problems = flight_problems(q)
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


def flight_problems(q: SegmentQuality) -> list[str]:
    """What makes a fitted path no aircraft's."""
    problems = []
    if not (q.height_m > 0):
        problems.append(f"sensor not above the returns (height {q.height_m:.1f} m)")
    if not (q.speed_mps > 1.0):
        problems.append(f"horizontal speed {q.speed_mps:.2f} m/s: heading undefined")
    return problems


__all__ = ["EstimateSettings", "SegmentFit", "SegmentModel", "SegmentQuality", "fit_segment",
           "flight_problems", "grade", "legendre", "segment_edges"]
