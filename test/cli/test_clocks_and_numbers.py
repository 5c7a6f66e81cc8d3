"""Clocks that step back, extreme numbers and hostile configuration values.

Each test builds the case (a bag whose pose stamps step back, poses or points at 1e308 or
subnormal, quaternions far from unit or zero, "1e400" or ".nan" in a flight configuration or
an option), runs ``lidarcal`` on it and checks the answer: one line naming the file, topic or
parameter, a non-zero exit and nothing left behind; or, where the tool goes on, a warning
line with the count and a result that lost nothing else.
"""

from __future__ import annotations

import subprocess
import sys
import warnings
from pathlib import Path
from typing import Any

import helpers_missions
import laspy
import numpy as np
import pytest
import yaml
from helpers_cli import one_line_error, run
from helpers_missions import (
    cloud_chunks,
    strip_points,
    write_calibration_yaml,
)

from lidarcal_ros.core.mission import REORDER_S, Mission, screen_samples
from lidarcal_ros.errors import TrajectoryError
from lidarcal_ros.io.bag.format import POSE_STAMPED, seconds_to_ns
from lidarcal_ros.io.bag.mission_bag import read_mission
from lidarcal_ros.io.bag.writer import BagWriter

mission_factory = helpers_missions.mission_factory
small_mission = helpers_missions.small_mission
calibration = helpers_missions.small_calibration


def _bag_with_stamps(path: Path, mission: Mission, stamps: np.ndarray, *,
                     shuffle: np.random.Generator | None = None) -> Path:
    """The mission's clouds (their points in random order with ``shuffle``), and its poses
    with header stamps ``stamps`` (s) logged at their true times: a recorder whose own clock
    ran on while the INS clock did what ``stamps`` says."""
    traj = mission.trajectory
    with BagWriter(path) as writer:
        for s in mission.strips:
            pts = strip_points(s)
            for sl in cloud_chunks(s, 0.5):
                cloud = pts[sl] if shuffle is None else shuffle.permutation(pts[sl])
                writer.write_cloud("/lidar/points", seconds_to_ns(float(s.t[sl.start])), "map",
                                   cloud)
        types = writer._types
        for i in range(len(traj)):
            x, y, z = (float(v) for v in traj.xyz[i])
            msg = types[POSE_STAMPED](
                header=writer._header(seconds_to_ns(float(stamps[i])), "map"),
                pose=types["geometry_msgs/msg/Pose"](
                    position=types["geometry_msgs/msg/Point"](x=x, y=y, z=z),
                    orientation=types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0,
                                                                      w=1.0)))
            writer.write_message("/lidar/trajectory", POSE_STAMPED,
                                 seconds_to_ns(float(traj.t[i])), msg)
    return path


# ---------------------------------------------------------------------------- clocks
def test_a_pose_clock_stepping_back_is_named_not_called_a_gap(capsys, tmp_path, small_mission,
                                                              calibration) -> None:
    """The INS clock steps back 10 s in the middle of strip 4: ``calibrate`` and ``correct``
    both say so (where, from what, by how much, on which topic), exit 1 and leave nothing;
    before, calibrate called it a trajectory gap and correct left half the points
    uncorrected with exit 0."""
    mission = small_mission.mission
    traj = mission.trajectory
    k = int(np.searchsorted(traj.t, mission.strips[3].t.mean()))
    stamps = traj.t.copy()
    stamps[k:] -= 10.0
    bag = _bag_with_stamps(tmp_path / "back", mission, stamps)
    words = (f"{bag}: trajectory /lidar/trajectory: stamps go backwards at pose {k + 1} of "
             f"{len(traj)}: t={stamps[k]:.3f} s after t={traj.t[k - 1]:.3f} s, "
             f"{traj.t[k - 1] - stamps[k]:.3f} s back (")
    rc, _, err = run(capsys, "calibrate", bag, "-o", tmp_path / "cal.yaml")
    assert one_line_error(rc, err).startswith(words), err
    assert "gap" not in err
    rc, _, err = run(capsys, "correct", bag, "--calibration", calibration,
                     "-o", tmp_path / "out.laz")
    assert one_line_error(rc, err, "correct").startswith(words), err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["back"]


def test_stamps_jumping_forward_stay_a_gap(capsys, tmp_path, small_mission) -> None:
    """The clock jumping 10 s forward mid-strip leaves 10 s of that strip's points without
    poses: a gap, as before (not a clock going backwards)."""
    mission = small_mission.mission
    traj = mission.trajectory
    k = int(np.searchsorted(traj.t, mission.strips[3].t.mean()))
    stamps = traj.t.copy()
    stamps[k:] += 10.0
    bag = _bag_with_stamps(tmp_path / "ahead", mission, stamps)
    rc, _, err = run(capsys, "calibrate", bag, "-o", tmp_path / "cal.yaml")
    assert "trajectory gap at t=" in one_line_error(rc, err)
    assert not (tmp_path / "cal.yaml").exists()


def test_reordered_or_repeated_stamps_are_no_clock_step() -> None:
    """Two poses swapped (a step back of one period, under REORDER_S) are sorted into place;
    a pose read again at its stamp and place is no step; a pose 2 * REORDER_S late is."""
    t = np.arange(100) * 0.02
    xyz = np.column_stack([t * 60.0, np.zeros(100), np.full(100, 1000.0)])
    swapped = np.r_[0:5, 6, 5, 7:100]
    assert screen_samples(t[swapped], xyz[swapped], "T").all()
    again = np.r_[0:100, 3]
    assert screen_samples(t[again], xyz[again], "T").all()
    late = np.r_[0:90, 4, 90:100]  # t=0.08 read after t=1.78
    assert 1.78 - 0.08 > 2 * REORDER_S
    xyz_late = xyz[late].copy()
    xyz_late[90] += [5.0, 0.0, 0.0]  # not the same place: a second source?
    with pytest.raises(TrajectoryError, match=r"^T: stamps go backwards at pose 91 of 101: "
                                              r"t=0\.080 s after t=1\.780 s, 1\.700 s back "
                                              r"\(1 poses"):
        screen_samples(t[late], xyz_late, "T")


def test_points_whose_times_go_backwards_within_a_cloud_are_corrected_alike(
        tmp_path, small_mission, calibration, capsys) -> None:
    """Every cloud's points in random order (times going back and forth within a strip):
    each point is corrected as in the ordered bag (points are taken by their own times, not
    their order), with no numpy warning."""
    mission = small_mission.mission
    stamps = mission.trajectory.t
    bags = (_bag_with_stamps(tmp_path / "ordered", mission, stamps),
            _bag_with_stamps(tmp_path / "shuffled", mission, stamps,
                             shuffle=np.random.default_rng(3)))
    import laspy

    clouds = []
    for bag in bags:
        out = tmp_path / f"{bag.name}.laz"
        with warnings.catch_warnings():
            warnings.simplefilter("error", RuntimeWarning)
            rc, _, err = run(capsys, "correct", bag, "--calibration", calibration, "-o", out)
        assert rc == 0, err
        las = laspy.read(out)
        key = np.lexsort((las.z, las.y, las.x, las.gps_time))
        clouds.append(np.column_stack([las.x, las.y, las.z, las.gps_time])[key])
    assert clouds[0].shape == clouds[1].shape and clouds[0].shape[0] == mission.n_points
    assert np.array_equal(clouds[0], clouds[1])


# ---------------------------------------------------------------------------- configuration
@pytest.mark.parametrize("text", ["1e400", "inf", "nan", ".nan", "-.inf"])
def test_configuration_numbers_that_are_not_finite_are_refused(capsys, tmp_path, small_mission,
                                                               text) -> None:
    """``1e400`` (inf once read), ``inf``, ``nan`` and YAML's ``.nan`` / ``-.inf`` in a flight
    configuration: one line naming the file and the parameter, before any work."""
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(f"/**:\n  ros__parameters:\n    sensor:\n      range_noise_m: {text}\n")
    rc, _, err = run(capsys, "calibrate", small_mission.bag, "-o", tmp_path / "cal.yaml",
                     "--config", cfg)
    reason = one_line_error(rc, err)
    assert reason.startswith(f"{cfg}: sensor.range_noise_m: "), reason
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cfg.yaml"]


@pytest.mark.parametrize("text", ["1e400", "inf", "nan", "-1e999"])
def test_option_numbers_that_are_not_finite_are_refused(capsys, tmp_path, text) -> None:
    """A numeric option given "nan", "inf" or "1e400" (which ``float`` reads as inf): the
    option named, exit 2 (argparse's), nothing written."""
    with pytest.raises(SystemExit) as stop:
        run(capsys, "simulate", "-o", tmp_path / "sim", f"--density={text}")
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert err.splitlines()[-1] == (f"lidarcal simulate: error: argument --density: expected "
                                    f"a finite number, got {text!r}")
    assert not list(tmp_path.iterdir())


# ---------------------------------------------------------------------------- extreme numbers
def _bag_with_numbers(path: Path, mission: Mission, *, pose: Any = None,
                      cloud: Any = None) -> Path:
    """The mission's bag with each pose given an orientation (its heading along the track)
    and spoiled by ``pose(i, xyz, q)`` in place, each cloud by ``cloud(k, points)``."""
    traj = mission.trajectory
    d = np.gradient(traj.xyz[:, :2], axis=0)
    yaw = np.arctan2(d[:, 1], d[:, 0])
    quats = np.column_stack([np.zeros((yaw.size, 2)), np.sin(yaw / 2), np.cos(yaw / 2)])
    with BagWriter(path) as writer:
        for s in mission.strips:
            pts = strip_points(s)
            for k, sl in enumerate(cloud_chunks(s, 0.5)):
                part = pts[sl].copy()
                if cloud is not None:
                    cloud(k, part)
                writer.write_cloud("/lidar/points", seconds_to_ns(float(s.t[sl.start])), "map",
                                   part)
        for i in range(len(traj)):
            xyz, q = traj.xyz[i].copy(), quats[i].copy()
            if pose is not None:
                pose(i, xyz, q)
            writer.write_pose("/lidar/trajectory", seconds_to_ns(float(traj.t[i])), "map", xyz,
                              quaternion_xyzw=q)
    return path


def _huge_positions(i: int, xyz: np.ndarray, q: np.ndarray) -> None:
    if i % 50 == 7:
        xyz[0] = 1e308 if i % 100 == 7 else -1e308


def _huge_points(k: int, points: np.ndarray) -> None:
    if k == 1:
        points["x"][:5], points["z"][5:10] = 1e308, -1e308


def _subnormal_points(k: int, points: np.ndarray) -> None:
    if k == 1:
        points["x"][:5], points["z"][5:10] = 5e-324, -5e-324


def _subnormal_positions(i: int, xyz: np.ndarray, q: np.ndarray) -> None:
    """The poses of the line flown along x = 0 (1636 of the mission's) at x = +-5e-324."""
    if xyz[0] == 0.0:
        xyz[0] = 5e-324 if i % 2 else -5e-324


def _subnormal_components(i: int, xyz: np.ndarray, q: np.ndarray) -> None:
    """Roll and pitch of the level poses (their x, y) subnormal, not zero: of unit length."""
    q[0], q[1] = 5e-324, -5e-324


def _zero_quaternions(i: int, xyz: np.ndarray, q: np.ndarray) -> None:
    if i % 50 == 7:
        q[:] = 0.0


NUMBERS: dict[str, tuple[dict[str, Any], str]] = {
    "poses at +-1e308": ({"pose": _huge_positions},
                         "trajectory /lidar/trajectory: {n50} of {n} poses left out: {n50} with "
                         "a coordinate beyond 1e+09 m"),
    "points at +-1e308": ({"cloud": _huge_points},
                          "dropped 60 points with non-finite x, y, z or t (or a coordinate "
                          "beyond 1e+09 m)"),
    "subnormal points": ({"cloud": _subnormal_points}, ""),
    "quaternions of norm 3": ({"pose": lambda i, xyz, q: q.__imul__(3.0)},
                              "trajectory /lidar/trajectory: of {n} orientation quaternions, "
                              "{n} not of unit length (norms 3 to 3): normalised"),
    "quaternions of norm 1e308": ({"pose": lambda i, xyz, q: q.__imul__(1e308)},
                                  "trajectory /lidar/trajectory: of {n} orientation "
                                  "quaternions, {n} not of unit length (norms 1e+308 to "
                                  "1e+308): normalised"),
    "subnormal quaternions": ({"pose": lambda i, xyz, q: q.__imul__(5e-324)},
                              "trajectory /lidar/trajectory: of {n} orientation quaternions, "
                              "{n} not of unit length (norms 4.94e-324 to 4.94e-324): "
                              "normalised"),
    "subnormal pose coordinates": ({"pose": _subnormal_positions}, ""),
    "subnormal quaternion components": ({"pose": _subnormal_components}, ""),
    "zero quaternions among others": ({"pose": _zero_quaternions},
                                      "trajectory /lidar/trajectory: of {n} orientation "
                                      "quaternions, {n50} zero: read as poses without "
                                      "orientation; {n50} poses without one between poses "
                                      "with one at most 0.1 s apart: their orientation "
                                      "interpolated"),
}


@pytest.mark.parametrize("case", NUMBERS)
def test_extreme_numbers_are_left_out_or_normalised_and_said(tmp_path, small_mission,
                                                             case) -> None:
    """Each case through ``calibrate`` in a fresh interpreter with numpy's RuntimeWarning an
    error: exit 0, one warning line with the count (none for subnormal points, which are
    numbers like any other), and every estimated bias within 4 sigmas of the truth (before:
    'internal error: RuntimeWarning: overflow' for poses or points at 1e308, and quaternions
    of norm 1e308 or 5e-324 read silently as no orientation)."""
    mission = small_mission.mission
    spoil, words = NUMBERS[case]
    bag = _bag_with_numbers(tmp_path / "bag", mission, **spoil)
    n = len(mission.trajectory)
    out = tmp_path / "cal.yaml"
    proc = subprocess.run([sys.executable, "-W", "error::RuntimeWarning", "-m", "lidarcal_ros",
                           "calibrate", bag, "-o", out, "--config", small_mission.fast_config,
                           "-q"], capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr
    said = [line for line in proc.stderr.splitlines() if line.startswith("lidarcal")]
    assert said == ([f"lidarcal calibrate: warning: {bag}: "
                     + words.format(n=n, n50=len(range(7, n, 50)))] if words else []), said
    biases = yaml.safe_load(out.read_text())["lidarcal_calibration"]["biases"]
    for name, truth in small_mission.sim.biases.items():
        if biases[name]["estimated"]:  # the truth within 4 sigmas: nothing silently wrong
            assert abs(biases[name]["value"] - truth) < 4.0 * biases[name]["sigma"], name


@pytest.mark.parametrize("suffix", [".mcap", ".las", ".laz"])
@pytest.mark.parametrize("spoil", [_huge_points, _subnormal_points])
def test_extreme_points_through_correct_to_every_format(tmp_path, small_mission, suffix,
                                                         spoil) -> None:
    """Points at +-1e308 (once a SIGABRT writing LAZ) and subnormal ones through ``correct``
    to a bag, LAS and LAZ with numpy's RuntimeWarning an error: exit 0, the huge ones said
    in one warning and left out of LAS/LAZ or passed on flagged in a bag, the file readable
    by an independent reader with every other point."""
    mission = small_mission.mission
    bag = _bag_with_numbers(tmp_path / "bag", mission, cloud=spoil)
    cal = write_calibration_yaml(tmp_path / "cal.yaml", small_mission.sim.biases)
    out = tmp_path / f"out{suffix}"
    crs = ["--crs", "EPSG:32633"] if suffix != ".mcap" else []
    proc = subprocess.run([sys.executable, "-W", "error::RuntimeWarning", "-m", "lidarcal_ros",
                           "correct", bag, "--calibration", cal, "-o", out, *crs, "-q"],
                          capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr
    said = [line for line in proc.stderr.splitlines() if line.startswith("lidarcal")]
    huge = spoil is _huge_points
    assert len(said) == (1 if huge else 0) and (not huge or ("60 " in said[0] and
                                                 "1e+09 m" in said[0])), said
    n = mission.n_points
    if suffix == ".mcap":
        points = read_mission(out, points_topic="/lidar/points_corrected")
        assert points.n_points == n - (60 if huge else 0)  # (the reader drops them again)
    else:
        las = laspy.read(str(out))
        assert len(las.points) == n - (60 if huge else 0)
        assert np.isfinite(np.asarray(las.x)).all() and np.abs(np.asarray(las.x)).max() < 1e7
