"""The biases' normal equations with every strip's trajectory parameters reduced out.

A sparse Schur complement over the strip blocks (docs/method.md section 11).
"""

from __future__ import annotations

import numpy as np
from scipy import sparse
from scipy.sparse import linalg as sparse_linalg

from lidarcal_ros.core.adjustment.least_squares import NormalEquations, Observations, Solution
from lidarcal_ros.core.params import PARAMETER_INDEX
from lidarcal_ros.core.trajectory.strip_errors import (
    TrajectoryErrorSettings,
    TrajectoryRows,
    TrajectoryState,
    error_columns,
)


class StripBlocks:
    """One linearised adjustment of the biases' increment and the trajectory parameters'.

    The correspondences ``y = a . d_delta + t . d_tau`` (``t``: the rows of
    :func:`~lidarcal_ros.core.trajectory.strip_errors.error_columns`) and the priors
    ``tau + d_tau = 0`` (weight ``(unit_sigma / prior sigma)^2``) give the normal equations;
    :attr:`reduced` holds those of ``d_delta`` alone, the trajectory parameters eliminated,
    which :func:`~lidarcal_ros.core.adjustment.least_squares.solve` analyses and solves as ever.

    Parameters
    ----------
    obs : Observations
        The correspondences at the current estimate, with their weights.
    rows : TrajectoryRows
        Their trajectory terms, row for row.
    state : TrajectoryState
        The current trajectory estimate (its parameters are the priors' ``tau``).
    settings : TrajectoryErrorSettings
    unit_sigma : float
        Sigma of a correspondence of weight 1, m.
    columns : scipy.sparse matrix, optional
        :func:`~lidarcal_ros.core.trajectory.strip_errors.error_columns` of ``rows``, where known.
    gram : scipy.sparse matrix, optional
        :func:`strip_gram` of ``columns`` with the observations' weights, where known.
    """

    def __init__(self, obs: Observations, rows: TrajectoryRows, state: TrajectoryState,
                 settings: TrajectoryErrorSettings, unit_sigma: float, *,
                 columns: sparse.csr_matrix | None = None,
                 gram: sparse.csr_matrix | None = None) -> None:
        w = obs.weights
        a = obs.rows
        # (``columns``: the rows' trajectory columns already built, for another weighting)
        self.t = error_columns(state, rows) if columns is None else columns
        tw = sparse.csr_matrix(self.t.multiply(w[:, None]))
        prior = state.prior(settings) * unit_sigma ** 2
        tau = state.params
        if gram is None:
            gram = strip_gram(self.t, w, rows, state.starts)
        n_tt = (gram + prior).tocsc()
        n_ts = np.asarray(tw.T @ a)  # (M, 8)
        u_t = tw.T @ obs.y - prior @ tau
        self._lu = sparse_linalg.splu(n_tt)
        self._x = self._lu.solve(n_ts) if n_ts.size else np.zeros_like(n_ts)
        self._z = self._lu.solve(u_t) if u_t.size else np.zeros_like(u_t)
        wa = a * w[:, None]
        self.reduced = NormalEquations(
            wa.T @ a - n_ts.T @ self._x, wa.T @ obs.y - n_ts.T @ self._z,
            float(np.dot(w * obs.y, obs.y) + tau @ (prior @ tau) - u_t @ self._z),
            int(np.count_nonzero(w)))
        self._starts = list(state.starts)

    def tau_step(self, delta_step: np.ndarray) -> np.ndarray:
        """The trajectory parameters' increment (all coefficients) given the biases'."""
        return self._z - self._x @ delta_step

    def residuals(self, obs: Observations, delta_step: np.ndarray,
                  tau_step: np.ndarray) -> np.ndarray:
        """``y - a . d_delta - t . d_tau`` of each correspondence, m."""
        return obs.residuals(delta_step) - self.t @ tau_step

    def reduced_rows(self, obs: Observations) -> np.ndarray:
        """The biases' design rows with the trajectory parameters partialled out
        (``a - t N_tt^-1 N_ts``): what the cluster-robust sigmas take."""
        return obs.rows - self.t @ self._x

    def tau_sigma(self, sol: Solution) -> np.ndarray:
        """Standard deviations of the trajectory parameters (all coefficients):
        ``sigma0^2 N_tt^-1 + X Cov(delta) X^T`` on the diagonal."""
        size = self._x.shape[0]
        diag = np.empty(size)
        for lo, hi in zip(self._starts[:-1], self._starts[1:], strict=True):
            if hi == lo:
                continue
            eye = np.zeros((size, hi - lo))  # one strip's columns of N_tt^-1 at a time
            eye[lo:hi] = np.eye(hi - lo)
            diag[lo:hi] = np.diag(self._lu.solve(eye)[lo:hi])
        var = sol.sigma0 ** 2 * diag
        if sol.estimated:
            idx = [PARAMETER_INDEX[n] for n in sol.estimated]
            xs = self._x[:, idx]
            var += np.einsum("ij,jk,ik->i", xs, sol.covariance, xs)
        return np.sqrt(np.maximum(var, 0.0))


def strip_gram(t: sparse.csr_matrix, w: np.ndarray, rows: TrajectoryRows,
          starts: list[int]) -> sparse.csr_matrix:
    """``t^T diag(w) t``, a block per pair of strips: each correspondence's columns are two
    strips' (one for a control point's), so the rows of one pair of strips form a dense block
    whose product BLAS makes (scipy's sparse product of the whole took seconds)."""
    size = t.shape[1]
    strips = len(starts) - 1
    used = np.flatnonzero(w != 0)
    if not used.size:
        return sparse.csr_matrix((size, size))
    # one integer per pair of strips (-1: none), sorted once
    key = (rows.strip_a[used] + 1) * (strips + 1) + rows.strip_b[used] + 1
    order = np.argsort(key, kind="stable")
    key = key[order]
    cut = np.flatnonzero(np.diff(key)) + 1
    out_i, out_j, out_v = [], [], []
    for lo, hi in zip(np.r_[0, cut], np.r_[cut, key.size], strict=True):
        a, b = divmod(int(key[lo]), strips + 1)
        a, b = a - 1, b - 1
        r = used[order[lo:hi]]
        cols = np.concatenate([np.arange(starts[k], starts[k + 1])
                               for k in sorted({int(a), int(b)}) if k >= 0])
        if not cols.size:
            continue
        dense = t[r][:, cols].toarray()
        block = (dense * w[r, None]).T @ dense
        out_i.append(np.repeat(cols, cols.size))
        out_j.append(np.tile(cols, cols.size))
        out_v.append(block.ravel())
    if not out_v:
        return sparse.csr_matrix((size, size))
    return sparse.csr_matrix((np.concatenate(out_v), (np.concatenate(out_i),
                                                      np.concatenate(out_j))),
                             shape=(size, size))


__all__ = ["StripBlocks", "strip_gram"]
