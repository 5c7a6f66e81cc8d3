"""The live calibrator's work without ROS (``pipeline.calibration_service``).

Fed the small mission message by message as the node hands it over and never asked to solve,
the service closes every strip once its input stops, converges by itself to ``lidarcal
calibrate``'s estimate, checkpoints every estimate it gives, and answers its requests; a new
service resumes from the checkpoint and converges again to the same estimate; a cloud that
the calibration refuses is counted with its reason while the next one is taken.
"""

from __future__ import annotations

import shutil
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import helpers_missions
import numpy as np
import pytest
from helpers_wait import wait_until

from lidarcal_ros.core.calibration.calibrate import calibrate
from lidarcal_ros.core.calibration.result import CalibrationResult
from lidarcal_ros.core.config import FlightConfig
from lidarcal_ros.core.params import PARAMETER_NAMES
from lidarcal_ros.errors import LidarcalError
from lidarcal_ros.io.calibration_file import read_calibration
from lidarcal_ros.io.cloud.columns import CloudColumns
from lidarcal_ros.pipeline.calibration.service import CalibrationService, CalibratorOptions

small_mission = helpers_missions.small_mission
mission_factory = helpers_missions.mission_factory


def _config(mission: Any, tmp_path: Path) -> FlightConfig:
    return FlightConfig.from_mapping({
        **helpers_missions.FAST_SETTINGS,
        "calibration.control_points_file": str(mission.control_csv),
        "calibration.calibration_file": str(tmp_path / "saved.yaml")})


def _started(config: FlightConfig, results: list[CalibrationResult],
             **options: Any) -> CalibrationService:
    service = CalibrationService(config, CalibratorOptions.from_parameters(options),
                                 on_result=results.append)
    service.start()
    return service


def _feed(service: CalibrationService, events: list[helpers_missions.StreamEvent]) -> None:
    """Hand the events over as the node does."""
    for t, kind, payload in events:
        if kind == "pose":
            xyz, q = payload
            service.add_pose(t, (float(xyz[0]), float(xyz[1]), float(xyz[2])), "map",
                             tuple(float(v) for v in q))
        else:
            service.add_cloud(payload, "map")


def _within(result: CalibrationResult, reference: CalibrationResult, fraction: float) -> None:
    est = np.isfinite(reference.solution.sigma)
    assert np.array_equal(np.isfinite(result.solution.sigma), est)
    off = np.abs(result.solution.delta - reference.solution.delta)[est] / \
        reference.solution.sigma[est]
    assert np.all(off <= fraction), off


@dataclass
class Fed:
    """The service after the whole mission and its convergence (:func:`fed`)."""

    service: CalibrationService
    results: list[CalibrationResult]
    offline: CalibrationResult
    config: FlightConfig
    events: list[helpers_missions.StreamEvent]
    converged_checkpoint: Path


@pytest.fixture(scope="module")
def fed(small_mission: Any, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Fed]:
    """The small mission handed over message by message, then left alone until the service
    published a converged estimate over all six strips."""
    tmp_path = tmp_path_factory.mktemp("service")
    config = _config(small_mission, tmp_path)
    offline = calibrate(small_mission.mission, config.calibration_settings())
    assert offline.converged
    results: list[CalibrationResult] = []
    checkpoint = tmp_path / "ckpt.npz"
    service = _started(config, results, idle_close_s=0.3, checkpoint_file=str(checkpoint))
    events = helpers_missions.stream_events(small_mission.mission)
    _feed(service, events)
    stream = service.stream
    wait_until(lambda: len(stream.strip_ids) == 6 and not stream.open_strip_ids
               and not stream.refinement_pending and service.queued_jobs == 0 and bool(results)
               and results[-1].converged and service.checkpoints == len(results), 120,
               "a converged estimate over the six strips, checkpointed")
    kept = tmp_path / "converged.npz"
    shutil.copy(checkpoint, kept)
    try:
        yield Fed(service, results, offline, config, events, kept)
    finally:
        service.close()


def test_fed_a_mission_it_converges_by_itself_to_the_offline_estimate(fed: Fed) -> None:
    service, results = fed.service, fed.results
    # quick estimates as strips completed (not converged), then the converged one
    assert not results[0].converged and results[-1] is service.stream.latest
    _within(results[-1], fed.offline, 0.1)
    assert results[-1].solution.sigma == pytest.approx(fed.offline.solution.sigma, rel=0.05,
                                                       nan_ok=True)
    assert len(results[-1].pairs) == len(fed.offline.pairs)
    # every estimate given was checkpointed, and what it reports adds up
    assert service.solves == len(results) == service.checkpoints
    clouds = [e[2] for e in fed.events if e[1] == "cloud"]
    assert service.input.clouds == len(clouds) and service.input.skipped == 0
    assert service.input.points == sum(len(c) for c in clouds) == service.stream.n_points
    assert service.input.poses == len(fed.events) - len(clouds)
    statuses = {s.name: s for s in service.statuses()}
    assert statuses["lidarcal: convergence"].values["refining"] == "false"
    assert statuses["lidarcal: memory"].values["strips"] == "1,2,3,4,5,6"
    assert statuses["lidarcal: memory"].values["open_strips"] == ""
    assert statuses["lidarcal: input"].level == 0
    assert statuses["lidarcal: state"].values["solves"] == str(len(results))
    assert "lidarcal: strips 1&2" in statuses


def test_a_new_service_resumes_from_the_checkpoint_and_converges_again(
        fed: Fed, tmp_path: Path) -> None:
    checkpoint = tmp_path / "resume.npz"
    shutil.copy(fed.converged_checkpoint, checkpoint)
    results: list[CalibrationResult] = []
    service = _started(fed.config, results, checkpoint_file=str(checkpoint))
    try:
        assert service.resumed_from == str(checkpoint)
        assert service.stream.strip_ids == [1, 2, 3, 4, 5, 6]
        wait_until(lambda: bool(results) and results[-1].converged, 60, "the converged estimate")
        _within(results[-1], fed.results[-1], 0.01)
    finally:
        service.close()


def test_requests_save_solve_and_reset(fed: Fed) -> None:
    """The last test of the module: it empties the fed service."""
    service = fed.service
    saved = service.save()
    path = Path(fed.config["calibration.calibration_file"])
    assert str(path) in saved and "NOT converged" not in saved
    latest = service.stream.latest
    assert latest is not None
    record = read_calibration(path)
    assert [record.values[n] for n in PARAMETER_NAMES] == pytest.approx(
        list(latest.solution.delta), rel=1e-9, abs=1e-12)
    solves = service.solves
    answer = service.solve()
    assert answer.startswith(f"solved: {len(fed.offline.pairs)} strip pairs")
    assert service.solves == solves + 1
    _within(fed.results[-1], fed.offline, 0.1)
    checkpoint = Path(service.options.checkpoint_file)
    assert checkpoint.is_file()
    answer = service.reset()
    assert "forgotten" in answer and str(checkpoint) in answer and not checkpoint.exists()
    assert service.stream.strip_ids == [] and service.stream.n_points == 0
    with pytest.raises(LidarcalError):
        service.solve()
    with pytest.raises(LidarcalError, match=r"^no estimate yet"):
        service.save()


def test_a_refused_cloud_is_counted_with_its_reason_and_the_next_taken(
        small_mission: Any, tmp_path: Path) -> None:
    """Jobs run in the order given: a cloud in another frame than the trajectory's is refused
    (counted, the reason kept) and the next one is taken; options set between them apply to
    what follows."""
    service = _started(_config(small_mission, tmp_path), [], idle_close_s=0.0)
    try:
        strip = small_mission.mission.strips[0]
        cols = CloudColumns(strip.xyz[:100], strip.t[:100], None, np.ones(100, np.uint32))
        service.add_pose(float(strip.t[0]), (0.0, 0.0, 1000.0), "map", (np.nan,) * 4)
        service.add_cloud(cols, "odom")
        service.set_options(CalibratorOptions.from_parameters({"memory_budget_points": 5000}))
        service.add_cloud(cols, "map")
        wait_until(lambda: service.stream.n_points == 100, 10, "the second cloud")
        assert service.input.clouds == 2 and service.input.skipped == 1
        assert "frame 'odom'" in service.input.last_error
        assert service.stream.max_points == 5000
        inputs = next(s for s in service.statuses() if s.name == "lidarcal: input")
        assert inputs.level == 1 and "1 malformed clouds skipped" in inputs.message
    finally:
        service.close()


def test_poses_that_lag_the_last_cloud_past_the_idle_close_still_close_the_strip(
        small_mission: Any, tmp_path: Path) -> None:
    """An INS whose last poses come after the clouds have been idle for ``idle_close_s``: the
    idle close finds the last strip not yet covered by the trajectory and leaves it open; the
    lagging poses then arrive, and once they too stop, the strip is closed (it used to stay
    open for good: the idle close was not made again after input)."""
    events = helpers_missions.stream_events(small_mission.mission)
    last_cloud = max(t for t, kind, _ in events if kind == "cloud")
    cut = next(i for i, (t, kind, _) in enumerate(events) if kind == "pose" and t > last_cloud)
    service = _started(_config(small_mission, tmp_path), [], idle_close_s=0.3)
    try:
        _feed(service, events[:cut])
        stream = service.stream
        wait_until(lambda: len(stream.strip_ids) == 6 and service.queued_jobs == 0
                   and len(stream.open_strip_ids) == 1, 60, "five strips closed, one open")
        time.sleep(1.0)  # (the idle close has come and gone: the last strip is not covered)
        assert stream.open_strip_ids == [6]
        _feed(service, events[cut:])
        # (a strip being closed is in neither list until the calibration holds it: closed
        # means held, not only no longer open)
        wait_until(lambda: not stream.open_strip_ids and stream.strip_ids == [1, 2, 3, 4, 5, 6],
                   30, "the last strip closed and held")
    finally:
        service.close()


def test_input_pausing_mid_strip_with_the_poses_ahead_loses_no_point(
        fed: Fed, small_mission: Any, tmp_path: Path) -> None:
    """The input stops in the middle of strip 3 for longer than ``idle_close_s``, the poses
    1.5 s ahead of the clouds' stamps (past the trajectory window, so the idle close closes
    the strip; short of ``strip_gap_s``), then goes on: the close is taken back, the strip
    closes whole and the estimate converges to the offline one (0.1 sigma). Before, the
    strip's later points were left out as late."""
    mission = small_mission.mission
    strip = next(s for s in mission.strips if s.strip_id == 3)
    cut = float(strip.t[0] + strip.t[-1]) / 2.0
    before = [(e[1] == "pose" and e[0] < cut + 1.5) or (e[1] == "cloud" and e[0] < cut)
              for e in fed.events]
    results: list[CalibrationResult] = []
    service = _started(fed.config, results, idle_close_s=0.3)
    try:
        _feed(service, [e for e, b in zip(fed.events, before, strict=True) if b])
        wait_until(lambda: service.queued_jobs == 0, 60, "the first part")
        time.sleep(1.0)  # (the idle close has come and gone)
        assert 3 in [s.strip_id for s in service.stream.closed_strips]
        _feed(service, [e for e, b in zip(fed.events, before, strict=True) if not b])
        wait_until(lambda: len(service.stream.closed_strips) == 6
                   and not service.stream.refinement_pending and service.queued_jobs == 0
                   and bool(results) and results[-1].converged, 120,
                   "a converged estimate over the six strips")
        stream = service.stream
        assert stream.late_points == 0
        assert stream.n_points == sum(len(s) for s in mission.strips)
        _within(results[-1], fed.offline, 0.1)
    finally:
        service.close()
