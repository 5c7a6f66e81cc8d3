"""``lidarcal evaluate --dask``: the strips corrected and each pair's ICP run on a two-worker
local Dask cluster give the serial evaluation bit for bit (its subsets drawn here); a worker
killed in a pair's task is replaced and the evaluation unchanged; the one-line refusals."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import helpers_dask
import helpers_missions
import numpy as np
import pytest
from helpers_cli import one_line_error, run
from helpers_missions import MissionFiles

from lidarcal_ros.core.calibration.calibrate import CalibrationSettings
from lidarcal_ros.core.params import as_vector
from lidarcal_ros.pipeline.evaluation import Evaluation, evaluate_mission
from lidarcal_ros.pipeline.executor import DaskExecutor, Executor

small_mission = helpers_missions.small_mission
mission_factory = helpers_missions.mission_factory
cluster = helpers_dask.cluster
calibration = helpers_missions.small_calibration

#: Points per pair: fewer than most pairs share, so that their subsets are drawn.
MAX_POINTS = 3000


def _evaluated(files: MissionFiles, executor: Executor | None = None) -> Evaluation:
    """The small mission evaluated at its true biases, its control point as a check point."""
    mission = files.mission
    return evaluate_mission(mission, as_vector(files.sim.biases), CalibrationSettings(),
                            check_points=mission.control, max_points_per_pair=MAX_POINTS,
                            executor=executor)


@pytest.fixture(scope="module")
def serial(small_mission: MissionFiles) -> Evaluation:
    return _evaluated(small_mission)


def test_two_workers_give_the_serial_evaluation(
        small_mission: MissionFiles, cluster: DaskExecutor, serial: Evaluation) -> None:
    parted = _evaluated(small_mission, cluster)
    assert helpers_dask.differences(parted, serial) == []
    # (and an evaluation worth comparing: every pair fitted on a drawn subset, the biases'
    # offsets gone after the correction, the check point seen)
    assert len(serial.pairs) >= 10
    assert all(p.before is not None and p.after is not None for p in serial.pairs)
    assert max(p.before.n_matches for p in serial.pairs if p.before) <= MAX_POINTS
    assert np.median([p.after.rms_before / p.before.rms_before
                      for p in serial.pairs if p.before and p.after]) < 0.7
    assert len(serial.check_points) == 1 and serial.check_points[0].strips


def test_a_killed_worker_is_replaced_and_the_evaluation_unchanged(
        small_mission: MissionFiles, cluster: DaskExecutor, serial: Evaluation,
        tmp_path: Path) -> None:
    marker = tmp_path / "killed"
    # (killed in a pair's ICP: the strips it held are corrected again elsewhere)
    killing = helpers_dask.KillingExecutor(cluster, marker, part="-pair")
    parted = _evaluated(small_mission, killing)
    assert marker.exists()  # (a worker did die)
    assert helpers_dask.differences(parted, serial) == []


def test_the_command_through_a_scheduler_prints_the_serial_json(
        capsys: pytest.CaptureFixture[str], small_mission: MissionFiles,
        cluster: DaskExecutor, calibration: Path) -> None:
    docs: dict[str, Any] = {}
    for label, extra in (("serial", []), ("dask", ["--dask", cluster.client.scheduler.address])):
        rc, out, err = run(capsys, "evaluate", small_mission.bag, "--calibration", calibration,
                           "--check-points", small_mission.control_csv, "--json",
                           "--max-points", MAX_POINTS, *extra)
        assert rc == 0, err
        docs[label] = json.loads(out)
    assert docs["dask"] == docs["serial"]
    assert len(docs["serial"]["pairs"]) >= 10 and docs["serial"]["check_points"]


@pytest.mark.parametrize(("value", "words"), [
    ("local:0", "--dask local:0: N must be 1 to"),
    ("local:two", "--dask local:two: N of local:N must be a whole number"),
    ("tcp://nowhere", "--dask tcp://nowhere: expected tcp://HOST:PORT")])
def test_a_bad_value_is_refused_before_any_work(
        capsys: pytest.CaptureFixture[str], tmp_path: Path, value: str, words: str) -> None:
    # (the bag and the calibration do not exist: the value is refused before they are read)
    rc, _out, err = run(capsys, "evaluate", tmp_path / "missing", "--calibration",
                        tmp_path / "missing.yaml", "--dask", value)
    assert words in one_line_error(rc, err, "evaluate")
