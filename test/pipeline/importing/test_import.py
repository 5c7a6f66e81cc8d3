"""``lidarcal import``: LAS/LAZ strips plus SBET / ASCII / rebuilt trajectory into a mission bag.

Simulated missions are exported the way a survey delivers them (LAS 1.4 / LAZ tiles, point
format 6, adjusted standard GPS time, point source id = strip; an SBET in GPS week seconds
with geographic positions) and imported again: the bag must hold the same points (within the
LAS scale) and give the same calibration. Multiple returns are synthesised on the exact
(biased) laser ray of a fraction of the pulses to test the trajectory estimate.

The exports are :mod:`helpers_las`'s, which also finds the real files (laspy's samples,
lidR's when available).
"""

from __future__ import annotations

import argparse
import copy
import logging
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers_las import (
    CRS,
    add_first_returns,
    plain_strips,
    real_las_file,
    write_las_tiles,
    write_mission_sbet,
)

from lidarcal_ros.cli.main import build_parser
from lidarcal_ros.cli.main import main as cli_main
from lidarcal_ros.core.calibration.calibrate import CalibrationSettings, calibrate
from lidarcal_ros.core.params import PARAMETER_NAMES, arcsec_to_rad
from lidarcal_ros.core.simulation.simulate import SimulatedMission, simulate_mission
from lidarcal_ros.core.simulation.spec import SimulationSpec
from lidarcal_ros.core.trajectory.segments import SegmentModel
from lidarcal_ros.errors import ConfigError, InputError, TrajectoryError
from lidarcal_ros.io.bag.mission_bag import read_mission
from lidarcal_ros.io.survey.las_reader import GpsTimeType
from lidarcal_ros.io.survey.las_writer import ADJUSTED_GPS_OFFSET, unix_to_adjusted_gps
from lidarcal_ros.io.survey.trajectory_crs import map_orientation
from lidarcal_ros.io.survey.trajectory_files import (
    WEEK_S,
    TimeBase,
    TrajectoryFile,
    TrajectoryFileKind,
    read_ascii_trajectory,
    read_sbet,
    read_trajectory_file,
    write_sbet,
)
from lidarcal_ros.pipeline.importing import importer
from lidarcal_ros.pipeline.importing.importer import import_mission
from lidarcal_ros.pipeline.importing.options import ImportOptions, Returns
from lidarcal_ros.pipeline.importing.time_bases import reconcile_times, trajectory_readings

ORIGIN = (500_000.0, 5_000_000.0)
FAST: dict[str, Any] = {"max_candidates_per_pair": 10_000, "per_class_cap": 500}
#: Twice the tolerances of the calibration issue (1 arcsec, 1 cm, 1e-5).
TWICE = {"dX": 0.02, "dY": 0.02, "dZ": 0.02, "dr": 0.02, "dS": 2e-5,
         "domega": arcsec_to_rad(2), "dphi": arcsec_to_rad(2), "dkappa": arcsec_to_rad(2)}


def _solution_diff(a: Any, b: Any) -> dict[str, float]:
    return {n: float(abs(a.solution.delta[i] - b.solution.delta[i]) / a.solution.sigma[i])
            for i, n in enumerate(PARAMETER_NAMES) if n in a.solution.estimated}


# ---------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def sim() -> SimulatedMission:
    return simulate_mission(SimulationSpec.from_options(density=0.2, line_length_m=250.0,
                                                        seed=11, origin=ORIGIN))


@pytest.fixture(scope="module")
def original_result(sim: SimulatedMission) -> Any:
    """Calibration of the original mission, its points rounded to the LAS scale (1 mm).

    The rounding alone moves the estimate by up to about 0.9 sigma here (sigmas of 0.04
    arcsec: the adjustment's discrete choices of correspondences change), so the import is
    compared with what the LAS files can hold.
    """
    mission = copy.deepcopy(sim.mission)
    for strip in mission.strips:
        strip.xyz = np.round(strip.xyz / 0.001) * 0.001
    return calibrate(mission, CalibrationSettings(**FAST))


@pytest.fixture(scope="module")
def exported(sim: SimulatedMission, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    work = tmp_path_factory.mktemp("export")
    tiles = write_las_tiles(plain_strips(sim), work)
    sbet = write_mission_sbet(sim.mission, work / "mission.out")
    return {"dir": work, "tiles": tiles, "sbet": sbet}


@pytest.fixture(scope="module")
def multi_return(sim: SimulatedMission, tmp_path_factory: pytest.TempPathFactory
                 ) -> dict[str, Any]:
    work = tmp_path_factory.mktemp("multi")
    tiles = write_las_tiles(add_first_returns(sim, fraction=0.3, seed=4), work, laz=(1, 2))
    bag = work / "estimated"
    report = import_mission(tiles, bag, ImportOptions(trajectory="estimate", returns=Returns.LAST))
    return {"tiles": tiles, "bag": bag, "report": report}


# ---------------------------------------------------------------------------- attitude
def test_sbet_heading_becomes_the_map_heading_of_the_poses(tmp_path: Path) -> None:
    """A crabbed mission 200 km east of its UTM zone's central meridian (2 deg of meridian
    convergence, as much as the crab): the SBET's true heading, less its wander angle and
    turned to grid north, comes back as the heading of every pose of the imported bag, which
    the calibration then takes (``matching.heading_source`` auto)."""
    from lidarcal_ros.core.georeferencing.local_trajectory import window_lines

    crabbed = simulate_mission(SimulationSpec.from_options(
        density=0.05, line_length_m=150.0, seed=5, origin=(700_000.0, 5_300_000.0),
        wind_mps=(4.0, 0.0), attitude=True))
    truth = crabbed.mission.trajectory
    assert truth.heading is not None
    tiles = write_las_tiles(plain_strips(crabbed), tmp_path, laz=())
    sbet = write_mission_sbet(crabbed.mission, tmp_path / "crab.out", wander_rad=0.7)
    assert read_sbet(sbet).heading_deg is not None
    bag = tmp_path / "imported"
    report = import_mission(tiles, bag, ImportOptions(trajectory=sbet))
    assert report.trajectory_kind == "SBET crab.out, with heading only"
    assert report.attitude_range_deg == {}
    got = read_mission(bag).trajectory
    assert got.heading is not None
    nearest = np.clip(np.searchsorted(truth.t, got.t), 0, len(truth) - 1)
    assert np.allclose(np.abs(truth.t[nearest] - got.t), 0.0, atol=1e-5)
    error = np.abs(np.remainder(got.heading - truth.heading[nearest] + math.pi, 2 * math.pi)
                   - math.pi)
    assert error.max() < 1e-6  # rad; ignoring the convergence would leave 2 deg
    lines = window_lines(np.array([float(crabbed.mission.strips[0].t[0])]), got)
    assert lines.heading_from == "attitude"


def test_sbet_without_attitude_and_ascii_heading_column(tmp_path: Path) -> None:
    """All-zero heading and wander (converters that fill only positions) mean no heading; an
    ASCII ``heading`` column is grid north for projected positions, degrees."""
    from lidarcal_ros.io.survey.trajectory_crs import map_heading

    sbet = write_sbet(tmp_path / "bare.out", np.array([1.0, 2.0]), np.radians([48.0, 48.0]),
                      np.radians([17.0, 17.0]), np.array([900.0, 900.0]))
    assert read_sbet(sbet).heading_deg is None
    text = "time,x,y,z,heading\n1,0,0,900,30\n2,0,60,900,-30\n"
    (tmp_path / "traj.csv").write_text(text)
    traj = read_ascii_trajectory(tmp_path / "traj.csv")
    kappa = map_heading(traj, None, None)
    assert kappa is not None and np.allclose(np.degrees(kappa), [-30.0, 30.0])
    (tmp_path / "plain.csv").write_text("1,0,0,900,0.1,0.2,90\n2,0,60,900,0.1,0.2,90\n")
    plain = read_ascii_trajectory(tmp_path / "plain.csv")  # time,x,y,z,roll,pitch,heading
    assert plain.heading_deg is not None and plain.heading_deg.tolist() == [90.0, 90.0]
    assert plain.attitude == "roll, pitch, heading"
    assert plain.roll_deg is not None and plain.roll_deg.tolist() == [0.1, 0.1]
    assert plain.pitch_deg is not None and plain.pitch_deg.tolist() == [0.2, 0.2]
    (tmp_path / "short.csv").write_text("1,0,0,900\n2,0,60,900\n")
    assert read_ascii_trajectory(tmp_path / "short.csv").heading_deg is None


#: ENU from NED (east, north, up from north, east, down) and REP-103's body (forward, left,
#: up) from the SBET's (forward, right, down), written out by hand.
ENU_FROM_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
FRD_FROM_FLU = np.diag([1.0, -1.0, -1.0])


def rotations_from_ned_euler(roll: np.ndarray, pitch: np.ndarray, heading: np.ndarray,
                             turn: np.ndarray | float = 0.0) -> Any:
    """SciPy Rotations of REP-103 body -> ENU of NED Euler angles (rad; Applanix:
    ``C_b^n = Rz(heading) Ry(pitch) Rx(roll)``), then turned counterclockwise about the
    vertical by ``turn`` (rad: true north to a map's grid north). Independent of
    :mod:`lidarcal_ros.core.georeferencing.attitude`."""
    from scipy.spatial.transform import Rotation

    c_bn = Rotation.from_euler("ZYX", np.column_stack([heading, pitch, roll])).as_matrix()
    turn_m = Rotation.from_euler("z", np.broadcast_to(turn, np.shape(roll))[:, None]
                                 ).as_matrix()
    return Rotation.from_matrix(turn_m @ ENU_FROM_NED @ c_bn @ FRD_FROM_FLU)


def rotation_errors(truth: Any, q_xyzw: np.ndarray) -> np.ndarray:
    """Angles (rad) between scipy Rotations and quaternions xyzw."""
    from scipy.spatial.transform import Rotation

    return np.asarray((truth.inv() * Rotation.from_quat(q_xyzw)).magnitude())


def test_sbet_euler_angles_become_rep103_quaternions(tmp_path: Path) -> None:
    """Random SBET attitudes (roll and pitch up to 30 deg, any heading, a wander angle): the
    orientation read back is scipy's rotation of the NED Euler angles, converted to ENU and
    REP-103's forward-left-up by hand, within 1e-9 rad; swapping the roll's sign or leaving
    out the pitch would not be."""
    rng = np.random.default_rng(3)
    n = 200
    roll, pitch = rng.uniform(-0.5, 0.5, n), rng.uniform(-0.5, 0.5, n)
    heading, wander = rng.uniform(-math.pi, math.pi, n), rng.uniform(-math.pi, math.pi, n)
    sbet = write_sbet(tmp_path / "att.out", np.arange(n, dtype=float), np.full(n, 0.8),
                      np.full(n, 0.3), np.full(n, 900.0), roll=roll, pitch=pitch,
                      heading=heading + wander, wander_angle=wander)
    traj = read_sbet(sbet)
    assert traj.attitude == "roll, pitch, heading"
    q, full = map_orientation(traj, None, None)  # no map: true north
    assert full and q is not None
    truth = rotations_from_ned_euler(roll, pitch, heading)
    assert rotation_errors(truth, q).max() < 1e-9
    wrong_roll = rotations_from_ned_euler(-roll, pitch, heading)
    assert np.median(rotation_errors(wrong_roll, q)) > 0.1
    level = rotations_from_ned_euler(roll, 0.0 * pitch, heading)
    assert np.median(rotation_errors(level, q)) > 0.1


#: A flight 200 km east of UTM 33's central meridian (2 deg of meridian convergence).
ATTITUDE_ORIGIN = (700_000.0, 5_300_000.0)


def _attitude_flight(t0_unix: float = 1.7e9) -> dict[str, Any]:
    """40 s of flight at 20 Hz, northward at 60 m/s, 1000 m up, with sinusoidal roll
    (+-4 deg), pitch (2 +- 3 deg) and true heading (178 +- 5 deg: across 180), and the
    true body -> grid ENU rotation of each sample (PROJ's meridian convergence)."""
    import pyproj

    dt = np.arange(0.0, 40.0, 0.05)
    t = t0_unix + dt
    east = np.full(dt.size, ATTITUDE_ORIGIN[0]) + 20.0 * np.sin(dt / 5.0)
    north = ATTITUDE_ORIGIN[1] + 60.0 * dt
    height = np.full(dt.size, 1000.0)
    roll = np.radians(4.0 * np.sin(2 * math.pi * dt / 9.0))
    pitch = np.radians(2.0 + 3.0 * np.sin(2 * math.pi * dt / 13.0 + 1.0))
    heading = np.radians(178.0 + 5.0 * np.sin(2 * math.pi * dt / 11.0))
    to_geo = pyproj.Transformer.from_crs(pyproj.CRS(CRS).to_3d(), "EPSG:4979", always_xy=True)
    lon, lat, h = to_geo.transform(east, north, height)
    convergence = np.radians(pyproj.Proj(CRS).get_factors(lon, lat).meridian_convergence)
    assert 1.9 < np.degrees(convergence).min() < np.degrees(convergence).max() < 2.1
    return {
        "t": t, "xyz": np.column_stack([east, north, height]), "lon": lon, "lat": lat,
        "h": h, "roll": roll, "pitch": pitch, "heading": heading,
        "grid_heading": heading - convergence,
        # grid azimuth = true azimuth - convergence: a counterclockwise turn by it
        "truth": rotations_from_ned_euler(roll, pitch, heading, convergence),
    }


def _strip_under(flight: dict[str, Any], n: int = 300) -> dict[str, np.ndarray]:
    """One strip of points on the ground under the flight, inside its time span."""
    rng = np.random.default_rng(8)
    t = np.sort(rng.uniform(flight["t"][0] + 1.0, flight["t"][-1] - 1.0, n))
    at = np.column_stack([np.interp(t, flight["t"], flight["xyz"][:, i]) for i in range(3)])
    xyz = at + np.column_stack([rng.uniform(-300.0, 300.0, n), rng.normal(0.0, 5.0, n),
                                np.full(n, -1000.0) + rng.normal(0.0, 2.0, n)])
    return {"xyz": xyz, "t": t, "intensity": rng.uniform(10.0, 200.0, n),
            "return_number": np.ones(n, np.uint8), "number_of_returns": np.ones(n, np.uint8),
            "strip_id": np.full(n, 3, dtype=np.uint16)}


def _check_imported_attitude(flight: dict[str, Any], bag: Path) -> np.ndarray:
    """Angles (rad) between the imported poses and the truth at the same times."""
    got = read_mission(bag).trajectory
    assert got.orientation is not None
    k = np.clip(np.searchsorted(flight["t"], got.t - 1e-4), 0, flight["t"].size - 1)
    assert np.abs(flight["t"][k] - got.t).max() < 1e-5
    assert len(got) >= 700  # every sample of the strip's span and 5 s either side
    return rotation_errors(flight["truth"][k], got.orientation)


def test_import_carries_the_full_attitude(tmp_path: Path, capsys) -> None:
    """The same flight with varying roll, pitch and heading as an SBET (wander angle 0.7
    rad), as an ASCII trajectory with named lat/lon columns (true north) and as a headerless
    ``time,x,y,z,roll,pitch,heading`` in the map's grid: every imported pose is the true
    rotation within 1e-6 rad. Dropping the meridian convergence would leave 2 deg, the roll
    or the pitch up to 4 or 5 deg."""
    flight = _attitude_flight()
    tiles = write_las_tiles([_strip_under(flight)], tmp_path, tiles=(1, 1), laz=())
    sow = np.mod(unix_to_adjusted_gps(flight["t"]) + ADJUSTED_GPS_OFFSET, WEEK_S)
    wander = 0.7
    sbet = write_sbet(tmp_path / "flight.out", sow, np.radians(flight["lat"]),
                      np.radians(flight["lon"]), flight["h"], roll=flight["roll"],
                      pitch=flight["pitch"], heading=flight["heading"] + wander,
                      wander_angle=np.full(sow.size, wander))
    deg = {k: np.degrees(flight[k]) for k in ("roll", "pitch", "heading", "grid_heading")}
    geographic = tmp_path / "flight_geo.csv"
    np.savetxt(geographic, np.column_stack([
        sow, deg["pitch"], flight["lat"], flight["lon"], flight["h"], deg["heading"],
        deg["roll"]]), delimiter=",", fmt="%.10f", comments="",
        header="gps_time,pitch (deg),latitude,longitude,height,heading,roll")
    grid = tmp_path / "flight_grid.txt"
    np.savetxt(grid, np.column_stack([sow, flight["xyz"], deg["roll"], deg["pitch"],
                                      np.mod(deg["grid_heading"], 360.0)]), fmt="%.10f")

    bag = tmp_path / "from_sbet"
    assert _cli(*tiles, "--trajectory", sbet, "-o", bag) == 0
    out = capsys.readouterr().out
    assert "SBET flight.out, with attitude (roll, pitch, heading)" in out
    assert f"roll {deg['roll'].min():+.1f}..{deg['roll'].max():+.1f} deg" in out
    assert f"pitch {deg['pitch'].min():+.1f}..{deg['pitch'].max():+.1f} deg" in out
    errors = {"sbet": _check_imported_attitude(flight, bag)}

    for name, path in (("ascii lat/lon", geographic), ("ascii grid", grid)):
        bag = tmp_path / path.stem
        report = import_mission(tiles, bag, ImportOptions(trajectory=path))
        assert report.trajectory_kind.endswith(", with attitude (roll, pitch, heading)")
        lo, hi = report.attitude_range_deg["roll"]
        assert lo == pytest.approx(deg["roll"].min(), abs=1e-6)
        assert hi == pytest.approx(deg["roll"].max(), abs=1e-6)
        errors[name] = _check_imported_attitude(flight, bag)
    for name, err in errors.items():
        assert err.max() < 1e-6, (name, err.max())


@pytest.mark.parametrize(("text", "attitude", "warning"), [
    ("time,x,y,z,roll,pitch,heading\n1,0,0,900,n/a,1,30\n2,0,60,900,n/a,1,31\n",
     "heading", "roll column 5 is not numeric: heading only"),
    ("time,x,y,z,roll,pitch,heading\n1,0,0,900,2,1,30\n2,0,60,900,2,nan,31\n",
     "heading", "pitch column 6 has 1 of 2 values not finite: heading only"),
    ("time,x,y,z,roll [deg],heading\n1,0,0,900,2,30\n2,0,60,900,2,31\n",
     "heading", "roll column 5 but no pitch column: heading only"),
    ("time,x,y,z,roll,pitch\n1,0,0,900,2,1\n2,0,60,900,2,1\n",
     "none", "roll column 5 and pitch column 6 but no heading: positions only"),
    ("1,0,0,900,2,1\n2,0,60,900,2,1\n",
     "none", "roll column 5 and pitch column 6 but no heading: positions only"),
    ("time,x,y,z,roll,pitch,heading\n1,0,0,900,0,0,30\n2,0,60,900,0,0,31\n",
     "heading", None),
])
def test_bad_roll_and_pitch_columns_fall_back(tmp_path, caplog, text, attitude,
                                               warning) -> None:
    """Roll or pitch not numbers, not finite or without its partner: one warning naming the
    file and column, and the heading alone; without a heading, positions only; all zero (a
    placeholder): the heading alone, silently."""
    path = tmp_path / "traj.csv"
    path.write_text(text)
    with caplog.at_level(logging.WARNING, logger="lidarcal_ros"):
        traj = read_trajectory_file(path)
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    if warning is None:
        assert warnings == []
    else:
        assert len(warnings) == 1 and warnings[0] == f"{path}: {warning}"
    assert traj.attitude == attitude
    q, full = map_orientation(traj, None, None)
    assert not full
    assert (q is None) == (attitude == "none")
    if q is not None:  # level poses along the heading (30 deg east of north: kappa -30 deg)
        assert np.allclose(q[0], rotations_from_ned_euler(
            np.zeros(1), np.zeros(1), np.radians([30.0])).as_quat()[0], atol=1e-12)


def test_sbet_roll_and_pitch_fallbacks(tmp_path, caplog) -> None:
    """An SBET with a heading but all-zero roll and pitch has a heading only; one with a
    non-finite roll warns and keeps the heading; one with roll and pitch but no heading
    warns and has positions only."""
    n = 3
    t, lat, lon, h = np.arange(n, dtype=float), np.full(n, 0.8), np.full(n, 0.3), np.full(n, 9.0)
    cases = [({"heading": np.full(n, 0.5)}, "heading", None),
             ({"heading": np.full(n, 0.5), "roll": np.array([0.01, np.nan, 0.02]),
               "pitch": np.full(n, 0.01)},
              "heading", "roll field has 1 of 3 values not finite: heading only"),
             ({"roll": np.full(n, 0.01), "pitch": np.full(n, 0.02)},
              "none", "roll field and pitch field but no heading: positions only")]
    for k, (fields, attitude, warning) in enumerate(cases):
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="lidarcal_ros"):
            traj = read_sbet(write_sbet(tmp_path / f"s{k}.out", t, lat, lon, h, **fields))
        assert traj.attitude == attitude
        assert [r.getMessage() for r in caplog.records] == (
            [] if warning is None else [f"{tmp_path / f's{k}.out'}: {warning}"])
        assert map_orientation(traj, None, None)[1] is False


# ---------------------------------------------------------------------------- round trip
def test_sbet_round_trip_gives_the_same_points(sim, exported, tmp_path) -> None:
    bag = tmp_path / "imported"
    report = import_mission(exported["tiles"], bag, ImportOptions(trajectory=exported["sbet"]))
    assert report.trajectory_kind == "SBET mission.out, positions only"
    assert report.time_rule.clock is TimeBase.UNIX
    assert report.time_rule.trajectory_base is TimeBase.WEEK
    mission = read_mission(bag)
    assert [s.strip_id for s in mission.strips] == [s.strip_id for s in sim.mission.strips]
    for got, want in zip(mission.strips, sim.mission.strips, strict=True):
        assert len(got) == len(want)
        assert np.max(np.abs(got.xyz - want.xyz)) <= 0.0005 + 1e-6
        assert np.max(np.abs(got.t - want.t)) < 1e-6
        assert got.intensity is not None and want.intensity is not None
        assert np.max(np.abs(got.intensity - want.intensity)) <= 0.5 + 1e-3
        assert set(got.extra) >= {"return_number", "number_of_returns", "classification"}
    # trajectory: the same positions at the same times (decimated to <= 50 Hz)
    traj, truth = mission.trajectory, sim.mission.trajectory
    at = np.column_stack([np.interp(traj.t, truth.t, truth.xyz[:, i]) for i in range(3)])
    assert np.max(np.abs(traj.xyz - at)) < 1e-3
    assert traj.t[0] <= sim.mission.strips[0].t[0]


def test_sbet_round_trip_gives_the_same_calibration(sim, exported, original_result,
                                                   tmp_path) -> None:
    bag = tmp_path / "imported.mcap"
    import_mission(exported["tiles"], bag, ImportOptions(trajectory=exported["sbet"]))
    mission = read_mission(bag)
    mission.control = sim.mission.control  # as `lidarcal calibrate --control CSV`
    result = calibrate(mission, CalibrationSettings(**FAST))
    diff = _solution_diff(original_result, result)
    assert max(diff.values()) <= 0.1, diff


def test_week_time_las_and_ascii_trajectory(sim, tmp_path) -> None:
    """LAS 1.2 in GPS week seconds, no point source ids, an ASCII trajectory in adjusted
    standard time: strips come from time gaps, the week from the trajectory."""
    tiles = write_las_tiles(plain_strips(sim), tmp_path, tiles=(1, 2), laz=(), version="1.2",
                            point_format=3, time_type=GpsTimeType.WEEK, point_source_id=False)
    traj = sim.mission.trajectory
    csv = tmp_path / "trajectory.csv"
    rows = np.column_stack([unix_to_adjusted_gps(traj.t), traj.xyz])
    np.savetxt(csv, rows, delimiter=",", fmt="%.6f", header="time,x,y,z", comments="")
    bag = tmp_path / "bag"
    report = import_mission(tiles, bag, ImportOptions(trajectory=csv))
    assert report.time_rule.points_base is TimeBase.WEEK
    assert report.time_rule.trajectory_base is TimeBase.ADJUSTED
    mission = read_mission(bag)
    assert [s.strip_id for s in mission.strips] == list(range(1, 7))
    assert all(s.source == "split at GPS-time gaps" for s in report.strips)
    for got, want in zip(mission.strips, sim.mission.strips, strict=True):
        assert len(got) == len(want)
        assert np.max(np.abs(got.t - want.t)) < 1e-5
        assert np.max(np.abs(got.xyz - want.xyz)) <= 0.0005 + 1e-6


def test_week_time_las_and_sbet_keep_week_seconds(sim, exported, tmp_path) -> None:
    tiles = write_las_tiles(plain_strips(sim), tmp_path, tiles=(1, 1), laz=(),
                            time_type=GpsTimeType.WEEK)
    bag = tmp_path / "bag"
    report = import_mission(tiles, bag, ImportOptions(trajectory=exported["sbet"]))
    assert report.time_rule.clock is TimeBase.WEEK
    mission = read_mission(bag)
    sow = np.mod(unix_to_adjusted_gps(sim.mission.strips[0].t) + ADJUSTED_GPS_OFFSET, WEEK_S)
    assert np.max(np.abs(mission.strips[0].t - sow)) < 1e-6
    # with the GPS week given, UNIX time again
    report = import_mission(tiles, tmp_path / "bag2", ImportOptions(
        trajectory=exported["sbet"], gps_week=report_week(sim)))
    assert report.time_rule.clock is TimeBase.UNIX
    assert np.max(np.abs(read_mission(tmp_path / "bag2").strips[0].t
                         - sim.mission.strips[0].t)) < 1e-6


def report_week(sim: SimulatedMission) -> int:
    gps = float(unix_to_adjusted_gps(sim.mission.strips[0].t[:1])[0]) + ADJUSTED_GPS_OFFSET
    return int(gps // WEEK_S)


def test_streaming_spills_and_merges(sim, exported, tmp_path) -> None:
    """A tiny memory budget forces sorted runs on disk; the bag is the same."""
    bag = tmp_path / "spilled"
    report = import_mission(exported["tiles"], bag, ImportOptions(
        trajectory=exported["sbet"], memory_points=20_000, chunk_points=7_000))
    assert report.spilled_runs >= 10
    mission = read_mission(bag)
    for got, want in zip(mission.strips, sim.mission.strips, strict=True):
        assert len(got) == len(want)
        assert np.max(np.abs(got.t - want.t)) < 1e-6


# ---------------------------------------------------------------------------- estimate
def test_rebuilt_trajectory_lies_near_the_truth(sim, multi_return) -> None:
    report = multi_return["report"]
    est = report.estimate
    assert est is not None and not est.failed_strips
    assert {q.level for q in est.segments} == {"OK"}
    assert {q.model for q in est.segments} == {SegmentModel.RAYS}  # (no fallback needed)
    traj = est.trajectory
    truth = sim.mission.trajectory
    at = np.column_stack([np.interp(traj.t, truth.t, truth.xyz[:, i]) for i in range(3)])
    err = np.linalg.norm(traj.xyz - at, axis=1)
    assert err.max() < 3.0, err.max()
    for q in est.segments:
        assert q.n_rays >= 100
        assert q.sigma_m < 1.0


def test_calibration_from_rebuilt_trajectory(sim, multi_return) -> None:
    mission = read_mission(multi_return["bag"])
    assert mission.n_points == sim.mission.n_points  # --returns last: the original points
    mission.control = sim.mission.control
    result = calibrate(mission, CalibrationSettings(**FAST))
    for i, name in enumerate(PARAMETER_NAMES):
        if name in result.solution.estimated:
            err = abs(result.solution.delta[i] - sim.biases[name])
            assert err <= TWICE[name], (name, err)


def test_no_multiple_returns_cannot_be_estimated(exported, tmp_path) -> None:
    with pytest.raises(TrajectoryError, match="multiple returns"):
        import_mission(exported["tiles"], tmp_path / "bag", ImportOptions(trajectory="estimate"))


# ---------------------------------------------------------------------------- time rules
def test_reconcile_week_from_points() -> None:
    gps = 2288 * WEEK_S + 250_000.0
    rule = reconcile_times(TimeBase.ADJUSTED, (gps - 1e9, gps - 1e9 + 600),
                           (249_000.0, 252_000.0), [TimeBase.WEEK])
    assert rule.week == 2288 and rule.clock is TimeBase.UNIX
    # a flight across the week boundary: trajectory week seconds of the previous week
    rule = reconcile_times(TimeBase.ADJUSTED, (gps - 1e9 - 250_100, gps - 1e9 - 250_000),
                           (WEEK_S - 200.0, WEEK_S + 1.0), [TimeBase.WEEK])
    assert rule.week == 2287


def _times_file(kind: TrajectoryFileKind, t: np.ndarray) -> TrajectoryFile:
    zero = np.zeros_like(t)
    return TrajectoryFile(Path("traj"), kind, t, zero, zero, zero, False)


def test_trajectory_readings_given_or_chosen() -> None:
    """A base given is the one reading; None chooses: an SBET's week seconds (restarting at
    0 past the week's end: continued), an ASCII file's by the times' magnitude."""
    across = np.array([WEEK_S - 10.0, WEEK_S - 5.0, 0.0, 5.0])
    sbet = _times_file(TrajectoryFileKind.SBET, across)
    assert trajectory_readings(sbet, None)[0] == [TimeBase.WEEK]
    assert trajectory_readings(sbet, None)[1].tolist() == [WEEK_S - 10, WEEK_S - 5, WEEK_S,
                                                           WEEK_S + 5]
    bases, raw = trajectory_readings(sbet, TimeBase.ADJUSTED)
    assert bases == [TimeBase.ADJUSTED] and raw is sbet.t  # (no week continued)
    for t, want in [(across, [TimeBase.WEEK, TimeBase.ADJUSTED]),
                    (np.array([1.38e9, 1.38e9 + 60]),
                     [TimeBase.GPS, TimeBase.UNIX, TimeBase.ADJUSTED]),
                    (np.array([3.3e8, 3.3e8 + 60]), [TimeBase.ADJUSTED])]:
        assert trajectory_readings(_times_file(TrajectoryFileKind.ASCII, t), None)[0] == want
    ascii_ = _times_file(TrajectoryFileKind.ASCII, across)
    assert trajectory_readings(ascii_, TimeBase.UNIX)[0] == [TimeBase.UNIX]


def test_reconcile_refuses_disjoint_times() -> None:
    with pytest.raises(TrajectoryError, match="do not overlap"):
        reconcile_times(TimeBase.WEEK, (1000.0, 2000.0), (5000.0, 6000.0),
                        [TimeBase.WEEK, TimeBase.ADJUSTED])


# ---------------------------------------------------------------------------- bad input
def _cli(*args: str | Path) -> int:
    return cli_main(["import", *map(str, args)])


def test_options_take_the_flags_strings() -> None:
    """``ImportOptions`` turns the flags' strings into their enums (``auto``: None) and
    refuses any other in one line naming the flag."""
    def options(**flags: Any) -> ImportOptions:  # (the strings, as a caller without types)
        return ImportOptions(**flags)

    got = options(returns="first", trajectory_time="gps")
    assert got.returns is Returns.FIRST and got.trajectory_time is TimeBase.GPS
    assert options(trajectory_time="auto").trajectory_time is None
    assert ImportOptions().returns is Returns.ALL and ImportOptions().trajectory_time is None
    with pytest.raises(ConfigError) as bad:
        options(returns="most")
    assert str(bad.value) == "--returns must be one of all, first, last, got 'most'"
    with pytest.raises(ConfigError) as bad:
        options(trajectory_time="utc")
    assert str(bad.value) == "--trajectory-time: unknown time base 'utc'"


def _import_parser() -> argparse.ArgumentParser:
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices["import"]


def test_cli_import_modes_are_the_enums(tmp_path, monkeypatch) -> None:
    """The choices of ``--returns`` and ``--trajectory-time`` are the values of
    :class:`Returns` and :class:`TimeBase` (and ``auto``), and each reaches the import as its
    member (``auto``: None); another is refused by the parser."""
    choices = {a.dest: a.choices for a in _import_parser()._actions}
    assert choices["returns"] == tuple(Returns)
    assert choices["trajectory_time"] == ("auto", *TimeBase)
    got: list[ImportOptions] = []

    class _Report:
        def lines(self) -> list[str]:
            return []

    def fake_import(inputs: Any, out: Any, options: ImportOptions, *_: Any, **__: Any) -> Any:
        got.append(options)
        return _Report()

    monkeypatch.setattr(importer, "import_mission", fake_import)
    strip = tmp_path / "strip.las"
    strip.write_bytes(b"")
    assert _cli(strip, "-o", tmp_path / "bag") == 0
    assert got[-1].returns is Returns.ALL and got[-1].trajectory_time is None
    for k, base in enumerate(TimeBase):
        returns = list(Returns)[k % len(Returns)]
        assert _cli(strip, "-o", tmp_path / "bag", "--returns", returns,
                    "--trajectory-time", base) == 0
        assert got[-1].returns is returns and got[-1].trajectory_time is base
    with pytest.raises(SystemExit):
        _cli(strip, "-o", tmp_path / "bag", "--trajectory-time", "utc")


def test_cli_import_and_calibrate(exported, tmp_path, capsys) -> None:
    bag = tmp_path / "cli_bag"
    assert _cli(*exported["tiles"], "--trajectory", exported["sbet"], "-o", bag) == 0
    out = capsys.readouterr().out
    assert "6 strips" in out
    assert read_mission(bag).n_points > 0


def test_las_without_gps_time(tmp_path, capsys) -> None:
    import laspy

    las = laspy.LasData(laspy.LasHeader(version="1.2", point_format=2))
    las.x = np.array([1.0, 2.0])
    las.y = np.array([1.0, 2.0])
    las.z = np.array([1.0, 2.0])
    path = tmp_path / "nogps.las"
    las.write(str(path))
    assert _cli(path, "-o", tmp_path / "bag") == 1
    err = capsys.readouterr().err.strip()
    assert "nogps.las" in err and "no GPS time" in err and "\n" not in err


def test_trajectory_not_covering_the_points(sim, exported, tmp_path, capsys) -> None:
    rec = read_sbet(exported["sbet"])
    short = tmp_path / "short.out"
    half = len(rec) // 2
    write_sbet(short, rec.t[:half], np.radians(rec.b[:half]), np.radians(rec.a[:half]),
               rec.c[:half])
    assert _cli(*exported["tiles"], "--trajectory", short, "-o", tmp_path / "bag") == 1
    err = capsys.readouterr().err.strip()
    assert "short.out" in err and "does not cover" in err and "\n" not in err
    assert not (tmp_path / "bag").exists()


def test_unknown_crs(exported, tmp_path, capsys) -> None:
    assert _cli(*exported["tiles"], "--trajectory", exported["sbet"], "--crs", "EPSG:999999",
                "-o", tmp_path / "bag") == 1
    err = capsys.readouterr().err.strip()
    assert "EPSG:999999" in err and "\n" not in err


def test_sbet_without_crs(sim, exported, tmp_path, capsys) -> None:
    tiles = write_las_tiles(plain_strips(sim), tmp_path, tiles=(1, 1), laz=(), crs=None)
    assert _cli(*tiles, "--trajectory", exported["sbet"], "-o", tmp_path / "bag") == 1
    err = capsys.readouterr().err.strip()
    assert "--crs" in err and "\n" not in err


def test_corrupt_laz(exported, tmp_path, capsys) -> None:
    laz = next(p for p in exported["tiles"] if p.suffix == ".laz")
    data = bytearray(laz.read_bytes())
    start = len(data) // 3
    data[start:start + 4000] = os.urandom(4000)
    bad = tmp_path / "corrupt.laz"
    bad.write_bytes(bytes(data))
    assert _cli(bad, "--trajectory", exported["sbet"], "-o", tmp_path / "bag") == 1
    err = capsys.readouterr().err.strip()
    assert "corrupt.laz" in err and "\n" not in err
    assert not (tmp_path / "bag").exists()


def test_not_an_sbet(exported, tmp_path) -> None:
    bad = tmp_path / "bad.out"
    bad.write_bytes(b"\x00" * 100)
    with pytest.raises(InputError, match="not an SBET"):
        import_mission(exported["tiles"], tmp_path / "bag", ImportOptions(trajectory=bad))


# ---------------------------------------------------------------------------- real data
def test_real_laspy_simple_strips_from_point_source_ids(tmp_path) -> None:
    """The laspy sample simple.las (LAS 1.2, week time, 9 point source ids, no CRS): reading and
    strip splitting; an ASCII trajectory made up to cover it."""
    path = real_las_file("simple.las")
    import laspy

    las = laspy.read(str(path))
    t = np.arange(math.floor(las.gps_time.min()) - 2, math.ceil(las.gps_time.max()) + 2, 0.25)
    centre = np.array([np.mean(las.x), np.mean(las.y), np.max(las.z) + 1000.0])
    xyz = centre + np.outer(t - t[0], [5.0, 0.0, 0.0])
    csv = tmp_path / "traj.txt"
    np.savetxt(csv, np.column_stack([t, xyz]), fmt="%.4f")
    report = import_mission([path], tmp_path / "bag", ImportOptions(trajectory=csv))
    mission = read_mission(tmp_path / "bag")
    ids, counts = np.unique(np.asarray(las.point_source_id), return_counts=True)
    assert [s.strip_id for s in mission.strips] == ids.tolist()
    assert [len(s) for s in mission.strips] == counts.tolist()
    assert report.time_rule.clock is TimeBase.WEEK


def _made_up_trajectory(path: Path, csv: Path, *, gap_s: float = 10.0,
                        adjusted: bool = False) -> np.ndarray:
    """An ASCII trajectory (GPS week seconds, header) 1500 m above each pass of a real file:
    one straight northward line per group of GPS times; returns the sorted raw times.
    ``adjusted``: the file's times are adjusted standard GPS time (week seconds derived)."""
    import laspy

    las = laspy.read(str(path))
    t_las = np.sort(np.asarray(las.gps_time))
    cuts = np.flatnonzero(np.diff(t_las) > gap_s)
    rows = []
    for lo, hi in zip(t_las[np.concatenate(([0], cuts + 1))],
                      t_las[np.concatenate((cuts, [t_las.size - 1]))], strict=True):
        t = np.arange(math.floor(lo) - 2, math.ceil(hi) + 2, 0.1)
        t_written = np.mod(t + 1e9, WEEK_S) if adjusted else t
        rows.append(np.column_stack([t_written, np.full(t.size, np.mean(las.x)),
                                     np.mean(las.y) + 60.0 * (t - t[0]),
                                     np.full(t.size, 1500.0)]))
    np.savetxt(csv, np.concatenate(rows), delimiter=",", fmt="%.4f",
               header="gps_time,easting,northing,height", comments="")
    return t_las


def test_real_laspy_lambert93_adjusted_time_and_overlap_qa(tmp_path) -> None:
    """The laspy sample append-bug.laz (LAS 1.4 format 8, adjusted standard time, RGF93 /
    Lambert-93, ids 712, 800-802): strips from ids, the week-second trajectory met through the
    points' absolute time, UNIX times in the bag, and the one real overlap (800 / 801, a strip of
    tile edge) checked by the swath-to-swath QA."""
    import laspy

    from lidarcal_ros.io.survey.trajectory_files import gps_to_unix

    path = real_las_file("append-bug.laz")
    _made_up_trajectory(path, tmp_path / "traj.csv", adjusted=True)
    report = import_mission([path], tmp_path / "bag",
                            ImportOptions(trajectory=tmp_path / "traj.csv"))
    las = laspy.read(str(path))
    ids, counts = np.unique(np.asarray(las.point_source_id), return_counts=True)
    mission = read_mission(tmp_path / "bag")
    assert [s.strip_id for s in mission.strips] == ids.tolist() == [712, 800, 801, 802]
    assert [len(s) for s in mission.strips] == counts.tolist()
    assert report.crs_name == "RGF93 / Lambert-93" and report.unit_factors == (1.0, 1.0)
    rule = report.time_rule
    assert (rule.points_base, rule.trajectory_base, rule.clock) == (
        TimeBase.ADJUSTED, TimeBase.WEEK, TimeBase.UNIX)
    sel = np.asarray(las.point_source_id) == 802
    want = np.sort(gps_to_unix(np.asarray(las.gps_time)[sel] + 1e9))
    assert np.allclose(np.sort(mission.strips[3].t), want, rtol=0, atol=1e-6)
    # Only 800 and 801 share ground: a 110 m sliver at x = 699000 m.
    assert [(q.strip_a, q.strip_b) for q in report.overlaps] == [(800, 801)]
    qa = report.overlaps[0]
    assert qa.n_cells >= 20 and abs(qa.median_dz) < 0.05 and qa.rms_dz < 0.08
    assert qa.level == "OK"


def test_real_nebraska_wrong_time_flag_gaps_and_crs_vlrs(tmp_path) -> None:
    """The laspy sample file_with_both_wkt_and_geotiff_vlrs.las (NAD83(2011) Nebraska in US feet,
    both a WKT and GeoTIFF keys, point source id 0, single returns): the header's week-time
    flag contradicts times of 3.3e8 s, which are read as adjusted standard time; strips come
    from time gaps; coordinates become metres."""
    import laspy

    path = real_las_file("file_with_both_wkt_and_geotiff_vlrs.las")
    # The passes span 9 days: the trajectory keeps the file's own (adjusted) times.
    t_las = _made_up_trajectory(path, tmp_path / "traj.csv")
    report = import_mission([path], tmp_path / "bag",
                            ImportOptions(trajectory=tmp_path / "traj.csv"))
    assert report.time_rule.points_base is report.time_rule.trajectory_base is TimeBase.ADJUSTED
    assert report.crs_name == "NAD83_2011_Nebraska_ft"
    assert report.unit_factors == pytest.approx((1200 / 3937, 1200 / 3937))
    passes = 1 + int(np.sum(np.diff(t_las) > 10.0))
    mission = read_mission(tmp_path / "bag")
    assert passes >= 2
    assert [s.strip_id for s in mission.strips] == list(range(1, passes + 1))
    assert all(s.source == "split at GPS-time gaps" for s in report.strips)
    assert sum(len(s) for s in mission.strips) == t_las.size
    las = laspy.read(str(path))
    z_min = min(float(s.xyz[:, 2].min()) for s in mission.strips)
    assert z_min == pytest.approx(1200 / 3937 * float(np.min(las.z)), abs=1e-3)


@pytest.mark.parametrize("keep", [100, 0.1, 0.5, 0.99, -8])
def test_real_truncated_laz_one_line(tmp_path, capsys, keep) -> None:
    """autzen_trim.laz cut in its header (100 bytes), in its points (10%, half, 99%) and in
    the chunk table at its end (8 bytes short): ``lidarcal import`` fails with one line
    naming the file and leaves no bag."""
    path = real_las_file("autzen_trim.laz")
    cut = tmp_path / "autzen_cut.laz"
    data = path.read_bytes()
    size = keep if isinstance(keep, int) and keep > 0 else \
        len(data) + keep if isinstance(keep, int) else int(len(data) * keep)
    cut.write_bytes(data[:size])
    rc = cli_main(["import", str(cut), "-o", str(tmp_path / "bag")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc != 0
    assert len([line for line in err if "error" in line]) == 1
    assert "autzen_cut.laz" in err[-1]
    assert not (tmp_path / "bag").exists()


def test_real_lidr_megaplot_strips_from_time_gaps(tmp_path) -> None:
    """The lidR sample Megaplot.laz (UTM 17N, week time): point source id 0 everywhere, two passes
    542 s apart become strips 1 and 2."""
    path = real_las_file("Megaplot.laz")
    t_las = _made_up_trajectory(path, tmp_path / "traj.csv")
    report = import_mission([path], tmp_path / "bag",
                            ImportOptions(trajectory=tmp_path / "traj.csv"))
    mission = read_mission(tmp_path / "bag")
    assert [s.strip_id for s in mission.strips] == [1, 2]
    assert sum(len(s) for s in mission.strips) == t_las.size
    assert all(s.source == "split at GPS-time gaps" for s in report.strips)
    t_split = t_las[np.argmax(np.diff(t_las))]
    assert mission.strips[0].t[-1] <= t_split < mission.strips[1].t[0]
    assert report.crs_name == "NAD83 / UTM zone 17N"


def test_real_lidr_mixed_conifer_overlap_qa(tmp_path) -> None:
    """The lidR sample MixedConifer.laz: four passes over a forest plot (ids 0, week time); the
    swath-to-swath QA of last returns on smooth 2 m cells finds the overlaps consistent
    to a few centimetres."""
    path = real_las_file("MixedConifer.laz")
    _made_up_trajectory(path, tmp_path / "traj.csv")
    report = import_mission([path], tmp_path / "bag",
                            ImportOptions(trajectory=tmp_path / "traj.csv", qa_cell_m=2.0))
    assert [s.strip_id for s in report.strips] == [1, 2, 3, 4]
    big = [q for q in report.overlaps if q.n_cells >= 100]
    assert len(big) >= 3
    for q in big:
        assert q.coverage > 0.8
        assert abs(q.median_dz) < 0.05 and q.rms_dz < 0.08 and q.level == "OK", q


def test_real_topography_trajectory_estimate(tmp_path) -> None:
    """The lidR sample Topography.laz (adjusted standard time, up to 6 returns, MTM zone 7): a
    sensor path is rebuilt from its multiple returns, high above the ground and moving at
    an aircraft's speed."""
    path = real_las_file("Topography.laz")
    report = import_mission([path], tmp_path / "bag", ImportOptions(trajectory="estimate"))
    est = report.estimate
    assert est is not None and not est.failed_strips
    q = est.segments[0]
    assert q.n_rays > 100
    assert 100.0 < q.height_m < 5000.0
    assert 20.0 < q.speed_mps < 150.0
    mission = read_mission(tmp_path / "bag")
    assert [s.strip_id for s in mission.strips] == [3]
    assert report.strips[0].source == "point_source_id 3"


def test_real_autzen_feet_to_metres(tmp_path) -> None:
    """The laspy sample autzen_trim.laz: Oregon Lambert in international feet, week time, one id
    (7326): coordinates become metres and the rebuilt sensor flies some 800 m up."""
    path = real_las_file("autzen_trim.laz")
    report = import_mission([path], tmp_path / "bag", ImportOptions(trajectory="estimate"))
    assert report.unit_factors == (0.3048, 0.3048)
    assert report.time_rule.clock is TimeBase.WEEK
    est = report.estimate
    assert est is not None and est.segments[0].level in ("OK", "WARN")
    assert 300.0 < est.segments[0].height_m < 3000.0
    mission = read_mission(tmp_path / "bag")
    import laspy

    las = laspy.read(str(path))
    assert np.isclose(mission.strips[0].xyz[:, 0].min(), 0.3048 * np.min(las.x), atol=1e-6)


def test_two_imports_of_the_same_files_write_the_same_messages(exported, tmp_path) -> None:
    """Every message's bytes are the same from run to run: the points' aligned layout has
    padding, which numpy's copies leave holding whatever memory was there; it is written as
    zero (the bags differ only in the name metadata.yaml gives the file)."""
    from mcap.reader import make_reader

    def messages(bag: Path) -> list[tuple[str, int, bytes]]:
        out = []
        for mcap_file in sorted(bag.glob("*.mcap")):
            with mcap_file.open("rb") as f:
                out += [(ch.topic, m.log_time, bytes(m.data))
                        for _s, ch, m in make_reader(f).iter_messages()]
        return out

    bags = [tmp_path / "first", tmp_path / "second"]
    for bag in bags:
        import_mission(exported["tiles"], bag, ImportOptions(trajectory=exported["sbet"]))
    first, second = (messages(b) for b in bags)
    assert len(first) > 100 and first == second
