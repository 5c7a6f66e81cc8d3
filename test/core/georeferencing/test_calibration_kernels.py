"""The compiled loops of the calibration (lidarcal_ros.core.georeferencing.bias_model_kernels and
the TIN's, lidarcal_ros.core.calibration.tin_kernels) against the numpy formulations they replace,
on simulated strips of both point-positioning models."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from lidarcal_ros.core.calibration import tin_kernels
from lidarcal_ros.core.calibration.tin import GridLocator, Tin, TinBackend, TinQuality, delaunay
from lidarcal_ros.core.georeferencing.bias_model import (
    add_geometry_normal_rows,
    boresight_matrix,
    correct_points_exact,
    corrected_geometry,
    exact_correction,
    geometry_normal_rows,
)
from lidarcal_ros.core.georeferencing.laser_geometry import (
    LaserGeometry,
    ScannerKind,
    geometry_at,
)

ARCSEC = math.pi / 180.0 / 3600.0
#: Large biases (150 arcsec, 0.2 m, 2e-4): the exact correction's whole range.
DELTA = np.array([0.12, -0.2, 0.05, 150 * ARCSEC, -140 * ARCSEC, 120 * ARCSEC, 0.18, -2e-4])


@pytest.fixture(scope="module")
def geometries() -> dict[str, tuple[np.ndarray, LaserGeometry]]:
    """A strip of each model: a level mission, and one in rough air (the rigorous model)."""
    from lidarcal_ros.core.georeferencing.rigorous import strip_geometry
    from lidarcal_ros.core.simulation.flight_path import RoughAir, crosswind_for_crab
    from lidarcal_ros.core.simulation.simulate import simulate_mission
    from lidarcal_ros.core.simulation.spec import SimulationSpec

    out: dict[str, tuple[np.ndarray, LaserGeometry]] = {}
    for name in ("level", "rigorous"):
        rough = name == "rigorous"
        mission = simulate_mission(SimulationSpec.from_options(
            density=0.1, line_length_m=200.0, seed=5, rough_air=RoughAir() if rough else None,
            attitude=rough, wind_mps=crosswind_for_crab(5.0, 60.0) if rough else (0.0, 0.0)
        )).mission
        strip = mission.strips[0]
        g, choice = strip_geometry(strip.t, strip.xyz, mission.trajectory)
        assert choice.model == name
        out[name] = (strip.xyz, g)
    return out


def _correct_points_exact_numpy(xyz: np.ndarray, frame: LaserGeometry, delta: np.ndarray
                                ) -> np.ndarray:
    """The exact correction in numpy (what model.correct_points_exact did)."""
    d = delta
    q = frame.to_body(xyz - frame.origin)
    q -= d[:3]
    rho = q @ boresight_matrix(d[3], d[4], d[5])
    r_rec = np.hypot(rho[:, 0], rho[:, 2])
    beta = np.arctan2(-rho[:, 0], -rho[:, 2])
    r_true = r_rec - d[6]
    theta = beta / (1.0 + d[7])
    body = np.empty_like(rho)
    body[:, 0] = -r_true * np.sin(theta)
    body[:, 1] = rho[:, 1]
    body[:, 2] = -r_true * np.cos(theta)
    return frame.origin + frame.to_map(body)


@pytest.mark.parametrize("model", ["level", "rigorous"])
@pytest.mark.parametrize("scale", [0.0, 1.0])
def test_exact_correction_is_the_numpy_correction_and_geometry(
        geometries: dict[str, tuple[np.ndarray, LaserGeometry]], model: str,
        scale: float) -> None:
    xyz, g0 = geometries[model]
    delta = DELTA * scale
    corrected, shift, g = exact_correction(xyz, g0, delta)
    expected = _correct_points_exact_numpy(xyz, g0, delta)
    np.testing.assert_allclose(corrected, expected, rtol=0, atol=1e-9)
    np.testing.assert_allclose(shift, xyz - expected, rtol=0, atol=1e-9)
    ref = geometry_at(expected, g0)
    for name in ("x", "z", "beta"):
        np.testing.assert_allclose(getattr(g, name), getattr(ref, name), rtol=0, atol=1e-9)
    if model == "rigorous":
        assert g.y is not None and ref.y is not None and g.rotation is g0.rotation
        np.testing.assert_allclose(g.y, ref.y, rtol=0, atol=1e-9)
    else:
        assert g.y is None and g.rotation is None
    _, _, sb, cb = ref.trig()
    _, _, got_sb, got_cb = g.trig()
    np.testing.assert_allclose(got_sb, sb, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got_cb, cb, rtol=0, atol=1e-12)
    # the biases move the points by decimetres; none moves them not at all
    moved = np.abs(shift).max()
    assert (moved > 0.1) if scale else (moved < 1e-9)


@pytest.mark.parametrize("model", ["level", "rigorous", "general"])
def test_the_geometry_of_some_corrected_points_is_that_of_all_to_the_bit(
        geometries: dict[str, tuple[np.ndarray, LaserGeometry]], model: str) -> None:
    """correct_points_exact gives exact_correction's points (their shift the bits of ``xyz -
    corrected``, as the matching computes it where used), and corrected_geometry at
    some of them (repeated, out of order) exact_correction's geometry there, bit for bit;
    a general scanner's (section 12) too."""
    xyz, g0 = geometries["level" if model == "level" else "rigorous"]
    if model == "general":
        g0 = replace(g0, scanner=ScannerKind.GENERAL)
    corrected, shift, g = exact_correction(xyz, g0, DELTA)
    np.testing.assert_array_equal(correct_points_exact(xyz, g0, DELTA), corrected)
    np.testing.assert_array_equal(shift, xyz - corrected)
    # the firing frames alone (what a prepared strip holds) give the same, every point too
    frames = g0.firing_frames()
    assert not frames.has_laser_frame and frames.x.size == 0
    with pytest.raises(ValueError, match="laser vectors"):
        frames.trig()
    np.testing.assert_array_equal(correct_points_exact(xyz, frames, DELTA), corrected)
    every = corrected_geometry(corrected, frames, None)
    for name in ("x", "z", "beta", "sin_beta", "cos_beta", "cos_kappa", "sin_kappa"):
        np.testing.assert_array_equal(getattr(every, name), getattr(g, name), name)
    index = np.random.default_rng(2).integers(0, len(xyz), 5000)
    np.testing.assert_array_equal(corrected_geometry(corrected, frames, index).beta,
                                  g.take(index).beta)
    part, want = corrected_geometry(corrected, g0, index), g.take(index)
    for name in ("x", "z", "beta", "sin_beta", "cos_beta", "cos_kappa", "sin_kappa", "kappa",
                 "origin"):
        np.testing.assert_array_equal(getattr(part, name), getattr(want, name), name)
    if model == "level":
        assert part.y is None and part.rotation is None
    else:
        assert part.y is not None and want.y is not None and part.rotation is not None
        np.testing.assert_array_equal(part.y, want.y)
        np.testing.assert_array_equal(part.rotation, want.rotation)
    assert (part.model, part.scanner) == (g.model, g.scanner)
    # the biases moved the points: the geometry is not the delivered one's
    assert np.abs(part.beta - g0.beta[index]).max() > 1e-4
    # a timing column moves the points after the geometry is taken: refused


@pytest.mark.parametrize("model", ["level", "rigorous"])
def test_normal_rows_of_a_subset_are_those_of_its_geometry(
        geometries: dict[str, tuple[np.ndarray, LaserGeometry]], model: str) -> None:
    xyz, g0 = geometries[model]
    _, _, g = exact_correction(xyz, g0, DELTA)
    rng = np.random.default_rng(1)
    index = rng.integers(0, len(xyz), 3000)
    normal = rng.normal(0.0, 0.3, (index.size, 3)) + np.array([0.0, 0.0, 1.0])
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    weight = rng.uniform(0.0, 1.0, index.size)
    expected = geometry_normal_rows(normal, g.take(index))
    got = np.zeros((index.size, 8))
    add_geometry_normal_rows(got, normal, g, index)
    np.testing.assert_array_equal(got, expected)
    start = rng.normal(0.0, 1.0, (index.size, 8))
    got = start.copy()
    add_geometry_normal_rows(got, normal, g, index, weight)
    np.testing.assert_array_equal(got, start + weight[:, None] * expected)


def _judge_numpy(local: np.ndarray, simplices: np.ndarray, neighbors: np.ndarray,
                 q: TinQuality) -> tuple[np.ndarray, np.ndarray]:
    """Tin._judge in numpy (what it did): usable and sloped triangles."""
    tri = local[simplices]
    edges = tri[:, [1, 2, 0], :2] - tri[:, :, :2]
    max_edge = np.sqrt((edges**2).sum(axis=2)).max(axis=1)
    v0 = local[simplices[:, 0]]
    nrm = np.cross(local[simplices[:, 1]] - v0, local[simplices[:, 2]] - v0)
    length = np.linalg.norm(nrm, axis=1)
    length[length == 0] = np.inf
    nrm /= length[:, None]
    nrm[nrm[:, 2] < 0] *= -1.0
    ok = (max_edge <= q.max_edge_m) & (nrm[:, 2] >= np.cos(np.radians(q.max_slope_deg)))
    cos_bend = np.cos(np.radians(q.max_bend_deg))
    cos_flat = np.cos(np.radians(q.flat_slope_deg))
    sloped = nrm[:, 2] < cos_flat
    for k in range(3):
        nb = neighbors[:, k]
        has = nb >= 0
        agree = np.ones_like(ok)
        agree[has] = (nrm[has] * nrm[nb[has]]).sum(axis=1) >= cos_bend
        ok &= agree
        sloped &= has
        sloped[has] &= nrm[nb[has], 2] < cos_flat
    return ok, sloped


def test_tin_quality_is_the_numpy_judgement(
        geometries: dict[str, tuple[np.ndarray, LaserGeometry]]) -> None:
    xyz = geometries["level"][0]
    quality = TinQuality(max_edge_m=4.0 / math.sqrt(0.1))
    tin = Tin(xyz, quality)
    usable, sloped = _judge_numpy(xyz - tin.origin, tin.simplices, tin.neighbors, quality)
    np.testing.assert_array_equal(tin.usable, usable)
    np.testing.assert_array_equal(tin.sloped, sloped)
    # built-up terrain: usable and unusable patches, sloped roofs and flat ground
    assert 0.3 < usable.mean() < 0.99 and 0.01 < sloped.mean() < 0.5


def _grid_numpy(xy: np.ndarray, simplices: np.ndarray) -> dict[str, np.ndarray | float]:
    """GridLocator's grid and barycentric transforms in numpy (what it built)."""
    tri = xy[simplices]
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    extent = hi - lo
    cell = max(float(np.median(np.maximum(extent[:, 0], extent[:, 1]))), 1e-3)
    x0, y0 = xy[:, 0].min(), xy[:, 1].min()
    nx = int((xy[:, 0].max() - x0) / cell) + 1
    ny = int((xy[:, 1].max() - y0) / cell) + 1
    ix0, iy0 = ((lo[:, 0] - x0) // cell).astype(np.int64), ((lo[:, 1] - y0) // cell).astype(
        np.int64)
    ix1, iy1 = ((hi[:, 0] - x0) // cell).astype(np.int64), ((hi[:, 1] - y0) // cell).astype(
        np.int64)
    wx, wy = ix1 - ix0 + 1, iy1 - iy0 + 1
    count = wx * wy
    listed = count <= GridLocator.MAX_CELLS_PER_TRIANGLE
    tri_ids = np.repeat(np.flatnonzero(listed), count[listed])
    first = np.repeat(np.cumsum(count[listed]) - count[listed], count[listed])
    k = np.arange(tri_ids.size) - first
    cells = (ix0[tri_ids] + k % wx[tri_ids]) * ny + iy0[tri_ids] + k // wx[tri_ids]
    order = np.argsort(cells, kind="stable")
    a = tri[:, 0]
    m = np.stack([tri[:, 1] - a, tri[:, 2] - a], axis=2)
    det = m[:, 0, 0] * m[:, 1, 1] - m[:, 0, 1] * m[:, 1, 0]
    det[det == 0] = np.inf
    inv = np.empty_like(m)
    inv[:, 0, 0] = m[:, 1, 1] / det
    inv[:, 0, 1] = -m[:, 0, 1] / det
    inv[:, 1, 0] = -m[:, 1, 0] / det
    inv[:, 1, 1] = m[:, 0, 0] / det
    return {"cell": cell, "x0": x0, "y0": y0, "nx": nx, "ny": ny, "entries": tri_ids[order],
            "starts": np.searchsorted(cells[order], np.arange(nx * ny + 1)), "a": a,
            "inv": inv}


def _locate_numpy(q: np.ndarray, start: np.ndarray | None, grid: dict, neighbors: np.ndarray,
                  max_steps: int) -> np.ndarray:
    """GridLocator.locate in numpy: the start in the query's cell, a walk of all queries a
    step at a time, and a scan of the cell for the walks that do not settle."""
    cell, x0, y0, nx, ny = grid["cell"], grid["x0"], grid["y0"], grid["nx"], grid["ny"]
    entries, starts, a, inv = grid["entries"], grid["starts"], grid["a"], grid["inv"]
    out = np.full(q.shape[0], -1, dtype=np.int64)
    with np.errstate(invalid="ignore"):  # (the cast of NaN: outside)
        ix = np.floor((q[:, 0] - x0) / cell).astype(np.int64)
        iy = np.floor((q[:, 1] - y0) / cell).astype(np.int64)
    inside = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny) & np.isfinite(q).all(1)
    cells = np.where(inside, ix * ny + iy, 0)
    has = inside & (starts[cells + 1] > starts[cells])
    tri = np.where(has, entries[np.minimum(starts[cells], entries.size - 1)], -1)
    if start is not None:
        tri = np.where((start >= 0) & inside, start, tri)
    active = np.flatnonzero(tri >= 0)
    t = tri[active]
    for _ in range(max_steps):
        if not active.size:
            break
        d = q[active] - a[t]
        l1 = inv[t, 0, 0] * d[:, 0] + inv[t, 0, 1] * d[:, 1]
        l2 = inv[t, 1, 0] * d[:, 0] + inv[t, 1, 1] * d[:, 1]
        lam = np.stack([1.0 - l1 - l2, l1, l2], axis=1)
        worst = np.argmin(lam, axis=1)
        hit = lam[np.arange(t.size), worst] >= -1e-12
        out[active[hit]] = t[hit]
        step = neighbors[t, worst]
        going = ~hit & (step >= 0)
        active, t = active[going], step[going]
    for i in active:  # unsettled: every triangle of the cell, in order
        for e in range(starts[cells[i]], starts[cells[i] + 1]):
            tt = entries[e]
            d = q[i] - a[tt]
            l1 = inv[tt, 0, 0] * d[0] + inv[tt, 0, 1] * d[1]
            l2 = inv[tt, 1, 0] * d[0] + inv[tt, 1, 1] * d[1]
            if l1 >= -1e-12 and l2 >= -1e-12 and 1.0 - l1 - l2 >= -1e-12:
                out[i] = tt
                break
    return out


@pytest.mark.parametrize("max_steps", [64, 3])
def test_locate_is_the_numpy_grid_walk_and_scan(max_steps: int,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(11)
    xy = rng.uniform(0.0, 100.0, (3000, 2))
    simplices, neighbors = delaunay(xy, backend=TinBackend.SCIPY)
    monkeypatch.setattr(GridLocator, "MAX_WALK", max_steps)
    locator = GridLocator(xy, simplices, neighbors)
    grid = _grid_numpy(xy, simplices)
    np.testing.assert_array_equal(locator.entries, grid["entries"])
    np.testing.assert_array_equal(locator.starts, grid["starts"])
    assert (locator.cell, locator.x0, locator.y0, locator.nx, locator.ny) == tuple(
        grid[k] for k in ("cell", "x0", "y0", "nx", "ny"))
    # inside, outside the hull and the grid, on vertices (ties), non-finite; far starts
    q = np.vstack([rng.uniform(-10.0, 110.0, (5000, 2)), xy[:200], [[50.0, 50.0]]])
    q[-1, 0] = np.nan
    start = np.asarray(rng.integers(-1, simplices.shape[0], q.shape[0]), dtype=np.int64)
    for s in (None, start):
        expected = _locate_numpy(q, s, grid, neighbors, max_steps)
        np.testing.assert_array_equal(locator.locate(q, s), expected)
        inside = (q[:, 0] > 5) & (q[:, 0] < 95) & (q[:, 1] > 5) & (q[:, 1] < 95)
        assert (expected[inside] >= 0).mean() > 0.99 and (expected[~inside] >= 0).mean() < 0.5


def test_locator_on_the_points_themselves_is_the_locator_on_a_local_copy() -> None:
    # the TIN's locator reads the strip's own (n, 3) points less an offset instead of
    # holding a local XY copy: the same grid and the same triangles, bit for bit
    rng = np.random.default_rng(12)
    origin = np.array([512_345.678, 5_432_109.876, 250.0])
    xyz = origin + rng.uniform(-60.0, 60.0, (4000, 3))
    local = xyz - origin
    simplices, neighbors = delaunay(local[:, :2])
    copy = GridLocator(np.ascontiguousarray(local[:, :2]), simplices, neighbors)
    own = GridLocator(xyz, simplices, neighbors, offset=origin[:2])
    np.testing.assert_array_equal(own.entries, copy.entries)
    np.testing.assert_array_equal(own.starts, copy.starts)
    assert (own.cell, own.x0, own.y0, own.nx, own.ny) == \
        (copy.cell, copy.x0, copy.y0, copy.nx, copy.ny)
    q = np.vstack([rng.uniform(-70.0, 70.0, (6000, 2)), local[:300, :2]])
    found = own.locate(q)
    np.testing.assert_array_equal(found, copy.locate(q))
    assert (found >= 0).mean() > 0.7


def test_shifted_queries_move_by_the_mean_shift_of_their_triangle() -> None:
    rng = np.random.default_rng(3)
    xy = rng.uniform(0.0, 50.0, (500, 2))
    simplices, _ = delaunay(xy, backend=TinBackend.SCIPY)
    shift = rng.normal(0.0, 0.1, (500, 3))
    q = rng.uniform(0.0, 50.0, (800, 2))
    tri = np.asarray(rng.integers(-1, simplices.shape[0], q.shape[0]), dtype=np.int64)
    expected = q.copy()
    found = tri >= 0
    expected[found] += shift[simplices[tri[found]]].mean(axis=1)[:, :2]
    np.testing.assert_array_equal(
        tin_kernels.shifted_queries(q, tri, simplices, shift, np.zeros((0, 3))), expected)
    # the shift of the vertices used, from the delivered and the corrected vertices: the
    # bits of the shift held whole (delivered - corrected)
    delivered = rng.uniform(0.0, 50.0, (500, 3)) + np.array([512_000.0, 5_400_000.0, 100.0])
    corrected = delivered - shift
    held = delivered - corrected
    expected = q.copy()
    expected[found] += held[simplices[tri[found]]].mean(axis=1)[:, :2]
    np.testing.assert_array_equal(
        tin_kernels.shifted_queries(q, tri, simplices, delivered, corrected), expected)
