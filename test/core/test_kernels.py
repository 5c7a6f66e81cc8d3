"""The compiled loops of the grid normals, the local trajectory, the correction, the TIN
matching and the cloud scans (lidarcal_ros.core.normals.grid_normals_kernels,
local_trajectory_kernels, correction_kernels, tin_kernels, lidarcal_ros.io.cloud.pointcloud_kernels)
against independent numpy computations on the points themselves."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from lidarcal_ros.core.calibration import tin_kernels
from lidarcal_ros.core.flags import FLAG_NOT_CORRECTED
from lidarcal_ros.core.georeferencing import correction_kernels, local_trajectory_kernels
from lidarcal_ros.core.normals import grid_normals_kernels as normals_kernels
from lidarcal_ros.io.cloud import pointcloud_kernels
from lidarcal_ros.pipeline.correction import corrected_cloud

MIN_POINTS = 4
MIN_SPREAD = 0.01


def _points(n: int, seed: int = 3, step_v: float = 3.0) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    u = rng.uniform(0.0, 6.0, n)
    v = rng.uniform(0.0, 5.0, n)
    # a tilted plane with noise, and a step (an edge) of 2 m at v = step_v
    z = 0.2 * u - 0.1 * v + rng.normal(0.0, 0.02, n) + np.where(v > step_v, 2.0, 0.0)
    iu = np.floor(u).astype(np.int64)
    iv = np.floor(v).astype(np.int64)
    return u, v, z, iu, iv


def _grid(u: np.ndarray, v: np.ndarray, z: np.ndarray, iu: np.ndarray, iv: np.ndarray
          ) -> np.ndarray:
    moments = np.zeros((int(iu.max()) + 1, int(iv.max()) + 1, 10))
    normals_kernels.accumulate_moments(moments, 0, 0, iu, iv, u, v, z)
    return moments


def test_accumulate_moments_matches_bincount_and_honours_the_grid_offset() -> None:
    u, v, z, iu, iv = _points(3000)
    nu, nv = int(iu.max()) + 1, int(iv.max()) + 1
    key = iu * nv + iv
    expected = np.stack([np.bincount(key, weights=w, minlength=nu * nv) for w in (
        None, u, v, z, u * u, u * v, u * z, v * v, v * z, z * z)], axis=-1).reshape(nu, nv, 10)
    np.testing.assert_allclose(_grid(u, v, z, iu, iv), expected, rtol=1e-12, atol=1e-9)
    # Rows and columns numbered from (row0, col0) = (-5, 7): the same sums, moved.
    shifted = np.zeros((nu + 2, nv + 3, 10))
    normals_kernels.accumulate_moments(shifted, -5 - 1, 7 - 2, iu - 5, iv + 7, u, v, z)
    np.testing.assert_allclose(shifted[1:1 + nu, 2:2 + nv], expected, rtol=1e-12, atol=1e-9)
    assert shifted[..., 0].sum() == u.size


def test_block_fits_match_least_squares_and_pca_on_the_points() -> None:
    u, v, z, iu, iv = _points(3000)
    moments = _grid(u, v, z, iu, iv)
    nu, nv, _ = moments.shape
    blocks, valid = normals_kernels.fit_blocks(moments, MIN_POINTS, MIN_SPREAD)
    normals, offset, residual = blocks[:, :3], blocks[:, 3], blocks[:, 4]
    checked = 0
    for i in range(nu):
        for j in range(nv):
            k = i * nv + j
            sel = (iu >= i) & (iu <= i + 1) & (iv >= j) & (iv <= j + 1)
            if sel.sum() < MIN_POINTS:
                assert not valid[k] and math.isinf(residual[k])
                continue
            pts = np.c_[u[sel], v[sel], z[sel]]
            cov = np.cov(pts.T, bias=True)
            # Horizontal spread in both directions: the height plane z = a + b u + c v.
            a_mat = np.c_[np.ones(sel.sum()), u[sel], v[sel]]
            coef, *_ = np.linalg.lstsq(a_mat, z[sel], rcond=None)
            expected_n = np.array([-coef[1], -coef[2], 1.0]) / math.hypot(1.0, *coef[1:])
            res_var = np.mean((z[sel] - a_mat @ coef) ** 2) / (1.0 + coef[1] ** 2 + coef[2] ** 2)
            assert np.linalg.eigvalsh(cov[:2, :2])[0] >= MIN_SPREAD
            assert valid[k]
            np.testing.assert_allclose(normals[k], expected_n, atol=1e-9)
            assert residual[k] == pytest.approx(res_var, rel=1e-6, abs=1e-12)
            assert offset[k] == pytest.approx(float(expected_n @ pts.mean(axis=0)), abs=1e-9)
            checked += 1
    assert checked > 10
    # The generic fit of the same sums gives the same planes.
    box = np.zeros((10, nu * nv))
    for i in range(nu):
        for j in range(nv):
            box[:, i * nv + j] = moments[i:i + 2, j:j + 2].sum(axis=(0, 1))
    r2, n2, ok2, _ = normals_kernels.fit_sums(box, MIN_POINTS, MIN_SPREAD)
    np.testing.assert_array_equal(ok2, valid)
    np.testing.assert_allclose(n2[valid], normals[valid], atol=1e-12)
    np.testing.assert_allclose(r2[valid], residual[valid], rtol=1e-9, atol=1e-15)


def test_a_wall_gets_the_principal_component_plane() -> None:
    rng = np.random.default_rng(5)
    n = 200
    # A vertical wall along u: no horizontal spread across it, so no height plane.
    u = rng.uniform(0.0, 1.9, n)
    v = 1.0 + rng.normal(0.0, 1e-4, n)
    z = rng.uniform(0.0, 3.0, n)
    sums = np.array([[float(n)], [u.sum()], [v.sum()], [z.sum()], [(u * u).sum()],
                     [(u * v).sum()], [(u * z).sum()], [(v * v).sum()], [(v * z).sum()],
                     [(z * z).sum()]])
    residual, normals, valid, _ = normals_kernels.fit_sums(sums, MIN_POINTS, MIN_SPREAD)
    assert valid[0]
    assert abs(normals[0, 1]) == pytest.approx(1.0, abs=1e-3)  # horizontal, across the wall
    assert normals[0, 2] >= 0.0
    assert residual[0] < 1e-6


def test_cell_planes_take_the_best_of_the_four_blocks_with_ties_to_the_own_block() -> None:
    nu, nv = 3, 3
    residual = np.full(nu * nv, np.inf)
    for k, lam in ((0, 0.5), (1, 0.2), (3, 0.2), (4, 0.2)):
        residual[k] = lam
    best, ok = normals_kernels.cell_planes(residual, nu, nv)
    # The block each cell's plane comes from: own block first, then (i-1, j), (i, j-1),
    # (i-1, j-1), a later one only if strictly better.
    np.testing.assert_array_equal(best, [0, 1, 1, 3, 4, 4, 3, 4, 4])
    assert ok.all()
    # A cell whose four blocks have no plane has none.
    residual[:] = np.inf
    residual[8] = 0.1
    best, ok = normals_kernels.cell_planes(residual, nu, nv)
    np.testing.assert_array_equal(ok, [False] * 8 + [True])


@pytest.mark.parametrize("step_v", [3.0, 2.5])
def test_points_near_an_edge_take_the_plane_of_their_side(step_v: float) -> None:
    u, v, z, iu, iv = _points(6000, seed=11, step_v=step_v)
    moments = _grid(u, v, z, iu, iv)
    nu, nv, _ = moments.shape
    blocks, valid = normals_kernels.fit_blocks(moments, MIN_POINTS, MIN_SPREAD)
    best, cell_ok = normals_kernels.cell_planes(blocks[:, 4], nu, nv)
    heading = 0.7
    # (cells numbered from (row0, col0) = (3, -2): the same normals)
    nrm, ok, rough = normals_kernels.point_normals(blocks, valid, np.empty((0, 5)), best, cell_ok,
                                                   nu, nv, iu + 3, iv - 2, 3, -2, u, v, z, 0.1,
                                                   math.cos(heading), math.sin(heading))
    # the plane's normal in the grid's frame, turned to the map's
    truth = normals_kernels.flight_to_map(np.array([[-0.2, 0.1, 1.0]]) / math.sqrt(1.05),
                                          math.cos(heading), math.sin(heading))[0]
    assert ok.all()
    good = ~rough
    np.testing.assert_allclose(nrm[good], np.broadcast_to(truth, nrm[good].shape), atol=0.02)
    if step_v == 3.0:
        # The step lies on a cell boundary: each side's cells have clean blocks of their own.
        assert not rough.any()
    else:
        # The step halves cell column 2: every block holding that cell straddles the step.
        k = iu * nv + iv
        assert (blocks[best[k[iv == 2]], 4] > 0.1).all()
        # Its points above the step find the clean blocks beyond it (column 3 on) ...
        upper = (iv == 2) & (v > step_v + 0.05)
        assert upper.any() and not rough[upper].any()
        # ... and only points of that column can be left rough.
        assert not rough[iv != 2].any()


def test_the_loops_work_where_no_cache_directory_is_writable() -> None:
    # numba finds no place for its cache (a read-only install and home): the module still
    # imports and its loops compile in the process.
    import subprocess
    import sys

    code = (
        "from numba.core import caching\n"
        "caching.CacheImpl._locator_classes = []\n"
        "import numpy as np\n"
        "from lidarcal_ros.core.normals import grid_normals_kernels as normals_kernels\n"
        "m = np.zeros((1, 3, 10))\n"
        "normals_kernels.accumulate_moments(m, 0, 0, np.zeros(2, np.int64), np.array([0, 2]),\n"
        "                           np.ones(2), np.ones(2), np.ones(2))\n"
        "assert m[..., 0].sum() == 2.0, m\n"
        "print('ok')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-2000:]


def test_eq13_in_one_pass_is_the_design_matrix_and_refuses_mismatched_points() -> None:
    from lidarcal_ros.core.georeferencing.bias_model import (
        correct_points,
        design_matrix,
        point_offsets,
    )

    rng = np.random.default_rng(2)
    n = 50
    x = rng.uniform(-400.0, 400.0, n)
    z = rng.uniform(-1200.0, -900.0, n)
    kappa = rng.uniform(-math.pi, math.pi, n)
    beta = np.arctan(x / z)
    delta = rng.normal(0.0, 1e-3, 8)
    xyz = rng.uniform(-1e3, 1e3, (n, 3)) + np.array([5e5, 4e6, 100.0])
    expected = np.einsum("nij,j->ni", design_matrix(x, z, kappa, beta), delta)
    np.testing.assert_allclose(point_offsets(delta, x, z, kappa, beta), expected, atol=1e-12)
    np.testing.assert_allclose(correct_points(xyz, delta, x, z, kappa, beta), xyz - expected,
                               rtol=0, atol=1e-9)
    with pytest.raises(ValueError, match="xyz of shape"):
        correct_points(xyz[:-1], delta, x, z, kappa, beta)


def test_laser_geometry_in_one_pass_matches_geometry_at_its_own_origins() -> None:
    from lidarcal_ros.core.georeferencing.laser_geometry import LaserGeometry, geometry_at
    from lidarcal_ros.core.georeferencing.local_trajectory import laser_geometry
    from lidarcal_ros.core.mission import Trajectory

    tt = np.arange(0.0, 10.0, 0.005)
    traj = Trajectory(tt, np.column_stack([30.0 * np.sin(0.1 * tt), 60.0 * tt,
                                           1000.0 + 2.0 * np.cos(0.3 * tt)]))
    rng = np.random.default_rng(4)
    t = np.sort(rng.uniform(1.0, 9.0, 5000))
    xyz = np.column_stack([rng.uniform(-300, 300, t.size), 60.0 * t + rng.normal(0, 5, t.size),
                           rng.normal(0.0, 3.0, t.size)])
    g = laser_geometry(t, xyz, traj)
    ref = geometry_at(xyz, LaserGeometry(g.x, g.z, g.kappa, g.beta, g.origin))
    for name in ("x", "z", "beta"):
        np.testing.assert_allclose(getattr(g, name), getattr(ref, name), rtol=0, atol=1e-9)
    assert g.cos_kappa is not None  # laser_geometry sets it for a non-empty cloud
    np.testing.assert_allclose(g.cos_kappa, np.cos(g.kappa), atol=1e-15)
    _, _, sin_beta, cos_beta = g.trig()
    np.testing.assert_allclose(sin_beta, np.sin(g.beta), rtol=0, atol=1e-12)
    np.testing.assert_allclose(cos_beta, np.cos(g.beta), rtol=0, atol=1e-12)
    # The firing positions lie on the trajectory (a smooth line: within centimetres).
    np.testing.assert_allclose(g.origin[:, 1], 60.0 * t, atol=0.05)
    # Out of time order (the general search): each point keeps its own geometry.
    shuffle = rng.permutation(t.size)
    g2 = laser_geometry(t[shuffle], xyz[shuffle], traj)
    for name in ("x", "z", "beta", "kappa"):
        np.testing.assert_array_equal(getattr(g2, name), getattr(g, name)[shuffle])
    np.testing.assert_array_equal(g2.trig()[2], sin_beta[shuffle])


def test_time_windows_in_one_pass_are_those_of_the_binary_search() -> None:
    from lidarcal_ros.core.georeferencing.local_trajectory import windows_cover_points

    window_s = 0.5
    traj_t = np.concatenate([np.arange(100.0, 103.0, 0.25), np.arange(104.5, 106.0, 0.25)])
    rng = np.random.default_rng(6)
    # before the start, across the 1.5 s gap, past the end; ties with samples +- window
    t = np.sort(np.concatenate([rng.uniform(99.0, 107.0, 3000), traj_t[:5] + window_s,
                                traj_t[3:9] - window_s, traj_t[2:4], [101.0] * 4]))
    for min_samples in (2, 4):
        in_order, start, stop, window, n_bad, first_bad = (
            local_trajectory_kernels.sorted_time_windows(traj_t, t, window_s, min_samples))
        assert in_order
        want_start = np.searchsorted(traj_t, t - window_s, side="right")
        want_stop = np.searchsorted(traj_t, t + window_s, side="left")
        np.testing.assert_array_equal(start[window], want_start)
        np.testing.assert_array_equal(stop[window], want_stop)
        assert np.all(np.diff(window) >= 0) and np.all(np.diff(window) <= 1)
        assert len(set(zip(start.tolist(), stop.tolist(), strict=True))) == start.size
        bad = ~windows_cover_points(t, traj_t, want_start, want_stop, min_samples)
        assert 0 < n_bad == int(bad.sum()) and first_bad == int(np.argmax(bad))
    shuffled = t[::-1].copy()
    assert not local_trajectory_kernels.sorted_time_windows(traj_t, shuffled, window_s, 2)[0]
    with_nan = t.copy()
    with_nan[10] = np.nan
    assert not local_trajectory_kernels.sorted_time_windows(traj_t, with_nan, window_s, 2)[0]


def test_flight_cells_are_the_flight_frame_and_cells_of_the_finite_points() -> None:
    rng = np.random.default_rng(7)
    xyz = rng.uniform(-50.0, 50.0, (500, 3)) + np.array([5e5, 4e6, 300.0])
    xyz[[3, 77]] = np.nan
    xyz[200, 2] = np.inf
    heading, x0, y0, z0 = 0.7, 5e5 - 1.0, 4e6 + 2.0, 290.0
    c, s = math.cos(heading), math.sin(heading)
    u, v, z, iu, iv, index, bounds = normals_kernels.flight_cells(xyz, c, s, x0, y0, z0, 1 / 0.6,
                                                                  1 / 0.075)
    keep = np.isfinite(xyz).all(axis=1)
    np.testing.assert_array_equal(index, np.flatnonzero(keep))
    dx, dy = xyz[keep, 0] - x0, xyz[keep, 1] - y0
    np.testing.assert_array_equal(u, -s * dx + c * dy)
    np.testing.assert_array_equal(v, c * dx + s * dy)
    np.testing.assert_array_equal(z, xyz[keep, 2] - z0)
    np.testing.assert_array_equal(iu, np.floor(u * (1 / 0.6)).astype(np.int64))
    np.testing.assert_array_equal(iv, np.floor(v * (1 / 0.075)).astype(np.int64))
    assert bounds.tolist() == [iu.min(), iu.max(), iv.min(), iv.max()]
    assert normals_kernels.flight_cells(xyz[:0], c, s, x0, y0, z0, 1.0, 1.0)[0].size == 0
    # Every point finite: the same, without the index (the rows in order).
    finite = np.ascontiguousarray(xyz[keep])
    got = normals_kernels.flight_cells(finite, c, s, x0, y0, z0, 1 / 0.6, 1 / 0.075)
    assert got[5].size == 0
    for a, b in zip(got[:5], (u, v, z, iu, iv), strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(got[6], bounds)


def test_flight_to_map_rotates_by_the_heading() -> None:
    heading = 2.1
    n_uvz = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, -1.0], [np.nan, 0.2, 0.3]])
    out = normals_kernels.flight_to_map(n_uvz, math.cos(heading), math.sin(heading))
    # forward along the heading kappa = atan2(-dx, dy); right is forward turned clockwise
    np.testing.assert_allclose(out[0], [-math.sin(heading), math.cos(heading), 0.5])
    np.testing.assert_allclose(out[1], [math.cos(heading), math.sin(heading), -1.0])
    assert np.isnan(out[2, :2]).all() and out[2, 2] == 0.3


def _returns_case(n: int = 400, seed: int = 8) -> tuple[Any, ...]:
    """A level flight along a heading of 0.3 rad over tilted ground, with the cases the
    compiled correction flags: a point not served, one above its firing point, a NaN
    normal, a normal along the beam (|cos| > 1 before clipping), grazing and rough ones,
    a NaN intensity."""
    from lidarcal_ros.core.georeferencing.local_trajectory import window_lines
    from lidarcal_ros.core.mission import Trajectory

    rng = np.random.default_rng(seed)
    tt = np.arange(0.0, 4.0, 0.01)
    heading = np.array([-math.sin(0.3), math.cos(0.3), 0.0])
    traj = Trajectory(tt, np.outer(60.0 * tt, heading) + np.array([500.0, 200.0, 1000.0]))
    t = np.sort(rng.uniform(1.0, 3.0, n))
    across = rng.uniform(-400.0, 400.0, n)
    right = np.array([math.cos(0.3), math.sin(0.3), 0.0])
    xyz = (traj.xyz[0] + np.outer(60.0 * t, heading) + np.outer(across, right)
           + np.column_stack([np.zeros(n), np.zeros(n), -1000.0 + 0.1 * across]))
    xyz[7, 2] = 1500.0  # above the aircraft
    ok = np.ones(n, dtype=bool)
    ok[3] = False
    lines = window_lines(t[ok], traj)
    normals = rng.normal(0.0, 0.1, (n, 3))
    normals[:, 2] = 1.0
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    normals[5] = np.nan
    normals[6] = 2.0 * (xyz[6] - traj.xyz[100])  # about along the beam, not unit
    normals[10:20] = heading  # walls facing along track: the beams graze them
    rough = rng.random(n) < 0.2
    intensity = rng.uniform(10.0, 200.0, n).astype(np.float32)
    intensity[9] = np.nan
    delta = np.array([0.05, -0.03, 0.02, 4e-4, -3e-4, 5e-4, 0.03, 2e-4])
    return t, xyz, ok, lines, traj, normals, rough, intensity, delta


def _run_correct_returns(t: np.ndarray, xyz: np.ndarray, ok: np.ndarray, lines: Any,
                         normals: np.ndarray, rough: np.ndarray, intensity: np.ndarray,
                         delta: np.ndarray, model: Any,
                         volume: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    n = t.shape[0]
    out = (np.empty((n, 3)), np.empty(n, np.float32), np.empty(n, np.float32),
           np.empty(n, np.float32), np.empty(n, np.float32), np.empty(n, np.uint8))
    correction_kernels.correct_returns(
        t, xyz, ok, lines.window, False,
        (lines.t_mean, lines.p_mean, lines.velocity, lines.cos_kappa, lines.sin_kappa),
        (np.zeros(0), np.zeros((0, 3)), np.zeros((0, 4))), delta, normals, rough,
        np.zeros(0, bool) if volume is None else volume, intensity,
        model.kernel_constants(), out, corrected_cloud.NO_ROWS)
    return out


def test_polynomial_arctangent_and_arc_cosine_match_numpy() -> None:
    q = np.concatenate([np.linspace(-30.0, 30.0, 600_001), [0.0, -0.0, 1e-300, 1e300,
                                                            np.tan(np.pi / 8)]])
    got = np.array([correction_kernels.atan_poly(v) for v in q[::7]])
    np.testing.assert_allclose(got, np.arctan(q[::7]), rtol=0, atol=5e-11)
    assert correction_kernels.atan_poly(math.inf) == pytest.approx(math.pi / 2, abs=1e-15)
    assert correction_kernels.atan_poly(-math.inf) == pytest.approx(-math.pi / 2, abs=1e-15)
    assert math.isnan(correction_kernels.atan_poly(math.nan))
    c = np.concatenate([np.linspace(0.0, 1.0, 200_001), 1.0 - np.logspace(-16, -1, 200)])
    got = np.array([correction_kernels.acos_poly(v) for v in c])
    np.testing.assert_allclose(got, np.arccos(c), rtol=0, atol=1e-10)
    assert correction_kernels.acos_poly(1.0) == 0.0
    assert math.isnan(correction_kernels.acos_poly(math.nan))


def test_correct_returns_matches_the_numpy_stages() -> None:
    from lidarcal_ros.core.flags import (
        FLAG_GRAZING,
        FLAG_NO_INTENSITY,
        FLAG_NO_NORMAL,
        FLAG_NOT_CORRECTED,
        FLAG_ROUGH,
        FLAG_VOLUME,
    )
    from lidarcal_ros.core.georeferencing.bias_model import correct_points
    from lidarcal_ros.core.georeferencing.local_trajectory import laser_geometry
    from lidarcal_ros.core.radiometry import RadiometricModel

    t, xyz, ok, lines, traj, normals, rough, intensity, delta = _returns_case()
    model = RadiometricModel(visibility_km=20.0)
    xc, rng_m, inc, scan, refl, flags = _run_correct_returns(
        t, xyz, ok, lines, normals, rough, intensity, delta, model)
    served = ok.copy()
    served[7] = False  # above its firing point
    geo = laser_geometry(t[served], xyz[served], traj)
    # the numpy stages, one after the other
    want_xc = correct_points(xyz[served], delta, geo.x, geo.z, geo.kappa, geo.beta)
    beam = want_xc - geo.origin
    want_r = np.linalg.norm(beam, axis=1)
    want_scan = np.arctan((beam[:, 0] * np.cos(geo.kappa) + beam[:, 1] * np.sin(geo.kappa))
                          / beam[:, 2])
    cos_t = np.minimum(np.abs(np.einsum("ij,ij->i", normals[served], beam)) / want_r, 1.0)
    want_refl, want_grazing = model.reflectance(intensity[served], want_r, cos_t,
                                                uncertain=rough[served])
    np.testing.assert_allclose(xc[served], want_xc, rtol=0, atol=1e-9)
    np.testing.assert_allclose(rng_m[served], want_r.astype(np.float32), rtol=1e-7)
    np.testing.assert_allclose(scan[served], want_scan, rtol=0, atol=1e-7)
    np.testing.assert_allclose(inc[served], np.arccos(cos_t), rtol=0, atol=2e-7)
    np.testing.assert_allclose(refl[served], want_refl, rtol=2e-6)
    # the flags, bit by bit
    assert np.array_equal(xc[~served], xyz[~served])
    assert flags[3] == flags[7] == FLAG_NOT_CORRECTED
    assert np.isnan(np.column_stack([rng_m, inc, scan, refl])[~served]).all()
    sub = flags[served]
    assert np.array_equal((sub & FLAG_NO_NORMAL) != 0, np.isnan(cos_t))
    assert np.array_equal((sub & FLAG_ROUGH) != 0, rough[served])
    assert np.array_equal((sub & FLAG_GRAZING) != 0, want_grazing)
    assert want_grazing[8:18].all() and 0.0 <= inc[6] < 0.05  # (|cos| clipped at 1)
    assert np.array_equal((sub & FLAG_NO_INTENSITY) != 0, ~np.isfinite(intensity[served]))
    assert not (sub & FLAG_NOT_CORRECTED).any()
    # without intensity: every point says so, no reflectance
    _, _, _, _, refl2, flags2 = _run_correct_returns(
        t, xyz, ok, lines, normals, np.zeros(0, bool), np.zeros(0, np.float32), delta, model)
    assert np.isnan(refl2).all() and ((flags2 & FLAG_NO_INTENSITY) != 0).all()
    assert not ((flags2 & (FLAG_ROUGH | FLAG_GRAZING)) != 0).any()
    # volume returns (among them a NaN normal and grazing walls): cos 1, NaN incidence
    volume = np.zeros(len(t), bool)
    volume[[0, 1, 2, 5, 10, 11, 12]] = True
    volume[30:60] = True
    _, _, inc3, _, refl3, flags3 = _run_correct_returns(
        t, xyz, ok, lines, normals, rough, intensity, delta, model, volume)
    want3, grazing3 = model.reflectance(intensity[served], want_r, cos_t,
                                        uncertain=rough[served], volume=volume[served])
    np.testing.assert_allclose(refl3[served], want3, rtol=2e-6)
    vol, sub3 = volume[served], flags3[served]
    assert np.array_equal((sub3 & FLAG_VOLUME) != 0, vol)
    assert np.isnan(inc3[served][vol]).all()
    np.testing.assert_array_equal(inc3[served][~vol], inc[served][~vol])
    assert np.array_equal((sub3 & FLAG_GRAZING) != 0, grazing3) and not grazing3[vol].any()
    assert np.array_equal((sub3 & FLAG_NO_NORMAL) != 0, np.isnan(cos_t) & ~vol)
    assert flags3[3] == FLAG_NOT_CORRECTED  # (not served: no volume flag either)


def test_finite_range_on_a_strided_field() -> None:
    rows = np.zeros(1000, dtype=[("t", "<f8"), ("flags", "u1"), ("pad", "u1", 7)])
    rng = np.random.default_rng(6)
    rows["t"] = rng.normal(1.7e9, 100.0, 1000)
    rows["t"][[0, 17, 999]] = np.nan
    t = rows["t"]  # a strided view
    assert pointcloud_kernels.finite_range(t) == (np.fmin.reduce(t), np.fmax.reduce(t))
    lo, hi = pointcloud_kernels.finite_range(np.full(3, np.nan))
    assert math.isnan(lo) and math.isnan(hi)
    assert all(math.isnan(v) for v in pointcloud_kernels.finite_range(np.empty(0)))
    # every length (four running extremes and a tail), the extremes anywhere, infinities
    for n in range(1, 11):
        for k in range(n):
            v = np.arange(n, dtype=np.float64)
            v[k] = -5.0
            v[(k + 1) % n] = np.nan if n > 2 else v[(k + 1) % n]
            assert pointcloud_kernels.finite_range(v) == (np.fmin.reduce(v), np.fmax.reduce(v))
    assert pointcloud_kernels.finite_range(np.array([np.inf, np.nan])) == (np.inf, np.inf)
    assert pointcloud_kernels.finite_range(np.array([2.0, -np.inf, 1.0])) == (-np.inf, 2.0)


def test_byte_counts_is_bincount() -> None:
    values = np.random.default_rng(4).integers(0, 256, 10_001).astype(np.uint8)
    values[:300] = 255
    np.testing.assert_array_equal(correction_kernels.byte_counts(values),
                                  np.bincount(values, minlength=256))
    assert correction_kernels.byte_counts(np.empty(0, np.uint8)).sum() == 0


@pytest.mark.parametrize("radius", [0, 1, 2])
def test_centred_sums_add_the_block_around_each_cell_inside_the_grid(radius: int) -> None:
    rng = np.random.default_rng(5)
    moments = rng.random((7, 9, 10))
    cells = np.array([0, 8, 9 * 3 + 4, 9 * 6 + 8, 9 * 6, 5], dtype=np.int64)  # corners, edges
    got = normals_kernels.centred_sums(moments, cells, radius)
    for k, cell in enumerate(cells):
        i, j = divmod(int(cell), 9)
        block = moments[max(i - radius, 0):i + radius + 1, max(j - radius, 0):j + radius + 1]
        np.testing.assert_allclose(got[:, k], block.sum(axis=(0, 1)), rtol=1e-12)


def test_below_line_decides_as_numpy_interp() -> None:
    rng = np.random.default_rng(8)
    line_t = np.cumsum(rng.uniform(0.001, 0.01, 400)) + 50.0
    line_z = 1000.0 + np.cumsum(rng.normal(0.0, 0.3, 400))
    t = np.sort(np.concatenate([rng.uniform(49.0, 54.0, 20_000), line_t[::7], [np.nan]]))
    # heights straddling the threshold to the last bit, some exactly on it
    threshold = np.interp(t, line_t, line_z) - 1.0
    z = threshold + rng.choice([-1e-9, 0.0, 1e-9, -3.0, 3.0], t.size)
    z[::11] = np.nextafter(threshold[::11], -np.inf)
    expected = z < threshold
    below_line = local_trajectory_kernels.below_line
    np.testing.assert_array_equal(below_line(t, z, line_t, line_z, 1.0), expected)
    shuffle = rng.permutation(t.size)
    np.testing.assert_array_equal(below_line(t[shuffle], z[shuffle], line_t, line_z,
                                             1.0), expected[shuffle])
    # a single sample: its height everywhere
    h = line_z[0]
    one = below_line(np.array([0.0, 99.0]), np.array([h - 1.5, h - 0.5]), line_t[:1],
                     line_z[:1], 1.0)
    assert one.tolist() == [True, False]


def _best_patches_numpy(points: np.ndarray, tri: np.ndarray, simplices: np.ndarray,
                        neighbors: np.ndarray, usable: np.ndarray, vertices: np.ndarray,
                        max_d: float) -> tuple[np.ndarray, ...]:
    """The candidate tests in numpy, a candidate at a time for all points (what
    tin._match_block and tin._patch_test did)."""
    n = points.shape[0]
    best_tri = np.full(n, -1, dtype=np.int64)
    best_abs = np.full(n, np.inf)
    best_nrm, best_w, best_d = np.zeros((n, 3)), np.zeros((n, 3)), np.full(n, np.nan)

    def consider(rows: np.ndarray, cand: np.ndarray) -> None:
        ok = cand >= 0
        ok[ok] = usable[cand[ok]]
        t = simplices[np.where(ok, cand, 0)]
        p = points[rows]
        v0, v1, v2 = (vertices[t[:, j]] - p for j in range(3))
        ax, ay, az = v0[:, 0], v0[:, 1], v0[:, 2]
        e1x, e1y, e1z = v1[:, 0] - ax, v1[:, 1] - ay, v1[:, 2] - az
        e2x, e2y, e2z = v2[:, 0] - ax, v2[:, 1] - ay, v2[:, 2] - az
        nx, ny, nz = e1y * e2z - e1z * e2y, e1z * e2x - e1x * e2z, e1x * e2y - e1y * e2x
        length = np.sqrt(nx * nx + ny * ny + nz * nz)
        ok &= length > 0
        length[length == 0] = 1.0
        length[nz < 0] *= -1.0
        nx, ny, nz = nx / length, ny / length, nz / length
        dist = -(nx * ax + ny * ay + nz * az)
        px, py, pz = -dist * nx - ax, -dist * ny - ay, -dist * nz - az
        d00 = e1x * e1x + e1y * e1y + e1z * e1z
        d01 = e1x * e2x + e1y * e2y + e1z * e2z
        d11 = e2x * e2x + e2y * e2y + e2z * e2z
        d20, d21 = px * e1x + py * e1y + pz * e1z, px * e2x + py * e2y + pz * e2z
        denom = d00 * d11 - d01 * d01
        denom[denom == 0] = np.inf
        wv, ww = (d11 * d20 - d01 * d21) / denom, (d00 * d21 - d01 * d20) / denom
        wu = 1.0 - wv - ww
        ok &= (wu >= -1e-9) & (wv >= -1e-9) & (ww >= -1e-9) & (np.abs(dist) <= max_d)
        better = ok & (np.abs(dist) < best_abs[rows])
        r = rows[better]
        best_tri[r], best_abs[r], best_d[r] = cand[better], np.abs(dist[better]), dist[better]
        best_nrm[r] = np.column_stack([nx, ny, nz])[better]
        best_w[r] = np.stack([wu, wv, ww], axis=1)[better]

    rows = np.flatnonzero(tri >= 0)
    consider(rows, tri[rows])
    rest = rows[best_tri[rows] < 0]
    for k in range(3):
        consider(rest, neighbors[tri[rest], k])
    return best_tri, best_d, best_nrm, best_w


def test_best_patches_is_the_numpy_matching() -> None:
    from lidarcal_ros.core.calibration.tin import Tin, TinQuality
    from lidarcal_ros.core.simulation.simulate import simulate_mission
    from lidarcal_ros.core.simulation.spec import SimulationSpec

    spec = SimulationSpec.from_options(density=0.1, line_length_m=150.0, seed=3)
    strips = simulate_mission(spec).mission.strips
    tin = Tin(strips[0].xyz, TinQuality())
    rng = np.random.default_rng(2)
    vertices = strips[0].xyz + rng.normal(0.0, 0.01, strips[0].xyz.shape)  # "corrected"
    points = strips[1].xyz
    tri = tin.locate(points[:, :2])
    assert (tri >= 0).mean() > 0.5
    expected = _best_patches_numpy(points, tri, tin.simplices, tin.neighbors, tin.usable,
                                   vertices, 0.5)
    n = points.shape[0]
    got = (np.full(n, -1, dtype=np.int64), np.full(n, np.nan), np.zeros((n, 3)),
           np.zeros((n, 3)))
    tin_kernels.best_patches(points, tri, tin.simplices, tin.neighbors, tin.usable, vertices, 0.5,
                             *got)
    for a, b in zip(got, expected, strict=True):
        np.testing.assert_array_equal(a, b)
    found = got[0] >= 0
    assert 0.3 < found.mean() < 1.0  # some settled by a neighbour, some by none
    assert (got[0][found] != tri[found]).any()


@pytest.mark.parametrize("field_type", ["<f8", "<f4"])
def test_gather_xyz_and_all_finite_xyz_on_the_fields_of_a_cloud(field_type: str) -> None:
    rng = np.random.default_rng(4)
    cloud = np.zeros(1000, dtype=[("x", field_type), ("t", "<f8"), ("y", field_type),
                                  ("i", "<u2"), ("z", field_type)])
    for c in "xyz":
        cloud[c] = rng.normal(0.0, 1e3, 1000)
    out = np.empty((1000, 3))
    pointcloud_kernels.gather_xyz(cloud["x"], cloud["y"], cloud["z"], out)
    np.testing.assert_array_equal(out, np.column_stack([cloud[c].astype(np.float64)
                                                        for c in "xyz"]))
    assert pointcloud_kernels.all_finite_xyz(cloud["x"], cloud["y"], cloud["z"])
    for bad, c, row in ((np.nan, "z", 999), (np.inf, "x", 0), (-np.inf, "y", 500)):
        spoilt = cloud.copy()
        spoilt[c][row] = bad
        assert not pointcloud_kernels.all_finite_xyz(spoilt["x"], spoilt["y"], spoilt["z"])


def test_cells_without_plane_is_the_numpy_expression() -> None:
    rng = np.random.default_rng(12)
    nu, nv = 9, 31
    iu = rng.integers(0, nu, 500)
    iv = rng.integers(0, nv, 500)
    cell_ok = rng.random(nu * nv) < 0.7
    wanted = np.zeros(nu * nv, dtype=bool)
    wanted[iu * nv + iv] = True
    np.testing.assert_array_equal(normals_kernels.cells_without_plane(iu, iv, 0, 0, nv, cell_ok),
                                  np.flatnonzero(wanted & ~cell_ok))
    # cells numbered from (row0, col0) = (-4, 9): the same grid cells
    np.testing.assert_array_equal(normals_kernels.cells_without_plane(iu - 4, iv + 9, -4, 9, nv,
                                                                      cell_ok),
                                  np.flatnonzero(wanted & ~cell_ok))
    assert normals_kernels.cells_without_plane(iu[:0], iv[:0], 0, 0, nv, cell_ok).size == 0


@pytest.mark.parametrize("all_served", [True, False])
@pytest.mark.parametrize("layout", ["lidarcal", "float32 xyz"])
def test_correct_returns_into_the_rows_writes_the_bytes_of_the_columns_and_rows(
        all_served: bool, layout: str) -> None:
    """Corrected straight into a cloud's rows (the node's path), the bytes and the tally are
    those of the columns written out by fill_corrected_rows, whether every point is served
    (the run-by-run path) or not (a point's window counted among the served ones), with
    8-byte (lidarcal's layout) or 4-byte words (single-precision coordinates)."""
    from lidarcal_ros.core.radiometry import RadiometricModel
    from lidarcal_ros.io.cloud.pointcloud import make_point_dtype

    t, xyz, ok, lines, _traj, normals, rough, intensity, delta = _returns_case(n=1000)
    if all_served:
        ok[:] = True
        xyz[7, 2] = xyz[6, 2]
        lines = _returns_lines(t, _traj)
    model = RadiometricModel(visibility_km=20.0)
    dtype = (make_point_dtype() if layout == "lidarcal" else np.dtype(
        [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("t", "<f8"), ("intensity", "<f4")]))
    points = np.zeros(len(t), dtype=dtype)
    points["x"], points["y"], points["z"], points["t"] = xyz[:, 0], xyz[:, 1], xyz[:, 2], t
    points["intensity"] = intensity
    if layout != "lidarcal":
        xyz = np.column_stack([points["x"], points["y"], points["z"]]).astype(np.float64)
    volume = np.zeros(len(t), bool)
    volume[::9] = True  # (volume returns among them: flag, NaN incidence, cos 1)
    xc, rng_m, inc, scan, refl, flags = _run_correct_returns(
        t, xyz, ok, lines, normals, rough, intensity, delta, model, volume)
    res = corrected_cloud.CorrectedColumns(xc, rng_m, inc, scan, refl, flags)
    expected_tally = corrected_cloud.CloudTally.empty()
    expected = corrected_cloud.build_corrected(points, res, tally=expected_tally)
    out = np.full(len(t) * expected.dtype.itemsize, 0xAB, np.uint8).view(expected.dtype)
    counts = np.zeros(257, dtype=np.int64)
    target = corrected_cloud.row_target(points, out, counts)
    assert target is not None
    n = len(t)
    correction_kernels.correct_returns(
        t, xyz, ok, lines.window, False,
        (lines.t_mean, lines.p_mean, lines.velocity, lines.cos_kappa, lines.sin_kappa),
        (np.zeros(0), np.zeros((0, 3)), np.zeros((0, 4))), delta, normals, rough,
        volume, intensity, model.kernel_constants(),
        (np.empty((0, 3)), *(np.empty(0, np.float32),) * 4, np.empty(0, np.uint8)), target)
    assert n > 2 * 256  # (several blocks)
    assert out.tobytes() == expected.tobytes()
    np.testing.assert_array_equal(counts, expected_tally.counts)
    assert expected_tally.flagged(FLAG_NOT_CORRECTED) == (0 if all_served
                                                                           else 2)


def _returns_lines(t: np.ndarray, traj: Any) -> Any:
    from lidarcal_ros.core.georeferencing.local_trajectory import window_lines

    return window_lines(t, traj)
