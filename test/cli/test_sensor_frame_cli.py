"""``lidarcal simulate --uav``, ``calibrate`` and ``correct`` of clouds in the sensor's frame:
the issue's command line, end to end on a small payload, and its refusals one line each (the
corrected points against the truth: test/pipeline/correction/test_sensor_correction.py)."""

from __future__ import annotations

import math
from pathlib import Path

import laspy
import numpy as np
import pytest
import yaml
from helpers_cli import one_line_error, run

from lidarcal_ros.core.config import FlightConfig
from lidarcal_ros.core.mission import Trajectory
from lidarcal_ros.core.simulation.uav_payload import UavPayloadSpec, simulate_uav_payload
from lidarcal_ros.io.bag.reader import open_bag
from lidarcal_ros.io.bag.sensor_bag import write_sensor_bag
from lidarcal_ros.io.calibration_file import read_calibration, urdf_path
from lidarcal_ros.io.cloud.pointcloud import cloud_to_array
from lidarcal_ros.pipeline.calibration.sensor_frame import truth_mounting

ARCSEC = math.radians(1.0 / 3600.0)


def test_simulate_then_calibrate_an_ouster_payload(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    bag, cal = tmp_path / "uav", tmp_path / "cal.yaml"
    rc, out, _ = run(capsys, "simulate", "--uav", "--layout", "os1-32", "--seed", "2",
                     "--columns", "64", "--uav-line-length", "120", "--exact-ins", "-o", bag)
    assert rc == 0 and "frame os_sensor" in out
    truth = tmp_path / "uav_truth.yaml"
    doc = yaml.safe_load(truth.read_text())
    assert doc["mounting"]["child"] == "os_sensor" and "uav_payload" in doc["simulation"]
    rc, out, err = run(capsys, "calibrate", bag, "--points", "/velodyne_points",
                       "--trajectory", "/ins/odometry", "--truth", truth, "-o", cal, "-q")
    assert rc == 0, err
    assert "per-point time from field 't' (UINT32): ns after header.stamp (assumed" in err
    assert "mounting base_link -> os_sensor (nominal from /tf_static)" in out
    record = read_calibration(cal)
    assert record.extrinsic is not None and record.extrinsic.child == "os_sensor"
    true = truth_mounting(truth)
    assert true is not None
    r = record.extrinsic.mounting.rotation
    angle = math.acos(min(1.0, (np.trace(r.T @ true.rotation) - 1.0) / 2.0))
    assert angle < 15 * ARCSEC
    assert np.abs(record.extrinsic.mounting.translation - true.translation)[:2].max() < 0.005
    assert urdf_path(cal).read_text().count("<joint ") == 1
    # correct: into the map frame with the calibrated mounting, as a bag and as LAZ
    topics = ("--points", "/velodyne_points", "--trajectory", "/ins/odometry")
    for out_name in ("out.mcap", "out.laz"):
        rc, out, err = run(capsys, "correct", bag, "--calibration", cal, *topics, "-o",
                           tmp_path / out_name)
        assert rc == 0, err
        assert "model: rigorous (INS attitude at 100 Hz) for 100% of the points" in out
        assert "not corrected (trajectory): 0" in out
    clouds = _corrected_clouds(tmp_path / "out.mcap")
    assert {frame for frame, _ in clouds} == {"map"}
    points = np.concatenate([p for _, p in clouds])
    fields = set(points.dtype.names or ())
    assert {"reflectance", "range", "incidence", "correction_flags"} <= fields
    assert np.isfinite(points["reflectance"]).mean() > 0.8  # (NaN: no surface normal)
    las = laspy.read(tmp_path / "out.laz")
    assert len(las.points) == len(points)
    assert np.abs(np.sort(np.asarray(las.z)) - np.sort(points["z"])).max() < 0.001
    # a calibration without the mounting: one line
    doc = yaml.safe_load(cal.read_text())
    del doc["lidarcal_calibration"]["extrinsic"]
    no_extrinsic = tmp_path / "no_extrinsic.yaml"
    no_extrinsic.write_text(yaml.safe_dump(doc))
    rc, _, err = run(capsys, "correct", bag, "--calibration", no_extrinsic, *topics, "-o",
                     tmp_path / "refused.mcap")
    assert ("clouds in the sensor's frame 'os_sensor' need the calibrated mounting, and the "
            "calibration has no extrinsic block") in one_line_error(rc, err, "correct")
    assert not (tmp_path / "refused.mcap").exists()


def _corrected_clouds(path: Path) -> list[tuple[str, np.ndarray]]:
    """The corrected clouds of an output bag: (frame_id, points) each."""
    topic = FlightConfig()["topics.corrected"]
    with open_bag(path) as bag:
        return [(msg.header.frame_id, cloud_to_array(msg, source=topic))
                for msg in (bag.deserialize(memoryview(raw), msgtype, topic=topic)
                            for _t, msgtype, _ns, raw in bag.messages([topic]))]


@pytest.fixture(scope="module")
def payload() -> object:
    return simulate_uav_payload(UavPayloadSpec(seed=3, columns=16, n_lines=2,
                                               line_length_m=40.0))


def test_calibrate_refusals_are_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                         payload: object) -> None:
    m = payload
    args = ("--points", "/velodyne_points", "--trajectory", "/ins/odometry", "-o",
            tmp_path / "cal.yaml")
    flat = write_sensor_bag(tmp_path / "flat", m.clouds,  # type: ignore[attr-defined]
                            Trajectory(m.trajectory.t, m.trajectory.xyz),  # type: ignore[attr-defined]
                            m.nominal)  # type: ignore[attr-defined]
    rc, _, err = run(capsys, "calibrate", flat, *args)
    assert "trajectory /ins/odometry carries no orientation" in one_line_error(rc, err)
    no_tf = write_sensor_bag(tmp_path / "no_tf", m.clouds, m.trajectory,  # type: ignore[attr-defined]
                             m.nominal, tf_topic="/tf")  # type: ignore[attr-defined]
    rc, _, err = run(capsys, "calibrate", no_tf, *args)
    assert "no mounting base_link -> velodyne" in one_line_error(rc, err)
    rc, _, err = run(capsys, "calibrate", no_tf, *args, "--time-field", "stamp")
    assert "no per-point time field (stamp); fields present: x, y, z, intensity, time, ring" \
        in one_line_error(rc, err)
    good = write_sensor_bag(tmp_path / "good", m.clouds, m.trajectory,  # type: ignore[attr-defined]
                            m.nominal)  # type: ignore[attr-defined]
    rc, _, err = run(capsys, "calibrate", good, *args, "--dask", "local:2")
    assert f"--dask: {good} holds clouds in the sensor's frame, whose mounting is calibrated " \
        "in this process only; leave --dask out" in one_line_error(rc, err)
