"""The calibrator on a driver's clouds in the sensor's frame at the driver's rate (issue 33).

    . /work/shared/ros-env.sh; .venv/bin/python bench/bench_sensor_live.py
    .venv/bin/python bench/bench_sensor_live.py --columns 1024 --lines 3 --rate 1

A simulated UAV payload (``os1-32`` by default: 32 beams at 10 Hz; 2048 columns give an
OS1-32's ~0.65M points/s, fewer a lighter run) is written as ``ros2 bag record`` writes it and
replayed by ``lidarcal replay --rate`` into a calibrator node in this process. Per cloud: when
the node's subscription had it (decoded, queued) and when its worker had taken it in (the
feed held it, the lines it settled handed on, the calibration updated where it was due).
Printed: the driver's rate (points per second of the bag's time, times ``--rate``), the
worker's processing rate (points over the seconds its work on clouds and poses took) and their
ratio (above 1: it keeps up), the latency from arrival to being taken in (median, 95th
percentile, most), and the ratio of the processing rate to an OS1-32's 0.65M points/s.
"""

from __future__ import annotations

import argparse
import math
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import machine  # bench/machine.py: this script's folder is on sys.path
import numpy as np

from lidarcal_ros.core.simulation.uav_payload import UavPayloadSpec, simulate_uav_payload
from lidarcal_ros.pipeline.calibration.sensor_frame import write_uav_simulation

#: An OS1-32's output at 2048 columns and 10 Hz, points/s.
OS1_32_RATE = 0.65e6
PYTHON = sys.executable


def _mounting_text(m: Any) -> str:
    return ",".join(repr(float(v)) for v in (*m.translation, *m.quaternion))


class _Timed:
    """Wrap the calibrator's service: arrival and intake of every cloud, the worker's busy
    seconds (clouds and poses)."""

    def __init__(self, service: Any) -> None:
        self.arrived: list[float] = []
        self.taken: list[float] = []
        self.points = 0
        self.busy_s = 0.0
        self.lock = threading.Lock()
        add, run, poses = service.add_sensor_cloud, service._run, service._add_poses

        def add_sensor_cloud(xyz: Any, t: Any, frame_id: str) -> None:
            with self.lock:
                self.arrived.append(time.perf_counter())
            add(xyz, t, frame_id)

        def timed_run(job: Any) -> Any:
            started = time.perf_counter()
            try:
                return run(job)
            finally:
                done = time.perf_counter()
                name = type(job).__name__
                if name in ("AddSensorCloud", "_Idle"):
                    self.busy_s += done - started
                if name == "AddSensorCloud":
                    self.taken.append(done)
                    self.points += len(job.t)

        def timed_poses(batch: Any) -> None:
            started = time.perf_counter()
            try:
                poses(batch)
            finally:
                self.busy_s += time.perf_counter() - started

        service.add_sensor_cloud = add_sensor_cloud
        service._run = timed_run
        service._add_poses = timed_poses


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Simulate, replay into the calibrator, and measure (module docstring)."""
    import rclpy
    from rclpy.executors import MultiThreadedExecutor
    from rclpy.parameter import Parameter

    from lidarcal_ros.nodes.calibrator import CalibratorNode

    started = time.perf_counter()
    mission = simulate_uav_payload(UavPayloadSpec(layout=args.layout, seed=args.seed,
                                                  columns=args.columns, n_lines=args.lines,
                                                  line_length_m=args.line_length))
    work = Path(tempfile.mkdtemp(prefix="bench_sensor_live_"))
    paths = write_uav_simulation(work / "uav", mission)
    clouds = mission.clouds
    bag_s = float(clouds.stamps[-1] - clouds.stamps[0]) + 0.1
    n_points = int(clouds.offsets[-1])
    driver_rate = n_points / bag_s * args.rate
    print(f"payload: {args.layout}, {args.columns or 'all'} columns, {args.lines} lines of "
          f"{args.line_length:g} m: {n_points} points, {len(clouds.stamps)} clouds over "
          f"{bag_s:.1f} s (simulated in {time.perf_counter() - started:.0f} s)")
    context = rclpy.Context()
    rclpy.init(context=context)
    values = {"topics.points": "/velodyne_points", "topics.trajectory": "/ins/odometry",
              "trajectory_type": "nav_msgs/msg/Odometry",
              "sensor_frame.mounting": _mounting_text(mission.nominal)}
    node = CalibratorNode(context=context, node_name="bench_sensor_calibrator",
                          parameter_overrides=[Parameter(k, value=v)
                                               for k, v in values.items()])
    timed = _Timed(node.calibration)
    executor = MultiThreadedExecutor(num_threads=2, context=context)
    executor.add_node(node)
    # (spin(), not a loop of spin_once(): that may run a ready callback twice)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    held = 0
    try:
        replay = subprocess.Popen(
            [PYTHON, "-m", "lidarcal_ros", "replay", str(paths["bag"]), "--rate",
             str(args.rate), "--topics", "/velodyne_points", "/ins/odometry",
             "--wait-for-subscribers", "20"], stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE, text=True)
        while replay.poll() is None:
            feed = node.calibration.sensor
            held = max(held, feed.pending_points)
            if args.verbose:
                print(f"held {feed.pending_points} handed to {feed.horizon:.1f} "
                      f"poses to {feed._fed_t:.1f} lines {len(feed.lines)}", flush=True)
            time.sleep(0.1 if not args.verbose else 1.0)
        replay_end = time.perf_counter()
        deadline = replay_end + 120.0
        while time.perf_counter() < deadline and (
                len(timed.taken) < len(timed.arrived) or node.calibration.queued_jobs):
            time.sleep(0.05)
        drained_s = time.perf_counter() - replay_end
    finally:
        executor.shutdown(timeout_sec=5)
        spinner.join(timeout=10)
        node.close()
        node.destroy_node()
        rclpy.shutdown(context=context)
    if replay.returncode:
        raise SystemExit(f"replay failed: {replay.stderr.read() if replay.stderr else ''}")
    n = min(len(timed.arrived), len(timed.taken))
    latency = np.array(timed.taken[:n]) - np.array(timed.arrived[:n])
    processing = timed.points / timed.busy_s if timed.busy_s > 0 else math.inf
    return {"clouds_sent": len(clouds.stamps), "clouds_received": len(timed.arrived),
            "clouds_taken": len(timed.taken), "points_taken": timed.points,
            "driver_rate": driver_rate, "processing_rate": processing,
            "ratio": processing / driver_rate, "ratio_os1_32": processing / OS1_32_RATE,
            "latency_ms": [float(np.percentile(latency, q)) * 1e3 for q in (50, 95, 100)]
            if n else [math.nan] * 3,
            "drained_after_replay_s": drained_s, "held_at_most": held,
            "lines": len(node.calibration.sensor.lines)}


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print its figures."""
    p = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    p.add_argument("--layout", default="os1-32", choices=("os1-32", "vlp16"))
    p.add_argument("--columns", type=int, default=512,
                   help="firings per revolution (2048: an OS1-32's 0.65M points/s)")
    p.add_argument("--lines", type=int, default=2)
    p.add_argument("--line-length", type=float, default=80.0, help="m")
    p.add_argument("--rate", type=float, default=1.0, help="lidarcal replay --rate")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--verbose", action="store_true", help="the feed's state every second")
    args = p.parse_args(argv)
    print("machine:", machine.describe())
    out = run(args)
    p50, p95, most = out["latency_ms"]
    print(f"clouds: {out['clouds_sent']} sent, {out['clouds_received']} received, "
          f"{out['clouds_taken']} taken in ({out['points_taken']} points); "
          f"{out['lines']} lines closed; at most {out['held_at_most']} points held by the feed")
    print(f"driver's rate {out['driver_rate'] / 1e3:.0f}k points/s (replay --rate "
          f"{args.rate:g}); processing rate {out['processing_rate'] / 1e3:.0f}k points/s: "
          f"ratio {out['ratio']:.1f} to the driver's rate, {out['ratio_os1_32']:.2f} to an "
          f"OS1-32's 0.65M points/s")
    print(f"latency from arrival to intake: median {p50:.1f} ms, 95th percentile "
          f"{p95:.1f} ms, most {most:.1f} ms; all taken in {out['drained_after_replay_s']:.2f} "
          "s after the replay ended")
    print("load average after:", f"{__import__('os').getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
