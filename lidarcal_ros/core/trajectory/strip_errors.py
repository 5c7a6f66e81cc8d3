"""Per-strip trajectory errors estimated with the biases (docs/method.md section 11).

The error of strip ``s`` is ``e_s(t) = sum_j b_j(t) c_s[j]`` (map frame, metres, delivered -
true; ``c_s[j]`` a 3-vector): ``offset`` has the basis ``[1]``, ``drift`` ``[1, t - t_s]``
(``t_s`` the strip's mid time, s), ``spline`` the cubic B-splines of uniform knots
``knot_interval_s`` apart over the strip (times beyond its ends clipped to them). A strip's
offset priors come from the trajectory's per-epoch position sigmas over its span where it
has them (:func:`strip_offset_sigmas`), else from the settings; with ``correlation_s`` the
strips' priors are tied across the flight (:func:`gauss_markov_prior`).
"""

from __future__ import annotations

import enum
import math
import warnings
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy import sparse
from scipy.interpolate import BSpline

from lidarcal_ros.core.mission import Trajectory


class TrajectoryModel(enum.Enum):
    """How each strip's trajectory error is parametrised (``calibration.trajectory.model``)."""

    #: ``spline`` where it fits the data clearly better than ``none``
    #: (:data:`AUTO_SIGMA0_RATIO`): both are calibrated and compared, batch and live alike.
    AUTO = "auto"
    NONE = "none"
    OFFSET = "offset"
    DRIFT = "drift"
    SPLINE = "spline"

    @property
    def estimated(self) -> bool:
        """The model has parameters (``auto`` has none until it has chosen)."""
        return self in (TrajectoryModel.OFFSET, TrajectoryModel.DRIFT, TrajectoryModel.SPLINE)


#: ``auto`` takes the trajectory errors where the adjustment without them leaves a sigma0 this
#: many times that with them: the strips disagree by more than their noise.
AUTO_SIGMA0_RATIO = 1.1
#: The interpolation of a spline strip's error, as the calibration file names it.
SPLINE_INTERPOLATION = ("cubic B-spline (scipy.interpolate.BSpline(knots, coefficients, 3)) "
                        "at t clipped to [knots[3], knots[-4]]")


@dataclass(frozen=True)
class TrajectoryErrorSettings:
    """The model and the navigation solution's accuracy (its priors); metres, seconds."""

    model: TrajectoryModel = TrajectoryModel.AUTO
    #: Sigma of a strip's offset (a spline coefficient's), horizontal and vertical, m.
    offset_sigma_horizontal_m: float = 0.05
    offset_sigma_vertical_m: float = 0.05
    #: Sigma of a strip's drift rate per axis, m/s (a spline: of the change from one
    #: coefficient to the next, per second of knot interval).
    drift_sigma_m_per_s: float = 0.002
    #: A-priori sigma of one correspondence, m: weighs the priors until the adjustment has
    #: its own sigma0.
    observation_sigma_m: float = 0.03
    #: Time between a spline's knots, s.
    knot_interval_s: float = 20.0
    #: How long the navigation solution's position error stays alike, s (a first-order
    #: Gauss-Markov process across the flight: :func:`gauss_markov_prior`); 0: each strip's
    #: error independent of the others'.
    correlation_s: float = 0.0

    @property
    def offset_sigmas(self) -> np.ndarray:
        """Sigma of an offset along map x, y, z, m."""
        h, v = self.offset_sigma_horizontal_m, self.offset_sigma_vertical_m
        return np.array([h, h, v])


#: The least offset sigma (m) a strip's prior takes from the trajectory's own sigmas: a file
#: too optimistic (a sigma of a millimetre) would make the strips rigid, their true errors
#: then pushed into the biases.
NAVIGATION_SIGMA_FLOOR_M = 0.005
#: Points whose spline error is evaluated at once (:meth:`StripBasis.error`).
_ERROR_BLOCK = 65_536


def strip_offset_sigmas(trajectory: Trajectory, t0: float, t1: float) -> np.ndarray | None:
    """The sigmas (m) of the offset of a strip flown from ``t0`` to ``t1`` (s) along map x,
    y, z from the trajectory's per-epoch position sigmas (docs/method.md section 11):
    horizontal ``sqrt(mean((s_E^2 + s_N^2) / 2))``, vertical ``sqrt(mean(s_U^2))`` over the
    samples in the span (the sigmas interpolated at its mid time where no sample falls in
    it), at least :data:`NAVIGATION_SIGMA_FLOOR_M`; NaN for a component no sample has; None
    where the trajectory carries no sigmas or none reaches the span."""
    sigma = trajectory.position_sigma
    if sigma is None or not len(trajectory):
        return None
    inside = (trajectory.t >= t0) & (trajectory.t <= t1)
    if inside.any():
        rows = sigma[inside]
    else:
        mid = 0.5 * (t0 + t1)
        rows = np.array([[np.interp(mid, trajectory.t, sigma[:, k]) for k in range(3)]])
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # (a component no sample has: NaN)
        h = math.sqrt(float(np.nanmean(0.5 * (rows[:, 0] ** 2 + rows[:, 1] ** 2))))
        v = math.sqrt(float(np.nanmean(rows[:, 2] ** 2)))
    if math.isnan(h) and math.isnan(v):
        return None
    return np.maximum(np.array([h, h, v]), NAVIGATION_SIGMA_FLOOR_M)  # (NaN stays NaN)


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
class StripBasis:
    """The basis of one strip's error: its reference time (s) and, for a spline, its knots."""

    model: TrajectoryModel
    t_ref: float
    knots: np.ndarray | None = None
    #: The strip's first and last time (s) where known (NaN: read from a file).
    span: tuple[float, float] = (math.nan, math.nan)
    #: Sigmas (m) of its offset along x, y, z from the navigation solution's own accuracy
    #: (:func:`strip_offset_sigmas`; NaN, or None, where it has none: the settings').
    navigation_sigmas: np.ndarray | None = None

    @classmethod
    def over(cls, model: TrajectoryModel, t0: float, t1: float, knot_interval_s: float, *,
             navigation_sigmas: np.ndarray | None = None) -> StripBasis:
        """The basis of a strip flown from ``t0`` to ``t1`` (s)."""
        knots = None
        if model is TrajectoryModel.SPLINE:
            spans = max(1, math.ceil((t1 - t0) / knot_interval_s - 1e-9))
            knots = t0 + knot_interval_s * np.arange(-3, spans + 4, dtype=np.float64)
        return cls(model, 0.5 * (t0 + t1), knots, (float(t0), float(t1)), navigation_sigmas)

    def offset_sigmas(self, settings: TrajectoryErrorSettings) -> np.ndarray:
        """Sigma (m) of its offset along x, y, z: the navigation solution's over the strip
        where known, else the settings'."""
        if self.navigation_sigmas is None:
            return settings.offset_sigmas
        return np.where(np.isfinite(self.navigation_sigmas), self.navigation_sigmas,
                        settings.offset_sigmas)

    @property
    def size(self) -> int:
        """Basis functions (each with a 3-vector coefficient)."""
        if self.knots is not None:
            return self.knots.shape[0] - 4
        return {TrajectoryModel.OFFSET: 1, TrajectoryModel.DRIFT: 2}.get(self.model, 0)

    def values(self, t: np.ndarray) -> np.ndarray:
        """Basis values ``(n, size)`` at absolute times ``t`` (s)."""
        t = np.asarray(t, dtype=np.float64).reshape(-1)
        if self.knots is not None:
            return self.sparse_values(t).toarray()
        out = np.ones((t.shape[0], self.size))
        if self.size > 1:
            out[:, 1] = t - self.t_ref
        return out

    def sparse_values(self, t: np.ndarray) -> sparse.csr_matrix:
        """:meth:`values` as a sparse matrix: a spline's row has four values, whatever its
        knots (dense, a long strip's row would cost 8 bytes a knot)."""
        t = np.asarray(t, dtype=np.float64).reshape(-1)
        if self.knots is None:
            return sparse.csr_matrix(self.values(t))
        inside = np.clip(t, self.knots[3], self.knots[-4])
        return BSpline.design_matrix(inside, self.knots, 3).tocsr()

    def error(self, coefficients: np.ndarray, t: np.ndarray) -> np.ndarray:
        """``e(t)`` (n, 3) of ``coefficients`` (size * 3,) at times ``t`` (s), map frame, m."""
        c = np.asarray(coefficients, dtype=np.float64).reshape(-1, 3)
        if self.knots is None:
            return self.values(t) @ c
        # (sparse: the dense values of every held point of a 30 km strip took gigabytes;
        # in blocks: a whole strip's sparse values and their making took some 150 bytes a
        # point at once. Each row is its own sum: the same bits either way.)
        t = np.asarray(t, dtype=np.float64).reshape(-1)
        out = np.empty((t.shape[0], 3))
        for start in range(0, t.shape[0], _ERROR_BLOCK):
            end = start + _ERROR_BLOCK
            out[start:end] = self.sparse_values(t[start:end]) @ c
        return out

    def prior(self, settings: TrajectoryErrorSettings) -> sparse.csr_matrix:
        """The priors' information (size * 3, size * 3) in units of 1/sigma^2: each
        offset-like coefficient observed as 0 with the offset sigmas, a drift with the drift
        sigma, and each spline coefficient's change from the one before with the drift sigma
        times the knot interval (a random walk)."""
        m = 3 * self.size
        offsets = np.tile(1.0 / self.offset_sigmas(settings) ** 2, self.size)
        if self.knots is None:
            if self.size > 1:
                offsets[3:] = 1.0 / settings.drift_sigma_m_per_s ** 2
            return sparse.diags(offsets).tocsr()
        step = settings.drift_sigma_m_per_s * float(self.knots[1] - self.knots[0])
        diff = sparse.eye(m - 3, m, k=3) - sparse.eye(m - 3, m)
        return (sparse.diags(offsets) + diff.T @ diff / step ** 2).tocsr()


@dataclass
class TrajectoryState:
    """The current estimate of every strip's error, strips in the calibration's order: their
    bases and one vector of all their coefficients (``starts``: where each strip's begin)."""

    model: TrajectoryModel
    knot_interval_s: float = 20.0
    bases: list[StripBasis] = field(default_factory=list)
    params: np.ndarray = field(default_factory=lambda: np.zeros(0))
    starts: list[int] = field(default_factory=lambda: [0])

    @property
    def active(self) -> bool:
        """Errors are modelled at all (``auto`` models none until it has chosen)."""
        return self.model.estimated

    @property
    def t_ref(self) -> list[float]:
        """Each strip's reference (mid) time, s."""
        return [b.t_ref for b in self.bases]

    @property
    def spans(self) -> np.ndarray:
        """Each strip's first and last time (S, 2), s."""
        return np.array([b.span for b in self.bases]).reshape(-1, 2)

    def add_strip(self, t0: float, t1: float, *,
                  navigation_sigmas: np.ndarray | None = None) -> None:
        """A new strip flown from ``t0`` to ``t1`` (s), its error zero; its offset priors
        ``navigation_sigmas`` (m, x y z) where the trajectory gives them."""
        basis = StripBasis.over(self.model, t0, t1, self.knot_interval_s,
                                navigation_sigmas=navigation_sigmas)
        self.bases.append(basis)
        self.starts.append(self.starts[-1] + 3 * basis.size)
        self.params = np.concatenate([self.params, np.zeros(3 * basis.size)])

    def strip_params(self, k: int) -> np.ndarray:
        """Strip ``k``'s coefficients (a view)."""
        return self.params[self.starts[k]:self.starts[k + 1]]

    def error(self, k: int, t: np.ndarray) -> np.ndarray:
        """``e_k(t)`` (n, 3), map frame, m, at times ``t`` (s) of strip ``k``."""
        return self.bases[k].error(self.strip_params(k), t)

    def projected(self, rows: TrajectoryRows) -> np.ndarray:
        """``n . (e_a(t_a) - e_b(t_b))`` of each row at the current estimate, m."""
        return error_columns(self, rows) @ self.params if len(rows) else np.empty(0)

    def prior(self, settings: TrajectoryErrorSettings) -> sparse.csr_matrix:
        """The priors' information of every coefficient (1/sigma^2): block diagonal, or
        with ``settings.correlation_s`` the flight-wide :func:`gauss_markov_prior`."""
        if not self.bases:
            return sparse.csr_matrix((0, 0))
        if settings.correlation_s > 0.0:
            return gauss_markov_prior(self, settings)
        return sparse.block_diag([b.prior(settings) for b in self.bases], format="csr")

    def prior_sigmas(self, settings: TrajectoryErrorSettings) -> np.ndarray:
        """A scale of each coefficient (m, m/s): the offsets' and drifts' prior sigmas."""
        out = []
        for b in self.bases:
            scale = np.tile(b.offset_sigmas(settings), b.size)
            if b.knots is None and b.size > 1:
                scale[3:] = settings.drift_sigma_m_per_s
            out.append(scale)
        return np.concatenate(out) if out else np.zeros(0)


#: The least share of a Gauss-Markov step's variance (``1 - phi^2``) a prior keeps: two
#: coefficients at the same time are then tied by a sigma a hundredth of the process's,
#: not by an infinite weight.
_GAUSS_MARKOV_FLOOR = 1e-4


def coefficient_times(basis: StripBasis) -> np.ndarray:
    """The time (s) each offset-like coefficient of ``basis`` stands for: a spline's
    Greville abscissae (the mean of the three knots after its first), else the strip's
    reference time (a drift's rate coefficients have none: NaN)."""
    if basis.knots is not None:
        k = basis.knots
        return (k[1:-3] + k[2:-2] + k[3:-1]) / 3.0
    out = np.full(basis.size, np.nan)
    out[:1] = basis.t_ref
    return out


def gauss_markov_prior(state: TrajectoryState,
                       settings: TrajectoryErrorSettings) -> sparse.csr_matrix:
    """The priors' information (1/sigma^2) of every strip's coefficients with the
    navigation error a first-order Gauss-Markov process across the flight (docs/method.md
    section 11): per axis, the offset-like coefficients sorted by their time
    (:func:`coefficient_times`), ``x_1 ~ N(0, s_1^2)`` and
    ``x_i+1 / s_i+1 = phi_i x_i / s_i + w_i``, ``phi_i = exp(-(t_i+1 - t_i) / correlation_s)``,
    ``var(w_i) = 1 - phi_i^2``; ``s`` each strip's offset sigma. Strips near in time are tied
    (the same INS error), far ones independent. A drift's rate keeps its own prior."""
    size = state.params.shape[0]
    times = np.repeat(np.concatenate([coefficient_times(b) for b in state.bases]), 3)
    sigmas = state.prior_sigmas(settings)  # (a rate's entry unused: not in a chain)
    axes = np.tile(np.arange(3), size // 3)
    rates = np.flatnonzero(~np.isfinite(times))
    parts = [sparse.csr_matrix((np.full(rates.size, settings.drift_sigma_m_per_s ** -2.0),
                                (rates, rates)), shape=(size, size))]
    for axis in range(3):
        chain = np.flatnonzero(np.isfinite(times) & (axes == axis))
        chain = chain[np.argsort(times[chain], kind="stable")]
        if not chain.size:
            continue
        inverse = 1.0 / sigmas[chain]
        phi = np.exp(-np.diff(times[chain]) / settings.correlation_s)
        scale = 1.0 / np.sqrt(np.maximum(1.0 - phi ** 2, _GAUSS_MARKOV_FLOOR))
        # the rows of a square root: x_1 / s_1, then each step's innovation over its sigma
        steps = np.arange(1, chain.size)
        root = sparse.csr_matrix((
            np.concatenate([inverse[:1], scale * inverse[1:], -scale * phi * inverse[:-1]]),
            (np.concatenate([[0], steps, steps]),
             np.concatenate([chain[:1], chain[1:], chain[:-1]]))), shape=(chain.size, size))
        parts.append(root.T @ root)
    return sum(parts[1:], parts[0]).tocsr()


def error_columns(state: TrajectoryState, rows: TrajectoryRows) -> sparse.csr_matrix:
    """The trajectory columns of the correspondences (k, all coefficients), sparse CSR: a
    point of strip ``a`` adds ``+n b(t_a)``, the patch of strip ``b`` ``-n b(t_b)``.

    Built in place, row by row in column order (each strip's coefficients one range, in
    strip order: the lower strip's side of a row first), from the basis values that are not
    zero: the dense values and their COO copies took some 0.5 GB at 300,000 rows, gigabytes
    on long strips."""
    k = len(rows)
    shape = (k, state.params.shape[0])
    sides = ((rows.strip_a, rows.t_a, 1.0), (rows.strip_b, rows.t_b, -1.0))
    groups = []
    counts = [np.zeros(k, np.int64), np.zeros(k, np.int64)]
    for side, (strips, times, sign) in enumerate(sides):
        for s in np.unique(strips[strips >= 0]):
            r = np.flatnonzero(strips == s)
            b = state.bases[int(s)].sparse_values(times[r])
            b.sort_indices()
            counts[side][r] = 3 * np.diff(b.indptr)
            groups.append((side, r, b, int(s), sign))
    if not groups:
        return sparse.csr_matrix(shape)
    total = counts[0] + counts[1]
    index = np.int32 if max(int(total.sum()), shape[1]) < 2**31 else np.int64
    indptr = np.zeros(k + 1, index)
    np.cumsum(total, out=indptr[1:])
    data = np.empty(int(indptr[-1]))
    indices = np.empty(int(indptr[-1]), index)
    # where each side's entries begin in its row: after the other side's if that strip is lower
    a_first = rows.strip_a < rows.strip_b
    begin = [indptr[:-1] + np.where(a_first, 0, counts[1]),
             indptr[:-1] + np.where(a_first, counts[0], 0)]
    xyz = np.arange(3)
    for side, r, b, s, sign in groups:
        row = np.repeat(np.arange(r.size), np.diff(b.indptr))
        at = begin[side][r[row]] + 3 * (np.arange(b.nnz) - b.indptr[row])
        pos = at[:, None] + xyz
        data[pos] = sign * b.data[:, None] * rows.normal[r[row]]
        indices[pos] = state.starts[s] + 3 * b.indices[:, None] + xyz
    out = sparse.csr_matrix((data, indices, indptr), shape=shape)
    if np.any((rows.strip_a >= 0) & (rows.strip_a == rows.strip_b)):
        out.sum_duplicates()  # a strip against itself: both sides in the same columns
    return out


@dataclass
class StripError:
    """One strip's estimated error (the calibration file's ``trajectory.strips``): its
    basis, coefficients (size, 3) and their sigmas; ``offset`` and ``drift`` (m, m/s) are
    the offset and drift models' coefficients, a spline's value at ``t_ref`` and no drift."""

    strip_id: int
    basis: StripBasis
    coefficients: np.ndarray
    sigma: np.ndarray

    @classmethod
    def linear(cls, strip_id: int, t_ref: float, offset: np.ndarray,
               offset_sigma: np.ndarray, drift: np.ndarray | None = None,
               drift_sigma: np.ndarray | None = None) -> StripError:
        """An offset (m) about ``t_ref`` (s), with a drift (m/s) where given; sigmas alike
        (NaN where not known)."""
        rows = [np.asarray(offset, dtype=np.float64)]
        sigmas = [np.asarray(offset_sigma, dtype=np.float64)]
        if drift is not None:
            rows.append(np.asarray(drift, dtype=np.float64))
            sigmas.append(np.full(3, np.nan) if drift_sigma is None
                          else np.asarray(drift_sigma, dtype=np.float64))
        model = TrajectoryModel.DRIFT if drift is not None else TrajectoryModel.OFFSET
        return cls(int(strip_id), StripBasis(model, float(t_ref)), np.vstack(rows),
                   np.vstack(sigmas))

    @property
    def t_ref(self) -> float:
        """The reference time of the strip's basis, s."""
        return self.basis.t_ref

    @property
    def offset(self) -> np.ndarray:
        """The error at ``t_ref``, m."""
        return self.error(np.array([self.t_ref]))[0]

    @property
    def offset_sigma(self) -> np.ndarray:
        """Its sigma (a spline's from the coefficients' sigmas alone), m."""
        b = self.basis.values(np.array([self.t_ref]))[0]
        return np.sqrt((b[:, None] ** 2 * self.sigma ** 2).sum(axis=0))

    @property
    def drift(self) -> np.ndarray | None:
        """The drift rate (m/s) of the drift model, else None."""
        return self.coefficients[1] if self.basis.model is TrajectoryModel.DRIFT else None

    @property
    def drift_sigma(self) -> np.ndarray | None:
        """The sigma (m/s) of the drift rate of the drift model, else None."""
        return self.sigma[1] if self.basis.model is TrajectoryModel.DRIFT else None

    def error(self, t: np.ndarray) -> np.ndarray:
        """``e(t)`` (n, 3) at absolute times ``t`` (s), map frame, m."""
        return self.basis.error(self.coefficients.ravel(), t)

    def sigma_at(self, t: np.ndarray) -> np.ndarray:
        """Standard deviation of ``e(t)`` (n, 3) per axis at absolute times ``t`` (s), m:
        ``sqrt(sum_j b_j(t)^2 sigma_j^2)`` (the drift model's ``sqrt(offset_sigma^2 + (t -
        t_ref)^2 drift_sigma^2)``), the covariances of the coefficients left out (the file
        does not hold them; about ``t_ref``, the strip's mid time, they are small). NaN where
        a sigma is not known."""
        b = self.basis.values(t)
        return np.sqrt(b ** 2 @ self.sigma ** 2)


@dataclass
class TrajectoryEstimate:
    """Every strip's estimated error, by strip id, and the model."""

    model: TrajectoryModel
    strips: dict[int, StripError]

    @classmethod
    def from_state(cls, state: TrajectoryState, strip_ids: Sequence[int],
                   sigma: np.ndarray) -> TrajectoryEstimate:
        """The estimate of ``state`` with standard deviations ``sigma`` (all coefficients)."""
        out = {}
        for k, sid in enumerate(strip_ids):
            part = slice(state.starts[k], state.starts[k + 1])
            out[int(sid)] = StripError(int(sid), state.bases[k],
                                       state.params[part].reshape(-1, 3).copy(),
                                       sigma[part].reshape(-1, 3).copy())
        return cls(state.model, out)

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
    ``X_o,delivered(t) - e_hat(t)`` is the corrected trajectory (docs/method.md section 11).

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
    at_start = np.vstack([estimate.errors(k, start[i:i + 1]) for i, k in enumerate(ids)])
    at_end = np.vstack([estimate.errors(k, end[i:i + 1]) for i, k in enumerate(ids)])
    finite = np.isfinite(t)
    inside = np.zeros(n, dtype=bool)
    for i, k in enumerate(ids):  # (in order of start: a later strip overrides an overlap)
        on = finite & (t >= start[i]) & (t <= end[i])
        if on.any():
            errors[on] = estimate.errors(k, t[on])
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
    "NAVIGATION_SIGMA_FLOOR_M",
    "POSE_BETWEEN_STRIPS",
    "POSE_BEYOND_STRIPS",
    "POSE_IN_STRIP",
    "SPLINE_INTERPOLATION",
    "StripBasis",
    "StripError",
    "TrajectoryCorrection",
    "TrajectoryErrorSettings",
    "TrajectoryEstimate",
    "TrajectoryModel",
    "TrajectoryRows",
    "TrajectoryState",
    "coefficient_times",
    "error_columns",
    "gauss_markov_prior",
    "strip_offset_sigmas",
    "trajectory_corrections",
]
