"""Per-strip trajectory errors estimated with the biases (method.md section 11).

The error of strip ``s`` is ``e_s(t) = sum_j b_j(t - t_s) p_s[j]`` (map frame, metres,
delivered - true): ``offset`` has the basis ``[1]``, ``drift`` ``[1, t - t_s]`` (``t_s`` the
strip's mid time, s), so a strip holds 3 or 6 parameters, axis by axis.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np


class TrajectoryModel(enum.Enum):
    """How each strip's trajectory error is parametrised (``calibration.trajectory.model``)."""

    #: ``drift`` where it fits the data clearly better than ``none``
    #: (:data:`AUTO_SIGMA0_RATIO`), decided by a batch calibration; ``none`` strip by strip.
    AUTO = "auto"
    NONE = "none"
    OFFSET = "offset"
    DRIFT = "drift"

    @property
    def basis_size(self) -> int:
        """Basis functions per axis: 0, 1 or 2 (``auto``: 0 until it has chosen)."""
        return {"auto": 0, "none": 0, "offset": 1, "drift": 2}[self.value]

    @property
    def per_strip(self) -> int:
        """Parameters per strip: three per basis function."""
        return 3 * self.basis_size


#: ``auto`` takes the trajectory errors where the adjustment without them leaves a sigma0 this
#: many times that with them: the strips disagree by more than their noise.
AUTO_SIGMA0_RATIO = 1.1


@dataclass(frozen=True)
class TrajectoryErrorSettings:
    """The model and the navigation solution's accuracy (its priors); metres, seconds."""

    model: TrajectoryModel = TrajectoryModel.AUTO
    #: Sigma of a strip's offset, horizontal and vertical, m.
    offset_sigma_horizontal_m: float = 0.05
    offset_sigma_vertical_m: float = 0.05
    #: Sigma of a strip's drift rate, per axis, m/s.
    drift_sigma_m_per_s: float = 0.002
    #: A-priori sigma of one correspondence, m: weighs the priors until the adjustment has
    #: its own sigma0.
    observation_sigma_m: float = 0.03

    def prior_sigmas(self) -> np.ndarray:
        """Sigma of each parameter of a strip, in parameter order (m, then m/s)."""
        offset = [self.offset_sigma_horizontal_m] * 2 + [self.offset_sigma_vertical_m]
        drift = [self.drift_sigma_m_per_s] * 3
        return np.array((offset + drift)[:self.model.per_strip])


def basis(model: TrajectoryModel, dt: np.ndarray) -> np.ndarray:
    """Basis values ``(n, basis_size)`` at times ``dt`` (s) from the strip's reference time."""
    dt = np.asarray(dt, dtype=np.float64).reshape(-1)
    out = np.empty((dt.shape[0], model.basis_size))
    if model.basis_size:
        out[:, 0] = 1.0
    if model.basis_size > 1:
        out[:, 1] = dt
    return out


@dataclass
class TrajectoryRows:
    """What a correspondence needs of the trajectory errors: the strips (indices, -1 for a
    control point's side) and times (s) of its point and its patch's foot, the patch's normal,
    and ``applied``, ``n . (e_a(t_a) - e_b(t_b))`` already removed when it was matched (m)."""

    strip_a: np.ndarray
    t_a: np.ndarray
    strip_b: np.ndarray
    t_b: np.ndarray
    normal: np.ndarray
    applied: np.ndarray

    @classmethod
    def none(cls, k: int) -> TrajectoryRows:
        """``k`` rows that observe no trajectory error (no strip on either side)."""
        no = np.full(k, -1, np.int64)
        return cls(no, np.zeros(k), no.copy(), np.zeros(k), np.zeros((k, 3)), np.zeros(k))

    @classmethod
    def concatenate(cls, parts: Iterable[TrajectoryRows]) -> TrajectoryRows:
        """The rows of ``parts`` one after another."""
        parts = list(parts)
        if not parts:
            return cls.none(0)
        return cls(*(np.concatenate([getattr(p, f) for p in parts])
                     for f in ("strip_a", "t_a", "strip_b", "t_b", "normal", "applied")))

    def __len__(self) -> int:
        return int(self.t_a.shape[0])


@dataclass
class TrajectoryState:
    """The current estimate of every strip's error: reference times ``t_ref`` (S,) s and
    parameters ``params`` (S, per_strip), strips in the calibration's order."""

    model: TrajectoryModel
    t_ref: list[float] = field(default_factory=list)
    params: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))

    def __post_init__(self) -> None:
        if self.params.shape != (len(self.t_ref), self.model.per_strip):
            self.params = np.zeros((len(self.t_ref), self.model.per_strip))

    @property
    def active(self) -> bool:
        """Errors are modelled at all (``auto`` models none until it has chosen)."""
        return self.model.per_strip > 0

    def add_strip(self, t_ref: float) -> None:
        """A new strip, its error zero about ``t_ref`` (s)."""
        self.t_ref.append(float(t_ref))
        self.params = np.vstack([self.params, np.zeros((1, self.model.per_strip))])

    def error(self, k: int, t: np.ndarray) -> np.ndarray:
        """``e_k(t)`` (n, 3), map frame, m, at times ``t`` (s) of strip ``k``."""
        return error_at(self.model, self.params[k], t - self.t_ref[k])

    def projected(self, rows: TrajectoryRows) -> np.ndarray:
        """``n . (e_a(t_a) - e_b(t_b))`` of each row at the current estimate, m."""
        return error_columns(self, rows) @ self.params.ravel() if len(rows) else np.empty(0)


def error_at(model: TrajectoryModel, params: np.ndarray, dt: np.ndarray) -> np.ndarray:
    """``e(t)`` (n, 3) of one strip's ``params`` at ``dt`` (s) from its reference time."""
    b = basis(model, dt)
    return b @ np.asarray(params, dtype=np.float64).reshape(model.basis_size, 3)


def error_columns(state: TrajectoryState, rows: TrajectoryRows):  # -> scipy.sparse matrix
    """The trajectory columns of the correspondences (k, S * per_strip), sparse CSR: a point
    of strip ``a`` adds ``+n b(t_a)``, the patch of strip ``b`` ``-n b(t_b)``."""
    from scipy import sparse

    model, m, nb = state.model, state.model.per_strip, state.model.basis_size
    k = len(rows)
    cols, vals, row_idx = [], [], []
    t_ref = np.asarray([*state.t_ref, 0.0])  # (index -1: no strip)
    for strips, times, sign in ((rows.strip_a, rows.t_a, 1.0), (rows.strip_b, rows.t_b, -1.0)):
        has = strips >= 0
        if not has.any():
            continue
        r = np.flatnonzero(has)
        b = basis(model, times[has] - t_ref[strips[has]])  # (h, nb)
        coef = sign * b[:, :, None] * rows.normal[has][:, None, :]  # (h, nb, 3)
        base = strips[has, None, None] * m + np.arange(nb)[None, :, None] * 3 + \
            np.arange(3)[None, None, :]
        row_idx.append(np.broadcast_to(r[:, None, None], coef.shape).ravel())
        cols.append(base.ravel())
        vals.append(coef.ravel())
    shape = (k, len(state.t_ref) * m)
    if not vals:
        return sparse.csr_matrix(shape)
    return sparse.csr_matrix((np.concatenate(vals), (np.concatenate(row_idx),
                                                     np.concatenate(cols))), shape=shape)


@dataclass
class StripError:
    """One strip's estimated error (the calibration file's ``trajectory.strips``)."""

    strip_id: int
    t_ref: float
    offset: np.ndarray
    offset_sigma: np.ndarray
    drift: np.ndarray | None = None
    drift_sigma: np.ndarray | None = None

    def error(self, t: np.ndarray) -> np.ndarray:
        """``e(t)`` (n, 3) at absolute times ``t`` (s), map frame, m."""
        t = np.asarray(t, dtype=np.float64).reshape(-1)
        out = np.broadcast_to(self.offset, (t.shape[0], 3)).copy()
        if self.drift is not None:
            out += (t - self.t_ref)[:, None] * self.drift[None, :]
        return out

    def sigma(self, t: np.ndarray) -> np.ndarray:
        """Standard deviation of ``e(t)`` (n, 3) per axis at absolute times ``t`` (s), m:
        ``sqrt(offset_sigma^2 + (t - t_ref)^2 drift_sigma^2)``, the covariance of offset and
        drift left out (the file does not hold it; about ``t_ref``, the strip's mid time,
        it is small). NaN where a sigma is not known."""
        t = np.asarray(t, dtype=np.float64).reshape(-1)
        var = np.broadcast_to(np.asarray(self.offset_sigma, dtype=np.float64) ** 2,
                              (t.shape[0], 3)).copy()
        if self.drift is not None:
            drift_sigma = (np.full(3, np.nan) if self.drift_sigma is None
                           else np.asarray(self.drift_sigma, dtype=np.float64))
            var += (t - self.t_ref)[:, None] ** 2 * drift_sigma[None, :] ** 2
        return np.sqrt(var)


@dataclass
class TrajectoryEstimate:
    """Every strip's estimated error, by strip id, and the model."""

    model: TrajectoryModel
    strips: dict[int, StripError]

    @classmethod
    def from_state(cls, state: TrajectoryState, strip_ids: Sequence[int],
                   sigma: np.ndarray) -> TrajectoryEstimate:
        """The estimate of ``state`` with standard deviations ``sigma`` (S, per_strip)."""
        out = {}
        for k, sid in enumerate(strip_ids):
            p, s = state.params[k], sigma[k]
            drift = state.model is TrajectoryModel.DRIFT
            out[int(sid)] = StripError(int(sid), state.t_ref[k], p[:3].copy(), s[:3].copy(),
                                       p[3:6].copy() if drift else None,
                                       s[3:6].copy() if drift else None)
        return cls(state.model, out)

    def error(self, strip_id: int, t: np.ndarray) -> np.ndarray:
        """``e_s(t)`` (n, 3) of strip ``strip_id`` (zero for a strip not estimated)."""
        se = self.strips.get(int(strip_id))
        if se is None:
            return np.zeros((np.asarray(t).reshape(-1).shape[0], 3))
        return se.error(t)

    def errors(self, strip_id: np.ndarray | int, t: np.ndarray) -> np.ndarray:
        """``e_s(t)`` (n, 3) of points of strips ``strip_id`` (one id, or one per point) at
        times ``t`` (s); zero for strips not estimated."""
        t = np.asarray(t, dtype=np.float64).reshape(-1)
        ids = np.broadcast_to(np.asarray(strip_id).reshape(-1), t.shape)
        out = np.zeros((t.shape[0], 3))
        for sid in np.unique(ids):
            se = self.strips.get(int(sid))
            if se is not None:
                on = ids == sid
                out[on] = se.error(t[on])
        return out

    def largest_offset_m(self) -> float:
        """The largest offset magnitude of any strip, m (NaN without strips)."""
        if not self.strips:
            return math.nan
        return max(float(np.linalg.norm(s.offset)) for s in self.strips.values())


#: Where a trajectory sample's correction comes from (:func:`trajectory_corrections`): its
#: strip's ``e_s(t)``; interpolated between the strips before and after it (a turn);
#: held at the nearest strip's end (before the first strip or after the last).
POSE_IN_STRIP, POSE_BETWEEN_STRIPS, POSE_BEYOND_STRIPS = 0, 1, 2


@dataclass
class TrajectoryCorrection:
    """The error removed from each trajectory sample: ``errors`` (n, 3) m, map frame
    (delivered - true), and ``source`` (n,) int8 (:data:`POSE_IN_STRIP`,
    :data:`POSE_BETWEEN_STRIPS`, :data:`POSE_BEYOND_STRIPS`)."""

    errors: np.ndarray
    source: np.ndarray

    def counts(self) -> tuple[int, int, int]:
        """Samples in a strip, between strips, beyond the first or last strip."""
        return tuple(int(np.count_nonzero(self.source == k))  # type: ignore[return-value]
                     for k in (POSE_IN_STRIP, POSE_BETWEEN_STRIPS, POSE_BEYOND_STRIPS))


def trajectory_corrections(estimate: TrajectoryEstimate, spans: dict[int, tuple[float, float]],
                           t: np.ndarray) -> TrajectoryCorrection:
    """The error ``e_hat(t)`` to remove from trajectory samples at times ``t`` (s), so that
    ``X_o,delivered(t) - e_hat(t)`` is the corrected trajectory (method.md section 11).

    Parameters
    ----------
    estimate : TrajectoryEstimate
    spans : dict of strip id -> (first, last) time, s
        When each strip was flown (its points' times). A strip of ``spans`` without an
        estimate has zero error, as its points were left (the corrected trajectory stays
        where the corrected points say the sensor was).
    t : (n,) float64
        Sample times, s.

    Notes
    -----
    During a strip (``first <= t <= last``; where spans overlap, the strip that started
    later): ``e_s(t)``. Between two strips (a turn: nothing observed it): linear in time from
    the earlier strip's error at its end to the later strip's at its start, so the corrected
    trajectory stays continuous. Before the first strip and after the last: the nearest
    strip's error at its end, held (a drift is not extrapolated). A non-finite time gets
    zero.
    """
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    n = t.shape[0]
    errors = np.zeros((n, 3))
    source = np.full(n, POSE_BEYOND_STRIPS, dtype=np.int8)
    usable = {int(k): (float(a), float(b)) for k, (a, b) in spans.items()
              if math.isfinite(a) and math.isfinite(b) and a <= b}
    if not usable or not n:
        return TrajectoryCorrection(errors, source)
    ids = sorted(usable, key=lambda k: (usable[k][0], k))
    start = np.array([usable[k][0] for k in ids])
    end = np.array([usable[k][1] for k in ids])
    at_start = np.vstack([estimate.error(k, start[i:i + 1]) for i, k in enumerate(ids)])
    at_end = np.vstack([estimate.error(k, end[i:i + 1]) for i, k in enumerate(ids)])
    finite = np.isfinite(t)
    inside = np.zeros(n, dtype=bool)
    for i, k in enumerate(ids):  # (in order of start: a later strip overrides an overlap)
        on = finite & (t >= start[i]) & (t <= end[i])
        if on.any():
            errors[on] = estimate.error(k, t[on])
            inside |= on
    source[inside] = POSE_IN_STRIP
    rest = finite & ~inside
    if rest.any():
        tr = t[rest]
        by_end = np.argsort(end, kind="stable")
        before = np.searchsorted(end[by_end], tr, side="left") - 1  # last strip ended before
        after = np.searchsorted(start, tr, side="right")  # first strip starting after
        has_before, has_after = before >= 0, after < len(ids)
        prev = by_end[np.clip(before, 0, None)]
        nxt = np.clip(after, None, len(ids) - 1)
        e_prev, e_next = at_end[prev], at_start[nxt]
        t0, t1 = end[prev], start[nxt]
        both = has_before & has_after
        with np.errstate(invalid="ignore", divide="ignore"):
            w = np.where(both & (t1 > t0), (tr - t0) / (t1 - t0), 0.0)
        e = np.where(has_before[:, None], e_prev, e_next)
        e = np.where(both[:, None], e_prev + w[:, None] * (e_next - e_prev), e)
        errors[rest] = e
        source[np.flatnonzero(rest)[both]] = POSE_BETWEEN_STRIPS
    return TrajectoryCorrection(errors, source)


__all__ = [
    "AUTO_SIGMA0_RATIO",
    "POSE_BETWEEN_STRIPS",
    "POSE_BEYOND_STRIPS",
    "POSE_IN_STRIP",
    "StripError",
    "TrajectoryCorrection",
    "TrajectoryErrorSettings",
    "TrajectoryEstimate",
    "TrajectoryModel",
    "TrajectoryRows",
    "TrajectoryState",
    "basis",
    "error_at",
    "error_columns",
    "trajectory_corrections",
]
