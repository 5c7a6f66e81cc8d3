"""The simulated UAV payload (core/simulation/uav_payload.py): its points, georeferenced with the
true mounting and the noise-free trajectory, lie on the terrain within the range noise; with the
nominal mounting they miss it by the section 12 columns times the mounting error; the drivers'
layouts, time fields and the flight are as specified."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lidarcal_ros.core.georeferencing.sensor_frame import design_matrix, georeference
from lidarcal_ros.core.simulation.uav_payload import (
    LAYOUTS,
    NANOSECONDS_UINT32,
    UavFlight,
    UavPayloadMission,
    UavPayloadSpec,
    simulate_uav_payload,
)
from lidarcal_ros.errors import ConfigError

#: Light missions: two lines of 60 m with a turn between them, a tenth of the columns.
LIGHT = {"n_lines": 2, "line_length_m": 60.0, "heights_m": (55.0, 80.0)}


@pytest.fixture(scope="module", params=["vlp16", "os1-32"])
def mission(request: pytest.FixtureRequest) -> UavPayloadMission:
    columns = {"vlp16": 120, "os1-32": 64}[request.param]
    return simulate_uav_payload(UavPayloadSpec(layout=request.param, seed=3, columns=columns,
                                               **LIGHT))  # type: ignore[arg-type]


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def test_true_mounting_puts_the_points_on_the_terrain(mission: UavPayloadMission) -> None:
    clouds = mission.clouds
    sigma = mission.scanner.range_noise_m
    geo = georeference(clouds.xyz, clouds.absolute_times(), mission.truth_trajectory,
                       mission.truth_mounting, range_offset=mission.biases[6])
    miss = geo.xyz - mission.truth_xyz
    beam = _unit(np.einsum("nij,nj->ni", geo.rotation, geo.rho))
    along = np.einsum("ij,ij->i", miss, beam)
    across = miss - along[:, None] * beam
    # the range noise along the beam, nothing across it (float32 points, interpolated poses)
    assert abs(np.std(along) / sigma - 1.0) < 0.05
    assert abs(np.mean(along)) < 0.05 * sigma
    assert np.abs(across).max() < 1e-3
    # and the truth is on the terrain: vertical distance of the points off walls
    off_wall = ~mission.on_wall
    x, y, z = geo.xyz[off_wall].T
    dz = z - mission.terrain.height(x, y)
    assert np.median(np.abs(dz)) < sigma
    assert np.mean(np.abs(dz) < 5 * sigma) > 0.995
    truth = mission.truth_xyz[off_wall]
    # (the ray caster bisects along the ray to 1e-6 m: steep crowns make that 0.2 mm in z)
    assert np.abs(truth[:, 2] - mission.terrain.height(truth[:, 0], truth[:, 1])).max() < 1e-3


def test_noise_free_points_are_exact() -> None:
    m = simulate_uav_payload(UavPayloadSpec(layout="vlp16", seed=5, columns=60, range_noise_m=0.0,
                                            **LIGHT))  # type: ignore[arg-type]
    geo = georeference(m.clouds.xyz, m.clouds.absolute_times(), m.truth_trajectory,
                       m.truth_mounting, range_offset=m.biases[6])
    miss = np.linalg.norm(geo.xyz - m.truth_xyz, axis=1)
    assert np.median(miss) < 2e-5 and miss.max() < 5e-4


def test_nominal_mounting_misses_by_the_columns_times_the_error(
        mission: UavPayloadMission) -> None:
    clouds = mission.clouds
    t = clouds.absolute_times()
    true = georeference(clouds.xyz, t, mission.truth_trajectory, mission.truth_mounting,
                        range_offset=mission.biases[6])
    nominal = georeference(clouds.xyz, t, mission.truth_trajectory, mission.nominal)
    moved = nominal.xyz - true.xyz
    expected = np.einsum("nij,j->ni", design_matrix(true), mission.biases)
    # second order: (0.4 deg)^2 at 120 m is 6 mm
    assert np.abs(moved - expected).max() < 0.008
    assert np.median(np.linalg.norm(moved, axis=1)) > 0.2
    x, y, z = nominal.xyz[~mission.on_wall].T
    assert np.median(np.abs(z - mission.terrain.height(x, y))) > 0.05


def test_the_mounting_error_is_tenths_of_a_degree_and_centimetres(
        mission: UavPayloadMission) -> None:
    turn = Rotation.from_matrix(mission.nominal.rotation @ mission.truth_mounting.rotation.T)
    assert 0.1 < math.degrees(turn.magnitude()) < 0.7
    shift = np.linalg.norm(mission.nominal.translation - mission.truth_mounting.translation)
    assert 0.03 < shift < 0.09
    assert 0.005 <= abs(mission.biases[6]) <= 0.02 and mission.biases[7] == 0.0
    # the spin axis along the track, pitched up by the tilt; the scan plane across the track
    axis = mission.nominal.rotation[:, 2]
    assert math.degrees(math.atan2(axis[2], axis[0])) == pytest.approx(20.0)


def test_the_drivers_layouts_and_time_fields(mission: UavPayloadMission) -> None:
    clouds, scanner = mission.clouds, mission.scanner
    assert clouds.xyz.dtype == np.float32 and clouds.ring.dtype == np.uint16
    if scanner.time_units == NANOSECONDS_UINT32:
        assert (clouds.frame_id, clouds.time_field) == ("os_sensor", "t")
        assert clouds.time.dtype == np.dtype(np.uint32)
        assert clouds.time.max() < 100_000_000
    else:
        assert (clouds.frame_id, clouds.time_field) == ("velodyne", "time")
        assert clouds.time.dtype == np.dtype(np.float32)
        assert 0.0 <= clouds.time.min() and clouds.time.max() < 0.1
    np.testing.assert_allclose(np.diff(clouds.stamps), 0.1, atol=1e-6)
    assert np.all(np.diff(clouds.offsets) > 0)
    # each beam at its elevation; the azimuth turning with the firing time, in the spin's sense
    p = clouds.xyz.astype(np.float64)
    elevation = np.degrees(np.arcsin(p[:, 2] / np.linalg.norm(p, axis=1)))
    beams = np.asarray(scanner.elevations_deg)
    assert np.abs(elevation - beams[clouds.ring]).max() < 1e-3
    assert np.unique(clouds.ring).size == beams.size
    scale = 1e-9 if scanner.time_units == NANOSECONDS_UINT32 else 1.0
    azimuth = np.arctan2(p[:, 1], p[:, 0])
    expected = scanner.spin * 2.0 * math.pi * scanner.rate_hz * clouds.time * scale
    turn = np.angle(np.exp(1j * (azimuth - expected)))
    assert np.abs(turn).max() < 1e-5
    # the layouts themselves
    vlp, ouster = LAYOUTS["vlp16"], LAYOUTS["os1-32"]
    assert vlp.elevations_deg == tuple(range(-15, 16, 2)) and vlp.rate_hz == 10.0
    assert len(ouster.elevations_deg) == 32
    assert ouster.elevations_deg[-1] - ouster.elevations_deg[0] == pytest.approx(45.0)


def test_the_flight_and_the_ins(mission: UavPayloadMission) -> None:
    truth, ins = mission.truth_trajectory, mission.trajectory
    np.testing.assert_allclose(np.diff(truth.t), 0.01, atol=1e-6)
    t = mission.clouds.absolute_times()
    assert truth.t[0] < t.min() and t.max() < truth.t[-1]
    # the lines at their heights above the ground; a turn between them
    heights = mission.spec.heights_m
    for line in (0, 1):
        on = mission.line == line
        assert on.sum() > 1000
    flight = UavFlight(mission.spec)
    tau = truth.t - mission.spec.start_time_s
    xyz, attitude = flight.pose(tau)
    np.testing.assert_allclose(xyz, truth.xyz, atol=1e-5)  # stamps at 1.7e9 s: 0.24 us
    for line, height in enumerate(heights):
        on = flight.line_of(tau) == line
        agl = xyz[on, 2] - mission.terrain.ground_height(xyz[on, 0], xyz[on, 1])
        assert abs(np.median(agl) - height) < 5.0
    roll, _, _ = attitude.as_euler("xyz").T
    turning = flight.line_of(tau) == -1
    assert turning.any() and np.degrees(np.abs(roll[turning])).max() > 10.0
    assert np.degrees(np.abs(roll[~turning])).max() < 3.0
    yaw = np.unwrap(attitude.as_euler("zyx")[:, 0])
    assert abs(abs(yaw[-1] - yaw[0]) - math.pi) < 0.1
    # the pose is continuous where segments meet
    for t0 in flight.t0[1:]:
        a, ra = flight.pose(np.array([t0 - 1e-7]))
        b, rb = flight.pose(np.array([t0 + 1e-7]))
        assert np.abs(a - b).max() < 1e-5
        assert (ra.inv() * rb).magnitude()[0] < 1e-6
    # the INS errs by a tactical-grade unit's centimetres and thousandths of a degree
    dpos = ins.xyz - truth.xyz
    assert 0.002 < np.sqrt(np.mean(dpos**2)) < 0.1
    assert ins.orientation is not None and truth.orientation is not None
    datt = (Rotation.from_quat(truth.orientation).inv() * Rotation.from_quat(ins.orientation))
    assert 0.001 < np.degrees(np.sqrt(np.mean(datt.magnitude() ** 2))) < 0.05


def test_deterministic_from_the_seed() -> None:
    spec = UavPayloadSpec(layout="os1-32", seed=7, columns=32, n_lines=1, line_length_m=20.0)
    a, b = simulate_uav_payload(spec), simulate_uav_payload(spec)
    for name in ("xyz", "time", "ring", "stamps", "offsets"):
        np.testing.assert_array_equal(getattr(a.clouds, name), getattr(b.clouds, name))
    np.testing.assert_array_equal(a.trajectory.xyz, b.trajectory.xyz)
    np.testing.assert_array_equal(a.biases, b.biases)
    other = simulate_uav_payload(UavPayloadSpec(layout="os1-32", seed=8, columns=32, n_lines=1,
                                                line_length_m=20.0))
    assert not np.array_equal(a.biases, other.biases)


@pytest.mark.parametrize(("changes", "words"), [
    ({"layout": "hdl64"}, "layout"),
    ({"heights_m": (10.0,)}, "heights_m"),
    ({"columns": 3}, "columns"),
    ({"biases": (0.0,) * 7 + (1e-4,)}, "dS 0"),
    ({"speed_mps": 0.0}, "speed_mps"),
])
def test_a_bad_spec_is_refused(changes: dict[str, object], words: str) -> None:
    with pytest.raises(ConfigError, match=words):
        UavPayloadSpec(**changes)  # type: ignore[arg-type]
