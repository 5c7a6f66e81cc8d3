"""``lidarcal import`` with an SBET's accuracy file (``smrmsg``): its per-epoch position sigmas
carried in the bag (PoseWithCovarianceStamped) and read back with the trajectory."""

from __future__ import annotations

from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers_las import plain_strips, write_las_tiles, write_mission_sbet

from lidarcal_ros.cli.main import main as cli_main
from lidarcal_ros.core.calibration.calibrate import CalibrationSettings, Calibrator
from lidarcal_ros.core.simulation.simulate import SimulatedMission, simulate_mission
from lidarcal_ros.core.simulation.spec import SimulationSpec
from lidarcal_ros.core.trajectory.strip_errors import strip_offset_sigmas
from lidarcal_ros.io.bag.mission_bag import read_mission
from lidarcal_ros.io.survey.las_writer import ADJUSTED_GPS_OFFSET, unix_to_adjusted_gps
from lidarcal_ros.io.survey.trajectory_files import (
    SMRMSG_FIELDS,
    WEEK_S,
    read_sbet,
    read_smrmsg,
    smrmsg_beside,
    write_smrmsg,
)
from lidarcal_ros.pipeline.importing.importer import import_mission
from lidarcal_ros.pipeline.importing.options import ImportOptions

POSE_COV = "geometry_msgs/msg/PoseWithCovarianceStamped"


@cache
def _sim() -> SimulatedMission:
    return simulate_mission(SimulationSpec.from_options(
        density=0.1, line_length_m=250.0, seed=11, origin=(500_000.0, 5_000_000.0)))


@pytest.fixture(scope="module")
def delivered(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """The mission as delivered: LAS tiles, ``sbet_flight.out`` and, beside it,
    ``smrmsg_flight.out`` at 1 Hz over the SBET's span and a second more, its sigmas
    changing over time (north 2-8 cm, east 3 cm, down 5 cm + 2 cm sin)."""
    work = tmp_path_factory.mktemp("accuracy")
    sim = _sim()
    tiles = write_las_tiles(plain_strips(sim), work, tiles=(1, 1), laz=())
    sbet = write_mission_sbet(sim.mission, work / "sbet_flight.out")
    sow = read_sbet(sbet).t
    t = np.arange(np.floor(sow[0]) - 1.0, np.ceil(sow[-1]) + 2.0)
    north = 0.02 + 0.06 * (t - t[0]) / (t[-1] - t[0])
    down = 0.05 + 0.02 * np.sin(t / 7.0)
    smrmsg = write_smrmsg(work / "smrmsg_flight.out", t, north, np.full(t.size, 0.03), down,
                          roll_rms=np.full(t.size, 0.24))
    return {"dir": work, "tiles": tiles, "sbet": sbet, "smrmsg": smrmsg, "t": t,
            "north": north, "down": down}


def _expected(delivered: dict[str, Any], t_unix: np.ndarray) -> np.ndarray:
    """The sigmas (E, N, U, m) the smrmsg gives at the bag's stamps (UNIX s)."""
    sow = np.mod(unix_to_adjusted_gps(t_unix) + ADJUSTED_GPS_OFFSET, WEEK_S)
    t = delivered["t"]
    return np.column_stack([np.full(sow.size, 0.03), np.interp(sow, t, delivered["north"]),
                            np.interp(sow, t, delivered["down"])])


def _bag_types_and_covariances(bag: Path) -> tuple[set[str], np.ndarray]:
    """The trajectory topic's message types and covariances (n, 36), read with rosbags."""
    from rosbags.highlevel import AnyReader

    types, cov = set(), []
    with AnyReader([bag]) as reader:
        conns = [c for c in reader.connections if c.topic == "/lidar/trajectory"]
        for conn, _ns, raw in reader.messages(connections=conns):
            types.add(conn.msgtype)
            if conn.msgtype == POSE_COV:
                msg: Any = reader.deserialize(raw, conn.msgtype)
                cov.append(np.array(msg.pose.covariance))
    return types, np.array(cov)


def test_the_smrmsg_beside_the_sbet_travels_in_the_bag(delivered: dict[str, Any],
                                                        tmp_path: Path) -> None:
    """``smrmsg_flight.out`` beside ``sbet_flight.out`` is taken (POSPac's names): every
    pose is a PoseWithCovarianceStamped whose covariance diagonal is the smrmsg's east,
    north, down RMS squared at its time (1e-9 m), read back as the trajectory's position
    sigmas; the strips' priors are their RMS over each strip; ``none`` leaves them out."""
    assert smrmsg_beside(delivered["sbet"]) == delivered["smrmsg"]
    bag = tmp_path / "with"
    report = import_mission(delivered["tiles"], bag, ImportOptions(trajectory=delivered["sbet"]))
    assert report.trajectory_kind.startswith(
        "SBET sbet_flight.out, positions only; position sigmas from smrmsg_flight.out "
        "(horizontal ")
    types, cov = _bag_types_and_covariances(bag)
    assert types == {POSE_COV}
    mission = read_mission(bag)
    traj = mission.trajectory
    assert traj.position_sigma is not None and len(cov) == len(traj)
    want = _expected(delivered, traj.t)
    np.testing.assert_allclose(traj.position_sigma, want, rtol=0, atol=1e-9)
    np.testing.assert_allclose(cov[:, [0, 7, 14]], want ** 2, rtol=0, atol=1e-12)
    assert not cov[:, [21, 28, 35]].any()  # (the orientation's: unknown)
    settings = CalibrationSettings(max_candidates_per_pair=10_000, per_class_cap=500)
    state = Calibrator.from_mission(mission, settings).matcher.trajectory
    for basis, strip in zip(state.bases, mission.strips, strict=True):
        inside = (traj.t >= strip.t.min()) & (traj.t <= strip.t.max())
        e, n, u = want[inside].T
        h = np.sqrt(np.mean((e ** 2 + n ** 2) / 2))
        got = strip_offset_sigmas(traj, strip.t.min(), strip.t.max())
        assert basis.navigation_sigmas is not None and got is not None
        np.testing.assert_allclose(basis.navigation_sigmas, [h, h, np.sqrt(np.mean(u ** 2))])
        np.testing.assert_allclose(got, basis.navigation_sigmas)
    plain = tmp_path / "without"
    import_mission(delivered["tiles"], plain,
                   ImportOptions(trajectory=delivered["sbet"], trajectory_accuracy="none"))
    assert _bag_types_and_covariances(plain)[0] == {"geometry_msgs/msg/PoseStamped"}
    assert read_mission(plain).trajectory.position_sigma is None


def test_an_smrmsg_given_by_name_and_the_layout(delivered: dict[str, Any],
                                                tmp_path: Path) -> None:
    """``--trajectory-accuracy FILE`` for an SBET of another name; the record layout as
    numpy writes it by hand (10 little-endian float64: time, north, east, down position RMS,
    velocity RMS, roll, pitch, heading RMS) reads back field for field."""
    sbet = tmp_path / "mission.out"
    sbet.write_bytes(delivered["sbet"].read_bytes())
    raw = np.fromfile(delivered["smrmsg"], dtype="<f8").reshape(-1, 10)
    assert len(SMRMSG_FIELDS) == 10
    acc = read_smrmsg(delivered["smrmsg"])
    np.testing.assert_array_equal(acc.t, raw[:, 0])
    np.testing.assert_array_equal(acc.position_rms, raw[:, 1:4])
    np.testing.assert_array_equal(raw[:, 7], 0.24)
    by_hand = tmp_path / "accuracy.bin"
    raw.astype("<f8").tofile(by_hand)
    bag = tmp_path / "named.mcap"
    rc = cli_main(["import", *map(str, delivered["tiles"]), "--trajectory", str(sbet),
                   "--trajectory-accuracy", str(by_hand), "-o", str(bag), "-q"])
    assert rc == 0
    traj = read_mission(bag).trajectory
    assert traj.position_sigma is not None
    np.testing.assert_allclose(traj.position_sigma, _expected(delivered, traj.t), atol=1e-9)


def _bad(path: Path, delivered: dict[str, Any], kind: str) -> Path:
    t, north, down = delivered["t"], delivered["north"], delivered["down"]
    if kind == "truncated":
        path.write_bytes(delivered["smrmsg"].read_bytes()[:-12])
    elif kind == "nan":
        north = north.copy()
        north[5] = np.nan
        write_smrmsg(path, t, north, np.full(t.size, 0.03), down)
    elif kind == "short":
        half = t.size // 2
        write_smrmsg(path, t[:half], north[:half], np.full(half, 0.03), down[:half])
    elif kind == "backwards":
        write_smrmsg(path, t[::-1], north, np.full(t.size, 0.03), down)
    return path


@pytest.mark.parametrize(("kind", "words"), [
    ("truncated", "is not a whole number of 80-byte records (truncated?)"),
    ("nan", "smrmsg record 5 has time"),
    ("short", "it does not cover the trajectory"),
    ("backwards", "does not follow record 0"),
    ("missing", "trajectory file not found"),
])
def test_a_bad_smrmsg_is_refused_in_one_line(delivered: dict[str, Any], tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str], kind: str,
                                             words: str) -> None:
    """Truncated, a NaN, epochs that do not cover the SBET's, times not increasing, or
    missing: one line naming the file, nothing written."""
    bad = _bad(tmp_path / "smrmsg_bad.out", delivered, kind)
    bag = tmp_path / "bag"
    rc = cli_main(["import", *map(str, delivered["tiles"]), "--trajectory",
                   str(delivered["sbet"]), "--trajectory-accuracy", str(bad), "-o", str(bag),
                   "-q"])
    err = capsys.readouterr().err
    assert rc == 1 and len(err.strip().splitlines()) == 1, err
    assert "smrmsg_bad.out" in err and words in err, err
    assert not bag.exists()


def test_an_accuracy_file_needs_a_trajectory_file(delivered: dict[str, Any],
                                                  tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    rc = cli_main(["import", *map(str, delivered["tiles"]), "--trajectory-accuracy",
                   str(delivered["smrmsg"]), "-o", str(tmp_path / "bag"), "-q"])
    err = capsys.readouterr().err
    assert rc == 1 and "needs a trajectory file" in err and len(err.strip().splitlines()) == 1
