"""The live corrector's work without ROS (lidarcal_ros.pipeline.correction.live and
cloud_backlog): clouds wait for the trajectory and go on in order, a stalled trajectory is
given up on, a backlog above its bound loses its oldest clouds, and a trajectory without
clouds is handed on rather than hoarded."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import helpers_missions
import numpy as np
import yaml
from helpers_missions import MissionFiles, write_calibration_yaml
from helpers_wait import wait_until as _wait

from lidarcal_ros.core.config import CORRECTOR_NODE, FlightConfig, node_options
from lidarcal_ros.core.flags import FLAG_NOT_CORRECTED
from lidarcal_ros.core.params import PARAMETER_NAMES
from lidarcal_ros.io.bag.reader import open_bag
from lidarcal_ros.io.cloud.messages import parse_cloud
from lidarcal_ros.pipeline.correction import live as live_corrector
from lidarcal_ros.pipeline.correction.backlog import (
    MAX_PUSH_POINTS,
    TRAJECTORY_MARGIN_S,
    WaitingCloud,
    WaitingClouds,
    take_ready,
)
from lidarcal_ros.pipeline.correction.live import CorrectorOptions, LiveCorrector
from lidarcal_ros.pipeline.correction.service import LocalCorrection

mission_factory = helpers_missions.mission_factory
small_mission = helpers_missions.small_mission


def _cloud(t_max: float, *, received: float = 0.0, points: int = 100, size: int = 1000
           ) -> WaitingCloud:
    return WaitingCloud(b"x" * size, received, size, parsed=True, n_points=points,
                        t_max=t_max)


def _never_parsed(_cloud: WaitingCloud) -> bool:
    raise AssertionError("parsed twice")


# ---------------------------------------------------------------------------- scheduling
def test_clouds_covered_by_the_trajectory_go_on_in_order_and_the_first_uncovered_holds_the_rest(
        ) -> None:
    clouds = [_cloud(1.0), _cloud(2.0), _cloud(3.0), _cloud(2.5)]
    # the trajectory ends at 2.5 s: clouds up to 2.48 s are covered (margin)
    ready, done = take_ready(clouds, 2.0 + TRAJECTORY_MARGIN_S, waited_since=0.0, now=1.0,
                             wait_s=5.0, parse=_never_parsed)
    assert ready == clouds[:2] and done == 2
    # cloud 3 (3.0 s) is not covered: cloud 4 (2.5 s), although covered, waits behind it
    ready, done = take_ready(clouds[2:], 2.9, waited_since=0.0, now=1.0, wait_s=5.0,
                             parse=_never_parsed)
    assert ready == [] and done == 0
    ready, done = take_ready(clouds[2:], 3.0 + TRAJECTORY_MARGIN_S, waited_since=0.0,
                             now=1.0, wait_s=5.0, parse=_never_parsed)
    assert ready == clouds[2:] and done == 2


def test_a_stalled_trajectory_is_given_up_on_but_not_one_that_still_arrives() -> None:
    cloud = _cloud(10.0, received=100.0)
    # waited 4 s of 5 since the cloud came: still waiting
    assert take_ready([cloud], 1.0, 50.0, 104.0, 5.0, _never_parsed) == ([], 0)
    # 5 s: given up, the cloud goes on uncovered
    assert take_ready([cloud], 1.0, 50.0, 105.0, 5.0, _never_parsed) == ([cloud], 1)
    # a sample arrived 1 s ago (late, behind a backlog): the wait starts again from it
    assert take_ready([cloud], 1.0, 104.0, 105.0, 5.0, _never_parsed) == ([], 0)


def test_malformed_clouds_are_done_with_and_not_handed_on() -> None:
    good, bad = WaitingCloud(b"good", 0.0, 4), WaitingCloud(b"bad", 0.0, 3)

    def parse(cloud: WaitingCloud) -> bool:
        if cloud is bad:
            return False
        cloud.parsed, cloud.n_points, cloud.t_max = True, 10, 1.0
        return True

    ready, done = take_ready([bad, good], 5.0, 0.0, 0.0, 5.0, parse)
    assert ready == [good] and done == 2 and good.parsed and not bad.parsed


def test_a_backlog_goes_on_in_pushes_of_bounded_size() -> None:
    per_cloud = MAX_PUSH_POINTS // 4
    clouds = [_cloud(float(k), points=per_cloud) for k in range(10)]
    ready, done = take_ready(clouds, 100.0, 0.0, 0.0, 5.0, _never_parsed)
    assert ready == clouds[:4] and done == 4


def test_the_oldest_waiting_clouds_are_dropped_above_the_bound_and_the_newest_kept() -> None:
    waiting = WaitingClouds()
    clouds = [_cloud(float(k), size=400) for k in range(10)]
    for c in clouds:
        waiting.append(c)
    assert waiting.bytes == 4000 and waiting.drop_oldest(0) == (0, 0)  # no limit
    assert waiting.drop_oldest(4000) == (0, 0)
    assert waiting.drop_oldest(1000) == (8, 3200)
    assert list(waiting) == clouds[8:] and waiting.bytes == 800
    assert waiting.drop_oldest(1) == (1, 400)  # the newest stays, whatever its size
    assert list(waiting) == clouds[9:]
    waiting.pop_oldest(1)
    assert len(waiting) == 0 and waiting.bytes == 0


class _Region:
    """A stand-in for the shared memory a cloud was received into: counts its release."""

    def __init__(self) -> None:
        self.released = 0

    def release(self) -> None:
        self.released += 1


def test_a_dropped_cloud_gives_back_its_shared_memory_and_a_handed_on_one_does_not() -> None:
    waiting = WaitingClouds()
    regions = [_Region() for _ in range(3)]
    clouds = [_cloud(float(k), size=400) for k in range(3)]
    for cloud, region in zip(clouds, regions, strict=True):
        cloud.region = region
        waiting.append(cloud)
    assert waiting.drop_oldest(400) == (2, 800)
    assert [r.released for r in regions] == [1, 1, 0]
    assert clouds[0].region is None and clouds[0].raw == b""
    waiting.pop_oldest(1)  # handed on: the correction owns its memory now
    assert regions[2].released == 0


def test_a_malformed_cloud_received_in_shared_memory_gives_it_back() -> None:
    live = LiveCorrector(FlightConfig(), _options(), publish=lambda _cdr: None)
    try:
        region = _Region()
        live.add_cloud(memoryview(bytearray(b"\x00\x01garbage")), region)
        _wait(lambda: live.stats.skipped == 1, 10, "the malformed cloud to be skipped")
        assert region.released == 1 and live.waiting_clouds == 0
    finally:
        live.close()


def test_without_a_correction_process_clouds_are_received_into_buffers_of_their_own() -> None:
    live = LiveCorrector(FlightConfig(), _options(), publish=lambda _cdr: None)
    try:
        view, region = live.receive_buffer(1000)
        assert region is None and len(view) == 1000 and not view.readonly
    finally:
        live.close()


# ---------------------------------------------------------------------------- the corrector
def _options(**changes: Any) -> CorrectorOptions:
    return dataclasses.replace(node_options(CorrectorOptions, CORRECTOR_NODE, {}),
                               separate_process=False, **changes)


def _clouds(mission: MissionFiles) -> list[bytes]:
    with open_bag(mission.bag) as b:
        return [raw for _t, _m, _ns, raw in b.messages(["/lidar/points"])]


def _corrector(clouds: list[bytes], **options: Any) -> tuple[LiveCorrector, list[bytes]]:
    """A live corrector in this process, given ``clouds``; and what it publishes."""
    published: list[bytes] = []
    live = LiveCorrector(FlightConfig(), _options(**options),
                         publish=lambda cdr: published.append(bytes(cdr)))
    for raw in clouds:
        live.add_cloud(raw)
    return live, published


def _add_trajectory(live: LiveCorrector, mission: MissionFiles, frame: str) -> None:
    """The mission's trajectory, sample by sample as a node's callback gives it."""
    trajectory = mission.sim.mission.trajectory
    for t, xyz in zip(trajectory.t, trajectory.xyz, strict=True):
        live.add_pose(float(t), (float(xyz[0]), float(xyz[1]), float(xyz[2])), frame,
                      (math.nan,) * 4)


def test_clouds_wait_for_the_trajectory_and_come_out_in_order_when_it_covers_them(
        small_mission: MissionFiles) -> None:
    clouds = _clouds(small_mission)[:6]
    live, published = _corrector(clouds, max_trajectory_wait_s=600.0)
    try:
        assert live.waiting_clouds == len(clouds)
        assert live.held_clouds == 0 and not published
        _add_trajectory(live, small_mission, parse_cloud(clouds[0]).frame_id)
        _wait(lambda: len(published) == len(clouds), 30, "the clouds to be corrected")
    finally:
        live.close()
    assert [parse_cloud(r).stamp_ns for r in published] == \
        [parse_cloud(r).stamp_ns for r in clouds]
    for raw in published:
        flags = parse_cloud(raw).points["correction_flags"]
        assert not (flags & FLAG_NOT_CORRECTED).any()  # the trajectory covered them
    assert live.stats.clouds_out == live.stats.clouds_in == len(clouds)
    assert live.status().values["transport"] == "thread"
    # The incidence rule the reflectance ran (canopy returns: none).
    assert "none (cos 1) for volume returns" in live.status().values["incidence"]


def test_clouds_go_on_uncovered_once_the_trajectory_has_stalled(
        small_mission: MissionFiles) -> None:
    clouds = _clouds(small_mission)[:3]
    live, published = _corrector(clouds, max_trajectory_wait_s=0.0)
    try:
        _wait(lambda: len(published) == len(clouds), 30, "the clouds to be given up on")
    finally:
        live.close()
    for raw in published:
        assert (parse_cloud(raw).points["correction_flags"] & FLAG_NOT_CORRECTED).all()
    status = live.status()
    assert status.level == 1 and "not covered by the trajectory" in status.message


def test_a_backlog_above_its_bound_drops_the_oldest_clouds_and_says_so(
        small_mission: MissionFiles) -> None:
    """Clouds that cannot be corrected yet (here: no trajectory) wait, but not without
    bound: above ``max_backlog_mib`` the oldest are dropped and counted, the diagnostics
    warn, and the newest are corrected once the trajectory comes."""
    clouds = _clouds(small_mission)
    sent, total = [], 0
    for raw in clouds:
        sent.append(raw)
        total += len(raw)
        if total > 3 << 20:
            break
    assert total > 3 << 20, "the mission is too small for this test"
    live, published = _corrector(sent, max_backlog_mib=1, max_trajectory_wait_s=600.0)
    try:
        _wait(lambda: live.stats.dropped > 0 and (live.waiting_bytes <= 1 << 20
                                                  or live.waiting_clouds == 1),
              10, "the backlog to be trimmed")
        kept = live.waiting_clouds
        assert live.stats.dropped == len(sent) - kept > 0
        assert live.stats.dropped_bytes == sum(len(r) for r in sent[:live.stats.dropped])
        status = live.status()
        assert status.level == 1 and "dropped" in status.message
        assert status.values["dropped_clouds"] == str(live.stats.dropped)
        _add_trajectory(live, small_mission, parse_cloud(sent[0]).frame_id)  # at last
        _wait(lambda: len(published) == kept, 30, "the kept clouds to be corrected")
    finally:
        live.close()
    newest = [parse_cloud(raw).stamp_ns for raw in sent[len(sent) - kept:]]
    assert [parse_cloud(raw).stamp_ns for raw in published] == newest


def test_a_trajectory_without_clouds_is_handed_on_not_hoarded() -> None:
    """Poses that come for long without clouds (transit to the site) go on to the
    correction in batches; the corrector does not keep them all, nor does its own buffer."""
    live = LiveCorrector(FlightConfig(), _options(trajectory_buffer_s=30.0),
                         publish=lambda _cdr: None)
    fed = 60_000  # 5 minutes at 200 Hz
    try:
        for k in range(fed):
            t = 1000.0 + k * 0.005
            live.add_pose(t, (0.0, 60.0 * t, 1000.0), "map", (math.nan,) * 4)
        runner = live.runner
        assert isinstance(runner, LocalCorrection)
        engine = runner.engine
        # The worker takes the poses under its lock, then adds them to the engine outside
        # it: wait for the hand-over to be complete, not merely begun. (Reading the engine's
        # count first can only undercount in that window, never reach ``fed``.)
        _wait(lambda: engine.trajectory.samples + live.poses_waiting == fed
              and live.poses_waiting <= live_corrector.POSES_PER_HANDOVER, 10,
              "the poses to be handed on")
        assert engine.trajectory.samples >= fed - live_corrector.POSES_PER_HANDOVER
        assert len(live.trajectory) < fed / 2  # its own buffer keeps ~30 s, not everything
    finally:
        live.close()


def test_a_calibration_file_with_trajectory_errors_is_applied_live(
        small_mission: MissionFiles, tmp_path: Path) -> None:
    """The corrector given a calibration file whose strips carry trajectory errors (an offset
    and a drift each, docs/method.md section 11) removes ``e_s(t)`` from every point by its
    strip: its clouds equal those corrected with the biases alone, less the errors (to the
    micrometres the delivered laser vectors leave); a new estimate from the topic (biases
    only) applies the biases alone."""
    from lidarcal_ros.core.trajectory.strip_errors import (
        StripError,
        TrajectoryEstimate,
        TrajectoryModel,
    )
    from lidarcal_ros.io.calibration_file import trajectory_document

    clouds = _clouds(small_mission)[:4]
    frame = parse_cloud(clouds[0]).frame_id
    points = [parse_cloud(raw).points for raw in clouds]
    strips = {int(sid) for p in points for sid in np.unique(p["strip_id"])}
    estimate = TrajectoryEstimate(TrajectoryModel.DRIFT, {
        sid: StripError.linear(sid, float(points[0]["t"][0]), np.array([0.03, -0.02, 0.05]),
                               np.full(3, 0.01), np.array([0.001, 0.0, -0.002]),
                               np.full(3, 0.001)) for sid in strips})
    zero = {name: 0.0 for name in PARAMETER_NAMES}
    path = write_calibration_yaml(tmp_path / "cal.yaml", zero)
    doc = yaml.safe_load(path.read_text())
    doc["lidarcal_calibration"]["trajectory"] = trajectory_document(estimate)
    path.write_text(yaml.safe_dump(doc))

    def corrected(calibration: str, moved: bool) -> list[np.ndarray]:
        published: list[bytes] = []
        live = LiveCorrector(FlightConfig(), _options(max_trajectory_wait_s=600.0),
                             publish=lambda cdr: published.append(bytes(cdr)),
                             calibration=calibration)
        try:
            assert (live.settings.trajectory_errors is not None) == moved
            for raw in clouds:
                live.add_cloud(raw)
            _add_trajectory(live, small_mission, frame)
            _wait(lambda: len(published) == len(clouds), 30, "the clouds to be corrected")
            if moved:
                live.set_estimate(np.zeros(8), "topic")
                assert live.settings.trajectory_errors is None
        finally:
            live.close()
        return [parse_cloud(raw).points for raw in published]

    plain = write_calibration_yaml(tmp_path / "plain.yaml", zero)
    for with_errors, without, delivered in zip(corrected(str(path), True),
                                               corrected(str(plain), False),
                                               points, strict=True):
        xyz = np.column_stack([with_errors[c] for c in "xyz"])
        ref = np.column_stack([without[c] for c in "xyz"])
        want = estimate.errors(delivered["strip_id"], delivered["t"])
        np.testing.assert_allclose(ref - xyz, want, atol=1e-4)
