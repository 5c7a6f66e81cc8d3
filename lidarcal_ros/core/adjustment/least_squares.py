"""The modified least-squares adjustment of docs/method.md section 6 and its observability analysis.

Normal equations accumulate by ``+`` (docs/internals.md, "The calibration"); a parameter that
cannot be estimated is held at its fixed value with the reason in words.
"""

from __future__ import annotations

import enum
import logging
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from lidarcal_ros.core.adjustment.ins_noise import PoseLoading
from lidarcal_ros.core.params import (
    N_PARAMETERS,
    PARAMETER_INDEX,
    PARAMETER_NAMES,
    as_vector,
    format_value,
)
from lidarcal_ros.core.trajectory.strip_errors import TrajectoryRows
from lidarcal_ros.errors import CalibrationError

logger = logging.getLogger(__name__)

#: A bias of this size is "typical": used to tell a column with no effect from a small one.
REFERENCE_MAGNITUDE = np.array([0.1, 0.1, 0.1, 1e-4, 1e-4, 1e-4, 0.1, 1e-4])

#: Default largest standard deviation for which a parameter counts as determined (SI units):
#: 2 cm for lengths, 5 arcsec for angles, 2e-5 for the scale: a few times the accuracy a
#: calibration is expected to reach (1 cm, 1 arcsec, 1e-5).
DEFAULT_MAX_SIGMA = {
    "dX": 0.02, "dY": 0.02, "dZ": 0.02,
    "domega": 2.5e-5, "dphi": 2.5e-5, "dkappa": 2.5e-5,
    "dr": 0.02, "dS": 2e-5,
}


@dataclass
class NormalEquations:
    """Accumulated normal equations over all eight parameters.

    Attributes
    ----------
    n : (8, 8) float64
        ``sum w a a^T``.
    u : (8,) float64
        ``sum w a y``.
    yy : float
        ``sum w y^2`` (for the residual sum of squares without storing observations).
    count : int
        Number of scalar observations (rank of ``P'``: one per correspondence).
    """

    n: np.ndarray = field(default_factory=lambda: np.zeros((N_PARAMETERS, N_PARAMETERS)))
    u: np.ndarray = field(default_factory=lambda: np.zeros(N_PARAMETERS))
    yy: float = 0.0
    count: int = 0

    def add(self, rows: np.ndarray, y: np.ndarray, weights: np.ndarray | None = None) -> None:
        """Add observations ``y = rows @ delta`` with weights (default 1); zero weights skip."""
        rows = np.asarray(rows, dtype=np.float64).reshape(-1, N_PARAMETERS)
        y = np.asarray(y, dtype=np.float64).ravel()
        w = np.ones_like(y) if weights is None else np.asarray(weights, dtype=np.float64)
        wr = rows * w[:, None]
        self.n += wr.T @ rows
        self.u += wr.T @ y
        self.yy += float(np.dot(w * y, y))
        self.count += int(np.count_nonzero(w))

    def __add__(self, other: NormalEquations) -> NormalEquations:
        return NormalEquations(
            self.n + other.n, self.u + other.u, self.yy + other.yy, self.count + other.count
        )

    def residual_square_sum(self, delta: np.ndarray) -> float:
        """``v^T P v`` for the full parameter vector ``delta``."""
        return float(self.yy - 2.0 * delta @ self.u + delta @ self.n @ delta)

    @classmethod
    def from_observations(cls, obs: Observations) -> NormalEquations:
        """The normal equations of ``obs`` (its rows, misclosures and weights)."""
        neq = cls()
        neq.add(obs.rows, obs.y, obs.weights)
        return neq


@dataclass
class Observations:
    """Scalar point-to-patch observations kept for robust re-weighting and QA.

    Attributes
    ----------
    rows : (k, 8) float64
        Design rows ``a``.
    y : (k,) float64
        Observed normal discrepancies ``n^T (X_A - X_B)`` in delivered coordinates, metres.
    weights : (k,) float64
        Current weights (robust zeros included).
    group : (k,) int64
        Index of the strip pair (>= 0) or ``-1 - control_index`` for control observations.
    cluster : (k,) int64
        Spatial cell of the observation: observations in one cell share errors (the same
        patches and points serve several strip pairs), see :func:`cluster_robust_sigma`.
    trajectory : TrajectoryRows, optional
        The trajectory terms of each row, where trajectory errors are estimated (docs/method.md
        section 11).
    pose_loading : PoseLoading, optional
        How each row's discrepancy moves with the INS's errors, where they are given
        (:mod:`~lidarcal_ros.core.adjustment.ins_noise`).
    """

    rows: np.ndarray
    y: np.ndarray
    weights: np.ndarray
    group: np.ndarray
    cluster: np.ndarray
    trajectory: TrajectoryRows | None = None
    pose_loading: PoseLoading | None = None

    @classmethod
    def empty(cls) -> Observations:
        """No observation at all (arrays of length 0)."""
        return cls(np.empty((0, N_PARAMETERS)), np.empty(0), np.empty(0),
                   np.empty(0, np.int64), np.empty(0, np.int64))

    @classmethod
    def concatenate(cls, parts: Iterable[Observations]) -> Observations:
        """The observations of ``parts`` one after the other (no part: :meth:`empty`); trajectory
        terms are kept if any part has them, the rows of the others get none."""
        parts = list(parts)
        if not parts:
            return cls.empty()
        trajectory = None
        if any(p.trajectory is not None for p in parts):
            # (rows kept without their trajectory terms get none: they observe no error)
            trajectory = TrajectoryRows.concatenate(
                p.trajectory if p.trajectory is not None else TrajectoryRows.none(len(p))
                for p in parts)
        loading = None
        if any(p.pose_loading is not None for p in parts):
            # (rows without a loading move with no INS error the calibration knows of)
            loading = PoseLoading.concatenate(
                p.pose_loading if p.pose_loading is not None else PoseLoading.none(len(p))
                for p in parts)
        return cls(
            np.concatenate([p.rows for p in parts]),
            np.concatenate([p.y for p in parts]),
            np.concatenate([p.weights for p in parts]),
            np.concatenate([p.group for p in parts]),
            np.concatenate([p.cluster for p in parts]),
            trajectory,
            loading,
        )

    def __len__(self) -> int:
        return int(self.y.shape[0])

    def residuals(self, delta: np.ndarray) -> np.ndarray:
        """``y - a . delta``: the normal discrepancy left after correcting by ``delta``."""
        return self.y - self.rows @ delta


class ParameterState(enum.StrEnum):
    """What the adjustment made of one parameter."""

    ESTIMATED = "estimated"
    #: Held at its given value: not asked for.
    FIXED = "fixed"
    #: Asked for, but the observations do not determine it (:attr:`ParameterStatus.reason`).
    NOT_ESTIMABLE = "not_estimable"


@dataclass
class ParameterStatus:
    """What the adjustment could say about one parameter: its ``state``, and for
    ``NOT_ESTIMABLE`` the ``reason`` in words."""

    state: ParameterState
    reason: str = ""


@dataclass
class Solution:
    """Result of one adjustment.

    Attributes
    ----------
    delta : (8,) float64
        Estimated values for estimated parameters, the fixed values otherwise (SI).
    sigma : (8,) float64
        Standard deviations (a-posteriori), NaN for parameters not estimated.
    estimated : tuple of str
        Names of estimated parameters, in :data:`PARAMETER_NAMES` order.
    covariance : (m, m) float64
        Covariance of the estimated parameters, ``sigma0^2 N^-1``.
    correlation : (m, m) float64
    sigma0 : float
        A-posteriori standard deviation of unit weight, metres.
    redundancy : int
        ``q - m``.
    status : dict of ParameterStatus
    """

    delta: np.ndarray
    sigma: np.ndarray
    estimated: tuple[str, ...]
    covariance: np.ndarray
    correlation: np.ndarray
    sigma0: float
    redundancy: int
    status: dict[str, ParameterStatus]
    warnings: list[str] = field(default_factory=list)

    def correlated_pairs(self, threshold: float = 0.5) -> list[tuple[str, str, float]]:
        """Pairs of estimated parameters with |correlation| above ``threshold``."""
        out = []
        m = len(self.estimated)
        for i in range(m):
            for j in range(i + 1, m):
                r = float(self.correlation[i, j])
                if abs(r) > threshold:
                    out.append((self.estimated[i], self.estimated[j], r))
        return sorted(out, key=lambda item: -abs(item[2]))


@dataclass
class ObservabilityLimits:
    """Thresholds of the observability analysis.

    Attributes
    ----------
    max_correlation : float
        Above this |correlation| two parameters are not separable.
    min_eigenvalue : float
        Smallest eigenvalue of the unit-diagonal normal matrix counted as non-singular.
    max_sigma : dict
        Largest standard deviation (SI) for which a parameter counts as determined.
    min_effect_m : float
        RMS effect (metres) of a typical bias below which a parameter is invisible.
    """

    max_correlation: float = 0.999
    min_eigenvalue: float = 1e-9
    max_sigma: Mapping[str, float] = field(default_factory=lambda: dict(DEFAULT_MAX_SIGMA))
    min_effect_m: float = 1e-6


def _names(indices: Iterable[int]) -> str:
    return ", ".join(PARAMETER_NAMES[i] for i in indices)


def solve(
    neq: NormalEquations,
    *,
    solve_for: Sequence[str],
    fixed: Mapping[str, float] | None = None,
    limits: ObservabilityLimits | None = None,
    sigma0_apriori: float | None = None,
) -> Solution:
    """Solve the normal equations for the parameters in ``solve_for``.

    Parameters not in ``solve_for`` are held at ``fixed`` (default 0). Parameters the data
    cannot determine are held at their fixed value too and reported as not estimable.

    Parameters
    ----------
    neq : NormalEquations
    solve_for : sequence of str
        Parameter names to estimate.
    fixed : mapping, optional
        Values (SI) of parameters held fixed, e.g. a surveyed ``dZ``.
    limits : ObservabilityLimits, optional
    sigma0_apriori : float, optional
        If given, use it instead of the a-posteriori sigma0 for the covariance (flight
        planning, where there are no residuals yet).

    Raises
    ------
    CalibrationError
        If there are no observations, or nothing is left to estimate.
    """
    limits = limits or ObservabilityLimits()
    if neq.count == 0:
        raise CalibrationError("no correspondences: nothing to adjust")
    unknown = [name for name in solve_for if name not in PARAMETER_INDEX]
    if unknown:
        raise CalibrationError(f"unknown parameter(s) to solve for: {', '.join(unknown)}")
    base = as_vector(dict(fixed or {}))
    status: dict[str, ParameterStatus] = {
        name: ParameterStatus(ParameterState.FIXED) for name in PARAMETER_NAMES
    }
    active = [PARAMETER_INDEX[name] for name in PARAMETER_NAMES if name in solve_for]
    if not active:
        raise CalibrationError("nothing to estimate: no parameter is to be solved for")

    def drop(indices: Iterable[int], reason: str) -> None:
        for i in indices:
            status[PARAMETER_NAMES[i]] = ParameterStatus(ParameterState.NOT_ESTIMABLE, reason)
            if i in active:
                active.remove(i)

    for i, reason in _without_effect(neq, active, limits):
        drop([i], reason)
    # Each pass drops what one check finds and starts again on the parameters left.
    for _ in range(2 * N_PARAMETERS):
        if not active:
            break
        idx = np.array(active)
        scaled = _ScaledSystem.of(neq, idx)
        found = _rank_deficiency(scaled, limits)
        if found is not None:
            drop(*found)
            continue
        found = _near_perfect_correlation(scaled, limits)
        if found is not None:
            drop(*found)
            continue
        fit = _estimate(neq, scaled, base, sigma0_apriori)
        weak = _too_weak(idx, fit.sigma, limits)
        if weak:
            for i, reason in weak:
                drop([i], reason)
            continue
        warnings = [f"{name} strongly correlated ({r:+.2f})"
                    for name, _, r in _pairs(idx, scaled.correlation, 0.9)]
        sigma = np.full(N_PARAMETERS, np.nan)
        sigma[idx] = fit.sigma
        for i in idx:
            status[PARAMETER_NAMES[i]] = ParameterStatus(ParameterState.ESTIMATED)
        return Solution(
            delta=fit.delta, sigma=sigma, estimated=tuple(PARAMETER_NAMES[i] for i in idx),
            covariance=fit.covariance, correlation=scaled.correlation, sigma0=fit.sigma0,
            redundancy=fit.redundancy, status=status, warnings=warnings,
        )
    reasons = "; ".join(f"{k}: {v.reason}" for k, v in status.items() if v.reason)
    raise CalibrationError(f"nothing left to estimate ({reasons})")


@dataclass(frozen=True)
class _ScaledSystem:
    """The normal matrix of the parameters ``idx``, scaled to a unit diagonal (``c``), its
    inverse and the correlations it implies."""

    idx: np.ndarray
    scale: np.ndarray  # 1 / sqrt(diag N)
    c: np.ndarray

    @classmethod
    def of(cls, neq: NormalEquations, idx: np.ndarray) -> _ScaledSystem:
        """The scaled system of ``neq`` over the parameters ``idx``."""
        n_sub = neq.n[np.ix_(idx, idx)]
        scale = 1.0 / np.sqrt(np.diag(n_sub))
        return cls(idx, scale, n_sub * scale[:, None] * scale[None, :])

    @cached_property
    def cinv(self) -> np.ndarray:
        """``c^-1``, taken once the rank is known to be full."""
        return np.linalg.inv(self.c)

    @cached_property
    def correlation(self) -> np.ndarray:
        """The parameters' correlation matrix."""
        d = np.sqrt(np.diag(self.cinv))
        return self.cinv / d[:, None] / d[None, :]


@dataclass(frozen=True)
class _Fit:
    """A solution of the scaled system: the estimate (SI, fixed parameters included), its
    sigma0, redundancy, covariance and sigmas of the parameters solved for."""

    delta: np.ndarray
    sigma0: float
    redundancy: int
    covariance: np.ndarray
    sigma: np.ndarray


def _without_effect(neq: NormalEquations, active: Sequence[int],
                    limits: ObservabilityLimits) -> list[tuple[int, str]]:
    """(a) The parameters with no effect at all on the observations, and why."""
    diag = np.diag(neq.n)
    effect = np.sqrt(np.maximum(diag, 0.0) / max(neq.count, 1)) * REFERENCE_MAGNITUDE
    return [(i, f"{PARAMETER_NAMES[i]} has no effect on the observations of this data "
                f"({_no_effect_hint(PARAMETER_NAMES[i])})")
            for i in active if effect[i] < limits.min_effect_m]


def _rank_deficiency(scaled: _ScaledSystem, limits: ObservabilityLimits
                     ) -> tuple[list[int], str] | None:
    """(b) A combination of parameters with (almost) no effect: those involved, and why."""
    eigval, eigvec = np.linalg.eigh(scaled.c)
    if eigval[0] >= limits.min_eigenvalue:
        return None
    involved = [int(scaled.idx[j]) for j in np.flatnonzero(np.abs(eigvec[:, 0]) > 0.25)]
    return involved, (f"{_names(involved)} cannot be told apart on this data: their effects "
                      "on the overlaps are the same (rank-deficient normal matrix)")


def _near_perfect_correlation(scaled: _ScaledSystem, limits: ObservabilityLimits
                              ) -> tuple[list[int], str] | None:
    """(c) The most correlated pair, where beyond ``max_correlation``, and why."""
    off = np.abs(scaled.correlation - np.eye(len(scaled.idx)))
    worst = np.unravel_index(np.argmax(off), off.shape)
    if off[worst] <= limits.max_correlation:
        return None
    pi, pj = int(scaled.idx[worst[0]]), int(scaled.idx[worst[1]])
    return [pi, pj], (f"{PARAMETER_NAMES[pi]} and {PARAMETER_NAMES[pj]} are correlated "
                      f"{float(off[worst]):.4f}: only their combination is determined"
                      f"{_correlation_hint(PARAMETER_NAMES[pi], PARAMETER_NAMES[pj])}")


def _estimate(neq: NormalEquations, scaled: _ScaledSystem, base: np.ndarray,
              sigma0_apriori: float | None) -> _Fit:
    """Solve with the fixed parameters (``base``) moved to the right-hand side.

    Raises
    ------
    CalibrationError
        No redundancy: as many parameters as correspondences, or more.
    """
    idx, scale, cinv = scaled.idx, scaled.scale, scaled.cinv
    rhs = neq.u[idx] - neq.n[np.ix_(idx, np.arange(N_PARAMETERS))] @ _zero_at(base, idx)
    delta = base.copy()
    delta[idx] = scale * (cinv @ (scale * rhs))
    q = neq.count
    redundancy = q - len(idx)
    if redundancy <= 0:
        k = len(idx)
        raise CalibrationError(
            f"{q} correspondence{'' if q == 1 else 's'} for {k} "
            f"parameter{'' if k == 1 else 's'}: too few to estimate "
            f"{'it' if k == 1 else 'them'} with any check (redundancy {redundancy})"
        )
    vtpv = max(neq.residual_square_sum(delta), 0.0)
    sigma0 = float(np.sqrt(vtpv / redundancy))
    s0 = sigma0_apriori if sigma0_apriori is not None else sigma0
    cov = (s0**2) * cinv * scale[:, None] * scale[None, :]
    return _Fit(delta, sigma0, redundancy, cov, np.sqrt(np.diag(cov)))


def _too_weak(idx: np.ndarray, sigma: np.ndarray,
              limits: ObservabilityLimits) -> list[tuple[int, str]]:
    """(d) The parameters determined too weakly to be of use, and why (their sigma against
    its limit, as people read them, and what would determine them)."""
    out = []
    for j in range(len(idx)):
        name = PARAMETER_NAMES[idx[j]]
        limit = limits.max_sigma.get(name, np.inf)
        if sigma[j] > limit:
            out.append((int(idx[j]), "the data flown determines it too weakly to be useful "
                        f"(sigma {format_value(name, sigma[j], sign=False)} above "
                        f"{format_value(name, limit, sign=False)}; {_weak_hint(name)})"))
    return out


def _zero_at(vector: np.ndarray, idx: np.ndarray) -> np.ndarray:
    out = vector.copy()
    out[idx] = 0.0
    return out


def _pairs(idx: np.ndarray, corr: np.ndarray, threshold: float) -> list[tuple[str, str, float]]:
    out = []
    for i in range(len(idx)):
        for j in range(i + 1, len(idx)):
            if abs(corr[i, j]) > threshold:
                out.append((f"{PARAMETER_NAMES[idx[i]]}/{PARAMETER_NAMES[idx[j]]}",
                            PARAMETER_NAMES[idx[j]], float(corr[i, j])))
    return out


def _no_effect_hint(name: str) -> str:
    if name == "dZ":
        return "strips alone cannot see dZ: it cancels between strips; add vertical control"
    if name == "dkappa":
        return ("dkappa cancels on lines flown along one track and on flat ground: it needs "
                "same-direction lines with an offset, or crossing lines, over sloped surfaces")
    if name in ("dX", "dY", "domega"):
        return "horizontal effects need sloped surfaces in the overlaps"
    return "no correspondence is sensitive to it"


def _correlation_hint(a: str, b: str) -> str:
    pair = {a, b}
    if pair == {"dZ", "dr"}:
        return "; fix dZ to its surveyed value and solve dr"
    if pair == {"dkappa", "dS"}:
        return "; opposite parallel lines show both alike: add a same-direction or crossing line"
    if pair == {"domega", "dY"}:
        return "; fly two heights or add sloped features"
    return ""


def _weak_hint(name: str) -> str:
    if name == "dkappa":
        return "dkappa needs lines flown in the same direction with an offset, or crossing lines"
    if name in ("dY", "domega"):
        return (f"{name} needs sloped features of varied aspect in the overlaps and lines at "
                "two flying heights")
    if name in ("dX", "dphi"):
        return f"{name} needs opposite lines over sloped features"
    if name in ("dr", "dZ"):
        return f"{name} needs vertical control or lines at different heights"
    return "dS needs data spread across the swath"


def cluster_robust_sigma(sol: Solution, obs: Observations, step: np.ndarray) -> np.ndarray:
    """Standard deviations that allow for errors shared within spatial clusters.

    Every overlapping strip pair is used, so the same points and patches (and their noise)
    enter several observations: the formal ``sigma0^2 N^-1`` then claims more independent
    information than the data hold. The cluster-robust ("sandwich") covariance
    ``N^-1 (sum_c s_c s_c^T) N^-1`` with ``s_c = sum_{i in c} w_i a_i v_i`` over spatial
    clusters ``c`` does not assume independence within a cluster.

    Parameters
    ----------
    sol : Solution
        The adjustment's result (``step`` solved from ``obs``).
    obs : Observations
    step : (8,) float64
        The increment the last solve found (residuals are ``y - a . step``).

    Returns
    -------
    (m,) float64
        Cluster-robust standard deviations of ``sol.estimated`` (small-sample corrected).
    """
    idx = np.array([PARAMETER_INDEX[n] for n in sol.estimated])
    w = obs.weights
    used = w > 0
    a = obs.rows[used][:, idx]
    v = obs.residuals(step)[used]
    score = a * (w[used] * v)[:, None]
    _, inverse = np.unique(obs.cluster[used], return_inverse=True)
    n_clusters = int(inverse.max()) + 1 if inverse.size else 0
    if n_clusters <= len(idx) + 1:
        return np.full(len(idx), np.nan)
    s = np.zeros((n_clusters, len(idx)))
    np.add.at(s, inverse.ravel(), score)
    meat = s.T @ s
    n_mat = (a * w[used][:, None]).T @ a
    n_inv = np.linalg.inv(n_mat)
    cov = n_inv @ meat @ n_inv
    q = int(used.sum())
    factor = n_clusters / (n_clusters - 1) * (q - 1) / max(q - len(idx), 1)
    return np.sqrt(np.maximum(np.diag(cov) * factor, 0.0))


__all__ = [
    "DEFAULT_MAX_SIGMA",
    "REFERENCE_MAGNITUDE",
    "NormalEquations",
    "ObservabilityLimits",
    "Observations",
    "ParameterState",
    "ParameterStatus",
    "Solution",
    "cluster_robust_sigma",
    "solve",
]
