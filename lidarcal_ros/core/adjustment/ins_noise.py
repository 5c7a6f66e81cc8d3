"""What the INS's own errors do to the biases' estimate (docs/method.md section 12)."""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter

#: Columns of a correspondence's loading: the position error's (east, north, up; map frame,
#: per metre) and the attitude error's (about the body's right, forward, up axes, per radian).
N_COMPONENTS = 6
#: INS samples a correspondence's discrepancy moves with: two either side of its point's
#: time, two of each of its patch's three vertices.
N_SAMPLES = 8
#: Longest grid of INS samples the propagation filters (a longer mission is taken on a
#: coarser step: its errors change little over one where they are correlated over seconds).
MAX_GRID = 2_000_000


@dataclass(frozen=True)
class InsNoise:
    """The INS's errors, each axis a first-order Gauss-Markov process (1 sigma).

    position_sigma_m : (east, north, up), m.
    attitude_sigma_rad : about the body's right, forward and up axes (pitch, roll, heading),
        rad.
    correlation_s : how long the position's and the attitude's errors stay alike, s (about
        the sample spacing: white noise, each sample its own).
    step_s : the INS's sample spacing, s (its errors linear between samples); None until
        known (a calibration takes its trajectory's).
    """

    position_sigma_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    attitude_sigma_rad: tuple[float, float, float] = (0.0, 0.0, 0.0)
    correlation_s: tuple[float, float] = (30.0, 20.0)
    step_s: float | None = None

    @property
    def active(self) -> bool:
        """Whether any error is given (all zero: the INS taken as exact)."""
        return any(s > 0 for s in (*self.position_sigma_m, *self.attitude_sigma_rad))

    def sigmas(self) -> np.ndarray:
        """The six sigmas in the loading's column order (SI)."""
        return np.array([*self.position_sigma_m, *self.attitude_sigma_rad], dtype=np.float64)

    def correlations(self) -> np.ndarray:
        """Each column's correlation time, s."""
        return np.repeat(np.asarray(self.correlation_s, dtype=np.float64), 3)


@dataclass
class PoseLoading:
    """How each correspondence's discrepancy moves with the INS's errors.

    nodes : (k, 8) int64
        The INS samples (``floor(t / step_s)``) either side of the point's time (columns 0-1)
        and of each patch vertex's (2-7).
    coef : (k, 8, 6) float32
        d(discrepancy) / d(the error at that sample): per metre of position error (east,
        north, up), per radian of attitude error (about body right, forward, up). Zero: the
        correspondence moves with no INS error (a control point's side).
    """

    nodes: np.ndarray
    coef: np.ndarray

    @classmethod
    def none(cls, k: int) -> PoseLoading:
        """``k`` correspondences that move with no INS error."""
        return cls(np.zeros((k, N_SAMPLES), np.int64),
                   np.zeros((k, N_SAMPLES, N_COMPONENTS), np.float32))

    @classmethod
    def concatenate(cls, parts: Iterable[PoseLoading]) -> PoseLoading:
        """The loadings of ``parts`` one after the other."""
        parts = list(parts)
        return cls(np.concatenate([p.nodes for p in parts]),
                   np.concatenate([p.coef for p in parts]))

    @classmethod
    def of_sides(cls, point: tuple[np.ndarray, np.ndarray],
                 vertices: list[tuple[np.ndarray, np.ndarray]]) -> PoseLoading:
        """A point's side ``(nodes (k, 2), coef (k, 2, 6))`` (:func:`side_loading`) against
        its patch's vertices' (each the same, weighted by its barycentric weight and
        negated): the discrepancy is ``n . (X_A - X_B)``."""
        nodes = np.concatenate([point[0], *(v[0] for v in vertices)], axis=1)
        coef = np.concatenate([point[1], *(-v[1] for v in vertices)], axis=1)
        return cls(nodes, coef.astype(np.float32))


def side_loading(t: np.ndarray, normal: np.ndarray, lever_body: np.ndarray, step_s: float,
                 weight: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """One side's loading: points at times ``t`` (k,) s seen along ``normal`` (k, 3; map
    frame), ``lever_body`` (k, 3) = ``R^T ((X - X_o) x n)`` (body frame: an attitude error
    ``e`` moves ``n . X`` by ``e . lever_body``), optionally scaled by ``weight`` (k,).
    Returns the two INS samples either side (k, 2) and their coefficients (k, 2, 6)."""
    node = np.floor(t / step_s)
    frac = t / step_s - node
    per_point = np.concatenate([normal, lever_body], axis=1)
    if weight is not None:
        per_point = per_point * weight[:, None]
    nodes = np.column_stack([node, node + 1]).astype(np.int64)
    coef = np.stack([per_point * (1.0 - frac)[:, None], per_point * frac[:, None]], axis=1)
    return nodes, coef


def ins_meat(weighted_rows: np.ndarray, loading: PoseLoading, noise: InsNoise) -> np.ndarray:
    """``sum_c sigma_c^2 M_c^T K_c M_c`` (p, p): the covariance of ``A^T W v`` that the INS's
    errors give, ``M_c`` (samples, p) each sample's summed ``w a`` times its loading in
    component ``c``, ``K_c`` the Gauss-Markov correlation between samples
    (``exp(-|dt| / correlation)``). ``weighted_rows`` (k, p): ``w a`` of each correspondence
    (0 for those not used)."""
    p = weighted_rows.shape[1]
    meat = np.zeros((p, p))
    used = np.any(loading.coef != 0, axis=(1, 2))
    if not used.any() or noise.step_s is None:
        return meat
    nodes, rows = loading.nodes[used], weighted_rows[used]
    coef = loading.coef[used]
    lo, hi = int(nodes.min()), int(nodes.max())
    thin = max(1, math.ceil((hi - lo + 1) / MAX_GRID))
    index = (nodes - lo) // thin
    size = (hi - lo) // thin + 1
    step = noise.step_s * thin
    for c, (sigma, tau) in enumerate(zip(noise.sigmas(), noise.correlations(), strict=True)):
        if sigma <= 0:
            continue
        load = coef[:, :, c].astype(np.float64)  # (k, 8)
        m = np.column_stack([  # (bincount: an order of magnitude quicker than np.add.at)
            np.bincount(index.ravel(), weights=(rows[:, col:col + 1] * load).ravel(),
                        minlength=size) for col in range(p)])
        rho = math.exp(-step / tau) if tau > 0 else 0.0
        # K m by two first-order recursions (forward and backward) less the diagonal
        forward = lfilter([1.0], [1.0, -rho], m, axis=0)
        backward = lfilter([1.0], [1.0, -rho], m[::-1], axis=0)[::-1]
        meat += sigma**2 * (m.T @ (forward + backward - m))
    return 0.5 * (meat + meat.T)


__all__ = ["MAX_GRID", "N_COMPONENTS", "N_SAMPLES", "InsNoise", "PoseLoading", "ins_meat",
           "side_loading"]
