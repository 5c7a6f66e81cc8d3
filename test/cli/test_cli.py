"""The ``lidarcal`` command line on real bags: bad input gets one line and a non-zero exit.

Bags are built with lidarcal's own writers (and, once, the mcap project's ROS 2 writer) from
one small simulated mission (helpers_missions). Most cases run ``main([...])`` in-process;
a few run ``python -m lidarcal_ros`` to check the real exit status and stderr.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
from pathlib import Path
from typing import Any

import helpers_missions
import numpy as np
import pytest
import yaml
from helpers_cli import one_line_error, run, run_on_a_terminal, run_process, warning_lines
from helpers_missions import (
    MissionFiles,
    shift_strip,
    strip_span,
    subset,
    truncate,
    with_non_finite,
    without_control,
    without_trajectory,
    write_cloud_bag,
    write_mcap_ros2_bag,
    write_params_file,
)

from lidarcal_ros.cli.main import main
from lidarcal_ros.core.params import PARAMETER_NAMES
from lidarcal_ros.io.bag.mission_bag import write_mission_bag

# The shared fixtures (module attributes are collected as fixtures).
mission_factory = helpers_missions.mission_factory
small_mission = helpers_missions.small_mission


# ------------------------------------------------------------------ helpers
def calibration_values(path: Path) -> dict[str, Any]:
    doc = yaml.safe_load(path.read_text())["lidarcal_calibration"]
    return doc


@pytest.fixture(scope="module")
def work(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("cli")


@pytest.fixture(scope="module")
def bag_without_control(small_mission: MissionFiles, work: Path) -> Path:
    return write_mission_bag(work / "no_control", without_control(small_mission.mission))


# ------------------------------------------------------------------ bag and topics
def test_bag_missing(capsys, tmp_path):
    rc, out, err = run(capsys, "calibrate", tmp_path / "nowhere", "-o", tmp_path / "c.yaml")
    reason = one_line_error(rc, err)
    assert reason.startswith(f"{tmp_path / 'nowhere'}: no such bag")
    assert out == ""
    assert not (tmp_path / "c.yaml").exists()


def test_bag_missing_subprocess(tmp_path):
    proc = run_process("calibrate", "nowhere", "-o", "c.yaml", cwd=tmp_path)
    reason = one_line_error(proc.returncode, proc.stderr)
    assert reason == "nowhere: no such bag (file or directory not found)"
    assert proc.stdout == ""


@pytest.mark.parametrize(("option", "topic"), [("--points", "/nope"),
                                               ("--trajectory", "/nav/pose")])
def test_topic_missing(capsys, tmp_path, small_mission, option, topic):
    rc, _, err = run(capsys, "calibrate", small_mission.bag, "-o", tmp_path / "c.yaml",
                     option, topic)
    reason = one_line_error(rc, err)
    assert f"topic {topic} not found" in reason
    assert str(small_mission.bag) in reason
    assert "/lidar/points" in reason.split("topics present:")[1]  # what there is instead


def test_topic_of_wrong_type(capsys, tmp_path, small_mission):
    rc, _, err = run(capsys, "calibrate", small_mission.bag, "-o", tmp_path / "c.yaml",
                     "--points", "/lidar/trajectory")
    reason = one_line_error(rc, err)
    assert "topic /lidar/trajectory has type geometry_msgs/msg/PoseStamped" in reason


def test_truncated_bag(capsys, small_mission, work):
    cut = truncate(small_mission.bag, work / "truncated")
    rc, _, err = run(capsys, "calibrate", cut, "-o", work / "c.yaml")
    reason = one_line_error(rc, err)
    assert "truncated" in reason
    assert str(cut / "mission.mcap") in reason


def test_truncated_bag_subprocess(small_mission, tmp_path):
    cut = truncate(small_mission.bag, tmp_path / "cut")
    proc = run_process("calibrate", cut, "-o", "c.yaml", cwd=tmp_path)
    reason = one_line_error(proc.returncode, proc.stderr)
    assert reason.startswith(f"{cut / 'mission.mcap'}: truncated or corrupt MCAP")
    assert not (tmp_path / "c.yaml").exists()


# ------------------------------------------------------------------ cloud fields
XY_T_SID = [("x", "<f8"), ("y", "<f8"), ("t", "<f8"), ("strip_id", "<u2")]
XYZ_SID = [("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("intensity", "<f4"), ("strip_id", "<u2")]


@pytest.mark.parametrize(("dtype", "expected"), [
    (XY_T_SID, "/lidar/points: cloud lacks field(s) z; fields present: x, y, t, strip_id"),
    (XYZ_SID, "/lidar/points: cloud lacks time field 't'; fields present: x, y, z, "
              "intensity, strip_id"),
], ids=["no-z", "no-time"])
def test_cloud_without_field(capsys, tmp_path, small_mission, dtype, expected):
    bag = write_cloud_bag(tmp_path / "bag", small_mission.mission, dtype=dtype,
                          max_chunks_per_strip=2)
    rc, _, err = run(capsys, "calibrate", bag, "-o", tmp_path / "c.yaml")
    assert one_line_error(rc, err) == expected


def test_time_field_option_names_the_field(capsys, tmp_path, small_mission):
    rc, _, err = run(capsys, "calibrate", small_mission.bag, "-o", tmp_path / "c.yaml",
                     "--time-field", "gps_time")
    assert "cloud lacks time field 'gps_time'" in one_line_error(rc, err)


def test_frame_ids_differ(capsys, tmp_path, small_mission):
    bag = write_cloud_bag(tmp_path / "bag", small_mission.mission, cloud_frame="map",
                          trajectory_frame="odom", max_chunks_per_strip=2)
    rc, _, err = run(capsys, "calibrate", bag, "-o", tmp_path / "c.yaml")
    reason = one_line_error(rc, err)
    assert reason == (f"{bag}: clouds on /lidar/points are in frame 'map' but the trajectory "
                      "on /lidar/trajectory is in frame 'odom'")


# ------------------------------------------------------------------ trajectory and geometry
def test_trajectory_gap(capsys, tmp_path, small_mission):
    mission = small_mission.mission
    t0, t1 = strip_span(mission, 2)
    mid = 0.5 * (t0 + t1)
    bag = write_mission_bag(tmp_path / "gap", without_trajectory(mission, mid - 1.5, mid + 1.5))
    rc, _, err = run(capsys, "calibrate", bag, "-o", tmp_path / "c.yaml",
                     "--config", small_mission.fast_config)
    reason = one_line_error(rc, err)
    assert reason.startswith("strip 2: trajectory gap at t=")
    t_gap = float(reason.split("t=")[1].split()[0])
    assert mid - 2.5 < t_gap < mid + 1.5  # within the window around the removed samples


def test_no_overlap_between_strips(capsys, tmp_path, small_mission):
    # Strips 1 and 3 flown 5 km apart, no control: nothing ties them together.
    apart = shift_strip(subset(small_mission.mission, [1, 3]), 3, (5000.0, 0.0, 0.0))
    bag = write_mission_bag(tmp_path / "apart", without_control(apart))
    rc, _, err = run(capsys, "calibrate", bag, "-o", tmp_path / "c.yaml",
                     "--config", small_mission.fast_config)
    assert "no overlap between strips" in one_line_error(rc, err)


def test_nothing_left_to_estimate(capsys, tmp_path, small_mission, bag_without_control):
    rc, _, err = run(capsys, "calibrate", bag_without_control, "-o", tmp_path / "c.yaml",
                     "--config", small_mission.fast_config, "--solve-for", "dZ")
    reason = one_line_error(rc, err)
    assert reason.startswith("nothing left to estimate")
    assert "dZ" in reason and "control" in reason  # why, and what would fix it
    assert not (tmp_path / "c.yaml").exists()


# ------------------------------------------------------------------ options and files
@pytest.mark.parametrize("value", ["dX,dfoo", "dx"])
def test_bad_solve_for(capsys, tmp_path, small_mission, value):
    rc, _, err = run(capsys, "calibrate", small_mission.bag, "-o", tmp_path / "c.yaml",
                     "--solve-for", value)
    reason = one_line_error(rc, err)
    assert reason.startswith("--solve-for: unknown parameter(s)")
    assert value.split(",")[-1] in reason
    assert ", ".join(PARAMETER_NAMES) in reason  # the names that exist


def test_bad_solve_for_subprocess(tmp_path, small_mission):
    proc = run_process("calibrate", small_mission.bag, "-o", "c.yaml", "--solve-for", "dQ",
                       cwd=tmp_path)
    assert "--solve-for: unknown parameter(s) dQ" in one_line_error(proc.returncode,
                                                                    proc.stderr)


@pytest.mark.parametrize(("values", "expected"), [
    ({"matching.max_slope_deg": "steep"}, "matching.max_slope_deg: expected a number, got"),
    ({"calibration.max_iterations": 2.5}, "calibration.max_iterations: expected an integer"),
    ({"calibration.robust_k": 0.5}, "calibration.robust_k: 0.5 is below the minimum 1.5"),
    ({"sensor.fov_deg": 500.0}, "sensor.fov_deg: 500.0 is above the maximum"),
    ({"calibration.solve_for": ["dX", "dQ"]}, "calibration.solve_for: unknown parameter(s) dQ"),
], ids=["type", "int", "below", "above", "solve_for"])
def test_bad_config(capsys, tmp_path, small_mission, values, expected):
    cfg = write_params_file(tmp_path / "flight.yaml", values)
    rc, _, err = run(capsys, "calibrate", small_mission.bag, "-o", tmp_path / "c.yaml",
                     "--config", cfg)
    reason = one_line_error(rc, err)
    assert reason.startswith(f"{cfg}: ")
    assert expected in reason


def test_keys_no_node_declares_are_named_in_one_warning(tmp_path, small_mission):
    """The parameters file of ``lidarcal run --ros-args --params-file`` serves ``--config``
    too: the nodes' own parameters are passed over in silence, a misspelt key (which would
    leave its parameter at the default) and a key in the section of a node that does not
    declare it are named in one warning line, and the calibration goes on."""
    cfg = write_params_file(tmp_path / "flight.yaml", {
        **helpers_missions.FAST_SETTINGS, "idle_close_s": 0.5, "lookahead": True,
        "matching.max_slope": 60.0})
    text = cfg.read_text() + yaml.safe_dump({"/lidarcal_calibrator": {"ros__parameters": {
        "strip_gap_s": 3.0, "max_backlog_mib": 64}}})
    cfg.write_text(text)
    proc = run_process("calibrate", small_mission.bag, "-o", "c.yaml", "--config", cfg,
                       cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    lines = warning_lines(proc.stderr, "calibrate")
    assert len(lines) == 1, proc.stderr
    assert lines[0].endswith("(misspelt?): matching.max_slope, max_backlog_mib "
                             "(lidarcal_calibrator)"), lines[0]
    assert str(cfg) in lines[0] and "2 parameter(s)" in lines[0]
    assert (tmp_path / "c.yaml").is_file()


@pytest.mark.parametrize(("text", "expected"), [
    ("a: [1\n", "parameters file is not valid YAML at line 2"),
    ("sensor: {fov_deg: 40}\n", "no 'ros__parameters' section under '/**'"),
], ids=["yaml", "layout"])
def test_config_file_not_parameters(capsys, tmp_path, small_mission, text, expected):
    cfg = tmp_path / "flight.yaml"
    cfg.write_text(text)
    rc, _, err = run(capsys, "calibrate", small_mission.bag, "-o", tmp_path / "c.yaml",
                     "--config", cfg)
    assert one_line_error(rc, err) == f"{cfg}: {expected}"


@pytest.mark.parametrize(("text", "expected"), [
    ("id,x,y,z\nC1,10.0,20.0,4x.2\n", "line 2: z value '4x.2' is not a number"),
    ("id,x,y\nC1,10.0,20.0\n", "line 1: header lacks column(s) z"),
    ("id,x,y,z\nC1,10.0,20.0\n", "line 2: 3 values, expected 4"),
    ("id,x,y,z\nC1,1,2,3\nC1,4,5,6\n", "line 3: duplicate id 'C1'"),
    ("id,x,y,z\nC1,1,2,nan\n", "line 2: z value 'nan' is not finite"),
    ("", "empty control point file"),
], ids=["number", "column", "short", "duplicate", "nan", "empty"])
def test_control_csv_malformed(capsys, tmp_path, small_mission, text, expected):
    csv = tmp_path / "control.csv"
    csv.write_text(text)
    rc, _, err = run(capsys, "calibrate", small_mission.bag, "-o", tmp_path / "c.yaml",
                     "--control", csv)
    reason = one_line_error(rc, err)
    assert reason.startswith(f"{csv}: ")
    assert expected in reason


def test_control_csv_missing(capsys, tmp_path, small_mission):
    rc, _, err = run(capsys, "calibrate", small_mission.bag, "-o", tmp_path / "c.yaml",
                     "--control", tmp_path / "nope.csv")
    assert one_line_error(rc, err) == f"{tmp_path / 'nope.csv'}: control point file not found"


def test_output_is_a_directory(capsys, tmp_path, small_mission):
    rc, _, err = run(capsys, "calibrate", small_mission.bag, "-o", tmp_path)
    assert one_line_error(rc, err).startswith(f"{tmp_path}: is a directory")


@pytest.mark.parametrize("name", ["out.txt", "out.PLY", "points.xyz"])
def test_correct_refuses_a_format_it_does_not_write(capsys, tmp_path, small_mission, name):
    calibration = helpers_missions.write_calibration_yaml(
        tmp_path / "calibration.yaml", dict.fromkeys(PARAMETER_NAMES, 0.0))
    rc, _, err = run(capsys, "correct", small_mission.bag, "--calibration", calibration,
                     "-o", tmp_path / name)
    reason = one_line_error(rc, err, "correct")
    assert reason.startswith(f"{tmp_path / name}: lidarcal correct does not write "
                             f"{(tmp_path / name).suffix.lower()} files")
    assert not (tmp_path / name).exists()


def test_usage_error_exits_2(capsys, small_mission):
    with pytest.raises(SystemExit) as exc:
        main(["calibrate", str(small_mission.bag)])  # no -o
    assert exc.value.code == 2
    assert "-o/--output" in capsys.readouterr().err


# ------------------------------------------------------------------ successful runs
def test_non_finite_points_dropped_and_counted(capsys, tmp_path, small_mission):
    spoiled, n_bad = with_non_finite(small_mission.mission, per_strip=2)
    bag = write_mission_bag(tmp_path / "nan", spoiled)
    cal = tmp_path / "cal.yaml"
    rc, out, err = run(capsys, "calibrate", bag, "-o", cal, "--config", small_mission.fast_config)
    assert rc == 0, err
    assert "Traceback" not in err
    assert f"dropped {n_bad} points with non-finite values" in out
    assert f"{small_mission.mission.n_points - n_bad} points" in out.splitlines()[0]
    doc = calibration_values(cal)
    assert doc["dropped_non_finite_points"] == n_bad
    assert all(math.isfinite(doc["biases"][n]["value"]) for n in PARAMETER_NAMES)


@pytest.fixture(scope="module")
def rosbags_calibration(small_mission: MissionFiles, work: Path) -> tuple[Path, str]:
    """Calibration of the lidarcal-written bag (with --truth): file and stdout."""
    cal = work / "rosbags_cal.yaml"
    buf = io.StringIO()  # capsys is function-scoped
    with contextlib.redirect_stdout(buf):
        rc = main(["calibrate", str(small_mission.bag), "-o", str(cal),
                   "--config", str(small_mission.fast_config), "--truth",
                   str(small_mission.truth)])
    assert rc == 0
    return cal, buf.getvalue()


def test_calibrate_with_truth_column(rosbags_calibration, small_mission):
    cal, out = rosbags_calibration
    lines = out.splitlines()
    header = next(line for line in lines if line.startswith("parameter"))
    assert header.split() == ["parameter", "estimate", "sigma", "truth", "error/sigma"]
    truth = yaml.safe_load(small_mission.truth.read_text())["biases"]
    assert truth["dX"] == pytest.approx(small_mission.sim.biases["dX"])
    row = next(line for line in lines if line.startswith("dX "))
    assert f"{truth['dX'] * 100:+.2f} cm" in row  # the truth, in the report's units
    assert "calibration written to" in lines[-1]
    doc = calibration_values(cal)
    assert doc["converged"] is True
    assert doc["biases"]["dZ"] == {"value": 0.0, "sigma": None, "estimated": False}
    for name in ("dX", "dY", "dr"):  # metres: close to the simulated truth
        assert doc["biases"][name]["value"] == pytest.approx(truth[name], abs=0.01)


def test_mcap_ros2_writer_bag_same_result(capsys, tmp_path, small_mission, rosbags_calibration):
    """The mcap project's own ROS 2 writer (bare .mcap, schema names without /msg/)."""
    from mcap.reader import make_reader

    foreign = write_mcap_ros2_bag(tmp_path / "foreign.mcap", small_mission.mission)
    with foreign.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None
    assert sorted(s.name for s in summary.schemas.values()) == [
        "geometry_msgs/PoseStamped", "sensor_msgs/PointCloud2"]
    cal = tmp_path / "foreign_cal.yaml"
    rc, out, err = run(capsys, "calibrate", foreign, "-o", cal,
                       "--config", small_mission.fast_config, "--json")
    assert rc == 0, err
    got = calibration_values(cal)
    assert json.loads(out)["lidarcal_calibration"] == got  # --json prints the same document
    want = calibration_values(rosbags_calibration[0])
    for name in PARAMETER_NAMES:
        g, w = got["biases"][name], want["biases"][name]
        assert g["estimated"] == w["estimated"]
        assert g["value"] == pytest.approx(w["value"], rel=1e-9, abs=1e-15), name
        if w["sigma"] is None:
            assert g["sigma"] is None
        else:
            assert g["sigma"] == pytest.approx(w["sigma"], rel=1e-9), name
    assert got["sigma0"] == pytest.approx(want["sigma0"], rel=1e-9)
    for key in ("redundancy", "iterations", "converged", "correspondences"):
        assert got[key] == want[key], key
    np.testing.assert_allclose(got["correlation"]["matrix"], want["correlation"]["matrix"],
                               rtol=1e-9, atol=1e-12)


def test_simulate_writes_and_refuses_overwrite(capsys, tmp_path):
    out_bag = tmp_path / "sim"
    args = ["simulate", "-o", out_bag, "--scenario", "one_track", "--density", "0.05",
            "--line-length", "100", "--seed", "3"]
    rc, out, err = run(capsys, *args)
    assert rc == 0, err
    assert (out_bag / "metadata.yaml").is_file() and list(out_bag.glob("*.mcap"))
    control = tmp_path / "sim_control.csv"
    truth = tmp_path / "sim_truth.yaml"
    assert control.read_text().splitlines()[0] == "id,x,y,z"
    assert set(yaml.safe_load(truth.read_text())["biases"]) == set(PARAMETER_NAMES)
    for path in (out_bag, control, truth):
        assert str(path) in out
    before = truth.read_text()

    rc, _, err = run(capsys, *args, "--seed", "4")
    reason = one_line_error(rc, err, command="simulate")
    assert "exists" in reason and "--overwrite" in reason
    assert truth.read_text() == before

    rc, _, err = run(capsys, *args, "--overwrite")
    assert rc == 0, err


@pytest.mark.parametrize(("wind", "reason"), [
    ("5,x", "--wind: expected E,N in m/s, got '5,x'"),
    ("1,2,3", "--wind: expected E,N in m/s"),
    ("40,0", "crosswind of 40.0 m/s is too strong"),
])
def test_simulate_bad_wind_is_one_line(capsys, tmp_path, wind, reason):
    rc, _, err = run(capsys, "simulate", "-o", tmp_path / "sim", "--scenario", "one_track",
                     "--density", "0.05", "--line-length", "100", "--wind", wind)
    assert reason in one_line_error(rc, err, command="simulate")
    assert not (tmp_path / "sim").exists()


def test_simulate_with_wind_says_the_crab_in_its_truth(capsys, tmp_path):
    rc, _, err = run(capsys, "simulate", "-o", tmp_path / "sim", "--scenario", "one_track",
                     "--density", "0.05", "--line-length", "100", "--wind", "3,0")
    assert rc == 0, err
    simulation = yaml.safe_load((tmp_path / "sim_truth.yaml").read_text())["simulation"]
    assert simulation["wind_mps"] == [3.0, 0.0]
    crab = math.degrees(math.asin(3.0 / 60.0))  # north-south lines: all of it is crosswind
    assert sorted(simulation["crab_deg"].values()) == pytest.approx([-crab, -crab, crab, crab])


def test_simulate_with_attitude_writes_the_crabbed_heading_as_the_orientation(capsys,
                                                                               tmp_path):
    """``--attitude``: each pose's orientation is the sensor's heading, the track's turned
    by the line's crab; without it the orientation is the identity."""
    from lidarcal_ros.io.bag.mission_bag import read_mission

    for attitude in (True, False):
        out = tmp_path / f"sim_{attitude}"
        rc, _, err = run(capsys, "simulate", "-o", out, "--scenario", "one_track",
                         "--density", "0.05", "--line-length", "100", "--wind", "3,0",
                         *(["--attitude"] if attitude else []))
        assert rc == 0, err
        mission = read_mission(out)
        trajectory = mission.trajectory
        if not attitude:
            assert trajectory.heading is None
            continue
        simulation = yaml.safe_load((tmp_path / f"sim_{attitude}_truth.yaml").read_text())[
            "simulation"]
        assert simulation["attitude"] is True and trajectory.heading is not None
        for strip in mission.strips:
            on = np.flatnonzero((trajectory.t >= strip.t.min()) & (trajectory.t <= strip.t.max()))
            dx, dy = trajectory.xyz[on[-1], :2] - trajectory.xyz[on[0], :2]
            crab = trajectory.heading[on] - math.atan2(-dx, dy)
            want = math.radians(simulation["crab_deg"][strip.strip_id])
            assert abs(want) > 0.04 and np.allclose(np.sin(crab - want), 0.0, atol=1e-9)


def test_simulate_rough_air_writes_the_ins_attitude_and_its_truth(capsys, tmp_path):
    """``--rough-air`` alone: the reported rough air (roll +-4 deg, pitch +-2.5 deg, 1 deg of
    heading wobble, 5 deg of crab), the orientation on the trajectory at 50 Hz; the truth
    says the settings and each line's attitude; ``--no-attitude`` keeps positions only."""
    from lidarcal_ros.core.georeferencing.attitude import attitude_from_quaternions
    from lidarcal_ros.io.bag.mission_bag import read_mission

    base = ["--scenario", "one_track", "--density", "0.05", "--line-length", "200",
            "--rough-air"]
    rc, _, err = run(capsys, "simulate", "-o", tmp_path / "rough", *base)
    assert rc == 0, err
    trajectory = read_mission(tmp_path / "rough").trajectory
    assert trajectory.orientation is not None
    assert np.median(np.diff(trajectory.t)) == pytest.approx(0.02, abs=1e-6)
    roll, pitch, _ = attitude_from_quaternions(trajectory.orientation)
    assert np.degrees(np.abs(roll).max()) == pytest.approx(4.0, abs=1e-6)
    assert np.degrees(np.abs(pitch).max()) == pytest.approx(2.5, abs=1e-6)
    simulation = yaml.safe_load((tmp_path / "rough_truth.yaml").read_text())["simulation"]
    assert simulation["attitude"] is True
    assert sorted(simulation["crab_deg"].values()) == pytest.approx([-5, -5, 5, 5])
    settings = simulation["rough_air"]
    assert (settings["roll_deg"], settings["pitch_deg"], settings["yaw_deg"],
            settings["ins_rate_hz"]) == (4.0, 2.5, 1.0, 50.0)
    assert set(settings["disturbances"]) == {"roll", "pitch", "yaw", "heave", "sway"}
    for stats in simulation["line_attitude"].values():
        assert -4.0 - 1e-9 <= stats["roll_deg"][0] <= stats["roll_deg"][1] <= 4.0 + 1e-9
        assert abs(stats["crab_deg"][0]) == pytest.approx(5.0)
        assert stats["turn_deg_s"] == 0.0

    rc, _, err = run(capsys, "simulate", "-o", tmp_path / "bare", *base, "--no-attitude",
                     "--wind", "0,0")
    assert rc == 0, err
    assert read_mission(tmp_path / "bare").trajectory.orientation is None
    simulation = yaml.safe_load((tmp_path / "bare_truth.yaml").read_text())["simulation"]
    assert simulation["attitude"] is False and simulation["wind_mps"] == [0.0, 0.0]


def test_simulate_trajectory_errors_move_the_bag_by_the_truths_e_s(capsys, tmp_path):
    """``--trajectory-errors`` spelt out equals ``typical``; the bag's points and trajectory
    minus those of the same simulation without errors are each strip's ``e_s(t)`` of the
    truth file."""
    from lidarcal_ros.io.bag.mission_bag import read_mission
    from lidarcal_ros.pipeline.calibration.procedure import Truth

    base = ["--scenario", "one_track", "--density", "0.05", "--line-length", "200",
            "--seed", "4"]
    runs = {"clean": [], "typical": ["--trajectory-errors", "typical"],
            "spelt": ["--trajectory-errors", "offset_h=4cm,offset_v=5cm,drift=1cm/10s,"
                      "oscillation=1cm,period=60s"],
            "other": ["--trajectory-errors", "typical, seed=9, period=2min"]}
    for name, option in runs.items():
        rc, _, err = run(capsys, "simulate", "-o", tmp_path / name, *base, *option)
        assert rc == 0, err
    truth = {name: Truth.read(tmp_path / f"{name}_truth.yaml") for name in runs}
    assert truth["typical"] == truth["spelt"] != truth["clean"]
    other = truth["other"].trajectory_errors[1]
    assert other.period_s == 120.0 and other.offset != truth["typical"].trajectory_errors[1].offset
    clean, delivered = read_mission(tmp_path / "clean"), read_mission(tmp_path / "typical")
    errors = truth["typical"].trajectory_errors
    for strip0, strip in zip(clean.strips, delivered.strips, strict=True):
        error = errors[strip.strip_id]
        np.testing.assert_allclose(strip.xyz - strip0.xyz, error.at(strip.t), rtol=0, atol=1e-9)
        assert np.abs(error.at(strip.t)).max() > 0.005
        trajectory = delivered.trajectory
        on = (trajectory.t >= error.t_span[0]) & (trajectory.t <= error.t_span[1])
        np.testing.assert_allclose(trajectory.xyz[on] - clean.trajectory.xyz[on],
                                   error.at(trajectory.t[on]), rtol=0, atol=1e-9)


def test_simulate_rough_air_changes_and_turning_lines(capsys, tmp_path):
    """``--rough-air KEY=VALUE,...`` changes the reported rough air; ``--lines`` flies a
    banked turn, which puts the orientation on the trajectory by itself."""
    lines = tmp_path / "lines.yaml"
    lines.write_text("lines:\n"
                     "  - {id: 1, start: [0, -300], end: [0, 300], height: 700}\n"
                     "  - {id: 2, start: [-300, 0], end: [300, 0], height: 700, "
                     "bank_deg: 12}\n")
    rc, _, err = run(capsys, "simulate", "-o", tmp_path / "turn", "--lines", lines,
                     "--density", "0.05", "--rough-air", "roll=2,yaw=0,rate=100,seed=7")
    assert rc == 0, err
    simulation = yaml.safe_load((tmp_path / "turn_truth.yaml").read_text())["simulation"]
    settings = simulation["rough_air"]
    assert (settings["roll_deg"], settings["yaw_deg"], settings["pitch_deg"],
            settings["ins_rate_hz"], settings["seed"]) == (2.0, 0.0, 2.5, 100.0, 7)
    assert simulation["trajectory_rate_hz"] == 100.0
    turn = simulation["line_attitude"][2]
    assert turn["bank_deg"] == pytest.approx(12.0)
    assert turn["roll_deg"][0] >= 10.0 - 1e-9 and turn["roll_deg"][1] <= 14.0 + 1e-9
    assert turn["radius_m"] == pytest.approx(60.0**2 / (9.80665 * math.tan(math.radians(12))))
    # the crab of --rough-air: 5 deg across the first line
    assert simulation["crab_deg"][1] == pytest.approx(5.0)

    rc, _, err = run(capsys, "simulate", "-o", tmp_path / "calm_turn", "--lines", lines,
                     "--density", "0.05")
    assert rc == 0, err
    simulation = yaml.safe_load((tmp_path / "calm_turn_truth.yaml").read_text())["simulation"]
    assert simulation["attitude"] is True and simulation["rough_air"] is None


@pytest.mark.parametrize(("option", "value", "reason"), [
    ("--rough-air", "roll=x", "--rough-air: roll 'x' is not a number"),
    ("--rough-air", "roll=40", "--rough-air: roll must be in [0, 30], got 40.0"),
    ("--rough-air", "gusts=3", "--rough-air: expected KEY=VALUE with KEY one of roll"),
    ("--rough-air", "components=2.5", "--rough-air: components '2.5' is not an integer"),
    ("--rough-air", "min-period=5,max-period=2",
     "--rough-air: periods must satisfy 0 < min-period <= max-period"),
    ("--trajectory-errors", "typcal", "--trajectory-errors: expected 'typical' first, then "
     "KEY=VALUE with KEY one of offset_h, offset_v, drift, oscillation, period, seed, got "
     "'typcal'"),
    ("--trajectory-errors", "drift=1cm/x", "--trajectory-errors: drift '1cm/x' is not a "
     "drift rate (e.g. 1cm/10s, 1mm/s, 0.001)"),
    ("--trajectory-errors", "offset_v=5km", "--trajectory-errors: offset_v '5km' is not a "
     "length"),
    ("--trajectory-errors", "typical,offset_h=-4cm",
     "--trajectory-errors: offset_h must be a finite number >= 0, got -0.04"),
    ("--trajectory-errors", "period=0s", "--trajectory-errors: period must be positive"),
    ("--trajectory-errors", "seed=1.5", "--trajectory-errors: seed '1.5' is not an integer"),
    ("--trajectory-errors", ",", "--trajectory-errors: expected 'typical' or KEY=VALUE"),
    ("--lines", "missing.yaml", "missing.yaml: cannot read flight lines"),
    ("--lines", "{id: 1}", "lines.yaml: expected a list of lines"),
    ("--lines", "[{id: 1, start: [0, 0], end: [0, 500], height: 600, turn_deg_s: x}]",
     "lines.yaml: line 1: turn_deg_s must be a finite number, got 'x'"),
    ("--lines", "[{id: 1, start: [0, 0], end: [0, 500], height: 600, turn_deg_s: 30}]",
     "line 1: a turn of 30 deg/s at 60 m/s (radius 115 m) cannot join start and end"),
])
def test_simulate_bad_flight_options_are_one_line(capsys, tmp_path, option, value, reason):
    if option == "--lines" and value != "missing.yaml":
        (tmp_path / "lines.yaml").write_text(value)
        value = str(tmp_path / "lines.yaml")
    rc, _, err = run(capsys, "simulate", "-o", tmp_path / "sim", "--scenario", "one_track",
                     "--density", "0.05", "--line-length", "100", option, value)
    assert reason in one_line_error(rc, err, command="simulate")
    assert not (tmp_path / "sim").exists()


@pytest.mark.parametrize("command", ["calibrate", "correct", "report", "evaluate"])
def test_the_attitude_asked_of_a_bag_without_one_is_one_line(capsys, tmp_path, small_mission,
                                                              rosbags_calibration, command):
    cfg = write_params_file(tmp_path / "attitude.yaml", {"matching.heading_source": "attitude"})
    cal = rosbags_calibration[0]
    out = {"calibrate": "cal_out.yaml", "correct": "out.las", "report": "report.html"}
    args = [command, small_mission.bag, "--config", cfg]
    if command != "calibrate":
        args += ["--calibration", cal]
    if command in out:
        args += ["-o", tmp_path / out[command]]
    rc, _, err = run(capsys, *args)
    reason = one_line_error(rc, err, command=command)
    assert "'attitude' but the trajectory's poses carry no orientation" in reason
    assert not any((tmp_path / name).exists() for name in out.values())


def test_simulate_refuses_existing_bag_subprocess(tmp_path):
    (tmp_path / "sim").mkdir()
    proc = run_process("simulate", "-o", "sim", "--scenario", "one_track", "--density", "0.05",
                       "--line-length", "100", cwd=tmp_path)
    reason = one_line_error(proc.returncode, proc.stderr, command="simulate")
    assert reason.startswith("sim: exists (use --overwrite")
    assert not (tmp_path / "sim_truth.yaml").exists()


def test_progress_on_a_terminal_and_quiet_otherwise(tmp_path, small_mission):
    """``calibrate`` and ``correct`` show a progress bar on a terminal, none with --quiet or when
    stderr is not a terminal."""
    base = ["calibrate", small_mission.bag, "--config", small_mission.fast_config,
            "--control", small_mission.control_csv, "-o"]
    cal = tmp_path / "cal.yaml"
    rc, shown = run_on_a_terminal(*base, cal, cwd=tmp_path)
    assert rc == 0 and "iteration 1: matching" in shown and "choosing sample points" in shown
    rc, shown = run_on_a_terminal(*base, tmp_path / "cal2.yaml", "--quiet", cwd=tmp_path)
    assert rc == 0 and "iteration" not in shown
    piped = run_process(*base, tmp_path / "cal3.yaml", cwd=tmp_path)
    assert piped.returncode == 0 and "iteration" not in piped.stderr
    correct = ["correct", small_mission.bag, "--calibration", cal, "-o"]
    rc, shown = run_on_a_terminal(*correct, tmp_path / "a.laz", cwd=tmp_path)
    assert rc == 0 and "correcting" in shown
    rc, shown = run_on_a_terminal(*correct, tmp_path / "b.laz", "-q", cwd=tmp_path)
    assert rc == 0 and "correcting" not in shown
    piped = run_process(*correct, tmp_path / "c.laz", cwd=tmp_path)
    assert piped.returncode == 0 and "correcting" not in piped.stderr
