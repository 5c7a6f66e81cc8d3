"""Tests of the mission simulator (lidarcal_ros.core.simulate) and terrain (core.terrain)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from lidarcal_ros.core.params import PARAMETER_NAMES, as_vector
from lidarcal_ros.core.simulate import (
    DEFAULT_BIASES,
    biased_point_exact,
    pulse_and_scan_rates,
    simulate_mission,
    swath_width,
)
from lidarcal_ros.core.terrain import ROOF, TREE, Terrain, cast_rays
from lidarcal_ros.errors import ConfigError

VECTORS = Path(__file__).resolve().parents[2] / "shared" / "vectors" / "method_vectors.json"

ZERO = dict.fromkeys(PARAMETER_NAMES, 0.0)


def design_matrix(x, z, kappa, beta):
    """method.md section 3, written out independently of lidarcal_ros.core.model."""
    c, s = np.cos(kappa), np.sin(kappa)
    sb, cb = np.sin(beta), np.cos(beta)
    a = np.zeros((len(x), 3, 8))
    a[:, 0, 0], a[:, 0, 1] = c, -s
    a[:, 0, 3], a[:, 0, 4], a[:, 0, 5] = z * s, z * c, -x * s
    a[:, 0, 6], a[:, 0, 7] = -c * sb, z * beta * c
    a[:, 1, 0], a[:, 1, 1] = s, c
    a[:, 1, 3], a[:, 1, 4], a[:, 1, 5] = -z * c, z * s, x * c
    a[:, 1, 6], a[:, 1, 7] = -s * sb, z * beta * s
    a[:, 2, 2] = 1.0
    a[:, 2, 4], a[:, 2, 6], a[:, 2, 7] = -x, -cb, -x * beta
    return a


def firing_positions(sim, i):
    tr = sim.mission.trajectory
    t = sim.mission.strips[i].t
    return np.column_stack([np.interp(t, tr.t, tr.xyz[:, j]) for j in range(3)])


@pytest.fixture(scope="module")
def paper():
    return simulate_mission(density=0.3, line_length_m=300.0, range_noise_m=0.0, n_control=3,
                            seed=3)


# ---------------------------------------------------------------------- exact model vs vectors


def test_biased_point_exact_matches_method_vectors():
    if not VECTORS.exists():  # pragma: no cover - shared/ sits beside every checkout
        pytest.skip(f"{VECTORS} not present")
    data = json.loads(VECTORS.read_text())
    biases = data["biases_used_for_pulses"]
    assert data["parameter_order"] == list(PARAMETER_NAMES)
    for pulse in data["pulses"]:
        xo = np.array(pulse["trajectory_position"])
        p = np.array(pulse["true_point"])
        xb = biased_point_exact(xo, pulse["kappa"], p, biases)
        assert xb.shape == (3,)
        np.testing.assert_allclose(xb - p, pulse["exact_offset"], rtol=0, atol=1e-6)
        np.testing.assert_allclose(xb, pulse["biased_point"], rtol=0, atol=1e-6)
        # second-order terms only: the vectors' own exact-linearised gap is up to 0.13 mm
        assert np.max(np.abs(xb - p - np.array(pulse["linearised_offset"]))) < 2e-4
    # vectorised form gives the same
    xo = np.array([q["trajectory_position"] for q in data["pulses"]])
    p = np.array([q["true_point"] for q in data["pulses"]])
    k = np.array([q["kappa"] for q in data["pulses"]])
    xb = biased_point_exact(xo, k, p, biases)
    np.testing.assert_allclose(xb - p, [q["exact_offset"] for q in data["pulses"]], atol=1e-6)


def test_biased_point_exact_zero_biases_is_identity():
    rng = np.random.default_rng(0)
    xo = np.column_stack([rng.uniform(-500, 500, 50), rng.uniform(-500, 500, 50),
                          np.full(50, 900.0)])
    k = rng.uniform(-math.pi, math.pi, 50)
    theta = rng.uniform(-0.4, 0.4, 50)
    r = rng.uniform(800, 1000, 50)
    p = xo + r[:, None] * np.column_stack(
        [-np.cos(k) * np.sin(theta), -np.sin(k) * np.sin(theta), -np.cos(theta)])
    np.testing.assert_allclose(biased_point_exact(xo, k, p, ZERO), p, atol=1e-9)


# ---------------------------------------------------------------------- simulation geometry


def test_zero_bias_zero_noise_points_are_true_points():
    lines = [{"id": 7, "start": (-30.0, -100.0), "end": (40.0, 120.0), "height": 1150.0}]
    sim = simulate_mission(lines=lines, biases=ZERO, range_noise_m=0.0, density=0.2,
                           n_control=0, seed=1)
    assert sim.mission.control is None
    strip = sim.mission.strips[0]
    assert strip.strip_id == 7 and len(strip) > 1000
    np.testing.assert_allclose(strip.xyz, sim.true_xyz[0], rtol=0, atol=1e-6)


def test_biased_offsets_agree_with_linearised_model(paper):
    delta = as_vector(paper.biases)
    assert paper.biases == DEFAULT_BIASES
    for i, strip in enumerate(paper.mission.strips):
        xo = firing_positions(paper, i)
        kappa = paper.lines[i]["kappa"]
        d = strip.xyz - xo
        x = np.cos(kappa) * d[:, 0] + np.sin(kappa) * d[:, 1]
        z = d[:, 2]
        beta = np.arctan(x / z)
        pred = design_matrix(x, z, np.full(x.size, kappa), beta) @ delta
        offset = strip.xyz - paper.true_xyz[i]
        # the exact offsets are far from zero ...
        assert np.abs(offset.mean(axis=0)).max() > 0.1
        # ... and agree with A * delta: mean within a few mm, every point within 1 mm
        np.testing.assert_allclose(offset.mean(axis=0), pred.mean(axis=0), atol=3e-3)
        assert np.abs(offset - pred).max() < 1e-3


def test_range_noise_and_mean_offset():
    lines = [{"id": 1, "start": (0.0, -100.0), "end": (0.0, 100.0), "height": 800.0}]
    sim = simulate_mission(lines=lines, density=0.3, n_control=0, range_noise_m=0.05,
                           terrain_kind="flat", seed=2)
    strip = sim.mission.strips[0]
    xo = firing_positions(sim, 0)
    # flat ground: the range residual along the beam is dr + noise
    u = sim.true_xyz[0] - xo
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    r_meas = np.einsum("ij,ij->i", strip.xyz - xo - np.array([0.05, -0.04, 0.0]), u)
    resid = r_meas - sim.range_true[0] - DEFAULT_BIASES["dr"]
    assert abs(resid.mean()) < 0.005
    assert 0.045 < resid.std() < 0.055
    assert np.all(sim.true_xyz[0][:, 2] == 0.0)


def test_paper_lines_headings_and_layout(paper):
    lines = {ln["id"]: ln for ln in paper.lines}
    assert sorted(lines) == [1, 2, 3, 4, 5, 6]
    assert [ln["id"] for ln in paper.lines] == [1, 2, 3, 4, 5, 6]
    dk = (lines[1]["kappa"] - lines[2]["kappa"]) % (2 * math.pi)
    assert dk == pytest.approx(math.pi, abs=1e-9)
    dk = (lines[3]["kappa"] - lines[4]["kappa"]) % (2 * math.pi)
    assert dk == pytest.approx(math.pi, abs=1e-9)
    assert lines[5]["kappa"] == pytest.approx(lines[6]["kappa"])
    assert lines[1]["direction"] == pytest.approx((0.0, 1.0))  # north-bound
    assert lines[2]["direction"] == pytest.approx((0.0, -1.0))
    assert [lines[i]["height"] for i in range(1, 7)] == [1150, 1150, 540, 540, 1150, 1150]
    w = swath_width(1150.0, 50.0)
    sep = abs(lines[5]["start"][0] - lines[6]["start"][0])
    assert 0.5 * w < sep < 0.6 * w
    # the headings seen in the data: fitted from the trajectory
    tr = paper.mission.trajectory
    for i, strip in enumerate(paper.mission.strips):
        xo = firing_positions(paper, i)
        d = xo[-1] - xo[0]
        assert math.atan2(-d[0], d[1]) == pytest.approx(paper.lines[i]["kappa"], abs=1e-9)
        # trajectory covers 2 s before the first pulse to 2 s after the last
        assert tr.t.min() <= strip.t.min() - 1.99
        inside = (tr.t >= strip.t.min() - 2.01) & (tr.t <= strip.t.max() + 2.01)
        assert tr.t[inside].min() <= strip.t.min() - 1.98
        assert tr.t[inside].max() >= strip.t.max() + 1.98
    # lines are separated in time by ~30 s turns, time increases
    for a, b in zip(paper.lines, paper.lines[1:]):
        assert 30.0 <= b["t_first"] - a["t_last"] <= 36.0
    assert np.all(np.diff(tr.t) > 0)
    assert paper.mission.strips[0].t[0] == pytest.approx(1.7e9 + 2.0)


def test_density_at_both_heights():
    sim = simulate_mission(scenario="one_track", density=0.5, line_length_m=300.0,
                           range_noise_m=0.0, n_control=0, seed=5)
    dens = {}
    for ln, pts in zip(sim.lines, sim.true_xyz):
        box = (np.abs(pts[:, 0]) < 60.0) & (np.abs(pts[:, 1]) < 60.0)
        dens[ln["id"]] = box.sum() / 120.0**2
    for i in (1, 2):
        assert dens[i] == pytest.approx(0.5, rel=0.2)
    ratio = (dens[3] + dens[4]) / (dens[1] + dens[2])
    assert ratio == pytest.approx(swath_width(1150, 50) / swath_width(540, 50), rel=0.1)
    assert 1.9 < ratio < 2.4
    prf, scan = pulse_and_scan_rates(0.5, 60.0, 50.0)
    assert sim.config["prf_hz"] == pytest.approx(prf)
    assert sim.config["scan_rate_hz"] == pytest.approx(scan)
    # one track: every line over x = 0
    assert all(ln["start"][0] == 0.0 and ln["end"][0] == 0.0 for ln in sim.lines)
    # the scan angle stays within the field of view
    assert max(np.abs(a).max() for a in sim.scan_angle_true) <= math.radians(25.0) + 1e-6


def test_control_points_on_open_ground_inside_every_strip(paper):
    ctrl = paper.mission.control
    assert ctrl is not None
    assert ctrl.ids == ["C1", "C2", "C3"]
    terrain = paper.terrain
    xy = ctrl.xyz[:, :2]
    # the first one at the centre of the common area
    assert np.hypot(*xy[0]) < 1e-9
    np.testing.assert_allclose(ctrl.xyz[:, 2], terrain.height(xy[:, 0], xy[:, 1]), atol=1e-9)
    np.testing.assert_allclose(ctrl.xyz[:, 2], terrain.ground_height(xy[:, 0], xy[:, 1]),
                               atol=1e-9)
    # open ground: no building or tree within 15 m
    ang = np.linspace(0, 2 * np.pi, 72, endpoint=False)
    for x, y in xy:
        for rad in (2.0, 5.0, 10.0, 15.0):
            cls = terrain.surface_class(x + rad * np.cos(ang), y + rad * np.sin(ang))
            assert not np.isin(cls, [ROOF, TREE]).any()
    # seen by every strip: points within 2 m, and well inside the swath
    for i, strip in enumerate(paper.mission.strips):
        ln = paper.lines[i]
        for x, y in xy:
            assert np.hypot(strip.xyz[:, 0] - x, strip.xyz[:, 1] - y).min() < 2.0
            ux, uy = ln["direction"]
            across = (x - ln["start"][0]) * uy - (y - ln["start"][1]) * ux
            assert abs(across) < 0.5 * ln["swath_width_m"] - 20.0


def test_roof_slopes_and_aspects_in_common_overlap(paper):
    terrain = paper.terrain
    # common overlap of all six strips: |x| < 236, |y| < 150 (300 m lines)
    gx, gy = np.meshgrid(np.arange(-230, 230, 1.0), np.arange(-145, 145, 1.0))
    gx, gy = gx.ravel(), gy.ravel()
    roof = terrain.surface_class(gx, gy) == ROOF
    assert roof.mean() > 0.05
    n = terrain.normal(gx[roof], gy[roof])
    slope = np.degrees(np.arccos(n[:, 2]))
    aspect = np.degrees(np.arctan2(n[:, 0], n[:, 1])) % 360.0  # azimuth of the downhill side
    sloped = (slope >= 15.0) & (slope <= 45.0)
    sectors = np.unique((aspect[sloped] // 45.0).astype(int))
    assert len(sectors) >= 6
    assert (slope < 1.0).any()  # flat roofs too
    # and near the centre (within 150 m)
    near = (np.hypot(gx[roof], gy[roof]) < 150.0) & sloped
    assert len(np.unique((aspect[near] // 45.0).astype(int))) >= 4


def test_strip_attributes(paper):
    for i, strip in enumerate(paper.mission.strips):
        n = len(strip)
        assert strip.xyz.dtype == np.float64 and strip.xyz.shape == (n, 3)
        assert strip.intensity is not None and strip.intensity.dtype == np.float32
        assert np.all(np.isfinite(strip.intensity)) and np.all(strip.intensity >= 0)
        assert strip.intensity.max() < 65535
        assert np.all(np.diff(strip.t) > 0)
        inc = paper.incidence_true[i]
        assert inc.shape == (n,) and inc.min() >= 0 and inc.max() <= math.pi / 2 + 1e-6
        cls = paper.surface_class[i]
        assert set(np.unique(cls)) <= {0, 1, 2, 3, 4}
        assert {0, 1, 2, 3, 4} <= set(np.unique(cls)) or i >= 2
        rho = paper.reflectance_true[i]
        base = np.array([0.30, 0.45, 0.12, 0.25, 0.50])[cls]
        assert np.all(rho >= 0.9 * base - 1e-6) and np.all(rho <= 1.1 * base + 1e-6)
        r = paper.range_true[i]
        np.testing.assert_allclose(
            np.linalg.norm(paper.true_xyz[i] - firing_positions(paper, i), axis=1), r,
            atol=1e-4)
        # radar equation (2% noise): I r^2 / (rho cos) nearly constant for a strip
        cos_inc = np.cos(inc.astype(np.float64))
        ok = cos_inc > 0.3
        k = strip.intensity[ok] * r[ok] ** 2 / (rho[ok] * cos_inc[ok])
        assert np.std(k) / np.mean(k) < 0.03
    assert paper.config["n_points"] == sum(len(s) for s in paper.mission.strips)
    for key in ("density", "biases", "prf_hz", "scan_rate_hz", "seed", "line_length_m"):
        assert key in paper.config


def test_origin_shifts_everything():
    line = {"id": 1, "start": (0.0, -80.0), "end": (0.0, 80.0), "height": 600.0}
    kw: dict[str, Any] = {"lines": [line],
                          "density": 0.2, "n_control": 1, "seed": 4, "range_noise_m": 0.0}
    a = simulate_mission(**kw)
    b = simulate_mission(origin=(500000.0, 5000000.0), **kw)
    off = np.array([500000.0, 5000000.0, 0.0])
    np.testing.assert_allclose(b.mission.strips[0].xyz - off, a.mission.strips[0].xyz,
                               atol=1e-6)
    np.testing.assert_allclose(b.mission.trajectory.xyz - off, a.mission.trajectory.xyz,
                               atol=1e-6)
    assert b.mission.control is not None and a.mission.control is not None
    np.testing.assert_allclose(b.mission.control.xyz - off, a.mission.control.xyz, atol=1e-6)
    assert b.lines[0]["start"] == pytest.approx((500000.0, 4999920.0))
    x, y = b.mission.control.xyz[0, :2]
    assert b.terrain.height(x, y) == pytest.approx(b.mission.control.xyz[0, 2])


def test_trajectory_noise_only_on_samples():
    line = {"id": 1, "start": (0.0, -60.0), "end": (0.0, 60.0), "height": 600.0}
    kw: dict[str, Any] = {"lines": [line],
                          "density": 0.1, "n_control": 0, "seed": 4}
    a = simulate_mission(**kw)
    b = simulate_mission(trajectory_noise_m=0.1, **kw)
    d = b.mission.trajectory.xyz - a.mission.trajectory.xyz
    assert 0.07 < d.std() < 0.13
    np.testing.assert_allclose(np.diff(a.mission.trajectory.t), 1 / 50.0, atol=1e-6)


def test_a_crosswind_crabs_the_sensor_into_the_wind_and_the_points_stay_true() -> None:
    """The heading of the sensor is the track's plus the crab, opposite on opposite lines;
    the system georeferences with it, so without biases the points are still the true
    points, while the trajectory keeps flying the track."""
    lines = [{"id": 1, "start": (0.0, -100.0), "end": (0.0, 100.0), "height": 1150.0},
             {"id": 2, "start": (0.0, 100.0), "end": (0.0, -100.0), "height": 1150.0}]
    sim = simulate_mission(lines=lines, biases=ZERO, range_noise_m=0.0, density=0.2,
                           n_control=0, seed=1, wind_mps=(5.0, 0.0))
    crab = math.degrees(math.asin(5.0 / 60.0))
    # flying north with the air moving east: the nose turns west (left, a larger kappa)
    assert [ln["crab_deg"] for ln in sim.lines] == pytest.approx([crab, -crab])
    for strip, true in zip(sim.mission.strips, sim.true_xyz, strict=True):
        np.testing.assert_allclose(strip.xyz, true, rtol=0, atol=1e-6)
    # the scan line is turned with the nose: each return lies on a beam from the firing
    # point (on the track, x = 0, flying north at 60 m/s) whose horizontal part points along
    # the sensor's right axis, (cos kappa, sin kappa): y - y_o = x tan(crab)
    x, y = sim.true_xyz[0][:, 0], sim.true_xyz[0][:, 1]
    t = sim.mission.strips[0].t
    along = y - 60.0 * (t - t[0])
    assert np.ptp(along - x * math.tan(math.radians(crab))) < 1e-4  # (t near 1.7e9 s)
    assert np.ptp(along) > 50.0  # (what no crab would give: 0)
    np.testing.assert_allclose(sim.mission.trajectory.xyz[:, 0], 0.0, atol=1e-9)
    with pytest.raises(ConfigError, match="crosswind"):
        simulate_mission(lines=lines, density=0.2, wind_mps=(40.0, 0.0))


def test_bad_options_raise():
    with pytest.raises(ConfigError):
        simulate_mission(scenario="nope")
    with pytest.raises(ConfigError):
        simulate_mission(biases={"dQ": 1.0})
    with pytest.raises(ConfigError):
        simulate_mission(density=0.0)


# ---------------------------------------------------------------------- terrain and ray casting


def test_flat_terrain():
    t = Terrain((-200, 200, -200, 200), kind="flat", seed=1)
    rng = np.random.default_rng(0)
    x, y = rng.uniform(-300, 300, (2, 1000))
    assert np.all(t.height(x, y) == 0.0)
    np.testing.assert_allclose(t.normal(x, y), np.tile([0.0, 0.0, 1.0], (1000, 1)))
    assert not np.isin(t.surface_class(x, y), [ROOF, TREE]).any()


def test_terrain_normals_match_finite_differences():
    t = Terrain((-400, 400, -400, 400), seed=2)
    rng = np.random.default_rng(1)
    x, y = rng.uniform(-390, 390, (2, 20000))
    n = t.normal(x, y)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-12)
    eps = 1e-4
    gx = (t.height(x + eps, y) - t.height(x - eps, y)) / (2 * eps)
    gy = (t.height(x, y + eps) - t.height(x, y - eps)) / (2 * eps)
    fd = np.column_stack([-gx, -gy, np.ones_like(gx)])
    fd /= np.linalg.norm(fd, axis=1, keepdims=True)
    good = np.abs(gx) + np.abs(gy) < 5.0  # away from walls, ridges and crown edges
    err = np.linalg.norm(n - fd, axis=1)[good]
    assert np.mean(err < 1e-3) > 0.97
    # ground undulates by a few metres
    g = t.ground_height(x, y)
    assert 1.0 < g.max() - g.min() < 12.0
    assert t.n_buildings > 50 and t.n_trees > 20
    assert {b["roof"] for b in t.buildings()} == {"flat", "gable", "hip", "shed"}
    h_above = np.array([b["top"] - b["base"] for b in t.buildings()])
    assert h_above.min() >= 4.0 and h_above.max() < 60.0


def test_ray_caster_finds_first_hit():
    t = Terrain((-300, 300, -300, 300), seed=7)
    rng = np.random.default_rng(3)
    n = 3000
    o = np.column_stack([rng.uniform(-200, 200, n), rng.uniform(-200, 200, n),
                         rng.uniform(300, 1200, n)])
    th = rng.uniform(-0.45, 0.45, n)
    az = rng.uniform(0, 2 * np.pi, n)
    d = np.column_stack([np.sin(th) * np.cos(az), np.sin(th) * np.sin(az), -np.cos(th)])
    hits = cast_rays(t, o, d, block=1000)
    p = hits.xyz
    h = t.height(p[:, 0], p[:, 1])
    w = hits.on_wall
    assert w.any() and (~w).any()
    # on the surface, or on a wall between the ground and the object's top
    assert np.median(np.abs(p[~w, 2] - h[~w])) < 1e-6
    assert np.all(np.abs(p[~w, 2] - h[~w]) < 1e-3)
    g = t.ground_height(p[w, 0], p[w, 1])
    hin = t.height(hits.inside[w, 0], hits.inside[w, 1])
    assert np.all((p[w, 2] >= g - 1e-6) & (p[w, 2] <= hin + 1e-6))
    assert np.all(np.linalg.norm(hits.inside - p, axis=1) < 1e-6)
    # brute force: nothing hit before (1 cm steps over the last 60 m); a ray may clip a roof
    # corner by less than the 0.5 m march step, which must stay rare
    steps = np.arange(-60.0, -1e-3, 0.01)
    missed = 0
    for i in range(n):
        q = o[i] + (hits.t[i] + steps)[:, None] * d[i]
        if np.any(q[:, 2] < t.height(q[:, 0], q[:, 1]) - 1e-9):
            missed += 1
    assert missed <= 0.005 * n
