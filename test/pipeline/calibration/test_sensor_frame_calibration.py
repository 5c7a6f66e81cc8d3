"""A bag of clouds in the sensor's frame calibrated end to end (pipeline/calibration/
sensor_frame.py, docs/method.md section 12): a simulated UAV payload written as ros2 bag record
writes it, read with the configuration's topics, the mounting calibrated against the known
truth, the calibration file's ``extrinsic`` block and the URDF joint read back.

The INS is exact (as test/core/calibration/test_extrinsic.py says why); the core reached
0.3-5.5 arcsec and x, y within 3 mm on such missions, the bars here are 15 arcsec and 5 mm
(the bag's FLOAT32 points and times are the simulator's own, so nothing is lost in the bag).
"""

from __future__ import annotations

import functools
import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
from helpers_cli import one_line_error, run
from helpers_missions import write_params_file
from scipy.spatial.transform import Rotation

from lidarcal_ros.core.calibration.extrinsic import (
    NOMINAL_LEVER_ARM_SIGMA_M,
    TIMING_MAX_CORRELATION,
    TIMING_MAX_SIGMA_S,
    TIMING_SLOT,
)
from lidarcal_ros.core.config import FlightConfig
from lidarcal_ros.core.georeferencing.sensor_frame import Mounting
from lidarcal_ros.core.params import PARAMETER_INDEX
from lidarcal_ros.core.simulation.uav_payload import (
    UavPayloadMission,
    UavPayloadSpec,
    simulate_uav_payload,
)
from lidarcal_ros.errors import ConfigError
from lidarcal_ros.io.calibration_file import read_calibration, urdf_path
from lidarcal_ros.pipeline.calibration.sensor_frame import (
    calibrate_sensor_bag,
    load_sensor_bag,
    parse_mounting,
    sensor_calibration_settings,
    write_mounting_calibration,
    write_uav_simulation,
)

ARCSEC = math.radians(1.0 / 3600.0)
EXACT_INS = {"ins_position_sigma_m": (0.0, 0.0, 0.0), "ins_attitude_sigma_deg": (0.0, 0.0, 0.0)}
TOPICS = {"topics.points": "/velodyne_points", "topics.trajectory": "/ins/odometry"}


@functools.cache
def _mission(layout: str, seed: int) -> UavPayloadMission:
    """Four lines of 120 m, a few tenths of the layout's columns (some 0.3M points)."""
    return simulate_uav_payload(UavPayloadSpec(
        layout=layout, seed=seed, columns={"vlp16": 100, "os1-32": 64}[layout], n_lines=4,
        line_length_m=120.0, **EXACT_INS))  # type: ignore[arg-type]


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    return math.acos(min(1.0, max(-1.0, (np.trace(a.T @ b) - 1.0) / 2.0)))


def _config(**values: object) -> FlightConfig:
    return FlightConfig.from_mapping({**TOPICS, **values})


def _as_parameter(m: Mounting) -> str:
    return ",".join(repr(float(v)) for v in (*m.translation, *m.quaternion))


@pytest.mark.parametrize(("layout", "seed"), [("vlp16", 1), ("os1-32", 2)])
def test_a_payload_bag_gives_the_true_mounting(tmp_path: Path, layout: str, seed: int) -> None:
    m = _mission(layout, seed)
    paths = write_uav_simulation(tmp_path / "uav", m)
    data = load_sensor_bag(paths["bag"], _config())
    assert data is not None and data.frame_id == m.clouds.frame_id
    cal = calibrate_sensor_bag(data)
    true = m.truth_mounting
    rotation = _angle(cal.mounting.rotation, true.rotation) / ARCSEC
    lever = (cal.mounting.translation - true.translation) * 1e3
    dr = (cal.range_offset_m - m.biases[PARAMETER_INDEX["dr"]]) * 1e3
    print(f"{layout} seed {seed}: rotation {rotation:.1f} arcsec, lever arm x, y "
          f"{lever[0]:+.1f}, {lever[1]:+.1f} mm, dr {dr:+.1f} mm")
    assert _angle(m.nominal.rotation, true.rotation) > 600 * ARCSEC  # (what it starts from)
    assert rotation < 15.0
    assert np.abs(lever[:2]).max() < 5.0
    assert abs(dr) < 4.0
    assert cal.mounting.translation[2] == m.nominal.translation[2]  # z held
    # the file: the biases and the extrinsic block of docs/interface.md; the URDF joint
    path = write_mounting_calibration(tmp_path / "cal.yaml", data, cal)
    record = read_calibration(path)
    assert record.extrinsic is not None
    assert (record.extrinsic.parent, record.extrinsic.child) == ("base_link", m.clouds.frame_id)
    np.testing.assert_allclose(record.extrinsic.mounting.rotation, cal.mounting.rotation,
                               atol=1e-12)
    np.testing.assert_allclose(record.extrinsic.nominal.translation, m.nominal.translation,
                               atol=1e-12)
    np.testing.assert_allclose(record.delta, cal.delta, atol=1e-15)
    joint = ET.parse(urdf_path(path)).getroot()
    assert joint.tag == "joint" and joint.get("type") == "fixed"
    assert joint.find("parent").get("link") == "base_link"  # type: ignore[union-attr]
    assert joint.find("child").get("link") == m.clouds.frame_id  # type: ignore[union-attr]
    origin = joint.find("origin")
    assert origin is not None
    xyz = np.array(origin.get("xyz", "").split(), dtype=float)
    rpy = np.array(origin.get("rpy", "").split(), dtype=float)
    np.testing.assert_allclose(xyz, cal.mounting.translation, atol=1e-6)
    urdf_rotation = Rotation.from_euler("xyz", rpy).as_matrix()  # URDF: fixed-axis r, p, y
    assert _angle(urdf_rotation, cal.mounting.rotation) < 0.01 * ARCSEC


def test_the_true_mounting_as_nominal_gives_no_bias(tmp_path: Path) -> None:
    """The configuration's mounting in place of /tf_static's: the true one, so every bias but
    ``dr`` is zero. ``dY``'s sigma does not allow for the held vertical lever arm's leak
    (test/core/calibration/test_extrinsic.py): held to millimetres, the others to 3 sigma."""
    m = _mission("vlp16", 1)
    paths = write_uav_simulation(tmp_path / "uav", m)
    data = load_sensor_bag(paths["bag"],
                           _config(**{"sensor_frame.mounting": _as_parameter(m.truth_mounting)}))
    assert data is not None and "configuration" in data.mounting_source
    cal = calibrate_sensor_bag(data)
    expected = np.zeros(8)
    expected[PARAMETER_INDEX["dr"]] = m.biases[PARAMETER_INDEX["dr"]]
    z = {name: (cal.delta[i] - expected[i]) / cal.sigma[i] for name, i in PARAMETER_INDEX.items()
         if name in ("dX", "domega", "dphi", "dkappa", "dr")}
    print({k: round(v, 2) for k, v in z.items()}, "dY", cal.delta[PARAMETER_INDEX["dY"]])
    assert max(abs(v) for v in z.values()) < 3.0, z
    assert abs(cal.delta[PARAMETER_INDEX["dY"]]) < 0.003


def test_the_mounting_parameter() -> None:
    assert parse_mounting("") is None
    m = parse_mounting("0.1,0,-0.2,0,0,0,2")
    assert m is not None and np.allclose(m.rotation, np.eye(3))
    with pytest.raises(ConfigError, match=r"sensor_frame.mounting: expected 'x,y,z,qx,qy,qz,qw'"):
        parse_mounting("0.1,0,-0.2")
    with pytest.raises(ConfigError, match=r"sensor_frame.mounting: mounting quaternion"):
        parse_mounting("0,0,0,0,0,0,0")


def test_the_flight_configurations_options_reach_a_mountings_calibration() -> None:
    config = FlightConfig().with_values(
        matching__per_class_cap=20_000, matching__max_candidates_per_pair=400_000,
        calibration__robust_k=4.0, calibration__trajectory__model="offset",
        calibration__trajectory__offset_sigma_horizontal_m=0.02, calibration__max_correlation=0.99)
    s = sensor_calibration_settings(("dX", "dY", "domega"), config=config)
    assert (s.per_class_cap, s.max_candidates_per_pair, s.robust_k) == (20_000, 400_000, 4.0)
    assert s.trajectory.model.value == "offset"
    assert s.trajectory.offset_sigma_horizontal_m == 0.02
    assert s.solve_for == ("dX", "dY", "domega")
    # a mounting's: a general scanner, the rigorous model, no bias held for its sigma
    assert (s.scanner.value, s.model.value) == ("general", "rigorous")
    assert s.limits.max_correlation == 0.99 and dict(s.limits.max_sigma) == {}
    # the configuration's defaults are the settings without one
    default = sensor_calibration_settings(config=FlightConfig())
    bare = sensor_calibration_settings()
    assert default.per_class_cap == bare.per_class_cap and default.robust_k == bare.robust_k
    assert default.solve_for == bare.solve_for and dict(default.limits.max_sigma) == {}
    # auto: none for a mounting (strip errors would take up the lever arm)
    assert default.trajectory.model.value == "none" == bare.trajectory.model.value


def test_the_timing_limits_reach_a_mountings_calibration() -> None:
    """``sensor_frame.timing_max_sigma_s`` and ``timing_max_correlation`` become the
    settings' limits of ``dt`` (their effect on a payload: test/core/calibration/
    test_timing_bias.py); their defaults are the core's constants; without
    ``estimate_timing`` no limit of dt is set."""
    config = FlightConfig().with_values(sensor_frame__estimate_timing=True,
                                        sensor_frame__timing_max_sigma_s=2e-4,
                                        sensor_frame__timing_max_correlation=0.8)
    s = sensor_calibration_settings(config=config)
    assert s.timing and TIMING_SLOT in s.solve_for
    assert dict(s.limits.max_sigma) == {TIMING_SLOT: 2e-4}
    assert s.timing_max_correlation == 0.8
    default = sensor_calibration_settings(config=FlightConfig().with_values(
        sensor_frame__estimate_timing=True))
    assert dict(default.limits.max_sigma) == {TIMING_SLOT: TIMING_MAX_SIGMA_S}
    assert default.timing_max_correlation == TIMING_MAX_CORRELATION
    off = sensor_calibration_settings(config=FlightConfig())
    assert not off.timing and dict(off.limits.max_sigma) == {}


def test_the_lever_arms_sigma_reaches_a_mountings_calibration() -> None:
    """``sensor_frame.lever_arm_sigma_m`` is the held lever arm's sigma (its effect on a
    payload's sigmas: test/core/calibration/test_extrinsic.py), 5 cm by default; a map-frame
    calibration considers no held bias."""
    s = sensor_calibration_settings(config=FlightConfig().with_values(
        sensor_frame__lever_arm_sigma_m=0.02))
    assert s.held_sigma == {"dX": 0.02, "dY": 0.02, "dZ": 0.02}
    default = sensor_calibration_settings(config=FlightConfig())
    assert default.held_sigma == {n: NOMINAL_LEVER_ARM_SIGMA_M for n in ("dX", "dY", "dZ")}
    assert NOMINAL_LEVER_ARM_SIGMA_M == 0.05
    assert FlightConfig().calibration_settings().held_sigma == {}


def test_the_ins_errors_reach_both_kinds_of_calibration() -> None:
    """``ins.*`` (metres, arcsec, seconds) become the settings' INS errors (SI; attitude about
    the body's right, forward, up: pitch, roll, heading), for a mounting's calibration and a
    map-frame one alike; all zero by default (the INS taken as exact)."""
    config = FlightConfig().with_values(
        ins__position_sigma_m=0.02, ins__height_sigma_m=0.03, ins__attitude_sigma_arcsec=18.0,
        ins__heading_sigma_arcsec=36.0, ins__position_correlation_s=0.0,
        ins__attitude_correlation_s=5.0)
    for s in (sensor_calibration_settings(config=config), config.calibration_settings()):
        assert s.ins_noise.active
        assert s.ins_noise.position_sigma_m == (0.02, 0.02, 0.03)
        np.testing.assert_allclose(s.ins_noise.attitude_sigma_rad,
                                   np.radians([18 / 3600, 18 / 3600, 36 / 3600]))
        assert s.ins_noise.correlation_s == (0.0, 5.0)
    assert not sensor_calibration_settings(config=FlightConfig()).ins_noise.active
    assert not FlightConfig().calibration_settings().ins_noise.active


@pytest.mark.parametrize(("name", "value", "words"), [
    ("sensor_frame.timing_max_correlation", 1.5,
     "sensor_frame.timing_max_correlation: 1.5 is above the maximum 1.0"),
    ("sensor_frame.timing_max_sigma_s", 0.0,
     "sensor_frame.timing_max_sigma_s: 0.0 is below the minimum 1e-06"),
])
def test_a_timing_limit_out_of_range_is_refused_in_one_line(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str, value: float,
        words: str) -> None:
    params = write_params_file(tmp_path / "config.yaml", {name: value,
                                                          "sensor_frame.estimate_timing": True})
    rc, _, err = run(capsys, "calibrate", tmp_path / "no_bag", "-o", tmp_path / "cal.yaml",
                     "--config", params)
    assert words in one_line_error(rc, err)
    assert not (tmp_path / "cal.yaml").exists()
