"""The node suite over loopback DDS: real nodes, a real replay, the offline result as reference.

One module-scoped suite (flight configuration, calibrator, corrector and a probe node in this
process, spun by a multi-threaded executor in a background thread) receives a replay of a small
simulated mission (``lidarcal replay`` in a child process). The tests then check, in order:
the estimate against ``lidarcal calibrate``'s, exactly-once correction, late joiners, live
parameters and refusals, malformed clouds. The checkpoint test runs the calibrator as a child
process it kills with SIGKILL.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import helpers_missions
import numpy as np
import pytest
import yaml
from helpers_wait import wait_until as _wait

from lidarcal_ros.core.calibration.thinning import first_per_cell
from lidarcal_ros.core.config import FlightConfig
from lidarcal_ros.core.params import PARAMETER_NAMES, format_estimate, format_value
from lidarcal_ros.io.bag.reader import open_bag
from lidarcal_ros.io.cloud.columns import extract_columns
from lidarcal_ros.io.cloud.messages import cloud_cdr, parse_cloud, parse_estimate
from lidarcal_ros.pipeline.calibration.procedure import calibrate_mission, load_mission
from lidarcal_ros.pipeline.correction.process import CorrectionProcess

if TYPE_CHECKING:
    from rclpy.client import Client

mission_factory = helpers_missions.mission_factory
small_mission = helpers_missions.small_mission

PYTHON = sys.executable
FAST = helpers_missions.FAST_SETTINGS
RATE = 25.0  # the small mission (199 s) replays in 8 s


def _replay(bag: Path, *extra: str, timeout: float = 90.0) -> str:
    res = subprocess.run(
        [PYTHON, "-m", "lidarcal_ros", "replay", str(bag), "--rate", str(RATE),
         "--wait-for-subscribers", "20", *extra],
        env=dict(os.environ), capture_output=True, text=True, timeout=timeout)
    assert res.returncode == 0, res.stderr
    return res.stdout


def _bag_points(bag: Path) -> tuple[np.ndarray, np.ndarray]:
    """Strip ids and times of every point on /lidar/points."""
    sid, t = [], []
    with open_bag(bag) as b:
        for _topic, _type, _ns, raw in b.messages(["/lidar/points"]):
            pts = parse_cloud(raw).points
            sid.append(pts["strip_id"].astype(np.int64))
            t.append(pts["t"].copy())
    return np.concatenate(sid), np.concatenate(t)


IN_THREAD_TOPIC = "/suite/points_corrected_in_thread"


@dataclass
class Probe:
    """What the probe node received."""

    corrected: list[bytes] = field(default_factory=list)
    corrected_in_thread: list[bytes] = field(default_factory=list)  # separate_process false
    estimates: list[Any] = field(default_factory=list)
    diagnostics: dict[str, Any] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def corrected_points(self) -> int:
        with self.lock:
            return sum(len(parse_cloud(raw)) for raw in self.corrected)


@dataclass
class Suite:
    context: Any
    fc: Any
    cal: Any
    cor: Any
    cor_in_thread: Any
    probe_node: Any
    probe: Probe
    mission: Any
    config: FlightConfig

    def call(self, service: str, timeout: float = 120.0) -> Any:
        from std_srvs.srv import Trigger

        client = self.probe_node.create_client(Trigger, service)
        try:
            assert client.wait_for_service(timeout_sec=10.0), f"{service} not available"
            future = client.call_async(Trigger.Request())
            _wait(future.done, timeout, service)
            return future.result()
        finally:
            self.probe_node.destroy_client(client)

    def set_parameters(self, node: str, **values: Any) -> list[Any]:
        from rclpy.parameter import Parameter
        from rclpy.parameter_client import AsyncParameterClient

        client = AsyncParameterClient(self.probe_node, node)
        assert client.wait_for_services(timeout_sec=10.0)
        params = [Parameter(k.replace("__", "."), value=v) for k, v in values.items()]
        future = client.set_parameters(params)
        _wait(future.done, 10.0, f"set_parameters on {node}")
        response = future.result()
        assert response is not None  # done and not failed: the service's response
        return list(response.results)


class Spinner:
    """A multi-threaded executor spinning in a background thread."""

    def __init__(self, context: Any, nodes: list[Any]) -> None:
        from rclpy.executors import MultiThreadedExecutor

        self.executor = MultiThreadedExecutor(num_threads=4, context=context)
        for n in nodes:
            self.executor.add_node(n)
        self._stop = threading.Event()
        self.errors: list[BaseException] = []
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        while not self._stop.is_set():
            try:
                self.executor.spin_once(timeout_sec=0.05)
            except Exception as exc:  # a callback failed: fail the test that looks, go on
                if type(exc).__name__ == "InvalidHandle" and "destruction" in str(exc):
                    # A test destroyed a publisher or client of the probe node while this
                    # thread was waiting on it: the race of the test, not a node's failure.
                    continue
                self.errors.append(exc)

    def stop(self) -> None:
        self._stop.set()
        self.thread.join(timeout=10)
        deadline = time.monotonic() + 5
        while any(not f.done() for f in getattr(self.executor, "_futures", ())) and \
                time.monotonic() < deadline:
            time.sleep(0.01)
        self.executor.shutdown(timeout_sec=5)


#: The suite's mission: the small one flown crabbed into a 4 m/s crosswind, its poses carrying
#: the IMU's heading, so that the replay also checks that the heading of the orientation
#: reaches the live calibration and correction as it reaches the offline ones.
CRABBED = {"wind_mps": (4.0, 0.0), "attitude": True}


@pytest.fixture(scope="module")
def suite_mission(mission_factory: Any) -> Any:
    return mission_factory(**CRABBED)


@pytest.fixture(scope="module")
def suite(ros_context: Any, suite_mission: Any) -> Iterator[Suite]:
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import PointCloud2
    from std_msgs.msg import Float64MultiArray

    from lidarcal_ros.nodes.calibrator import CalibratorNode
    from lidarcal_ros.nodes.corrector import CorrectorNode
    from lidarcal_ros.nodes.flight_config import FlightConfigNode
    from lidarcal_ros.nodes.topics import latched_qos

    workdir = suite_mission.workdir
    shared = {**FAST, "calibration.control_points_file": str(suite_mission.control_csv),
              "calibration.calibration_file": str(workdir / "suite_calibration.yaml")}
    overrides = [Parameter(k, value=v) for k, v in shared.items()]
    fc = FlightConfigNode(context=ros_context, parameter_overrides=overrides)
    cal = CalibratorNode(context=ros_context, parameter_overrides=[
        *overrides, Parameter("idle_close_s", value=0.5)])
    cor = CorrectorNode(context=ros_context, parameter_overrides=overrides)
    # The same correction in a thread of the node instead of a child process.
    cor_in_thread = CorrectorNode(
        context=ros_context, node_name="lidarcal_corrector_in_thread", parameter_overrides=[
            *overrides, Parameter("separate_process", value=False),
            Parameter("topics.corrected", value=IN_THREAD_TOPIC)])
    node = rclpy.create_node("suite_probe", context=ros_context)
    probe = Probe()

    def on_corrected(raw: bytes) -> None:
        with probe.lock:
            probe.corrected.append(raw)

    def on_diag(msg: Any) -> None:
        for s in msg.status:
            probe.diagnostics[s.name] = (s.level[0] if isinstance(s.level, bytes) else s.level,
                                         s.message, {kv.key: kv.value for kv in s.values})

    def on_corrected_in_thread(raw: bytes) -> None:
        with probe.lock:
            probe.corrected_in_thread.append(raw)

    node.create_subscription(PointCloud2, "/lidar/points_corrected", on_corrected, 1000,
                             raw=True)
    node.create_subscription(PointCloud2, IN_THREAD_TOPIC, on_corrected_in_thread, 1000,
                             raw=True)
    node.create_subscription(Float64MultiArray, "/lidar/calibration/estimate",
                             lambda m: probe.estimates.append(m), latched_qos())
    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 100)
    spinner = Spinner(ros_context, [fc, cal, cor, cor_in_thread, node])
    config = FlightConfig.from_mapping(shared)
    try:
        yield Suite(ros_context, fc, cal, cor, cor_in_thread, node, probe, suite_mission, config)
    finally:
        spinner.stop()
        assert not spinner.errors, f"callbacks failed: {spinner.errors}"
        for n in (cal, cor, cor_in_thread, fc):
            n.close()
        for ros_node in (node, cal, cor, cor_in_thread, fc):
            ros_node.destroy_node()


# ---------------------------------------------------------------------------- replay
@dataclass
class Replayed:
    """The suite after the replay of its mission (the :func:`replayed` fixture): every cloud
    corrected by both correctors, all six strips closed, one solve asked for; what had
    arrived by then (later tests publish more clouds and change the nodes)."""

    suite: Suite
    corrected: list[bytes]
    corrected_in_thread: list[bytes]
    points_out: dict[str, int]
    skipped: dict[str, int]
    solve: Any


@pytest.fixture(scope="module")
def replayed(suite: Suite) -> Replayed:
    """The mission replayed through the suite, once per module, whichever tests run: the
    tests that need an estimate or closed strips take this, so that each also runs alone
    (``-k``)."""
    bag = suite.mission.bag
    with open_bag(bag) as b:
        n_clouds = b.topics["/lidar/points"].count
    # Points and trajectory each have three subscribers: the calibrator and both correctors.
    # Starting before all three are there loses the first poses for the late one.
    out = _replay(bag, "--min-subscribers", "3")
    assert "done:" in out
    _wait(lambda: len(suite.probe.corrected) >= n_clouds, 60, "every corrected cloud")
    _wait(lambda: len(suite.probe.corrected_in_thread) >= n_clouds, 60,
          "every cloud corrected in a thread")
    cal = suite.cal.calibration
    _wait(lambda: cal.stream.strip_ids == [1, 2, 3, 4, 5, 6] and not cal.stream.open_strip_ids
          and cal.queued_jobs == 0, 90, "the calibrator to close all six strips",
          state=lambda: f"strips {cal.stream.strip_ids}, open {cal.stream.open_strip_ids}, "
                        f"queued jobs {cal.queued_jobs}, diagnostics "
                        f"{suite.probe.diagnostics.get('lidarcal: input')}")
    _wait(lambda: "lidarcal: strips 1&2" in suite.probe.diagnostics, 30, "pair diagnostics")
    with suite.probe.lock:
        corrected = list(suite.probe.corrected)
        corrected_in_thread = list(suite.probe.corrected_in_thread)
    nodes = {"process": suite.cor, "thread": suite.cor_in_thread}
    points_out = {k: n.correction.stats.points_out for k, n in nodes.items()}
    skipped = {k: n.correction.stats.skipped for k, n in nodes.items()}
    solve = suite.call("/lidarcal_calibrator/solve")
    assert solve.success, solve.message
    _wait(lambda: cal.solves >= 1 and len(suite.probe.estimates) >= 1, 10, "an estimate")
    time.sleep(0.3)
    return Replayed(suite, corrected, corrected_in_thread, points_out, skipped, solve)


def test_replayed_mission_gives_the_offline_estimate(replayed: Replayed) -> None:
    suite = replayed.suite
    bag = suite.mission.bag
    cal = suite.cal
    # the live estimate exists and QA was published per pair
    level, message, values = suite.probe.diagnostics["lidarcal: strips 1&2"]
    assert {"coverage", "rms_before", "rms_after", "p95_after"} <= set(values)
    assert message.startswith("RMS ") and message.endswith(("OK", "WARN", "ERROR"))
    assert level == 0 and float(values["rms_before"]) > float(values["rms_after"])
    assert "lidarcal: observability" in suite.probe.diagnostics
    assert "lidarcal: convergence" in suite.probe.diagnostics
    # an ideal mission: auto keeps the trajectory exact, and says so
    level, message, values = suite.probe.diagnostics["lidarcal: trajectory"]
    assert level == 0 and message.startswith("taken as exact (auto: none")

    assert "15 strip pairs" in replayed.solve.message
    assert cal.calibration.solves >= 1
    live = parse_estimate(suite.probe.estimates[-1].data,
                          [d.label for d in suite.probe.estimates[-1].layout.dim])

    mission = load_mission(bag, suite.config)
    assert mission.trajectory.heading is not None  # the poses carry the IMU's heading
    offline = calibrate_mission(mission, suite.config).solution
    for i, name in enumerate(PARAMETER_NAMES):
        if name not in offline.estimated:
            assert live.sigmas[name] is None
            continue
        sigma = float(offline.sigma[i])
        assert abs(live.values[name] - offline.delta[i]) <= 0.1 * sigma, name
        assert live.sigmas[name] == pytest.approx(sigma, rel=0.05), name
    # ... which is not what the track's heading gives: the live estimate took the
    # orientation off the topic (a calibrator that lost it would be sigmas away)
    by_track = calibrate_mission(
        mission, suite.config.with_values(matching__heading_source="track")).solution
    assert max(abs(live.values[n] - by_track.delta[i]) / by_track.sigma[i]
               for i, n in enumerate(PARAMETER_NAMES) if n in by_track.estimated) > 1.0
    # the same estimate for people on /diagnostics, in arcsec and cm
    def shown(name: str) -> str:
        sigma = live.sigmas[name]
        if sigma is None:
            return f"fixed at {format_value(name, live.values[name])}"
        return format_estimate(name, live.values[name], sigma)

    _wait(lambda: suite.probe.diagnostics.get("lidarcal: estimate", (0, "", {}))[2] == {
        **{name: shown(name) for name in PARAMETER_NAMES},
        # 4 m/s across 60 m/s: asin(4 / 60) = 3.8 deg of crab, opposite on opposite lines
        "heading": "heading from the poses' orientation (IMU) for every strip (crab -3.8 to "
                   "+3.8 deg)",
        "model": "level (the poses carry a heading only (no roll or pitch)) for every strip"},
        10, "the estimate on /diagnostics")
    level, message, values = suite.probe.diagnostics["lidarcal: estimate"]
    assert level == 0 and message.startswith("dX ") and " arcsec" in values["dphi"]
    assert f"dphi {shown('dphi')}" in message and "dZ" not in message  # dZ is held fixed
    cov = live.covariance
    assert np.allclose(cov, cov.T)
    k = PARAMETER_NAMES.index("dX")
    assert math.sqrt(cov[k, k]) == pytest.approx(live.sigmas["dX"])

    save = suite.call("/lidarcal_calibrator/save")
    assert save.success and "suite_calibration.yaml" in save.message
    assert (suite.mission.workdir / "suite_calibration.yaml").is_file()


def test_every_input_point_is_corrected_exactly_once(replayed: Replayed) -> None:
    """Both ways of running the correction: in a child process (as shipped) and in a thread
    of the node (``separate_process`` false)."""
    suite = replayed.suite
    sid_in, t_in = _bag_points(suite.mission.bag)
    key_in = np.lexsort((t_in, sid_in))
    for how, received in (("process", replayed.corrected),
                          ("thread", replayed.corrected_in_thread)):
        clouds = [parse_cloud(raw) for raw in received]
        pts = np.concatenate([c.points for c in clouds])
        assert pts.dtype.names is not None  # a structured array (a point cloud)
        assert {"reflectance", "range", "incidence", "scan_angle", "correction_flags"} <= set(
            pts.dtype.names)
        sid_out, t_out = pts["strip_id"].astype(np.int64), pts["t"]
        key_out = np.lexsort((t_out, sid_out))
        assert len(pts) == len(t_in)
        assert np.array_equal(sid_in[key_in], sid_out[key_out])
        assert np.array_equal(t_in[key_in], t_out[key_out])
        assert replayed.points_out[how] == len(t_in) and replayed.skipped[how] == 0
        flags = pts["correction_flags"]
        bad = (flags & 1) != 0
        assert not bad.any(), (
            f"{int(bad.sum())} points not covered by the trajectory, strips "
            f"{np.unique(pts['strip_id'][bad]).tolist()}")
        assert np.isfinite(pts["range"]).all() and (pts["range"] > 100).all()
    # The child process got and gave back the clouds through shared memory.
    assert suite.cor.status().values["transport"] == "shared memory"
    assert suite.cor_in_thread.status().values["transport"] == "thread"
    # the crabbed mission's poses carry the IMU's heading, and the corrector says it uses it
    assert suite.cor.status().values["heading"].startswith("from the poses' orientation")
    runner = suite.cor.correction.runner
    assert isinstance(runner, CorrectionProcess)
    carried = runner.carried
    assert carried["ring in"] > 0 and carried["ring out"] > 0, carried
    # the clouds were taken from DDS into the ring, not copied there
    assert carried["in place"] > 0 and suite.cor.points_input.direct, carried


def test_late_subscriber_gets_the_latest_estimate(replayed: Replayed) -> None:
    import rclpy
    from std_msgs.msg import Float64MultiArray, String

    from lidarcal_ros.nodes.topics import latched_qos

    suite = replayed.suite
    latest = list(suite.probe.estimates[-1].data)
    node = rclpy.create_node("late_joiner", context=suite.context)
    got: list[Any] = []
    text: list[str] = []
    node.create_subscription(Float64MultiArray, "/lidar/calibration/estimate",
                             lambda m: got.append(list(m.data)), latched_qos())
    node.create_subscription(String, "/lidar/calibration/yaml", lambda m: text.append(m.data),
                             latched_qos())
    from rclpy.executors import SingleThreadedExecutor

    executor = SingleThreadedExecutor(context=suite.context)
    executor.add_node(node)
    try:
        deadline = time.monotonic() + 10
        while (not got or not text) and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
    finally:
        executor.shutdown()
        node.destroy_node()
    assert len(got) == 1 and np.array_equal(got[0], latest, equal_nan=True)
    assert text and text[0].startswith("lidarcal_calibration:")


# ---------------------------------------------------------------------------- parameters
def _reflectance_of(suite: Suite, raw_in: bytes, stamp: int) -> np.ndarray:
    """Publish one cloud on /lidar/points; return the reflectance of its corrected copy."""
    from sensor_msgs.msg import PointCloud2

    pub = suite.probe_node.create_publisher(PointCloud2, "/lidar/points", 10)
    try:
        _wait(lambda: pub.get_subscription_count() >= 2, 10, "point subscribers")
        before = len(suite.probe.corrected)
        pub.publish(raw_in)
        _wait(lambda: len(suite.probe.corrected) > before, 20, "the corrected cloud")
        out = parse_cloud(suite.probe.corrected[before])
        assert out.stamp_ns == stamp
        return np.asarray(out.points["reflectance"], dtype=np.float64)
    finally:
        suite.probe_node.destroy_publisher(pub)


def test_a_parameter_set_at_run_time_changes_what_the_nodes_do(replayed: Replayed) -> None:
    suite = replayed.suite
    with open_bag(suite.mission.bag) as b:
        raw = next(raw for _t, _m, _ns, raw in b.messages(["/lidar/points"]))
    stamp = parse_cloud(raw).stamp_ns
    before = _reflectance_of(suite, raw, stamp)
    results = suite.set_parameters("lidarcal_flight_config", atmosphere__visibility_km=5.0)
    assert results[0].successful, results[0].reason
    for node in (suite.cal, suite.cor):
        def follows(n: Any = node) -> bool:
            return n.params["atmosphere.visibility_km"] == 5.0

        _wait(follows, 10, f"{node.get_name()} to follow")
    after = _reflectance_of(suite, raw, stamp)
    ok = np.isfinite(before) & np.isfinite(after)
    assert ok.mean() > 0.5  # the first chunk of a strip lacks neighbours for some normals
    # thicker haze: more attenuation to undo, so a higher reflectance for the same intensity
    assert np.all(after[ok] > before[ok])

    # QA thresholds set live change the calibrator's verdicts at the next solve
    results = suite.set_parameters("lidarcal_flight_config", qa__rmsdz_warn_m=0.001,
                                   qa__max_difference_m=0.002)
    assert all(r.successful for r in results)
    _wait(lambda: suite.cal.params["qa.max_difference_m"] == 0.002, 10, "the calibrator")
    suite.probe.diagnostics.pop("lidarcal: strips 1&2", None)
    assert suite.call("/lidarcal_calibrator/solve").success
    _wait(lambda: "lidarcal: strips 1&2" in suite.probe.diagnostics, 10, "pair diagnostics")
    level, message, _ = suite.probe.diagnostics["lidarcal: strips 1&2"]
    assert level == 2 and message.endswith("ERROR")


@pytest.mark.parametrize(("values", "reason"), [
    ({"sensor__fov_deg": 500.0}, "fov_deg"),
    ({"calibration__solve_for": ["dX", "dQ"]}, "unknown parameter(s) dQ"),
    ({"matching__min_normal_distance_m": 5.0}, "exceeds matching.max_normal_distance_m"),
    ({"radiometry__power_model": "quadratic"}, "not one of constant, pulse_rate"),
    ({"topics__points": "/elsewhere"}, "read-only"),
    ({"sensor__fov_deg": "wide"}, "type"),
    # not numbers: out of a declared range (rclpy), or not finite (the node's own check)
    ({"sensor__fov_deg": float("nan")}, "sensor.fov_deg out of range"),
    ({"atmosphere__visibility_km": float("inf")}, "atmosphere.visibility_km out of range"),
    ({"calibration__fixed__dX": float("nan")}, "calibration.fixed.dX: must be finite"),
    ({"calibration__fixed__dr": -float("inf")}, "calibration.fixed.dr: must be finite"),
])
def test_a_bad_value_is_refused_with_its_reason(suite: Suite, values: dict[str, Any],
                                                reason: str) -> None:
    name = next(iter(values)).replace("__", ".")
    old = suite.fc.params[name]
    results = suite.set_parameters("lidarcal_flight_config", **values)
    assert not results[0].successful
    assert reason in results[0].reason
    time.sleep(0.2)
    for node in (suite.fc, suite.cal, suite.cor):
        assert node.params[name] == old


def test_the_cli_knows_every_parameter_the_nodes_declare(ros_context: Any) -> None:
    """The commands tell a misspelt key from a node's own parameter by the names of
    ``core.config``: they must be those the nodes declare."""
    from lidarcal_ros.core.config import (
        CALIBRATOR_NODE,
        CORRECTOR_NODE,
        FLIGHT_CONFIG_NODE,
        NODE_PARAMETERS,
        ROS_PARAMETERS,
        SCHEMA,
    )
    from lidarcal_ros.nodes import calibrator, corrector
    from lidarcal_ros.nodes.flight_config import FlightConfigNode

    assert set(NODE_PARAMETERS) == {CALIBRATOR_NODE, CORRECTOR_NODE, FLIGHT_CONFIG_NODE}
    assert set(NODE_PARAMETERS[CALIBRATOR_NODE]) == set(calibrator.CALIBRATOR_PARAMETERS)
    assert set(NODE_PARAMETERS[CORRECTOR_NODE]) == set(corrector.CORRECTOR_PARAMETERS)
    node = FlightConfigNode(context=ros_context, node_name="fc_declared")
    try:
        declared = set(node.list_parameters([], 0).names)
    finally:
        node.destroy_node()
    assert declared == set(SCHEMA) | set(ROS_PARAMETERS) | set(
        NODE_PARAMETERS[FLIGHT_CONFIG_NODE])


def test_dz_and_dr_without_control_is_refused(suite: Suite) -> None:
    from lidarcal_ros.nodes.flight_config import FlightConfigNode

    node = FlightConfigNode(context=suite.context, node_name="fc_without_control")
    try:
        from rclpy.parameter import Parameter

        result = node.set_parameters([Parameter("calibration.solve_for",
                                                value=["dX", "dZ", "dr"])])[0]
        assert not result.successful and "without" in result.reason and "control" in \
            result.reason
        ok = node.set_parameters([Parameter("calibration.solve_for", value=["dX", "dr"])])[0]
        assert ok.successful
    finally:
        node.destroy_node()


# ---------------------------------------------------------------------------- bad input
def test_a_malformed_cloud_is_logged_and_skipped(replayed: Replayed) -> None:
    from sensor_msgs.msg import PointCloud2

    suite = replayed.suite
    good = np.zeros(5, dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("t", "<f8"),
                              ("intensity", "<f4"), ("strip_id", "<u2")])
    no_time = np.zeros(5, dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8")])
    truncated = cloud_cdr(10**18, "map", good)[:-41]
    messages = [cloud_cdr(10**18, "map", no_time), bytes(truncated), b"\x00\x01\x00\x00junk"]
    skipped_cal = suite.cal.calibration.input.skipped
    skipped_cor = suite.cor.correction.stats.skipped
    pub = suite.probe_node.create_publisher(PointCloud2, "/lidar/points", 10)
    try:
        _wait(lambda: pub.get_subscription_count() >= 2, 10, "point subscribers")
        for raw in messages:
            pub.publish(raw)
        _wait(lambda: suite.cal.calibration.input.skipped >= skipped_cal + 3 and
              suite.cor.correction.stats.skipped >= skipped_cor + 3, 10, "the clouds to be skipped")
    finally:
        suite.probe_node.destroy_publisher(pub)
    assert "lacks time field" in suite.cor.correction.stats.last_error or \
        "undecodable" in suite.cor.correction.stats.last_error
    # still running: a good cloud goes through, the diagnostics say what was skipped
    with open_bag(suite.mission.bag) as b:
        raw = next(raw for _t, _m, _ns, raw in b.messages(["/lidar/points"]))
    refl = _reflectance_of(suite, raw, parse_cloud(raw).stamp_ns)
    assert np.isfinite(refl).any()
    status = suite.cor.status()
    assert status.level == 1 and "malformed" in status.message
    inputs = suite.cal.calibration.operating_statuses()[1]
    assert inputs.level == 1
    # the good cloud belongs to strip 1, complete since the mission's replay: ignored, said
    assert int(inputs.values["late_points"]) >= len(parse_cloud(raw).points)
    assert "already closed" in inputs.message


def test_interleaved_malformed_clouds_are_counted_on_diagnostics(replayed: Replayed) -> None:
    """A stream with a malformed cloud after every good one: the suite keeps correcting the
    good ones, and /diagnostics counts every malformed one (calibrator and corrector)."""
    from sensor_msgs.msg import PointCloud2

    suite = replayed.suite
    good_fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("t", "<f8"),
                   ("intensity", "<f4"), ("strip_id", "<u2")]
    bad = [cloud_cdr(10**18, "map", np.zeros(4, dtype=[("x", "<f8"), ("y", "<f8")])),
           bytes(cloud_cdr(10**18, "map", np.zeros(5, dtype=good_fields))[:-41]),
           b"\x00\x01\x00\x00junk",
           cloud_cdr(10**18, "map", np.zeros(3, dtype=[("y", "<f8"), ("z", "<f8"),
                                                        ("t", "<f8")]))]
    with open_bag(suite.mission.bag) as b:
        good = [bytes(raw) for _t, _m, _ns, raw in b.messages(["/lidar/points"])][:len(bad)]
    cal_before = suite.cal.calibration.input.skipped
    cor_before = suite.cor.correction.stats.skipped
    with suite.probe.lock:
        out_before = len(suite.probe.corrected)
    pub = suite.probe_node.create_publisher(PointCloud2, "/lidar/points", 10)
    try:
        _wait(lambda: pub.get_subscription_count() >= 3, 10, "point subscribers")
        for g, m in zip(good, bad, strict=True):
            pub.publish(g)
            pub.publish(m)

        def counted() -> bool:
            diag = suite.probe.diagnostics
            return (diag.get("lidarcal: input", (0, "", {}))[2].get("skipped_clouds")
                    == str(cal_before + len(bad)) and
                    suite.cor.correction.stats.skipped == cor_before + len(bad))
        _wait(counted, 20, "every malformed cloud counted on /diagnostics")
        _wait(lambda: len(suite.probe.corrected) >= out_before + len(good), 20,
              "every good cloud corrected")
    finally:
        suite.probe_node.destroy_publisher(pub)
    level, message, _ = suite.probe.diagnostics["lidarcal: input"]
    assert level == 1 and f"{cal_before + len(bad)} malformed clouds skipped" in message
    status = suite.cor.status()
    assert status.values["skipped_clouds"] == str(cor_before + len(bad))


def test_a_dead_correction_process_is_replaced_and_the_next_cloud_corrected(
        replayed: Replayed) -> None:
    """The correction process killed between clouds: the node starts a new one (with its own
    shared memory, the old rings' files gone) and corrects the next cloud."""
    suite = replayed.suite
    old = suite.cor.correction.runner
    assert isinstance(old, CorrectionProcess)
    rings = old.ring_paths
    old.kill()
    _wait(lambda: not old.alive, 10, "the correction process to die")
    with open_bag(suite.mission.bag) as b:
        raw = next(raw for _t, _m, _ns, raw in b.messages(["/lidar/points"]))
    refl = _reflectance_of(suite, raw, parse_cloud(raw).stamp_ns)
    assert np.isfinite(refl).any()
    new = suite.cor.correction.runner
    assert isinstance(new, CorrectionProcess)
    assert new is not old and new.alive
    assert all(not Path(path).exists() for path in rings)
    _wait(lambda: new.shared_memory, 30, "the new process to map its rings")
    assert suite.cor.status().values["transport"] == "shared memory"


def test_memory_budget_releases_the_oldest_strips_and_says_so(replayed: Replayed) -> None:
    suite = replayed.suite
    held = suite.cal.calibration.stream.n_points
    results = suite.set_parameters("lidarcal_calibrator", memory_budget_points=held // 2)
    assert results[0].successful, results[0].reason
    with open_bag(suite.mission.bag) as b:
        raw = next(raw for _t, _m, _ns, raw in b.messages(["/lidar/points"]))
    _reflectance_of(suite, raw, parse_cloud(raw).stamp_ns)  # any cloud triggers the budget
    _wait(lambda: suite.cal.calibration.stream.dropped_points > 0, 10, "strips to be released")
    memory = suite.cal.calibration.operating_statuses()[0]
    assert memory.name == "lidarcal: memory" and memory.level == 1
    assert suite.cal.calibration.stream.n_points <= held // 2
    assert memory.values["dropped_strips"].startswith("1")  # the oldest first
    assert int(memory.values["dropped_points"]) == suite.cal.calibration.stream.dropped_points
    assert "released" in memory.message


def test_thinning_set_at_run_time_thins_the_next_clouds_and_says_so(replayed: Replayed
                                                                      ) -> None:
    """``calibration.thinning_cell_m`` set on the flight configuration reaches the
    calibrator, which thins the clouds after it (as ``lidarcal calibrate`` reads a bag) and
    counts what it left out in its memory status."""
    suite = replayed.suite
    before = suite.cal.calibration.stream.thinned_points
    results = suite.set_parameters("lidarcal_flight_config", calibration__thinning_cell_m=5.0)
    assert results[0].successful, results[0].reason
    try:
        _wait(lambda: suite.cal.calibration.stream.config["calibration.thinning_cell_m"] == 5.0,
              10, "the calibrator to follow")
        with open_bag(suite.mission.bag) as b:
            raw = next(raw for _t, _m, _ns, raw in b.messages(["/lidar/points"]))
        cols = extract_columns(parse_cloud(raw).points)
        assert cols.strip_id is not None
        expected = int((~first_per_cell(cols.xyz, cols.strip_id, 5.0)).sum())
        assert expected > 0
        _reflectance_of(suite, raw, parse_cloud(raw).stamp_ns)
        _wait(lambda: suite.cal.calibration.stream.thinned_points == before + expected, 10,
              "the cloud to be thinned")
        memory = suite.cal.calibration.operating_statuses()[0]
        assert memory.values["thinning_cell_m"] == "5"
        assert int(memory.values["thinned_points"]) == before + expected
        assert "left out by thinning" in memory.message
    finally:
        suite.set_parameters("lidarcal_flight_config", calibration__thinning_cell_m=0.0)


def test_reset_forgets_everything_and_its_checkpoint(replayed: Replayed,
                                                     tmp_path: Path) -> None:
    """``~/reset`` (the last test of the suite: it empties the calibrator) leaves nothing to
    solve, save or resume from; the latest estimate stays latched."""
    suite = replayed.suite
    ckpt = tmp_path / "reset_ckpt.npz"
    results = suite.set_parameters("lidarcal_calibrator", checkpoint_file=str(ckpt))
    assert results[0].successful, results[0].reason
    try:
        solved = suite.call("/lidarcal_calibrator/solve")  # the checkpoint is written
        assert solved.success, solved.message
        assert ckpt.is_file() and _checkpoint_state(ckpt)[0] > 0
        estimates = len(suite.probe.estimates)
        response = suite.call("/lidarcal_calibrator/reset")
        assert response.success and "forgotten" in response.message
        assert str(ckpt) in response.message and not ckpt.exists()
        stream = suite.cal.calibration.stream
        assert stream.strip_ids == [] and stream.n_points == 0
        assert stream.normal_equations.count == 0 and stream.latest is None
        solve = suite.call("/lidarcal_calibrator/solve")
        assert not solve.success and solve.message
        save = suite.call("/lidarcal_calibrator/save")
        assert not save.success and save.message.startswith("no estimate yet")
        assert len(suite.probe.estimates) == estimates  # nothing new was published
    finally:
        suite.set_parameters("lidarcal_calibrator", checkpoint_file="")


# ---------------------------------------------------------------------------- convergence
@dataclass
class Outputs:
    """What a calibrator of its own topics publishes, as a probe subscribed before it
    started receives it (:meth:`subscribe`)."""

    estimates: list[Any] = field(default_factory=list)
    yamls: list[tuple[float, str]] = field(default_factory=list)  # (wall time, text)
    diagnostics: dict[str, dict[str, str]] = field(default_factory=dict)

    def subscribe(self, node: Any, prefix: str) -> None:
        """Estimate, YAML and diagnostics on ``{prefix}/estimate``, ``/yaml``,
        ``/diagnostics``."""
        from diagnostic_msgs.msg import DiagnosticArray
        from std_msgs.msg import Float64MultiArray, String

        from lidarcal_ros.nodes.topics import latched_qos

        node.create_subscription(Float64MultiArray, f"{prefix}/estimate",
                                 self.estimates.append, latched_qos())
        node.create_subscription(String, f"{prefix}/yaml", lambda m: self.yamls.append(
            (time.monotonic(), m.data)), latched_qos())
        node.create_subscription(DiagnosticArray, f"{prefix}/diagnostics",
                                 lambda m: self.diagnostics.update(
                                     {s.name: {kv.key: kv.value for kv in s.values}
                                      for s in m.status}), 100)

    def latest(self) -> dict[str, Any] | None:
        """The latest calibration received (the YAML's document), None before any."""
        if not self.yamls:
            return None
        return dict(yaml.safe_load(self.yamls[-1][1])["lidarcal_calibration"])

    def converged_over(self, pairs: set[tuple[int, int]]) -> bool:
        """Whether the latest calibration is converged over exactly the strip ``pairs``."""
        doc = self.latest()
        return doc is not None and bool(doc["converged"]) and {
            (int(a), int(b)) for a, b in (p["strips"] for p in doc["strip_pairs"])} == pairs


def _remapped(prefix: str) -> list[str]:
    """``-r`` rules that move a calibrator's topics under ``prefix``, away from the suite's
    (the input ones first)."""
    topics = {"/lidar/points": "points", "/lidar/trajectory": "trajectory",
              "/lidar/control_points": "control_points",
              "/lidar/calibration/estimate": "estimate", "/lidar/calibration/yaml": "yaml",
              "/diagnostics": "diagnostics"}
    return [arg for topic, name in topics.items() for arg in ("-r", f"{topic}:={prefix}/{name}")]


def _check_offline(values: dict[str, float], offline: Any, what: str) -> None:
    """Every estimated parameter of ``values`` within 0.1 sigma of the ``offline`` solution."""
    for i, name in enumerate(PARAMETER_NAMES):
        if name in offline.estimated:
            off = abs(values[name] - offline.delta[i]) / offline.sigma[i]
            assert off <= 0.1, f"{what}: {name} {off:.2f} sigma from lidarcal calibrate"


def _pairs(result: Any) -> set[tuple[int, int]]:
    return {(p.strip_a, p.strip_b) for p in result.pairs}


def _checkpoint_state(path: Path) -> tuple[int, bool, list[int]]:
    """Normal-equation count, converged, strips closed, of a checkpoint file."""
    with np.load(path) as data:
        return (int(data["neq_count"]), bool(data["converged"]),
                sorted(int(i) for i in data["closed_ids"]))


def _stop(procs: list[subprocess.Popen[str]]) -> None:
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


class _LiveCalibrator:
    """``lidarcal run --nodes flight_config,calibrator`` in a child process, under its own
    namespace and topics (``prefix``), with a probe node of this process subscribed to its
    outputs (:class:`Outputs`) before it starts; on leaving, stopped, and its exit status
    checked (its log written to ``log``)."""

    def __init__(self, ros_context: Any, params: Path, prefix: str, log: Path) -> None:
        self.ros_context, self.params, self.prefix, self.log = ros_context, params, prefix, log
        self.remap = _remapped(prefix)
        self.outputs = Outputs()
        self.procs: list[subprocess.Popen[str]] = []

    def __enter__(self) -> _LiveCalibrator:
        import rclpy

        self.node = rclpy.create_node(f"{self.prefix.strip('/')}_probe",
                                      context=self.ros_context)
        self.outputs.subscribe(self.node, self.prefix)
        self.spinner = Spinner(self.ros_context, [self.node])
        with self.log.open("w") as err:  # (a file: a pipe nobody reads would fill and block)
            # Its own namespace: the calibrator follows the flight configuration started
            # with it, not the suite's.
            self.procs.append(subprocess.Popen(
                [PYTHON, "-m", "lidarcal_ros", "run", "--nodes", "flight_config,calibrator",
                 "--ros-args", "--params-file", str(self.params), "-r",
                 f"__ns:={self.prefix}", *self.remap], env=dict(os.environ),
                stdout=subprocess.DEVNULL, stderr=err, text=True))
        return self

    def __exit__(self, *exc: object) -> None:
        _stop(self.procs)
        self.spinner.stop()
        self.node.destroy_node()
        if exc[0] is None:
            assert self.procs[0].returncode == 0, self.log_text()[-2000:]

    def log_text(self) -> str:
        return self.log.read_text()


def test_lidarcal_run_fed_by_a_replay_converges_without_a_service_call(
        ros_context: Any, mission_factory: Any, tmp_path: Path) -> None:
    """The issue's new user: ``lidarcal run`` (flight configuration and calibrator, its
    parameters file as ``--ros-args --params-file``) fed by ``lidarcal replay`` of a mission
    of another seed than the suite's, never asked to solve. After the last strip the latched
    estimate and YAML say converged and are ``lidarcal calibrate``'s on the same bag within
    0.1 sigma, and so is the calibration ``~/save`` writes. A misspelt key of the file is
    named in one warning line, the nodes' own keys are not."""
    from lidarcal_ros.io.calibration_file import read_calibration

    mission = mission_factory(**CRABBED, seed=11)
    saved = tmp_path / "saved.yaml"
    params = helpers_missions.write_params_file(tmp_path / "params.yaml", {
        **FAST, "calibration.control_points_file": str(mission.control_csv),
        "calibration.calibration_file": str(saved), "idle_close_s": 0.5, "lookahead": False,
        "qa.rmsdz_warn": 0.05})  # (misspelt: qa.rmsdz_warn_m)
    config = FlightConfig.from_mapping({**FAST, "calibration.control_points_file":
                                        str(mission.control_csv)})
    offline = calibrate_mission(load_mission(mission.bag, config), config)
    assert offline.converged
    prefix = "/converged"
    with _LiveCalibrator(ros_context, params, prefix, tmp_path / "run.log") as live:
        outputs, node = live.outputs, live.node
        _replay(mission.bag, "--ros-args", *live.remap[:6])
        replayed_at = time.monotonic()
        _wait(lambda: outputs.converged_over(_pairs(offline)), 120,
              "a converged estimate over every strip pair")
        converged_at = outputs.yamls[-1][0]
        doc = outputs.latest()
        assert doc is not None
        # The quick update of the last strip came first, not converged.
        first = next(yaml.safe_load(text)["lidarcal_calibration"] for _, text in outputs.yamls
                     if len(yaml.safe_load(text)["lidarcal_calibration"]["strip_pairs"])
                     == len(offline.pairs))
        assert not first["converged"]
        print(f"converged latched estimate {converged_at - replayed_at:.1f} s after the "
              f"replay ended ({doc['iterations']} iterations)")
        values = {n: float(doc["biases"][n]["value"]) for n in PARAMETER_NAMES}
        _check_offline(values, offline.solution, "latched YAML")
        _wait(lambda: bool(outputs.estimates) and parse_estimate(
            outputs.estimates[-1].data, [d.label for d in outputs.estimates[-1].layout.dim]
        ).values == values, 10, "the estimate message of the same calibration")
        said = [parse_estimate(m.data, [d.label for d in m.layout.dim]).converged
                for m in outputs.estimates]
        assert said[-1] is True and False in said  # (each quick update's: not converged)
        latched = outputs.estimates[-1]
        estimate = parse_estimate(latched.data, [d.label for d in latched.layout.dim])
        for i, name in enumerate(PARAMETER_NAMES):
            if name in offline.solution.estimated:
                sigma = estimate.sigmas[name]
                assert sigma == pytest.approx(offline.solution.sigma[i], rel=0.05), name
        _wait(lambda: outputs.diagnostics.get("lidarcal: convergence", {}).get("refining")
              == "false", 10, "the convergence status")
        assert outputs.diagnostics["lidarcal: convergence"]["converged"] == "True"
        # ~/save: the same calibration, converged, in the file
        from std_srvs.srv import Trigger

        client: Client[Any, Any] = node.create_client(Trigger,
                                                      f"{prefix}/lidarcal_calibrator/save")
        assert client.wait_for_service(timeout_sec=10)
        future = client.call_async(Trigger.Request())
        _wait(future.done, 60, "~/save")
        response = future.result()
        assert response is not None and response.success, response
        assert str(saved) in response.message and "NOT converged" not in response.message
        record = read_calibration(saved)
        assert yaml.safe_load(saved.read_text())["lidarcal_calibration"]["converged"] is True
        assert record.values == values
        _check_offline(record.values, offline.solution, "saved calibration")
        assert outputs.yamls[-1][0] == converged_at  # nothing published since
    warnings = [ln for ln in live.log_text().splitlines() if "(misspelt?)" in ln]
    assert len(warnings) == 1 and warnings[0].endswith("(misspelt?): qa.rmsdz_warn"), warnings


def test_the_live_calibrator_runs_the_rigorous_model_from_the_poses_attitude(
        ros_context: Any, mission_factory: Any, tmp_path: Path) -> None:
    """A mission flown in rough air (roll, pitch, heading wobble and crab, the INS attitude
    on the PoseStamped poses at 50 Hz), replayed into ``lidarcal run``: every strip gets
    the rigorous model from the orientations on the topic, says so on ``/diagnostics`` and
    in the latched calibration, and the converged estimate is ``lidarcal calibrate``'s on
    the same bag within 0.1 sigma."""
    from lidarcal_ros.core.simulation.flight_path import RoughAir, crosswind_for_crab

    mission = mission_factory(seed=13, rough_air=RoughAir(),
                              wind_mps=crosswind_for_crab(5.0, 60.0))
    params = helpers_missions.write_params_file(tmp_path / "params.yaml", {
        **FAST, "calibration.control_points_file": str(mission.control_csv),
        "calibration.calibration_file": str(tmp_path / "rigorous.yaml"), "idle_close_s": 0.5})
    config = FlightConfig.from_mapping({**FAST, "calibration.control_points_file":
                                        str(mission.control_csv)})
    offline = calibrate_mission(load_mission(mission.bag, config), config)
    assert {c.model for c in offline.models.values()} == {"rigorous"}
    with _LiveCalibrator(ros_context, params, "/rigorous", tmp_path / "run.log") as live:
        _replay(mission.bag, "--ros-args", *live.remap[:6])
        _wait(lambda: live.outputs.converged_over(_pairs(offline)), 120,
              "a converged estimate over every strip pair")
        doc = live.outputs.latest()
        assert doc is not None and doc["model"] == "rigorous"
        assert {s["model"] for s in doc["strips"]} == {"rigorous"}
        _check_offline({n: float(doc["biases"][n]["value"]) for n in PARAMETER_NAMES},
                       offline.solution, "latched YAML")
        _wait(lambda: live.outputs.diagnostics.get("lidarcal: geometry", {}).get("model")
              == "rigorous (INS attitude at 50 Hz) for every strip", 10,
              "the model on /diagnostics")


def test_calibrator_killed_mid_replay_resumes_from_its_checkpoint(
        ros_context: Any, small_mission: Any, tmp_path: Path) -> None:
    """Killed (SIGKILL) after three strips, the calibrator restarted from its checkpoint
    holds them, converges again without being asked and publishes ``lidarcal calibrate``'s
    estimate of those strips; fed the rest of the mission, the whole mission's, and its
    checkpoints say whether converged."""
    import rclpy

    params = tmp_path / "params.yaml"
    helpers_missions.write_params_file(params, {
        **FAST, "calibration.control_points_file": str(small_mission.control_csv),
        "idle_close_s": 0.5, "checkpoint_file": str(tmp_path / "ckpt.npz")},
        section="/**")
    ckpt = tmp_path / "ckpt.npz"
    # Own names, so that the suite of this module (still running) does not interfere.
    remap = ["-r", "__node:=ckpt_calibrator", *_remapped("/ckpt")]
    cmd = [PYTHON, "-m", "lidarcal_ros.nodes.calibrator", "--ros-args", "--params-file",
           str(params), *remap]
    replay_remap = ["--ros-args", *remap[2:8]]
    spans = [helpers_missions.strip_span(small_mission.mission, k) for k in (3, 4)]
    with open_bag(small_mission.bag) as b:
        start_s = b.start_ns / 1e9
    cut = (spans[0][1] + spans[1][0]) / 2 - start_s  # between strips 3 and 4
    config = FlightConfig.from_mapping({**FAST, "calibration.control_points_file":
                                        str(small_mission.control_csv)})
    mission = load_mission(small_mission.bag, config)
    first_three = calibrate_mission(helpers_missions.subset(mission, [1, 2, 3]), config)
    whole = calibrate_mission(mission, config)
    node = rclpy.create_node("ckpt_probe", context=ros_context)
    outputs = Outputs()
    outputs.subscribe(node, "/ckpt")
    diag = outputs.diagnostics
    spinner = Spinner(ros_context, [node])
    procs: list[subprocess.Popen[str]] = []
    try:
        procs.append(subprocess.Popen(cmd, env=dict(os.environ), stdout=subprocess.DEVNULL,
                                      stderr=subprocess.PIPE, text=True))
        _replay(small_mission.bag, "--duration", f"{cut:.3f}", *replay_remap)
        _wait(lambda: ckpt.is_file() and _checkpoint_state(ckpt)[2] == [1, 2, 3], 60,
              "a checkpoint with strips 1-3")
        count = _checkpoint_state(ckpt)[0]
        assert count > 0
        procs[0].send_signal(signal.SIGKILL)
        procs[0].wait(timeout=10)
        diag.clear()
        outputs.yamls.clear()
        procs.append(subprocess.Popen(cmd, env=dict(os.environ), stdout=subprocess.DEVNULL,
                                      stderr=subprocess.PIPE, text=True))
        _wait(lambda: "lidarcal: state" in diag, 30, "the restarted calibrator")
        assert diag["lidarcal: state"]["resumed_from"] == str(ckpt)
        assert diag["lidarcal: memory"]["strips"] == "1,2,3"
        # converged again from the checkpoint, without a service call: the estimate of
        # strips 1-3, and the checkpoint says converged
        _wait(lambda: outputs.converged_over(_pairs(first_three)), 60,
              "the restarted calibrator's converged estimate")
        doc = outputs.latest()
        assert doc is not None
        _check_offline({n: float(doc["biases"][n]["value"]) for n in PARAMETER_NAMES},
                       first_three.solution, "resumed, strips 1-3")
        _wait(lambda: _checkpoint_state(ckpt)[1:] == (True, [1, 2, 3]), 30,
              "a converged checkpoint")
        # the rest of the mission: the whole mission's estimate, without a service call
        _replay(small_mission.bag, "--start", f"{cut:.3f}", *replay_remap)
        _wait(lambda: outputs.converged_over(_pairs(whole)), 120,
              "the converged estimate of strips 1-6")
        doc = outputs.latest()
        assert doc is not None
        _check_offline({n: float(doc["biases"][n]["value"]) for n in PARAMETER_NAMES},
                       whole.solution, "resumed, strips 1-6")
        _wait(lambda: _checkpoint_state(ckpt)[1:] == (True, [1, 2, 3, 4, 5, 6]), 30,
              "the checkpoint")
        assert _checkpoint_state(ckpt)[0] > count
    finally:
        _stop(procs)
        spinner.stop()
        node.destroy_node()
    assert procs[-1].returncode == 0, procs[-1].stderr.read() if procs[-1].stderr else ""


def test_a_flight_config_change_shows_only_once_the_node_has_applied_it(
        ros_context: Any) -> None:
    # Whoever sees the new value (another thread; the node following the flight-config node)
    # may rely on its effect: a listener still applying it must not be overtaken.
    import rclpy
    from rclpy.parameter import Parameter

    from lidarcal_ros.nodes.parameters import FlightParameters

    node = rclpy.create_node("apply_order_probe", context=ros_context)
    try:
        params = FlightParameters(node, follow=False)
        applied: list[float] = []
        seen_before_applied: list[float] = []

        def slow_listener(cfg: Any, changed: set[str]) -> None:
            time.sleep(0.3)
            applied.append(cfg["atmosphere.visibility_km"])

        params.on_change(slow_listener)

        def watch() -> None:
            deadline = time.monotonic() + 5
            while time.monotonic() < deadline:
                if params["atmosphere.visibility_km"] == 7.0:
                    if not applied:
                        seen_before_applied.append(7.0)
                    return
                time.sleep(0.001)

        watcher = threading.Thread(target=watch)
        watcher.start()
        result = node.set_parameters([Parameter("atmosphere.visibility_km", value=7.0)])
        watcher.join()
        assert result[0].successful
        assert applied == [7.0]
        assert params["atmosphere.visibility_km"] == 7.0
        assert not seen_before_applied
    finally:
        node.destroy_node()


def test_shared_memory_can_be_turned_off_or_refused_with_a_reason(ros_context: Any) -> None:
    """``shared_memory_mib:=0`` sends clouds through pipes (diagnostics say so); a negative
    size is refused at start with the parameter's name."""
    from rclpy.parameter import Parameter

    from lidarcal_ros.errors import ConfigError
    from lidarcal_ros.nodes.corrector import CorrectorNode

    node = CorrectorNode(context=ros_context, node_name="lidarcal_corrector_pipes",
                         parameter_overrides=[Parameter("shared_memory_mib", value=0)])
    try:
        runner = node.correction.runner
        assert isinstance(runner, CorrectionProcess)
        assert node.status().values["transport"] == "pipes"
        assert runner.ring_paths == []
    finally:
        node.close()
        node.destroy_node()
    with pytest.raises((ConfigError, ValueError), match="shared_memory_mib"):
        CorrectorNode(context=ros_context, node_name="lidarcal_corrector_bad",
                      parameter_overrides=[Parameter("shared_memory_mib", value=-1)])
