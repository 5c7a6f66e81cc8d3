"""The calibrator's work on clouds in the sensor's frame without ROS (pipeline/calibration/
service.py over sensor_stream.py, docs/method.md section 12): a small simulated UAV payload
handed over message by message as the node hands it over.

``calibration.solve_for`` is honoured as ``lidarcal calibrate`` honours it (dS and, without
control, dZ left out in one line); a service stopped mid-flight without closing resumes from
its checkpoint as a mounting's calibration and saves the mounting of the whole flight; the
points held while a line is flown stay within :data:`HELD_S` of the trajectory.
"""

from __future__ import annotations

import functools
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers_wait import wait_until as _wait

from lidarcal_ros.core.calibration.extrinsic import (
    MOUNTING_SOLVE_FOR,
    MountingCalibration,
    calibrate_mounting,
    timing_statement,
)
from lidarcal_ros.core.config import SCHEMA, FlightConfig
from lidarcal_ros.core.georeferencing.sensor_frame import Mounting
from lidarcal_ros.core.mission import ControlPoints
from lidarcal_ros.core.params import PARAMETER_INDEX
from lidarcal_ros.core.simulation.uav_payload import (
    NANOSECONDS_UINT32,
    UavPayloadMission,
    UavPayloadSpec,
    simulate_uav_payload,
)
from lidarcal_ros.io.calibration_file import Extrinsic, read_calibration
from lidarcal_ros.io.cloud.messages import OK, StatusSpec, qa_summary
from lidarcal_ros.pipeline.calibration.sensor_frame import (
    log_solve_for_note,
    mounting_solve_for,
    sensor_calibration_settings,
)
from lidarcal_ros.pipeline.calibration.sensor_stream import HELD_S, SensorFrameFeed
from lidarcal_ros.pipeline.calibration.service import CalibrationService, CalibratorOptions
from lidarcal_ros.pipeline.calibration.statuses import timing_status_text, with_timing_bias
from lidarcal_ros.pipeline.calibration.streaming import StreamingCalibration


@functools.cache
def _mission() -> UavPayloadMission:
    """Three lines of 80 m by a VLP-16 of 48 columns (the node test's payload)."""
    return simulate_uav_payload(UavPayloadSpec(seed=3, columns=48, n_lines=3,
                                               line_length_m=80.0))


def _clouds(m: UavPayloadMission) -> list[tuple[float, np.ndarray, np.ndarray]]:
    """Each cloud: stamp s, points (n, 3) in the sensor's frame, absolute times s."""
    c = m.clouds
    scale = 1e-9 if c.time_units == NANOSECONDS_UINT32 else 1.0
    out = []
    for k, stamp in enumerate(c.stamps):
        a, b = int(c.offsets[k]), int(c.offsets[k + 1])
        out.append((float(stamp), np.asarray(c.xyz[a:b]),
                    float(stamp) + np.asarray(c.time[a:b], dtype=np.float64) * scale))
    return out


def _events(m: UavPayloadMission, start: float = -np.inf,
            end: float = np.inf) -> list[tuple[float, str, Any]]:
    """Poses and clouds stamped in [start, end), in time order (poses first at a tie)."""
    tr = m.trajectory
    assert tr.orientation is not None
    events: list[tuple[float, str, Any]] = [
        (float(t), "pose", (xyz, q)) for t, xyz, q in zip(tr.t, tr.xyz, tr.orientation,
                                                           strict=True)
        if start <= t < end]
    events += [(s, "~cloud", (xyz, t)) for s, xyz, t in _clouds(m) if start <= s < end]
    return sorted(events, key=lambda e: (e[0], e[1]))


def _feed(service: CalibrationService, events: list[tuple[float, str, Any]]) -> None:
    for t, kind, payload in events:
        if kind != "pose":
            service.add_sensor_cloud(payload[0], payload[1], "velodyne")
            continue
        x, y, z = (float(v) for v in payload[0])
        service.add_pose(t, (x, y, z), "map", tuple(float(v) for v in payload[1]))


def _offline(m: UavPayloadMission, solve_for: tuple[str, ...]) -> MountingCalibration:
    xyz = np.concatenate([c[1] for c in _clouds(m)])
    t = np.concatenate([c[2] for c in _clouds(m)])
    return calibrate_mounting(xyz, t, m.trajectory, m.nominal,
                              settings=sensor_calibration_settings(solve_for))


def _mounting_text(m: Any) -> str:
    return ",".join(repr(float(v)) for v in (*m.translation, *m.quaternion))


def _service(tmp_path: Path, **values: Any) -> CalibrationService:
    m = _mission()
    options = {"idle_close_s": 0.0, **{k: v for k, v in values.items() if "." not in k}}
    config = FlightConfig.from_mapping({
        "sensor_frame.mounting": _mounting_text(m.nominal),
        "calibration.calibration_file": str(tmp_path / "live.yaml"),
        **{k: v for k, v in values.items() if "." in k}})
    service = CalibrationService(config, CalibratorOptions.from_parameters(options))
    service.start()
    return service


def _stop_without_closing(service: CalibrationService) -> None:
    """A kill: the worker stops, no last checkpoint."""
    service._closing.set()
    service._worker.join(timeout=30)


def _same_mounting(saved: Path, offline: MountingCalibration, fraction: float) -> None:
    record = read_calibration(saved)
    assert record.extrinsic is not None
    live = record.extrinsic.mounting
    est = np.isfinite(offline.translation_sigma_m)
    diff = np.abs(live.translation - offline.mounting.translation)
    assert np.all(diff[est] <= fraction * offline.translation_sigma_m[est]), diff
    assert np.allclose(diff[~est], 0.0, atol=1e-9)
    r = live.rotation.T @ offline.mounting.rotation
    angle = np.arccos(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0))
    assert angle <= fraction * float(np.nanmin(offline.rotation_sigma_rad)), angle
    off = np.abs(record.delta - offline.delta)[np.isfinite(offline.sigma)] / \
        offline.sigma[np.isfinite(offline.sigma)]
    assert np.all(off <= fraction), off


# ------------------------------------------------------------------- solve_for

def test_solve_for_of_a_mounting() -> None:
    default = tuple(SCHEMA["calibration.solve_for"].default)
    names, note = mounting_solve_for(default, has_control=False)
    assert names == MOUNTING_SOLVE_FOR
    assert note.startswith("calibration.solve_for: dS is no parameter") and "\n" not in note
    names, note = mounting_solve_for(("dZ", "dX", "domega", "dS"), has_control=False)
    assert names == ("dX", "domega") and "dZ needs control points" in note
    names, note = mounting_solve_for(("dZ", "dX", "domega"), has_control=True)
    assert names == ("dX", "dZ", "domega") and note == ""
    # the default with control points: the vertical lever arm too
    names, _ = mounting_solve_for(default, has_control=True)
    assert names == ("dX", "dY", "dZ", "domega", "dphi", "dkappa", "dr")


def test_the_note_is_a_warning_only_where_asked_for(caplog: pytest.LogCaptureFixture) -> None:
    default = SCHEMA["calibration.solve_for"].default
    with caplog.at_level(logging.INFO):
        log_solve_for_note(mounting_solve_for(default, has_control=False)[1], default)
        log_solve_for_note(mounting_solve_for(["dS", "dX"], has_control=False)[1],
                           ["dS", "dX"])
    assert [r.levelno for r in caplog.records] == [logging.INFO, logging.WARNING]


def test_the_configured_solve_for_is_honoured_live_as_offline(tmp_path: Path) -> None:
    """With dr not asked for (and dS, which is left out), the live service estimates dX, dY and
    the boresight alone, and saves ``lidarcal calibrate``'s mounting of them (0.1 sigma)."""
    m = _mission()
    asked = ["dX", "dY", "domega", "dphi", "dkappa", "dS"]
    service = _service(tmp_path, **{"calibration.solve_for": asked})
    try:
        _feed(service, _events(m))
        assert "solved" in service.solve()
        saved = service.save().split("written to ")[1].split(",")[0]
    finally:
        service.close()
    latest = service.stream.latest
    assert latest is not None
    estimated = {n for n, i in PARAMETER_INDEX.items() if np.isfinite(latest.solution.sigma[i])}
    assert estimated == {"dX", "dY", "domega", "dphi", "dkappa"}
    offline = _offline(m, mounting_solve_for(asked, has_control=False)[0])
    _same_mounting(Path(saved), offline, 0.1)
    assert service.mounting is not None and service.mounting.range_offset_m == 0.0


def test_control_arriving_brings_dz_in(tmp_path: Path) -> None:
    """With dZ asked for, it is held until control points arrive, then estimated (the strips
    re-prepared with the new settings)."""
    m = _mission()
    service = _service(tmp_path, **{"calibration.solve_for": ["dX", "dY", "dZ", "domega"]})
    try:
        service.add_sensor_cloud(*_clouds(m)[0][1:], "velodyne")
        _wait(lambda: service.sensor.active and service.queued_jobs == 0, 30, "a cloud")
        assert "dZ" not in service.stream._settings.solve_for
        xyz = m.truth_xyz[::5000][:4]
        service.set_control(ControlPoints([f"C{i}" for i in range(len(xyz))], xyz), "test")
        _wait(lambda: service.queued_jobs == 0 and "dZ" in service.stream._settings.solve_for,
              30, "dZ with control")
    finally:
        service.close()


# ------------------------------------------------------------------- idle closes

@pytest.mark.parametrize("poses_ahead_s", [0.0, 3.0])
def test_input_pausing_mid_line_loses_no_point(tmp_path: Path, poses_ahead_s: float) -> None:
    """The input stops mid-line for longer than ``idle_close_s`` (a link drop, a starved
    player) and goes on; once the rest has come the saved mounting is ``lidarcal
    calibrate``'s (0.1 sigma), no point late. With the poses short of the newest points (as a
    recorder interleaves them) the idle close takes no end of the flight from the pause and
    closes nothing (it used to close the line there); with the poses 3 s ahead it takes the
    flight as ended and closes the line, and the close is taken back when the input comes
    again (every later point was late)."""
    m = _mission()
    t_all = np.concatenate([c[2] for c in _clouds(m)])
    on_first = t_all[m.line == 0]
    cut = float(on_first.min()) + 0.8 * float(np.ptp(on_first))  # (a line from 5 s on)
    events = _events(m)
    first = [e[0] < cut + (poses_ahead_s if e[1] == "pose" else 0.0) for e in events]
    service = _service(tmp_path, idle_close_s=0.3)
    try:
        _feed(service, [e for e, b in zip(events, first, strict=True) if b])
        _wait(lambda: service.queued_jobs == 0, 60, "the first part")
        time.sleep(1.0)  # (the idle close has come and gone)
        if poses_ahead_s:
            assert service.sensor.ended and service.stream.closed_strips != ()
        else:
            assert service.stream.closed_strips == (), service.stream.strip_ids
        _feed(service, [e for e, b in zip(events, first, strict=True) if not b])
        assert "solved" in service.solve()
        saved = service.save().split("written to ")[1].split(",")[0]
    finally:
        service.close()
    assert service.stream.late_points == 0 and service.sensor.late_points == 0
    assert len(service.sensor.lines) == 3
    _same_mounting(Path(saved), _offline(m, MOUNTING_SOLVE_FOR), 0.1)


# ------------------------------------------------------------------- checkpoints

def test_stopped_mid_flight_it_resumes_as_a_mounting_calibration(tmp_path: Path) -> None:
    """Stopped without closing in the turn after the second line (its checkpoint written
    at its last estimate), a new service resumes the mounting's calibration (mode, nominal,
    lines, points held), is fed the rest and saves the whole flight's mounting (0.1 sigma
    of ``lidarcal calibrate``'s)."""
    m = _mission()
    checkpoint = tmp_path / "ckpt.npz"
    t_all = np.concatenate([c[2] for c in _clouds(m)])
    line = m.line
    end_1, start_2 = float(t_all[line == 1].max()), float(t_all[line == 2].min())
    cut = (end_1 + start_2) / 2.0
    first = _service(tmp_path, checkpoint_file=str(checkpoint))
    _feed(first, _events(m, end=cut))
    # the first estimate (lines 0, 1) and its convergence, checkpointed
    _wait(lambda: first.queued_jobs == 0 and first.solves > 0 and first.stream.converged
          and first.checkpoints >= first.solves, 120, "a converged estimate")
    lines_before = first.sensor.lines.copy()
    nominal_before = first.sensor.mounting
    assert nominal_before is not None
    _stop_without_closing(first)
    assert len(lines_before) == 2

    second = _service(tmp_path, checkpoint_file=str(checkpoint))
    try:
        assert second.resumed_from == str(checkpoint) and second.sensor.active
        assert second.sensor.frame_id == "velodyne"
        np.testing.assert_array_equal(second.sensor.lines, lines_before)
        assert second.sensor.mounting is not None
        np.testing.assert_array_equal(second.sensor.mounting.rotation, nominal_before.rotation)
        np.testing.assert_array_equal(second.sensor.mounting.translation,
                                      nominal_before.translation)
        assert set(second.stream._settings.solve_for) == set(MOUNTING_SOLVE_FOR)
        _feed(second, _events(m, start=cut))
        assert "solved" in second.solve()
        saved = second.save().split("written to ")[1].split(",")[0]
    finally:
        second.close()
    assert len(second.sensor.lines) == 3
    _same_mounting(Path(saved), _offline(m, MOUNTING_SOLVE_FOR), 0.1)


# ------------------------------------------------------------------- memory

def test_a_long_line_holds_no_more_than_the_bound() -> None:
    """One long line (60 s): the feed hands its points on in blocks, holding at any moment
    only those of the last HELD_S seconds of the trajectory and the cloud ahead of it, and
    the strips it hands on are those the whole flight gives."""
    m = simulate_uav_payload(UavPayloadSpec(seed=5, columns=24, n_lines=2,
                                            line_length_m=480.0))
    clouds = _clouds(m)
    feed = SensorFrameFeed(base_frame="base_link", mounting=m.nominal)
    stream = StreamingCalibration(FlightConfig(), settings_of=lambda _c:
                                  sensor_calibration_settings())
    tr = m.trajectory
    assert tr.orientation is not None
    all_t = np.sort(np.concatenate([c[2] for c in clouds]))
    # the bound: the points of the last HELD_S s behind the newest pose, the cloud ahead of
    # it and those of one step's period (0.2 s): at most the most points in such a window
    window = HELD_S + 0.1 + 0.2
    bound = int(np.max(np.searchsorted(all_t, all_t + window) - np.arange(all_t.size)))
    most = 0
    for k, (stamp, xyz, t) in enumerate(clouds):
        new = (tr.t >= (clouds[k - 1][0] if k else -np.inf)) & (tr.t < stamp)
        feed.add_poses(tr.t[new], tr.xyz[new], tr.orientation[new], "map")
        feed.add_cloud(xyz, t, "velodyne")
        if k % 2 == 0:  # (the service's update period: 0.2 s)
            feed.step(stream)
        most = max(most, feed.pending_points)
    rest = tr.t >= clouds[-1][0]
    feed.add_poses(tr.t[rest], tr.xyz[rest], tr.orientation[rest], "map")
    feed.step(stream, final=True)
    stream.update(np.inf)
    total = all_t.size
    print(f"{total} points; held at most {most} (bound {bound}: {window:.1f} s)")
    assert most <= bound
    assert most < total / 4  # (not the whole line)
    assert feed.pending_points == 0 and len(feed.lines) == 2
    # blocks make the strips a whole line makes
    from lidarcal_ros.core.calibration.extrinsic import line_strips, sensor_trajectory

    whole = line_strips(np.concatenate([c[1] for c in clouds]),
                        np.concatenate([c[2] for c in clouds]),
                        sensor_trajectory(tr, m.nominal), m.nominal, feed.lines)
    held = {s.strip_id: s for s in stream.closed_strips}
    assert sorted(held) == [s.strip_id for s in whole]
    for s in whole:
        np.testing.assert_array_equal(held[s.strip_id].t, s.t)
        np.testing.assert_allclose(held[s.strip_id].xyz, s.xyz, atol=1e-9)


@pytest.mark.parametrize("case", ["estimated", "held", "not tried"])
def test_the_estimate_line_and_the_sensor_status_say_the_timing_bias(case: str) -> None:
    """The estimate's one-line status (logged by the calibrator, ``lidarcal: estimate``) and
    ``lidarcal: sensor frame`` end with dt in ms where it was estimated, 'dt held at 0' (the
    statement in the values) where asked for and held, nothing where not asked for."""
    statement = timing_statement("dS depends on the other biases nearly (multiple "
                                 "correlation 0.996, -0.99 with dY): only their combination "
                                 "is determined")
    cases: dict[str, dict[str, Any]] = {
        "estimated": {"time_offset_s": 0.0030142, "time_offset_sigma_s": 8.9e-5},
        "held": {"time_offset_note": statement}, "not tried": {}}
    timing = cases[case]
    nominal = Mounting(np.eye(3), np.array([0.1, 0.0, -0.05]))
    block = Extrinsic("base_link", "velodyne", nominal, nominal, **timing)
    said = {"estimated": "dt +3.01 +- 0.09 ms", "held": "dt held at 0", "not tried": ""}[case]
    assert timing_status_text(block) == said
    assert timing_status_text(None) == ""
    line = "dX +1.20 +- 0.10 cm, dphi -90.98 +- 0.04 arcsec"
    estimate = with_timing_bias(StatusSpec(OK, "lidarcal: estimate", line), block)
    sensor = with_timing_bias(StatusSpec(OK, "lidarcal: sensor frame", "3 lines closed",
                                         {"lines": "3"}), block)
    if case == "not tried":
        assert (estimate.message, estimate.values) == (line, {})
        assert (sensor.message, sensor.values) == ("3 lines closed", {"lines": "3"})
        return
    assert estimate.message == f"{line}, {said}"
    assert qa_summary([estimate]) == f"{line}, {said}"
    assert sensor.message == f"3 lines closed; {said}" and sensor.values["lines"] == "3"
    assert sensor.values["dt"] == estimate.values["dt"] == said
    if case == "estimated":
        assert float(estimate.values["time_offset_s"]) == 0.0030142
        assert float(estimate.values["time_offset_sigma_s"]) == 8.9e-5
        assert estimate.values["time_offset_not_estimable"] == ""
    else:
        assert float(estimate.values["time_offset_s"]) == 0.0
        assert estimate.values["time_offset_sigma_s"] == ""
        assert estimate.values["time_offset_not_estimable"] == statement


# ------------------------------------------------------------------- the timing bias

@functools.cache
def _steady_mission() -> UavPayloadMission:
    """The payload above flown without wobble, its clock 3 ms late: straight lines at one
    speed and a steady attitude, where dt moves each line along its track as dY does."""
    return simulate_uav_payload(UavPayloadSpec(seed=3, columns=48, n_lines=3,
                                               line_length_m=80.0, wobble_deg=0.0,
                                               time_offset_s=0.003))


@pytest.mark.parametrize("steady", [True, False])
def test_a_timing_bias_the_lines_cannot_see_is_held_live_as_offline(
        tmp_path: Path, steady: bool) -> None:
    """With ``sensor_frame.estimate_timing`` (its sigma limit wide, so that the multiple
    correlation decides): on a steady flight every estimate the service publishes, in flight
    and after, holds dt at 0 and says why once dt proved inseparable from the mounting (the
    calibration rebuilt without it, no blurred dt in the mounting), and the saved mounting is
    ``lidarcal calibrate``'s, which held dt too (0.1 sigma); with the multirotor's wobble dt
    is estimated live and offline alike. A reset forgets the hold."""
    m = _steady_mission() if steady else simulate_uav_payload(UavPayloadSpec(
        seed=3, columns=48, n_lines=3, line_length_m=80.0, time_offset_s=0.003))
    published: list[Any] = []
    config = FlightConfig.from_mapping({
        "sensor_frame.mounting": _mounting_text(m.nominal),
        "sensor_frame.estimate_timing": True,
        "sensor_frame.timing_max_sigma_s": 0.05,
        "calibration.calibration_file": str(tmp_path / "live.yaml")})
    service = CalibrationService(config, CalibratorOptions.from_parameters(
        {"idle_close_s": 0.0}), on_result=published.append)
    service.start()
    t_all = np.concatenate([c[2] for c in _clouds(m)])
    third = float(t_all[m.line == 2].min()) + 2.0  # (two lines flown, the third begun)
    try:
        _feed(service, _events(m, end=third))
        _wait(lambda: service.queued_jobs == 0 and bool(published), 120,
              "an estimate of two lines")
        assert not service.sensor.ended
        during = len(published)
        _feed(service, _events(m, start=third))
        _wait(lambda: service.queued_jobs == 0, 120, "the flight")
        assert "solved" in service.solve()
        saved = service.save().split("written to ")[1].split(",")[0]
        held = service._timing_held
        service.reset()
        _wait(lambda: service.queued_jobs == 0, 30, "the reset")
        assert service._timing_held == ""
        assert service._mounting_settings(config).timing  # (the next flight's stream's)
    finally:
        service.close()
    xyz = np.concatenate([c[1] for c in _clouds(m)])
    t = np.concatenate([c[2] for c in _clouds(m)])
    offline = calibrate_mounting(xyz, t, m.trajectory, m.nominal, settings=(
        sensor_calibration_settings(MOUNTING_SOLVE_FOR, config=config)))
    assert offline.timing_asked
    record = read_calibration(Path(saved))
    assert record.extrinsic is not None
    slot = PARAMETER_INDEX["dS"]
    assert 0 < during < len(published)
    if steady:
        assert "cannot be seen" in offline.time_offset_note and offline.time_offset_s == 0.0
        assert "multiple correlation" in held
        assert record.extrinsic.time_offset_s == 0.0
        assert record.extrinsic.time_offset_sigma_s is None
        assert "dt cannot be seen on this flight" in record.extrinsic.time_offset_note
        # (the mounting's calibration takes dt out of the result: the slot held, a warning)
        for result in published:
            assert result.solution.delta[slot] == 0.0 and "dS" not in result.solution.estimated
            assert any(w.startswith("the timing bias dt cannot be seen") and
                       "multiple correlation" in w for w in result.solution.warnings)
    else:
        assert offline.time_offset_note == "" and np.isfinite(offline.time_offset_sigma_s)
        assert held == ""
        assert record.extrinsic.time_offset_sigma_s is not None
        assert abs(record.extrinsic.time_offset_s - offline.time_offset_s) <= \
            0.1 * offline.time_offset_sigma_s
        assert not any("dt cannot be seen" in w for r in published for w in r.solution.warnings)
    _same_mounting(Path(saved), offline, 0.1)


def test_the_flight_is_calibrated_once_after_its_end(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """After the flight's end every estimate published (the refinement's, ``~/solve``'s,
    ``~/save``'s) carries the mounting ``lidarcal calibrate`` gives of the points held: made
    once for the same strips and settings, again when the settings change."""
    from lidarcal_ros.pipeline.calibration import service as service_module

    made: list[int] = []
    real = service_module.calibrate_mounting

    def counted(*args: Any, **kwargs: Any) -> MountingCalibration:
        made.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(service_module, "calibrate_mounting", counted)
    m = _mission()
    service = _service(tmp_path)
    try:
        _feed(service, _events(m))
        assert "solved" in service.solve()
        first = service.mounting
        assert "solved" in service.solve()
        service.save()
        assert len(made) == 1 and service.mounting is first
        service.set_config(service.config.with_values(sensor_frame__lever_arm_sigma_m=0.02),
                           {"sensor_frame.lever_arm_sigma_m"})
        assert "solved" in service.solve()
    finally:
        service.close()
    assert len(made) == 2 and service.mounting is not first
    assert service.mounting is not None and first is not None
    dx = PARAMETER_INDEX["dX"]
    assert service.mounting.sigma[dx] < first.sigma[dx]  # (the held dZ known better)
