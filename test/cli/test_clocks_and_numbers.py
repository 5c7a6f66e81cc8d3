"""Clocks that step back, extreme numbers and hostile configuration values.

Each test builds the case (a bag whose pose stamps step back, poses or points at 1e308 or
subnormal, quaternions far from unit or zero, "1e400" or ".nan" in a flight configuration or
an option), runs ``lidarcal`` on it and checks the answer: one line naming the file, topic or
parameter, a non-zero exit and nothing left behind; or, where the tool goes on, a warning
line with the count and a result that lost nothing else.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import helpers_missions
import numpy as np
import pytest
from helpers_cli import one_line_error, run
from helpers_missions import (
    MissionFiles,
    cloud_chunks,
    strip_points,
    write_calibration_yaml,
)

from lidarcal_ros.core.mission import REORDER_S, Mission, screen_samples
from lidarcal_ros.errors import TrajectoryError
from lidarcal_ros.io.bag.format import POSE_STAMPED, seconds_to_ns
from lidarcal_ros.io.bag.writer import BagWriter

mission_factory = helpers_missions.mission_factory
small_mission = helpers_missions.small_mission


@pytest.fixture(scope="module")
def calibration(small_mission: MissionFiles, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The small mission's true biases as a calibration file."""
    return write_calibration_yaml(tmp_path_factory.mktemp("cal") / "cal.yaml",
                                  small_mission.sim.biases)


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
