"""The fallback for a segment its rays alone rebuild poorly: level flight at a lent altitude.

When it applies and why: docs/import.md, "Weak segments".
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence

import numpy as np

from lidarcal_ros.core.trajectory.segments import (
    EstimateSettings,
    SegmentFit,
    SegmentQuality,
    flight_problems,
)

#: Spread of rays across the track (deg) below which they fix the sensor's height poorly.
_MIN_FAN_DEG = 10.0


def _why_weak(q: SegmentQuality, need: int) -> str:
    """Why the rays alone rebuild a segment poorly, in words (from its first fit, ERROR;
    ``need``: the rays that fit needs)."""
    if q.n_rays == 0:
        return "no pulse with a first and a last return"
    if q.n_rays < need:
        return f"few multiple returns, {q.n_rays} rays"
    if not math.isfinite(q.sigma_m):  # not fitted: singular
        return q.message
    if flight_problems(q):
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
    other strip's (docs/import.md, "Weak segments"); None without any."""
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


def level_fallback(seg: SegmentFit, good: list[SegmentQuality], settings: EstimateSettings
                   ) -> None:
    """Refit a segment the rays alone rebuild poorly as level flight, its height drawn also
    from the segments rebuilt well (``good``), in place; left unfitted with the reason as
    its message where even that fails
    (:func:`~lidarcal_ros.core.trajectory.estimation.estimate_trajectory`)."""
    why = _why_weak(seg.q, settings.rays_needed)
    min_rays = settings.min_weak_rays
    if len(seg.rays) < min_rays:
        seg.q.message = f"{why}; the level fallback needs {min_rays}" if len(seg.rays) else why
        return
    own = SegmentFit(seg.rays, seg.first, seg.last, copy.copy(seg.q))
    own.fit(settings, level=True)
    own_ok = own.coef is not None and math.isfinite(own.q.altitude_sigma_m) \
        and not flight_problems(own.q)
    own_alt, own_sigma = own.q.altitude_m, own.q.altitude_sigma_m
    prior = _altitude_prior(seg.q.strip_id, good, settings.altitude_fraction)
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
        chosen = SegmentFit(seg.rays, seg.first, seg.last, copy.copy(seg.q))
        chosen.fit(settings, level=True, altitude=given)
    chosen.q.altitude_from = ids
    q = chosen.q
    if chosen.coef is None:
        seg.q.message = f"{why}; level fallback: {q.message}"
        return
    problems = flight_problems(q)
    if not (q.sigma_m <= settings.max_weak_fraction * q.height_m):
        problems.append(f"position sigma {q.sigma_m:.0f} m, over "
                        f"{settings.max_weak_fraction:.0%} of the height")
    if problems:
        seg.q.message = f"{why}; level fallback: {'; '.join(problems)}"
        return
    q.level, q.weak, q.message, q.fallback = "WARN", q.sigma_m > settings.max_sigma_m, why, how
    seg.q, seg.coef, seg.tc, seg.half = q, chosen.coef, chosen.tc, chosen.half


__all__ = ["level_fallback"]
