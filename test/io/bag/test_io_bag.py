"""Mission bags: write, read back (ours and the mcap project's tools), and bad input."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from mcap_ros2.writer import Writer as McapRos2Writer
from rosbags.typesys import Stores, get_typestore

from lidarcal_ros.core.mission import ControlPoints, Mission, Strip, Trajectory
from lidarcal_ros.errors import BagError, CloudFormatError, InputError, OutputError
from lidarcal_ros.io.bag.format import seconds_to_ns
from lidarcal_ros.io.bag.mission_bag import read_mission, write_mission_bag
from lidarcal_ros.io.bag.reader import open_bag
from lidarcal_ros.io.bag.writer import BagWriter

T0 = 1.7e9  # absolute seconds, as a GPS-synchronised recorder would stamp
TS = get_typestore(Stores.ROS2_HUMBLE)


def _mission() -> Mission:
    rng = np.random.default_rng(42)
    strips = []
    # Out of order on purpose; strip 2 overlaps strip 7 in time.
    for sid, start, n, with_intensity in ((7, 0.0, 400, True), (2, 1.5, 300, True),
                                          (5, 6.0, 250, False)):
        t = T0 + start + np.sort(rng.uniform(0.0, 2.0, n))
        xyz = np.column_stack([
            4.5e5 + rng.normal(0, 300, n),
            5.4e6 + rng.normal(0, 300, n),
            rng.normal(40, 5, n),
        ])
        intensity = rng.uniform(0, 1000, n).astype(np.float32) if with_intensity else None
        strips.append(Strip(sid, xyz, t, intensity))
    strips[0].extra["return_number"] = rng.integers(1, 4, 400).astype(np.uint8)
    tt = T0 - 1.0 + 0.1 * np.arange(100)
    traj = Trajectory(tt, np.column_stack([4.5e5 + 60 * (tt - T0), 5.4e6 + 0 * tt,
                                           1150.0 + 0 * tt]))
    control = ControlPoints(["a", "b", "c"], np.array([[4.5e5, 5.4e6, 41.25],
                                                        [4.5e5 + 10, 5.4e6 - 3, 40.5],
                                                        [4.5e5 - 7, 5.4e6 + 2, 39.0]]))
    return Mission(traj, strips, control, frame_id="map")


def _sorted_strips(mission: Mission) -> list[Strip]:
    return sorted(mission.strips, key=lambda s: s.strip_id)


def _assert_same(got: Mission, want: Mission, *, intensity: bool = True) -> None:
    assert [s.strip_id for s in got.strips] == [2, 5, 7]
    for g, w in zip(got.strips, _sorted_strips(want), strict=True):
        assert g.strip_id == w.strip_id
        assert g.xyz.dtype == np.float64 and g.t.dtype == np.float64
        assert np.array_equal(g.xyz, w.xyz)  # exact float64
        assert np.array_equal(g.t, w.t)
        if intensity:
            if w.intensity is None:
                assert g.intensity is None
            else:
                assert g.intensity is not None and np.array_equal(g.intensity, w.intensity)
    assert got.frame_id == want.frame_id
    assert np.allclose(got.trajectory.t, want.trajectory.t, rtol=0, atol=1e-6)
    assert np.array_equal(got.trajectory.xyz, want.trajectory.xyz)
    assert got.dropped_non_finite == 0


@pytest.fixture(scope="module")
def mission() -> Mission:
    return _mission()


@pytest.fixture(scope="module")
def bag(tmp_path_factory, mission) -> Path:
    path = tmp_path_factory.mktemp("bags") / "mission"
    reflectance = [np.full(len(s), 0.5 + k, dtype=np.float32) for k, s in enumerate(mission.strips)]
    write_mission_bag(path, mission, chunk_seconds=0.25,
                      extra_point_fields={"reflectance": reflectance})
    return path


def test_round_trip_exact(bag, mission):
    assert (bag / "metadata.yaml").is_file() and (bag / "mission.mcap").is_file()
    got = read_mission(bag)
    _assert_same(got, mission)
    by_id = {s.strip_id: s for s in got.strips}
    assert by_id[7].extra["return_number"].dtype == np.uint8
    assert np.array_equal(by_id[7].extra["return_number"], mission.strips[0].extra["return_number"])
    assert "return_number" not in by_id[2].extra
    assert by_id[2].extra["reflectance"].dtype == np.float32
    assert np.all(by_id[2].extra["reflectance"] == 1.5)
    assert got.control is not None
    assert got.control.ids == ["C1", "C2", "C3"]
    assert np.array_equal(got.control.xyz, mission.control.xyz)


def test_bag_layout(bag, mission):
    with open_bag(bag) as reader:
        topics = reader.topics
        assert set(topics) == {"/lidar/points", "/lidar/trajectory", "/lidar/control_points"}
        assert topics["/lidar/points"].msgtype == "sensor_msgs/msg/PointCloud2"
        assert topics["/lidar/trajectory"].msgtype == "geometry_msgs/msg/PoseStamped"
        assert topics["/lidar/trajectory"].count == 100
        assert topics["/lidar/control_points"].count == 1
        assert topics["/lidar/control_points"].transient_local
        assert not topics["/lidar/points"].transient_local
        log_times, first = [], None
        for topic, msgtype, log_ns, raw in reader.messages():
            log_times.append(log_ns)
            first = first or topic
            msg = reader.deserialize(raw, msgtype)
            stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
            assert stamp == log_ns and msg.header.frame_id == "map"
            if topic == "/lidar/points":
                names = [f.name for f in msg.fields]
                assert names[:6] == ["x", "y", "z", "t", "intensity", "strip_id"] or names[:5] == [
                    "x", "y", "z", "t", "strip_id"]
                t = np.frombuffer(msg.data, dtype="<f8")[3:: msg.point_step // 8]
                assert stamp == seconds_to_ns(t[0]) and t[-1] - t[0] < 0.25
        assert first == "/lidar/control_points"
        assert log_times == sorted(log_times) and len(log_times) == sum(
            i.count for i in topics.values())
        assert reader.start_ns == log_times[0] and reader.end_ns == log_times[-1]


def test_independent_readback_with_mcap(bag, mission):
    """Our bag decoded by the mcap project's own reader and decoder."""
    codes = {7: "f4", 8: "f8", 2: "u1", 4: "u2"}
    xyzt: dict[int, list[np.ndarray]] = {}
    poses = []
    with (bag / "mission.mcap").open("rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        for schema, channel, _message, msg in reader.iter_decoded_messages():
            if channel.topic == "/lidar/points":
                assert schema is not None and schema.name == "sensor_msgs/msg/PointCloud2"
                dt = np.dtype({"names": [f.name for f in msg.fields],
                               "formats": ["<" + codes[f.datatype] for f in msg.fields],
                               "offsets": [f.offset for f in msg.fields],
                               "itemsize": msg.point_step})
                pts = np.frombuffer(bytes(msg.data), dtype=dt)
                for sid in np.unique(pts["strip_id"]):
                    sel = pts[pts["strip_id"] == sid]
                    xyzt.setdefault(int(sid), []).append(
                        np.column_stack([sel["x"], sel["y"], sel["z"], sel["t"]]))
            elif channel.topic == "/lidar/trajectory":
                p = msg.pose.position
                stamp = msg.header.stamp
                poses.append((stamp.sec + stamp.nanosec * 1e-9, p.x, p.y, p.z))
    for strip in mission.strips:
        got = np.concatenate(xyzt[strip.strip_id])
        assert np.array_equal(got, np.column_stack([strip.xyz, strip.t]))
    poses_arr = np.array(poses)
    assert np.array_equal(poses_arr[:, 1:], mission.trajectory.xyz)
    assert np.allclose(poses_arr[:, 0], mission.trajectory.t, rtol=0, atol=1e-6)


def test_bare_mcap(tmp_path, mission, bag):
    out = tmp_path / "mission.mcap"
    write_mission_bag(out, mission)
    assert out.is_file() and not any(p.name.startswith(".") for p in tmp_path.iterdir())
    _assert_same(read_mission(out), mission, intensity=True)
    # The storage file inside a rosbag2 directory is itself a readable bare MCAP.
    _assert_same(read_mission(bag / "mission.mcap"), mission)


def _msgdef(msgtype: str) -> str:
    return TS.generate_msgdef(msgtype, ros_version=2)[0]


def _cloud_dict(points: np.ndarray, stamp_ns: int, frame: str) -> dict:
    codes = {"f8": 8, "f4": 7, "u2": 4, "u1": 2}
    layout: dict = dict(points.dtype.fields or {})
    fields = [{"name": n, "offset": layout[n][1], "datatype": codes[layout[n][0].str[1:]],
               "count": 1} for n in layout]
    return {"header": {"stamp": {"sec": stamp_ns // 10**9, "nanosec": stamp_ns % 10**9},
                       "frame_id": frame},
            "height": 1, "width": len(points), "fields": fields, "is_bigendian": False,
            "point_step": points.dtype.itemsize, "row_step": points.nbytes,
            "data": points.tobytes(), "is_dense": True}


def test_mcap_ros2_writer_bag(tmp_path, mission):
    """A bag from mcap-ros2-support, schema names without /msg/, mixed-strip chunks."""
    path = tmp_path / "foreign.mcap"
    # Unusual layout: float32 padding field first, time called gps_time, point_source_id.
    dt = np.dtype([("pad", "<f4"), ("gps_time", "<f8"), ("x", "<f8"), ("y", "<f8"),
                   ("z", "<f8"), ("intensity", "<f4"), ("point_source_id", "<u2")])
    allpts = []
    for s in mission.strips:
        p = np.zeros(len(s), dtype=dt)
        p["x"], p["y"], p["z"] = s.xyz.T
        p["gps_time"] = s.t
        p["intensity"] = s.intensity if s.intensity is not None else 0
        p["point_source_id"] = s.strip_id
        allpts.append(p)
    pts = np.concatenate(allpts)
    pts = pts[np.random.default_rng(1).permutation(len(pts))]  # strips mixed in every chunk
    with path.open("wb") as stream:
        writer = McapRos2Writer(stream)
        pc = writer.register_msgdef("sensor_msgs/PointCloud2",
                                    _msgdef("sensor_msgs/msg/PointCloud2"))
        ps = writer.register_msgdef("geometry_msgs/PoseStamped",
                                    _msgdef("geometry_msgs/msg/PoseStamped"))
        cp = np.zeros(3, dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8")])
        cp["x"], cp["y"], cp["z"] = mission.control.xyz.T
        writer.write_message("/lidar/control_points", pc, _cloud_dict(cp, 1, "map"), log_time=1)
        for k, chunk in enumerate(np.array_split(pts, 4)):
            stamp = seconds_to_ns(T0) + k
            writer.write_message("/lidar/points", pc, _cloud_dict(chunk, stamp, "map"),
                                 log_time=stamp)
        for t, (x, y, z) in zip(mission.trajectory.t, mission.trajectory.xyz, strict=True):
            ns = seconds_to_ns(t)
            writer.write_message("/lidar/trajectory", ps, {
                "header": {"stamp": {"sec": ns // 10**9, "nanosec": ns % 10**9}, "frame_id": "map"},
                "pose": {"position": {"x": x, "y": y, "z": z},
                         "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}},
            }, log_time=ns)
        writer.finish()
    with open_bag(path) as reader:
        assert reader.topics["/lidar/points"].msgtype == "sensor_msgs/msg/PointCloud2"
        assert reader.topics["/lidar/trajectory"].msgtype == "geometry_msgs/msg/PoseStamped"
    got = read_mission(path)
    # Strip 5 had no intensity; here every point has the field (zeros).
    _assert_same(got, mission, intensity=False)
    for g, w in zip(got.strips, _sorted_strips(mission), strict=True):
        assert g.intensity is not None
        want = w.intensity if w.intensity is not None else np.zeros(len(w), np.float32)
        assert np.array_equal(g.intensity, want)
        assert np.array_equal(g.extra["pad"], np.zeros(len(w), np.float32))
    assert got.control is not None and np.array_equal(got.control.xyz, mission.control.xyz)


def test_custom_type_registered_from_schema(tmp_path):
    path = tmp_path / "custom.mcap"
    with path.open("wb") as stream:
        writer = McapRos2Writer(stream)
        schema = writer.register_msgdef(
            "my_pkg/Tag", "string label\nfloat64[] values\n"
            "================================================================================\n"
            "MSG: my_pkg/Unused\nint32 a\n")
        writer.write_message("/tags", schema, {"label": "hello", "values": [1.5, 2.5]},
                             log_time=7)
        writer.finish()
    with open_bag(path) as reader:
        assert reader.topics["/tags"].msgtype == "my_pkg/msg/Tag"
        [(topic, msgtype, log_ns, raw)] = list(reader.messages())
        msg = reader.deserialize(raw, msgtype, topic=topic)
    assert (topic, log_ns, msg.label) == ("/tags", 7, "hello")
    assert list(msg.values) == [1.5, 2.5]


def test_a_bag_decodes_with_its_own_definitions(tmp_path):
    """A type of a standard name defined otherwise in the bag (an int32 ``data``, where the
    standard std_msgs/String has a string) decodes as the bag defines it."""
    path = tmp_path / "own.mcap"
    with path.open("wb") as stream:
        writer = McapRos2Writer(stream)
        schema = writer.register_msgdef("std_msgs/String", "int32 data\n")
        writer.write_message("/count", schema, {"data": 42}, log_time=5)
        writer.finish()
    with open_bag(path) as reader:
        [(topic, msgtype, _ns, raw)] = list(reader.messages())
        assert reader.deserialize(raw, msgtype, topic=topic).data == 42


def _one_cloud(tmp_path: Path, cloud: np.ndarray) -> tuple[str, int, bytes, str]:
    """``cloud`` written by lidarcal on /lidar/points and read back: its type, log time,
    CDR bytes and the definition text the bag carries."""
    source = tmp_path / "source"
    with BagWriter(source, compress=False) as bag_writer:
        bag_writer.write_cloud("/lidar/points", seconds_to_ns(10.0), "map", cloud)
    with open_bag(source) as reader:
        [(_topic, msgtype, ns, raw)] = list(reader.messages())
        return msgtype, ns, bytes(raw), reader.topics["/lidar/points"].msgdef


def _bare_mcap(path: Path, msgtype: str, definition: str, ns: int, raw: bytes) -> None:
    """One message on /lidar/points in an MCAP file whose schema holds ``definition``
    (written with the mcap project's own writer)."""
    from mcap.writer import Writer

    with path.open("wb") as stream:
        writer = Writer(stream)
        writer.start(profile="ros2", library="test")
        schema = writer.register_schema(name=msgtype, encoding="ros2msg",
                                        data=definition.encode())
        channel = writer.register_channel(topic="/lidar/points", message_encoding="cdr",
                                          schema_id=schema)
        writer.add_message(channel, log_time=ns, data=raw, publish_time=ns)
        writer.finish()


def test_a_type_the_bag_does_not_define_decodes_with_the_standard_one(tmp_path):
    """A channel whose schema carries no definition text: the standard ROS 2 one decodes it."""
    cloud = _points(20, 4, 10.0)
    msgtype, ns, raw, _definition = _one_cloud(tmp_path, cloud)
    path = tmp_path / "bare.mcap"
    _bare_mcap(path, msgtype, "", ns, raw)
    with open_bag(path) as reader:
        assert reader.topics["/lidar/points"].msgdef == ""
        [(topic, msgtype, _ns, raw)] = list(reader.messages())
        msg = reader.deserialize(raw, msgtype, topic=topic)
    assert msg.width == 20
    assert [f.name for f in msg.fields] == list(cloud.dtype.names or ())


def test_a_definition_without_those_it_uses_is_completed_by_the_standard_ones(tmp_path):
    """A schema holding PointCloud2's own fields but not the definitions of the types they
    use (Header, PointField): those come from the standard ROS 2 ones."""
    msgtype, ns, raw, definition = _one_cloud(tmp_path, _points(12, 2, 10.0))
    own_fields = definition.split("=" * 80)[0]
    assert "MSG:" not in own_fields and "std_msgs/Header header" in own_fields
    path = tmp_path / "partial.mcap"
    _bare_mcap(path, msgtype, own_fields, ns, raw)
    with open_bag(path) as reader:
        [(topic, msgtype, _ns, raw)] = list(reader.messages())
        msg = reader.deserialize(raw, msgtype, topic=topic)
    assert (msg.width, msg.header.frame_id) == (12, "map")


def test_a_copy_of_a_bag_needs_no_standard_definitions(tmp_path):
    """Reading a lidarcal bag and writing its messages to another with the reader's
    definitions (as ``lidarcal correct`` does) never builds the standard typestore (every
    ROS 2 release's definitions imported: 0.07 s of each command's start); the copy reads
    back the same."""
    import subprocess
    import sys

    source = tmp_path / "source"
    _small_bag(source)
    script = f"""
import sys
from lidarcal_ros.io.bag.reader import open_bag
from lidarcal_ros.io.bag.writer import BagWriter
with open_bag({str(source)!r}) as bag, BagWriter({str(tmp_path / "copy")!r},
                                                 typestore=bag.typestore) as out:
    for topic, msgtype, ns, raw in bag.messages():
        out.write_raw(topic, msgtype, ns, raw, msgdef=bag.topics[topic].msgdef or None)
print(sorted(m for m in sys.modules if m.startswith("rosbags.typesys.stores.")))
"""
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=60, check=False)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "['rosbags.typesys.stores.empty']"
    with open_bag(source) as a, open_bag(tmp_path / "copy") as b:
        assert list(a.messages()) == list(b.messages())
        assert a.topics == b.topics


def _odometry_raw(stamp_ns: int, frame: str, xyz) -> bytes:
    t = TS.types
    header = t["std_msgs/msg/Header"](
        stamp=t["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9),
        frame_id=frame)
    pose = t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=xyz[0], y=xyz[1], z=xyz[2]),
        orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))
    vec = t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    msg = t["nav_msgs/msg/Odometry"](
        header=header, child_frame_id="imu",
        pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=t["geometry_msgs/msg/TwistWithCovariance"](
            twist=t["geometry_msgs/msg/Twist"](linear=vec, angular=vec), covariance=np.zeros(36)))
    return bytes(TS.serialize_cdr(msg, "nav_msgs/msg/Odometry"))


def _points(n: int, sid: int, t0: float, *, fields=("x", "y", "z", "t", "strip_id")) -> np.ndarray:
    types = {"strip_id": "<u2"}
    arr = np.zeros(n, dtype=[(f, types.get(f, "<f8")) for f in fields])
    for i, f in enumerate(fields):
        if f != "strip_id":
            arr[f] = np.arange(n) * 0.5 + i
    if "t" in fields:
        arr["t"] = t0 + 0.01 * np.arange(n)
    if "strip_id" in fields:
        arr["strip_id"] = sid
    return arr


def _small_bag(path: Path, *, cloud_frame="map", traj_frame="map", odometry=False,
               points=None) -> None:
    pts = _points(50, 3, 100.0) if points is None else points
    with BagWriter(path) as writer:
        writer.write_cloud("/lidar/points", seconds_to_ns(100.0), cloud_frame, pts)
        for k in range(5):
            stamp = seconds_to_ns(99.5 + 0.5 * k)
            xyz = (1.0 * k, 2.0, 1000.0 + k)
            if odometry:
                writer.write_raw("/lidar/trajectory", "nav_msgs/msg/Odometry", stamp,
                                 _odometry_raw(stamp, traj_frame, xyz))
            else:
                writer.write_pose("/lidar/trajectory", stamp, traj_frame, xyz)


def test_odometry_trajectory(tmp_path):
    path = tmp_path / "odom"
    _small_bag(path, odometry=True)
    with open_bag(path) as reader:
        assert reader.topics["/lidar/trajectory"].msgtype == "nav_msgs/msg/Odometry"
    got = read_mission(path)
    assert np.allclose(got.trajectory.t, 99.5 + 0.5 * np.arange(5), rtol=0, atol=1e-9)
    assert got.trajectory.xyz.tolist() == [[float(k), 2.0, 1000.0 + k] for k in range(5)]
    assert [s.strip_id for s in got.strips] == [3] and len(got.strips[0]) == 50
    assert got.control is None


def test_truncated_mcap(tmp_path, bag):
    data = (bag / "mission.mcap").read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(BagError, match=r"cut\.mcap: truncated or corrupt MCAP .*\d+ messages") as e:
        read_mission(cut)
    assert "\n" not in str(e.value)


def test_corrupt_chunk_while_reading(tmp_path):
    path = tmp_path / "damaged.mcap"
    with BagWriter(path) as writer:  # zstd chunks
        for k in range(40):
            writer.write_cloud("/pts", 10**9 + k, "map", _points(2000, 1, float(k)))
    data = bytearray(path.read_bytes())
    start = len(data) // 2  # inside the compressed chunk: wreck the zstd stream
    data[start: start + 64] = b"\xff" * 64
    path.write_bytes(bytes(data))
    with pytest.raises(BagError, match=r"damaged\.mcap: truncated or corrupt"):
        with open_bag(path) as reader:
            for _ in reader.messages():
                pass


def test_missing_topic(bag):
    with pytest.raises(BagError, match=r"topic /nav/pose not found; topics present: "
                                       r"/lidar/control_points, /lidar/points, /lidar/trajectory"):
        read_mission(bag, trajectory_topic="/nav/pose")
    with pytest.raises(BagError, match=r"topic /velodyne_points not found"):
        read_mission(bag, points_topic="/velodyne_points")
    with pytest.raises(BagError, match=r"topic /lidar/trajectory has type geometry_msgs/msg/"
                                       r"PoseStamped; expected sensor_msgs/msg/PointCloud2"):
        read_mission(bag, points_topic="/lidar/trajectory")


def test_frame_mismatch(tmp_path):
    path = tmp_path / "frames"
    _small_bag(path, cloud_frame="utm_32n", traj_frame="odom")
    with pytest.raises(InputError, match=r"frame 'utm_32n' but the trajectory .* frame 'odom'"):
        read_mission(path)


def test_cloud_without_strip_id(tmp_path):
    path = tmp_path / "nostrip"
    _small_bag(path, points=_points(10, 0, 100.0, fields=("x", "y", "z", "t")))
    with pytest.raises(CloudFormatError, match=r"/lidar/points: cloud lacks field 'strip_id'"):
        read_mission(path)


def test_nan_points_dropped(tmp_path, mission, caplog):
    strips = []
    for s in mission.strips:
        xyz, t = s.xyz.copy(), s.t.copy()
        strips.append(Strip(s.strip_id, xyz, t, s.intensity))
    strips[0].xyz[[3, 10], 1] = np.nan
    strips[1].xyz[5, 2] = np.inf
    strips[2].t[7] = np.nan
    m = Mission(mission.trajectory, strips, None, "map")
    path = tmp_path / "nan"
    write_mission_bag(path, m)
    with caplog.at_level(logging.WARNING, logger="lidarcal_ros.io.bag.mission_bag"):
        got = read_mission(path)
    assert got.dropped_non_finite == 4
    assert "dropped 4 points" in caplog.text
    for g, w in zip(got.strips, sorted(strips, key=lambda s: s.strip_id), strict=True):
        ok = np.isfinite(w.xyz).all(axis=1) & np.isfinite(w.t)
        assert np.array_equal(g.xyz, w.xyz[ok]) and np.array_equal(g.t, w.t[ok])
    assert got.control is None


def test_control_topic_options(bag, mission):
    assert read_mission(bag, control_topic=None).control is None
    assert read_mission(bag, control_topic="/gcp").control is None


def test_multi_file_bag_merged_by_time(tmp_path):
    bagdir = tmp_path / "split"
    bagdir.mkdir()
    for name, offset in (("split_0.mcap", 0), ("split_1.mcap", 5)):
        with BagWriter(bagdir / name) as writer:
            for k in range(5):
                writer.write_pose("/pose", 10 * k + offset, "map", (k, offset, 0))
    (bagdir / "metadata.yaml").write_text(
        "rosbag2_bagfile_information:\n  version: 8\n  storage_identifier: mcap\n"
        "  relative_file_paths: [split_0.mcap, split_1.mcap]\n  compression_mode: ''\n"
        "  compression_format: ''\n  topics_with_message_count: []\n")
    with open_bag(bagdir) as reader:
        assert reader.topics["/pose"].count == 10
        times = [m[2] for m in reader.messages(["/pose"])]
    assert times == [0, 5, 10, 15, 20, 25, 30, 35, 40, 45]


def test_open_errors(tmp_path):
    with pytest.raises(BagError, match=r"nowhere: no such bag"):
        open_bag(tmp_path / "nowhere")
    empty = tmp_path / "emptydir"
    empty.mkdir()
    with pytest.raises(BagError, match=r"emptydir: not a rosbag2 bag"):
        open_bag(empty)
    sq = tmp_path / "sq"
    sq.mkdir()
    (sq / "metadata.yaml").write_text(
        "rosbag2_bagfile_information:\n  version: 5\n  storage_identifier: sqlite3\n"
        "  relative_file_paths: [sq_0.db3]\n")
    with pytest.raises(BagError, match=r"sq: storage 'sqlite3' is not supported"):
        open_bag(sq)
    db3 = tmp_path / "x.db3"
    db3.write_bytes(b"SQLite format 3\x00" + b"\0" * 100)
    with pytest.raises(BagError, match=r"x\.db3: sqlite3 storage is not supported"):
        open_bag(db3)
    txt = tmp_path / "notes.mcap"
    txt.write_text("hello, not an mcap file\n")
    with pytest.raises(BagError, match=r"notes\.mcap: not an MCAP file"):
        open_bag(txt)


def test_overwrite(tmp_path, mission):
    path = tmp_path / "out"
    write_mission_bag(path, mission)
    with pytest.raises(OutputError, match=r"out: exists \(use --overwrite to replace it\)"):
        write_mission_bag(path, mission)
    small = Mission(mission.trajectory, mission.strips[:1], None, "map")
    write_mission_bag(path, small, overwrite=True)
    assert [s.strip_id for s in read_mission(path).strips] == [7]
    other = tmp_path / "project"
    other.mkdir()
    (other / "notes.txt").write_text("keep me")
    with pytest.raises(OutputError, match=r"refusing to overwrite a directory that is not a bag"):
        write_mission_bag(other, mission, overwrite=True)
    assert (other / "notes.txt").read_text() == "keep me"


def test_failed_write_leaves_nothing(tmp_path, mission):
    path = tmp_path / "broken"
    with pytest.raises(RuntimeError), BagWriter(path) as writer:
        writer.write_pose("/p", 1, "map", (0.0, 0.0, 0.0))
        raise RuntimeError("boom")
    assert not path.exists()


def test_control_csv_matches_bag_control(tmp_path, bag, mission):
    from lidarcal_ros.io.survey.control import read_control_csv, write_control_csv

    csv = tmp_path / "gcp.csv"
    write_control_csv(csv, mission.control)
    from_csv = read_control_csv(csv)
    from_bag = read_mission(bag).control
    assert from_csv.ids == ["a", "b", "c"]
    assert from_bag is not None and np.array_equal(from_csv.xyz, from_bag.xyz)
    loose = tmp_path / "loose.csv"
    loose.write_text(" ID , z, x ,y \n\n# surveyed 2024\n P1 , 41.5 , 10 , 20\nP2,1e1,-3,4\n")
    got = read_control_csv(loose)
    assert got.ids == ["P1", "P2"] and got.xyz.tolist() == [[10, 20, 41.5], [-3, 4, 10]]
    for text, pattern in (
        ("id,x,y\nA,1,2\n", r"bad\.csv: line 1: header lacks column\(s\) z"),
        ("id,x,y,z\nA,1,2,3\nB,1,two,3\n", r"bad\.csv: line 3: y value 'two' is not a number"),
        ("id,x,y,z\n", r"bad\.csv: no control points"),
        ("", r"bad\.csv: empty control point file"),
    ):
        (tmp_path / "bad.csv").write_text(text)
        with pytest.raises(InputError, match=pattern):
            read_control_csv(tmp_path / "bad.csv")
    with pytest.raises(InputError, match=r"nope\.csv: control point file not found"):
        read_control_csv(tmp_path / "nope.csv")


def test_chunks_compressed_in_threads_keep_order_and_bytes(tmp_path, monkeypatch):
    """Many chunks, compressed out of order by the storage's threads, are written in order:
    the mcap project's reader gives back every message and its bytes in log-time order, and
    each chunk says how it is compressed."""
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader

    from lidarcal_ros.io.bag import chunk_writer as mcap_chunk_writer

    monkeypatch.setattr(mcap_chunk_writer, "CHUNK_BYTES", 20_000)
    rng = np.random.default_rng(5)
    written = []
    out = tmp_path / "many.mcap"
    with BagWriter(out) as writer:
        for k in range(400):
            raw = rng.integers(0, 4, rng.integers(100, 3000)).astype(np.uint8).tobytes()
            topic = "/a" if k % 3 else "/b"
            written.append((topic, 1_000 + 10 * k, raw))
            writer.write_raw(topic, "std_msgs/msg/String", 1_000 + 10 * k, raw)
    with out.open("rb") as stream:
        chunks = [r for r in StreamReader(stream, emit_chunks=True).records
                  if isinstance(r, Chunk)]
    assert len(chunks) > 2 * mcap_chunk_writer.MAX_PENDING
    assert {c.compression for c in chunks} == {"zstd"}
    with out.open("rb") as stream:
        got = [(c.topic, m.log_time, bytes(m.data)) for _s, c, m in
               make_reader(stream).iter_messages(log_time_order=True)]
    assert got == written
    with open_bag(out) as bag:
        assert [(t, ns, bytes(raw)) for t, _ty, ns, raw in bag.messages()] == written


def test_chunks_read_ahead_give_rosbags_messages(bag, tmp_path, monkeypatch):
    """Chunks decompressed ahead in threads give the messages, bytes and order of rosbags'
    reader (a bag of ours, and one whose chunks overlap in time, which rosbags merges)."""
    from rosbags.rosbag2.storage_mcap import McapReader

    from lidarcal_ros.io.bag import chunk_reader as mcap_chunk_reader
    from lidarcal_ros.io.bag import reader as bag_module

    def read(path: Path, topics: list[str] | None = None) -> list[tuple[str, str, int, bytes]]:
        with open_bag(path) as reader:
            return [(t, ty, ns, bytes(raw)) for t, ty, ns, raw in reader.messages(topics)]

    def chunk_index(path: Path) -> list:
        """The chunk index of an MCAP file, as rosbags' reader holds it."""
        mcap = McapReader(path)
        mcap.open()
        try:
            return list(mcap.chunks)
        finally:
            mcap.close()

    overlapping = tmp_path / "overlap.mcap"
    with BagWriter(overlapping) as writer:
        for k in range(300):  # two topics written out of time order: chunks overlap
            writer.write_raw("/a" if k % 2 else "/b", "std_msgs/msg/String",
                             10_000 + (k % 7) * 1000 + k, bytes([k % 256]) * 5000)
    in_order = tmp_path / "in_order.mcap"
    with BagWriter(in_order) as writer:
        for k in range(900):  # many chunks, equal log times across their boundaries
            writer.write_raw("/a" if k % 3 else "/b", "std_msgs/msg/String",
                             10_000 + k // 4, bytes([k % 256]) * 5000)
    assert not mcap_chunk_reader.in_time_order(chunk_index(overlapping))
    chunks = chunk_index(in_order)
    assert len(chunks) > 3 and mcap_chunk_reader.in_time_order(chunks)
    cases = [(bag, None), (bag, ["/lidar/trajectory"]), (in_order, None), (in_order, ["/b"]),
             (overlapping, None)]
    fast = [read(path, topics) for path, topics in cases]
    monkeypatch.setattr(bag_module, "chunk_messages", lambda reader, channels: None)
    assert fast == [read(path, topics) for path, topics in cases]
    assert len(fast[0]) > len(fast[1]) > 0


def test_poses_read_from_their_bytes_are_those_decoded():
    """A PoseStamped read straight from its CDR bytes gives the numbers and frame of its
    decoded message, whatever the frame id's length (and so its padding); other types and
    big-endian bytes go through the decoder."""
    from lidarcal_ros.io.bag.format import POSE_STAMPED
    from lidarcal_ros.io.cloud.trajectory_messages import TrajectorySamples

    types = TS.types
    rng = np.random.default_rng(9)
    raws = []
    for k, frame in enumerate(["", "m", "map", "utm32", "odom_ned", "a" * 9, "éé", "x" * 31]):
        pose = types["geometry_msgs/msg/Pose"](
            position=types["geometry_msgs/msg/Point"](*rng.normal(0, 1e5, 3)),
            orientation=types["geometry_msgs/msg/Quaternion"](*rng.normal(0, 1, 4)))
        msg = types[POSE_STAMPED](header=types["std_msgs/msg/Header"](
            stamp=types["builtin_interfaces/msg/Time"](sec=1_700_000_000 + k,
                                                       nanosec=123_456_789 * k % 10**9),
            frame_id=frame), pose=pose)
        raws.append(bytes(TS.serialize_cdr(msg, POSE_STAMPED)))
        raws.append(bytes(TS.serialize_cdr(msg, POSE_STAMPED, little_endian=False)))
    decoded = []

    def decode(raw, msgtype):
        decoded.append(msgtype)
        return TS.deserialize_cdr(raw, msgtype)

    fast, slow = TrajectorySamples(), TrajectorySamples()
    for raw in raws:
        fast.add_raw(POSE_STAMPED, raw, decode)
        slow.add(POSE_STAMPED, TS.deserialize_cdr(raw, POSE_STAMPED))
    assert len(decoded) == len(raws) // 2  # the big-endian ones
    for name in ("t", "xyz", "orientation"):
        assert getattr(fast, name) == getattr(slow, name)
    assert fast.frames == slow.frames and len(fast.frames) == 8
