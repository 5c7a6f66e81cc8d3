"""The adjustment side of a calibration's match-and-solve iteration (docs/method.md sections 6-7).

The robust solve, the next matching threshold and the convergence judgement (docs/internals.md,
"The calibration").
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from lidarcal_ros.core.adjustment.ins_noise import InsNoise, ins_meat
from lidarcal_ros.core.adjustment.least_squares import (
    NormalEquations,
    ObservabilityLimits,
    Observations,
    Solution,
    cluster_robust_sigma,
    solve,
)
from lidarcal_ros.core.adjustment.strip_blocks import StripBlocks, strip_gram
from lidarcal_ros.core.params import N_PARAMETERS, PARAMETER_NAMES
from lidarcal_ros.core.trajectory.strip_errors import (
    TrajectoryErrorSettings,
    TrajectoryRows,
    TrajectoryState,
    error_columns,
)


@dataclass
class TrajectoryTerms:
    """The trajectory errors :func:`robust_solve` estimates with the biases (docs/method.md section
    11), and what it leaves of them: the blocks of its last solve and the parameters'
    increment (all coefficients)."""

    state: TrajectoryState
    settings: TrajectoryErrorSettings
    #: Sigma of a correspondence of weight 1, m (weighs the priors).
    unit_sigma: float
    blocks: StripBlocks | None = None
    step: np.ndarray | None = None


@dataclass
class Iteration:
    """One match-and-adjust iteration of :meth:`~lidarcal_ros.core.calibration.calibrate.Calibrator.
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
        The estimate is converged (:func:`judge_convergence`; ``outcome`` says how).
    history : list of (8,) float64
        The estimate after each iteration so far from the same start, this one's last.
    ended : bool
        No further iteration is wanted: converged, or more iterations cannot help
        (``outcome`` says why).
    outcome : str
        How the iteration stands, in words (:class:`Convergence`).
    noise : (8,) float64
        The re-matching noise of ``step`` (:func:`rematching_noise`, SI; NaN where not
        estimated or at the first iteration).
    trajectory : TrajectoryTerms, optional
        The trajectory errors solved for with the biases (docs/method.md section 11).
    """

    number: int
    solution: Solution
    observations: Observations
    step: np.ndarray
    converged: bool
    history: list[np.ndarray]
    ended: bool = False
    outcome: str = ""
    noise: np.ndarray = field(default_factory=lambda: np.full(N_PARAMETERS, np.nan))
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
    return Observations(obs.rows, y, obs.weights, obs.group, obs.cluster, rows,
                        obs.pose_loading)


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
    # the trajectory columns once: the robust weights change, the rows do not
    columns = error_columns(trajectory.state, obs.trajectory) \
        if trajectory is not None and obs.trajectory is not None else None
    base_gram = None
    for _ in range(6):
        if trajectory is None or obs.trajectory is None:
            sol = solve(NormalEquations.from_observations(obs), solve_for=solve_for,
                        fixed=fixed_step, limits=limits)
            v = obs.residuals(sol.delta)
        else:
            assert columns is not None
            starts = trajectory.state.starts
            if base_gram is None:
                base_gram = strip_gram(columns, base_w, obs.trajectory, starts)
            # the outliers' rows taken out of the Gram of all (they are few)
            out = np.where((base_w > 0) & (obs.weights == 0), base_w, 0.0)
            gram = base_gram - strip_gram(columns, out, obs.trajectory, starts) \
                if out.any() else base_gram
            blocks = StripBlocks(obs, obs.trajectory, trajectory.state, trajectory.settings,
                                 trajectory.unit_sigma, columns=columns, gram=gram)
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


@dataclass
class MatchedSet:
    """The strip-pair correspondences one adjustment kept (robust weight above zero), by
    pair: which sample point, matched to which patch, with its design row; what tells which
    correspondences changed from one matching to the next.

    Attributes
    ----------
    pairs : dict
        Pair index -> (positions in the pair's sample, patch indices, design rows scaled by
        the square root of their weights ``(k, 8)``), in sample order.
    """

    pairs: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]

    @classmethod
    def of(cls, obs: Observations, layout: list[tuple[int, int, np.ndarray]]) -> MatchedSet:
        """The set adjusted in ``obs`` (weights final), whose pairs' rows start at the
        offsets of ``layout``: (pair index, first row in ``obs``, the patch of every sample
        point, -1 where none matched)."""
        pairs = {}
        for index, start, triangles in layout:
            pos = np.flatnonzero(triangles >= 0)
            part = slice(start, start + pos.size)
            kept = obs.weights[part] > 0
            rows = obs.rows[part][kept] * np.sqrt(obs.weights[part][kept])[:, None]
            pairs[index] = (pos[kept], triangles[pos[kept]], rows)
        return cls(pairs)

    def changes(self, earlier: MatchedSet) -> tuple[int, np.ndarray]:
        """The correspondences that entered or left since ``earlier`` (a point matched to
        another patch does both), and the normal-equation matrix ``sum w a a^T`` (8 x 8) of
        their rows (those that left with their rows of ``earlier``)."""
        moved = [rows[_not_in(pos, tri, *earlier.pairs.get(index, _NONE)[:2])]
                 for index, (pos, tri, rows) in self.pairs.items()]
        moved += [rows[_not_in(pos, tri, *self.pairs.get(index, _NONE)[:2])]
                  for index, (pos, tri, rows) in earlier.pairs.items()]
        stacked = np.concatenate([np.empty((0, N_PARAMETERS)), *moved])
        return stacked.shape[0], stacked.T @ stacked


_NONE = (np.empty(0, np.int64), np.empty(0, np.int64), np.empty((0, N_PARAMETERS)))


def _not_in(pos: np.ndarray, tri: np.ndarray, other_pos: np.ndarray, other_tri: np.ndarray
            ) -> np.ndarray:
    """Which of the correspondences (sample position ``pos``, patch ``tri``) the other set
    lacks (both sorted by position, one patch per position)."""
    if not other_pos.size:
        return np.ones(pos.size, bool)
    at = np.minimum(np.searchsorted(other_pos, pos), other_pos.size - 1)
    return (other_pos[at] != pos) | (other_tri[at] != tri)


def rematching_noise(sol: Solution, changed_normal: np.ndarray) -> np.ndarray:
    """How far re-matching alone moves each estimated parameter (one standard deviation, SI;
    NaN where not estimated): the step between two adjustments whose correspondences differ by
    those of the normal-equation matrix ``changed_normal`` (8 x 8), each with a residual of
    ``sigma0``, is ``N^-1 (sum_in a v - sum_out a v)``, of covariance
    ``sigma0^2 N^-1 changed_normal N^-1 = C changed_normal C / sigma0^2``.
    """
    noise = np.full(N_PARAMETERS, np.nan)
    idx = [PARAMETER_NAMES.index(n) for n in sol.estimated]
    if not idx:
        return noise
    if not sol.sigma0 > 0:
        noise[idx] = 0.0
        return noise
    c = sol.covariance
    var = np.einsum("ij,jk,ki->i", c, changed_normal[np.ix_(idx, idx)], c) / sol.sigma0**2
    noise[idx] = np.sqrt(np.maximum(var, 0.0))
    return noise


#: A step within this many standard deviations of its re-matching noise is what the
#: correspondences that changed move the estimate by (:func:`judge_convergence`).
NOISE_Z = 3.0
#: The steps of an estimate settled within the re-matching noise are taken for convergence up
#: to this many sigmas; beyond, the matching leaves the estimate less determined than its
#: sigmas say, and the iteration ends not converged.
SETTLED_MAX_SIGMA = 1.0


@dataclass
class Convergence:
    """How an iteration stands (:func:`judge_convergence`).

    ``converged``: the estimate is converged; ``ended``: no further iteration is wanted
    (converged, or further ones cannot help); ``outcome``: which, and why, in words.
    """

    converged: bool
    ended: bool
    outcome: str


def judge_convergence(history: list[np.ndarray], steps: list[np.ndarray],
                      sigmas: list[np.ndarray], noises: list[np.ndarray], changed: list[int],
                      fraction: float) -> Convergence:
    """Whether the iterations so far (``history``: the estimate after each, SI; per
    iteration its ``steps``, its formal ``sigmas``, the re-matching ``noises`` of its step
    (:func:`rematching_noise`) and the correspondences ``changed`` since the one before) have
    converged.

    - every estimated parameter's last step below ``fraction`` of its sigma
      (:func:`has_converged`), or a :func:`matching_cycle`: converged;
    - from the third iteration on, the last two steps each within ``NOISE_Z`` re-matching
      noises, and the last no smaller than half the one two before (the steps stopped
      shrinking: re-matching alone moves the estimate that much, so further iterations only
      trade one matching for another): converged within the re-matching noise if no step
      of the two exceeds ``SETTLED_MAX_SIGMA`` sigma, else ended, not converged.
    """
    step, sigma = steps[-1], sigmas[-1]
    est = np.isfinite(sigma)
    ratio = _in_sigmas(step, sigma)
    worst = int(np.argmax(ratio))
    last = (f"its last step moved {PARAMETER_NAMES[worst]} by {ratio[worst]:.2g} sigma"
            if est.any() else "nothing estimated")
    if len(history) > 1 and np.all(np.abs(step[est]) <= fraction * sigma[est]):
        return Convergence(True, True, f"converged: every step below {fraction:g} sigma")
    if has_converged(history, step, sigma, fraction):
        return Convergence(True, True, f"converged: the estimate settled into a cycle of the "
                           f"matching ({last})")
    if len(steps) < 3 or not est.any():
        return Convergence(False, False, f"not converged: {last}")
    within = [np.all(np.abs(s[est]) <= NOISE_Z * n[est]) for s, n in
              zip(steps[-2:], noises[-2:], strict=True)]
    shrinking = ratio.max() <= 0.5 * _in_sigmas(steps[-3], sigmas[-3]).max()
    noise_ratio = _in_sigmas(noises[-1], sigma)
    noise_text = (f"{changed[-1]} correspondence{'' if changed[-1] == 1 else 's'} changed at "
                  f"the last matching, which moves {PARAMETER_NAMES[worst]} by "
                  f"{noise_ratio[worst]:.2g} sigma (one standard deviation)")
    if not all(within) or shrinking:
        if np.all(np.isfinite(noise_ratio[est])):
            return Convergence(False, False, f"not converged: {last}; {noise_text}")
        return Convergence(False, False, f"not converged: {last}")
    largest = max(_in_sigmas(s, g).max() for s, g in zip(steps[-2:], sigmas[-2:], strict=True))
    what = (f"the last two steps (up to {largest:.2g} sigma) stopped shrinking and are what "
            f"re-matching alone moves the estimate by: {noise_text}")
    if largest <= SETTLED_MAX_SIGMA:
        return Convergence(True, True, f"converged within the re-matching noise: {what}")
    return Convergence(False, True, f"not converged, and more iterations will not converge "
                       f"it: {what}; the matching determines the estimate to about "
                       f"{largest:.2g} sigma only")


def _in_sigmas(values: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """``|values| / sigma`` where ``sigma`` is finite, 0 elsewhere."""
    est = np.isfinite(sigma) & (sigma > 0)
    out = np.zeros(values.shape)
    out[est] = np.abs(values[est]) / sigma[est]
    return out


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


def allow_for_ins_noise(sol: Solution, obs: Observations, noise: InsNoise) -> None:
    """Widen the covariance of ``sol`` by what the INS's errors ``noise`` move the estimate
    by: ``N^-1 (sum_c sigma_c^2 M_c^T K_c M_c) N^-1`` over the correspondences ``obs`` it was
    solved from (their ``pose_loading``; :func:`ins_meat`). One sample's error moves
    every point of its footprint (tens of metres of a spinning scanner's swath) and the
    patches there of every strip flown over it: errors shared wider than the sandwich's
    cells (measured on the simulated payload with a tactical unit's white noise: the
    sandwich's sigmas 1.4-2.9 times narrower than the spread of 12 noise draws, these within
    0.7-1.3 of it). Only the sigmas grow, as :func:`allow_for_shared_errors`'s."""
    if obs.pose_loading is None or not noise.active or not sol.estimated:
        return
    idx = [PARAMETER_NAMES.index(n) for n in sol.estimated]
    a = obs.rows[:, idx]
    weighted = a * np.where(obs.weights > 0, obs.weights, 0.0)[:, None]
    try:
        n_inv = np.linalg.inv(weighted.T @ a)
    except np.linalg.LinAlgError:  # (the solve itself would have said so)
        return
    extra = n_inv @ ins_meat(weighted, obs.pose_loading, noise) @ n_inv
    sigma = np.sqrt(np.diag(sol.covariance) + np.maximum(np.diag(extra), 0.0))
    sol.sigma[idx] = sigma
    sol.covariance = sol.correlation * sigma[:, None] * sigma[None, :]


def allow_for_held_biases(sol: Solution, normal: np.ndarray,
                          held_sigma: Mapping[str, float]) -> None:
    """Widen the covariance of ``sol`` by what the biases held at values known only to
    ``held_sigma`` (1 sigma SI, by name; those estimated or of sigma 0 ignored) move the
    estimate by: ``S C_h S^T`` with ``S = -N_ee^-1 N_eh`` from ``normal`` (8, 8), the normal
    matrix ``sol`` was solved from (the held biases as "consider" parameters). E.g. a
    mounting's ``dZ``, held at a robot description's value without control, moves ``dX``
    through the attitude's changes: millimetres per centimetre it is off. Only the sigmas
    grow (the correlations stay the formal ones, the covariance positive semi-definite)."""
    names = [n for n, s in held_sigma.items() if s > 0 and n not in sol.estimated]
    if not names or not sol.estimated:
        return
    e = [PARAMETER_NAMES.index(n) for n in sol.estimated]
    h = [PARAMETER_NAMES.index(n) for n in names]
    try:
        sensitivity = -np.linalg.solve(normal[np.ix_(e, e)], normal[np.ix_(e, h)])
    except np.linalg.LinAlgError:  # (the solve itself would have said so)
        return
    c_h = np.diag([float(held_sigma[n]) ** 2 for n in names])
    # As allow_for_shared_errors: the sigmas grow, the correlations stay the data's (what
    # tells whether a bias can be told from another, e.g. timing_unseen's test)
    sigma = np.sqrt(np.diag(sol.covariance + sensitivity @ c_h @ sensitivity.T))
    sol.sigma[e] = sigma
    sol.covariance = sol.correlation * sigma[:, None] * sigma[None, :]


__all__ = [
    "CYCLE_FACTOR", "NOISE_Z", "SETTLED_MAX_SIGMA", "Convergence", "Iteration", "MatchedSet",
    "TrajectoryTerms", "allow_for_held_biases", "allow_for_ins_noise", "allow_for_shared_errors",
    "has_converged", "judge_convergence", "matching_cycle",
    "next_threshold", "reexpress_observations", "rematching_noise", "robust_solve",
]
