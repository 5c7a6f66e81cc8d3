"""Pin every sign of docs/method.md with the shared test vectors."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers_paths import SHARED

from lidarcal_ros.core.georeferencing.bias_model import (
    correct_points,
    design_matrix,
    normal_design_rows,
    point_offsets,
)
from lidarcal_ros.core.georeferencing.local_trajectory import TrajectoryWindow, laser_geometry
from lidarcal_ros.core.mission import Trajectory
from lidarcal_ros.core.params import PARAMETER_NAMES, as_vector
from lidarcal_ros.errors import TrajectoryError

VECTORS = SHARED / "vectors" / "method_vectors.json"


@pytest.fixture(scope="module")
def vectors() -> dict:
    if not VECTORS.exists():  # pragma: no cover - shared/ sits beside every checkout
        pytest.skip(f"{VECTORS} not present")
    return json.loads(VECTORS.read_text())


def test_parameter_order(vectors: dict) -> None:
    assert tuple(vectors["parameter_order"]) == PARAMETER_NAMES


def test_design_rows(vectors: dict) -> None:
    for row in vectors["design_rows"]:
        args = [np.array([row[k]]) for k in ("x", "z", "kappa", "beta")]
        a = design_matrix(*args)[0]
        np.testing.assert_allclose(a, np.array(row["A"]), rtol=0, atol=1e-9)


def test_normal_rows_and_offsets_agree_with_design_matrix(vectors: dict) -> None:
    rng = np.random.default_rng(1)
    for row in vectors["design_rows"]:
        args = [np.array([row[k]]) for k in ("x", "z", "kappa", "beta")]
        a = design_matrix(*args)[0]
        delta = rng.normal(size=8)
        n = rng.normal(size=(1, 3))
        n /= np.linalg.norm(n)
        np.testing.assert_allclose(point_offsets(delta, *args)[0], a @ delta, atol=1e-9)
        np.testing.assert_allclose(normal_design_rows(n, *args)[0], n[0] @ a, atol=1e-9)


def test_linearised_offsets_of_pulses(vectors: dict) -> None:
    delta = as_vector(vectors["biases_used_for_pulses"])
    for pulse in vectors["pulses"]:
        args = [np.array([pulse[k]]) for k in ("x", "z", "kappa", "beta")]
        offset = point_offsets(delta, *args)[0]
        np.testing.assert_allclose(offset, pulse["linearised_offset"], atol=1e-9)
        # The linearised model is within about 0.1 mm of the exact one.
        assert np.max(np.abs(offset - np.array(pulse["exact_offset"]))) < 1.5e-4
        # Eq. [13] takes the biased point back to the true one (within linearisation).
        corrected = correct_points(np.array([pulse["biased_point"]]), delta, *args)[0]
        assert np.max(np.abs(corrected - np.array(pulse["true_point"]))) < 2e-4


def test_local_trajectory(vectors: dict) -> None:
    lt = vectors["local_trajectory"]
    samples = np.array(lt["samples"])
    traj = Trajectory(samples[:, 0], samples[:, 1:])
    t = np.array([p["t"] for p in lt["points"]])
    xyz = np.array([p["point"] for p in lt["points"]])
    g = laser_geometry(t, xyz, traj, window=TrajectoryWindow(window_s=0.5))
    for i, p in enumerate(lt["points"]):
        e = p["expected"]
        assert g.x[i] == pytest.approx(e["x"], abs=1e-6)
        assert g.z[i] == pytest.approx(e["z"], abs=1e-6)
        assert g.kappa[i] == pytest.approx(e["kappa"], abs=1e-9)
        assert g.beta[i] == pytest.approx(e["beta"], abs=1e-9)


def test_local_trajectory_at_projected_magnitudes_and_gps_time() -> None:
    """Absolute GPS seconds and UTM-size coordinates must not cost precision."""
    t = 1.4e9 + np.arange(0.0, 60.0, 0.005)  # 200 Hz
    kappa = np.radians(37.0)
    direction = np.array([-np.sin(kappa), np.cos(kappa), 0.0])
    start = np.array([512_345.678, 5_432_109.876, 1150.0])
    traj = Trajectory(t, start + np.outer(t - t[0], 65.0 * direction))
    tp = t[0] + np.array([10.0012, 33.3337])
    right = np.array([np.cos(kappa), np.sin(kappa), 0.0])
    origin = start + np.outer(tp - t[0], 65.0 * direction)
    pts = origin + np.outer([-212.5, 401.25], right) + np.array([0, 0, -1107.0])
    g = laser_geometry(tp, pts, traj)
    np.testing.assert_allclose(g.x, [-212.5, 401.25], atol=1e-6)
    np.testing.assert_allclose(g.z, [-1107.0, -1107.0], atol=1e-6)
    np.testing.assert_allclose(g.kappa, kappa, atol=1e-10)


def test_local_trajectory_same_in_any_point_order() -> None:
    """Time-ordered points take a linear-time path (windows as runs, running sample counts);
    shuffled points the general one: both give the same geometry and trig, also with points
    exactly on sample times and a curving, irregularly sampled trajectory."""
    rng = np.random.default_rng(5)
    t_traj = np.cumsum(rng.uniform(0.004, 0.03, 3000))
    heading = 0.3 + 0.02 * t_traj
    vel = 60.0 * np.column_stack([-np.sin(heading), np.cos(heading), np.zeros_like(t_traj)])
    traj = Trajectory(t_traj, np.array([4e5, 5e6, 1100.0]) + np.cumsum(vel * 0.01, axis=0))
    t = np.sort(np.concatenate([rng.uniform(t_traj[30], t_traj[-30], 20_000),
                                t_traj[100:110]]))
    xyz = (np.column_stack([np.interp(t, t_traj, traj.xyz[:, k]) for k in range(3)])
           + np.column_stack([rng.uniform(-400, 400, (t.size, 2)), np.full(t.size, -1050.0)]))
    ordered = laser_geometry(t, xyz, traj)
    perm = rng.permutation(t.size)
    shuffled = laser_geometry(t[perm], xyz[perm], traj)
    back = np.argsort(perm)
    for name in ("x", "z", "kappa", "beta"):
        np.testing.assert_array_equal(getattr(shuffled, name)[back], getattr(ordered, name))
    for a, b in zip(ordered.trig(), shuffled.take(back).trig(), strict=True):
        np.testing.assert_array_equal(a, b)
    c, s, sb, cb = ordered.trig()
    np.testing.assert_allclose(c, np.cos(ordered.kappa), atol=1e-15)
    np.testing.assert_allclose(s, np.sin(ordered.kappa), atol=1e-15)
    np.testing.assert_allclose(sb, np.sin(ordered.beta), atol=1e-15)
    np.testing.assert_allclose(cb, np.cos(ordered.beta), atol=1e-15)


def test_trajectory_gap_is_reported() -> None:
    t = np.concatenate([np.arange(0.0, 10.0, 0.1), np.arange(20.0, 30.0, 0.1)])
    xyz = np.column_stack([np.zeros_like(t), 50.0 * t, np.full_like(t, 1000.0)])
    traj = Trajectory(t, xyz)
    with pytest.raises(TrajectoryError, match=r"trajectory gap at t=15\.000"):
        laser_geometry(np.array([5.0, 15.0]), np.array([[10, 250, 0], [10, 750, 0.0]]), traj,
                       source="strip 7")
    with pytest.raises(TrajectoryError, match="strip 7"):
        laser_geometry(np.array([35.0]), np.array([[10, 1750, 0.0]]), traj, source="strip 7")


def test_exact_correction_inverts_the_biased_pulses(vectors: dict) -> None:
    from lidarcal_ros.core.georeferencing.bias_model import correct_points_exact
    from lidarcal_ros.core.georeferencing.laser_geometry import LaserGeometry

    delta = as_vector(vectors["biases_used_for_pulses"])
    for pulse in vectors["pulses"]:
        xo = np.array([pulse["trajectory_position"]])
        x, z, kappa, beta = (np.array([pulse[k]]) for k in ("x", "z", "kappa", "beta"))
        frame = LaserGeometry(x, z, kappa, beta, xo)
        corrected = correct_points_exact(np.array([pulse["biased_point"]]), frame, delta)[0]
        np.testing.assert_allclose(corrected, pulse["true_point"], atol=1e-8)
        # And differs from the linear eq. [13] only at second order.
        args = [np.array([pulse[k]]) for k in ("x", "z", "kappa", "beta")]
        linear = correct_points(np.array([pulse["biased_point"]]), delta, *args)[0]
        assert np.max(np.abs(linear - corrected)) < 2e-4
