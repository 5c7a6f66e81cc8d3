"""The rigorous model of docs/method.md section 10 (``core.attitude``, ``core.georeferencing``):
every number of the shared ``rigorous_vectors.json``, the interpolation of the attitude, and
which model a strip gets and why."""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np
import pytest
from helpers_missions import MissionFiles, mission_factory  # noqa: F401  (fixture)
from helpers_paths import SHARED

from lidarcal_ros.core.calibration.calibrate import CalibrationSettings
from lidarcal_ros.core.georeferencing.attitude import (
    attitude_from_quaternions,
    body_rotations,
    interpolated_frames,
    normalise_quaternions,
    quaternions_from_attitude,
    quaternions_from_headings,
    slerp,
)
from lidarcal_ros.core.georeferencing.bias_model import (
    boresight_matrix,
    correct_geometry,
    correct_points_exact,
    geometry_design_matrix,
    geometry_normal_rows,
    geometry_offsets,
)
from lidarcal_ros.core.georeferencing.heading import HeadingSource
from lidarcal_ros.core.georeferencing.laser_geometry import (
    LaserGeometry,
    PositioningModel,
    ScannerKind,
    geometry_at,
)
from lidarcal_ros.core.georeferencing.rigorous import (
    GENERAL_QA_SKIPS,
    GENERAL_SKIPS,
    choose_model,
    laser_vector_qa,
    rigorous_geometry,
    strip_geometry,
)
from lidarcal_ros.core.mission import Trajectory
from lidarcal_ros.core.params import PARAMETER_NAMES
from lidarcal_ros.errors import ConfigError, TrajectoryError

VECTORS = SHARED / "vectors" / "rigorous_vectors.json"


@pytest.fixture(scope="module")
def vectors() -> dict[str, Any]:
    if not VECTORS.exists():
        pytest.skip(f"{VECTORS} not available")
    data: dict[str, Any] = json.loads(VECTORS.read_text())
    return data


def _delta(vectors: dict[str, Any]) -> np.ndarray:
    assert vectors["parameter_order"] == list(PARAMETER_NAMES)
    return np.array([vectors["biases"][n] for n in PARAMETER_NAMES])


def _pulse_geometry(pulse: dict[str, Any], point: np.ndarray) -> LaserGeometry:
    """The rigorous geometry of one point fired at a pose held over two samples (so the
    interpolation gives the pose itself)."""
    q = np.tile(pulse["orientation_xyzw"], (2, 1))
    traj = Trajectory(np.array([0.3, 0.7]), np.tile(pulse["position"], (2, 1)), q)
    return rigorous_geometry(np.array([0.5]), point[None, :], traj)


def test_orientation_convention_is_the_vectors_one(vectors: dict[str, Any]) -> None:
    p_body = np.array(vectors["P"])
    for pulse in vectors["pulses"]:
        roll, pitch, kappa = pulse["roll"], pulse["pitch"], pulse["heading_kappa"]
        q = np.array(pulse["orientation_xyzw"])
        cr, sr, cp, sp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
        ck, sk = math.cos(kappa), math.sin(kappa)
        rz = np.array([[ck, -sk, 0], [sk, ck, 0], [0, 0, 1]])
        rx = np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])
        ry = np.array([[cr, 0, sr], [0, 1, 0], [-sr, 0, cr]])
        r_ins = body_rotations(q)[0]
        np.testing.assert_allclose(r_ins, rz @ rx @ ry, atol=1e-12)
        # R(q) P^T, P from the vectors: the body columns right, forward, up
        np.testing.assert_allclose(r_ins @ p_body, body_rotations(q)[0] @ p_body, atol=0)
        got = quaternions_from_attitude(roll, pitch, kappa)[0]
        assert min(np.abs(got - q).max(), np.abs(got + q).max()) < 1e-12
        back = attitude_from_quaternions(q)
        np.testing.assert_allclose([b[0] for b in back], [roll, pitch, kappa], atol=1e-12)


def test_recovered_laser_vector_and_rows(vectors: dict[str, Any]) -> None:
    delta = _delta(vectors)
    for pulse in vectors["pulses"]:
        xb = np.array(pulse["X_biased"])
        g = _pulse_geometry(pulse, xb)
        rec = pulse["recovered"]
        assert g.model == PositioningModel.RIGOROUS
        np.testing.assert_allclose([g.x[0], g.y[0], g.z[0]],  # type: ignore[index]
                                   [rec["x"], rec["y"], rec["z"]], atol=1e-9)
        assert g.range[0] == pytest.approx(rec["r"], abs=1e-9)
        assert g.beta[0] == pytest.approx(rec["beta"], abs=1e-12)
        a = geometry_design_matrix(g)[0]
        np.testing.assert_allclose(a, pulse["A_rows_from_point"], rtol=1e-12, atol=1e-9)
        # rows from the true laser vector: the true point seen from the same pose
        a_true = geometry_design_matrix(geometry_at(np.array([pulse["X_true"]]), g))[0]
        np.testing.assert_allclose(a_true, pulse["A_rows_true"], rtol=1e-12, atol=1e-9)
        # n^T A without the 3 x 8 matrix, and A delta in one pass
        n = np.array([[0.3, -0.2, 0.93]])
        n /= np.linalg.norm(n)
        np.testing.assert_allclose(geometry_normal_rows(n, g)[0], n[0] @ a, atol=1e-9)
        np.testing.assert_allclose(geometry_offsets(delta, g)[0], a @ delta, atol=1e-12)
        # eq. [13] from the point, and its error against the truth
        corrected = correct_geometry(xb[None, :], delta, g)[0]
        np.testing.assert_allclose(corrected, pulse["corrected_from_point"], atol=1e-9)
        error = float(np.max(np.abs(corrected - np.array(pulse["X_true"]))))
        assert error == pytest.approx(pulse["correction_error_m"], abs=1e-9)
        # linearised from the truth
        linear = np.array(pulse["X_true"]) + np.array(pulse["A_rows_true"]) @ delta
        lin_error = float(np.max(np.abs(xb - linear)))
        assert lin_error == pytest.approx(pulse["linearisation_error_m"], abs=1e-9)
        assert lin_error < 2e-4 and error < 2e-4


def test_exact_point_and_its_exact_inverse(vectors: dict[str, Any]) -> None:
    """The biased point of each pulse from its true range and mirror angle (section 10's
    positioning with the exact boresight), and the exact removal of the biases."""
    delta = _delta(vectors)
    rb = boresight_matrix(*delta[3:6])
    for pulse in vectors["pulses"]:
        r_ins = body_rotations(np.array(pulse["orientation_xyzw"]))[0]
        sbeta = (1.0 + delta[7]) * pulse["beta_true"]
        rho = -(pulse["range_true"] + delta[6]) * np.array([math.sin(sbeta), 0.0,
                                                             math.cos(sbeta)])
        xb = np.array(pulse["position"]) + r_ins @ delta[:3] + r_ins @ rb @ rho
        np.testing.assert_allclose(xb, pulse["X_biased"], atol=1e-8)
        g = _pulse_geometry(pulse, xb)
        back = correct_points_exact(xb[None, :], g, delta)[0]
        np.testing.assert_allclose(back, pulse["X_true"], atol=1e-8)


def test_level_pose_reduces_to_the_level_model() -> None:
    """Level poses: R_ins = R_kappa, and the rigorous rows are eq. [8]'s."""
    rng = np.random.default_rng(3)
    kappa = 0.7
    t = np.arange(0.0, 2.0, 0.02)
    xyz_traj = np.column_stack([-60 * t * math.sin(kappa), 60 * t * math.cos(kappa),
                                np.full_like(t, 1000.0)])
    traj = Trajectory(t, xyz_traj, quaternions_from_headings(np.full(t.size, kappa)))
    tp = np.sort(rng.uniform(0.6, 1.4, 50))
    origin = np.column_stack([np.interp(tp, t, xyz_traj[:, k]) for k in range(3)])
    right = np.array([math.cos(kappa), math.sin(kappa), 0.0])
    pts = origin + rng.uniform(-300, 300, (50, 1)) * right + np.array([0, 0, -980.0])
    g = rigorous_geometry(tp, pts, traj)
    from lidarcal_ros.core.georeferencing.bias_model import design_matrix
    level = design_matrix(g.x, g.z, np.full(50, kappa), g.beta)
    np.testing.assert_allclose(geometry_design_matrix(g), level, atol=1e-9)
    assert g.y is not None and np.abs(g.y).max() < 1e-9
    assert np.allclose(g.kappa, kappa)


def test_attitude_interpolation_follows_rough_air_between_samples() -> None:
    """Roll swinging by 4 deg with a 2 s period, pitch 2.5 deg, sampled at 50 Hz: the cubic
    of :func:`interpolated_frames` follows it to 5e-7 rad between samples (0.5 mm at 1 km),
    where slerp misses by 3e-5 rad (3 cm at 1 km); a sample without neighbours is a
    slerp."""
    def truth(tt: np.ndarray) -> np.ndarray:
        return quaternions_from_attitude(np.radians(4.0) * np.sin(np.pi * tt),
                                         np.radians(2.5) * np.cos(2 * np.pi * 0.3 * tt),
                                         0.3 + 0.01 * tt)

    ts = np.arange(0.0, 10.0 + 1e-9, 0.02)
    traj = Trajectory(ts, np.zeros((ts.size, 3)), truth(ts))
    assert traj.orientation is not None
    fine = np.linspace(0.05, 9.95, 3001)
    seg = np.clip(np.searchsorted(ts, fine, side="right") - 1, 0, ts.size - 2)
    want = body_rotations(normalise_quaternions(truth(fine)))

    def angle(a: np.ndarray) -> np.ndarray:
        trace = np.einsum("nij,nij->n", a, want)
        return np.arccos(np.clip(0.5 * (trace - 1.0), -1.0, 1.0))

    _, cubic, _ = interpolated_frames(fine, np.zeros((fine.size, 3)), seg, ts, traj.xyz,
                                      traj.orientation)
    assert angle(cubic).max() < 5e-7
    assert angle(body_rotations(slerp(ts, traj.orientation, fine))).max() > 2e-5
    # the rigorous model's own estimate of its interpolation error
    c = choose_model(traj, 1.0, 9.0)
    assert 1e-8 < c.interpolation_error_rad < 5e-7
    # with every other orientation missing, each segment is a slerp of its two ends
    holes = traj.orientation.copy()
    holes[1::2] = np.nan
    two = Trajectory(ts[:3], np.zeros((3, 3)), traj.orientation[:3])
    assert two.orientation is not None
    _, seg_rot, _ = interpolated_frames(np.array([0.01]), np.zeros((1, 3)),
                                        np.zeros(1, dtype=np.int64), two.t[:2], two.xyz[:2],
                                        two.orientation[:2])
    np.testing.assert_allclose(seg_rot[0], body_rotations(slerp(
        two.t[:2], two.orientation[:2], np.array([0.01])))[0], atol=1e-12)


def _rough_trajectory(rate_hz: float = 50.0, *, full: bool = True) -> Trajectory:
    t = np.arange(0.0, 20.0, 1.0 / rate_hz)
    xyz = np.column_stack([np.zeros_like(t), 60.0 * t, np.full_like(t, 1000.0)])
    q = quaternions_from_attitude(np.radians(4.0) * np.sin(0.9 * t),
                                  np.radians(2.5) * np.sin(0.5 * t + 1), np.radians(5.0))
    return Trajectory(t, xyz, q, full_attitude=full)


def test_model_choice_and_its_reasons() -> None:
    traj = _rough_trajectory()
    c = choose_model(traj, 5.0, 15.0)
    assert c.model == "rigorous" and c.reason == "INS attitude at 50 Hz"
    assert c.interpolation_error_rad < 5e-7
    assert choose_model(traj, 5.0, 15.0, mode=PositioningModel.LEVEL).model == "level"
    assert choose_model(traj, 5.0, 15.0, heading_source=HeadingSource.TRACK).model == "level"
    bare = Trajectory(traj.t, traj.xyz)
    assert choose_model(bare, 5, 15).reason == "the poses carry no orientation"
    with pytest.raises(TrajectoryError, match=r"strip 4: matching\.model is 'rigorous' but "
                       r"the poses carry no orientation"):
        choose_model(bare, 5, 15, mode=PositioningModel.RIGOROUS, source="strip 4")
    levelled = _rough_trajectory(full=False)
    assert "heading only" in choose_model(levelled, 5, 15).reason
    sparse = _rough_trajectory(5.0)
    c = choose_model(sparse, 5, 15)
    assert c.model == "level" and "5.0 Hz" in c.reason and "10 Hz" in c.reason
    with pytest.raises(TrajectoryError, match=r"5\.0 Hz"):
        choose_model(sparse, 5, 15, mode=PositioningModel.RIGOROUS)
    # A NED-like body frame (z down): the body's up axis points down
    ned = Trajectory(traj.t, traj.xyz, quaternions_from_attitude(
        np.full(traj.t.size, math.pi), 0.0, np.radians(5.0)))
    c = choose_model(ned, 5, 15)
    assert c.model == "level" and "not REP-103" in c.reason


def test_laser_vector_qa_sees_a_timing_offset_and_a_wrong_field_of_view() -> None:
    t = np.arange(0.0, 20.0, 0.02)  # rolling by 4 deg (a roll leaves the forward axis)
    traj = Trajectory(t, np.column_stack([np.zeros_like(t), 60.0 * t, np.full_like(t, 1000.0)]),
                      quaternions_from_attitude(np.radians(4.0) * np.sin(0.9 * t), 0.0, 0.0))
    rng = np.random.default_rng(5)
    tp = np.sort(rng.uniform(2.0, 18.0, 4000))
    # points on flat ground at z = 0 under the scan plane of each pulse
    beta = np.radians(24.0) * np.sin(2 * np.pi * 40.0 * tp)
    q = slerp(traj.t, traj.orientation, tp)  # type: ignore[arg-type]
    r_ins = body_rotations(q)
    origin = np.column_stack([np.interp(tp, traj.t, traj.xyz[:, k]) for k in range(3)])
    beam = np.einsum("nij,nj->ni", r_ins, np.column_stack([-np.sin(beta), 0 * beta,
                                                           -np.cos(beta)]))
    pts = origin + beam * (origin[:, 2:3] / -beam[:, 2:3])
    qa = laser_vector_qa(rigorous_geometry(tp, pts, traj), fov_deg=50.0, speed_mps=60.0)
    assert abs(qa.along_median_m) < 1e-6 and qa.along_spread_m < 1e-6
    assert qa.outside_fov == 0.0 and not qa.warnings
    assert qa.scan_max_deg == pytest.approx(24.0, abs=0.1)
    # the points' times 20 ms late: the laser vectors lean 1.2 m back along track
    late = laser_vector_qa(rigorous_geometry(tp + 0.02, pts, traj), fov_deg=50.0,
                           speed_mps=60.0)
    assert late.along_median_m == pytest.approx(-1.2, abs=0.01)
    assert any("timing offset of -20 ms" in w for w in late.warnings)
    narrow = laser_vector_qa(rigorous_geometry(tp, pts, traj), fov_deg=30.0, speed_mps=60.0)
    assert any("beyond the field of view" in w and "body convention" in w
               for w in narrow.warnings)
    # a body frame turned by a quarter turn (y forward read as x forward): the scan lines
    # run along track
    turned = Trajectory(traj.t, traj.xyz, quaternions_from_attitude(
        np.radians(4.0) * np.sin(0.9 * traj.t), 0.0, math.pi / 2))
    wrong = laser_vector_qa(rigorous_geometry(tp, pts, turned), fov_deg=50.0, speed_mps=60.0)
    assert any("spread" in w and "not the scanner's" in w for w in wrong.warnings)


def test_strip_geometry_dispatches_by_model() -> None:
    traj = _rough_trajectory()
    tp = np.linspace(3.0, 17.0, 100)
    pts = np.column_stack([np.linspace(-200, 200, 100), 60 * tp, np.zeros(100)])
    g, c = strip_geometry(tp, pts, traj)
    assert (g.model, c.model) == ("rigorous", "rigorous") and g.rotation is not None
    g, c = strip_geometry(tp, pts, traj, model=PositioningModel.LEVEL)
    assert (g.model, c.model) == ("level", "level") and g.rotation is None


def test_a_general_scanner_skips_the_checks_made_for_a_linear_one() -> None:
    """A general scanner's strips (docs/method.md section 12): a heading off the track (a
    multirotor flying sideways) is no wrong convention, points may lie above the sensor and
    the laser vectors' along-track part is no error; each skipped check is said in words;
    the level model and dS are refused in one line."""
    traj = _rough_trajectory()
    sideways = Trajectory(traj.t, traj.xyz, quaternions_from_attitude(
        np.radians(4.0) * np.sin(0.9 * traj.t), 0.0, np.radians(70.0)))
    assert "disagrees with the track" in choose_model(sideways, 5, 15).reason
    c = choose_model(sideways, 5, 15, mode=PositioningModel.RIGOROUS, scanner=ScannerKind.GENERAL)
    assert c.model == "rigorous" and c.reason == f"INS attitude at 50 Hz; {GENERAL_SKIPS}"
    with pytest.raises(ConfigError, match=r"strip 2: a general scanner's laser vectors need "
                       r"matching\.model 'rigorous', not 'auto'"):
        choose_model(traj, 5, 15, scanner=ScannerKind.GENERAL, source="strip 2")
    tp = np.linspace(3.0, 17.0, 100)
    # a spinning scanner's returns: ahead, behind, and some above the sensor (1000 m up)
    pts = np.column_stack([np.linspace(-200, 200, 100), 60 * tp + np.linspace(-80, 80, 100),
                           np.where(np.arange(100) % 10 == 0, 1020.0, 0.0)])
    with pytest.raises(TrajectoryError, match="not below the trajectory"):
        strip_geometry(tp, pts, traj, model=PositioningModel.RIGOROUS)
    g, c = strip_geometry(tp, pts, traj, model=PositioningModel.RIGOROUS,
                          scanner=ScannerKind.GENERAL)
    assert g.scanner is ScannerKind.GENERAL and g.y is not None and np.ptp(g.y) > 100.0
    assert GENERAL_SKIPS in c.reason
    qa = laser_vector_qa(g, fov_deg=30.0, speed_mps=60.0)
    assert not qa.warnings and qa.skipped == GENERAL_QA_SKIPS
    linear = laser_vector_qa(replace(g, scanner=ScannerKind.LINEAR), fov_deg=30.0,
                             speed_mps=60.0)
    assert any("along track" in w for w in linear.warnings) and not linear.skipped
    with pytest.raises(ConfigError, match=r"dS .* no parameter of a general scanner"):
        CalibrationSettings(scanner=ScannerKind.GENERAL)
    assert "dS" not in CalibrationSettings(scanner=ScannerKind.GENERAL,
                                           solve_for=("dX", "dr")).solve_for


# ---------------------------------------------------------------- what it is for
#: A rough-air mission (the simulator's preset: roll +-4 deg, pitch +-2.5 deg, 1 deg of
#: heading wobble, 5 deg of crab, the INS attitude at 50 Hz) whose attitude the level model
#: gets wrong by several sigmas.
ROUGH = {"density": 0.15, "line_length_m": 600.0, "seed": 3}
TOLERANCE = {"dX": 0.01, "dY": 0.01, "dZ": 0.01, "dr": 0.01, "dS": 1e-5,
             "domega": 1 / 206264.806, "dphi": 1 / 206264.806, "dkappa": 1 / 206264.806}


def _errors(result: Any, biases: dict[str, float]) -> dict[str, tuple[float, float]]:
    """Per estimated parameter: (error, error / sigma)."""
    sol = result.solution
    return {n: (sol.delta[i] - biases[n], (sol.delta[i] - biases[n]) / sol.sigma[i])
            for i, n in enumerate(PARAMETER_NAMES) if n in sol.estimated}


def test_rough_air_needs_the_rigorous_model(
        mission_factory: Callable[..., MissionFiles]) -> None:  # noqa: F811
    """Read back from its bag, a mission flown in rough air calibrates within 3 sigma and
    the issue's tolerances (1 arcsec, 1 cm, 1e-5) with the INS attitude (``auto`` chooses
    the rigorous model), and its corrected points lie on the true surface (median within
    5 mm); the level model puts boresight and range several sigmas off."""
    from lidarcal_ros.core.calibration.calibrate import CalibrationSettings, calibrate
    from lidarcal_ros.core.simulation.flight_path import RoughAir, crosswind_for_crab
    from lidarcal_ros.io.bag.mission_bag import read_mission
    from lidarcal_ros.pipeline.correction.apply import CorrectionSettings, correct_columns

    rough = mission_factory(**ROUGH, rough_air=RoughAir(),
                            wind_mps=crosswind_for_crab(5.0, 60.0))
    mission = read_mission(rough.bag)
    assert mission.trajectory.full_attitude
    rigorous = calibrate(mission, CalibrationSettings())
    assert {c.model for c in rigorous.models.values()} == {"rigorous"}
    assert rigorous.converged
    errors = _errors(rigorous, rough.sim.biases)
    for name, (err, in_sigmas) in errors.items():
        assert abs(err) <= TOLERANCE[name] and abs(in_sigmas) <= 3.0, (name, errors)
    assert not any(qa.warnings for qa in rigorous.laser_qa.values())
    level = calibrate(mission, CalibrationSettings(model=PositioningModel.LEVEL))
    level_errors = _errors(level, rough.sim.biases)
    assert max(abs(s) for _, s in level_errors.values()) > 4.0, level_errors
    # the corrected points, with the rigorous estimate and model
    settings = CorrectionSettings(delta=rigorous.solution.delta, model=PositioningModel.RIGOROUS)
    dz = []
    for strip, truth in zip(mission.strips, rough.sim.true_xyz, strict=True):
        res = correct_columns(strip.xyz, strip.t, strip.intensity, mission.trajectory,
                              settings)
        ok = (res.flags & 1) == 0
        assert ok.mean() > 0.99
        dz.append(res.xyz[ok, 2] - truth[ok, 2])
    assert abs(float(np.median(np.concatenate(dz)))) < 0.005


def test_level_missions_give_the_same_estimate_with_either_model(
        mission_factory: Callable[..., MissionFiles]) -> None:  # noqa: F811
    """A level flight whose poses carry their (crabbed) heading: the rigorous model, asked
    for, agrees with the level one within 0.1 sigma (and ``auto`` takes the level one:
    level poses carry a heading only)."""
    from lidarcal_ros.core.calibration.calibrate import CalibrationSettings, calibrate

    crabbed = mission_factory(density=0.15, line_length_m=600.0, seed=5, wind_mps=(4.0, 0.0),
                              attitude=True)
    mission = crabbed.sim.mission
    assert not mission.trajectory.full_attitude
    auto = calibrate(mission, CalibrationSettings())
    assert {c.model for c in auto.models.values()} == {"level"}
    rigorous = calibrate(mission, CalibrationSettings(model=PositioningModel.RIGOROUS))
    assert {c.model for c in rigorous.models.values()} == {"rigorous"}
    sa, sr = auto.solution, rigorous.solution
    for i, name in enumerate(PARAMETER_NAMES):
        if name in sa.estimated:
            assert abs(sa.delta[i] - sr.delta[i]) <= 0.1 * sa.sigma[i], name
