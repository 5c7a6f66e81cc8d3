"""Unit tests of the radiometric model (core.radiometry), the grid normals (core.normals) and
the small pieces of the correction pipeline that do not need a mission."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from lidarcal_ros.core.config import FlightConfig
from lidarcal_ros.core.georeferencing.local_trajectory import (
    TrajectoryWindow,
    covered_by_trajectory,
)
from lidarcal_ros.core.mission import Trajectory
from lidarcal_ros.core.normals import strip_normals as strip_normals_module
from lidarcal_ros.core.normals.grid_normals import (
    CELL_SPACINGS,
    GridNormals,
    cell_size,
    grid_normals,
)
from lidarcal_ros.core.normals.grid_planes import smallest_eigen
from lidarcal_ros.core.normals.strip_normals import StripNormals
from lidarcal_ros.core.radiometry import (
    PowerModel,
    RadiometricModel,
    atmospheric_alpha,
    constant_from_target,
    cos_incidence,
    extinction_coefficient,
    kim_q,
    power_ratio,
    rayleigh_alpha,
    two_way_transmittance,
)
from lidarcal_ros.errors import ConfigError, TrajectoryError
from lidarcal_ros.io.survey.las_writer import adjusted_gps_to_unix, unix_to_adjusted_gps
from lidarcal_ros.pipeline.correction.corrected_cloud import (
    ADDED_FIELDS,
    CloudTally,
    CorrectedColumns,
    build_corrected,
    corrected_dtype,
)

# ---------------------------------------------------------------------- atmosphere


@pytest.mark.parametrize(("visibility", "q"), [
    (80.0, 1.6), (50.0, 1.3), (48.3, 1.3), (6.0, 0.16 * 6.0 + 0.34), (3.0, 0.16 * 3.0 + 0.34),
    (0.8, 0.3), (0.4, 0.0),
])
def test_kim_q_branches(visibility: float, q: float) -> None:
    assert kim_q(visibility) == pytest.approx(q)


def test_kim_alpha_values() -> None:
    # The paper's day: visibility 48.3 km at 1064 nm.
    expected = 3.912 / 48.3 * (1064.0 / 550.0) ** -1.3 / 1000.0
    assert atmospheric_alpha(48.3, 1064.0) == pytest.approx(expected, rel=1e-12)
    assert atmospheric_alpha(48.3, 1064.0) == pytest.approx(3.435e-5, rel=1e-3)
    # At 550 nm Koschmieder: 3.912 / V whatever q.
    assert atmospheric_alpha(10.0, 550.0) == pytest.approx(3.912e-4, rel=1e-12)
    with pytest.raises(ConfigError, match="visibility"):
        atmospheric_alpha(0.0)


def test_temperature_and_pressure_rescale_the_molecular_part() -> None:
    # Standard air: Kim alone.
    assert extinction_coefficient(48.3, 1064.0, 15.0, 101.325) == pytest.approx(
        atmospheric_alpha(48.3, 1064.0), rel=1e-12)
    assert rayleigh_alpha(550.0) == pytest.approx(1.162e-5, rel=1e-9)
    assert rayleigh_alpha(1100.0) == pytest.approx(1.162e-5 / 16.0, rel=1e-9)
    # Warmer, thinner air extinguishes less; the effect is tiny at 1064 nm.
    hot = extinction_coefficient(48.3, 1064.0, 29.8, 101.81)
    cold = extinction_coefficient(48.3, 1064.0, -20.0, 101.81)
    std = atmospheric_alpha(48.3, 1064.0)
    assert hot < std < cold
    density = (101.81 / 101.325) * (288.15 / (29.8 + 273.15))
    assert hot - std == pytest.approx(rayleigh_alpha(1064.0) * (density - 1.0), rel=1e-9)
    assert abs(hot - std) < 1e-7  # per metre: below 1e-4 per km


def test_two_way_transmittance() -> None:
    alpha = 3.435e-5
    eta = two_way_transmittance(np.array([0.0, 1000.0, 1150.0]), alpha)
    np.testing.assert_allclose(eta, np.exp(-2 * alpha * np.array([0.0, 1000.0, 1150.0])))
    assert 0.92 < eta[2] < 0.93


def test_power_ratio() -> None:
    assert power_ratio("constant", 140e3, 70e3) == 1.0
    assert power_ratio("pulse_rate", 140e3, 70e3) == pytest.approx(2.0)
    with pytest.raises(ConfigError, match="power_model"):
        power_ratio("laser", 1.0, 1.0)


# ---------------------------------------------------------------------- reflectance


def test_reflectance_undoes_range_atmosphere_and_incidence() -> None:
    model = RadiometricModel(reference_range_m=1000.0)
    alpha = model.alpha_per_m
    rng = np.random.default_rng(1)
    rho = rng.uniform(0.1, 0.6, 1000)
    r = rng.uniform(500.0, 1300.0, 1000)
    cos_t = rng.uniform(0.2, 1.0, 1000)
    intensity = 1e10 * rho * cos_t * np.exp(-2 * alpha * r) / r**2
    out, grazing = model.reflectance(intensity, r, cos_t)
    assert out.dtype == np.float32
    assert not grazing.any()
    np.testing.assert_allclose(out, 1e10 / 1000.0**2 * rho, rtol=1e-6)


def test_range_normalisation_to_the_reference_range() -> None:
    model = RadiometricModel(reference_range_m=1000.0, visibility_km=500.0)
    # A target at the reference range, normal incidence: reflectance = intensity / eta(r_ref).
    out, _ = model.reflectance(np.array([1000.0]), np.array([1000.0]), np.array([1.0]))
    eta_ref = two_way_transmittance(np.asarray(1000.0), model.alpha_per_m)
    assert out[0] == pytest.approx(1000.0 / eta_ref)
    # Twice as far: four times the normalisation.
    far, _ = model.reflectance(np.array([1000.0]), np.array([2000.0]), np.array([1.0]))
    ratio = far[0] / out[0]
    assert ratio == pytest.approx(4.0 * math.exp(2 * model.alpha_per_m * 1000.0), rel=1e-6)


def test_the_calibration_constant_makes_reflectance_the_lambertian_one() -> None:
    """``C``: the intensity of a reflectance-1 Lambertian target at the reference range,
    normal incidence, clear air. A radar-equation intensity of known reflectance then reads
    back as that reflectance, whatever the range and incidence; without ``C`` the same
    points read as the intensity at the reference range (intensity units)."""
    k = 1e10  # I = k rho cos(theta) eta(r) / r^2
    relative = RadiometricModel(reference_range_m=800.0)
    absolute = relative.with_constant(k / 800.0**2)
    rng = np.random.default_rng(5)
    rho = rng.uniform(0.05, 0.9, 500)
    r = rng.uniform(300.0, 2500.0, 500)
    cos_t = rng.uniform(0.3, 1.0, 500)
    intensity = k * rho * cos_t * np.exp(-2 * relative.alpha_per_m * r) / r**2
    np.testing.assert_allclose(absolute.reflectance(intensity, r, cos_t)[0], rho, rtol=1e-5)
    np.testing.assert_allclose(relative.reflectance(intensity, r, cos_t)[0],
                               rho * k / 800.0**2, rtol=1e-5)
    assert absolute.absolute and not relative.absolute
    assert absolute.unit == "1" and relative.unit == "intensity units"
    assert "Lambertian reflectance" in absolute.meaning and "15625" in absolute.meaning
    assert "relative" in relative.meaning and "800 m" in relative.meaning
    for model in (relative, absolute, RadiometricModel(reference_range_m=1e5)):
        assert len(model.las_description) <= 32
    assert relative.las_description == "I at 800 m, 0 deg incidence"
    with pytest.raises(ConfigError, match="calibration_constant"):
        RadiometricModel(calibration_constant=-1.0)
    cfg = FlightConfig().with_values(radiometry__calibration_constant=2500.0)
    assert RadiometricModel.from_config(cfg).calibration_constant == 2500.0


def test_constant_from_a_reference_target() -> None:
    """The median of the target's relative reflectance over its known reflectance: a few
    points of another surface (its edge) do not move it."""
    rng = np.random.default_rng(6)
    target = 0.3 * 12_000.0 * (1.0 + 0.02 * rng.standard_normal(1000))
    edge = np.full(100, 0.9 * 12_000.0)
    values = np.concatenate([target, edge, [np.nan, -1.0]])
    assert constant_from_target(values, 0.3) == pytest.approx(12_000.0, rel=0.01)
    with pytest.raises(ConfigError, match="no point"):
        constant_from_target(np.array([np.nan]), 0.3)
    with pytest.raises(ConfigError, match="reference_target_reflectance"):
        constant_from_target(values, 0.0)


def test_reference_target_configuration() -> None:
    from lidarcal_ros.core.config import parse_target_box

    assert parse_target_box("10, 20.5,30,40") == (10.0, 20.5, 30.0, 40.0)
    for bad, reason in (("1,2,3", "xmin,ymin,xmax,ymax"), ("a,b,c,d", "xmin,ymin,xmax,ymax"),
                        ("3,2,1,4", "empty box")):
        with pytest.raises(ConfigError, match=reason):
            parse_target_box(bad)
    with pytest.raises(ConfigError, match="go together"):
        FlightConfig.from_mapping({"radiometry.reference_target": "0,0,10,10"})
    with pytest.raises(ConfigError, match="empty box"):
        FlightConfig.from_mapping({"radiometry.reference_target": "0,0,0,10",
                                   "radiometry.reference_target_reflectance": 0.4})
    ok = FlightConfig.from_mapping({"radiometry.reference_target": "0,0,10,10",
                                    "radiometry.reference_target_reflectance": 0.4})
    assert ok["radiometry.reference_target_reflectance"] == 0.4


def test_grazing_incidence_is_clamped_and_flagged() -> None:
    model = RadiometricModel(min_cos_incidence=0.1, uncertain_incidence_max_deg=60.0)
    cos_t = np.array([1.0, 0.1, 0.05, 0.0, np.nan])
    out, grazing = model.reflectance(np.ones(5), np.full(5, 1000.0), cos_t)
    assert grazing.tolist() == [False, False, True, True, False]
    assert np.isfinite(out[:4]).all()
    # Exactly at the clamp: divided by 0.1. Beyond it the normal is doubtful: the incidence
    # term is bounded at 60 deg (factor 2), never divided by a cosine below the clamp.
    assert out[1] == pytest.approx(10.0 * out[0], rel=1e-6)
    assert out[2] == out[3] == pytest.approx(2.0 * out[0], rel=1e-6)
    assert np.isnan(out[4])
    # A bound at or below the clamp's angle leaves the clamp in force.
    steep = RadiometricModel(min_cos_incidence=0.1, uncertain_incidence_max_deg=89.0)
    out2, _ = steep.reflectance(np.ones(2), np.full(2, 1000.0), np.array([1.0, 0.0]))
    assert out2[1] == pytest.approx(10.0 * out2[0], rel=1e-6)


def test_uncertain_normals_bound_the_incidence_term() -> None:
    model = RadiometricModel(uncertain_incidence_max_deg=60.0)
    cos_t = np.array([0.9, 0.3, 0.3, np.nan])
    uncertain = np.array([True, True, False, True])
    out, grazing = model.reflectance(np.ones(4), np.full(4, 1000.0), cos_t,
                                     uncertain=uncertain)
    plain, _ = model.reflectance(np.ones(4), np.full(4, 1000.0), cos_t)
    assert not grazing.any()
    assert out[0] == plain[0]  # below the bound: unchanged
    assert out[1] == pytest.approx(plain[1] * 0.3 / 0.5, rel=1e-6)  # cos 0.3 -> cos 60 deg
    assert out[2] == plain[2]  # trusted normal: the full correction
    assert np.isnan(out[3])
    with pytest.raises(ConfigError, match="uncertain_incidence_max_deg"):
        RadiometricModel(uncertain_incidence_max_deg=90.0)


def test_pulse_rate_power_model() -> None:
    base = RadiometricModel(power_model=PowerModel.CONSTANT, pulse_rate_hz=140e3)
    prf = RadiometricModel(power_model=PowerModel.PULSE_RATE, pulse_rate_hz=140e3,
                           reference_pulse_rate_hz=70e3)
    args = (np.array([100.0]), np.array([1000.0]), np.array([1.0]))
    assert prf.reflectance(*args)[0][0] == pytest.approx(2.0 * base.reflectance(*args)[0][0])


def test_model_from_flight_configuration() -> None:
    cfg = FlightConfig().with_values(atmosphere__visibility_km=20.0,
                                     radiometry__reference_range_m=800.0)
    model = RadiometricModel.from_config(cfg)
    assert model.visibility_km == 20.0
    assert model.reference_range_m == 800.0
    assert model.wavelength_nm == 1064.0
    assert model.min_cos_incidence == 0.1
    with pytest.raises(ConfigError):
        RadiometricModel(min_cos_incidence=0.0)


def test_cos_incidence_is_orientation_free() -> None:
    n = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    l = np.array([[0.0, 0.6, -0.8], [0.0, 0.6, -0.8], [0.0, 0.6, -0.8]])
    np.testing.assert_allclose(cos_incidence(n, l), [0.8, 0.8, 0.0])


# ---------------------------------------------------------------------- normals


def test_smallest_eigen_matches_numpy() -> None:
    rng = np.random.default_rng(2)
    a = rng.normal(size=(500, 3, 3))
    c = a @ np.transpose(a, (0, 2, 1))
    lam_min, lam_mid, vec, ok = smallest_eigen(c[:, 0, 0], c[:, 0, 1], c[:, 0, 2],
                                               c[:, 1, 1], c[:, 1, 2], c[:, 2, 2])
    w, v = np.linalg.eigh(c)
    assert ok.all()
    np.testing.assert_allclose(lam_min, w[:, 0], atol=1e-9)
    np.testing.assert_allclose(lam_mid, w[:, 1], atol=1e-9)
    np.testing.assert_allclose(np.abs(np.einsum("ij,ij->i", vec, v[:, :, 0])), 1.0, atol=1e-6)
    assert (vec[:, 2] >= 0).all()


def _scan_pattern(n_sweeps: int = 120, per_sweep: int = 400, swath: float = 400.0,
                  spacing_along: float = 1.2) -> tuple[np.ndarray, np.ndarray]:
    """A zig-zag scan over the plane z = 0: (u, v) in a north-flying frame, and times."""
    k = np.arange(n_sweeps * per_sweep)
    sweep, pos = np.divmod(k, per_sweep)
    frac = np.where(sweep % 2 == 0, pos / per_sweep, 1.0 - pos / per_sweep)
    v = (frac - 0.5) * swath
    u = (k / per_sweep) * spacing_along
    return np.column_stack([v, u]), k * 1e-5


def test_plane_normals_of_any_orientation() -> None:
    xy, t = _scan_pattern()
    rng = np.random.default_rng(3)
    for normal in ([0.3, -0.2, 1.0], [0.0, 0.0, 1.0], [-0.7, 0.5, 1.0]):
        nt = np.asarray(normal) / np.linalg.norm(normal)
        z = -(nt[0] * xy[:, 0] + nt[1] * xy[:, 1]) / nt[2] + rng.normal(0, 0.02, len(t))
        xyz = np.column_stack([xy, z])
        g = grid_normals(xyz, 0.0, t=t)
        assert g.valid.mean() > 0.995  # the first and last sweeps are a V, not a plane
        err = np.degrees(np.arccos(np.clip(g.normals[g.valid] @ nt, -1, 1)))
        assert np.median(err) < 1.0
        assert np.percentile(err, 99) < 5.0


def test_cells_follow_the_scan_pattern() -> None:
    # 0.5 m between pulses across, 1.5 m between sweeps along: rectangular cells, of 1.5
    # spacings where two would exceed a metre, else of two up to a metre.
    xy, t = _scan_pattern(n_sweeps=60, per_sweep=400, swath=200.0, spacing_along=1.5)
    xyz = np.column_stack([xy, np.zeros(len(t))])
    along, across = cell_size(xyz, 0.0, t)
    assert along == pytest.approx(1.5 * 1.5, rel=0.1)
    assert across == pytest.approx(1.0, rel=0.1)
    # Dense (0.1 m across, 0.3 m along): two spacings each.
    along, across = cell_size(xyz * 0.2, 0.0, t)
    assert along == pytest.approx(CELL_SPACINGS * 0.3, rel=0.1)
    assert across == pytest.approx(CELL_SPACINGS * 0.1, rel=0.1)
    # Without times the cell is square.
    sq = cell_size(xyz, 0.0)
    assert sq[0] == sq[1]


def test_gable_roof_keeps_the_ridge_sharp() -> None:
    xy, t = _scan_pattern(swath=200.0, spacing_along=1.0, per_sweep=200)
    x = xy[:, 0]
    rng = np.random.default_rng(4)
    z = 10.0 - 0.5 * np.abs(x) + rng.normal(0, 0.02, len(t))
    g = grid_normals(np.column_stack([xy, z]), 0.0, t=t)
    truth = np.column_stack([0.5 * np.sign(x), np.zeros_like(x), np.ones_like(x)]) / math.sqrt(1.25)
    err = np.degrees(np.arccos(np.clip(np.sum(g.normals * truth, axis=1), -1, 1)))
    assert g.valid.mean() > 0.99
    far = (np.abs(x) > 2.0 * max(g.cell_m)) & g.valid
    assert np.percentile(err[far], 99) < 3.0
    # Most points beside the ridge still take a block on their own side.
    near = (np.abs(x) > 0.5 * g.cell_m[1]) & ~far & g.valid
    assert np.mean(err[near] < 5.0) > 0.6


def test_degenerate_neighbourhoods_get_no_normal() -> None:
    # Points on a single line: no plane.
    x = np.linspace(0, 100, 500)
    xyz = np.column_stack([x, np.zeros_like(x), np.zeros_like(x)])
    g = grid_normals(xyz, 0.0, cell_m=1.0)
    assert not g.valid.any()
    assert np.isnan(g.normals).all()
    # Non-finite points are ignored.
    xy, t = _scan_pattern(n_sweeps=20)
    xyz = np.column_stack([xy, np.zeros(len(t))])
    xyz[5] = np.nan
    g = grid_normals(xyz, 0.0, t=t)
    assert not g.valid[5]
    assert g.valid.mean() > 0.98


def test_groups_are_never_neighbours() -> None:
    xy, t = _scan_pattern(n_sweeps=40)
    a = np.column_stack([xy, np.zeros(len(t))])
    b = np.column_stack([xy + 0.3, 0.5 * xy[:, 0] + 3.0])  # a slope through the same area
    xyz = np.concatenate([a, b])
    group = np.repeat([1, 2], len(t))
    g = grid_normals(xyz, 0.0, cell_m=(1.8, 1.8), group=group)
    flat = g.normals[:len(t)][g.valid[:len(t)]]
    assert np.median(flat[:, 2]) > 0.9999
    slope = g.normals[len(t):][g.valid[len(t):]]
    np.testing.assert_allclose(np.median(slope, axis=0), [-0.5 / math.sqrt(1.25), 0.0,
                                                          1 / math.sqrt(1.25)], atol=1e-3)


# ---------------------------------------------------------------------- pipeline pieces


def test_coverage_rule_matches_laser_geometry() -> None:
    from lidarcal_ros.core.georeferencing.local_trajectory import laser_geometry

    tt = np.concatenate([np.arange(0.0, 10.0, 0.02), np.arange(12.0, 20.0, 0.02)])
    traj = Trajectory(tt, np.column_stack([np.zeros_like(tt), 60.0 * tt, np.full_like(tt, 1e3)]))
    t = np.linspace(-1.0, 21.0, 2000)
    cov = covered_by_trajectory(t, traj, window=TrajectoryWindow(window_s=0.5))
    assert not cov[(t > 10.5) & (t < 11.5)].any()
    assert not cov[t < 0].any() and not cov[t > 19.98].any()
    assert cov[(t > 0.1) & (t < 9.9)].all()
    xyz = np.column_stack([np.full_like(t, 5.0), 60.0 * t, np.zeros_like(t)])
    laser_geometry(t[cov], xyz[cov], traj)  # does not raise
    with pytest.raises(TrajectoryError):
        laser_geometry(t[~cov][:1], xyz[~cov][:1], traj)
    # The fast path (no gap at all) agrees with the point-by-point rule.
    inner = t[(t > 1.0) & (t < 9.0)]
    assert covered_by_trajectory(inner, traj).all()


def test_served_points_are_covered_finite_and_a_metre_below_the_trajectory() -> None:
    from lidarcal_ros.core.georeferencing.local_trajectory import (
        laser_geometry,
        served_by_trajectory,
    )

    tt = np.arange(0.0, 10.0, 0.02)
    climb = 1000.0 + 10.0 * tt  # climbing at 10 m/s
    traj = Trajectory(tt, np.column_stack([np.zeros_like(tt), 60.0 * tt, climb]))
    t = np.linspace(1.0, 9.0, 9)
    z = np.zeros_like(t)
    z[1] = 1000.0 + 10.0 * t[1] - 0.5  # half a metre below the aircraft
    z[2] = 1000.0 + 10.0 * t[2] + 30.0  # above it
    z[3] = np.nan
    z[4] = 1000.0 + 10.0 * t[4] - 1.5
    xyz = np.column_stack([np.full_like(t, 100.0), 60.0 * t, z])
    t[5] = np.nan
    served = served_by_trajectory(t, xyz, traj)
    assert served.tolist() == [True, False, False, False, True, False, True, True, True]
    laser_geometry(t[served], xyz[served], traj)  # does not raise
    with pytest.raises(TrajectoryError, match="not below"):
        laser_geometry(t[2:3], xyz[2:3], traj)


def test_corrected_dtype_keeps_input_layout() -> None:
    dt = np.dtype({"names": ["x", "y", "z", "t", "intensity", "reflectance"],
                   "formats": ["<f4", "<f4", "<f4", "<f8", "<u2", "<f8"],
                   "offsets": [0, 4, 8, 16, 24, 32], "itemsize": 48})
    out = corrected_dtype(dt)
    names = out.names or ()
    assert names[:5] == ("x", "y", "z", "t", "intensity")
    assert [n for n, _ in ADDED_FIELDS] == list(names[5:])
    assert out.fields is not None
    assert out.fields["x"][1] == 0 and out.fields["t"][1] == 16
    assert out.fields["reflectance"][0] == np.dtype("<f4")
    assert out.fields["reflectance"][1] >= 48


_ODD_LAYOUT = np.dtype({"names": ["x", "y", "z", "t", "intensity"],
                        "formats": ["<f8", "<f8", "<f8", "<f8", "u1"],
                        "offsets": [0, 8, 16, 24, 33], "itemsize": 35})  # odd size, a hole
_FLOAT32_LAYOUT = np.dtype({"names": ["x", "y", "z", "t", "range", "intensity"],
                            "formats": ["<f4", "<f4", "<f4", "<f8", "<f8", "<u2"],
                            "offsets": [0, 4, 8, 16, 24, 34], "itemsize": 44})
_PACKED_LAYOUT = np.dtype([("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("t", "<f8"),
                           ("intensity", "<f4"), ("strip_id", "<u2")], align=True)


@pytest.mark.parametrize("layout", [_ODD_LAYOUT, _FLOAT32_LAYOUT, _PACKED_LAYOUT],
                         ids=["odd-size", "float32-xyz-and-old-range", "sensor-layout"])
def test_a_corrected_cloud_built_in_a_used_buffer_has_the_bytes_of_a_new_one(
        layout: np.dtype) -> None:
    """Building into a buffer that held other bytes (a shared-memory ring) writes every
    byte: the input's, the added fields' and zeros in the gaps between them; the row-wise
    compiled pass (4-byte rows) and numpy's field passes (other rows) give the same."""
    n = 50
    rng = np.random.default_rng(1)
    raw = rng.integers(0, 256, n * layout.itemsize, dtype=np.uint8)  # holes hold bytes too
    pts = raw.view(layout)
    xyz = rng.normal(size=(n, 3))
    range_, incidence, scan_angle, reflectance = (rng.random(n).astype(np.float32)
                                                  for _ in range(4))
    xyz[[3, 7], 1] = np.nan  # (not corrected: kept as delivered)
    res = CorrectedColumns(xyz, range_, incidence, scan_angle, reflectance,
                           rng.integers(0, 32, n).astype(np.uint8))
    # The expected bytes, spelt out: input row, zeros, then each field written.
    dt = corrected_dtype(layout)
    assert dt.fields is not None  # a structured dtype
    expected = np.zeros(n * dt.itemsize, dtype=np.uint8).reshape(n, dt.itemsize)
    expected[:, :layout.itemsize] = raw.reshape(n, layout.itemsize)
    ex = expected.reshape(-1).view(dt)
    for i, axis in enumerate("xyz"):
        ex[axis] = res.xyz[:, i]
    for name, column in (("reflectance", res.reflectance), ("range", res.range),
                         ("incidence", res.incidence), ("scan_angle", res.scan_angle),
                         ("correction_flags", res.flags)):
        ex[name] = column
    fresh = build_corrected(pts, res)
    assert fresh.tobytes() == expected.tobytes()
    used = np.full(n * dt.itemsize, 0xAB, dtype=np.uint8).view(dt)
    tally = CloudTally.empty()
    built = build_corrected(pts, res, out=used, tally=tally)
    assert built is used
    assert used.tobytes() == expected.tobytes()
    # counted on the way: the flag bytes, and the two points that make it not dense
    np.testing.assert_array_equal(tally.counts[:256], np.bincount(res.flags, minlength=256))
    assert tally.points == n and tally.counts[256] == 2 and not tally.dense
    for mask in (1, 2, 16, 31):
        assert tally.flagged(mask) == np.count_nonzero(res.flags & mask)
    # Rows 10:40 of the columns, as the stream corrector builds a cloud of a batch.
    part_tally = CloudTally.empty()
    part = build_corrected(pts[:30], res, 10, 40, tally=part_tally)
    assert part_tally.points == 30 and part_tally.dense
    assert (part_tally + tally).points == n + 30
    np.testing.assert_array_equal(part["x"], res.xyz[10:40, 0].astype(dt.fields["x"][0]))
    np.testing.assert_array_equal(part["range"], res.range[10:40])
    np.testing.assert_array_equal(part["t"], pts["t"][:30])
    np.testing.assert_array_equal(part["correction_flags"], res.flags[10:40])
    with pytest.raises(ValueError, match="output"):
        build_corrected(pts, res, out=used[:-1])


def test_las_gps_time_conversion() -> None:
    # 2023-11-14T22:13:20Z: GPS - UTC = 18 s.
    assert unix_to_adjusted_gps(np.array([1.7e9]))[0] == pytest.approx(
        1.7e9 - 315964800 + 18 - 1e9)
    # 2010: 15 leap seconds.
    assert unix_to_adjusted_gps(np.array([1.27e9]))[0] == pytest.approx(
        1.27e9 - 315964800 + 15 - 1e9)
    t = np.array([1.0e9, 1.5e9, 1.7e9 + 0.123456])
    np.testing.assert_allclose(adjusted_gps_to_unix(unix_to_adjusted_gps(t)), t, atol=1e-6)


# ------------------------------------------------------------------ streaming normals
def _gable_strip(seed: int = 5) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A zig-zag strip over a gable roof (ridge along track at x = 0): points, times and
    the true normals."""
    xy, t = _scan_pattern(n_sweeps=120, per_sweep=300, swath=200.0, spacing_along=1.0)
    x = xy[:, 0]
    z = 10.0 - 0.5 * np.abs(x) + np.random.default_rng(seed).normal(0, 0.02, len(t))
    truth = np.column_stack([0.5 * np.sign(x), np.zeros_like(x), np.ones_like(x)])
    return np.column_stack([xy, z]), t, truth / math.sqrt(1.25)


def _p99_error(g: GridNormals, xyz: np.ndarray, truth: np.ndarray) -> float:
    """99th percentile of the normals' error (deg) away from the ridge."""
    err = np.degrees(np.arccos(np.clip(np.sum(g.normals * truth, axis=1), -1, 1)))
    far = (np.abs(xyz[:, 0]) > 2.0 * max(g.cell_m)) & g.valid
    return float(np.percentile(err[far], 99))


def _stream(xyz: np.ndarray, t: np.ndarray, cuts: list[int], *, lookahead: bool = True
            ) -> tuple[GridNormals, StripNormals, list[int]]:
    """Feed a strip to StripNormals in parts; the normals in order, and after which add
    each part came out."""
    sn = StripNormals(lambda _t: 0.0, lookahead=lookahead)
    out: dict[int, GridNormals] = {}
    released_after: list[int] = []
    for k, (a, b) in enumerate(itertools.pairwise([0, *cuts, len(t)])):
        sn.add(k, xyz[a:b], t[a:b])
        for key, g in sn.pop_ready():
            out[int(key)] = g  # type: ignore[call-overload]
            released_after.append(k)
    for key, g in sn.pop_ready(final=True):
        out[int(key)] = g  # type: ignore[call-overload]
        released_after.append(len(cuts))
    assert sorted(out) == list(range(len(cuts) + 1))
    parts = [out[k] for k in range(len(cuts) + 1)]
    rough = [p.rough for p in parts]
    assert all(r is not None for r in rough)
    return (GridNormals(np.concatenate([p.normals for p in parts]),
                        np.concatenate([p.valid for p in parts]), parts[0].cell_m,
                        np.concatenate(rough)),  # type: ignore[arg-type]
            sn, released_after)


def test_stream_normals_do_not_depend_on_the_cut() -> None:
    """With look-ahead, parts of any size give the normals of the whole strip at once."""
    xyz, t, truth = _gable_strip()
    whole, _, _ = _stream(xyz, t, [])
    rng = np.random.default_rng(0)
    cuts = sorted(rng.choice(np.arange(1, len(t)), size=40, replace=False).tolist())
    parts, sn, released = _stream(xyz, t, cuts)
    assert sn.late_points == 0
    both = whole.valid & parts.valid
    assert whole.valid.mean() > 0.99 and (parts.valid == whole.valid).all()
    # (up to the order in which the moment sums were added)
    np.testing.assert_allclose(parts.normals[both], whole.normals[both], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(parts.rough, whole.rough)
    # As accurate as grid_normals over the whole strip at once.
    assert _p99_error(parts, xyz, truth) < _p99_error(grid_normals(xyz, 0.0, t=t), xyz,
                                                      truth) + 0.1
    # Parts wait for the strip's first points (they fix the grid), then only for a few
    # rows of look-ahead, not for the end of the strip.
    assert released[0] < 15 and sum(r < len(cuts) for r in released) > 30


def test_stream_normals_without_lookahead_release_every_part_at_once() -> None:
    xyz, t, truth = _gable_strip()
    cuts = list(range(12_000, len(t), 3000))
    g, _, released = _stream(xyz, t, cuts, lookahead=False)
    # Every part after the grid started comes out with its own add.
    assert released[4:] == list(range(4, len(cuts) + 1))
    assert g.valid.mean() > 0.99
    # The leading rows of each part see the neighbours behind them only.
    assert _p99_error(g, xyz, truth) < _p99_error(grid_normals(xyz, 0.0, t=t), xyz,
                                                  truth) + 1.0


def test_stream_normals_outliers_and_late_points_get_no_normal() -> None:
    xyz, t, _ = _gable_strip()
    xyz = xyz.copy()
    xyz[20_000] = [50.0, 1e6, 10.0]  # 1000 km ahead: must not grow the grid to there
    xyz[20_001] = np.nan
    g, sn, _ = _stream(xyz, t, list(range(5000, len(t), 5000)))
    assert not g.valid[20_000] and not g.valid[20_001]
    assert sn.moment_grid.nbytes < 50e6
    assert g.valid.mean() > 0.99
    # A point far behind the rows kept arrives late: no normal, counted.
    xy, t = _scan_pattern(n_sweeps=400, per_sweep=100, swath=100.0, spacing_along=1.0)
    xyz = np.column_stack([xy, np.zeros(len(t))])
    late = StripNormals(lambda _t: 0.0)
    for a in range(0, len(t) - 2000, 2000):
        late.add(a, xyz[a:a + 2000], t[a:a + 2000])
        late.pop_ready()
    late.add("late", xyz[:1], t[:1])
    late.add("last", xyz[-2000:], t[-2000:])
    out = dict(late.pop_ready(final=True))
    assert late.late_points == 1 and not out["late"].valid[0]
    assert out["last"].valid.mean() > 0.95


def _spinning_strip(revolutions: int, columns: int = 360, seed: int = 7
                    ) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """A spinning 16-beam scanner (its spin axis forward, pitched up 20 deg; beams -15..15
    deg) flying north at 8 m/s, 60 m over a gable roof (ridge along track), one cloud per
    revolution at 10 Hz, returns within 100 m: points, times and the cuts between clouds.
    Each revolution's footprint spans some 50 m along track, from behind the sensor at the
    swath's edges to 40 m ahead; every third revolution has returns within 20 deg of nadir
    only (water at the sides), so its lowest row lies some 7 m ahead of the next one's."""
    rng = np.random.default_rng(seed)
    tilt, h = math.radians(20.0), 60.0
    elev = np.radians(np.arange(-15.0, 16.0, 2.0))[:, None]
    theta = np.linspace(-math.pi / 2, math.pi / 2, columns // 2)[None, :]  # the ground side
    # the beam directions in an (east, north, up) frame of the sensor flying north
    east = np.cos(elev) * np.sin(theta) + 0.0 * elev
    north = np.cos(elev) * np.cos(theta) * math.sin(tilt) + np.sin(elev) * math.cos(tilt)
    down = np.cos(elev) * np.cos(theta) * math.cos(tilt) - np.sin(elev) * math.sin(tilt)
    rng_m = h / np.where(down > 0, down, np.nan)
    keep = rng_m < 100.0
    xyz, t, cuts = [], [], []
    for k in range(revolutions):
        ok = keep & (np.abs(theta) < math.radians(20.0)) if k % 3 == 1 else keep
        tk = k * 0.1 + 0.1 * (theta + math.pi / 2) / math.pi + 0.0 * elev
        x = (rng_m * east)[ok]
        y = (rng_m * north)[ok] + 8.0 * tk[ok]
        order = np.argsort(tk[ok], kind="stable")
        z = 10.0 - 0.5 * np.abs(x) + rng.normal(0, 0.02, x.size)
        xyz.append(np.column_stack([x, y, z])[order])
        t.append(tk[ok][order])
        cuts.append(sum(len(a) for a in t))
    return np.concatenate(xyz), np.concatenate(t), cuts[:-1]


def test_spinning_scanner_clouds_give_the_normals_of_the_whole_strip() -> None:
    """A revolution's points land over some 50 m along track, and a later one's lowest row
    lies rows behind an earlier one's: the lateness allowed follows the parts' row span,
    so every point is binned and each cloud's normals are those of the strip at once."""
    xyz, t, cuts = _spinning_strip(revolutions=500)
    whole, _, _ = _stream(xyz, t, [])
    parts, sn, released = _stream(xyz, t, cuts)
    assert sn.late_points == 0
    assert sn.late_rows > 5  # (the fewest: 2 rows)
    assert whole.valid.mean() > 0.99 and (parts.valid == whole.valid).all()
    both = whole.valid & parts.valid
    np.testing.assert_allclose(parts.normals[both], whole.normals[both], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(parts.rough, whole.rough)
    # released along the strip, some two footprints (14 s) behind, not at its end; the grid
    # holds the rows of some three footprints, not the strip's 450 m
    assert sum(r <= 300 for r in released) > 300 - 150
    rows = (xyz[:, 1].max() - xyz[:, 1].min()) / sn.cell[0]
    assert sn.moment_grid.shape[0] < rows / 2


@pytest.mark.parametrize("widening", [False, True], ids=["steady-swath", "widening-swath"])
def test_a_long_strip_advances_the_grid_in_place_with_the_normals_of_the_whole(
        monkeypatch: pytest.MonkeyPatch, widening: bool) -> None:
    """Over a strip many grids long the grid moves its rows down in the same array (no new
    array per advance) and zeroes rows before reuse: the normals stay those of the strip
    given at once, so no stale sums survive a move. New grids start as garbage (NaN here):
    a row read before it was zeroed would show, also where a widening swath (terrain
    rising towards the aircraft, say) makes the grid grow sideways."""
    monkeypatch.setattr(strip_normals_module, "new_moment_grid",
                        lambda shape: np.full(shape, np.nan))
    xy, t = _scan_pattern(n_sweeps=900, per_sweep=150, swath=150.0, spacing_along=0.5)
    if widening:
        xy[:, 0] *= 1.0 + 1.5 * t / t[-1]
    x = xy[:, 0]
    z = 10.0 - 0.5 * np.abs(x) + np.random.default_rng(8).normal(0, 0.02, len(t))
    xyz = np.column_stack([xy, z])
    whole, _, _ = _stream(xyz, t, [])
    sn = StripNormals(lambda _t: 0.0)
    arrays: set[int] = set()
    out: dict[int, GridNormals] = {}
    cuts = [0, *range(3000, len(t), 3000), len(t)]
    columns = []
    for k, (a, b) in enumerate(itertools.pairwise(cuts)):
        sn.add(k, xyz[a:b], t[a:b])
        arrays.add(id(sn.moment_grid))
        columns.append(sn.moment_grid.shape[1])
        out.update(sn.pop_ready())  # type: ignore[arg-type]
    out.update(sn.pop_ready(final=True))  # type: ignore[arg-type]
    rows_along = int(np.ptp(xy[:, 1]) / sn.cell[0])
    assert rows_along > 4 * sn.moment_grid.shape[0]  # the strip is several grids long
    if widening:
        assert len(set(columns)) >= 3  # the grid widened more than once
    else:
        assert len(arrays) <= 3  # the first grid and its growth to the strip's needs only
    parts = [out[k] for k in range(len(cuts) - 1)]
    normals = np.concatenate([p.normals for p in parts])
    valid = np.concatenate([p.valid for p in parts])
    assert whole.valid.mean() > 0.99 and (valid == whole.valid).all()
    np.testing.assert_allclose(normals[valid], whole.normals[valid], rtol=0, atol=1e-9)
