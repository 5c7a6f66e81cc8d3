"""Strips the live input delivered only in part: begun before the input, or with holes.

The two signs and their thresholds: docs/nodes.md, "How the calibrator works". Times in seconds,
the points' time base.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["HOLE_FRACTION", "JOIN_S", "MIN_HOLE_S", "StripCoverage"]

#: A strip whose first point came less than this after the first pose received (point time,
#: s) began before the input did.
JOIN_S = 1.0
#: A gap between two clouds of a strip longer than this fraction of its median cloud span is
#: a hole.
HOLE_FRACTION = 0.75
#: ... and longer than this (s): clouds of single points have no span to compare with.
MIN_HOLE_S = 0.01
_SPANS_KEPT = 64  # (the median of the latest clouds' spans follows a change of cadence)


@dataclass
class _Seen:
    """What arrived of one strip: its first and latest point time (s), the spans of its latest
    clouds (s) and the holes between them."""

    first_t: float
    last_t: float
    spans: list[float] = field(default_factory=list)
    holes: int = 0
    missing_s: float = 0.0
    first_hole_at_s: float = 0.0  # after the strip's first point


class StripCoverage:
    """Follows the clouds and poses received and names the strips seen in part (module
    docstring)."""

    def __init__(self) -> None:
        #: The earliest pose time received, s (inf: none yet).
        self.first_pose_t = float("inf")
        self._strips: dict[int, _Seen] = {}

    def add_poses(self, t: np.ndarray) -> None:
        """Trajectory samples received (times, s; non-finite ones ignored)."""
        t = np.asarray(t, dtype=float)
        t = t[np.isfinite(t)]
        if t.size:
            self.first_pose_t = min(self.first_pose_t, float(t.min()))

    def add_cloud(self, strip_id: int, t: np.ndarray) -> None:
        """The (finite) point times of one strip in one cloud received."""
        if not t.size:
            return
        t0, t1 = float(t.min()), float(t.max())
        seen = self._strips.get(strip_id)
        if seen is None:
            self._strips[strip_id] = _Seen(t0, t1, [t1 - t0])
            return
        gap = t0 - seen.last_t
        if len(seen.spans) >= 2 and gap > max(HOLE_FRACTION * float(np.median(seen.spans)),
                                              MIN_HOLE_S):
            if not seen.holes:
                seen.first_hole_at_s = seen.last_t - seen.first_t
            seen.holes += 1
            seen.missing_s += gap
        seen.spans = [*seen.spans[1 - _SPANS_KEPT:], t1 - t0]
        seen.last_t = max(seen.last_t, t1)

    def describe(self, strip_id: int) -> str:
        """What is missing of a strip, as one line ('' : nothing seen missing)."""
        seen = self._strips.get(strip_id)
        if seen is None:
            return ""
        parts = []
        lead = seen.first_t - self.first_pose_t  # (-inf before the first pose: not judged)
        if 0 <= lead < JOIN_S:
            parts.append(f"beginning missed: its first point came {lead:.2f} s after the "
                         "first pose received (the input began while it was flown)")
        elif -np.inf < lead < 0:
            parts.append(f"begun before the trajectory: its first point came {-lead:.2f} s "
                         "before the first pose received (points the trajectory does not "
                         "serve are left out)")
        if seen.holes:
            parts.append(f"{seen.missing_s:.2f} s of points missing in {seen.holes} gap(s) "
                         f"between its clouds, the first {seen.first_hole_at_s:.2f} s into it")
        return "; ".join(parts)

    @property
    def partial_strips(self) -> dict[int, str]:
        """The strips seen in part, with what is missing (:meth:`describe`)."""
        out = {sid: self.describe(sid) for sid in sorted(self._strips)}
        return {sid: text for sid, text in out.items() if text}
