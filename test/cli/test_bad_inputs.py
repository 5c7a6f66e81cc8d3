"""Every bad input answered in one line, nothing silently wrong.

Each test writes a damaged input (cloud, bag, trajectory, control, calibration or plan file,
LAS/LAZ) or an output that cannot be written, runs ``lidarcal`` on it, and checks the answer:
where no valid result exists, one line naming what is wrong (what, where, how many) and a
non-zero exit, with no output left behind and a previous output untouched; where the tool
goes on, a warning line with the count, and a result that lost nothing else.
"""

from __future__ import annotations

import contextlib
import copy
import hashlib
import json
import math
import resource
import signal
import struct
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import helpers_missions
import numpy as np
import pytest
import yaml
from helpers_cli import one_line_error, run, warning_lines
from helpers_missions import (
    FAST_SETTINGS,
    MissionFiles,
    cloud_chunks,
    shift_strip,
    strip_points,
    subset,
    without_control,
    write_calibration_yaml,
    write_cloud_bag,
    write_params_file,
)

from lidarcal_ros.core.mission import Mission, Trajectory, screen_samples
from lidarcal_ros.core.params import PARAMETER_NAMES
from lidarcal_ros.errors import CloudFormatError, TrajectoryError
from lidarcal_ros.io.bag.format import seconds_to_ns
from lidarcal_ros.io.bag.mission_bag import read_mission, write_mission_bag
from lidarcal_ros.io.bag.writer import BagWriter
from lidarcal_ros.io.cloud.columns import extract_columns, float32_step, float32_warning
from lidarcal_ros.io.survey.las_writer import LasChunkWriter

mission_factory = helpers_missions.mission_factory
small_mission = helpers_missions.small_mission

#: Clouds with FLOAT32 coordinates (what a driver in a local frame sends).
FLOAT32_XYZ = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("t", "<f8"), ("intensity", "<f4"),
               ("strip_id", "<u2")]
EXISTS = "exists (use --overwrite to replace it)"
#: Where a LAS header holds its x, y, z scale factors (LAS 1.4 R15, table 3).
LAS_SCALES_AT = 131


def first_chunks_points(mission: Mission, chunks: int) -> int:
    """The points :func:`write_cloud_bag` writes with ``max_chunks_per_strip=chunks``."""
    return sum(sl.stop - sl.start for s in mission.strips
               for _, sl in zip(range(chunks), cloud_chunks(s, 0.5)))


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def left_in(directory: Path) -> list[str]:
    """The names in ``directory`` (hidden temporary files included)."""
    return sorted(p.name for p in directory.iterdir())


@pytest.fixture(scope="module")
def calibration(small_mission: MissionFiles, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The small mission's true biases as a calibration file."""
    return write_calibration_yaml(tmp_path_factory.mktemp("cal") / "cal.yaml",
                                  small_mission.sim.biases)


@contextlib.contextmanager
def file_size_limit(nbytes: int) -> Iterator[None]:
    """Writes past ``nbytes`` of any file fail as on a full disk (``EFBIG``, "File too
    large"; RLIMIT_FSIZE, SIGXFSZ ignored), for the block's duration."""
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    handler = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (nbytes, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, handler)


# ---------------------------------------------------------------------------- FLOAT32 x, y, z
def test_float32_step_is_measured_at_the_data_magnitude() -> None:
    """The rounding step of FLOAT32 at a UTM northing of 5000 km is 0.5 m, at an easting of
    500 km 1/32 m, at 60 km 1/256 m; extraction refuses a step coarser than the tolerance
    (the range noise) in one line naming the field, and the warning names the step."""
    for magnitude, step in ((5_000_000.0, 0.5), (500_000.0, 2.0**-5), (60_000.0, 2.0**-8)):
        xyz = np.array([[10.0, magnitude, 100.0], [20.0, -magnitude / 2, 90.0]])
        assert float32_step(xyz) == (step, 1, magnitude)
    cloud = np.zeros(3, dtype=FLOAT32_XYZ)
    cloud["x"], cloud["y"] = 500_000.0, [5_000_000.0, 5_000_010.0, 5_000_020.0]
    with pytest.raises(CloudFormatError) as exc:
        extract_columns(cloud, source="/lidar/points", coordinate_tolerance_m=0.03)
    assert str(exc.value).startswith("/lidar/points: FLOAT32 field 'y' holds coordinates up "
                                     "to 5000020 m, where FLOAT32 has 0.5 m steps")
    cloud["y"] = 60_000.0  # a UTM easting alone: 1/32 m steps, still above the noise
    with pytest.raises(CloudFormatError, match=r"^cloud: FLOAT32 field 'x' holds coordinates "
                                               r"up to 500000 m, where FLOAT32 has 0\.0312 m"):
        extract_columns(cloud, coordinate_tolerance_m=0.03)
    assert extract_columns(cloud, coordinate_tolerance_m=0.05).coordinate_step_m == 2.0**-5
    cloud["x"] = 60_000.0
    cols = extract_columns(cloud, coordinate_tolerance_m=0.03)
    assert cols.coordinate_step_m == 2.0**-8
    assert "0.00391 m" in str(float32_warning(cols.coordinate_step_m, 0.03))
    assert float32_warning(2.0**-12, 0.03) is None  # 0.24 mm: below a tenth of the noise
    big = np.zeros(1, dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("t", "<f8")])
    big["y"] = 5_000_000.0
    assert extract_columns(big).coordinate_step_m == 0.0  # FLOAT64: exact


def test_float32_coordinates_at_utm_magnitudes_are_refused(capsys, tmp_path, mission_factory,
                                                           calibration) -> None:
    """E 500 km, N 5000 km in FLOAT32: rounded by up to 0.25 m, which moved the estimate by
    4.8 cm when read silently; now ``calibrate`` and ``correct`` refuse it in one line."""
    utm = mission_factory(origin=(500_000.0, 5_000_000.0)).mission
    bag = write_cloud_bag(tmp_path / "f32", utm, dtype=FLOAT32_XYZ, max_chunks_per_strip=2)
    rc, _, err = run(capsys, "calibrate", bag, "-o", tmp_path / "cal.yaml")
    reason = one_line_error(rc, err)
    assert reason.startswith("/lidar/points: FLOAT32 field 'y' holds coordinates up to")
    assert "FLOAT32 has 0.5 m steps, coarser than the 0.03 m range noise" in reason
    assert "FLOAT64" in reason
    rc, _, err = run(capsys, "correct", bag, "--calibration", calibration,
                     "-o", tmp_path / "out.laz")
    assert "FLOAT32 field 'y'" in one_line_error(rc, err, "correct")
    assert left_in(tmp_path) == ["f32"]


def test_float32_coordinates_below_the_noise_are_warned_about(capsys, tmp_path,
                                                              mission_factory,
                                                              calibration) -> None:
    """At 60 km FLOAT32 rounds to 3.9 mm steps, under the 3 cm range noise: the correction
    goes on with one warning line naming the step, and every point is corrected."""
    local = mission_factory(origin=(60_000.0, 60_000.0)).mission
    bag = write_cloud_bag(tmp_path / "f32", local, dtype=FLOAT32_XYZ, max_chunks_per_strip=4)
    out = tmp_path / "out.mcap"
    rc, _, err = run(capsys, "correct", bag, "--calibration", calibration, "-o", out)
    assert rc == 0, err
    (warning,) = warning_lines(err, "correct")
    assert warning.startswith("/lidar/points: FLOAT32 x, y, z are rounded to steps of up to "
                              "0.00391 m at these coordinates (range noise 0.03 m")
    corrected = read_mission(out, points_topic="/lidar/points_corrected")
    assert corrected.n_points == first_chunks_points(local, 4)


# ---------------------------------------------------------------------------- write failures
def test_a_laz_write_failing_midway_is_one_line_and_leaves_the_previous_file(
        capsys, tmp_path, small_mission, calibration) -> None:
    """Correcting to LAZ on a disk that fills half-way: one line naming the file and the
    operating system's reason (not lazrs' bare 'IoError'), no partial file, and the previous
    output (``--overwrite``) untouched."""
    out = tmp_path / "out.laz"
    args = ("correct", small_mission.bag, "--calibration", calibration, "-o", out,
            "--crs", "EPSG:32633")
    rc, _, err = run(capsys, *args)
    assert rc == 0, err
    before = digest(out)
    assert out.stat().st_size > 600_000
    with file_size_limit(300_000):
        rc, _, err = run(capsys, *args, "--overwrite")
    assert one_line_error(rc, err, "correct") == f"{out}: cannot write (File too large)"
    assert left_in(tmp_path) == ["out.laz"] and digest(out) == before


@pytest.mark.parametrize("suffix", [".mcap", ""])
def test_a_bag_write_failing_midway_is_one_line_and_leaves_nothing(
        capsys, tmp_path, small_mission, calibration, suffix) -> None:
    out = tmp_path / f"out{suffix}"
    with file_size_limit(300_000):
        rc, _, err = run(capsys, "correct", small_mission.bag, "--calibration", calibration,
                         "-o", out)
    assert one_line_error(rc, err, "correct") == f"{out}: cannot write bag (File too large)"
    assert left_in(tmp_path) == []


def test_a_calibration_write_failing_is_one_line_and_leaves_the_previous_file(
        capsys, tmp_path, small_mission) -> None:
    out = tmp_path / "cal.yaml"
    args = ("calibrate", small_mission.bag, "-o", out, "--config", small_mission.fast_config)
    rc, _, err = run(capsys, *args)
    assert rc == 0, err
    before = digest(out)
    with file_size_limit(1000):
        rc, _, err = run(capsys, *args, "--overwrite")
    assert one_line_error(rc, err) == f"{out}: cannot write calibration (File too large)"
    assert left_in(tmp_path) == ["cal.yaml"] and digest(out) == before


# ---------------------------------------------------------------------------- clouds
def _empty_clouds_bag(path: Path, mission: Mission) -> Path:
    with BagWriter(path) as writer:
        for s in mission.strips:
            writer.write_cloud("/lidar/points", seconds_to_ns(float(s.t[0])), "map",
                               strip_points(s)[:0])
        for t, xyz in zip(mission.trajectory.t, mission.trajectory.xyz):
            writer.write_pose("/lidar/trajectory", seconds_to_ns(float(t)), "map", xyz)
    return path


def _non_finite_bag(path: Path, mission: Mission) -> Path:
    spoiled = copy.deepcopy(mission)
    for k, s in enumerate(spoiled.strips):
        s.xyz = s.xyz.copy()
        s.xyz[:, k % 3] = (np.nan, np.inf, -np.inf)[k % 3]
    return write_cloud_bag(path, spoiled, max_chunks_per_strip=2)


@pytest.mark.parametrize("command", ["calibrate", "correct"])
def test_every_cloud_empty_or_every_point_non_finite(capsys, tmp_path, small_mission,
                                                     calibration, command) -> None:
    mission = small_mission.mission
    empty = _empty_clouds_bag(tmp_path / "empty", mission)
    spoiled = _non_finite_bag(tmp_path / "nan", mission)
    n_points = first_chunks_points(mission, 2)
    out = tmp_path / ("out.yaml" if command == "calibrate" else "out.laz")
    extra = ("--calibration", calibration) if command == "correct" else ()
    rc, _, err = run(capsys, command, empty, *extra, "-o", out)
    assert one_line_error(rc, err, command).startswith(
        f"{empty}: all 6 clouds on /lidar/points are empty")
    rc, _, err = run(capsys, command, spoiled, *extra, "-o", out)
    reason = one_line_error(rc, err, command)
    assert reason.startswith(f"{spoiled}: all {n_points} points on /lidar/points have a "
                             "non-finite x, y")
    assert left_in(tmp_path) == ["empty", "nan"]


# ---------------------------------------------------------------------------- strips
def test_a_single_strip_or_strips_apart_are_named(capsys, tmp_path, small_mission) -> None:
    """Not 'N correspondences for N parameters: no redundancy' but how many strips there
    are, how far apart, and what the control alone could not do."""
    mission = small_mission.mission
    cases = [
        (without_control(subset(mission, [1])),
         "no overlap between strips: the mission has 1 strip (id 1), and no control points"),
        (subset(mission, [1]), "no overlap between strips: the mission has 1 strip (id 1), "
                               "and 1 control point alone cannot calibrate: nothing left to "
                               "estimate (dX: dX has no effect"),
        (without_control(shift_strip(subset(mission, [1, 3]), 3, (5000.0, 0.0, 0.0))),
         "no overlap between strips: none of the 2 strips (1, 3) overlaps another (their "
         "footprints are 4"),
    ]
    for k, (case, words) in enumerate(cases):
        bag = write_mission_bag(tmp_path / f"bag{k}", case)
        rc, _, err = run(capsys, "calibrate", bag, "-o", tmp_path / "cal.yaml",
                         "--config", small_mission.fast_config)
        reason = one_line_error(rc, err)
        assert reason.startswith(words), reason
        assert reason.endswith("a calibration needs overlapping strips (two pairs of opposite "
                               "lines at least)")
    assert not (tmp_path / "cal.yaml").exists()


# ---------------------------------------------------------------------------- trajectories
def test_trajectory_screening_counts_what_it_leaves_out(caplog) -> None:
    t = np.arange(10.0)
    xyz = np.column_stack([t, np.zeros(10), np.full(10, 1000.0)])
    keep = screen_samples(t, xyz, "BAG: /traj")
    assert keep.all() and not caplog.records
    # a message recorded twice is harmless; a stamp at two places drops both; NaN dropped
    # (each repeat read after its first: in time order, no clock stepping back)
    order = np.argsort(np.concatenate([t, [3.0, 5.0, 7.0]]), kind="stable")
    t2 = np.concatenate([t, [3.0, 5.0, 7.0]])[order]
    xyz2 = np.concatenate([xyz, [xyz[3], xyz[5] + [2.5, 0, 0], xyz[7]]])[order]
    xyz2[11] = np.nan  # (t = 8)
    with caplog.at_level("WARNING"):
        keep = screen_samples(t2, xyz2, "BAG: /traj")
    assert np.flatnonzero(~keep).tolist() == [6, 7, 11]
    (record,) = caplog.records
    assert record.getMessage() == (
        "BAG: /traj: 3 of 13 poses left out: 1 with a non-finite stamp or position; 2 at 1 "
        "stamp repeated at positions up to 2.5 m apart (first at t=5.000 s; which one is "
        "right is unknown)")
    traj = Trajectory.from_samples(t2, xyz2, source="BAG: /traj")
    assert traj.t.tolist() == [0, 1, 2, 3, 4, 6, 7, 9]
    with pytest.raises(TrajectoryError, match=r"^BAG: /traj: all 10 poses carry the same "
                                              r"stamp t=4\.000 s"):
        screen_samples(np.full(10, 4.0), xyz, "BAG: /traj")
    xyz[1:] = np.nan
    with pytest.raises(TrajectoryError, match=r"^BAG: /traj: 1 usable pose stamp among 10 "
                                              r"poses \(9 with a non-finite stamp or position"):
        screen_samples(t, xyz, "BAG: /traj")


def _odd_trajectory_bag(path: Path, mission: Mission) -> tuple[Path, dict[str, int]]:
    """The mission with every 50th pose's position NaN and every 20th stamp repeated 3 m
    away, the wrong pose first (a reader keeping the first would use it). Returns the bag
    and the counts: poses written, non-finite, at conflicting stamps, those stamps."""
    traj = mission.trajectory
    xyz = traj.xyz.copy()
    xyz[::50] = np.nan
    poses: list[tuple[float, int, np.ndarray]] = [(float(t), 1, p) for t, p in zip(traj.t, xyz)]
    away = np.array([3.0, 0.0, 0.0])
    poses += [(float(t), 0, p + away) for t, p in zip(traj.t[10::20], xyz[10::20])]
    poses.sort(key=lambda pose: (pose[0], pose[1]))
    with BagWriter(path) as writer:
        for s in mission.strips:
            pts = strip_points(s)
            for sl in cloud_chunks(s, 0.5):
                writer.write_cloud("/lidar/points", seconds_to_ns(float(s.t[sl.start])), "map",
                                   pts[sl])
        for t, _, p in poses:
            writer.write_pose("/lidar/trajectory", seconds_to_ns(t), "map", p)
    finite = np.array([np.isfinite(p).all() for _, _, p in poses])
    stamps = int(np.count_nonzero(np.isfinite(xyz[10::20]).all(axis=1)))
    return path, {"poses": len(poses), "non_finite": int(np.count_nonzero(~finite)),
                  "conflicting": 2 * stamps, "stamps": stamps}


def test_odd_poses_and_unseen_control_are_warned_about_and_the_calibration_holds(
        capsys, tmp_path, small_mission) -> None:
    """Poses with NaN positions, stamps repeated at positions 3 m apart, and a control point
    outside every strip: ``calibrate`` goes on with a warning line for each (counts, ids),
    the file says which control point went unused, and the estimate still finds the truth."""
    mission = small_mission.mission
    bag, n = _odd_trajectory_bag(tmp_path / "odd", mission)
    control = tmp_path / "control.csv"
    control.write_text(small_mission.control_csv.read_text() + "FAR,100000.0,100000.0,50.0\n")
    cal = tmp_path / "cal.yaml"
    rc, _, err = run(capsys, "calibrate", bag, "-o", cal, "--config", small_mission.fast_config,
                     "--control", control)
    assert rc == 0, err
    poses, unused = warning_lines(err, "calibrate")
    assert poses.startswith(
        f"{bag}: trajectory /lidar/trajectory: {n['non_finite'] + n['conflicting']} of "
        f"{n['poses']} poses "
        f"left out: {n['non_finite']} with a non-finite stamp or position; {n['conflicting']} "
        f"at {n['stamps']} stamps repeated at positions up to 3 m apart (first at t=")
    assert unused == "1 of 2 control points not used (FAR): 1 outside every strip"
    doc = yaml.safe_load(cal.read_text())["lidarcal_calibration"]
    assert unused in doc["warnings"]
    assert doc["correspondences"]["control"] > 0  # the control point under the strips is used
    for name in PARAMETER_NAMES:
        entry = doc["biases"][name]
        if entry["estimated"]:
            truth = small_mission.sim.biases[name]
            assert abs(entry["value"] - truth) < 4 * entry["sigma"], (name, entry, truth)


def test_poses_all_at_one_stamp_are_refused(capsys, tmp_path, small_mission,
                                            calibration) -> None:
    stuck = copy.deepcopy(small_mission.mission)
    stuck.trajectory = Trajectory(np.full(len(stuck.trajectory), stuck.trajectory.t[0]),
                                  stuck.trajectory.xyz)
    bag = write_cloud_bag(tmp_path / "stuck", stuck, max_chunks_per_strip=1)
    words = (f"{bag}: trajectory /lidar/trajectory: all {len(stuck.trajectory)} poses carry the "
             "same "
             f"stamp t={stuck.trajectory.t[0]:.3f} s")
    rc, _, err = run(capsys, "calibrate", bag, "-o", tmp_path / "cal.yaml")
    assert one_line_error(rc, err).startswith(words)
    rc, _, err = run(capsys, "correct", bag, "--calibration", calibration,
                     "-o", tmp_path / "out.laz")
    assert one_line_error(rc, err, "correct").startswith(words)
    assert left_in(tmp_path) == ["stuck"]


def test_a_bag_of_json_channels_is_not_read_as_damage(capsys, tmp_path) -> None:
    from mcap.writer import Writer

    path = tmp_path / "json.mcap"
    with path.open("wb") as stream:
        writer = Writer(stream)
        writer.start(profile="", library="test")
        schema = writer.register_schema(name="pose", encoding="jsonschema", data=b"{}")
        for topic in ("/lidar/trajectory", "/lidar/points"):
            channel = writer.register_channel(topic=topic, message_encoding="json",
                                              schema_id=schema)
            for i in range(5):
                writer.add_message(channel_id=channel, log_time=i * 10**9,
                                   publish_time=i * 10**9, data=json.dumps({"x": i}).encode())
        writer.finish()
    rc, _, err = run(capsys, "calibrate", path, "-o", tmp_path / "cal.yaml")
    assert one_line_error(rc, err) == (
        f"{path}: not a ROS 2 bag: messages on /lidar/trajectory (json), /lidar/points (json) "
        "are not CDR-encoded ROS 2 messages (lidarcal reads the bags of ros2 bag record -s "
        "mcap)")
    rc, _, err = run(capsys, "recover", path, "-o", tmp_path / "new.mcap")
    assert one_line_error(rc, err, "recover") == (
        f"{path}: no message is readable; /lidar/trajectory left out: encoding 'json', not a "
        "ROS 2 CDR message; /lidar/points left out: encoding 'json', not a ROS 2 CDR message")
    assert left_in(tmp_path) == ["json.mcap"]


# ---------------------------------------------------------------------------- LAS / LAZ
def _write_laz(path: Path, n: int = 20_000) -> Path:
    import laspy

    rng = np.random.default_rng(3)
    header = laspy.LasHeader(version="1.4", point_format=6)
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.array([500_000.0, 5_000_000.0, 0.0])
    las = laspy.LasData(header)
    las.x = 500_000.0 + rng.uniform(0, 200, n)
    las.y = 5_000_000.0 + rng.uniform(0, 200, n)
    las.z = rng.uniform(0, 20, n)
    las.gps_time = 3.0e8 + np.sort(rng.uniform(0, 20, n))
    las.point_source_id = np.full(n, 7, dtype=np.uint16)
    las.header.global_encoding.gps_time_type = laspy.header.GpsTimeType.STANDARD
    las.write(str(path))
    return path


def _ascii_trajectory(path: Path, t: np.ndarray, xyz: np.ndarray) -> Path:
    """``time,x,y,z`` lines (adjusted standard GPS time, the strip's map frame)."""
    np.savetxt(path, np.column_stack([t, xyz]), delimiter=",", fmt="%.6f",
               header="time,x,y,z", comments="")
    return path


def test_an_imported_trajectory_with_conflicting_or_equal_times(capsys, tmp_path) -> None:
    """An ASCII trajectory repeating times at positions 3 m apart: both left out in one
    warning line (not the first kept silently), the rest imported; one whose samples all
    carry one time is refused as such (not as times that 'do not overlap' the points')."""
    strip = _write_laz(tmp_path / "strip.laz", 2000)
    t = 3.0e8 + np.arange(-2.0, 22.0, 0.1)
    xyz = np.column_stack([500_000.0 + 5.0 * (t - t[0]), np.full(t.size, 5_000_100.0),
                           np.full(t.size, 1000.0)])
    twice = np.arange(5, t.size, 40)
    order = np.argsort(np.concatenate([t, t[twice]]), kind="stable")  # each after its first
    csv = _ascii_trajectory(tmp_path / "traj.csv", np.concatenate([t, t[twice]])[order],
                            np.concatenate([xyz, xyz[twice] + [3.0, 0.0, 0.0]])[order])
    rc, _, err = run(capsys, "import", strip, "--trajectory", csv, "-o", tmp_path / "bag")
    assert rc == 0, err
    assert warning_lines(err, "import") == [
        f"{csv}: {2 * twice.size} of {t.size + twice.size} poses left out: {2 * twice.size} at "
        f"{twice.size} stamps repeated at positions up to 3 m apart (first at "
        f"t={t[twice[0]]:.3f} s; which one is right is unknown)"]
    imported = read_mission(tmp_path / "bag").trajectory
    assert len(imported) == t.size - twice.size
    stuck = _ascii_trajectory(tmp_path / "stuck.csv", np.full(t.size, t[50]), xyz)
    rc, _, err = run(capsys, "import", strip, "--trajectory", stuck, "-o", tmp_path / "bag2")
    assert one_line_error(rc, err, "import") == (
        f"{stuck}: all {t.size} samples carry the same time {t[50]:.3f} s; a trajectory needs "
        "each sample at its own time")
    assert not (tmp_path / "bag2").exists()


def test_a_truncated_laz_is_one_line(capsys, tmp_path) -> None:
    """A LAZ failure is logged by laspy before it is raised: only lidarcal's own line is printed."""
    data = _write_laz(tmp_path / "whole.laz").read_bytes()
    cut = tmp_path / "cut.laz"
    cut.write_bytes(data[: len(data) // 2])
    rc, _, err = run(capsys, "import", cut, "-o", tmp_path / "bag")
    reason = one_line_error(rc, err, "import")
    assert reason.startswith(f"{cut}: corrupt or truncated point data after ")
    assert left_in(tmp_path) == ["cut.laz", "whole.laz"]


def test_a_las_header_without_usable_scales_is_refused(capsys, tmp_path) -> None:
    """Scale factors of zero would read every point at the offsets: refused by name."""
    path = _write_laz(tmp_path / "strip.las", 100)
    data = bytearray(path.read_bytes())
    struct.pack_into("<3d", data, LAS_SCALES_AT, 0.0, 0.0, 0.0)
    path.write_bytes(bytes(data))
    rc, _, err = run(capsys, "import", path, "-o", tmp_path / "bag")
    assert one_line_error(rc, err, "import") == (
        f"{path}: header scale factors [0.0, 0.0, 0.0] and offsets [500000.0, 5000000.0, 0.0] "
        "do not give coordinates (scales must be non-zero, both finite)")
    assert left_in(tmp_path) == ["strip.las"]


def test_las_output_without_a_crs_says_so(capsys, tmp_path, small_mission,
                                          calibration) -> None:
    bag = write_cloud_bag(tmp_path / "bag", small_mission.mission, max_chunks_per_strip=2)
    rc, _, err = run(capsys, "correct", bag, "--calibration", calibration,
                     "-o", tmp_path / "out.las")
    assert rc == 0, err
    assert warning_lines(err, "correct") == [
        f"{tmp_path / 'out.las'}: written without a CRS: the LAS/LAZ file does not say where "
        "its map frame is (give it with --crs, e.g. --crs EPSG:32633)"]
    rc, _, err = run(capsys, "correct", bag, "--calibration", calibration,
                     "-o", tmp_path / "crs.las", "--crs", "EPSG:32633")
    assert rc == 0 and err == ""


def test_points_beyond_las_coordinates_are_skipped_and_counted(tmp_path) -> None:
    """A glitch point 5000 km away cannot be stored in LAS's 32-bit coordinates: skipped and
    counted (not an OverflowError), and it does not move the offsets off the survey even
    when it comes first."""
    import laspy

    cloud = np.zeros(4, dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("t", "<f8")])
    cloud["x"] = [5.0e6, 1000.0, 1500.5, 2000.25]
    cloud["t"] = 1.7e9
    path = tmp_path / "out.las"
    with LasChunkWriter(path, time_field="t") as writer:
        writer.write(cloud)
        writer.write(cloud[::-1])
    assert writer.stats.points == 6 and writer.stats.skipped_out_of_range == 2
    las = laspy.read(str(path))
    assert sorted(np.asarray(las.x)) == [1000.0, 1000.0, 1500.5, 1500.5, 2000.25, 2000.25]


# ---------------------------------------------------------------------------- calibration
@pytest.mark.parametrize(("key", "value", "words"), [
    ("dX.sigma", -0.01, "biases.dX.sigma must be null or a finite number >= 0, got -0.01"),
    ("dr.sigma", ".inf", "biases.dr.sigma must be null or a finite number >= 0, got inf"),
    ("dS.sigma", "'small'", "biases.dS.sigma must be null or a finite number >= 0, got "
                            "'small'"),
    ("sigma0", -1, "sigma0 must be null or a finite number >= 0, got -1"),
    ("dphi.estimated", "'yes'", "biases.dphi.estimated is not true or false: 'yes'"),
])
def test_a_calibration_with_an_impossible_value_is_refused(capsys, tmp_path, small_mission,
                                                           calibration, key, value,
                                                           words) -> None:
    text = calibration.read_text()
    doc = yaml.safe_load(text)
    body = doc["lidarcal_calibration"]
    *parents, leaf = (["biases"] if "." in key else []) + key.split(".")
    for part in parents:
        body = body[part]
    body[leaf] = "PLACEHOLDER"
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(doc, sort_keys=False).replace("PLACEHOLDER", str(value)))
    rc, _, err = run(capsys, "correct", small_mission.bag, "--calibration", bad,
                     "-o", tmp_path / "out.laz")
    assert one_line_error(rc, err, "correct") == f"{bad}: {words}"
    assert left_in(tmp_path) == ["bad.yaml"]


def test_a_calibration_that_did_not_converge_exits_4_with_a_warning(
        capsys, tmp_path, small_mission) -> None:
    config = write_params_file(tmp_path / "one.yaml",
                               {**FAST_SETTINGS, "calibration.max_iterations": 1})
    cal = tmp_path / "cal.yaml"
    rc, out, err = run(capsys, "calibrate", small_mission.bag, "-o", cal, "--config", config)
    assert rc == 4
    (warning,) = warning_lines(err, "calibrate")
    assert warning.startswith(f"{cal}: the adjustment did not converge in 1 iteration "
                              "(calibration.max_iterations 1); its last step moved ")
    assert warning.endswith("the calibration is written with converged: false")
    doc = yaml.safe_load(cal.read_text())["lidarcal_calibration"]
    assert doc["converged"] is False and doc["iterations"] == 1
    assert f"calibration written to {cal}" in out


# ---------------------------------------------------------------------------- outputs
@pytest.mark.parametrize("command", ["calibrate", "correct", "report", "import", "simulate",
                                     "recover", "record"])
def test_every_writing_command_refuses_an_existing_output_alike(capsys, tmp_path,
                                                                small_mission, calibration,
                                                                command) -> None:
    bag = small_mission.bag
    out = {"calibrate": "cal.yaml", "correct": "out.laz", "report": "report.html",
           "import": "bag.mcap", "simulate": "sim_truth.yaml", "recover": "new.mcap",
           "record": "rec.mcap"}[command]
    existing = tmp_path / out
    existing.write_text("keep me\n")
    args: dict[str, tuple[Any, ...]] = {
        "calibrate": (bag, "-o", existing),
        "correct": (bag, "--calibration", calibration, "-o", existing),
        "report": (bag, "--calibration", calibration, "-o", existing),
        "import": (_write_laz(tmp_path / "strip.laz", 100), "-o", existing),
        "simulate": ("-o", tmp_path / "sim"),
        "recover": (bag, "-o", existing),
        "record": ("-o", existing, "--duration", "1"),
    }
    rc, _, err = run(capsys, command, *args[command])
    assert one_line_error(rc, err, command) == f"{existing}: {EXISTS}"
    assert existing.read_text() == "keep me\n"


def test_outputs_in_a_missing_directory_are_refused_before_any_work(capsys, tmp_path,
                                                                    small_mission) -> None:
    out = tmp_path / "no" / "such" / "cal.yaml"
    rc, _, err = run(capsys, "calibrate", small_mission.bag, "-o", out)
    assert one_line_error(rc, err) == f"{out}: directory {out.parent} does not exist"
    parent_is_a_file = tmp_path / "file"
    parent_is_a_file.write_text("")
    out = parent_is_a_file / "c.yaml"
    rc, _, err = run(capsys, "calibrate", small_mission.bag, "-o", out)
    assert one_line_error(rc, err) == f"{out}: {parent_is_a_file} is not a directory"


# ---------------------------------------------------------------------------- flight plans
PLAN_LINES = [{"id": 1, "start": [0, -250], "end": [0, 250], "height": 1150},
              {"id": 2, "start": [0, 250], "end": [0, -250], "height": 1150},
              {"id": 3, "start": [300, -250], "end": [300, 250], "height": 1150},
              {"id": 4, "start": [300, 250], "end": [300, -250], "height": 1150}]


def test_a_plan_control_point_not_finite_is_refused(capsys, tmp_path) -> None:
    plan = tmp_path / "plan.yaml"
    plan.write_text(yaml.safe_dump({"lines": PLAN_LINES, "control": [[math.nan, 0, 0]]}))
    rc, _, err = run(capsys, "plan", plan)
    assert one_line_error(rc, err, "plan") == (
        f"{plan}: control point 1 must be finite numbers [x, y, z], got [nan, 0, 0]")


def test_a_plan_control_point_outside_every_swath_is_said_and_not_counted(capsys,
                                                                          tmp_path) -> None:
    plan = tmp_path / "plan.yaml"
    plan.write_text(yaml.safe_dump({"lines": PLAN_LINES, "sensor": {"density": 0.05},
                                    "control": [[50_000, 0, 0]]}))
    rc, out, err = run(capsys, "plan", plan, "--json")
    assert rc == 0
    assert warning_lines(err, "plan") == [
        "control point 1 at (50000, 0) lies outside every line's swath: no line sees it, the "
        "plan does not use it"]
    report = json.loads(out)
    assert report["advice"][0].startswith("control point 1: outside every line's swath")
    assert not report["parameters"]["dZ"]["estimable"]
    assert any(a.startswith("dZ: not observable from strips alone; add a vertical control")
               for a in report["advice"])
