"""Hostile live input over loopback DDS: a stream with a malformed cloud every few messages,
and set-parameters calls with nan, inf and values out of range.

A calibrator and a corrector (each in this process, spun in a background thread) receive a
replay of the small mission in which every third cloud is replaced by a malformed one (a
``point_step`` smaller than its fields, a cloud without its time field, data shorter than its
width says), in turn. Both must keep running, count on ``/diagnostics`` exactly the malformed
clouds sent, and correct (the corrector) or take in (the calibrator) every good one. Then
nan, inf and values out of range set on each node's parameters are refused with a reason
naming the parameter, and the node keeps its value.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import helpers_missions
import pytest
from helpers_wait import wait_until

from lidarcal_ros.io.bag.format import POINTCLOUD2, standard_typestore
from lidarcal_ros.io.bag.reader import open_bag
from lidarcal_ros.io.bag.writer import BagWriter
from lidarcal_ros.io.cloud.messages import parse_cloud

mission_factory = helpers_missions.mission_factory
small_mission = helpers_missions.small_mission

#: The malformed clouds sent in turn, each in place of every third cloud.
MALFORMED = ("point_step", "no time field", "truncated")


def _spoilt(raw: bytes, how: str) -> bytes:
    """A good cloud's CDR made malformed ``how``."""
    store = standard_typestore()
    msg: Any = store.deserialize_cdr(raw, POINTCLOUD2)
    if how == "point_step":  # the fields reach past the step
        msg.point_step = 8
        msg.row_step = msg.width * 8
        msg.data = msg.data[: msg.width * 8]
    elif how == "no time field":
        msg.fields = [f for f in msg.fields if f.name != "t"]
    else:  # the data ends short of width x point_step
        msg.data = msg.data[: len(msg.data) - msg.point_step - 5]
    return bytes(store.serialize_cdr(msg, POINTCLOUD2))


@dataclass
class Stream:
    """The spoilt bag and what it holds."""

    bag: Path
    good: int
    malformed: dict[str, int] = field(default_factory=dict)
    good_points: int = 0


@pytest.fixture(scope="module")
def stream(small_mission: Any, tmp_path_factory: pytest.TempPathFactory) -> Stream:
    out = tmp_path_factory.mktemp("hostile") / "spoilt.mcap"
    result = Stream(out, 0)
    with open_bag(small_mission.bag) as src, BagWriter(out) as writer:
        k = 0
        for topic, msgtype, ns, raw in src.messages():
            if topic == "/lidar/points":
                k += 1
                if k % 3 == 0:
                    how = MALFORMED[(k // 3) % len(MALFORMED)]
                    result.malformed[how] = result.malformed.get(how, 0) + 1
                    raw = _spoilt(bytes(raw), how)
                else:
                    result.good += 1
                    result.good_points += len(parse_cloud(raw))
            writer.write_raw(topic, msgtype, ns, raw)
    assert set(result.malformed) == set(MALFORMED)
    return result


@dataclass
class Nodes:
    cal: Any
    cor: Any
    probe: Any
    corrected: list[bytes]
    diagnostics: dict[str, Any]
    lock: threading.Lock


@pytest.fixture(scope="module")
def nodes(ros_context: Any, small_mission: Any) -> Iterator[Nodes]:
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import MultiThreadedExecutor
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import PointCloud2

    from lidarcal_ros.nodes.calibrator import CalibratorNode
    from lidarcal_ros.nodes.corrector import CorrectorNode

    overrides = [Parameter(k, value=v) for k, v in helpers_missions.FAST_SETTINGS.items()]
    # Names of their own: the suite of test_nodes.py runs nodes of the default names next,
    # in the same process and domain, and must not meet these in the DDS graph.
    cal = CalibratorNode(context=ros_context, node_name="hostile_calibrator", parameter_overrides=[
        *overrides, Parameter("idle_close_s", value=0.5)])
    cor = CorrectorNode(context=ros_context, node_name="hostile_corrector", parameter_overrides=[
        *overrides, Parameter("separate_process", value=False)])
    probe = rclpy.create_node("hostile_probe", context=ros_context)
    lock = threading.Lock()
    got = Nodes(cal, cor, probe, [], {}, lock)

    def on_corrected(raw: bytes) -> None:
        with lock:
            got.corrected.append(raw)

    def on_diagnostics(msg: Any) -> None:
        with lock:
            for s in msg.status:
                got.diagnostics[s.name] = (s.message, {kv.key: kv.value for kv in s.values})

    probe.create_subscription(PointCloud2, "/lidar/points_corrected", on_corrected, 1000,
                              raw=True)
    probe.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 100)
    executor = MultiThreadedExecutor(num_threads=4, context=ros_context)
    for n in (cal, cor, probe):
        executor.add_node(n)
    stop = threading.Event()
    errors: list[BaseException] = []

    def spin() -> None:
        while not stop.is_set():
            try:
                executor.spin_once(timeout_sec=0.05)
            except Exception as exc:  # a callback failed: the test fails at the end
                errors.append(exc)

    thread = threading.Thread(target=spin, daemon=True)
    thread.start()
    try:
        yield got
    finally:
        stop.set()
        thread.join(timeout=10)
        executor.shutdown(timeout_sec=5)
        for n in (cal, cor):
            n.close()
        for n in (probe, cal, cor):
            n.destroy_node()
        assert not errors, errors


@pytest.fixture(scope="module")
def replayed(nodes: Nodes, stream: Stream) -> Nodes:
    res = subprocess.run(
        [sys.executable, "-m", "lidarcal_ros", "replay", str(stream.bag), "--rate", "25",
         "--wait-for-subscribers", "20", "--min-subscribers", "2"],
        env=dict(os.environ), capture_output=True, text=True, timeout=120, check=False)
    assert res.returncode == 0, res.stderr
    return nodes


def test_malformed_clouds_are_counted_and_the_good_ones_go_through(replayed: Nodes,
                                                                  stream: Stream) -> None:
    n = replayed
    sent = sum(stream.malformed.values())

    def counted() -> bool:
        with n.lock:
            cor = n.diagnostics.get("lidarcal: corrector", ("", {}))[1]
            inp = n.diagnostics.get("lidarcal: input", ("", {}))[1]
        return (cor.get("skipped_clouds") == str(sent) and inp.get("skipped_clouds") == str(sent)
                and cor.get("clouds_out") == str(stream.good))

    wait_until(counted, 60, f"{sent} malformed clouds counted and {stream.good} corrected "
               f"on /diagnostics (seen: {n.diagnostics})")
    with n.lock:
        corrected = list(n.corrected)
        cor_message, cor = n.diagnostics["lidarcal: corrector"]
        inp_message, inp = n.diagnostics["lidarcal: input"]
    # every good cloud out, corrected, with all its points; nothing of a malformed one
    assert len(corrected) == stream.good
    assert sum(len(parse_cloud(raw)) for raw in corrected) == stream.good_points
    assert cor["clouds_in"] == str(stream.good)  # (a malformed one is no cloud)
    assert cor["points_out"] == str(stream.good_points)
    assert f"{sent} malformed clouds skipped" in cor_message
    # the calibrator took in every good cloud, its points all
    assert inp["clouds"] == str(stream.good) and inp["points"] == str(stream.good_points)
    assert f"{sent} malformed clouds skipped" in inp_message
    assert n.cal.calibration.stream.n_points > 0  # (held for the calibration)


def _float_parameters(node: Any) -> dict[str, Any]:
    """The node's numeric parameters that may be set (name: value)."""
    from rcl_interfaces.msg import ParameterType

    out = {}
    for name in node.list_parameters([], 0).names:
        descriptor = node.describe_parameter(name)
        if descriptor.read_only:
            continue
        if descriptor.type in (ParameterType.PARAMETER_DOUBLE, ParameterType.PARAMETER_INTEGER):
            out[name] = node.get_parameter(name).value
    return out


@pytest.mark.parametrize("which", ["cal", "cor"])
def test_nan_inf_and_out_of_range_are_refused_naming_the_parameter(nodes: Nodes,
                                                                  which: str) -> None:
    """Every numeric parameter a node lets be set, through the node's set_parameters: nan,
    +-inf (floats), and for each a value beyond its declared range; refused, the reason
    naming the parameter, the value kept (the node's and the parameter's)."""
    from rclpy.parameter import Parameter

    node = nodes.cal if which == "cal" else nodes.cor
    numbers = _float_parameters(node)
    assert len(numbers) > 20
    tried = 0
    for name, old in numbers.items():
        descriptor = node.describe_parameter(name)
        bad: list[Any] = []
        if isinstance(old, float):
            bad += [math.nan, math.inf, -math.inf]
        for r in (*descriptor.floating_point_range, *descriptor.integer_range):
            if r.to_value < (2**62 if isinstance(old, int) else 1e300):
                bad.append(type(old)(r.to_value * 2 + 1))
            if r.from_value > -(2**62):
                bad.append(type(old)(r.from_value - abs(r.from_value) - 1))
        for value in bad:
            (result,) = node.set_parameters([Parameter(name, value=value)])
            assert not result.successful, (name, value)
            assert name in result.reason, (name, value, result.reason)
            assert node.get_parameter(name).value == old or (
                isinstance(old, float) and math.isnan(old))
            assert node.params[name] == old, (name, value)
            tried += 1
    assert tried > 40


@pytest.mark.parametrize(("node_name", "name", "value"), [
    ("hostile_calibrator", "idle_close_s", math.nan),
    ("hostile_calibrator", "strip_gap_s", math.inf),
    ("hostile_corrector", "max_trajectory_wait_s", -math.inf),
    ("hostile_corrector", "max_backlog_mib", 1 << 30),
])
def test_a_refused_value_over_the_parameter_service(nodes: Nodes, node_name: str, name: str,
                                                    value: Any) -> None:
    """The same through the nodes' set_parameters service, as ``ros2 param set`` calls it:
    the response says why, naming the parameter; the node's value unchanged."""
    from rclpy.parameter import Parameter
    from rclpy.parameter_client import AsyncParameterClient

    node = nodes.cal if node_name == "hostile_calibrator" else nodes.cor
    old = node.params[name]
    client = AsyncParameterClient(nodes.probe, node_name)
    assert client.wait_for_services(timeout_sec=10.0)
    future = client.set_parameters([Parameter(name, value=value)])
    wait_until(future.done, 10.0, f"set_parameters on {node_name}")
    response = future.result()
    assert response is not None
    (result,) = response.results
    assert not result.successful and name in result.reason, result.reason
    assert node.params[name] == old and node.get_parameter(name).value == old
