"""Benchmark of the ROS 2 nodes over loopback DDS (bench/README.md, "Nodes").

    .venv/bin/python bench/bench_nodes.py                    # everything (~8 min)
    .venv/bin/python bench/bench_nodes.py --only codec,corrector
    .venv/bin/python bench/bench_nodes.py --rates 0.25,0.5,1,2,4 --seconds 10
    .venv/bin/python bench/bench_nodes.py --only corrector --variants raw,relay --rates 3,4 \
        --repeats 3                                          # the 4 M/s goal, ~10 min

Sections (every figure measured in this run; the typed-rclpy path is measured beside the raw
CDR path under the same load):

codec      per-chunk cost of getting a PointCloud2 in and out of Python: raw CDR (rosbags
           ``deserialize_cdr`` view, :func:`lidarcal_ros.io.cloud.messages.cloud_cdr`) against
           rclpy's typed messages (``deserialize_message`` + ``np.frombuffer``, building a
           ``sensor_msgs.msg.PointCloud2`` + ``serialize_message``), no DDS.
corrector  sustained throughput of ``lidarcal_corrector`` through DDS: a source process offers
           synthetic chunks at a given point rate (trajectory ahead of them), the corrector runs
           in its own process, the benchmark process receives the corrected chunks. Per offered
           rate: points/s out, latency per chunk (source publish -> corrected chunk received;
           header stamps carry the publish wall time) p50/p99, and the latency trend (last third
           minus first third: growth = backlog). Once with the node's raw path, once with a
           typed-rclpy variant of the same node (typed subscription and publisher); the
           ``relay`` variant, a bare node that takes each cloud and publishes one of the
           corrected layout without correcting, measures the floor DDS sets under it. With
           both ``raw`` and ``relay``, a summary per rate: their CPU per point, its ratio
           run by run, and the goal (GOAL_NS_PER_POINT, GOAL_RELAY_RATIO, the p99, no
           chunk lost); ``--repeats`` runs the variants in turn that many times.
calibrator-rate (only when asked for) ``lidarcal_calibrator`` alone fed the corrector's
           synthetic stream at each offered rate with ``calibration.thinning_cell_m``
           (``--calibrator-thinning``): whether its intake keeps up (the queue of clouds
           waiting for its worker, from ``/diagnostics``), its CPU and what it holds.
calibrator ``lidarcal run`` (separate processes) fed ``lidarcal replay bags/paper_sample --rate
           10``: when each strip's estimate appears relative to the end of the strip in the
           replay, and the lag of the last estimate behind the end of the replay.
memory     resident memory of the calibrator and corrector processes (with their child
           processes) over a looped replay of the sample mission (``--loop``), sampled every
           second.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import statistics
import struct
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

BENCH = Path(__file__).resolve().parent
ROOT = BENCH.parent
PYTHON = sys.executable
SAMPLE_BAG = ROOT / "bags" / "paper_sample"
SAMPLE_CONTROL = ROOT / "bags" / "paper_sample_control.csv"

GOAL_POINTS_PER_S = 4.0e6
GOAL_P99_S = 0.100
#: The corrector's whole CPU per point (node and correction processes, steady state): at most
#: this, and at most GOAL_RELAY_RATIO times that of the relay (the same DDS traffic without
#: the correction) measured in the same run.
GOAL_NS_PER_POINT = 200.0
GOAL_RELAY_RATIO = 2.5

#: Synthetic stream: aircraft at 1000 m along +y at 60 m/s; flat ground; swath +-400 m.
SPEED = 60.0
HEIGHT = 1000.0
SWATH = 400.0
TRAJ_HZ = 200.0


# ---------------------------------------------------------------------------- synthetic data
def synthetic_chunk(k: int, n: int, dt: float, t0: float, rng: np.random.Generator) -> np.ndarray:
    """Chunk ``k`` of ``n`` points covering mission time ``[t0 + k dt, t0 + (k+1) dt)``."""
    from lidarcal_ros.io.cloud.pointcloud import make_point_dtype

    pts = np.zeros(n, dtype=make_point_dtype())
    t = t0 + (k + np.sort(rng.random(n))) * dt
    pts["t"] = t
    # a zig-zag scanner: across-track position from the mirror phase
    phase = (t * 70.0) % 2.0
    across = SWATH * (np.abs(phase - 1.0) * 2.0 - 1.0)
    pts["x"] = across
    pts["y"] = SPEED * (t - t0) + rng.normal(0, 0.3, n)
    pts["z"] = rng.normal(0.0, 0.05, n) + 0.01 * across
    pts["intensity"] = rng.uniform(20, 200, n).astype(np.float32)
    pts["strip_id"] = 1
    return pts


#: ``--attitude``: what orientation the source's poses carry. ``none``: the identity (no
#: orientation, the positions' track gives the heading); ``heading``: a level attitude along
#: the track (a heading only: the level model with the INS heading); ``ins``: a few hundredths
#: of a radian of roll and pitch besides (the rigorous model).
ATTITUDES = ("none", "heading", "ins")


def pose_quaternion(t: float, attitude: str) -> tuple[float, float, float, float]:
    """The orientation ``(x, y, z, w)`` of the source's pose at time ``t`` (``ATTITUDES``):
    REP-103's body (x forward) heading along +y, the synthetic flight line."""
    if attitude == "none":
        return 0.0, 0.0, 0.0, 1.0
    roll = pitch = 0.0
    if attitude == "ins":
        roll = 0.02 * math.sin(2.0 * math.pi * 0.3 * (t - T0))
        pitch = 0.01 * math.sin(2.0 * math.pi * 0.2 * (t - T0))
    cy, sy = math.cos(math.pi / 4.0), math.sin(math.pi / 4.0)  # yaw pi/2: along +y
    cp, sp = math.cos(pitch / 2.0), math.sin(pitch / 2.0)
    cr, sr = math.cos(roll / 2.0), math.sin(roll / 2.0)
    return (sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy, cr * cp * cy + sr * sp * sy)


def pose_cdr(t: float, attitude: str = "none") -> bytes:
    """The CDR of the synthetic source's ``PoseStamped`` at time ``t`` (s): map frame, along +y
    at the flight speed and height, oriented as ``attitude`` says (``ATTITUDES``)."""
    from lidarcal_ros.io.cloud.messages import serialize, typestore

    types = typestore().types
    qx, qy, qz, qw = pose_quaternion(t, attitude)
    sec, nsec = divmod(round(t * 1e9), 1_000_000_000)
    msg = types["geometry_msgs/msg/PoseStamped"](
        header=types["std_msgs/msg/Header"](
            stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id="map"),
        pose=types["geometry_msgs/msg/Pose"](
            position=types["geometry_msgs/msg/Point"](x=0.0, y=SPEED * (t - T0), z=HEIGHT),
            orientation=types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw)))
    return serialize(msg, "geometry_msgs/msg/PoseStamped")


T0 = 1.7e9


def _source_main(argv: list[str]) -> int:
    """Child process: publish synthetic chunks at ``rate`` points/s for ``seconds`` (poses with
    ``attitude``, ``history`` seconds of them before the first chunk)."""
    rate, points, seconds, topic = float(argv[0]), int(argv[1]), float(argv[2]), argv[3]
    attitude = argv[4] if len(argv) > 4 else "none"
    history = float(argv[5]) if len(argv) > 5 else 0.0
    from lidarcal_ros.ros.environment import configure_ros_environment

    configure_ros_environment()
    import rclpy
    from geometry_msgs.msg import PoseStamped

    from lidarcal_ros.core.allocator import tune_allocator

    tune_allocator(single_arena=False)  # as every lidarcal process that talks to DDS
    from rclpy.context import Context
    from sensor_msgs.msg import PointCloud2

    from lidarcal_ros.io.cloud.messages import cloud_cdr
    from lidarcal_ros.nodes.topics import stream_qos

    ctx = Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node("bench_source", context=ctx)
    pub = node.create_publisher(PointCloud2, topic, stream_qos(200))
    traj = node.create_publisher(PoseStamped, "/lidar/trajectory", stream_qos(10000))
    dt = points / rate
    n_chunks = max(int(seconds / dt), 1)
    rng = np.random.default_rng(0)
    # Four chunks serialised once (cycled); each publication patches the header stamp and
    # the times and along-track positions in place, as a driver writing its message buffer
    # would, so that the source's own CPU (on the same two cores as the corrector) goes to
    # publishing, not to building messages in numpy.
    templates = [synthetic_chunk(k, points, dt, 0.0, rng) for k in range(4)]
    buffers = [bytearray(cloud_cdr(0, "map", pts)) for pts in templates]
    itemsize = templates[0].dtype.itemsize
    views = [np.frombuffer(buf, dtype=templates[0].dtype, count=points,
                           offset=len(buf) - 1 - points * itemsize) for buf in buffers]
    for buf in buffers:  # the copy each publication makes, once before the clock starts
        bytes(buf)
    deadline = time.monotonic() + 20
    while (pub.get_subscription_count() < 1 or traj.get_subscription_count() < 1) and \
            time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(1.0)
    # A flight under way: the trajectory of the last ``history`` seconds first (in bursts,
    # so that the subscriber's queue takes them all).
    for k in range(-round(history * TRAJ_HZ), 0):
        traj.publish(pose_cdr(T0 + k / TRAJ_HZ, attitude))
        if k % 1000 == 0:
            time.sleep(0.05)
    if history:
        time.sleep(2.0)
    next_pose = 0.0
    # the trajectory covers the first chunks before they are sent
    while next_pose < 2 * dt + 0.5:
        traj.publish(pose_cdr(T0 + next_pose, attitude))
        next_pose += 1.0 / TRAJ_HZ
    start = time.monotonic()
    for k in range(n_chunks):
        target = start + k * dt
        now = time.monotonic()
        if target > now:
            time.sleep(target - now)
        while next_pose < (k + 2) * dt + 0.5:
            traj.publish(pose_cdr(T0 + next_pose, attitude))
            next_pose += 1.0 / TRAJ_HZ
        j = k % 4
        shift = (k - j) * dt
        np.add(templates[j]["t"], T0 + shift, out=views[j]["t"])
        np.add(templates[j]["y"], SPEED * shift, out=views[j]["y"])
        buffers[j][4:12] = struct.pack("<iI", *divmod(time.time_ns(), 1_000_000_000))
        pub.publish(bytes(buffers[j]))
    print(json.dumps({"chunks": n_chunks, "seconds": time.monotonic() - start}), flush=True)
    time.sleep(1.0)
    node.destroy_node()
    ctx.try_shutdown()
    return 0


# ---------------------------------------------------------------------------- typed corrector
def _typed_corrector_main(argv: list[str]) -> int:
    """Child process: the corrector with rclpy's typed PointCloud2 in and out (the message
    objects are converted to and from the CDR bytes the correction takes and gives)."""
    from lidarcal_ros.ros.environment import configure_ros_environment

    configure_ros_environment()
    from rclpy.parameter import Parameter
    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import PointCloud2

    from lidarcal_ros.nodes import corrector as mod
    from lidarcal_ros.nodes.process import run_main
    from lidarcal_ros.nodes.topics import stream_qos

    class TypedCorrector(mod.CorrectorNode):
        def __init__(self, *, context: Any = None) -> None:
            super().__init__(context=context, parameter_overrides=[
                Parameter("topics.points", value="/bench/unused"),
                Parameter("topics.corrected", value="/bench/unused_out")])
            self.typed_pub = self.create_publisher(PointCloud2, "/lidar/points_corrected",
                                                   stream_qos(1000))
            self.create_subscription(PointCloud2, "/lidar/points", self._on_typed,
                                     stream_qos(1000))

        def _on_typed(self, msg: PointCloud2) -> None:
            self.correction.add_cloud(serialize_message(msg))

        def publish_corrected(self, cdr: bytes | memoryview) -> None:
            self.typed_pub.publish(deserialize_message(bytes(cdr), PointCloud2))

    return run_main([TypedCorrector], ["bench_typed_corrector"], threads=1)


def _relay_main(argv: list[str]) -> int:
    """Child process: the corrector's DDS traffic without the correction. Takes each cloud
    raw off ``/lidar/points`` (and the trajectory, as the node does) and publishes, with the
    cloud's header stamp, a message of the corrected layout and the same width: the floor
    that taking and publishing alone set under the corrector on this machine. It publishes
    as a plain rclpy node does, a ``bytes`` built for each cloud; with ``direct`` (variant
    ``relay-direct``) it hands rcl its buffer as the corrector does
    (:class:`~lidarcal_ros.nodes.serialized_publisher.SerializedPublisher`)."""
    direct = bool(argv) and argv[0] == "direct"
    from lidarcal_ros.ros.environment import configure_ros_environment

    configure_ros_environment()
    from geometry_msgs.msg import PoseStamped
    from rclpy.node import Node
    from sensor_msgs.msg import PointCloud2

    from lidarcal_ros.core.allocator import tune_allocator
    from lidarcal_ros.io.cloud.messages import cloud_cdr
    from lidarcal_ros.io.cloud.pointcloud import make_point_dtype
    from lidarcal_ros.nodes.process import run_main
    from lidarcal_ros.nodes.serialized_publisher import SerializedPublisher
    from lidarcal_ros.nodes.topics import stream_qos
    from lidarcal_ros.pipeline.correction.corrected_cloud import corrected_dtype

    tune_allocator(single_arena=False)  # as the corrector's node process
    layout = corrected_dtype(make_point_dtype())

    class Relay(Node):
        def __init__(self, *, context: Any = None) -> None:
            super().__init__("bench_relay", context=context)
            self.templates: dict[int, bytearray] = {}
            self.pub = self.create_publisher(PointCloud2, "/lidar/points_corrected",
                                             stream_qos(1000))
            self.direct = SerializedPublisher(self.pub) if direct else None
            self.create_subscription(PointCloud2, "/lidar/points", self._on_cloud,
                                     stream_qos(1000), raw=True)
            self.create_subscription(PoseStamped, "/lidar/trajectory", lambda raw: None,
                                     stream_qos(10000), raw=True)

        def _on_cloud(self, raw: bytes) -> None:
            flen = struct.unpack_from("<I", raw, 12)[0]
            off = 16 + flen
            off += (-(off - 4)) % 4
            width = struct.unpack_from("<I", raw, off + 4)[0]
            out = self.templates.get(width)
            if out is None:
                out = self.templates[width] = bytearray(
                    cloud_cdr(0, "map", np.zeros(width, dtype=layout)))
            out[4:12] = raw[4:12]  # the input's stamp: the latency is measured from it
            if self.direct is not None:
                self.direct.publish(out)
            else:
                self.pub.publish(bytes(out))  # the message built, as a node must build it

    return run_main([Relay], ["bench_relay"], threads=1)


# ---------------------------------------------------------------------------- helpers
def _goal_verdict(keeps_up: bool, p99: float, p99_steady: float) -> str:
    """How a run stands against the p99 goal: over the whole run, start included, or only
    from the first second on (the start of a stream left a queue)."""
    if not keeps_up:
        return ""
    if p99 <= GOAL_P99_S:
        return ", p99 goal met (whole run)"
    if p99_steady <= GOAL_P99_S:
        return ", p99 goal met after the first second"
    return ", p99 goal missed"


def _env() -> dict[str, str]:
    from lidarcal_ros.ros.environment import configure_ros_environment

    env = dict(os.environ)
    configure_ros_environment(env)
    return env


def _stop(proc: subprocess.Popen[Any], timeout: float = 20.0) -> int:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            return proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
    return proc.wait()


def _process_tree(pid: int) -> list[int]:
    """A process and its descendants (the corrector's correction runs in a child process)."""
    tree, todo = [], [pid]
    while todo:
        p = todo.pop()
        tree.append(p)
        try:
            for task in Path(f"/proc/{p}/task").iterdir():
                todo.extend(int(c) for c in (task / "children").read_text().split())
        except OSError:
            pass
    return tree


def _proc_sum_mib(pid: int, name: str, key: str) -> float:
    """A memory figure (``key``, kB) of ``/proc/PID/name`` summed over a process and its
    descendants, in MiB (NaN if none could be read)."""
    total, seen = 0.0, False
    for p in _process_tree(pid):
        try:
            for line in Path(f"/proc/{p}/{name}").read_text().splitlines():
                if line.startswith(key):
                    total += int(line.split()[1]) / 1024.0
                    seen = True
        except OSError:
            pass
    return total if seen else math.nan


def _rss_mib(pid: int) -> float:
    """Resident memory (MiB) of a process and its descendants (the sum of their resident
    sets: pages they share count once per process)."""
    return _proc_sum_mib(pid, "status", "VmRSS:")


def _pss_mib(pid: int) -> float:
    """Proportional set size (MiB) of a process and its descendants: resident memory with
    pages shared between them counted once (shared memory, libraries), unlike the sum of
    their resident sets."""
    return _proc_sum_mib(pid, "smaps_rollup", "Pss:")


def _cpu_s(pid: int) -> tuple[float, float]:
    """CPU time (user + system, s) used so far by a process, and by its live descendants."""
    own = others = 0.0
    for p in _process_tree(pid):
        try:
            fields = Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()
            used = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
        except (OSError, IndexError, ValueError):
            continue
        if p == pid:
            own += used
        else:
            others += used
    return own, others


def _machine_busy_s() -> float:
    """CPU seconds all cores of the machine have spent busy so far (``/proc/stat``: every
    column but idle and iowait), or NaN where that file is not."""
    try:
        fields = [int(v) for v in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    except (OSError, ValueError):
        return math.nan
    return (sum(fields[:8]) - fields[3] - fields[4]) / os.sysconf("SC_CLK_TCK")


class CpuSampler:
    """Samples the CPU time of a process and its descendants every ``period`` s (wall time,
    own, descendants, the whole machine's busy time), so that the steady state can be told
    from start-up."""

    def __init__(self, pid: int, period: float = 0.2) -> None:
        self.pid = pid
        self.samples: list[tuple[float, float, float, float]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(period,), daemon=True)
        self._thread.start()

    def _run(self, period: float) -> None:
        while not self._stop.is_set():
            self.samples.append((time.time(), *_cpu_s(self.pid), _machine_busy_s()))
            self._stop.wait(period)

    def stop(self) -> None:
        """Stop sampling and wait for the sampling thread."""
        self._stop.set()
        self._thread.join()

    def usage(self, t0: float, t1: float) -> tuple[float, float, float, float]:
        """CPU seconds of the process, of its descendants and of the whole machine between
        the samples nearest ``t0`` and ``t1``, and the wall time between those samples."""
        if len(self.samples) < 2:
            return math.nan, math.nan, math.nan, math.nan
        times = np.array([x[0] for x in self.samples])
        a = int(np.argmin(np.abs(times - t0)))
        b = int(np.argmin(np.abs(times - t1)))
        if b <= a:
            return math.nan, math.nan, math.nan, math.nan
        first, last = self.samples[a], self.samples[b]
        return last[1] - first[1], last[2] - first[2], last[3] - first[3], last[0] - first[0]


class Receiver:
    """Counts corrected chunks in the benchmark process (raw CDR, header only)."""

    def __init__(self, context: Any) -> None:
        import rclpy
        from sensor_msgs.msg import PointCloud2

        from lidarcal_ros.nodes.topics import stream_qos

        self.node = rclpy.create_node("bench_sink", context=context)
        self.samples: list[tuple[float, float, int]] = []  # (recv wall, latency, points)
        self.node.create_subscription(PointCloud2, "/lidar/points_corrected", self._on,
                                      stream_qos(1000), raw=True)

    def _on(self, raw: bytes) -> None:
        now = time.time_ns()
        sec, nsec = np.frombuffer(raw, dtype="<i4", count=2, offset=4)
        stamp = int(sec) * 1_000_000_000 + int(np.uint32(nsec))
        # width: after the frame id string
        flen = int(np.frombuffer(raw, dtype="<u4", count=1, offset=12)[0])
        off = 16 + flen
        off += (-(off - 4)) % 4
        width = int(np.frombuffer(raw, dtype="<u4", count=1, offset=off + 4)[0])
        self.samples.append((now / 1e9, (now - stamp) / 1e9, width))


def _spin_in_thread(context: Any, nodes: list[Any]) -> tuple[threading.Event, threading.Thread,
                                                              Any]:
    from rclpy.executors import SingleThreadedExecutor

    ex = SingleThreadedExecutor(context=context)
    for n in nodes:
        ex.add_node(n)
    stop = threading.Event()

    def spin() -> None:
        while not stop.is_set():
            ex.spin_once(timeout_sec=0.05)

    th = threading.Thread(target=spin, daemon=True)
    th.start()
    return stop, th, ex


# ---------------------------------------------------------------------------- codec
def bench_codec(points: int, repeats: int) -> dict[str, Any]:
    """The codec section: median seconds per chunk of ``points`` points of each way in (raw CDR,
    typed rclpy) and out, with the bytes in and out; no DDS."""
    from lidarcal_ros.ros.environment import configure_ros_environment

    configure_ros_environment()
    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import PointCloud2, PointField

    from lidarcal_ros.io.cloud.messages import cloud_cdr, parse_cloud
    from lidarcal_ros.io.cloud.pointcloud import array_to_cloud_parts, cloud_to_array
    from lidarcal_ros.pipeline.correction.corrected_cloud import corrected_dtype

    rng = np.random.default_rng(1)
    pts = synthetic_chunk(0, points, 0.05, T0, rng)
    out_dtype = corrected_dtype(pts.dtype)
    out = np.zeros(points, dtype=out_dtype)
    raw = cloud_cdr(1, "map", pts)

    def raw_in() -> None:
        c = parse_cloud(raw)
        c.points["x"].sum()

    def typed_in() -> None:
        m = deserialize_message(raw, PointCloud2)
        cloud_to_array(m)["x"].sum()

    def raw_out() -> None:
        cloud_cdr(1, "map", out)

    def typed_out() -> None:
        fields, step, data = array_to_cloud_parts(out)
        m = PointCloud2()
        m.header.frame_id = "map"
        m.height, m.width = 1, len(out)
        m.fields = [PointField(name=n, offset=o, datatype=d, count=c) for n, o, d, c in fields]
        m.point_step, m.row_step = step, step * len(out)
        m.data = data.tobytes()
        serialize_message(m)

    res: dict[str, Any] = {"points": points, "bytes_in": len(raw),
                           "bytes_out": points * out_dtype.itemsize}
    for name, fn in (("raw_in", raw_in), ("typed_in", typed_in), ("raw_out", raw_out),
                     ("typed_out", typed_out)):
        fn()
        times = []
        for _ in range(repeats):
            t = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t)
        res[name] = statistics.median(times)
    return res


# ---------------------------------------------------------------------------- corrector
def bench_corrector(rates: list[float], seconds: float, chunk_s: float, variant: str,
                    context: Any, attitude: str = "none", history: float = 0.0
                    ) -> list[dict[str, Any]]:
    """The corrector section for one ``variant``: per offered rate (points/s), the rate out, the
    chunk latencies (s), the CPU per point (ns) and whether the node keeps up."""
    results = []
    env = _env()
    typed = variant == "typed"
    cmd = ([PYTHON, str(Path(__file__)), "_typed_corrector"] if typed else
           [PYTHON, "-m", "lidarcal_ros.nodes.corrector"])
    if variant in ("relay", "relay-direct"):
        cmd = [PYTHON, str(Path(__file__)), "_relay"] + (["direct"] if
                                                         variant == "relay-direct" else [])
    elif variant == "raw-lookahead":
        cmd += ["--ros-args", "-p", "lookahead:=true"]
    elif variant == "raw-2workers":
        cmd += ["--ros-args", "-p", "workers:=2"]
    elif variant == "raw-thread":
        cmd += ["--ros-args", "-p", "separate_process:=false"]
    for rate in rates:
        points = max(int(rate * chunk_s), 100)
        log_path = Path(tempfile.gettempdir()) / f"bench_corrector_{os.getpid()}.log"
        log = open(log_path, "wb")
        corrector = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT)
        receiver = Receiver(context)
        stop, th, ex = _spin_in_thread(context, [receiver.node])
        try:
            time.sleep(2.0)
            sampler = CpuSampler(corrector.pid)
            source = subprocess.run(
                [PYTHON, str(Path(__file__)), "_source", str(rate), str(points), str(seconds),
                 "/lidar/points", attitude, str(history)], env=env, capture_output=True,
                text=True, timeout=seconds + 120 + history / 10.0)
            sent = json.loads(source.stdout.strip().splitlines()[-1]) if \
                source.returncode == 0 else {"chunks": 0, "seconds": math.nan}
            # let the corrector drain (bounded)
            deadline = time.monotonic() + 30
            while len(receiver.samples) < sent["chunks"] and time.monotonic() < deadline:
                time.sleep(0.1)
            sampler.stop()
            rss = _rss_mib(corrector.pid)
        finally:
            stop.set()
            th.join()
            ex.shutdown()
            receiver.node.destroy_node()
            _stop(corrector)
            log.close()
        if len(receiver.samples) != sent["chunks"]:
            errors = [line for line in log_path.read_text(errors="replace").splitlines()
                      if "ERROR" in line or "WARN" in line]
            print(f"  ({len(errors)} warnings/errors from the corrector; the last: "
                  f"{errors[-3:]})", flush=True)
        log_path.unlink(missing_ok=True)
        s = receiver.samples
        if len(s) >= 3:
            recv = np.array([x[0] for x in s])
            lat = np.array([x[1] for x in s])
            n_pts = np.array([x[2] for x in s])
            span = recv[-1] - recv[0]
            thirds = np.array_split(lat, 3)
            out_rate = float(n_pts[1:].sum() / span) if span > 0 else math.nan
            growth = float(np.median(thirds[-1]) - np.median(thirds[0]))
            p50, p99 = (float(v) for v in np.percentile(lat, [50, 99]))
            # Steady state: after the first second of output (the start of a stream pays
            # once for the first grid rows, first allocations and discovery).
            steady = lat[recv - recv[0] > 1.0]
            p99_steady = float(np.percentile(steady, 99)) if steady.size else math.nan
            # Once any start-up backlog is worked off: the second half of the output.
            p99_late = float(np.percentile(lat[len(lat) // 2:], 99))
            first = float(lat[0])
            # CPU of the corrector (node process, correction process) in the steady state:
            # from one second after the first corrected chunk to the last.
            node_cpu, child_cpu, machine_cpu, wall = sampler.usage(recv[0] + 1.0, recv[-1])
            steady_points = int(n_pts[(recv > recv[0] + 1.0)].sum())
        else:
            out_rate = growth = p50 = p99 = p99_steady = p99_late = first = math.nan
            node_cpu = child_cpu = machine_cpu = wall = math.nan
            steady_points = 0
        results.append({
            "path": variant, "offered_pts_s": rate, "chunk_points": points,
            "chunks_sent": sent["chunks"], "chunks_received": len(s),
            "out_pts_s": out_rate, "latency_p50_s": p50, "latency_p99_s": p99,
            "latency_growth_s": growth, "corrector_rss_mib": rss,
            "latency_p99_steady_s": p99_steady, "latency_p99_second_half_s": p99_late,
            "first_chunk_latency_s": first,
            "latencies_s": [round(x[1], 4) for x in s],  # per chunk, in order received
            "node_cpu_share": node_cpu / wall, "correction_cpu_share": child_cpu / wall,
            "machine_busy_share": machine_cpu / wall / (os.cpu_count() or 1),
            "corrector_ns_per_point": 1e9 * (node_cpu + child_cpu) / max(steady_points, 1),
        })
        keeps_up = (len(s) == sent["chunks"] and out_rate >= 0.95 * rate
                    and growth < 0.05)
        results[-1]["keeps_up"] = keeps_up
        results[-1]["load_avg"] = os.getloadavg()[0]
        print(f"  {variant:15} offered {rate / 1e6:5.2f} M/s ({points} pts/chunk): "
              f"out {out_rate / 1e6:5.2f} M/s, {len(s)}/{sent['chunks']} chunks, "
              f"p50 {p50 * 1000:7.1f} ms, p99 {p99 * 1000:7.1f} ms (after 1 s "
              f"{p99_steady * 1000:7.1f} ms, second half {p99_late * 1000:7.1f} ms; first chunk "
              f"{first * 1000:5.0f} ms), "
              f"growth {growth * 1000:+7.1f} ms; CPU node {node_cpu / wall:4.0%} + "
              f"correction {child_cpu / wall:4.0%} = "
              f"{results[-1]['corrector_ns_per_point']:.0f} ns/point, machine "
              f"{results[-1]['machine_busy_share']:.0%} busy: "
              f"{'keeps up' if keeps_up else 'falls behind'}"
              f"{_goal_verdict(keeps_up, p99, p99_steady)}",
              flush=True)
    return results


def summarize_against_relay(runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The corrector as shipped (``raw``) against the relay at each offered rate: CPU per
    point of each run, their ratio run by run (the n-th corrector run with the n-th relay
    run of the same rate: measured minutes apart, under the same load), and the goals
    (:data:`GOAL_NS_PER_POINT`, :data:`GOAL_RELAY_RATIO`, the p99 after the first second,
    every chunk out), which are those of a 4 MHz sensor (:data:`GOAL_POINTS_PER_S`): at
    another rate the same tests are printed for comparison. Printed, and returned for
    ``--json``."""
    rows = []
    for rate in sorted({r["offered_pts_s"] for r in runs}):
        raw = [r for r in runs if r["path"] == "raw" and r["offered_pts_s"] == rate]
        relay = [r for r in runs if r["path"] == "relay" and r["offered_pts_s"] == rate]
        if not raw or not relay:
            continue
        raw_ns = [r["corrector_ns_per_point"] for r in raw]
        relay_ns = [r["corrector_ns_per_point"] for r in relay]
        ratios = [a / b for a, b in zip(raw_ns, relay_ns)]
        p99 = [r["latency_p99_steady_s"] for r in raw]
        chunks = (sum(r["chunks_received"] for r in raw), sum(r["chunks_sent"] for r in raw))
        median_ns, median_ratio = statistics.median(raw_ns), statistics.median(ratios)
        met = (all(r["keeps_up"] for r in raw) and chunks[0] == chunks[1]
               and max(p99) <= GOAL_P99_S and median_ns <= GOAL_NS_PER_POINT
               and median_ratio <= GOAL_RELAY_RATIO)
        if rate == GOAL_POINTS_PER_S:
            verdict = "goal met" if met else "goal missed"
        else:
            verdict = (f"{'within' if met else 'outside'} the goal's bounds (for comparison: "
                       f"the goal is at {GOAL_POINTS_PER_S / 1e6:g} M/s)")
        row = {"offered_pts_s": rate, "corrector_ns_per_point": raw_ns,
               "relay_ns_per_point": relay_ns, "ratio": ratios, "p99_steady_s": p99,
               "chunks": chunks, "load_avg": [r["load_avg"] for r in raw + relay],
               "goal_met": met, "goal_rate": rate == GOAL_POINTS_PER_S}
        rows.append(row)

        def spread(values: list[float], fmt: str) -> str:
            text = ", ".join(format(v, fmt) for v in values)
            return f"median {statistics.median(values):{fmt}}" + (
                f" (min {min(values):{fmt}}; runs {text})" if len(values) > 1 else "")

        print(f"  {rate / 1e6:5.2f} M/s: corrector {spread(raw_ns, '.0f')} ns/point, relay "
              f"{spread(relay_ns, '.0f')} ns/point; ratio {spread(ratios, '.2f')}; p99 after "
              f"1 s at most {max(p99) * 1000:.0f} ms; {chunks[0]}/{chunks[1]} chunks out; "
              f"1-min load {min(row['load_avg']):.1f}-{max(row['load_avg']):.1f}: "
              f"{verdict}", flush=True)
        direct = [r["corrector_ns_per_point"] for r in runs
                  if r["path"] == "relay-direct" and r["offered_pts_s"] == rate]
        if direct:  # (not the goal's floor: the relay publishing as the corrector does)
            row["relay_direct_ns_per_point"] = direct
            print(f"  {'':10} relay-direct {spread(direct, '.0f')} ns/point; the corrector "
                  f"{statistics.median(raw_ns) / statistics.median(direct):.2f}x its median",
                  flush=True)
    return rows


def bench_transport(rate: float, seconds: float, chunk_s: float,
                    context: Any) -> dict[str, Any]:
    """The source publishing straight to the receiver: what DDS alone costs."""
    points = max(int(rate * chunk_s), 100)
    receiver = Receiver(context)
    stop, th, ex = _spin_in_thread(context, [receiver.node])
    try:
        source = subprocess.run(
            [PYTHON, str(Path(__file__)), "_source", str(rate), str(points), str(seconds),
             "/lidar/points_corrected"], env=_env(), capture_output=True, text=True,
            timeout=seconds + 120)
        sent = json.loads(source.stdout.strip().splitlines()[-1])
        time.sleep(1.0)
    finally:
        stop.set()
        th.join()
        ex.shutdown()
        receiver.node.destroy_node()
    s = receiver.samples
    recv = np.array([x[0] for x in s])
    lat = np.array([x[1] for x in s])
    n_pts = np.array([x[2] for x in s])
    span = recv[-1] - recv[0] if len(s) > 1 else math.nan
    p50, p99 = (float(v) for v in np.percentile(lat, [50, 99])) if len(s) else (math.nan,) * 2
    return {"offered_pts_s": rate, "chunk_points": points, "chunks_sent": sent["chunks"],
            "chunks_received": len(s), "out_pts_s": float(n_pts[1:].sum() / span),
            "latency_p50_s": p50, "latency_p99_s": p99,
            "first_chunk_latency_s": float(lat[0]) if len(s) else math.nan}


# ---------------------------------------------------------------------------- calibrator
def bench_calibrator(rate: float, context: Any) -> dict[str, Any]:
    """The calibrator section: ``lidarcal run`` fed the sample mission replayed at ``rate``; when
    each strip's estimate appears after the strip's end in the replay, and the last estimate's
    lag behind the replay's end (wall s)."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from std_msgs.msg import Float64MultiArray

    from lidarcal_ros.io.bag.reader import open_bag
    from lidarcal_ros.io.cloud.messages import parse_cloud
    from lidarcal_ros.nodes.topics import latched_qos

    env = _env()
    with open_bag(SAMPLE_BAG) as bag:
        start_ns = bag.start_ns
        strip_end: dict[int, float] = {}
        for _t, _m, ns, raw in bag.messages(["/lidar/points"]):
            sid = int(parse_cloud(raw).points["strip_id"][0])
            strip_end[sid] = (ns - start_ns) / 1e9
    node = rclpy.create_node("bench_cal_probe", context=context)
    events: list[tuple[float, str]] = []
    estimates: list[float] = []
    closed: dict[str, float] = {}

    def on_diag(msg: Any) -> None:
        for s in msg.status:
            if s.name == "lidarcal: memory":
                values = {kv.key: kv.value for kv in s.values}
                closed_ids = set(values["strips"].split(",")) - set(
                    values["open_strips"].split(",")) - {""}
                for sid in closed_ids:
                    closed.setdefault(sid, time.monotonic())
            if s.name == "lidarcal: state":
                values = {kv.key: kv.value for kv in s.values}
                events.append((time.monotonic(), values["solves"]))

    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 100)
    node.create_subscription(Float64MultiArray, "/lidar/calibration/estimate",
                             lambda m: estimates.append(time.monotonic()), latched_qos())
    stop, th, ex = _spin_in_thread(context, [node])
    suite = subprocess.Popen([PYTHON, "-m", "lidarcal_ros", "run", "--control",
                              str(SAMPLE_CONTROL), "--ros-args", "-p", "idle_close_s:=1.0"],
                             env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                             text=True)
    try:
        time.sleep(3.0)
        t_start = time.monotonic()
        replay = subprocess.run(
            [PYTHON, "-m", "lidarcal_ros", "replay", str(SAMPLE_BAG), "--rate", str(rate),
             "--wait-for-subscribers", "30", "--min-subscribers", "2"],
            env=env, capture_output=True, text=True, timeout=600)
        t_end = time.monotonic()
        deadline = time.monotonic() + 300
        while len(closed) < len(strip_end) and time.monotonic() < deadline:
            time.sleep(0.1)
        # the estimate after the last strip closed
        time.sleep(0.5)
        while time.monotonic() < deadline and (not estimates or estimates[-1] <
                                               max(closed.values(), default=0)):
            time.sleep(0.1)
        rss = _rss_mib(suite.pid)
    finally:
        stop.set()
        th.join()
        ex.shutdown()
        node.destroy_node()
        _stop(suite)
    wall_per_bag_s = 1.0 / rate
    # replay start: bag time 0 at the first message, after --wait-for-subscribers
    first_pub = t_end - (bag_duration(SAMPLE_BAG) * wall_per_bag_s)
    lags = {sid: closed.get(str(sid), math.nan) - (first_pub + end * wall_per_bag_s)
            for sid, end in strip_end.items()}
    last_estimate_lag = (estimates[-1] - t_end) if estimates else math.nan
    out = {"rate": rate, "replay_wall_s": t_end - t_start, "replay_rc": replay.returncode,
           "strip_closed_lag_s": lags, "estimates": len(estimates),
           "last_estimate_after_replay_end_s": last_estimate_lag,
           "strip_interval_wall_s": float(np.median(np.diff(sorted(strip_end.values()))))
           * wall_per_bag_s, "run_parent_rss_mib": rss}
    return out


def bench_calibrator_rate(rate: float, seconds: float, chunk_s: float, thinning_cell_m: float,
                          context: Any) -> dict[str, Any]:
    """``lidarcal_calibrator`` alone fed the synthetic stream at ``rate`` points/s (one long
    strip, the trajectory ahead of it): whether its intake keeps up (the queue of decoded
    clouds its worker has not yet taken, sampled from ``/diagnostics``), its CPU, the points
    it holds and thins, and how long after the source stops it has taken every cloud."""
    from diagnostic_msgs.msg import DiagnosticArray

    points = max(int(rate * chunk_s), 100)
    samples: list[tuple[float, dict[str, str], dict[str, str]]] = []
    import rclpy

    node = rclpy.create_node("bench_cal_rate_probe", context=context)

    def on_diag(msg: Any) -> None:
        status = {st.name: {kv.key: kv.value for kv in st.values} for st in msg.status}
        if "lidarcal: input" in status and "lidarcal: memory" in status:
            samples.append((time.monotonic(), status["lidarcal: input"],
                            status["lidarcal: memory"]))

    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 100)
    stop, th, ex = _spin_in_thread(context, [node])
    calibrator = subprocess.Popen(
        [PYTHON, "-m", "lidarcal_ros.nodes.calibrator", "--ros-args",
         "-p", f"calibration.thinning_cell_m:={thinning_cell_m}"],
        env=_env(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        time.sleep(2.0)
        sampler = CpuSampler(calibrator.pid)
        t0, wall0 = time.monotonic(), time.time()
        source = subprocess.run(
            [PYTHON, str(Path(__file__)), "_source", str(rate), str(points), str(seconds),
             "/lidar/points"], env=_env(), capture_output=True, text=True,
            timeout=seconds + 120)
        t_end, wall_end = time.monotonic(), time.time()
        sent = json.loads(source.stdout.strip().splitlines()[-1])
        deadline = time.monotonic() + 60
        drained = math.nan
        while time.monotonic() < deadline:
            if samples and int(samples[-1][1]["clouds"]) >= sent["chunks"] and \
                    samples[-1][1]["queued_jobs"] == "0":
                drained = max(samples[-1][0] - t_end, 0.0)  # (0: before the source quit)
                break
            time.sleep(0.05)
        sampler.stop()
        rss = _rss_mib(calibrator.pid)
    finally:
        stop.set()
        th.join()
        ex.shutdown()
        node.destroy_node()
        _stop(calibrator)
    during = [x for x in samples if t0 + 2.0 <= x[0] <= t_end]
    queued = [int(x[1]["queued_jobs"]) for x in during]
    own, children, machine_busy, wall = sampler.usage(wall0 + 2.0, wall_end)
    last = samples[-1] if samples else (0.0, {}, {})
    return {"offered_pts_s": rate, "chunk_points": points, "chunks_sent": sent["chunks"],
            "clouds_taken": int(last[1].get("clouds", 0)),
            "thinning_cell_m": thinning_cell_m,
            "queued_max": max(queued, default=-1), "queued_median":
            float(np.median(queued)) if queued else math.nan,
            "drained_after_end_s": drained, "cpu_share": (own + children) / wall,
            "machine_busy_share": machine_busy / wall / (os.cpu_count() or 1),
            "points_held": int(last[2].get("points_held", 0)),
            "thinned_points": int(last[2].get("thinned_points", 0)),
            "dropped_points": int(last[2].get("dropped_points", 0)), "rss_mib": rss}


def bag_duration(path: Path) -> float:
    """The time from a bag's first message to its last, s."""
    from lidarcal_ros.io.bag.reader import open_bag

    with open_bag(path) as bag:
        return (bag.end_ns - bag.start_ns) / 1e9


# ---------------------------------------------------------------------------- memory
def bench_memory(rate: float, passes: int) -> dict[str, Any]:
    """The memory section: the largest resident memory (MiB) of the calibrator and corrector
    processes in each of ``passes`` passes of the sample mission replayed in a loop at ``rate``."""
    env = _env()
    procs = {name: subprocess.Popen(
        [PYTHON, "-m", f"lidarcal_ros.nodes.{name}", "--ros-args", "-p",
         f"calibration.control_points_file:={SAMPLE_CONTROL}", "-p", "idle_close_s:=1.0"],
        env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        for name in ("calibrator", "corrector")}
    samples: list[tuple[float, float, float, float]] = []
    try:
        time.sleep(3.0)
        length = bag_duration(SAMPLE_BAG) / rate
        replay = subprocess.Popen(
            [PYTHON, "-m", "lidarcal_ros", "replay", str(SAMPLE_BAG), "--rate", str(rate),
             "--loop", "--wait-for-subscribers", "30", "--min-subscribers", "2"],
            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        t0 = time.monotonic()
        while time.monotonic() - t0 < passes * length + 5:
            samples.append((time.monotonic() - t0, _rss_mib(procs["calibrator"].pid),
                            _rss_mib(procs["corrector"].pid), _pss_mib(procs["corrector"].pid)))
            time.sleep(1.0)
        _stop(replay)
    finally:
        for p in procs.values():
            _stop(p)
    per_pass = []
    for k in range(passes):
        sel = [s for s in samples if k * length <= s[0] < (k + 1) * length]
        if sel:
            per_pass.append({"pass": k + 1, "calibrator_max_mib": max(s[1] for s in sel),
                             "corrector_max_mib": max(s[2] for s in sel),
                             "corrector_max_pss_mib": max(s[3] for s in sel)})
    return {"rate": rate, "passes": passes, "pass_wall_s": length, "per_pass": per_pass}


# ---------------------------------------------------------------------------- main
def main() -> int:
    """Run the sections of the command line and print their figures, or be one of the child
    processes the benchmark starts; the exit status."""
    if len(sys.argv) > 1 and sys.argv[1] == "_source":
        return _source_main(sys.argv[2:])
    if len(sys.argv) > 1 and sys.argv[1] == "_typed_corrector":
        return _typed_corrector_main(sys.argv[2:])
    if len(sys.argv) > 1 and sys.argv[1] == "_relay":
        return _relay_main(sys.argv[2:])
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--only", default="codec,transport,corrector,calibrator,memory")
    parser.add_argument("--rates", default="0.25,0.5,1,2,4",
                        help="offered corrector loads, million points/s")
    parser.add_argument("--seconds", type=float, default=8.0, help="per offered load")
    parser.add_argument("--chunk-s", type=float, default=0.05,
                        help="mission time per chunk, s (points per chunk = rate x this)")
    parser.add_argument("--variants", default="raw,relay,raw-lookahead,typed",
                        help="corrector variants: raw (the node as shipped), raw-lookahead "
                        "(lookahead:=true), raw-2workers (workers:=2), raw-thread "
                        "(separate_process:=false: numerics in a thread of the node), typed "
                        "(typed-rclpy PointCloud2 in and out), relay (the node's DDS "
                        "traffic alone: take each cloud, publish one of the corrected "
                        "layout, no correction), relay-direct (the relay publishing as the "
                        "corrector does, rcl given its buffer)")
    parser.add_argument("--attitude", choices=ATTITUDES, default="none",
                        help="orientation of the corrector section's poses: none (the "
                        "identity), heading (level, along the track) or ins (with some roll "
                        "and pitch: the rigorous model)")
    parser.add_argument("--history", type=float, default=0.0,
                        help="seconds of trajectory the corrector section's source publishes "
                        "before its first chunk (a flight under way: the corrector keeps "
                        "trajectory_buffer_s, 600 s, of it)")
    parser.add_argument("--repeats", type=int, default=1,
                        help="runs of the corrector section, its variants in turn each time "
                        "(the summary against the relay gives the median and the spread)")
    parser.add_argument("--calibrator-rate", type=float, default=10.0)
    parser.add_argument("--calibrator-thinning", type=float, default=1.0,
                        help="calibration.thinning_cell_m of the calibrator-rate section, m")
    parser.add_argument("--memory-rate", type=float, default=20.0)
    parser.add_argument("--memory-passes", type=int, default=4)
    parser.add_argument("--dds-profile", type=Path,
                        help="Fast DDS profile for every process (default: the project's "
                        "config/loopback.xml); e.g. a copy without its segment size to see the "
                        "cost of Fast DDS's default 512 KiB shared-memory segment")
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args()
    only = set(args.only.split(","))

    from lidarcal_ros.ros.environment import claim_domain_id, configure_ros_environment

    if args.dds_profile is not None:
        os.environ["FASTDDS_DEFAULT_PROFILES_FILE"] = str(args.dds_profile.resolve())
    if not os.environ.get("ROS_DOMAIN_ID"):
        configure_ros_environment(domain_id=claim_domain_id())
    else:
        configure_ros_environment()
    import rclpy
    from rclpy.context import Context

    from lidarcal_ros.core.allocator import tune_allocator

    # The receiver (this process) stands for a downstream consumer; tuned as the nodes are,
    # it takes a third of the CPU it would otherwise, which the corrector shares.
    tune_allocator(single_arena=False)
    context = Context()
    rclpy.init(context=context)
    import machine  # bench/machine.py: this script's folder is on sys.path

    results: dict[str, Any] = {"cpus": os.cpu_count(), "cpu_model": machine.cpu_model(),
                               "dds_profile": os.environ["FASTDDS_DEFAULT_PROFILES_FILE"],
                               "load_avg_at_start": os.getloadavg(),
                               "machine_speed": machine.memory_speed()}
    print(f"machine: {machine.describe(results['machine_speed'])}", flush=True)
    print(f"bench_nodes: ROS_DOMAIN_ID {os.environ['ROS_DOMAIN_ID']}, DDS profile "
          f"{os.environ['FASTDDS_DEFAULT_PROFILES_FILE']}", flush=True)
    try:
        if "codec" in only:
            print("codec (per chunk, no DDS):", flush=True)
            results["codec"] = []
            for n in (2_000, 200_000):
                r = bench_codec(n, 30 if n < 100_000 else 10)
                results["codec"].append(r)
                print(f"  {n:>7} points: in  raw {r['raw_in'] * 1e3:7.3f} ms  typed "
                      f"{r['typed_in'] * 1e3:7.3f} ms ({r['typed_in'] / r['raw_in']:5.1f}x)   "
                      f"out raw {r['raw_out'] * 1e3:7.3f} ms  typed "
                      f"{r['typed_out'] * 1e3:7.3f} ms ({r['typed_out'] / r['raw_out']:5.1f}x)",
                      flush=True)
        if "transport" in only:
            print("transport only (source -> this process, no corrector):", flush=True)
            results["transport"] = []
            for rate in [float(r) * 1e6 for r in args.rates.split(",")]:
                r = bench_transport(rate, args.seconds, args.chunk_s, context)
                results["transport"].append(r)
                print(f"  offered {rate / 1e6:5.2f} M/s: out {r['out_pts_s'] / 1e6:5.2f} M/s, "
                      f"{r['chunks_received']}/{r['chunks_sent']} chunks, p50 "
                      f"{r['latency_p50_s'] * 1000:6.1f} ms, p99 "
                      f"{r['latency_p99_s'] * 1000:6.1f} ms (first chunk "
                      f"{r['first_chunk_latency_s'] * 1000:5.0f} ms)", flush=True)
        if "corrector" in only:
            rates = [float(r) * 1e6 for r in args.rates.split(",")]
            print(f"corrector through DDS ({args.seconds:g} s per load, chunks of "
                  f"{args.chunk_s * 1000:g} ms):", flush=True)
            results["corrector"] = []
            for repeat in range(max(args.repeats, 1)):
                if args.repeats > 1:
                    print(f" run {repeat + 1} of {args.repeats}:", flush=True)
                for variant in args.variants.split(","):
                    results["corrector"] += bench_corrector(
                        rates, args.seconds, args.chunk_s, variant, context,
                        attitude=args.attitude, history=args.history)
            print(f"corrector against the relay (CPU per point in the steady state, node and "
                  f"correction processes; goal: at most {GOAL_NS_PER_POINT:.0f} ns and "
                  f"{GOAL_RELAY_RATIO:g}x the relay, p99 after the first second at most "
                  f"{GOAL_P99_S * 1000:.0f} ms, every chunk out):", flush=True)
            results["corrector_against_relay"] = summarize_against_relay(results["corrector"])
            if not results["corrector_against_relay"]:
                print("  (needs --variants with both raw and relay)", flush=True)
        if "calibrator-rate" in only:
            print(f"calibrator fed the synthetic stream ({args.seconds:g} s per load, "
                  f"thinning {args.calibrator_thinning:g} m):", flush=True)
            results["calibrator_rate"] = []
            for rate in [float(r) * 1e6 for r in args.rates.split(",")]:
                r = bench_calibrator_rate(rate, args.seconds, args.chunk_s,
                                          args.calibrator_thinning, context)
                results["calibrator_rate"].append(r)
                keeps_up = (r["clouds_taken"] == r["chunks_sent"]
                            and r["drained_after_end_s"] < 2.0)
                print(f"  offered {rate / 1e6:5.2f} M/s: {r['clouds_taken']}/"
                      f"{r['chunks_sent']} clouds taken, queue median "
                      f"{r['queued_median']:.0f} max {r['queued_max']}, drained "
                      f"{r['drained_after_end_s']:.1f} s after the end; CPU "
                      f"{r['cpu_share']:.0%} of a core, machine "
                      f"{r['machine_busy_share']:.0%} busy; holds {r['points_held']} points "
                      f"({r['thinned_points']} thinned, {r['dropped_points']} dropped), "
                      f"{r['rss_mib']:.0f} MiB: {'keeps up' if keeps_up else 'falls behind'}",
                      flush=True)
        if "calibrator" in only:
            print(f"calibrator: sample mission replayed at {args.calibrator_rate:g}x:",
                  flush=True)
            r = bench_calibrator(args.calibrator_rate, context)
            results["calibrator"] = r
            lags = ", ".join(f"{k}: {v:.1f} s" for k, v in sorted(r["strip_closed_lag_s"].items()))
            print(f"  replay {r['replay_wall_s']:.1f} s wall; strip interval "
                  f"{r['strip_interval_wall_s']:.1f} s wall; strip closed + solved after its "
                  f"end: {lags}; last estimate {r['last_estimate_after_replay_end_s']:.1f} s "
                  f"after the replay ended ({r['estimates']} estimates)", flush=True)
        if "memory" in only:
            print(f"memory: looped replay at {args.memory_rate:g}x, {args.memory_passes} "
                  "passes:", flush=True)
            r = bench_memory(args.memory_rate, args.memory_passes)
            results["memory"] = r
            for p in r["per_pass"]:
                print(f"  pass {p['pass']}: calibrator {p['calibrator_max_mib']:.0f} MiB, "
                      f"corrector {p['corrector_max_mib']:.0f} MiB (PSS, shared pages once: "
                      f"{p['corrector_max_pss_mib']:.0f} MiB)", flush=True)
    finally:
        context.try_shutdown()
    results["load_avg_at_end"] = os.getloadavg()
    if args.json:
        args.json.write_text(json.dumps(results, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
