"""The least-squares adjustment and its observability analysis on controlled observations."""

from __future__ import annotations

import numpy as np
import pytest

from lidarcal_ros.core.adjustment.least_squares import NormalEquations, Observations, solve
from lidarcal_ros.core.georeferencing.bias_model import normal_design_rows
from lidarcal_ros.core.params import PARAMETER_NAMES, as_vector
from lidarcal_ros.errors import CalibrationError

TRUE = as_vector({"dX": 0.05, "dY": -0.04, "dZ": 0.02, "domega": -1.4e-4, "dphi": -4.4e-4,
                  "dkappa": 2.2e-4, "dr": 0.118, "dS": 1e-4})


def _pair_rows(rng: np.random.Generator, n: int, *, flat: bool = False,
               heading_b: float = np.pi, height_b: float = 1150.0) -> np.ndarray:
    """Rows n^T (A_A - A_B) for conjugate points seen from two lines."""
    normal = rng.normal(size=(n, 3)) * (0.05 if flat else 0.6)
    normal[:, 2] = 1.0
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    x_a = rng.uniform(-500, 500, n)
    z_a = np.full(n, -1150.0)
    # Line B over the same ground: opposite heading mirrors the lateral coordinate.
    x_b = -x_a if abs(np.cos(heading_b)) > 0.5 and np.cos(heading_b) < 0 else x_a + 300.0
    z_b = np.full(n, -height_b)
    ra = normal_design_rows(normal, x_a, z_a, np.zeros(n), np.arctan(x_a / z_a))
    rb = normal_design_rows(normal, x_b, z_b, np.full(n, heading_b), np.arctan(x_b / z_b))
    return ra - rb


def test_recovers_known_biases_with_sigma0() -> None:
    rng = np.random.default_rng(3)
    rows = np.vstack([_pair_rows(rng, 4000), _pair_rows(rng, 4000, height_b=540.0),
                      _pair_rows(rng, 4000, heading_b=0.0)])
    y = rows @ TRUE + rng.normal(0, 0.02, rows.shape[0])
    neq = NormalEquations()
    # Accumulated in pieces, as the live node does, equals one batch.
    for part in np.array_split(np.arange(rows.shape[0]), 7):
        neq.add(rows[part], y[part])
    batch = NormalEquations.from_observations(
        Observations(rows, y, np.ones(y.size), np.zeros(y.size, np.int64),
                     np.zeros(y.size, np.int64)))
    np.testing.assert_allclose(neq.n, batch.n, rtol=1e-12)
    sol = solve(neq, solve_for=["dX", "dY", "domega", "dphi", "dkappa", "dr", "dS"],
                fixed={"dZ": 0.02})
    assert sol.status["dZ"].state == "fixed"
    est = np.isfinite(sol.sigma)
    z = (sol.delta - TRUE)[est] / sol.sigma[est]
    assert np.all(np.abs(z) < 4.0), z
    assert sol.sigma0 == pytest.approx(0.02, rel=0.05)
    assert sol.redundancy == rows.shape[0] - 7
    assert sol.correlation.shape == (7, 7)
    np.testing.assert_allclose(np.diag(sol.correlation), 1.0)


def test_dz_from_strips_alone_is_not_estimable_in_words() -> None:
    rng = np.random.default_rng(4)
    rows = _pair_rows(rng, 3000)
    neq = NormalEquations()
    neq.add(rows, rows @ TRUE + rng.normal(0, 0.02, rows.shape[0]))
    sol = solve(neq, solve_for=PARAMETER_NAMES)
    st = sol.status["dZ"]
    assert st.state == "not_estimable"
    assert "cancels between strips" in st.reason
    assert np.isnan(sol.sigma[PARAMETER_NAMES.index("dZ")])


def test_opposite_lines_at_one_height_cannot_see_dkappa_or_ds() -> None:
    """Remark 4: on opposite lines with full overlap the dkappa and dS effects cancel."""
    rng = np.random.default_rng(5)
    rows = _pair_rows(rng, 3000)  # one opposite pair at one height only
    neq = NormalEquations()
    neq.add(rows, rows @ TRUE + rng.normal(0, 0.02, rows.shape[0]))
    sol = solve(neq, solve_for=("dX", "dY", "domega", "dphi", "dkappa", "dS"))
    bad = {n for n, s in sol.status.items() if s.state == "not_estimable"}
    # Remark 5 too: at one flying height over flat ground domega and dY act alike.
    assert bad == {"dkappa", "dS", "domega", "dY"}
    assert all(sol.status[n].reason for n in bad)
    assert "dY" in sol.status["domega"].reason
    assert set(sol.estimated) == {"dX", "dphi"}
    est = np.isfinite(sol.sigma)
    assert np.all(np.abs((sol.delta - TRUE)[est] / sol.sigma[est]) < 4.0)


def test_nothing_to_estimate_and_no_observations() -> None:
    with pytest.raises(CalibrationError, match="no correspondences"):
        solve(NormalEquations(), solve_for=["dX"])
    rng = np.random.default_rng(6)
    neq = NormalEquations()
    neq.add(_pair_rows(rng, 100), np.zeros(100))
    with pytest.raises(CalibrationError, match="nothing to estimate"):
        solve(neq, solve_for=[])
    with pytest.raises(CalibrationError, match="nothing left to estimate"):
        solve(neq, solve_for=["dZ"])
