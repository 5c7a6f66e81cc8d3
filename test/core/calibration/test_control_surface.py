"""core/calibration/control_surface.py: the plane under a control point, against known planes."""

from __future__ import annotations

import numpy as np
import pytest

from lidarcal_ros.core.calibration.control_surface import PLANE_MAX_RMS_M, fit_control_planes


def scattered(rng: np.random.Generator, n: int, half_width: float) -> np.ndarray:
    """``n`` random map positions (x, y) within ``half_width`` metres of the origin."""
    return rng.uniform(-half_width, half_width, size=(n, 2))


def test_the_weights_reproduce_any_plane_under_the_control_point() -> None:
    """The foot ``sum w_i X_i`` lies right under the control point and on the plane: the
    weights sum to one and cancel the neighbours' horizontal offsets."""
    rng = np.random.default_rng(1)
    xy = scattered(rng, 200, 5.0)
    points = np.column_stack([xy, 3.5 + 0.2 * xy[:, 0] - 0.7 * xy[:, 1]])
    control = np.array([[0.3, -0.4, 10.0]])
    surface = fit_control_planes(control, points, np.arange(len(points)), k=24,
                                 max_radius=5.0)
    w = surface.weights[0]
    assert w.sum() == pytest.approx(1.0, abs=1e-12)
    foot = w @ points[surface.neighbours[0]]
    np.testing.assert_allclose(foot, [0.3, -0.4, 3.5 + 0.2 * 0.3 + 0.7 * 0.4], atol=1e-12)


@pytest.mark.parametrize("slope", [(0.0, 0.0), (0.3, -0.1), (-0.8, 0.5)])
def test_a_control_point_above_a_noisy_plane(slope: tuple[float, float]) -> None:
    """The distance is the control point's height above the plane along its normal, to the
    noise over sqrt(k); the normal is the plane's."""
    rng = np.random.default_rng(2)
    a, b = slope
    xy = scattered(rng, 4000, 20.0)
    z = 100.0 + a * xy[:, 0] + b * xy[:, 1] + rng.normal(0.0, 0.02, len(xy))
    points = np.column_stack([xy, z])
    control = np.array([[1.0, -2.0, 100.0 + a * 1.0 + b * -2.0 + 0.10]])
    surface = fit_control_planes(control, points, np.arange(len(points)), k=48,
                                 max_radius=5.0)
    normal = np.array([-a, -b, 1.0]) / np.sqrt(a * a + b * b + 1.0)
    assert surface.valid[0]
    assert surface.distance[0] == pytest.approx(0.10 * normal[2], abs=4 * 0.02 / np.sqrt(48))
    np.testing.assert_allclose(surface.normal[0], normal, atol=0.02)
    foot = surface.weights[0] @ points[surface.neighbours[0]]
    np.testing.assert_allclose(foot[:2], control[0, :2], atol=1e-9)


def test_noise_of_the_plane_falls_as_one_over_sqrt_k() -> None:
    """Over many draws, the distance's spread is that of the least-squares plane's height,
    about sigma / sqrt(k) at the centre of its points."""
    rng = np.random.default_rng(3)
    spreads = {}
    for k in (6, 48):
        d = []
        for _ in range(300):
            xy = scattered(rng, 400, 6.0)
            points = np.column_stack([xy, rng.normal(0.0, 0.02, len(xy))])
            surface = fit_control_planes(np.zeros((1, 3)), points, np.arange(len(points)), k=k,
                                         max_radius=6.0)
            d.append(surface.distance[0])
        spreads[k] = float(np.std(d))
    assert spreads[48] < 0.6 * spreads[6]
    assert spreads[48] == pytest.approx(0.02 / np.sqrt(48), rel=0.35)


def test_no_plane_across_an_edge_or_where_points_are_too_far() -> None:
    rng = np.random.default_rng(4)
    xy = scattered(rng, 2000, 10.0)
    step = np.where(xy[:, 0] > 0.0, 0.5, 0.0)  # a kerb of 0.5 m through x = 0
    points = np.column_stack([xy, step + rng.normal(0.0, 0.01, len(xy))])
    control = np.array([[0.0, 0.0, 0.2], [-6.0, 0.0, 0.0], [30.0, 0.0, 0.0]])
    surface = fit_control_planes(control, points, np.arange(len(points)), k=24,
                                 max_radius=3.0)
    np.testing.assert_array_equal(surface.valid, [False, True, False])
    assert PLANE_MAX_RMS_M < 0.25  # the edge's residuals exceed the limit
    assert (surface.neighbours[~surface.valid] == -1).all()
    assert np.isnan(surface.distance[~surface.valid]).all()


def test_too_few_candidates_give_no_plane() -> None:
    points = np.zeros((10, 3))
    surface = fit_control_planes(np.zeros((2, 3)), points, np.arange(5), k=6, max_radius=9.0)
    assert not surface.valid.any()
