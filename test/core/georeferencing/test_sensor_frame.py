"""Clouds in the sensor's frame (docs/method.md section 12): the mounting's conventions against
scipy, direct georeferencing against an independent evaluation, the general columns and the
timing column against central differences of the georeferencing itself, the calibrated
mounting's round trip, and the calibration's kernels with a general scanner's laser vectors."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lidarcal_ros.core.georeferencing.attitude import P_BODY
from lidarcal_ros.core.georeferencing.bias_model import (
    add_geometry_normal_rows,
    body_columns,
    boresight_matrix,
    correct_geometry,
    exact_correction,
    geometry_design_matrix,
    geometry_normal_rows,
    geometry_offsets,
)
from lidarcal_ros.core.georeferencing.laser_geometry import (
    LaserGeometry,
    PositioningModel,
    ScannerKind,
)
from lidarcal_ros.core.georeferencing.sensor_frame import (
    Mounting,
    SensorGeoreference,
    biases_between,
    body_rates,
    design_matrix,
    general_columns,
    georeference,
    mounting_from_biases,
    mounting_with_biases,
    point_rates,
    quaternion_from_matrix,
    timing_column,
)
from lidarcal_ros.core.mission import Trajectory
from lidarcal_ros.core.params import N_PARAMETERS, PARAMETER_INDEX
from lidarcal_ros.errors import ConfigError, TrajectoryError

RATE_HZ = 100.0


def _trajectory(rng: np.random.Generator, m: int = 60) -> Trajectory:
    """A wandering body at 100 Hz: positions 70 m up, an attitude of any heading with some
    degrees of roll and pitch turning at up to about a radian per second."""
    t = 1.7e9 + np.arange(m) / RATE_HZ
    xyz = np.cumsum(rng.normal(0.0, 0.08, (m, 3)), axis=0) + np.array([10.0, -20.0, 70.0])
    base = Rotation.from_euler("zyx", [rng.uniform(-np.pi, np.pi), rng.uniform(-0.1, 0.1),
                                       rng.uniform(-0.1, 0.1)])
    wobble = Rotation.from_rotvec(np.cumsum(rng.normal(0.0, 0.01, (m, 3)), axis=0))
    return Trajectory(t, xyz, (base * wobble).as_quat())


def _mounting(rng: np.random.Generator) -> Mounting:
    return Mounting(Rotation.random(random_state=rng).as_matrix(), rng.uniform(-0.3, 0.3, 3))


def _times(rng: np.random.Generator, trajectory: Trajectory, n: int) -> np.ndarray:
    """Times inside segments (not within 10% of a sample: a central difference there would
    straddle the kink of the linear position)."""
    j = rng.integers(2, len(trajectory) - 3, n)
    return trajectory.t[j] + rng.uniform(0.1, 0.9, n) / RATE_HZ


def _points(rng: np.random.Generator, mounting: Mounting, n: int) -> np.ndarray:
    """Sensor-frame points 40-120 m away, below the body's origin whatever the mounting,
    with a forward component (``y != 0`` in the body frame)."""
    body = np.column_stack([rng.uniform(-60, 60, n), rng.uniform(-40, 40, n),
                            rng.uniform(-100, -40, n)])
    return (body - mounting.lever_arm) @ mounting.body_rotation  # P R_bs p = rho


def _scene(seed: int, n: int
           ) -> tuple[Trajectory, Mounting, np.ndarray, np.ndarray, SensorGeoreference]:
    """A trajectory, a mounting, ``n`` points' times and sensor-frame coordinates, and the
    points georeferenced."""
    rng = np.random.default_rng(seed)
    traj = _trajectory(rng)
    mount = _mounting(rng)
    t = _times(rng, traj, n)
    p = _points(rng, mount, n)
    return traj, mount, t, p, georeference(p, t, traj, mount)


# ------------------------------------------------------------------ the mounting

def test_quaternions_are_rep103_xyzw_as_scipy() -> None:
    rng = np.random.default_rng(0)
    rotations = list(Rotation.random(200, random_state=rng))
    # near half turns: Shepperd's other branches (trace < 0)
    rotations += [Rotation.from_rotvec(axis / np.linalg.norm(axis) * (np.pi - 1e-4))
                  for axis in rng.normal(size=(20, 3))]
    for rot in rotations:
        t = rng.normal(size=3)
        mount = Mounting.from_quaternion(t, rot.as_quat())  # scipy's as_quat is (x, y, z, w)
        np.testing.assert_allclose(mount.rotation, rot.as_matrix(), atol=1e-14)
        q = mount.quaternion
        expected = rot.as_quat()
        expected = -expected if expected[3] < 0 else expected
        np.testing.assert_allclose(q, expected, atol=1e-12)
        assert q[3] >= 0.0
        p = rng.normal(size=(4, 3))
        # TF: the transform base_link -> sensor maps sensor points into base_link
        np.testing.assert_allclose(mount.to_base(p), rot.apply(p) + t, atol=1e-12)
    # the sign of q: the same rotation
    q = Rotation.random(random_state=1).as_quat()
    np.testing.assert_allclose(Mounting.from_quaternion([0, 0, 0], -q).rotation,
                               Mounting.from_quaternion([0, 0, 0], q).rotation, atol=1e-15)
    np.testing.assert_allclose(quaternion_from_matrix(np.eye(3)), [0, 0, 0, 1])


def test_a_velodyne_spinning_along_track_in_rep103() -> None:
    """REP-103 spelled out: a sensor whose z (spin) axis points forward and whose x points
    down sees a point 10 m along its x at 10 m below base_link; its y (z cross x) points
    left, base_link's y; a left-handed choice is refused."""
    r = np.column_stack([[0, 0, -1], [0, 1, 0], [1, 0, 0]]).astype(float)  # columns: x, y, z
    mount = Mounting(r, np.array([0.2, 0.0, -0.1]))
    np.testing.assert_allclose(mount.to_base([[10.0, 0, 0]]), np.array([[0.2, 0.0, -10.1]]))
    np.testing.assert_allclose(mount.to_base([[0, 1.0, 0]]), np.array([[0.2, 1.0, -0.1]]))
    with pytest.raises(ConfigError, match="det -1"):
        Mounting(r * [1.0, -1.0, 1.0], np.zeros(3))
    # in method.md's body frame (right, forward, up): the spin axis is forward
    np.testing.assert_allclose(mount.body_rotation @ [0, 0, 1.0], [0, 1.0, 0], atol=1e-15)
    np.testing.assert_allclose(mount.lever_arm, [0.0, 0.2, -0.1])


@pytest.mark.parametrize(("rotation", "translation", "words"), [
    (np.diag([1.0, 1.0, -1.0]), [0, 0, 0], "not a rotation"),
    (np.eye(3) * 1.01, [0, 0, 0], "not a rotation"),
    (np.eye(2), [0, 0, 0], "3x3"),
    (np.eye(3), [0, np.nan, 0], "translation"),
])
def test_a_bad_mounting_is_refused(rotation: np.ndarray, translation: list[float],
                                   words: str) -> None:
    with pytest.raises(ConfigError, match=words):
        Mounting(rotation, np.asarray(translation))


def test_a_zero_quaternion_is_refused() -> None:
    with pytest.raises(ConfigError, match="quaternion"):
        Mounting.from_quaternion([0, 0, 0], [0, 0, 0, 0])


# ------------------------------------------------------------------ georeferencing

def test_georeference_at_the_samples_is_the_pose_applied() -> None:
    """At a sample's time the interpolated pose is the sample's: X = X_mb + R(q) (t + R_bs p),
    evaluated here with scipy."""
    rng = np.random.default_rng(1)
    traj = _trajectory(rng)
    mount = _mounting(rng)
    k = np.arange(3, 50, 5)
    p = rng.normal(0.0, 30.0, (k.size, 3)).astype(np.float32)
    geo = georeference(p, traj.t[k], traj, mount)
    assert traj.orientation is not None
    rot = Rotation.from_quat(traj.orientation[k])
    expected = traj.xyz[k] + rot.apply(mount.translation + p.astype(np.float64) @
                                       mount.rotation.T)
    np.testing.assert_allclose(geo.xyz, expected, atol=1e-9)
    np.testing.assert_allclose(geo.base_rotation, rot.as_matrix(), atol=1e-12)
    # method.md's body frame: X = X_mb + R_ins (P t_bs + rho), R_ins = R_mb P^T
    np.testing.assert_allclose(geo.rotation, rot.as_matrix() @ P_BODY.T, atol=1e-12)
    np.testing.assert_allclose(geo.range, np.linalg.norm(p.astype(np.float64), axis=1))


def test_georeference_refuses_what_it_cannot_place() -> None:
    rng = np.random.default_rng(2)
    traj = _trajectory(rng)
    mount = _mounting(rng)
    with pytest.raises(TrajectoryError, match="outside the trajectory's time span"):
        georeference(np.ones((2, 3)), np.array([traj.t[3], traj.t[-1] + 0.5]), traj, mount)
    flat = Trajectory(traj.t, traj.xyz)
    with pytest.raises(TrajectoryError, match="orientation of base_link"):
        georeference(np.ones((1, 3)), traj.t[3:4], flat, mount)
    with pytest.raises(ConfigError, match="2 points but 1 times"):
        georeference(np.ones((2, 3)), traj.t[3:4], traj, mount)


# ------------------------------------------------------------------ columns

def _delivered(delta: np.ndarray, p_true: np.ndarray, t: np.ndarray, traj: Trajectory,
               true: Mounting) -> np.ndarray:
    """What a system computes whose mounting and range err by ``delta`` (nominal - true):
    the sensor reports the range plus ``dr``, the system uses the nominal mounting."""
    r = np.linalg.norm(p_true, axis=1)
    p_measured = p_true * (1.0 + delta[PARAMETER_INDEX["dr"]] / r)[:, None]
    return georeference(p_measured, t, traj, mounting_with_biases(true, delta)).xyz


@pytest.mark.parametrize("seed", [3, 4, 5])
def test_columns_are_the_derivatives_of_the_georeferencing(seed: int) -> None:
    traj, true, t, p, geo = _scene(seed, 40)
    assert np.abs(geo.rho[:, 1]).min() > 0.0 and np.abs(geo.rho[:, 1]).max() > 20.0
    a = design_matrix(geo)
    for k in range(N_PARAMETERS - 1):  # dS: not a parameter of a general scanner
        eps = np.zeros(N_PARAMETERS)
        eps[k] = 1e-6
        fd = (_delivered(eps, p, t, traj, true) - _delivered(-eps, p, t, traj, true)) / 2e-6
        np.testing.assert_allclose(a[:, :, k], fd, atol=2e-5, err_msg=f"column {k}")
    assert not a[:, :, 7].any()
    # and a bias moves the delivered point by A delta, to first order
    delta = np.array([0.03, -0.04, 0.02, 0.004, -0.005, 0.006, 0.015, 0.0])
    moved = _delivered(delta, p, t, traj, true) - geo.xyz
    linear = np.einsum("nij,j->ni", a, delta)
    second_order = np.abs(delta[3:6]).sum() ** 2 * 120.0 + 0.1 * np.abs(delta[3:6]).sum()
    assert np.abs(moved - linear).max() < second_order
    assert np.abs(moved).max() > 20 * second_order


def test_with_y_zero_the_columns_are_section_10s() -> None:
    rng = np.random.default_rng(6)
    n = 50
    x = rng.uniform(-300, 300, n)
    z = rng.uniform(-1200, -300, n)
    rho = np.column_stack([x, np.zeros(n), z])
    r = np.hypot(x, z)
    beta = np.arctan2(-x, -z)
    old = body_columns(x, z, beta, -x / r, -z / r)
    np.testing.assert_allclose(general_columns(rho, linear_scanner=True), old, atol=1e-12)
    general = general_columns(rho)
    np.testing.assert_allclose(general[:, :, :7], old[:, :, :7], atol=1e-12)
    assert not general[:, :, 7].any()
    # and A = R_ins C as section 10's geometry_design_matrix has it
    rotation = Rotation.random(n, random_state=7).as_matrix()
    origin = rng.normal(size=(n, 3))
    geometry = LaserGeometry(x=x, z=z, kappa=np.zeros(n), beta=beta, origin=origin,
                             rotation=rotation, y=np.zeros(n), model=PositioningModel.RIGOROUS)
    geo = SensorGeoreference(xyz=origin, origin=origin, rotation=rotation, rho=rho,
                             lever_arm=np.zeros(3))
    np.testing.assert_allclose(design_matrix(geo, linear_scanner=True),
                               geometry_design_matrix(geometry), atol=1e-9)


@pytest.mark.parametrize("seed", [8, 9])
def test_timing_column_is_the_derivative_in_time(seed: int) -> None:
    """``dt`` (delivered - true time): the pose looked up ``dt`` late moves the point by
    ``dt (v + w x (X - X_mb))``; central differences of the georeferencing in time."""
    traj, mount, t, p, geo = _scene(seed, 60)
    v, w = body_rates(t, traj)
    column = timing_column(geo, v, w)
    h = 2.0**-14  # s: exact steps at 1.7e9 s, whose float64 spacing is 2.4e-7 s
    fd = (georeference(p, t + h, traj, mount).xyz - georeference(p, t - h, traj, mount).xyz
          ) / (2 * h)
    np.testing.assert_allclose(column, fd, atol=1e-4 * np.abs(column).max())
    # the rotation matters: some 50 m/s at 100 m from rates of about half a rad/s
    assert np.abs(np.cross(w, geo.xyz - geo.origin)).max() > 10.0


# ------------------------------------------------------------------ calibrated mounting

@pytest.mark.parametrize("seed", [10, 11, 12])
def test_calibrated_mounting_round_trip(seed: int) -> None:
    rng = np.random.default_rng(seed)
    true = _mounting(rng)
    delta = np.concatenate([rng.uniform(-0.05, 0.05, 3), np.radians(rng.uniform(-0.5, 0.5, 3)),
                            [rng.uniform(-0.02, 0.02), 0.0]])
    nominal = mounting_with_biases(true, delta)
    assert np.abs(nominal.rotation - true.rotation).max() > 1e-3
    recovered = mounting_from_biases(nominal, delta)
    np.testing.assert_allclose(recovered.rotation, true.rotation, atol=1e-12)
    # and back: the biases between the two mountings (dr, dS no part of a transform)
    np.testing.assert_allclose(biases_between(nominal, true), [*delta[:6], 0.0, 0.0],
                               atol=1e-14)
    np.testing.assert_allclose(recovered.translation, true.translation, atol=1e-12)
    # the biases in method.md's body frame: the lever arm moves by [dX, dY, dZ] there,
    # and the boresight turns the laser vector by R_B = Rz(dkappa) Ry(dphi) Rx(domega)
    np.testing.assert_allclose(nominal.lever_arm - true.lever_arm, delta[:3], atol=1e-15)
    turn = nominal.body_rotation @ true.body_rotation.T
    np.testing.assert_allclose(turn, boresight_matrix(*delta[3:6]), atol=1e-15)
    # the points: the sensor's report georeferenced with the calibrated mounting and r - dr
    traj = _trajectory(rng)
    t = _times(rng, traj, 30)
    p_true = _points(rng, true, 30)
    r = np.linalg.norm(p_true, axis=1)
    p_measured = p_true * (1.0 + delta[PARAMETER_INDEX["dr"]] / r)[:, None]
    truth = georeference(p_true, t, traj, true).xyz
    calibrated = georeference(p_measured, t, traj, recovered,
                              range_offset=delta[PARAMETER_INDEX["dr"]]).xyz
    np.testing.assert_allclose(calibrated, truth, atol=1e-9)
    # with the nominal mounting they miss by decimetres
    assert np.abs(georeference(p_measured, t, traj, nominal).xyz - truth).max() > 0.1


def test_bad_biases_are_refused() -> None:
    with pytest.raises(ConfigError, match="8 finite numbers"):
        mounting_from_biases(Mounting(np.eye(3), np.zeros(3)), [0.0] * 7)


# ------------------------------------------------------------------ the calibration's kernels

def _general_geometry(geo: SensorGeoreference, origin: np.ndarray) -> LaserGeometry:
    """The rigorous model's geometry of georeferenced points seen from ``origin`` (the
    sensor's origin per point), as a general scanner's."""
    rho = np.einsum("nji,nj->ni", geo.rotation, geo.xyz - origin)
    x, y, z = rho.T
    return LaserGeometry(x=x, z=z, kappa=np.zeros(x.size), beta=np.arctan(x / z),
                         origin=origin, rotation=geo.rotation, y=y, model=PositioningModel.RIGOROUS,
                         scanner=ScannerKind.GENERAL)


@pytest.mark.parametrize("seed", [13, 14])
def test_a_general_scanners_rows_and_offsets_are_section_12s(seed: int) -> None:
    """The compiled rows and offsets of the calibration (eq. [11], [13]) with a general laser
    vector are ``n^T R_ins C(rho)`` and ``R_ins C(rho) delta`` of section 12's columns."""
    geo = _scene(seed, 40)[-1]
    origin = geo.xyz - np.einsum("nij,nj->ni", geo.rotation, geo.rho)
    geometry = _general_geometry(geo, origin)
    assert geometry.y is not None
    np.testing.assert_allclose(geometry.y, geo.rho[:, 1], atol=1e-9)
    a = design_matrix(geo)
    np.testing.assert_allclose(geometry_design_matrix(geometry), a, atol=1e-9)
    rng = np.random.default_rng(seed)
    normal = rng.normal(size=(40, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    expected = np.einsum("ni,nik->nk", normal, a)
    np.testing.assert_allclose(geometry_normal_rows(normal, geometry), expected, atol=1e-9)
    rows = np.zeros((40, N_PARAMETERS))
    add_geometry_normal_rows(rows, normal, geometry, np.arange(40))
    np.testing.assert_allclose(rows, expected, atol=1e-9)
    delta = np.array([0.03, -0.04, 0.02, 0.004, -0.005, 0.006, 0.015, 0.0])
    np.testing.assert_allclose(geometry_offsets(delta, geometry), a @ delta, atol=1e-9)
    np.testing.assert_allclose(correct_geometry(geo.xyz, delta, geometry),
                               geo.xyz - a @ delta, atol=1e-9)
    # the y terms are no small matter here: a linear scanner's rows miss by metres
    linear = replace(geometry, scanner=ScannerKind.LINEAR)
    assert np.abs(geometry_offsets(delta, linear) - a @ delta).max() > 0.1


def test_with_y_zero_a_general_scanners_rows_are_a_linear_ones_to_the_bit() -> None:
    """The y terms are added last: with ``y = 0`` the compiled rows (but ``dS``'s, no
    parameter of a general scanner) and offsets are section 10's, bit for bit."""
    geo = _scene(15, 50)[-1]
    general = replace(_general_geometry(geo, geo.origin), y=np.zeros(50))
    linear = replace(general, scanner=ScannerKind.LINEAR)
    normal = np.tile([0.1, -0.2, 0.97], (50, 1))
    rows_general, rows_linear = np.zeros((50, N_PARAMETERS)), np.zeros((50, N_PARAMETERS))
    add_geometry_normal_rows(rows_general, normal, general, np.arange(50))
    add_geometry_normal_rows(rows_linear, normal, linear, np.arange(50))
    assert np.array_equal(rows_general[:, :7], rows_linear[:, :7])
    assert not rows_general[:, 7].any() and rows_linear[:, 7].any()
    delta = np.array([0.03, -0.04, 0.02, 0.004, -0.005, 0.006, 0.015, 0.0])
    assert np.array_equal(geometry_offsets(delta, general), geometry_offsets(delta, linear))


@pytest.mark.parametrize("seed", [16, 17])
def test_a_general_scanners_exact_correction_is_the_calibrated_mounting(seed: int) -> None:
    """Points georeferenced with the nominal mounting (from the trajectory of its origin),
    corrected exactly by the biases ``nominal - true``, are the points the true mounting and
    range give: the calibration's correction and ``mounting_from_biases`` agree exactly."""
    rng = np.random.default_rng(seed)
    traj = _trajectory(rng)
    true = _mounting(rng)
    delta = np.array([0.04, -0.03, 0.05, 0.006, -0.004, 0.007, 0.02, 0.0])
    nominal = mounting_with_biases(true, delta)
    t = _times(rng, traj, 40)
    p_true = _points(rng, true, 40)
    r = np.linalg.norm(p_true, axis=1)
    p_measured = p_true * (1.0 + delta[PARAMETER_INDEX["dr"]] / r)[:, None]
    truth = georeference(p_true, t, traj, true).xyz
    delivered = georeference(p_measured, t, traj, nominal)
    origin = delivered.origin + delivered.rotation @ nominal.lever_arm
    frame = _general_geometry(delivered, origin)
    corrected, shift, geometry = exact_correction(delivered.xyz, frame, delta)
    np.testing.assert_allclose(corrected, truth, atol=1e-9)
    np.testing.assert_allclose(shift, delivered.xyz - truth, atol=1e-9)
    assert np.abs(shift).max() > 0.1
    assert geometry.scanner is ScannerKind.GENERAL
    assert geometry.y is not None and frame.rotation is not None
    np.testing.assert_allclose(np.column_stack([geometry.x, geometry.y, geometry.z]),
                               np.einsum("nji,nj->ni", frame.rotation, truth - origin),
                               atol=1e-9)
    # first order: eq. [13] with section 12's columns, within the square of the biases
    first = correct_geometry(delivered.xyz, delta, frame)
    assert np.abs(first - truth).max() < 120.0 * np.abs(delta[3:6]).sum() ** 2 + 1e-3


@pytest.mark.parametrize("seed", [18, 19])
def test_the_timing_bias_takes_ds_place_in_a_general_scanners_rows(seed: int) -> None:
    """With a timing column (``LaserGeometry.timing``) the eighth bias is ``dt``: its rows are
    ``n^T (v + w x (X - X_o))``, its offset ``dt`` times the column; the exact correction
    of points georeferenced ``dt`` late (the times delivered ``dt`` after the true ones) with
    the nominal mounting gives the true points, to the square of ``dt``."""
    rng = np.random.default_rng(seed)
    traj = _trajectory(rng)
    true = _mounting(rng)
    # dt 0.2 ms: this body's velocity jumps by some 10 m/s at each pose and its rate by a
    # radian a second in 10 ms, so that what dt's first order leaves (a millimetre here,
    # decimetres at 4 ms) stays below what it corrects
    delta = np.array([0.04, -0.03, 0.05, 0.006, -0.004, 0.007, 0.02, 2e-4])
    nominal = mounting_with_biases(true, np.r_[delta[:7], 0.0])
    t = _times(rng, traj, 40)
    p_true = _points(rng, true, 40)
    r = np.linalg.norm(p_true, axis=1)
    p_measured = p_true * (1.0 + delta[PARAMETER_INDEX["dr"]] / r)[:, None]
    truth = georeference(p_true, t, traj, true).xyz
    late = t + delta[7]  # the pose looked up at the delivered time
    delivered = georeference(p_measured, late, traj, nominal)
    origin = delivered.origin + delivered.rotation @ nominal.lever_arm
    v, w = body_rates(late, traj)  # base_link's: seen from its origin
    column = v + np.cross(w, delivered.xyz - delivered.origin)
    np.testing.assert_allclose(point_rates(late, delivered.xyz, delivered.origin, traj),
                               column, atol=1e-9)
    frame = replace(_general_geometry(delivered, origin), timing=column)
    corrected, shift, _ = exact_correction(delivered.xyz, frame, delta)
    without = exact_correction(delivered.xyz, replace(frame, timing=None), delta)[0]
    error, error_without = (np.abs(c - truth).max() for c in (corrected, without))
    print(f"from the truth: {error * 1e3:.2f} mm, without dt {error_without * 1e3:.1f} mm")
    assert error < 3e-3 and error < 0.1 * error_without
    np.testing.assert_allclose(shift, delivered.xyz - corrected, atol=1e-12)
    # the rows: dS's column is the timing column, the others a general scanner's
    normal = rng.normal(size=(40, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    a = geometry_design_matrix(frame)
    np.testing.assert_allclose(a[:, :, 7], column, atol=1e-12)
    np.testing.assert_allclose(a[:, :, :7], geometry_design_matrix(replace(frame, timing=None))
                               [:, :, :7], atol=1e-12)
    expected = np.einsum("ni,nik->nk", normal, a)
    np.testing.assert_allclose(geometry_normal_rows(normal, frame), expected, atol=1e-9)
    weight = rng.uniform(0.5, 2.0, 40)
    rows = np.zeros((40, N_PARAMETERS))
    add_geometry_normal_rows(rows, normal, frame, np.arange(40), weight)
    np.testing.assert_allclose(rows, weight[:, None] * expected, atol=1e-9)
    np.testing.assert_allclose(geometry_offsets(delta, frame), a @ delta, atol=1e-9)
    np.testing.assert_allclose(correct_geometry(delivered.xyz, delta, frame),
                               delivered.xyz - a @ delta, atol=1e-9)
