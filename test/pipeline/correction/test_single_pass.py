"""``lidarcal correct`` in one pass over a bag (the trajectory gathered as it comes,
:mod:`lidarcal_ros.pipeline.correction.trajectory_gate`) writes the very bytes of two passes (the
trajectory read first: ``max_held_points=0``), read back with the mcap project's reader and
laspy: a level mission, a rough-air mission (rigorous model), one with a trajectory gap,
points not covered at either end and non-finite poses; and bags whose trajectory does not
come in step with the clouds (written after them, or some poses late), which are read again.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import helpers_missions
import laspy
import numpy as np
import pytest
from helpers_missions import (
    MissionFiles,
    cloud_chunks,
    strip_points,
    strip_span,
    without_trajectory,
    write_calibration_yaml,
    write_cloud_bag,
)

from lidarcal_ros.core.config import FlightConfig
from lidarcal_ros.core.georeferencing.laser_geometry import PositioningModel
from lidarcal_ros.core.mission import Mission, Trajectory
from lidarcal_ros.errors import LidarcalError
from lidarcal_ros.pipeline.correction import trajectory_gate
from lidarcal_ros.pipeline.correction.apply import UNCORRECTED_WARNINGS
from lidarcal_ros.pipeline.correction.bag import (
    CorrectionReport,
    CorrectOptions,
    correct_bag,
)

mission_factory = helpers_missions.mission_factory
small_mission = helpers_missions.small_mission

#: Small batches, so that a small mission's clouds leave the gate while the bag is read.
BATCH = 20_000
REREAD = "reading the bag again"
_HOURS: list[int] = []


@dataclasses.dataclass
class Run:
    """One correction: its report, output, stages of progress, the clouds the gate still
    held at the end of the bag, and whether the bag was read again."""

    report: CorrectionReport
    output: Path
    stages: set[str]
    held_at_end: int
    reread: bool


def _correct(bag: Path, cal: Path, out: Path, caplog: pytest.LogCaptureFixture, *,
             config: FlightConfig | None = None, **options: Any) -> Run:
    stages: set[str] = set()
    held: list[int] = []
    finish = trajectory_gate.TrajectoryGate.finish

    def spy(gate: trajectory_gate.TrajectoryGate) -> list[Any]:
        out_ = finish(gate)
        held.append(len(out_))
        return out_

    caplog.clear()
    with pytest.MonkeyPatch.context() as mp, caplog.at_level(logging.INFO):
        mp.setattr(trajectory_gate.TrajectoryGate, "finish", spy)
        # (the warnings of clouds left uncorrected are throttled by wall time: each run
        # starts an hour after the last)
        _HOURS.append(len(_HOURS))
        mp.setattr(UNCORRECTED_WARNINGS, "clock",
                   lambda: time.monotonic() + 3600.0 * len(_HOURS))
        report = correct_bag(bag, cal, out, config,
                             CorrectOptions(batch_points=BATCH, **options),
                             progress=lambda stage, _f: stages.add(stage))
    reread = any(REREAD in r.getMessage() for r in caplog.records)
    return Run(report, out, stages, sum(held), reread)


def _mcap_messages(path: Path) -> list[tuple[str, int, int, bytes]]:
    """Every message (topic, log time, publish time, bytes) with the mcap project's
    reader, in the file's order."""
    from mcap.reader import make_reader

    with path.open("rb") as f:
        return [(channel.topic, m.log_time, m.publish_time, bytes(m.data))
                for _schema, channel, m in make_reader(f).iter_messages(log_time_order=False)]


def _assert_same_output(a: Run, b: Run) -> None:
    """Byte for byte the same file, and the same content read independently."""
    assert a.output.name == b.output.name  # (a bag holds its name)
    if a.output.suffix == ".mcap":
        ma, mb = _mcap_messages(a.output), _mcap_messages(b.output)
        assert len(ma) == len(mb) > 0
        assert ma == mb
    else:
        la, lb = laspy.read(a.output), laspy.read(b.output)
        assert la.header.point_count == lb.header.point_count > 0
        assert la.points.array.tobytes() == lb.points.array.tobytes()
    assert a.output.read_bytes() == b.output.read_bytes()
    assert a.report.lines()[1:] == b.report.lines()[1:]  # (the first one says the time)
    assert a.report.warnings == b.report.warnings
    assert a.report.frame_id == b.report.frame_id


def _one_and_two_passes(bag: Path, cal: Path, work: Path, caplog: pytest.LogCaptureFixture,
                        suffix: str, **kwargs: Any) -> tuple[Run, Run]:
    (work / "one").mkdir(exist_ok=True)
    (work / "two").mkdir(exist_ok=True)
    one = _correct(bag, cal, work / "one" / f"out{suffix}", caplog, **kwargs)
    one_warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    two = _correct(bag, cal, work / "two" / f"out{suffix}", caplog,
                   **{**kwargs, "max_held_points": 0})
    two_warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert "reading trajectory" in two.stages and not two.reread
    assert [w.replace("/one/", "/") for w in one_warnings] == [
        w.replace("/two/", "/") for w in two_warnings]
    _assert_same_output(one, two)
    return one, two


def _assert_one_pass(run: Run) -> None:
    """The trajectory was not read first, the bag not read again, and clouds left the gate
    before the end of the bag."""
    assert "reading trajectory" not in run.stages and not run.reread
    assert run.held_at_end < run.report.stats.clouds


# ------------------------------------------------------------------ missions
def _rewrite(src: Path, dst: Path, log_ns: Callable[[int, str, int], int]) -> Path:
    """``src`` written again with each message's log time ``log_ns(index, topic, ns)``
    (the messages sorted by it)."""
    from lidarcal_ros.io.bag.reader import open_bag
    from lidarcal_ros.io.bag.writer import BagWriter

    with open_bag(src) as bag:
        latched = [t for t, info in bag.topics.items() if info.transient_local]
        defs = {t: info.msgdef or None for t, info in bag.topics.items()}
        msgs = [(log_ns(k, topic, ns), k, topic, msgtype, bytes(raw))
                for k, (topic, msgtype, ns, raw) in enumerate(bag.messages())]
    msgs.sort()
    with BagWriter(dst, latched_topics=latched) as writer:
        for ns, _k, topic, msgtype, raw in msgs:
            writer.write_raw(topic, msgtype, ns, raw, msgdef=defs[topic])
    return dst


def _gappy(mission: Mission) -> tuple[Mission, int]:
    """A gap in the trajectory in the middle of strip 2, its first and last 1.5 s left out
    (points not covered at either end), and some poses with a non-finite position; and how
    many poses are non-finite."""
    t0, t1 = strip_span(mission, 2)
    mid = 0.5 * (t0 + t1)
    out = without_trajectory(mission, mid - 0.6, mid + 0.6)
    t_first = min(float(np.nanmin(s.t)) for s in out.strips)
    t_last = max(float(np.nanmax(s.t)) for s in out.strips)
    traj = out.trajectory
    keep = (traj.t > t_first + 1.5) & (traj.t < t_last - 1.5)
    xyz = traj.xyz[keep].copy()
    bad = np.arange(40, xyz.shape[0], 997)
    xyz[bad, 1] = np.nan
    out.trajectory = Trajectory(traj.t[keep], xyz)
    return out, int(bad.size)


@pytest.fixture(scope="module")
def level(small_mission: MissionFiles, tmp_path_factory: pytest.TempPathFactory
          ) -> tuple[MissionFiles, Path]:
    cal = write_calibration_yaml(tmp_path_factory.mktemp("cal") / "cal.yaml",
                                 small_mission.sim.biases)
    return small_mission, cal


@pytest.mark.parametrize("suffix", [".mcap", ".laz"])
def test_level_mission_one_pass_equals_two(level: tuple[MissionFiles, Path], tmp_path: Path,
                                           caplog: pytest.LogCaptureFixture,
                                           suffix: str) -> None:
    files, cal = level
    # (two worker threads: the batches come back grouped as the threads finish them, and
    # the LAZ file's runs, and with them the Extra Bytes record's minima and maxima that
    # laspy takes per write, must not depend on that)
    one, _two = _one_and_two_passes(files.bag, cal, tmp_path, caplog, suffix, workers=2)
    _assert_one_pass(one)
    assert one.report.stats.points == files.sim.mission.n_points
    if suffix == ".mcap":  # every input message passed through as well
        assert one.report.passthrough_messages > one.report.stats.clouds


def test_rough_air_rigorous_one_pass_equals_two(
        mission_factory: Callable[..., MissionFiles], tmp_path: Path,
        caplog: pytest.LogCaptureFixture) -> None:
    from lidarcal_ros.core.simulation.flight_path import RoughAir, crosswind_for_crab

    rough = mission_factory(density=0.15, line_length_m=600.0, seed=3, rough_air=RoughAir(),
                            wind_mps=crosswind_for_crab(5.0, 60.0))
    cal = write_calibration_yaml(tmp_path / "cal.yaml", rough.sim.biases)
    one, _two = _one_and_two_passes(rough.bag, cal, tmp_path, caplog, ".mcap")
    _assert_one_pass(one)
    assert "rigorous" in one.report.stats.describe_models()
    assert one.report.stats.not_corrected < 0.01 * one.report.stats.points


@pytest.mark.parametrize("model", [PositioningModel.LEVEL, PositioningModel.RIGOROUS])
def test_gate_gives_each_cloud_the_samples_of_the_whole_trajectory(
        mission_factory: Callable[..., MissionFiles], model: PositioningModel) -> None:
    """Clouds of 20 ms corrected as soon as the gate lets them through (no batches, no
    look-ahead for the normals: nothing but the gate's reach keeps a cloud from the end of
    the trajectory read so far), the trajectory growing pose by pose as a bag interleaves
    them (each cloud at its first point's time): the bytes of a correction with the whole
    trajectory, with the level model (local-trajectory windows) and the rigorous one
    (attitude splines)."""
    from lidarcal_ros.core.params import PARAMETER_NAMES
    from lidarcal_ros.core.simulation.flight_path import RoughAir, crosswind_for_crab
    from lidarcal_ros.io.cloud.trajectory_messages import TrajectorySamples
    from lidarcal_ros.pipeline.correction.apply import CorrectionSettings
    from lidarcal_ros.pipeline.correction.stream import StreamCorrector

    files = (mission_factory(density=0.15, line_length_m=600.0, seed=3, rough_air=RoughAir(),
                             wind_mps=crosswind_for_crab(5.0, 60.0))
             if model == PositioningModel.RIGOROUS else mission_factory())
    mission = files.sim.mission
    traj = mission.trajectory
    q = (traj.orientation if traj.orientation is not None
         else np.full((len(traj), 4), np.nan))
    settings = CorrectionSettings(delta=np.array([files.sim.biases[n]
                                                  for n in PARAMETER_NAMES]), model=model)
    events: list[tuple[float, int, Any]] = [
        (float(t), 0, (float(t), tuple(xyz), tuple(qi)))
        for t, xyz, qi in zip(traj.t, traj.xyz, q, strict=True)]
    for s in mission.strips:
        pts = strip_points(s)
        events.extend((float(s.t[sl.start]), 1, pts[sl]) for sl in cloud_chunks(s, 0.02))
    events.sort(key=lambda e: (e[0], e[1]))
    header = type("Msg", (), {"header": type("Header", (), {"frame_id": "map"})()})()

    def corrector(trajectory: Trajectory) -> StreamCorrector:
        return StreamCorrector(trajectory, settings, batch_points=0, lookahead=False)

    def add_pose(samples: TrajectorySamples, sample: Any) -> None:
        samples.t.append(sample[0])
        samples.xyz.append(sample[1])
        samples.orientation.append(sample[2])
        samples.frames.add("map")

    samples = TrajectorySamples()
    gated = corrector(Trajectory(np.zeros(0), np.zeros((0, 3))))
    gate = trajectory_gate.TrajectoryGate(
        gated, samples, lambda _msgtype, sample: add_pose(samples, sample),
        lambda: (samples.trajectory("test"), "map"),
        source="test", topic="/lidar/points", max_held_points=10**9)
    # (the whole trajectory as two passes make it: the samples normalised once, from all)
    everything = TrajectorySamples()
    for _t, kind, payload in events:
        if kind == 0:
            add_pose(everything, payload)
    whole = corrector(everything.trajectory("test"))
    got: list[np.ndarray] = []
    want: list[np.ndarray] = []
    given = set()
    for _t, kind, payload in events:
        if kind == 0:
            gate.pose("geometry_msgs/msg/PoseStamped", payload)
            continue
        for _tag, points in gate.cloud(None, header, payload):
            given.add(len(gated.trajectory))
            got.extend(out for _tag2, out in gated.push(points))
        want.extend(out for _tag, out in whole.push(payload))
    for _tag, points in gate.finish():
        got.extend(out for _tag2, out in gated.push(points))
    got.extend(out for _tag, out in gated.flush())
    want.extend(out for _tag, out in whole.flush())
    assert len(given) > 100  # (the trajectory grew while the clouds went through)
    assert len(got) == len(want) > 1000
    assert gated.stats.describe_models() == whole.stats.describe_models()
    assert model in whole.stats.describe_models()
    assert np.concatenate(got).tobytes() == np.concatenate(want).tobytes()


@pytest.mark.parametrize("suffix", [".mcap", ".laz"])
def test_gaps_uncovered_ends_and_bad_poses_one_pass_equals_two(
        level: tuple[MissionFiles, Path], tmp_path: Path, caplog: pytest.LogCaptureFixture,
        suffix: str) -> None:
    files, cal = level
    mission, n_bad = _gappy(files.sim.mission)
    bag = write_cloud_bag(tmp_path / "gappy", mission)
    one, _two = _one_and_two_passes(bag, cal, tmp_path, caplog, suffix)
    _assert_one_pass(one)
    # the clouds after the trajectory's end waited for the end of the bag
    assert one.held_at_end > 0
    stats = one.report.stats
    assert stats.not_corrected > 1000  # the gap and both ends
    assert any(f"{n_bad} of" in r.getMessage() and "non-finite" in r.getMessage()
               for r in caplog.records)


def test_trajectory_after_the_clouds(level: tuple[MissionFiles, Path], tmp_path: Path,
                                     caplog: pytest.LogCaptureFixture) -> None:
    """Every pose written after the last cloud (as an importer might): held within the
    bound (every cloud waits for the end of the bag), read again beyond it; the output of
    two passes either way."""
    files, cal = level
    last_ns = 2**62

    def poses_last(k: int, topic: str, ns: int) -> int:
        return last_ns + k if topic == "/lidar/trajectory" else ns

    bag = _rewrite(files.bag, tmp_path / "late", poses_last)
    from lidarcal_ros.io.bag.reader import open_bag

    with open_bag(bag) as b:  # (the order the bag holds)
        topics = [t for t, *_ in b.messages()]
    first_pose = topics.index("/lidar/trajectory")
    assert "/lidar/points" not in topics[first_pose:]

    n = files.sim.mission.n_points
    held, _two = _one_and_two_passes(bag, cal, tmp_path, caplog, ".mcap",
                                     max_held_points=n)
    assert not held.reread and held.held_at_end == held.report.stats.clouds
    for run in ("one", "two"):
        (tmp_path / run / "out.mcap").unlink()
    reread, _two = _one_and_two_passes(bag, cal, tmp_path, caplog, ".mcap",
                                       max_held_points=n // 10)
    assert reread.reread and "reading trajectory" in reread.stages


def test_poses_out_of_time_order_are_read_again(level: tuple[MissionFiles, Path],
                                                tmp_path: Path,
                                                caplog: pytest.LogCaptureFixture) -> None:
    """Some poses in the middle of a strip logged after all others, when clouds that needed
    them have been corrected: the trajectories the one pass used were not the beginning of
    the whole one, so the bag is read again (same output)."""
    files, cal = level
    t_late = 0.5 * sum(strip_span(files.sim.mission, 3))

    def some_poses_late(_k: int, topic: str, ns: int) -> int:
        if topic == "/lidar/trajectory" and abs(ns * 1e-9 - t_late) < 0.2:
            return ns + 10**12
        return ns

    bag = _rewrite(files.bag, tmp_path / "late", some_poses_late)
    one, _two = _one_and_two_passes(bag, cal, tmp_path, caplog, ".mcap")
    assert one.reread


@pytest.mark.parametrize("late_fault", ["frame", "rigorous"])
def test_error_found_at_the_end_is_that_of_two_passes(
        level: tuple[MissionFiles, Path], tmp_path: Path, caplog: pytest.LogCaptureFixture,
        late_fault: str) -> None:
    """What the whole trajectory shows (poses in a second frame from the last strip on; the
    rigorous model asked of poses without orientation) is refused in one line, the same as
    reading the trajectory first, and no output is left."""
    files, cal = level
    mission = files.sim.mission
    config = None
    if late_fault == "frame":
        last = mission.strips[-1]
        t_switch = float(np.nanmin(last.t))
        early = mission.trajectory.t < t_switch
        a = Mission(Trajectory(mission.trajectory.t[early], mission.trajectory.xyz[early]),
                    mission.strips[:-1], frame_id=mission.frame_id)
        b = Mission(Trajectory(mission.trajectory.t[~early], mission.trajectory.xyz[~early]),
                    mission.strips[-1:], frame_id=mission.frame_id)
        first = write_cloud_bag(tmp_path / "a", a)
        second = write_cloud_bag(tmp_path / "b", b, trajectory_frame="odom")
        bag = _merge(first, second, tmp_path / "two_frames")
    else:
        bag = write_cloud_bag(tmp_path / "positions_only", mission)
        config = FlightConfig().with_values(matching__model="rigorous")
    errors = []
    for held in (None, 0):
        out = tmp_path / f"out_{held}.mcap"
        with pytest.raises(LidarcalError) as exc:
            _correct(bag, cal, out, caplog, config=config, max_held_points=held)
        assert not out.exists()
        assert not list(tmp_path.glob(".*out_*"))  # (nothing staged left either)
        errors.append(str(exc.value))
    assert errors[0] == errors[1]
    assert ("several frames" if late_fault == "frame" else "rigorous") in errors[0]


def _merge(a: Path, b: Path, dst: Path) -> Path:
    """The messages of two bags in one (log-time order)."""
    from lidarcal_ros.io.bag.reader import open_bag
    from lidarcal_ros.io.bag.writer import BagWriter

    msgs: list[tuple[int, str, str, bytes]] = []
    for src in (a, b):
        with open_bag(src) as bag:
            msgs.extend((ns, topic, msgtype, bytes(raw))
                        for topic, msgtype, ns, raw in bag.messages())
    msgs.sort()
    with BagWriter(dst) as writer:
        for ns, topic, msgtype, raw in msgs:
            writer.write_raw(topic, msgtype, ns, raw)
    return dst
