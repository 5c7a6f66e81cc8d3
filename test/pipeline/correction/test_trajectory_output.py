"""The corrected trajectory (docs/method.md section 11): ``lidarcal correct``'s topic
``/lidar/trajectory_corrected`` and ``--trajectory-out``, read back with rosbags and numpy."""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from helpers_cli import one_line_error, run, run_process
from helpers_missions import SMALL_MISSION, write_calibration_yaml

from lidarcal_ros.core.georeferencing.attitude import quaternions_from_attitude
from lidarcal_ros.core.mission import Trajectory
from lidarcal_ros.core.simulation.simulate import SimulatedMission, simulate_mission
from lidarcal_ros.core.simulation.spec import TYPICAL_TRAJECTORY_ERRORS, SimulationSpec
from lidarcal_ros.core.trajectory.strip_errors import (
    POSE_BETWEEN_STRIPS,
    POSE_BEYOND_STRIPS,
    POSE_IN_STRIP,
    StripError,
    TrajectoryEstimate,
    TrajectoryModel,
    trajectory_corrections,
)
from lidarcal_ros.io.calibration_file import read_calibration, trajectory_document
from lidarcal_ros.io.survey.trajectory_crs import (
    SBET_CRS,
    map_orientation,
    project,
    write_sbet_trajectory,
)
from lidarcal_ros.io.survey.trajectory_files import (
    SBET_FIELDS,
    WEEK_S,
    gps_to_unix,
    read_ascii_trajectory,
    read_sbet,
    write_ascii_trajectory,
)
from lidarcal_ros.pipeline.calibration.procedure import write_simulation

DELIVERED, CORRECTED = "/lidar/trajectory", "/lidar/trajectory_corrected"


@dataclass(frozen=True)
class Drifting:
    """A small mission flown with typical trajectory errors, its bag and a calibration file
    holding the true biases and each strip's true offset and drift (not its oscillation)."""

    sim: SimulatedMission
    bag: Path
    truth: Path
    calibration: Path
    plain: Path  # the same biases, no trajectory block
    workdir: Path


@cache
def _simulated() -> SimulatedMission:
    spec = SimulationSpec.from_options(**SMALL_MISSION)
    return simulate_mission(replace(spec, trajectory_errors=TYPICAL_TRAJECTORY_ERRORS))


@pytest.fixture(scope="module")
def drifting(tmp_path_factory: pytest.TempPathFactory) -> Drifting:
    work = tmp_path_factory.mktemp("drifting")
    sim = _simulated()
    paths = write_simulation(work / "mission", sim)
    estimate = TrajectoryEstimate(TrajectoryModel.DRIFT, {
        sid: StripError.linear(sid, err.t_ref, np.array(err.offset), np.full(3, 0.01),
                        np.array(err.drift), np.full(3, 0.001))
        for sid, err in sim.trajectory_errors.items()})
    plain = write_calibration_yaml(work / "plain.yaml", sim.biases)
    doc = yaml.safe_load(plain.read_text())
    doc["lidarcal_calibration"]["trajectory"] = trajectory_document(estimate)
    doc["lidarcal_calibration"]["trajectory_model"] = "drift"
    calibration = work / "cal.yaml"
    calibration.write_text(yaml.safe_dump(doc, sort_keys=False))
    return Drifting(sim, paths["bag"], paths["truth"], calibration, plain, work)


def _poses(bag: Path) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]]:
    """Per trajectory topic of ``bag``, read with rosbags: stamps (s), positions (n, 3),
    orientations (n, 4) and message types, in log-time order."""
    from rosbags.highlevel import AnyReader

    out: dict[str, tuple[list, list, list, list]] = {}
    with AnyReader([bag]) as reader:
        connections = [c for c in reader.connections if c.topic in (DELIVERED, CORRECTED)]
        for conn, _ns, raw in reader.messages(connections=connections):
            msg: Any = reader.deserialize(raw, conn.msgtype)
            t, xyz, q, types = out.setdefault(conn.topic, ([], [], [], []))
            t.append(msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9)
            p, o = msg.pose.position, msg.pose.orientation
            xyz.append((p.x, p.y, p.z))
            q.append((o.x, o.y, o.z, o.w))
            types.append(conn.msgtype)
    return {k: (np.array(t), np.array(xyz), np.array(q), types)
            for k, (t, xyz, q, types) in out.items()}


def _table(path: Path) -> dict[str, np.ndarray]:
    """An ASCII trajectory read with numpy alone: its columns by the header's names."""
    lines = [ln for ln in path.read_text().splitlines() if not ln.startswith("#")]
    data = np.loadtxt(lines[1:], delimiter=",", ndmin=2)
    return dict(zip(lines[0].split(","), data.T, strict=True))


def _spans(sim: SimulatedMission) -> dict[int, tuple[float, float]]:
    return {s.strip_id: (float(s.t.min()), float(s.t.max())) for s in sim.mission.strips}


def _expected_errors(sim: SimulatedMission, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The error the correction should remove at ``t`` (written out here from the rule:
    the strip's offset + drift inside its points' times, linear between strips, held
    beyond), and which samples lie in a strip."""
    spans = sorted((a, b, sid) for sid, (a, b) in _spans(sim).items())

    def e(sid: int, tt: np.ndarray) -> np.ndarray:
        err = sim.trajectory_errors[sid]
        return np.asarray(err.offset) + (tt - err.t_ref)[:, None] * np.asarray(err.drift)

    knots_t = [x for a, b, _ in spans for x in (a, b)]
    knots_e = np.vstack([e(sid, np.array([a, b])) for a, b, sid in spans])
    want = np.column_stack([np.interp(t, knots_t, knots_e[:, k]) for k in range(3)])
    inside = np.zeros(t.shape, bool)
    for a, b, sid in spans:
        on = (t >= a) & (t <= b)
        want[on] = e(sid, t[on])
        inside |= on
    return want, inside


def _true_positions(sim: SimulatedMission, t: np.ndarray) -> np.ndarray:
    true = sim.true_trajectory
    assert true is not None
    k = np.searchsorted(true.t, t - 1e-6)  # (an ASCII file's times: to the microsecond)
    np.testing.assert_allclose(true.t[k], t, rtol=0, atol=1e-6)
    return true.xyz[k]


def test_the_corrected_topic_is_the_delivered_trajectory_less_each_strip_s_error(
        drifting: Drifting, capsys: pytest.CaptureFixture[str]) -> None:
    """Every delivered pose comes again on /lidar/trajectory_corrected, same stamp, type and
    orientation, its position the delivered one less ``e_hat_s(t)`` inside its strip's
    times and the interpolation between strips (1e-9 m); the corrected trajectory is within
    1 cm (median, each axis) of the true one, under a third of the delivered's distance;
    the ASCII file holds the same positions."""
    out, text = drifting.workdir / "out.mcap", drifting.workdir / "traj.csv"
    rc, stdout, err = run(capsys, "correct", drifting.bag, "--calibration",
                          drifting.calibration, "-o", out, "--trajectory-out", text, "-q")
    assert rc == 0, err
    assert f"-> {CORRECTED} (" in stdout and f"-> {text} (" in stdout
    poses = _poses(out)
    t, xyz, q, types = poses[DELIVERED]
    t2, xyz2, q2, types2 = poses[CORRECTED]
    assert types2 == types and set(types) == {"geometry_msgs/msg/PoseStamped"}
    np.testing.assert_array_equal(t2, t)
    np.testing.assert_array_equal(q2, q)
    want, inside = _expected_errors(drifting.sim, t)
    assert inside.sum() > 0.3 * len(t) and (~inside).sum() > 0
    np.testing.assert_allclose(xyz - xyz2, want, rtol=0, atol=1e-9)
    true = _true_positions(drifting.sim, t)
    # (what is left is each strip's 1 cm oscillation, which a drift does not model)
    before, after = np.abs(xyz - true), np.abs(xyz2 - true)
    assert (np.median(after, axis=0) < 0.01).all()
    assert (np.median(after[inside], axis=0) < 0.01).all()
    assert np.median(np.linalg.norm(after, axis=1)) < 0.3 * np.median(
        np.linalg.norm(before, axis=1))
    # the ASCII file, read with numpy alone
    table = _table(text)
    assert list(table) == ["time", "x", "y", "z"]  # (this mission has no attitude)
    np.testing.assert_allclose(table["time"], t, rtol=0, atol=1e-6)
    np.testing.assert_allclose(np.column_stack([table["x"], table["y"], table["z"]]), xyz2,
                               rtol=0, atol=6e-5)


def test_a_bag_pass_and_a_las_output_write_the_same_trajectory_file(
        drifting: Drifting, capsys: pytest.CaptureFixture[str]) -> None:
    """The bag read once or twice (trajectory first), into a bag or a LAS file: the same
    ASCII trajectory; ``--overwrite`` replaces it, without it an existing file is refused
    in one line before any work."""
    first = drifting.workdir / "first.csv"
    rc, _, err = run(capsys, "correct", drifting.bag, "--calibration", drifting.calibration,
                     "-o", drifting.workdir / "first.mcap", "--trajectory-out", first, "-q")
    assert rc == 0, err
    from lidarcal_ros.core.config import FlightConfig
    from lidarcal_ros.pipeline.correction.bag import CorrectOptions, correct_bag

    second = drifting.workdir / "second.csv"
    report = correct_bag(drifting.bag, drifting.calibration, drifting.workdir / "two.mcap",
                         FlightConfig(), CorrectOptions(max_held_points=0,
                                                        trajectory_out=second))
    assert CORRECTED in report.trajectory
    assert second.read_text().splitlines()[1:] == first.read_text().splitlines()[1:]
    las = drifting.workdir / "third.csv"
    rc, _, err = run(capsys, "correct", drifting.bag, "--calibration", drifting.calibration,
                     "-o", drifting.workdir / "out.laz", "--trajectory-out", las, "-q")
    assert rc == 0, err
    assert las.read_text().splitlines()[1:] == first.read_text().splitlines()[1:]
    rc, _, err = run(capsys, "correct", drifting.bag, "--calibration", drifting.calibration,
                     "-o", drifting.workdir / "again.mcap", "--trajectory-out", first, "-q")
    assert one_line_error(rc, err, "correct").endswith("exists (use --overwrite to replace it)")
    assert not (drifting.workdir / "again.mcap").exists()
    first.write_text("old\n")
    rc, _, err = run(capsys, "correct", drifting.bag, "--calibration", drifting.calibration,
                     "-o", drifting.workdir / "again.mcap", "--trajectory-out", first, "-q",
                     "--overwrite")
    assert rc == 0, err
    assert first.read_text().splitlines()[1:] == las.read_text().splitlines()[1:]
    rc, _, err = run(capsys, "correct", drifting.bag, "--calibration", drifting.calibration,
                     "-o", drifting.workdir / "new.mcap", "--trajectory-out",
                     drifting.workdir / "missing" / "t.csv", "-q")
    assert "missing" in one_line_error(rc, err, "correct")
    assert not (drifting.workdir / "new.mcap").exists()


def test_without_a_trajectory_block_no_topic_and_the_file_as_delivered(
        drifting: Drifting, capsys: pytest.CaptureFixture[str]) -> None:
    """A calibration without trajectory errors: the corrected bag has no corrected
    trajectory topic; ``--trajectory-out`` writes the delivered trajectory and says so."""
    out, text = drifting.workdir / "plain.mcap", drifting.workdir / "plain.csv"
    rc, stdout, err = run(capsys, "correct", drifting.bag, "--calibration", drifting.plain,
                          "-o", out, "--trajectory-out", text, "-q")
    assert rc == 0, err
    poses = _poses(out)
    assert CORRECTED not in poses
    assert "holds no trajectory errors" in stdout + err
    table = _table(text)
    _t, xyz, _q, _types = poses[DELIVERED]
    np.testing.assert_allclose(np.column_stack([table["x"], table["y"], table["z"]]), xyz,
                               rtol=0, atol=6e-5)


def test_a_calibrated_drift_corrects_the_trajectory_s_heights(
        drifting: Drifting, capsys: pytest.CaptureFixture[str]) -> None:
    """``lidarcal calibrate`` (default: auto, drift chosen) then ``correct``: the corrected
    trajectory's heights are within 1 cm (median) of the true ones, the delivered ones
    centimetres off. No claim horizontally: there the strips' offsets also carry the lever arm
    and boresight held fixed where the data cannot determine them (docs/method.md section 11)."""
    cal, text = drifting.workdir / "calibrated.yaml", drifting.workdir / "calibrated.csv"
    proc = run_process("calibrate", drifting.bag, "-o", cal, "-q", cwd=Path.cwd())
    assert proc.returncode == 0, proc.stderr
    assert read_calibration(cal).trajectory is not None
    rc, _, err = run(capsys, "correct", drifting.bag, "--calibration", cal, "-o",
                     drifting.workdir / "calibrated.mcap", "--trajectory-out", text, "-q")
    assert rc == 0, err
    back = read_ascii_trajectory(text)
    true = _true_positions(drifting.sim, back.t)
    delivered = drifting.sim.mission.trajectory.xyz
    assert np.median(np.abs(back.c - true[:, 2])) < 0.01
    assert np.median(np.abs(delivered[:, 2] - true[:, 2])) > 0.02


# ---------------------------------------------------------------------- the parts
def test_corrections_in_strips_between_and_beyond() -> None:
    """Inside a strip its ``e_s(t)``; between two strips the straight line from the first's
    end value to the second's start value; before the first and after the last the end
    values held; a strip without an estimate zero; overlapping strips: the later one."""
    a = StripError.linear(1, 15.0, np.array([0.1, 0.0, 0.0]), np.zeros(3),
                          np.array([0.0, 0.0, 0.01]), np.zeros(3))
    b = StripError.linear(2, 45.0, np.array([0.0, 0.2, 0.0]), np.zeros(3), np.zeros(3), np.zeros(3))
    estimate = TrajectoryEstimate(TrajectoryModel.DRIFT, {1: a, 2: b})
    spans = {1: (10.0, 20.0), 2: (40.0, 50.0), 3: (60.0, 70.0)}
    t = np.array([0.0, 10.0, 15.0, 20.0, 30.0, 40.0, 55.0, 65.0, 80.0, np.nan])
    got = trajectory_corrections(estimate, spans, t)
    end1 = np.array([0.1, 0.0, 0.05])
    want = np.array([[0.1, 0.0, -0.05], [0.1, 0.0, -0.05], [0.1, 0.0, 0.0], end1,
                     0.5 * end1 + 0.5 * np.array([0.0, 0.2, 0.0]), [0.0, 0.2, 0.0],
                     [0.0, 0.1, 0.0], [0, 0, 0], [0, 0, 0], [0, 0, 0]])
    want[0] = a.error(np.array([10.0]))[0]  # (held at the first strip's start)
    np.testing.assert_allclose(got.errors, want, atol=1e-12)
    inside, between, beyond = POSE_IN_STRIP, POSE_BETWEEN_STRIPS, POSE_BEYOND_STRIPS
    assert got.source.tolist() == [beyond, inside, inside, inside, between, inside, between,
                                   inside, beyond, beyond]
    assert got.counts() == (5, 2, 3)
    overlap = trajectory_corrections(estimate, {1: (10.0, 45.0), 2: (40.0, 50.0)},
                                     np.array([42.0]))
    np.testing.assert_allclose(overlap.errors[0], b.error(np.array([42.0]))[0])
    none = trajectory_corrections(estimate, {}, np.array([1.0, 2.0]))
    assert not none.errors.any() and (none.source == POSE_BEYOND_STRIPS).all()


def test_strip_sigma_grows_with_time_from_t_ref() -> None:
    se = StripError.linear(1, 100.0, np.zeros(3), np.array([0.03, 0.04, 0.0]), np.zeros(3),
                    np.array([0.0, 0.003, 0.001]))
    np.testing.assert_allclose(se.sigma_at(np.array([100.0, 110.0])),
                               [[0.03, 0.04, 0.0], [0.03, 0.05, 0.01]])
    offset_only = StripError.linear(1, 100.0, np.zeros(3), np.array([0.02, 0.02, 0.03]))
    np.testing.assert_allclose(offset_only.sigma_at(np.array([0.0])), [[0.02, 0.02, 0.03]])


def test_ascii_trajectory_with_attitude_reads_back_as_written(tmp_path: Path) -> None:
    """Roll, pitch and heading written in degrees as an SBET's: read back and turned into
    the map's quaternions by the import's own conversion, the same orientation; positions
    to 0.1 mm; a levelled trajectory gets a heading column alone."""
    rng = np.random.default_rng(3)
    n = 50
    t = 1.7e9 + np.arange(n) * 0.02
    roll, pitch = rng.uniform(-0.2, 0.2, n), rng.uniform(-0.1, 0.1, n)
    kappa = rng.uniform(-3.0, 3.0, n)
    q = quaternions_from_attitude(roll, pitch, kappa)
    xyz = np.column_stack([5e5 + rng.uniform(0, 1e3, n), 5.5e6 + rng.uniform(0, 1e3, n),
                           rng.uniform(900, 1100, n)])
    path = write_ascii_trajectory(tmp_path / "t.csv", Trajectory(t, xyz, q),
                                  comments=["a comment"])
    back = read_ascii_trajectory(path)
    assert back.attitude == "roll, pitch, heading"
    np.testing.assert_allclose(back.t, t, atol=1e-6)
    np.testing.assert_allclose(np.column_stack([back.a, back.b, back.c]), xyz, atol=6e-5)
    q_back, full = map_orientation(back, None, None)
    assert full and q_back is not None
    # (q and -q are one rotation)
    np.testing.assert_allclose(np.abs(np.sum(q_back * q, axis=1)), 1.0, atol=1e-9)
    level = Trajectory(t, xyz, quaternions_from_attitude(0.0 * kappa, 0.0 * kappa, kappa))
    assert not level.full_attitude
    back = read_ascii_trajectory(write_ascii_trajectory(tmp_path / "level.csv", level))
    assert back.attitude == "heading" and back.heading_deg is not None
    # (heading clockwise from north = -kappa)
    np.testing.assert_allclose(np.cos(np.radians(back.heading_deg) + kappa), 1.0, atol=1e-12)


def test_an_odometry_pose_keeps_all_but_its_position() -> None:
    """A non-PoseStamped trajectory message is decoded, moved and encoded again: the
    position changes, stamp, frames, orientation, twist and covariances stay."""
    from lidarcal_ros.io.bag.format import ODOMETRY, POSE_STAMPED, standard_typestore
    from lidarcal_ros.io.cloud.trajectory_messages import moved_message

    store = standard_typestore()
    types = store.types
    header = types["std_msgs/msg/Header"](
        stamp=types["builtin_interfaces/msg/Time"](sec=17, nanosec=5), frame_id="map")
    pose: Any = types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=1.0, y=2.0, z=3.0),
        orientation=types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.6, w=0.8))
    cov = np.arange(36, dtype=np.float64)
    twist = types["geometry_msgs/msg/Twist"](
        linear=types["geometry_msgs/msg/Vector3"](x=60.0, y=0.5, z=0.1),
        angular=types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.01))
    odom = types[ODOMETRY](
        header=header, child_frame_id="base_link",
        pose=types["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=cov),
        twist=types["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=cov * 2))
    raw = bytes(store.serialize_cdr(odom, ODOMETRY))
    out = moved_message(ODOMETRY, raw, (4.0, 5.0, 6.0), store.deserialize_cdr,
                        store.serialize_cdr)
    back: Any = store.deserialize_cdr(out, ODOMETRY)
    p = back.pose.pose.position
    assert (p.x, p.y, p.z) == (4.0, 5.0, 6.0)
    assert back.child_frame_id == "base_link" and back.header.stamp.nanosec == 5
    assert back.pose.pose.orientation.z == 0.6 and back.twist.twist.linear.x == 60.0
    np.testing.assert_array_equal(back.twist.covariance, cov * 2)
    # a PoseStamped is patched in its bytes: the same as through the typestore
    stamped = types[POSE_STAMPED](header=header, pose=pose)
    raw = bytes(store.serialize_cdr(stamped, POSE_STAMPED))
    patched = moved_message(POSE_STAMPED, raw, (4.0, 5.0, 6.0), store.deserialize_cdr,
                            store.serialize_cdr)
    pose.position.x, pose.position.y, pose.position.z = 4.0, 5.0, 6.0
    assert patched == bytes(store.serialize_cdr(stamped, POSE_STAMPED))


# ---------------------------------------------------------------------- SBET output
def _from_sbet(path: Path, map_crs: str) -> tuple[Any, np.ndarray, np.ndarray | None, bool]:
    """An SBET read back as ``lidarcal import`` reads one: the file, its positions in the
    map (m) and its map-frame orientation (the import's own conversion)."""
    import pyproj

    back = read_sbet(path)
    source, target = pyproj.CRS(SBET_CRS), pyproj.CRS(map_crs)
    q, full = map_orientation(back, source, target)
    return back, project(back, source, target), q, full


def test_an_sbet_trajectory_out_reads_back_as_the_corrected_positions(
        drifting: Drifting, capsys: pytest.CaptureFixture[str]) -> None:
    """``--trajectory-out X.out --crs EPSG:32633``: an SBET whose records, read back and
    projected to the map by the import's own path, are the corrected topic's positions
    (1 mm) at its stamps (GPS week seconds, 1 us); the layout checked with numpy alone (17
    little-endian float64 a record, time increasing, velocities the positions' rate).
    Without ``--crs``: refused in one line before any work, nothing written."""
    out, sbet = drifting.workdir / "sbet.mcap", drifting.workdir / "corrected.out"
    rc, stdout, err = run(capsys, "correct", drifting.bag, "--calibration",
                          drifting.calibration, "-o", out, "--trajectory-out", sbet,
                          "--crs", "EPSG:32633", "-q")
    assert rc == 0, err
    assert f"-> {sbet} (SBET" in stdout and "GPS week" in stdout
    assert "--crs applies" not in stdout + err
    t, xyz2, _q, _types = _poses(out)[CORRECTED]
    back, xyz, q, _full = _from_sbet(sbet, "EPSG:32633")
    assert q is None and back.heading_deg is None  # (this mission has no attitude)
    np.testing.assert_allclose(xyz, xyz2, rtol=0, atol=1e-3)
    week = int(np.floor((t[0] - 315_964_800 + 18) / WEEK_S))
    np.testing.assert_allclose(gps_to_unix(back.t + week * WEEK_S), t, rtol=0, atol=1e-6)
    raw = np.fromfile(sbet, dtype="<f8")
    assert raw.size == 17 * len(t) and len(SBET_FIELDS) == 17
    records = raw.reshape(-1, 17)
    assert np.all(np.diff(records[:, 0]) > 0) and 0 <= records[0, 0] < WEEK_S
    np.testing.assert_allclose(np.degrees(records[:, 1:3]), np.column_stack([back.b, back.a]))
    speed = np.hypot(records[:, 4], records[:, 5])
    track = np.hypot(*np.gradient(xyz2[:, :2], t, axis=0).T)
    np.testing.assert_allclose(speed, track, rtol=1e-6)
    assert not records[:, 7:].any()  # (no attitude, wander angle, accelerations or rates)
    refused = drifting.workdir / "refused.out"
    rc, _, err = run(capsys, "correct", drifting.bag, "--calibration", drifting.calibration,
                     "-o", drifting.workdir / "refused.mcap", "--trajectory-out", refused, "-q")
    assert one_line_error(rc, err, "correct") == (
        f"--trajectory-out {refused}: an SBET needs the map's CRS; give --crs EPSG:...")
    assert not refused.exists() and not (drifting.workdir / "refused.mcap").exists()
    rc, _, err = run(capsys, "correct", drifting.bag, "--calibration", drifting.calibration,
                     "-o", drifting.workdir / "refused.mcap", "--trajectory-out", refused,
                     "--crs", "EPSG:4326", "-q")
    assert "is not projected" in one_line_error(rc, err, "correct")
    assert not refused.exists() and not (drifting.workdir / "refused.mcap").exists()


def test_an_sbet_with_attitude_reads_back_as_written(tmp_path: Path) -> None:
    """Roll, pitch and heading in UTM 33N 2 degrees off its central meridian (a meridian
    convergence of some 1.5 degrees): read back and turned into the map's quaternions by the
    import's conversion, the same orientation (1e-9 rad) and positions (1 mm); the SBET's
    heading is the true one (grid heading less the convergence); a heading-only trajectory
    comes back heading only, one without orientation positions only; an existing file is
    refused without ``overwrite``."""
    rng = np.random.default_rng(5)
    n = 40
    t = 1.7e9 + np.arange(n) * 0.005
    roll, pitch = rng.uniform(-0.2, 0.2, n), rng.uniform(-0.1, 0.1, n)
    kappa = rng.uniform(-3.0, 3.0, n)
    xyz = np.column_stack([352_000.0 + 50.0 * np.arange(n) * 0.005, 5_400_000.0 + np.zeros(n),
                           rng.uniform(900, 1100, n)])
    q = quaternions_from_attitude(roll, pitch, kappa)
    path, week = write_sbet_trajectory(tmp_path / "t.sbet", Trajectory(t, xyz, q), _utm33())
    assert week is not None and week > 2000
    back, xyz_back, q_back, full = _from_sbet(path, "EPSG:32633")
    assert full and q_back is not None and back.attitude == "roll, pitch, heading"
    np.testing.assert_allclose(xyz_back, xyz, rtol=0, atol=1e-3)
    r2, p2, k2 = (np.asarray(v) for v in _attitude(q_back))
    np.testing.assert_allclose(r2, roll, rtol=0, atol=1e-9)
    np.testing.assert_allclose(p2, pitch, rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.angle(np.exp(1j * (k2 - kappa))), 0.0, rtol=0, atol=1e-9)
    # the file's heading is true north's: the grid heading less the convergence (~ -1.5 deg)
    turn = np.angle(np.exp(1j * (np.radians(back.heading_deg) + kappa)))
    assert np.all(np.abs(np.degrees(turn) + 1.5) < 0.2)
    # the track flown east along grid x: the velocity east of true north, 50 m/s
    records = np.fromfile(path, dtype="<f8").reshape(-1, 17)
    # (UNIX stamps hold 0.24 us: 5 ms apart, a rate to 1e-4)
    np.testing.assert_allclose(np.hypot(records[:, 4], records[:, 5]), 50.0, rtol=1e-4)
    assert np.all(records[:, 4] > 0.0)  # (grid east is north of true east west of the CM)
    level = Trajectory(t, xyz, quaternions_from_attitude(0 * kappa, 0 * kappa, kappa))
    path, _ = write_sbet_trajectory(tmp_path / "level.out", level, _utm33())
    back, _, q_back, full = _from_sbet(path, "EPSG:32633")
    assert back.attitude == "heading" and not full and q_back is not None
    none, _ = write_sbet_trajectory(tmp_path / "none.out", Trajectory(t, xyz), _utm33())
    assert read_sbet(none).attitude == "none"
    from lidarcal_ros.errors import OutputError

    with pytest.raises(OutputError, match="exists"):
        write_sbet_trajectory(none, Trajectory(t, xyz), _utm33())


def _utm33() -> Any:
    import pyproj

    return pyproj.CRS("EPSG:32633")


def _attitude(q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    from lidarcal_ros.core.georeferencing.attitude import attitude_from_quaternions

    return attitude_from_quaternions(q)
