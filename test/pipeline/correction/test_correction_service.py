"""The correction behind the corrector node: a child process and the in-thread engine give
the same bytes, report every cloud once and in order, skip malformed clouds with a reason,
and report the clouds a dead child held instead of losing them silently."""

from __future__ import annotations

import dataclasses
import itertools
import threading
import time
from pathlib import Path
from typing import Any

import helpers_missions
import numpy as np
import pytest
from helpers_missions import MissionFiles

from lidarcal_ros.core.config import FlightConfig
from lidarcal_ros.core.params import PARAMETER_NAMES
from lidarcal_ros.io.bag.mission_bag import strip_point_array
from lidarcal_ros.io.cloud.messages import cloud_cdr, parse_cloud
from lidarcal_ros.io.cloud.shared_ring import SharedRing
from lidarcal_ros.pipeline.correction import batch as correction_batch
from lidarcal_ros.pipeline.correction.apply import CorrectionSettings
from lidarcal_ros.pipeline.correction.process import CorrectionProcess
from lidarcal_ros.pipeline.correction.service import LocalCorrection, ServiceOptions
from lidarcal_ros.pipeline.correction.stream import StreamCorrector

mission_factory = helpers_missions.mission_factory
small_mission = helpers_missions.small_mission


class Collector:
    """Results and errors as the service reports them (from any thread)."""

    def __init__(self) -> None:
        self.events: list[tuple[str, Any, Any]] = []
        self.lock = threading.Lock()

    def result(self, tag: Any, cdr: bytes | memoryview, n: int, bad: int, _seconds: float
               ) -> None:
        with self.lock:  # (a view of the outbound ring is valid during the call only)
            self.events.append(("out", tag, bytes(cdr)))

    def error(self, tag: Any, reason: str) -> None:
        with self.lock:
            self.events.append(("error", tag, reason))

    def wait(self, count: int, timeout: float = 30.0) -> None:
        deadline = time.monotonic() + timeout
        while len(self.events) < count and time.monotonic() < deadline:
            time.sleep(0.01)


def _stream(small_mission: MissionFiles) -> tuple[CorrectionSettings, Any, list[bytes]]:
    sim = small_mission.sim
    settings = CorrectionSettings.from_config(
        FlightConfig(), np.array([sim.biases[n] for n in PARAMETER_NAMES]))
    pts = strip_point_array(sim.mission.strips[0], {}, "test")
    cuts = [*range(0, len(pts), 3000), len(pts)]
    clouds = [cloud_cdr(1_000_000_000 + k, "map", pts[a:b])
              for k, (a, b) in enumerate(itertools.pairwise(cuts))]
    return settings, sim.mission.trajectory, clouds


@pytest.mark.parametrize("lookahead", [True, False])
def test_child_process_gives_the_bytes_of_the_stream_corrector(
        small_mission: MissionFiles, lookahead: bool) -> None:
    settings, trajectory, clouds = _stream(small_mission)
    options = ServiceOptions(lookahead=lookahead)
    # The reference: the stream corrector on the same clouds, serialised the same way (three
    # clouds a request, as under a backlog: without look-ahead a cloud's points then also
    # have the other two as neighbours).
    ref = StreamCorrector(trajectory, settings, batch_points=0, lookahead=lookahead)
    expected: dict[int, bytes] = {}
    for k in range(0, len(clouds), 3):
        group = [(parse_cloud(clouds[j]).points, j) for j in range(k, min(k + 3, len(clouds)))]
        for tag, arr in ref.push_many(group):
            expected[tag] = cloud_cdr(1_000_000_000 + tag, "map", arr)
    for tag, arr in ref.flush():
        expected[tag] = cloud_cdr(1_000_000_000 + tag, "map", arr)

    got = Collector()
    local = LocalCorrection(settings, options, on_result=got.result, on_error=got.error)
    assert _feed(local, got, trajectory, clouds) == expected
    assert _run_process(settings, options, trajectory, clouds) == expected


def test_the_imu_heading_reaches_the_correction_process(
        mission_factory: Any) -> None:
    """A crabbed mission whose poses carry the IMU's heading: the child process, given the
    samples with their headings, gives the bytes of the stream corrector on that trajectory,
    which are not those of the positions alone."""
    crabbed = mission_factory(wind_mps=(4.0, 0.0), attitude=True)
    settings, trajectory, clouds = _stream(crabbed)
    assert trajectory.heading is not None
    options = ServiceOptions(lookahead=False)

    def reference(traj: Any) -> dict[int, bytes]:
        ref = StreamCorrector(traj, settings, batch_points=0, lookahead=False)
        out: dict[int, bytes] = {}
        for k in range(0, len(clouds), 3):
            group = [(parse_cloud(clouds[j]).points, j)
                     for j in range(k, min(k + 3, len(clouds)))]
            out.update((tag, cloud_cdr(1_000_000_000 + tag, "map", arr))
                       for tag, arr in ref.push_many(group))
        out.update((tag, cloud_cdr(1_000_000_000 + tag, "map", arr)) for tag, arr in ref.flush())
        return out

    expected = reference(trajectory)
    assert _run_process(settings, options, trajectory, clouds) == expected
    positions_only = reference(dataclasses.replace(trajectory, orientation=None))
    assert all(positions_only[k] != expected[k] for k in expected)


def _feed(service: Any, got: Collector, trajectory: Any, clouds: list[bytes]
          ) -> dict[int, bytes]:
    """The trajectory, then the clouds three a request, then close: each cloud must come
    out once, in order; what came out, by tag."""
    service.poses(trajectory.t, trajectory.xyz, trajectory.orientation)
    for k in range(0, len(clouds), 3):
        service.push([(j, clouds[j]) for j in range(k, min(k + 3, len(clouds)))])
    service.close()
    assert [e[0] for e in got.events] == ["out"] * len(clouds)
    assert [e[1] for e in got.events] == list(range(len(clouds)))  # once, in order
    return {e[1]: e[2] for e in got.events}


def _run_process(settings: CorrectionSettings, options: ServiceOptions, trajectory: Any,
                 clouds: list[bytes], *, shared_memory: bool = True,
                 carried: dict[str, int] | None = None) -> dict[int, bytes]:
    """The clouds through a CorrectionProcess, three a request: what came out, by tag (and
    in ``carried``, how many went which way)."""
    got = Collector()
    service = CorrectionProcess(settings, options, on_result=got.result, on_error=got.error)
    deadline = time.monotonic() + 60
    while shared_memory and not service.shared_memory and time.monotonic() < deadline:
        time.sleep(0.01)  # the rings are used once the child has mapped them
    assert service.shared_memory == shared_memory
    out = _feed(service, got, trajectory, clouds)
    for path in service.ring_paths:
        assert not Path(path).exists()  # no file left behind
    if carried is not None:
        carried.update(service.carried)
    return out


@pytest.mark.parametrize("transport", ["small rings", "pipes", "no rings wanted"])
def test_clouds_that_find_no_room_in_shared_memory_go_through_the_pipe(
        small_mission: MissionFiles, monkeypatch: pytest.MonkeyPatch,
        caplog: pytest.LogCaptureFixture, transport: str) -> None:
    """With rings of about two clouds (look-ahead holds several), clouds go by ring and by
    pipe, in and out, and come out the same; with no shared memory to be had, or none
    wanted (``ring_bytes`` 0), by pipe."""
    settings, trajectory, clouds = _stream(small_mission)
    options = ServiceOptions(lookahead=True)
    carried: dict[str, int] = {}
    expected = _run_process(settings, options, trajectory, clouds, carried=carried)
    assert carried["ring in"] == carried["ring out"] == len(clouds)  # all by the rings
    if transport == "small rings":
        options = dataclasses.replace(options, ring_bytes=2 * max(map(len, clouds)) + 64)
    elif transport == "no rings wanted":
        options = dataclasses.replace(options, ring_bytes=0)
    else:
        def refuse(size: int, **_kw: Any) -> SharedRing:
            raise OSError(28, "No space left on device")

        monkeypatch.setattr(SharedRing, "create", refuse)
    got = _run_process(settings, options, trajectory, clouds,
                       shared_memory=transport == "small rings", carried=carried)
    assert got == expected
    if transport != "small rings":
        assert carried["ring in"] == carried["ring out"] == 0
    if transport == "pipes":
        assert "through pipes" in caplog.text and "No space" in caplog.text
    elif transport == "small rings":
        assert carried["ring in"] > 0 and carried["pipe in"] > 0, carried
        assert carried["ring out"] > 0, carried


@pytest.mark.parametrize("lookahead", [True, False])
def test_malformed_cloud_is_reported_and_the_rest_corrected(
        small_mission: MissionFiles, lookahead: bool) -> None:
    settings, trajectory, clouds = _stream(small_mission)
    got = Collector()
    service = CorrectionProcess(settings, ServiceOptions(lookahead=lookahead),
                                on_result=got.result, on_error=got.error)
    service.poses(trajectory.t, trajectory.xyz)
    no_time = np.zeros(10, dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8")])
    service.push([(0, clouds[0]), (1, b"\x00\x01garbage"), (2, cloud_cdr(0, "map", no_time)),
                  (3, clouds[1])])
    service.close()
    kinds = {e[1]: e for e in got.events}
    assert sorted(kinds) == [0, 1, 2, 3]
    assert kinds[0][0] == kinds[3][0] == "out"
    assert kinds[1][0] == "error" and "\n" not in kinds[1][2]
    assert kinds[2][0] == "error" and "time" in kinds[2][2]


@pytest.mark.parametrize("workers", [1, 2])
def test_a_batch_that_raises_reports_its_own_clouds_and_the_stream_goes_on(
        small_mission: MissionFiles, monkeypatch: pytest.MonkeyPatch, workers: int) -> None:
    """A bug in the correction of one batch (in a worker thread or not) is reported for the
    clouds of that batch, not for those of whatever request is being handled when it
    surfaces; the other clouds come out corrected, each once."""
    settings, trajectory, clouds = _stream(small_mission)
    real_run_batch = correction_batch.run_batch
    failing: list[Any] = []

    def run_batch(job: Any, source: str) -> Any:
        tags = [m.tag for m in job.messages]
        if 6 in tags:
            failing.extend(tags)
            raise RuntimeError("injected")
        return real_run_batch(job, source)

    monkeypatch.setattr(correction_batch, "run_batch", run_batch)
    got = Collector()
    service = LocalCorrection(settings, ServiceOptions(workers=workers, lookahead=False,
                                                       batch_points=0),
                              on_result=got.result, on_error=got.error)
    service.poses(trajectory.t, trajectory.xyz)
    for k, cloud in enumerate(clouds[:8]):
        service.push([(k, cloud)])
        service.poll()
    service.close()
    assert sorted(e[1] for e in got.events) == list(range(8))  # each cloud once
    errors = {e[1]: e[2] for e in got.events if e[0] == "error"}
    assert sorted(errors) == sorted(failing) and 0 < len(failing) < 6
    assert set(errors.values()) == {"internal error: RuntimeError: injected"}
    assert all(parse_cloud(e[2]).points.size for e in got.events if e[0] == "out")


def test_a_dead_child_reports_the_clouds_it_held(small_mission: MissionFiles) -> None:
    settings, trajectory, clouds = _stream(small_mission)
    got = Collector()
    failures: list[str] = []
    service = CorrectionProcess(settings, ServiceOptions(lookahead=True),
                                on_result=got.result, on_error=got.error,
                                on_failure=failures.append)
    service.poses(trajectory.t, trajectory.xyz)
    service.push([(k, clouds[k]) for k in range(4)])  # held for look-ahead
    time.sleep(0.5)
    service.kill()
    got.wait(4)
    assert not service.alive
    assert sorted(e[1] for e in got.events) == [0, 1, 2, 3]
    lost = [e for e in got.events if e[0] == "error"]
    assert lost and all("ended" in e[2] for e in lost)
    assert failures and "ended" in failures[0]
    for path in service.ring_paths:
        assert not Path(path).exists()
    service.close(timeout=1.0)


@pytest.mark.parametrize("kind", [LocalCorrection, CorrectionProcess])
def test_look_ahead_switched_off_at_run_time_releases_what_waits(
        small_mission: MissionFiles, kind: Any) -> None:
    settings, trajectory, clouds = _stream(small_mission)
    got = Collector()
    service = kind(settings, ServiceOptions(lookahead=True), on_result=got.result,
                   on_error=got.error)
    service.poses(trajectory.t, trajectory.xyz)
    service.set_trajectory_keep(60.0)
    service.push([(k, clouds[k]) for k in range(6)])
    time.sleep(1.0)
    waiting = 6 - len(got.events)
    assert waiting >= 1  # the last clouds wait for the rows after them
    service.set_lookahead(False)
    service.push([(6, clouds[6])])
    got.wait(7, timeout=10.0)
    assert [e[1] for e in got.events] == list(range(7))  # all out, in order, before the end
    service.close()


def test_clouds_received_into_the_inbound_ring_are_corrected_in_place(
        small_mission: MissionFiles) -> None:
    """Clouds written into regions of the inbound ring (as the node's subscription takes
    them, :meth:`CorrectionProcess.inbound_region`) come out as the same clouds pushed as
    bytes, with no copy in (the regions are those handed out, and all are free again at the
    end); a region of another process's ring is copied from."""
    settings, trajectory, clouds = _stream(small_mission)
    options = ServiceOptions(lookahead=True)
    expected = _run_process(settings, options, trajectory, clouds)
    got = Collector()
    service = CorrectionProcess(settings, options, on_result=got.result, on_error=got.error)
    other = CorrectionProcess(settings, options, on_result=Collector().result,
                              on_error=Collector().error)
    deadline = time.monotonic() + 60
    while not (service.shared_memory and other.shared_memory) and time.monotonic() < deadline:
        time.sleep(0.01)
    writes: list[int] = []
    assert service._inbound is not None
    original_write = service._inbound.write

    def counted_write(offset: int, parts: list[Any]) -> int:
        writes.append(offset)
        return original_write(offset, parts)

    service._inbound.write = counted_write  # type: ignore[method-assign]
    service.poses(trajectory.t, trajectory.xyz, trajectory.orientation)
    foreign = other.inbound_region(len(clouds[0]))
    assert foreign is not None
    foreign.view[:] = clouds[0]
    pushed: list[tuple[int, Any]] = [(0, foreign)]
    for tag, raw in enumerate(clouds[1:], start=1):
        region = service.inbound_region(len(raw))
        assert region is not None and region.ring is service._inbound
        region.view[:] = raw
        pushed.append((tag, region))
    service.push(pushed)
    service.close()
    other.close()
    assert {e[1]: e[2] for e in got.events} == expected
    assert len(writes) == 1  # the foreign region only: the others were read where they lay
    assert service.carried["ring in"] == len(clouds)
    assert service.carried["in place"] == len(clouds) - 1
    assert service._inbound.regions_in_use == 0
