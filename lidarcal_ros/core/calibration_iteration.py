"""The adjustment side of a calibration's match-and-solve iteration (method.md sections 6-7).

Each iteration of :meth:`~lidarcal_ros.core.calibrate.Calibrator.iterate` matches, then:
solves for the increment to the estimate with robust weights (:func:`robust_solve`), narrows
the matching threshold to the residuals (:func:`next_threshold`) and tests convergence
(:func:`has_converged`: every step below a fraction of its sigma, or the estimate settled into
a cycle of the discrete matching, :func:`matching_cycle`). Correspondences kept without
re-matching are re-expressed at each new estimate (:func:`reexpress_observations`); the last
solution's sigmas are widened for the errors the observations share
(:func:`allow_for_shared_errors`). :class:`Iteration` records one iteration.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from lidarcal_ros.core.adjustment import (
    NormalEquations,
    ObservabilityLimits,
    Observations,
    Solution,
    cluster_robust_sigma,
    solve,
)
from lidarcal_ros.core.params import PARAMETER_NAMES
from lidarcal_ros.core.strip_blocks import StripBlocks
from lidarcal_ros.core.trajectory_errors import (
    TrajectoryErrorSettings,
    TrajectoryRows,
    TrajectoryState,
)


@dataclass
class TrajectoryTerms:
    """The trajectory errors :func:`robust_solve` estimates with the biases (method.md section
    11), and what it leaves of them: the blocks of its last solve and the parameters'
    increment (S * per_strip,)."""

    state: TrajectoryState
    settings: TrajectoryErrorSettings
    #: Sigma of a correspondence of weight 1, m (weighs the priors).
    unit_sigma: float
    blocks: StripBlocks | None = None
    step: np.ndarray | None = None


@dataclass
class Iteration:
    """One match-and-adjust iteration of :meth:`~lidarcal_ros.core.calibrate.Calibrator.
    iterate`.

    Attributes
    ----------
    number : int
        1 for the first iteration from the estimate the calibrator held.
    solution : Solution
        The adjustment (formal sigmas); ``solution.delta`` is the new estimate (SI).
    observations : Observations
        The correspondences adjusted, with their robust weights.
    step : (8,) float64
        Change of the estimate in this iteration (SI).
    converged : bool
        From the second iteration on: no estimated parameter moved by more than
        ``convergence_fraction`` of its sigma.
    history : list of (8,) float64
        The estimate after each iteration so far from the same start, this one's last.
    trajectory : TrajectoryTerms, optional
        The trajectory errors solved for with the biases (method.md section 11).
    """

    number: int
    solution: Solution
    observations: Observations
    step: np.ndarray
    converged: bool
    history: list[np.ndarray]
    trajectory: TrajectoryTerms | None = None


def reexpress_observations(obs: Observations, matched_at: np.ndarray, delta: np.ndarray,
                           trajectory: TrajectoryState | None = None) -> Observations:
    """Observations matched at the estimate ``matched_at`` re-expressed at the estimate
    ``delta`` (8 biases, SI) and ``trajectory``: the discrepancy left after the correction
    ``delta`` is ``y - a . (delta - matched_at)`` (linear in between), less the change of the
    trajectory errors' projection since the match."""
    rows = obs.trajectory
    moved = rows is not None and trajectory is not None and trajectory.active and len(rows)
    if not len(obs) or (not np.any(delta - matched_at) and not moved):
        return obs
    y = obs.residuals(delta - matched_at)
    if moved:
        assert rows is not None and trajectory is not None
        now = trajectory.projected(rows)
        y = y - (now - rows.applied)
        rows = TrajectoryRows(rows.strip_a, rows.t_a, rows.strip_b, rows.t_b, rows.normal, now)
    return Observations(obs.rows, y, obs.weights, obs.group, obs.cluster, rows)


def robust_solve(
    obs: Observations, delta: np.ndarray, *, solve_for: tuple[str, ...],
    fixed: Mapping[str, float], limits: ObservabilityLimits, robust_k: float,
    trajectory: TrajectoryTerms | None = None,
) -> Solution:
    """Solve for the increment to the estimate ``delta``, zeroing the weights of strip-pair
    outliers (> ``robust_k`` robust sigmas) until they no longer change (``obs.weights`` is
    left at the final weights). With ``trajectory``, each strip's trajectory errors are
    solved for too (their increment left in ``trajectory.step``).

    Returns the solution with ``delta`` = current estimate + increment; the parameters not in
    ``solve_for`` are moved to their ``fixed`` values (0 where not given, SI).
    """
    fixed_step = {name: float(fixed.get(name, 0.0) - delta[i])
                  for i, name in enumerate(PARAMETER_NAMES)}
    base_w = obs.weights.copy()
    sol = None
    for _ in range(6):
        if trajectory is None or obs.trajectory is None:
            sol = solve(NormalEquations.from_observations(obs), solve_for=solve_for,
                        fixed=fixed_step, limits=limits)
            v = obs.residuals(sol.delta)
        else:
            blocks = StripBlocks(obs, obs.trajectory, trajectory.state, trajectory.settings,
                                 trajectory.unit_sigma)
            sol = solve(blocks.reduced, solve_for=solve_for, fixed=fixed_step, limits=limits)
            trajectory.blocks, trajectory.step = blocks, blocks.tau_step(sol.delta)
            v = blocks.residuals(obs, sol.delta, trajectory.step)
        # Robust weights for strip pairs only: control points are surveyed and few, and
        # before dZ and dr are estimated their discrepancies are legitimately large.
        pairs = (obs.group >= 0) & (base_w > 0)
        scale = 1.4826 * np.median(np.abs(v[pairs])) if pairs.any() else 1.0
        outlier = pairs & (np.abs(v) > robust_k * max(scale, 1e-6))
        new_w = np.where(outlier, 0.0, base_w)
        if np.array_equal(new_w > 0, obs.weights > 0):
            break
        obs.weights = new_w
    assert sol is not None
    sol.delta = sol.delta + delta
    return sol


def next_threshold(obs: Observations, residuals: np.ndarray, *, robust_k: float,
                   floor_m: float, current_m: float) -> float:
    """The matching threshold for the next iteration, metres: ``2 robust_k`` times the RMS
    of the strip-pair inliers' ``residuals`` after the iteration's step, between ``floor_m``
    and the ``current_m`` threshold (it only shrinks)."""
    inl = (obs.weights > 0) & (obs.group >= 0)
    scale = float(np.sqrt(np.mean(residuals[inl] ** 2))) if inl.any() else 0.0
    return float(np.clip(2.0 * robust_k * scale, floor_m, current_m))


def has_converged(history: list[np.ndarray], step: np.ndarray, sigma: np.ndarray,
                  fraction: float) -> bool:
    """From the second iteration on (``history``: the estimate after each iteration, the
    latest after ``step``): no estimated parameter (finite ``sigma``) moved by more than
    ``fraction`` of its sigma, or the iteration settled into a :func:`matching_cycle`."""
    est = np.isfinite(sigma)
    return len(history) > 1 and bool(
        np.all(np.abs(step[est]) <= fraction * sigma[est])
        or matching_cycle(history, sigma, est, fraction))


#: Largest step (in sigmas, times ``convergence_fraction``) of a cycle of the matching taken
#: for convergence: a correspondence entering and leaving the matched set at each iteration
#: moves the estimate back and forth by a few hundredths of its sigmas, for ever.
CYCLE_FACTOR = 10.0


def matching_cycle(history: list[np.ndarray], sigma: np.ndarray, est: np.ndarray,
                   fraction: float) -> bool:
    """The estimates of the last iterations repeat with a period of two or three (to 1e-6
    sigma), and their steps are below ``CYCLE_FACTOR * fraction`` sigma: the iteration has
    settled into a cycle of the discrete matching, not drifting."""
    if len(history) < 4:
        return False
    last = history[-1][est]
    width = sigma[est]
    for period in (2, 3):
        if len(history) > period and np.all(
                np.abs(last - history[-1 - period][est]) <= 1e-6 * width):
            spread = np.ptp(np.stack([h[est] for h in history[-period - 1:]]), axis=0)
            return bool(np.all(spread <= CYCLE_FACTOR * fraction * width))
    return False


def allow_for_shared_errors(sol: Solution, obs: Observations, step: np.ndarray) -> None:
    """Widen each sigma of ``sol`` to its cluster-robust value where that is larger.

    The formal covariance assumes independent observations, but the same patches and
    points serve several strip pairs. Correlations stay those of the formal covariance;
    only standard deviations grow (the covariance stays positive semi-definite).
    """
    robust = cluster_robust_sigma(sol, obs, step)
    idx = [PARAMETER_NAMES.index(n) for n in sol.estimated]
    formal = sol.sigma[idx]
    wider = np.where(np.isfinite(robust), np.maximum(formal, robust), formal)
    sol.sigma[idx] = wider
    sol.covariance = sol.correlation * wider[:, None] * wider[None, :]


__all__ = [
    "CYCLE_FACTOR", "Iteration", "TrajectoryTerms", "allow_for_shared_errors", "has_converged",
    "matching_cycle", "next_threshold", "reexpress_observations", "robust_solve",
]
