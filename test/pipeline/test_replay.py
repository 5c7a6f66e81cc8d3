"""``lidarcal replay`` and ``lidarcal record``: timing without ROS, publishing over loopback DDS."""

from __future__ import annotations

import itertools
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers_paths import REPO

from lidarcal_ros.errors import ConfigError
from lidarcal_ros.io.bag.reader import open_bag
from lidarcal_ros.io.bag.writer import BagWriter
from lidarcal_ros.io.cloud.messages import cloud_cdr, parse_cloud, serialize, typestore
from lidarcal_ros.io.cloud.pointcloud import make_point_dtype
from lidarcal_ros.pipeline.replay import (
    Pacer,
    ReplayWindow,
    iter_window,
    replay,
    replay_window,
    wait_for_subscribers,
)

NS = 1_000_000_000
PYTHON = sys.executable


# ---------------------------------------------------------------------------- fake clock
class FakeClock:
    """Monotonic time that advances only when waited on."""

    def __init__(self) -> None:
        self.t = 100.0
        self.stop_at: float | None = None

    def now(self) -> float:
        return self.t

    def wait(self, seconds: float) -> bool:
        self.t += max(seconds, 1e-9)
        return self.stop_at is not None and self.t >= self.stop_at


def _messages(times_s: list[float], topic: str = "/a") -> list[tuple[str, str, int, bytes]]:
    return [(topic, "std_msgs/msg/String", round(t * NS), b"x") for t in times_s]


def _run(msgs: list[Any], *, rate: float = 1.0, window: ReplayWindow | None = None,
         clock_hz: float | None = None, loop: bool = False, max_passes: int | None = None,
         latched: tuple[str, ...] = ()) -> tuple[list[tuple[float, str, int]], list[int], Any]:
    fake = FakeClock()
    published: list[tuple[float, str, int]] = []
    clocks: list[int] = []
    pacer = Pacer(rate, clock=clocks.append if clock_hz else None, clock_hz=clock_hz or 40.0,
                  now=fake.now, wait=fake.wait)
    win = window or ReplayWindow(msgs[0][2], msgs[-1][2])
    stats = replay(lambda: iter(msgs), lambda topic, _m, ns, _raw: published.append(
        (fake.t - 100.0, topic, ns)), win, pacer, loop=loop, max_passes=max_passes,
        latched=latched)
    return published, clocks, stats


def test_original_timing_scaled_by_rate() -> None:
    msgs = _messages([10.0, 10.5, 12.0, 14.0])
    out, _, stats = _run(msgs, rate=2.0)
    assert [round(t, 6) for t, _, _ in out] == [0.0, 0.25, 1.0, 2.0]
    assert stats.messages == 4 and stats.passes == 1 and not stats.interrupted
    assert stats.max_lateness_s < 1e-6


def test_start_and_duration_cut_the_window() -> None:
    msgs = _messages([10.0, 11.0, 12.0, 13.0, 14.0])
    win = replay_window(msgs[0][2], msgs[-1][2], start_s=1.0, duration_s=2.0)
    assert (win.start_ns, win.end_ns) == (11 * NS, 13 * NS)
    out, _, _ = _run(msgs, window=win)
    assert [ns // NS for _, _, ns in out] == [11, 12, 13]
    assert [round(t, 6) for t, _, _ in out] == [0.0, 1.0, 2.0]
    assert [m[2] // NS for m in iter_window(msgs, win)] == [11, 12, 13]


def test_latched_history_before_the_window_is_published_first() -> None:
    msgs = [("/control", "sensor_msgs/msg/PointCloud2", 10 * NS, b"c"),
            *_messages([10.5, 11.0, 12.0])]
    win = replay_window(10 * NS, 12 * NS, start_s=1.0)
    out, _, _ = _run(msgs, window=win, latched=("/control",))
    assert [(topic, ns // NS) for _, topic, ns in out] == [("/control", 10), ("/a", 11),
                                                           ("/a", 12)]


def test_loop_replays_again_from_the_start() -> None:
    msgs = _messages([0.0, 1.0])
    out, _, stats = _run(msgs, loop=True, max_passes=3)
    assert stats.passes == 3
    assert [round(t, 6) for t, _, _ in out] == [0.0, 1.0, 1.0, 2.0, 2.0, 3.0]


def test_clock_follows_bag_time_at_its_rate() -> None:
    msgs = _messages([50.0, 51.0])
    _, clocks, stats = _run(msgs, rate=4.0, clock_hz=10.0)
    # 0.25 s of wall time at 10 Hz: the start plus about 2-3 ticks, bag time 50.0 .. 51.0 s
    assert clocks[0] == 50 * NS
    assert 3 <= len(clocks) <= 5 and stats.clock_messages == len(clocks)
    assert all(b >= a for a, b in itertools.pairwise(clocks))
    assert all(50 * NS <= c <= 51 * NS for c in clocks)
    steps = np.diff(clocks) / NS
    assert np.allclose(steps, 0.4, atol=1e-6)  # 0.1 s wall x rate 4


def test_stop_interrupts_the_wait() -> None:
    fake = FakeClock()
    fake.stop_at = fake.t + 0.5
    pacer = Pacer(1.0, now=fake.now, wait=fake.wait)
    out: list[int] = []
    msgs = _messages([0.0, 10.0])
    stats = replay(lambda: iter(msgs), lambda *m: out.append(m[2]),
                   ReplayWindow(0, 10 * NS), pacer)
    assert stats.interrupted and out == [0]


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"start_s": -1.0}, "--start"),
    ({"start_s": 100.0}, "beyond the end"),
    ({"duration_s": 0.0}, "--duration"),
])
def test_bad_window_is_refused(kwargs: dict[str, float], match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        replay_window(0, 10 * NS, **kwargs)


def test_bad_rate_is_refused() -> None:
    with pytest.raises(ConfigError, match="--rate"):
        Pacer(0.0)


# ---------------------------------------------------------------------------- CDR helpers
def test_the_wait_ends_when_every_topic_has_its_subscribers_and_they_settled() -> None:
    """Subscribers appear one by one (a suite's nodes); the wait ends 1 s after the last
    change once each topic has one, and not while a ``lidarcal run`` is still starting."""
    fake = FakeClock()
    seen = {"/lidar/points": [(100.0, 0), (102.0, 1), (103.5, 2)],
            "/lidar/trajectory": [(100.0, 0), (102.5, 1)]}

    def counts() -> dict[str, int]:
        return {t: max(n for at, n in steps if at <= fake.t) for t, steps in seen.items()}

    outcome = wait_for_subscribers(counts, timeout_s=30.0, settle_s=1.0, now=fake.now,
                                   wait=fake.wait)
    assert outcome.ready and outcome.counts == {"/lidar/points": 2, "/lidar/trajectory": 1}
    assert 4.5 <= outcome.waited_s <= 4.6  # 1 s after the last new subscriber (3.5 s)
    fake = FakeClock()
    outcome = wait_for_subscribers(counts, timeout_s=30.0, settle_s=1.0, now=fake.now,
                                   wait=fake.wait, suite_starting=lambda: fake.t < 110.0)
    assert outcome.ready and 10.0 <= outcome.waited_s <= 10.1


def test_the_wait_times_out_naming_the_topics_short_of_subscribers() -> None:
    fake = FakeClock()
    outcome = wait_for_subscribers(lambda: {"/a": 1, "/b": 0}, timeout_s=2.0, now=fake.now,
                                   wait=fake.wait)
    assert not outcome.ready and outcome.missing == ["/b"] and not outcome.suite_starting
    assert 2.0 <= outcome.waited_s <= 2.1
    fake = FakeClock()
    outcome = wait_for_subscribers(lambda: {"/a": 1}, timeout_s=2.0, now=fake.now,
                                   wait=fake.wait, suite_starting=lambda: True)
    assert not outcome.ready and outcome.missing == [] and outcome.suite_starting
    with pytest.raises(ConfigError, match="--min-subscribers"):
        wait_for_subscribers(lambda: {}, timeout_s=1.0, minimum=0)


def test_cloud_cdr_matches_rosbags_serialisation() -> None:
    pts = np.zeros(7, dtype=make_point_dtype(("reflectance",)))
    pts["x"] = np.arange(7)
    pts["t"] = 1.7e9 + np.arange(7) * 1e-3
    for frame in ("map", "ab", "utm_33n"):
        raw = cloud_cdr(1_700_000_000_123_456_789, frame, pts)
        msg = typestore().deserialize_cdr(raw, "sensor_msgs/msg/PointCloud2")
        assert serialize(msg, "sensor_msgs/msg/PointCloud2") == raw
        cloud = parse_cloud(raw)
        assert cloud.stamp_ns == 1_700_000_000_123_456_789 and cloud.frame_id == frame
        assert np.array_equal(cloud.points["x"], pts["x"])
        assert cloud.points.base is not None  # a view on the bytes, not a copy


# ---------------------------------------------------------------------------- over DDS
def _small_bag(path: Path) -> Path:
    """Two topics: 20 clouds at 10 Hz, 40 poses at 20 Hz, control (latched) at the start."""
    dtype = make_point_dtype()
    with BagWriter(path, latched_topics=["/lidar/control_points"]) as w:
        cp = np.zeros(1, dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8")])
        w.write_cloud("/lidar/control_points", 1 * NS, "map", cp)
        for i in range(40):
            w.write_pose("/lidar/trajectory", NS + i * NS // 20, "map", (i, 0.0, 1000.0))
            if i % 2 == 0:
                pts = np.zeros(10, dtype=dtype)
                pts["t"] = 1.0 + i / 20
                pts["strip_id"] = i
                w.write_cloud("/lidar/points", NS + i * NS // 20, "map", pts)
    return path


def _env() -> dict[str, str]:
    return dict(os.environ)


def test_replay_publishes_every_message_with_its_timing(ros_context: Any, tmp_path: Path) -> None:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import PointCloud2

    from lidarcal_ros.nodes.topics import latched_qos
    from lidarcal_ros.nodes.trajectory_input import trajectory_message_classes

    bag = _small_bag(tmp_path / "small.mcap")
    node = rclpy.create_node("replay_probe", context=ros_context)
    got: dict[str, list[Any]] = {"points": [], "poses": [], "control": [], "clock": []}
    node.create_subscription(PointCloud2, "/lidar/points",
                             lambda raw: got["points"].append((time.monotonic(), raw)), 100,
                             raw=True)
    node.create_subscription(trajectory_message_classes()["geometry_msgs/msg/PoseStamped"],
                             "/lidar/trajectory", lambda m: got["poses"].append(m), 100)
    node.create_subscription(PointCloud2, "/lidar/control_points",
                             lambda raw: got["control"].append(raw), latched_qos(), raw=True)
    node.create_subscription(Clock, "/clock", lambda m: got["clock"].append(m), 100)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    proc = subprocess.Popen(
        [PYTHON, "-m", "lidarcal_ros", "replay", str(bag), "--rate", "2", "--clock",
         "--wait-for-subscribers", "10"], env=_env(), stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 30
        while proc.poll() is None and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.02)
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.02)
        out, err = proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        executor.shutdown()
        node.destroy_node()
    assert proc.returncode == 0, err
    assert len(got["points"]) == 20 and len(got["poses"]) == 40 and len(got["control"]) == 1
    # clouds 0.1 s apart in bag time, 0.05 s apart at rate 2
    stamps = [parse_cloud(raw).points["strip_id"][0] for _, raw in got["points"]]
    assert stamps == list(range(0, 40, 2))
    wall = np.array([t for t, _ in got["points"]])
    # 1.9 s of bag time between the first and last cloud: 0.95 s at rate 2. The first delivery
    # of a new publisher may come late (discovery, first shared-memory use), so the timing is
    # judged from the second cloud on: 18 steps of 0.05 s.
    assert 0.035 <= float(np.median(np.diff(wall[1:]))) <= 0.075
    assert 0.7 <= wall[-1] - wall[1] <= 1.5
    assert got["clock"], "no /clock"
    clock_s = [m.clock.sec + m.clock.nanosec * 1e-9 for m in got["clock"]]
    assert all(b >= a for a, b in itertools.pairwise(clock_s))
    assert 1.0 <= clock_s[0] and clock_s[-1] <= 2.96
    assert "done: 61 messages" in out


def test_replay_reports_a_missing_bag_in_one_line(tmp_path: Path) -> None:
    res = subprocess.run([PYTHON, "-m", "lidarcal_ros", "replay", str(tmp_path / "nope")],
                         env=_env(), capture_output=True, text=True, timeout=60)
    assert res.returncode == 1
    assert res.stderr.strip().count("\n") == 0 and "nope" in res.stderr


def test_record_writes_a_valid_bag_stopped_by_sigterm(ros_context: Any, tmp_path: Path) -> None:
    import rclpy
    from std_msgs.msg import String

    from lidarcal_ros.nodes.topics import latched_qos

    out = tmp_path / "rec.mcap"
    node = rclpy.create_node("record_source", context=ros_context)
    latched = node.create_publisher(String, "/lidar/calibration/yaml", latched_qos())
    latched.publish(String(data="published before the recorder started"))
    pub = node.create_publisher(String, "/chatter", 100)
    proc = subprocess.Popen([PYTHON, "-m", "lidarcal_ros", "record", "-o", str(out),
                             "--topics", "/chatter", "/lidar/calibration/yaml"],
                            env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        deadline = time.monotonic() + 20
        while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert pub.get_subscription_count() == 1, "recorder did not subscribe"
        time.sleep(0.3)
        for i in range(25):
            pub.publish(String(data=f"m{i}"))
            time.sleep(0.01)
        assert pub.wait_for_all_acked(rclpy.duration.Duration(seconds=5))
        time.sleep(0.2)
        proc.send_signal(signal.SIGTERM)
        _stdout, stderr = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        node.destroy_node()
    assert proc.returncode == 0, stderr
    assert "Traceback" not in stderr
    with open_bag(out) as bag:
        assert bag.topics["/chatter"].count == 25
        assert bag.topics["/lidar/calibration/yaml"].count == 1
        assert bag.topics["/lidar/calibration/yaml"].transient_local
        texts = [bag.deserialize(raw, t).data for _, t, _, raw in bag.messages(["/chatter"])]
    assert texts == [f"m{i}" for i in range(25)]


def test_run_says_when_the_suite_is_up_and_stops_cleanly_on_sigterm(ros_context: Any,
                                                                     tmp_path: Path) -> None:
    """``lidarcal run`` starts the three nodes, prints one line once each has its
    subscriptions and services (the graph shows them then), and ends with status 0 on
    SIGTERM."""
    import rclpy

    from lidarcal_ros.nodes.suite import SUITE_NODES, node_is_up

    node = rclpy.create_node("run_probe", context=ros_context)
    proc = subprocess.Popen([PYTHON, "-m", "lidarcal_ros", "run"], env=_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=REPO)
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()  # (blocks until the line, or the end of the process)
        want = {"lidarcal_calibrator", "lidarcal_corrector", "lidarcal_flight_config"}
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and not all(
                node_is_up(node, n, SUITE_NODES[n]) for n in want):
            time.sleep(0.1)
        up = {n for n in want if node_is_up(node, n, SUITE_NODES[n])}
        services = {s for s, _ in node.get_service_names_and_types()}
        proc.send_signal(signal.SIGTERM)
        out, stderr = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        node.destroy_node()
    assert line.startswith("lidarcal run: suite up (lidarcal_calibrator, lidarcal_corrector, "
                           "lidarcal_flight_config) in "), (line, stderr)
    assert 0.0 < float(line.rsplit(" in ", 1)[1].removesuffix(" s\n")) < 120.0
    assert up == want and "/lidarcal_calibrator/save" in services
    assert "suite up" not in out  # one line
    assert proc.returncode == 0, stderr
    assert "Traceback" not in stderr


def test_run_reports_a_bad_config_in_one_line(tmp_path: Path) -> None:
    cfg = tmp_path / "bad.yaml"
    cfg.write_text("/**:\n  ros__parameters:\n    sensor:\n      fov_deg: 500.0\n")
    res = subprocess.run([PYTHON, "-m", "lidarcal_ros", "run", "--config", str(cfg)],
                         env=_env(), capture_output=True, text=True, timeout=60)
    assert res.returncode == 1
    assert "sensor.fov_deg" in res.stderr and res.stderr.strip().count("\n") == 0



def test_the_replay_waits_for_every_subscriber_of_a_suite(ros_context: Any,
                                                          tmp_path: Path) -> None:
    """Nodes started before a replay are matched one by one: the replay waits until no new
    subscriber came for the settle time, not only for the first one."""
    import threading

    import rclpy
    from sensor_msgs.msg import PointCloud2

    from lidarcal_ros.nodes.player import PlayerNode

    with open_bag(_small_bag(tmp_path / "small.mcap")) as bag:
        player = PlayerNode(bag, topics=["/lidar/points"], context=ros_context,
                            node_name="settle_player")
        first = rclpy.create_node("settle_first", context=ros_context)
        second = rclpy.create_node("settle_second", context=ros_context)
        try:
            first.create_subscription(PointCloud2, "/lidar/points", lambda raw: None, 10,
                                      raw=True)
            late = threading.Timer(0.6, lambda: second.create_subscription(
                PointCloud2, "/lidar/points", lambda raw: None, 10, raw=True))
            started = time.monotonic()
            late.start()
            outcome = player.wait_for_subscribers(10.0, minimum=1, settle_s=1.0)
            waited = time.monotonic() - started
            late.join()
            assert outcome.ready and outcome.missing == []
            assert player.publishers_by_topic["/lidar/points"].get_subscription_count() >= 2
            assert 1.6 <= waited < 5.0  # the second match, then a second without a new one
            # nobody there: the time-out ends the wait and names the topic
            nobody = PlayerNode(bag, topics=["/lidar/trajectory"], context=ros_context,
                                node_name="settle_alone")
            try:
                started = time.monotonic()
                outcome = nobody.wait_for_subscribers(0.5, minimum=1)
                assert not outcome.ready and outcome.missing == ["/lidar/trajectory"]
                assert time.monotonic() - started < 2.0
            finally:
                nobody.destroy_node()
        finally:
            for node in (player, first, second):
                node.destroy_node()


def _replay(bag: Path, *options: str) -> subprocess.Popen[str]:
    return subprocess.Popen([PYTHON, "-m", "lidarcal_ros", "replay", str(bag), *options],
                            env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)


def _finish(proc: subprocess.Popen[str], timeout: float = 60.0) -> tuple[str, str]:
    try:
        return proc.communicate(timeout=timeout)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_the_replay_waits_for_subscribers_that_come_late(ros_context: Any,
                                                         tmp_path: Path) -> None:
    """Started before anyone listens, the replay waits (default) until the points and
    trajectory have a subscriber: the subscriber made 3 s later gets the first cloud."""
    from sensor_msgs.msg import PointCloud2

    from lidarcal_ros.nodes.trajectory_input import trajectory_message_classes

    bag = _small_bag(tmp_path / "small.mcap")
    proc = _replay(bag)
    node = None
    try:
        time.sleep(3.0)
        assert proc.poll() is None, "the replay did not wait"
        import rclpy
        from rclpy.executors import SingleThreadedExecutor

        node = rclpy.create_node("late_listener", context=ros_context)
        strips: list[int] = []
        node.create_subscription(PointCloud2, "/lidar/points", lambda raw: strips.append(
            int(parse_cloud(raw).points["strip_id"][0])), 100, raw=True)
        node.create_subscription(trajectory_message_classes()["geometry_msgs/msg/PoseStamped"],
                                 "/lidar/trajectory", lambda m: None, 100)
        executor = SingleThreadedExecutor(context=ros_context)
        executor.add_node(node)
        deadline = time.monotonic() + 40
        while proc.poll() is None and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.02)
        for _ in range(50):
            executor.spin_once(timeout_sec=0.02)
        executor.shutdown()
        out, err = _finish(proc)
    finally:
        _finish(proc, 1.0)
        if node is not None:
            node.destroy_node()
    assert proc.returncode == 0, err
    assert strips[:1] == [0] and len(strips) == 20
    found = [line for line in out.splitlines() if "subscribers found" in line]
    assert len(found) == 1 and "/lidar/points (1), /lidar/trajectory (1)" in found[0], out


@pytest.mark.parametrize("options", [("--no-wait",), ("--wait-for-subscribers", "1.5")])
def test_without_subscribers_the_replay_plays_at_once_or_after_the_time_out(
        tmp_path: Path, options: tuple[str, ...]) -> None:
    """``--no-wait`` plays at once and says nothing; past ``--wait-for-subscribers`` one
    warning names the topics without a subscriber (not the latched control points), then it
    plays anyway."""
    bag = _small_bag(tmp_path / "small.mcap")
    started = time.monotonic()
    proc = _replay(bag, *options)
    out, err = _finish(proc)
    took = time.monotonic() - started
    assert proc.returncode == 0, err
    assert "done: 61 messages" in out and "subscribers found" not in out
    if options == ("--no-wait",):
        assert err.strip() == "", err
    else:
        assert err.strip().splitlines() == [
            "lidarcal replay: warning: after 1.5 s (--wait-for-subscribers), fewer than 1 "
            "subscriber(s) on /lidar/points, /lidar/trajectory; replaying anyway"]
        assert took >= 1.5 + 1.9


def test_the_replay_waits_for_a_lidarcal_run_still_starting(ros_context: Any,
                                                           tmp_path: Path) -> None:
    """A ``lidarcal run`` seen still starting holds the replay although the topics already
    have a subscriber (a quick node up, a slow one still importing): the replay starts once
    the monitor says the suite is up, and says so."""
    import threading

    import rclpy
    from rclpy.executors import MultiThreadedExecutor
    from sensor_msgs.msg import PointCloud2

    from lidarcal_ros.nodes.flight_config import FlightConfigNode
    from lidarcal_ros.nodes.suite import SuiteMonitor
    from lidarcal_ros.nodes.trajectory_input import trajectory_message_classes

    lines: list[str] = []
    monitor = SuiteMonitor(["lidarcal_flight_config"], started=time.monotonic(),
                           announce=lines.append, context=ros_context)
    quick = rclpy.create_node("quick_listener", context=ros_context)
    arrivals: list[float] = []
    quick.create_subscription(PointCloud2, "/lidar/points",
                              lambda raw: arrivals.append(time.monotonic()), 100, raw=True)
    quick.create_subscription(trajectory_message_classes()["geometry_msgs/msg/PoseStamped"],
                              "/lidar/trajectory", lambda m: None, 100)
    executor = MultiThreadedExecutor(num_threads=2, context=ros_context)
    for n in (monitor, quick):
        executor.add_node(n)
    spinning = threading.Event()
    spinning.set()

    def spin() -> None:
        while spinning.is_set():
            executor.spin_once(timeout_sec=0.05)

    spinner = threading.Thread(target=spin, daemon=True)
    spinner.start()
    proc = _replay(_small_bag(tmp_path / "small.mcap"))
    slow = None
    try:
        time.sleep(4.0)
        assert proc.poll() is None and not arrivals, "the replay did not wait for the suite"
        slow = FlightConfigNode(context=ros_context)
        up_at = time.monotonic()
        executor.add_node(slow)
        out, err = _finish(proc)
    finally:
        _finish(proc, 1.0)
        spinning.clear()
        spinner.join(timeout=5)
        executor.shutdown()
        for held in (monitor, quick, slow):
            if held is not None:
                held.destroy_node()
    assert proc.returncode == 0, err
    assert len(lines) == 1 and lines[0].startswith("lidarcal run: suite up "
                                                   "(lidarcal_flight_config) in ")
    assert monitor.up_after_s is not None and monitor.up_after_s >= 4.0
    assert len(arrivals) == 20 and arrivals[0] > up_at
    assert "lidarcal run's suite up" in out, out
