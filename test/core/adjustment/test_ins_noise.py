"""The INS's errors propagated to the biases (core/adjustment/ins_noise.py) against draws of
those errors and against the dense correlation matrix."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lidarcal_ros.core.adjustment.ins_noise import (
    InsNoise,
    PoseLoading,
    ins_meat,
    side_loading,
)


def _problem(rng: np.random.Generator, k: int = 400, samples: int = 60
             ) -> tuple[np.ndarray, PoseLoading]:
    """``k`` correspondences of 3 parameters, each loading 8 random samples of 60."""
    rows = rng.standard_normal((k, 3))
    nodes = rng.integers(1000, 1000 + samples, size=(k, 8))
    coef = rng.standard_normal((k, 8, 6)).astype(np.float32)
    return rows, PoseLoading(nodes, coef)


def _dense(loading: PoseLoading, rows: np.ndarray, noise: InsNoise) -> np.ndarray:
    """``sum_c sigma_c^2 M_c^T K_c M_c`` with ``K_c`` written out."""
    lo = int(loading.nodes.min())
    size = int(loading.nodes.max()) - lo + 1
    assert noise.step_s is not None
    t = np.arange(size) * noise.step_s
    out = np.zeros((rows.shape[1],) * 2)
    for c, (sigma, tau) in enumerate(zip(noise.sigmas(), noise.correlations(), strict=True)):
        m = np.zeros((size, rows.shape[1]))
        for j in range(8):
            np.add.at(m, loading.nodes[:, j] - lo, rows * loading.coef[:, j, c:c + 1])
        k = np.exp(-np.abs(t[:, None] - t[None, :]) / tau) if tau > 0 else np.eye(size)
        out += sigma**2 * m.T @ k @ m
    return out


@pytest.mark.parametrize("correlation_s", [(0.0, 0.0), (0.05, 0.2), (3.0, 30.0)])
def test_the_meat_is_the_dense_correlation_matrixs(correlation_s: tuple[float, float]) -> None:
    rows, loading = _problem(np.random.default_rng(3))
    noise = InsNoise((0.02, 0.03, 0.04), (1e-4, 2e-4, 3e-4), correlation_s, step_s=0.01)
    np.testing.assert_allclose(ins_meat(rows, loading, noise), _dense(loading, rows, noise),
                               rtol=1e-9, atol=1e-15)


def test_the_propagated_covariance_is_the_spread_of_drawn_errors() -> None:
    """Gauss-Markov errors drawn on the samples, moved through the loadings into the
    discrepancies and solved for: their covariance is ``N^-1 meat N^-1``."""
    rng = np.random.default_rng(5)
    rows, loading = _problem(rng, k=300, samples=40)
    noise = InsNoise((0.02, 0.0, 0.03), (0.0, 1e-4, 0.0), (0.1, 0.0), step_s=0.01)
    lo = int(loading.nodes.min())
    size = int(loading.nodes.max()) - lo + 1
    n_inv = np.linalg.inv(rows.T @ rows)
    predicted = n_inv @ ins_meat(rows, loading, noise) @ n_inv
    draws = 4000
    tau = noise.correlations()
    rho = np.exp(-0.01 / np.where(tau > 0, tau, np.inf)) * (tau > 0)
    errors = np.zeros((draws, size, 6))
    errors[:, 0] = rng.standard_normal((draws, 6))
    for i in range(1, size):  # stationary first-order Gauss-Markov, unit variance
        errors[:, i] = rho * errors[:, i - 1] + np.sqrt(1 - rho**2) * \
            rng.standard_normal((draws, 6))
    errors *= noise.sigmas()
    at = errors[:, loading.nodes - lo]  # (draws, k, 8, 6)
    y = np.einsum("dkjc,kjc->dk", at, loading.coef.astype(np.float64))
    estimates = y @ rows @ n_inv  # (draws, 3)
    np.testing.assert_allclose(np.cov(estimates.T), predicted, rtol=0.1,
                               atol=0.1 * np.sqrt(np.outer(np.diag(predicted),
                                                           np.diag(predicted))).max())


def test_a_sides_loading_moves_the_discrepancy_as_the_error_moves_the_point() -> None:
    """Between two samples the error is linear; an attitude error ``e`` (body frame) moves
    ``n . X`` by ``e . R^T ((X - X_o) x n)``."""
    step = 0.01
    t = np.array([100.0, 100.0025, 100.005])
    n = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, 0.6, 0.8]])
    rotation = Rotation.from_euler("xyz", [[2, -3, 30], [1, 0, 120], [-4, 2, -75]],
                                   degrees=True)
    origin = np.array([[0.0, 0.0, 60.0], [5.0, 1.0, 62.0], [-3.0, 2.0, 58.0]])
    body = np.array([[10.0, 3.0, -58.0], [-20.0, 5.0, -55.0], [30.0, -8.0, -50.0]])
    x = origin + rotation.apply(body)
    lever = rotation.inv().apply(np.cross(x - origin, n))
    nodes, coef = side_loading(t, n, lever, step)
    np.testing.assert_array_equal(nodes, [[10000, 10001], [10000, 10001], [10000, 10001]])
    np.testing.assert_allclose(coef[:, 0, 0].sum() + coef[:, 1, 0].sum(), n[:, 0].sum())
    np.testing.assert_allclose(coef[:, 1, 2] / (coef[:, 0, 2] + coef[:, 1, 2]),
                               [0.0, 0.25, 0.5], atol=1e-9)
    e = np.array([3e-6, -2e-6, 5e-6])  # rad, about the body's axes (small: linear)
    moved = origin + (rotation * Rotation.from_rotvec(e)).apply(body)
    change = np.einsum("ij,ij->i", n, moved - x)
    predicted = (coef[:, 0, 3:] + coef[:, 1, 3:]) @ e
    np.testing.assert_allclose(predicted, change, rtol=1e-4)


def test_a_patchs_side_is_weighted_and_negated() -> None:
    n = np.array([[0.0, 0.0, 1.0]])
    lever = np.zeros((1, 3))
    point = side_loading(np.array([1.0]), n, lever, 0.01)
    vertex = side_loading(np.array([2.0]), n, lever, 0.01, np.array([0.25]))
    loading = PoseLoading.of_sides(point, [vertex, vertex, vertex])
    assert loading.nodes.shape == (1, 8) and loading.coef.shape == (1, 8, 6)
    np.testing.assert_allclose(loading.coef[0, :, 2], [1, 0, -0.25, 0, -0.25, 0, -0.25, 0])
    both = PoseLoading.concatenate([loading, PoseLoading.none(2)])
    assert both.nodes.shape == (3, 8) and not both.coef[1:].any()


def test_no_error_given_no_widening() -> None:
    """No sigma, no correspondence loaded, or no step known yet: nothing to add."""
    rows, loading = _problem(np.random.default_rng(1))
    assert not InsNoise().active
    assert not ins_meat(rows, loading, InsNoise(step_s=0.01)).any()
    assert not ins_meat(rows, PoseLoading.none(len(rows)),
                        InsNoise((0.1, 0.1, 0.1), step_s=0.01)).any()
    assert not ins_meat(rows, loading, InsNoise((0.1, 0.1, 0.1))).any()
    assert ins_meat(rows, loading, InsNoise((0.1, 0.1, 0.1), step_s=0.01)).any()


def test_a_long_mission_is_propagated_on_a_coarser_grid(monkeypatch: pytest.MonkeyPatch
                                                        ) -> None:
    """Beyond MAX_GRID samples the grid thins; with errors correlated over far more than the
    step, the meat barely changes."""
    import lidarcal_ros.core.adjustment.ins_noise as module

    rows, loading = _problem(np.random.default_rng(2), samples=400)
    noise = InsNoise((0.02, 0.02, 0.03), (0.0, 0.0, 0.0), (30.0, 20.0), step_s=0.01)
    full = ins_meat(rows, loading, noise)
    monkeypatch.setattr(module, "MAX_GRID", 100)
    thinned = ins_meat(rows, loading, noise)
    assert math.isclose(np.trace(thinned), np.trace(full), rel_tol=1e-3)
