"""Bags of clouds in the sensor's frame (io/bag/sensor_bag.py, io/cloud/sensor_time.py): a
simulated UAV payload written as ``ros2 bag record`` writes the drivers' topics, read back by
rosbags (an independent reader) and by lidarcal, for both layouts and every time convention;
the refusals, one line each."""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pytest
import yaml
from rosbags.interfaces import QosDurability
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore

from lidarcal_ros.core.georeferencing.sensor_frame import Mounting, TimeConvention
from lidarcal_ros.core.mission import Mission, Strip, Trajectory
from lidarcal_ros.core.simulation.uav_payload import (
    UavPayloadMission,
    UavPayloadSpec,
    simulate_uav_payload,
)
from lidarcal_ros.errors import BagError, CloudFormatError, TrajectoryError
from lidarcal_ros.io.bag.mission_bag import write_mission_bag
from lidarcal_ros.io.bag.reader import open_bag
from lidarcal_ros.io.bag.sensor_bag import (
    SensorTimeFormat,
    read_sensor_bag,
    sensor_frame_of,
    static_mounting,
    write_sensor_bag,
)
from lidarcal_ros.io.cloud.sensor_time import time_reading

POINTS = {"vlp16": "/velodyne_points", "os1-32": "/ouster/points"}
ODOM = "/ins/odometry"


@functools.cache
def _mission(layout: str) -> UavPayloadMission:
    """Two short lines, a few columns: a few thousand points."""
    return simulate_uav_payload(UavPayloadSpec(layout=layout, seed=3, columns=16, n_lines=2,
                                               line_length_m=40.0))


def _write(tmp_path: Path, layout: str, fmt: SensorTimeFormat = SensorTimeFormat.DRIVER,
           **options: object) -> Path:
    m = _mission(layout)
    return write_sensor_bag(tmp_path / f"{layout}-{fmt}", m.clouds, m.trajectory, m.nominal,
                            points_topic=POINTS[layout], time_format=fmt,
                            **options)  # type: ignore[arg-type]


@pytest.mark.parametrize("layout", ["vlp16", "os1-32"])
@pytest.mark.parametrize("fmt", list(SensorTimeFormat))
def test_a_payload_bag_reads_back_as_written(tmp_path: Path, layout: str,
                                             fmt: SensorTimeFormat) -> None:
    m = _mission(layout)
    path = _write(tmp_path, layout, fmt)
    # rosbags, on its own: topics, types, QoS, fields and frames as the drivers publish them
    store = get_typestore(Stores.ROS2_HUMBLE)
    with Reader(path) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        assert types == {POINTS[layout]: "sensor_msgs/msg/PointCloud2",
                         "/ins/odometry": "nav_msgs/msg/Odometry",
                         "/tf_static": "tf2_msgs/msg/TFMessage"}
        qos = {c.topic: c.ext.offered_qos_profiles[0].durability  # type: ignore[union-attr]
               for c in reader.connections}
        assert qos["/tf_static"] == QosDurability.TRANSIENT_LOCAL
        assert qos[POINTS[layout]] == QosDurability.VOLATILE
        seen: dict[str, object] = {}
        for conn, _t, raw in reader.messages():
            if conn.topic not in seen:
                seen[conn.topic] = store.deserialize_cdr(raw, conn.msgtype)
    cloud, odom, tf = (seen[POINTS[layout]], seen["/ins/odometry"], seen["/tf_static"])
    fields = {f.name: f.datatype for f in cloud.fields}  # type: ignore[attr-defined]
    time_field = {SensorTimeFormat.DRIVER: m.clouds.time_field}.get(fmt, "timestamp")
    time_type = {"time": 7, "t": 6, "timestamp": 8}[time_field]  # FLOAT32, UINT32, FLOAT64
    assert fields == {"x": 7, "y": 7, "z": 7, "intensity": 7, time_field: time_type, "ring": 4}
    assert cloud.header.frame_id == m.clouds.frame_id  # type: ignore[attr-defined]
    assert (odom.header.frame_id, odom.child_frame_id) == ("map", "base_link")  # type: ignore[attr-defined]
    transform = tf.transforms[0]  # type: ignore[attr-defined]
    assert (transform.header.frame_id, transform.child_frame_id) == ("base_link",
                                                                     m.clouds.frame_id)
    # lidarcal: every point at its time, in the sensor's frame, the mounting from /tf_static
    frame = sensor_frame_of(path, points_topic=POINTS[layout], trajectory_topic=ODOM)
    assert frame == m.clouds.frame_id
    bag = read_sensor_bag(path, points_topic=POINTS[layout], trajectory_topic=ODOM)
    assert (bag.frame_id, bag.map_frame, bag.base_frame) == (m.clouds.frame_id, "map",
                                                             "base_link")
    assert bag.time.field == time_field
    assert bag.time.relative == (fmt != SensorTimeFormat.TIMESTAMP_ABSOLUTE)
    assert bag.time.assumed
    np.testing.assert_array_equal(bag.stamps, m.clouds.stamps)
    np.testing.assert_array_equal(bag.offsets, m.clouds.offsets)
    np.testing.assert_array_equal(bag.xyz, m.clouds.xyz)
    # FLOAT32 s and UINT32 ns exactly; FLOAT64 s to its rounding at 1.7e9 s
    np.testing.assert_allclose(bag.t, m.clouds.absolute_times(), rtol=0, atol=1e-6)
    np.testing.assert_allclose(bag.trajectory.xyz, m.trajectory.xyz, rtol=0, atol=1e-12)
    q, q_true = bag.trajectory.orientation, m.trajectory.orientation
    assert q is not None and q_true is not None
    assert np.abs(np.abs(np.einsum("ij,ij->i", q, q_true)) - 1.0).max() < 1e-12
    assert bag.mounting_source == "/tf_static"
    np.testing.assert_allclose(bag.mounting.rotation, m.nominal.rotation, atol=1e-12)
    np.testing.assert_allclose(bag.mounting.translation, m.nominal.translation, atol=1e-12)


def test_the_time_convention_given_overrides_the_guess(tmp_path: Path) -> None:
    path = _write(tmp_path, "vlp16", SensorTimeFormat.TIMESTAMP_RELATIVE)
    m = _mission("vlp16")
    wrong = read_sensor_bag(path, points_topic=POINTS["vlp16"], trajectory_topic=ODOM,
                            time_convention=TimeConvention.ABSOLUTE)
    assert not wrong.time.relative and not wrong.time.assumed
    assert np.abs(wrong.t - m.clouds.absolute_times()).min() > 1e9  # offsets taken as times


@pytest.mark.parametrize("form", ["humble", "jazzy"])
def test_metadata_as_ros2_bag_record_writes_it(tmp_path: Path, form: str) -> None:
    """metadata.yaml rewritten as rosbag2 writes it: Humble's version 5 (QoS a YAML string of
    integer enums), Jazzy's version 9 (QoS a list of mappings of names)."""
    path = _write(tmp_path, "os1-32")
    meta = path / "metadata.yaml"
    doc = yaml.safe_load(meta.read_text())
    info = doc["rosbag2_bagfile_information"]
    info["version"] = 5 if form == "humble" else 9
    for entry in info["topics_with_message_count"]:
        tm = entry["topic_metadata"]
        latched = tm["name"] == "/tf_static"
        profile = {"history": 3 if form == "humble" else "unknown", "depth": 0,
                   "reliability": 1 if form == "humble" else "reliable",
                   "durability": (1 if latched else 2) if form == "humble" else
                   ("transient_local" if latched else "volatile"),
                   "deadline": {"sec": 9223372036, "nsec": 854775807},
                   "lifespan": {"sec": 9223372036, "nsec": 854775807},
                   "liveliness": 1 if form == "humble" else "automatic",
                   "liveliness_lease_duration": {"sec": 9223372036, "nsec": 854775807},
                   "avoid_ros_namespace_conventions": False}
        tm["offered_qos_profiles"] = (yaml.safe_dump([profile]) if form == "humble"
                                      else [profile])
        if form == "jazzy":
            tm["type_description_hash"] = "RIHS01_" + "0" * 64
    meta.write_text(yaml.safe_dump(doc, sort_keys=False))
    with open_bag(path) as bag:
        assert bag.topics["/tf_static"].transient_local
        assert not bag.topics["/ouster/points"].transient_local
    bag_read = read_sensor_bag(path, points_topic="/ouster/points", trajectory_topic=ODOM)
    assert bag_read.frame_id == "os_sensor" and bag_read.n_points == _mission(
        "os1-32").clouds.xyz.shape[0]


def test_a_map_frame_bag_is_not_a_sensor_frame_one(tmp_path: Path) -> None:
    m = _mission("vlp16")
    strip = Strip(0, np.tile([1.0, 2.0, 3.0], (3, 1)), m.clouds.stamps[:3])
    path = write_mission_bag(tmp_path / "map", Mission(m.trajectory, [strip], frame_id="map"))
    assert sensor_frame_of(path, points_topic="/lidar/points",
                           trajectory_topic="/lidar/trajectory") is None


def test_a_trajectory_without_orientation_is_refused_in_one_line(tmp_path: Path) -> None:
    m = _mission("vlp16")
    flat = Trajectory(m.trajectory.t, m.trajectory.xyz)  # identity quaternions written
    path = write_sensor_bag(tmp_path / "b", m.clouds, flat, m.nominal)
    with pytest.raises(TrajectoryError, match=r"trajectory /ins/odometry carries no "
                       r"orientation \(identity or zero quaternions throughout\)") as err:
        read_sensor_bag(path, points_topic="/velodyne_points", trajectory_topic=ODOM)
    assert "\n" not in str(err.value)


def test_no_mounting_is_refused_and_the_configuration_gives_one(tmp_path: Path) -> None:
    m = _mission("vlp16")
    (tmp_path / "no_tf").mkdir()
    path = _write(tmp_path / "no_tf", "vlp16", tf_topic="/tf_elsewhere")
    with pytest.raises(BagError, match=r"no mounting base_link -> velodyne: no /tf_static in "
                       r"the bag and sensor_frame.mounting is not set") as err:
        read_sensor_bag(path, points_topic="/velodyne_points", trajectory_topic=ODOM)
    assert "\n" not in str(err.value)
    given = read_sensor_bag(path, points_topic="/velodyne_points", trajectory_topic=ODOM,
                            mounting=m.truth_mounting)
    assert given.mounting is m.truth_mounting and "configuration" in given.mounting_source
    # the Odometry's child_frame_id names the body frame, not the configuration's
    other = _write(tmp_path, "vlp16", base_frame="body")  # /tf_static: body -> velodyne
    assert read_sensor_bag(other, points_topic="/velodyne_points", trajectory_topic=ODOM,
                           base_frame="imu_link").base_frame == "body"


def test_a_chain_of_static_transforms_is_composed() -> None:
    a = Mounting.from_quaternion([0.1, 0.0, -0.2], [0.0, 0.2588190451, 0.0, 0.9659258263])
    b = Mounting.from_quaternion([0.0, 0.05, 0.03], [0.0, 0.0, 0.7071067812, 0.7071067812])
    found = static_mounting({"mount": ("base_link", a), "velodyne": ("mount", b)},
                            "base_link", "velodyne")
    assert found is not None
    p = np.array([[3.0, -2.0, 1.0]])
    np.testing.assert_allclose(found.to_base(p), a.to_base(b.to_base(p)), atol=1e-12)
    assert static_mounting({"velodyne": ("mount", b)}, "base_link", "velodyne") is None


def _cloud(**fields: tuple[str, np.ndarray]) -> np.ndarray:
    n = len(next(iter(fields.values()))[1])
    out = np.zeros(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
                   + [(k, v[0]) for k, v in fields.items()])
    for k, (_, values) in fields.items():
        out[k] = values
    return out


def test_time_fields_and_their_conventions() -> None:
    stamp = 1_700_000_000.25
    offsets = np.array([0.0, 0.05, 0.099])
    # Livox's driver: FLOAT64 absolute nanoseconds
    livox = time_reading(_cloud(timestamp=("<f8", (stamp + offsets) * 1e9)), stamp)
    assert (livox.scale, livox.relative) == (1e-9, False)
    np.testing.assert_allclose(livox.absolute(_cloud(timestamp=("<f8", (stamp + offsets)
                                                                * 1e9))["timestamp"], stamp),
                               stamp + offsets, atol=1e-6)
    # a simulator's clock near zero: still told apart by the stamp
    sim = time_reading(_cloud(timestamp=("<f8", 12.0 + offsets)), 12.0)
    assert not sim.relative
    rel = time_reading(_cloud(time=("<f4", offsets)), 12.0)
    assert rel.relative and rel.field == "time" and "after header.stamp" in rel.describe()
    # Livox's ROS 1 custom layout: UINT32 ns after the stamp
    assert time_reading(_cloud(offset_time=("<u4", offsets * 1e9)), stamp).scale == 1e-9


def test_time_fields_refused_in_one_line() -> None:
    with pytest.raises(CloudFormatError, match=r"velodyne_points: no per-point time field "
                       r"\(time, t, timestamp, offset_time\); fields present: x, y, z, "
                       r"intensity"):
        time_reading(_cloud(intensity=("<f4", np.ones(3))), 1.0, source="velodyne_points")
    with pytest.raises(CloudFormatError, match=r"time field 'time' is UINT16"):
        time_reading(_cloud(time=("<u2", np.ones(3))), 1.0)
    with pytest.raises(CloudFormatError, match=r"'t' is UINT32 nanoseconds, which cannot be "
                       r"absolute"):
        time_reading(_cloud(t=("<u4", np.ones(3))), 1.0, convention="absolute")
    with pytest.raises(CloudFormatError, match=r"no per-point time field \(stamp\)"):
        time_reading(_cloud(t=("<u4", np.ones(3))), 1.0, field="stamp")
