"""Rebuilding the flight path from multiple returns, where no trajectory was delivered.

Each strip is cut into segments, each fitted to its rays (:mod:`.segments`), the weak ones
flown level (:mod:`.fallback`). Map frame, metres, seconds. The model, its weights and what the
position found is: docs/import.md, "Without a trajectory".
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from lidarcal_ros.core.mission import Trajectory
from lidarcal_ros.core.trajectory.fallback import level_fallback
from lidarcal_ros.core.trajectory.rays import Rays
from lidarcal_ros.core.trajectory.segments import (
    EstimateSettings,
    SegmentFit,
    SegmentQuality,
    grade,
    segment_edges,
)
from lidarcal_ros.errors import TrajectoryError

logger = logging.getLogger(__name__)


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


def estimate_trajectory(
    rays: Rays,
    spans: dict[int, tuple[float, float]],
    settings: EstimateSettings | None = None,
) -> EstimatedTrajectory:
    """Rebuild the sensor path of each strip from its rays (docs/import.md, "Without a trajectory").

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
    settings : EstimateSettings, optional
        Segment length, polynomial degree, sampling, ray noise and the thresholds above
        (default: :class:`EstimateSettings`'s defaults).

    Returns
    -------
    EstimatedTrajectory
        Strips without a usable segment are listed in ``failed_strips`` and get no samples.
    """
    settings = settings or EstimateSettings()
    if settings.degree < 0 or settings.degree > 5:
        raise TrajectoryError(f"trajectory estimate: degree {settings.degree} outside 0..5")
    need = settings.rays_needed
    order = np.argsort(rays.group, kind="stable")
    g_sorted = rays.group[order]
    fits: dict[int, list[SegmentFit]] = {}
    for sid, (t_first, t_last) in sorted(spans.items()):
        lo, hi = np.searchsorted(g_sorted, [sid, sid + 1])
        strip_rays = rays.take(order[lo:hi])
        edges = segment_edges(strip_rays.t, t_first, t_last, settings.segment_s,
                              settings.min_rays)
        fits[sid] = []
        for k in range(len(edges) - 1):
            a, b = edges[k], edges[k + 1]
            last = k == len(edges) - 2
            inside = (strip_rays.t >= a) & ((strip_rays.t <= b) if last else (strip_rays.t < b))
            seg = SegmentFit(strip_rays.take(inside), k == 0, last,
                             SegmentQuality(sid, a, b, int(inside.sum())))
            fits[sid].append(seg)
            if len(seg.rays) < need:
                seg.q.message = f"{len(seg.rays)} multi-return pulses, need {need}"
                continue
            seg.fit(settings)
            if seg.coef is not None:
                grade(seg.q, max_sigma_m=settings.max_sigma_m)
    good = [f.q for strip in fits.values() for f in strip if f.q.level != "ERROR"]
    for strip in fits.values():
        for seg in strip:
            if seg.q.level == "ERROR":
                level_fallback(seg, good, settings)
    traj = _sampled([seg for strip in fits.values() for seg in strip], settings)
    segments = [f.q for strip in fits.values() for f in strip]
    for q in segments:
        log = logger.warning if q.level != "OK" else logger.info
        log("trajectory estimate, strip %d %.1f-%.1f s: %s, %d rays, RMS %.2f m, sigma %.2f m, "
            "height %.0f m%s", q.strip_id, q.t_start, q.t_end, q.level, q.n_rays, q.rms_m,
            q.sigma_m, q.height_m, f" ({q.message})" if q.message else "")
    outcomes = [_strip_outcome(sid, [f.q for f in strip]) for sid, strip in fits.items()]
    failed = [o.strip_id for o in outcomes if not o.kept]
    return EstimatedTrajectory(traj, segments, failed, outcomes)


def _sampled(fits: list[SegmentFit], settings: EstimateSettings) -> Trajectory:
    """Samples of the segments kept at ``settings.rate_hz``, a strip's first and last
    reaching ``settings.lead_s`` beyond its points."""
    samples_t: list[np.ndarray] = []
    samples_xyz: list[np.ndarray] = []
    for seg in fits:
        if seg.q.level == "ERROR" or seg.coef is None:
            continue
        a, b = seg.q.t_start, seg.q.t_end
        s0 = a - settings.lead_s if seg.first else a
        s1 = b + settings.lead_s if seg.last else b
        n = max(2, int(math.ceil((s1 - s0) * settings.rate_hz)) + 1)
        ts = np.linspace(s0, s1, n)
        if not seg.last:
            ts = ts[:-1]  # the next segment starts there
        samples_t.append(ts)
        samples_xyz.append(seg.positions(ts))
    if not samples_t:
        return Trajectory(np.empty(0), np.empty((0, 3)))
    return Trajectory.from_samples(np.concatenate(samples_t), np.concatenate(samples_xyz))


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


__all__ = ["EstimatedTrajectory", "StripEstimate", "estimate_trajectory"]
