"""``lidarcal correct`` in parts (``--dask``): through a two-worker local Dask cluster, and
in this process, the output's bytes are the serial run's (bag and LAZ); a worker killed in
its task is replaced and the part run again, the output unchanged; where the mission is cut.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import re
import signal
import subprocess
import sys
from pathlib import Path

import cloudpickle
import helpers_dask
import helpers_missions
import numpy as np
import pytest
import yaml
from helpers_missions import MissionFiles, write_calibration_yaml
from helpers_wait import wait_until

from lidarcal_ros.core.mission import Trajectory
from lidarcal_ros.core.simulation.simulate import simulate_mission
from lidarcal_ros.core.simulation.spec import TYPICAL_TRAJECTORY_ERRORS, SimulationSpec
from lidarcal_ros.core.trajectory.strip_errors import (
    StripError,
    TrajectoryEstimate,
    TrajectoryModel,
)
from lidarcal_ros.errors import InputError
from lidarcal_ros.io.bag.writer import BagWriter
from lidarcal_ros.io.calibration_file import trajectory_document
from lidarcal_ros.pipeline.calibration.procedure import write_simulation
from lidarcal_ros.pipeline.correction.apply import CorrectionSettings
from lidarcal_ros.pipeline.correction.bag import CorrectOptions, correct_bag
from lidarcal_ros.pipeline.correction.parts import (
    CloudSpan,
    _correct_part,
    _PartTask,
    plan_parts,
)
from lidarcal_ros.pipeline.executor import (
    DaskExecutor,
    Executor,
    SerialExecutor,
    open_executor,
)

mission_factory = helpers_missions.mission_factory
small_mission = helpers_missions.small_mission

# (the workers unpickle this module's functions by value: they cannot import a test module)
cloudpickle.register_pickle_by_value(sys.modules[__name__])

cluster = helpers_dask.cluster


@pytest.fixture(scope="module")
def calibration(small_mission: MissionFiles, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The small mission's true biases as a calibration file."""
    return write_calibration_yaml(tmp_path_factory.mktemp("cal") / "cal.yaml",
                                  small_mission.sim.biases)


def _corrected(bag: Path, calibration: Path, folder: Path, name: str,
               executor: Executor | None = None) -> bytes:
    """The bytes of ``name`` (a .mcap's, a .laz's) corrected in ``folder`` (the same name
    for every run: a bag's metadata holds its file name)."""
    folder.mkdir()
    out = folder / name
    correct_bag(bag, calibration, out, options=CorrectOptions(batch_points=20_000),
                executor=executor)
    assert not [p for p in folder.iterdir() if p.name.startswith(".")], "parts left behind"
    return out.read_bytes()


@pytest.mark.parametrize("name", ["out.mcap", "out.laz"])
def test_two_workers_write_the_serial_bytes(
        small_mission: MissionFiles, calibration: Path, cluster: DaskExecutor, name: str,
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    serial = _corrected(small_mission.bag, calibration, tmp_path / "serial", name)
    with caplog.at_level(logging.INFO, logger="lidarcal_ros.pipeline.correction.parts"):
        parted = _corrected(small_mission.bag, calibration, tmp_path / "dask", name, cluster)
    found = re.search(r"in (\d+) parts on Dask local cluster, 2 worker processes", caplog.text)
    assert found and int(found[1]) >= 2  # (cut between strips: the parts meet)
    assert parted == serial


def test_parts_in_this_process_write_the_serial_bytes(
        small_mission: MissionFiles, calibration: Path, tmp_path: Path) -> None:
    serial = _corrected(small_mission.bag, calibration, tmp_path / "serial", "out.las")
    parted = _corrected(small_mission.bag, calibration, tmp_path / "parts", "out.las",
                        SerialExecutor())
    assert parted == serial


@pytest.fixture(scope="module")
def drifting(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A small mission flown with typical trajectory errors, and a calibration holding each
    strip's true offset and drift: the output gets the corrected trajectory, made from the
    strips' time spans the parts gather."""
    work = tmp_path_factory.mktemp("drifting")
    spec = SimulationSpec.from_options(**helpers_missions.SMALL_MISSION)
    sim = simulate_mission(dataclasses.replace(spec,
                                                trajectory_errors=TYPICAL_TRAJECTORY_ERRORS))
    bag = write_simulation(work / "mission", sim)["bag"]
    estimate = TrajectoryEstimate(TrajectoryModel.DRIFT, {
        sid: StripError.linear(sid, err.t_ref, np.array(err.offset), np.full(3, 0.01),
                               np.array(err.drift), np.full(3, 0.001))
        for sid, err in sim.trajectory_errors.items()})
    doc = yaml.safe_load(write_calibration_yaml(work / "plain.yaml", sim.biases).read_text())
    doc["lidarcal_calibration"]["trajectory"] = trajectory_document(estimate)
    doc["lidarcal_calibration"]["trajectory_model"] = "drift"
    calibration = work / "cal.yaml"
    calibration.write_text(yaml.safe_dump(doc, sort_keys=False))
    return bag, calibration


def test_the_corrected_trajectory_from_parts_is_the_serial_one(
        drifting: tuple[Path, Path], cluster: DaskExecutor, tmp_path: Path) -> None:
    bag, calibration = drifting
    outputs = {}
    for label, executor in (("serial", None), ("dask", cluster)):
        folder = tmp_path / label
        folder.mkdir()
        report = correct_bag(bag, calibration, folder / "out.mcap",
                             options=CorrectOptions(trajectory_out=folder / "trajectory.csv"),
                             executor=executor)
        assert "poses -> /lidar/trajectory_corrected" in report.trajectory
        outputs[label] = [(folder / n).read_bytes() for n in ("out.mcap", "trajectory.csv")]
    assert outputs["dask"] == outputs["serial"]


def test_parts_pass_every_message_through_where_chunks_are_not_copied(
        small_mission: MissionFiles, calibration: Path, tmp_path: Path,
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(BagWriter, "copy_chunks_of", lambda self, bag, new_topics: None)
    serial = _corrected(small_mission.bag, calibration, tmp_path / "serial", "out.mcap")
    parted = _corrected(small_mission.bag, calibration, tmp_path / "parts", "out.mcap",
                        SerialExecutor())
    assert parted == serial


def test_a_scheduler_by_its_address_and_a_path_its_workers_do_not_see(
        small_mission: MissionFiles, calibration: Path, cluster: DaskExecutor,
        tmp_path: Path) -> None:
    serial = _corrected(small_mission.bag, calibration, tmp_path / "serial", "out.laz")
    with open_executor(cluster.client.scheduler.address) as remote:
        assert remote.description.startswith("Dask scheduler tcp://127.0.0.1:")
        parted = _corrected(small_mission.bag, calibration, tmp_path / "remote", "out.laz",
                            remote)
        assert parted == serial
        # (a worker that does not see the part's folder: as on a machine without the share)
        nowhere = Trajectory(np.zeros(0), np.zeros((0, 3)))
        task = _PartTask(str(small_mission.bag), "/lidar/points", "map", nowhere,
                         CorrectionSettings(delta=np.zeros(8)), "las", 1000, 0, 1,
                         str(tmp_path / "elsewhere" / "part-00000"))
        with pytest.raises(InputError, match=r"elsewhere: not found on Dask worker .*: the "
                           r"workers must see the output's folder at the same path"):
            remote.submit(_correct_part, task, key="unseen").result()


def test_a_killed_worker_is_replaced_and_the_output_unchanged(
        small_mission: MissionFiles, calibration: Path, cluster: DaskExecutor,
        tmp_path: Path) -> None:
    serial = _corrected(small_mission.bag, calibration, tmp_path / "serial", "out.mcap")
    marker = tmp_path / "killed"
    parted = _corrected(small_mission.bag, calibration, tmp_path / "dask", "out.mcap",
                        helpers_dask.KillingExecutor(cluster, marker))
    assert marker.exists()  # (a worker did die)
    assert parted == serial


# -------------------------------------------------------------------------- plan_parts
def _clouds(*spans: tuple[float, float], points: int = 100) -> list[CloudSpan]:
    return [CloudSpan(points, lo, hi) for lo, hi in spans]


def test_parts_are_cut_only_at_pauses_longer_than_the_grids_gap() -> None:
    clouds = _clouds((0, 1), (1, 2), (4.5, 5), (5, 6), (8.01, 9), (9, 10))
    # pauses: 2.5 s before cloud 2, 2.01 s before cloud 4; 2 s exactly is no cut
    assert plan_parts(clouds, 3) == [(0, 2), (2, 4), (4, 6)]
    assert plan_parts(clouds, 2) == [(0, 4), (4, 6)]
    assert plan_parts(clouds, 1) == [(0, 6)]
    assert plan_parts(_clouds((0, 1), (3, 4)), 2) == [(0, 2)]


def test_an_earlier_cloud_reaching_past_the_pause_prevents_the_cut() -> None:
    # cloud 1 ends at 9 s: the pause between clouds 2 and 3 (6 -> 7.5 s) is then none
    clouds = _clouds((0, 1), (1, 9), (5, 6), (9.5, 10))
    assert plan_parts(clouds, 4) == [(0, 4)]


def test_empty_clouds_and_unknown_times() -> None:
    empty = CloudSpan(0, math.nan, math.nan)
    clouds = [*_clouds((0, 1)), empty, *_clouds((5, 6))]
    assert plan_parts(clouds, 2) == [(0, 1), (1, 3)]  # (an empty cloud holds no grid)
    unknown = CloudSpan(10, math.nan, math.nan)
    assert plan_parts([*_clouds((0, 1)), unknown, *_clouds((5, 6))], 2) == [(0, 3)]
    assert plan_parts([], 2) == []


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_ends_the_command_and_its_cluster(
        small_mission: MissionFiles, calibration: Path, tmp_path: Path,
        sig: signal.Signals) -> None:
    out = tmp_path / "out.mcap"
    process = subprocess.Popen(
        [sys.executable, "-m", "lidarcal_ros", "correct", str(small_mission.bag),
         "--calibration", str(calibration), "-o", str(out), "-q", "--dask", "local:2"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    wait_until(lambda: len(_children(process.pid)) >= 2 or process.poll() is not None,
               30.0, "the cluster's worker processes")
    children = _children(process.pid)
    process.send_signal(sig)
    _out, err = process.communicate(timeout=60)
    assert process.returncode == (128 + sig if sig == signal.SIGTERM else 130)
    assert err.strip() == ("lidarcal correct: terminated" if sig == signal.SIGTERM
                           else "lidarcal correct: interrupted")
    wait_until(lambda: not [c for c in children if _running(c)], 10.0, "workers to end")
    assert list(tmp_path.iterdir()) == []  # no output, no parts


def _children(pid: int) -> list[str]:
    found = subprocess.run(["pgrep", "-P", str(pid)], capture_output=True, text=True)
    return found.stdout.split()


def _running(pid: str) -> bool:
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except FileNotFoundError:
        return False
    return "zombie" not in status
