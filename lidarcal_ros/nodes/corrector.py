"""``lidarcal_corrector``: applies the latest estimate and the radiometric model to each chunk.

    ros2 run lidarcal_ros lidarcal_corrector --ros-args --params-file config/flight_config.yaml

Subscribes (raw CDR) to the points (``topics.points``) and the trajectory
(``topics.trajectory``), and to the calibrator's estimate (``/lidar/calibration/estimate``,
transient-local); publishes each chunk corrected on ``topics.corrected`` with every input
field, ``x, y, z`` corrected (method.md eq. [13]) and the FLOAT32 ``reflectance``, ``range``,
``incidence``, ``scan_angle`` plus UINT8 ``correction_flags``
(:mod:`lidarcal_ros.pipeline.correction`). Header stamp and frame are the input's. The
``reflectance`` is the Lambertian reflectance (0-1) when ``radiometry.calibration_constant``
is set, else relative (intensity normalised to ``radiometry.reference_range_m``; intensity
units: :mod:`lidarcal_ros.core.radiometry`); a ``radiometry.reference_target`` needs the
whole mission, so the node does not use it (``lidarcal report`` and ``lidarcal correct`` derive
the constant from it).

A new estimate is used from the next chunk on, without a restart; so are accepted changes of
the flight configuration (atmosphere, radiometry, time field...). Until an estimate arrives the
corrector uses the file named by its ``calibration`` parameter, else the configuration's
``calibration.fixed.*`` values.

Every input point comes out exactly once, in the order received. A chunk is corrected once
the trajectory covers it (a sample past its last point time) or after
``max_trajectory_wait_s``. The normals come from one grid per strip that every chunk's points
join (:class:`~lidarcal_ros.core.strip_normals.StripNormals`): by default (``lookahead`` false) a
chunk is corrected at once, its points seeing the earlier chunks as neighbours; with
``lookahead`` true it waits until the next chunks cover the grid rows beyond it (about three
rows, a few chunks), which gives exactly the normals of ``lidarcal correct`` at that cost in
latency. Held chunks are corrected without look-ahead once no chunk came for
``flush_timeout_s``. A malformed chunk (bad layout, missing field, wrong frame) is logged and
skipped; the node keeps running.

The numerics run in a child process (``separate_process``, :mod:`~lidarcal_ros.pipeline.
correction_service`): this process only takes messages off DDS and publishes, so that its
callbacks (hundreds of trajectory samples a second) never wait for the interpreter lock of
the numerics. The clouds go there and back through shared memory (``shared_memory_mib``;
pipes where a host has none: diagnostics key ``transport``).

Node-specific parameters: ``calibration`` (YAML path), ``queue_depth``, ``best_effort``,
``trajectory_type`` (``auto`` or a type), ``trajectory_buffer_s``, ``max_trajectory_wait_s``,
``flush_timeout_s``, ``lookahead``, ``workers``, ``batch_points``, ``separate_process``,
``shared_memory_mib``.
Diagnostics (``lidarcal: corrector``) report clouds and points in and out, skipped chunks,
points not covered by the trajectory and the latency.
"""

from __future__ import annotations

import math
import sys
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Float64MultiArray

from lidarcal_ros.core.config import CORRECTOR_NODE, NODE_PARAMETERS, FlightConfig
from lidarcal_ros.core.georeferencing import describe_model_policy
from lidarcal_ros.core.heading import describe_heading_policy
from lidarcal_ros.core.params import format_value
from lidarcal_ros.core.trajectory_buffer import TrajectoryBuffer
from lidarcal_ros.errors import LidarcalError
from lidarcal_ros.io.cloud_columns import resolve_time_field, time_span
from lidarcal_ros.io.ros_messages import (
    OK,
    WARN,
    StatusSpec,
    parse_cloud,
    parse_estimate,
    warm_up_cloud_codec,
)
from lidarcal_ros.nodes.parameters import FlightParameters
from lidarcal_ros.nodes.process import run_main
from lidarcal_ros.nodes.topics import (
    DIAGNOSTICS_TOPIC,
    ESTIMATE_TOPIC,
    diagnostic_array,
    latched_qos,
    stream_qos,
)
from lidarcal_ros.nodes.trajectory_input import TrajectoryInput
from lidarcal_ros.pipeline.correction import CorrectionSettings
from lidarcal_ros.pipeline.correction_service import (
    CorrectionProcess,
    LocalCorrection,
    ServiceOptions,
)

EXTRA_PARAMETERS = NODE_PARAMETERS[CORRECTOR_NODE]

_TRAJECTORY_MARGIN_S = 0.02
#: Trajectory samples the node holds for the correction at most: they go with the next
#: cloud, or on their own beyond this (a trajectory without clouds, e.g. on transit to the
#: site, is not kept as Python objects for hours).
_POSES_PER_HANDOVER = 2000
#: Most points handed to the correction at once when a backlog has built up: larger batches
#: only cost cache and memory, and the corrector would fall further behind.
MAX_PUSH_POINTS = 400_000


@dataclass
class _Chunk:
    raw: bytes
    received: float
    size: int = 0  # bytes received (``raw`` is emptied once pushed)
    parsed: bool = False
    n_points: int = 0
    t_max: float = -math.inf


@dataclass
class CorrectorStats:
    """Counts since start (or the last reset)."""

    clouds_in: int = 0
    points_in: int = 0
    clouds_out: int = 0
    points_out: int = 0
    skipped: int = 0
    dropped: int = 0  # clouds dropped from a backlog above max_backlog_mib
    dropped_bytes: int = 0
    last_error: str = ""
    not_corrected: int = 0
    latencies: deque[float] = field(default_factory=lambda: deque(maxlen=10000))
    busy_s: float = 0.0


class CorrectorNode(Node):
    """Corrects point-cloud chunks with the latest estimate (module docstring)."""

    def __init__(self, *, context: Any = None, node_name: str = CORRECTOR_NODE,
                 **kwargs: Any) -> None:
        super().__init__(node_name, context=context, **kwargs)
        self.params = FlightParameters(self, extra=EXTRA_PARAMETERS)
        cfg = self.params.config
        self.stats = CorrectorStats()
        self._lock = threading.Condition()
        self._queue: deque[_Chunk] = deque()
        self._queued_bytes = 0
        self._closing = False
        self.estimate_source = "configuration"
        self._delta = self._initial_delta(cfg)
        self._settings = CorrectionSettings.from_config(cfg, self._delta)
        if cfg["radiometry.reference_target"] and not self._settings.radiometry.absolute:
            self.get_logger().warning(
                "radiometry.reference_target is not used live (it needs the whole mission: "
                "lidarcal report or correct derive radiometry.calibration_constant from it); "
                "reflectance stays relative, in intensity units")
        self._settings_changed = False
        self._lookahead_changed = False
        self._keep_changed = False
        self._segment_checked = False
        self.trajectory = TrajectoryBuffer(self.params["trajectory_buffer_s"])
        self._poses_t: list[float] = []  # samples not yet given to the correction
        self._poses_xyz: list[tuple[float, float, float]] = []
        self._poses_q: list[tuple[float, ...]] = []
        self._held: dict[int, _Chunk] = {}  # pushed, not yet reported back
        self._next_tag = 0
        self._last_push = time.monotonic()
        self._released_tag = -1  # the newest tag at the last time-out release
        self._service = self._start_service()
        warm_up_cloud_codec()

        self.publisher = self.create_publisher(PointCloud2, cfg["topics.corrected"],
                                               stream_qos(self.params["queue_depth"]))
        self.diagnostics = self.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, 10)
        points_group = MutuallyExclusiveCallbackGroup()
        other_group = MutuallyExclusiveCallbackGroup()
        self.create_subscription(
            PointCloud2, cfg["topics.points"], self._on_points,
            stream_qos(self.params["queue_depth"], best_effort=self.params["best_effort"]),
            raw=True, callback_group=points_group)
        self.trajectory_input = TrajectoryInput(
            self, cfg["topics.trajectory"], self.params["trajectory_type"], self._on_pose,
            callback_group=other_group)
        self.create_subscription(Float64MultiArray, ESTIMATE_TOPIC, self._on_estimate,
                                 latched_qos(), callback_group=other_group)
        self.params.on_change(self._on_config)
        self.params.on_extra_change(self._on_extra)
        self.create_timer(1.0, self._publish_diagnostics, callback_group=other_group)
        self._worker = threading.Thread(target=self._work, name="lidarcal-corrector",
                                        daemon=True)
        self._worker.start()
        self.get_logger().info(f"correcting {cfg['topics.points']} -> "
                               f"{cfg['topics.corrected']} (biases from "
                               f"{self.estimate_source})")

    # -- configuration ---------------------------------------------------------------
    def _initial_delta(self, cfg: FlightConfig) -> np.ndarray:
        from lidarcal_ros.core.params import PARAMETER_NAMES
        from lidarcal_ros.io.calibration_file import read_calibration

        path = self.params["calibration"]
        if path:
            record = read_calibration(path)  # ConfigError: a one-line reason at start-up
            self.estimate_source = str(path)
            return record.delta
        return np.array([cfg[f"calibration.fixed.{n}"] for n in PARAMETER_NAMES])

    def _on_config(self, cfg: FlightConfig, changed: set[str]) -> None:
        if self.estimate_source == "configuration":
            from lidarcal_ros.core.params import PARAMETER_NAMES

            self._delta = np.array([cfg[f"calibration.fixed.{n}"] for n in PARAMETER_NAMES])
        with self._lock:
            self._settings = CorrectionSettings.from_config(cfg, self._delta)
            self._settings_changed = True

    def _on_extra(self, name: str, value: Any) -> None:
        if name == "trajectory_buffer_s":
            self.trajectory.keep_s = float(value)
            with self._lock:
                self._keep_changed = True
        elif name == "lookahead":
            with self._lock:
                self._lookahead_changed = True

    def _on_estimate(self, msg: Float64MultiArray) -> None:
        try:
            est = parse_estimate(msg.data, [d.label for d in msg.layout.dim])
        except ValueError as exc:
            self.get_logger().error(f"{ESTIMATE_TOPIC}: {exc}; ignored")
            return
        if not np.isfinite(est.delta).all():
            self.get_logger().error(f"{ESTIMATE_TOPIC}: non-finite values; ignored")
            return
        with self._lock:
            self._delta = est.delta
            self.estimate_source = ESTIMATE_TOPIC
            self._settings = CorrectionSettings.from_config(self.params.config, self._delta)
            self._settings_changed = True
        self.get_logger().info("new estimate: " + ", ".join(
            f"{n} {format_value(n, v)}" for n, v in est.values.items()))

    # -- input -----------------------------------------------------------------------
    def _on_pose(self, t: float, xyz: tuple[float, float, float], frame_id: str,
                 orientation: tuple[float, ...]) -> None:
        self.trajectory.add(t, xyz, frame_id, orientation)
        with self._lock:
            self._poses_t.append(t)
            self._poses_xyz.append(xyz)
            self._poses_q.append(orientation)
            if self._queue:  # a cloud may be waiting for the trajectory to cover it
                # (not otherwise: hundreds of samples a second would each wake the worker)
                self._lock.notify()

    def _on_points(self, raw: bytes) -> None:
        chunk = _Chunk(raw, time.monotonic(), len(raw))
        if not self._segment_checked and len(raw) > 256 * 1024:
            self._warn_small_segment(len(raw))
        with self._lock:
            self._queue.append(chunk)
            self._queued_bytes += chunk.size
            self._lock.notify()

    def _drop_over_backlog(self) -> None:
        """Drop the oldest waiting clouds while more than ``max_backlog_mib`` wait (called
        by the worker, the only one to take from the queue, with the lock held). The newest
        are kept: for QA in flight the present matters more than the past."""
        limit = int(self.params["max_backlog_mib"]) << 20
        if not limit or self._queued_bytes <= limit:
            return
        dropped = dropped_bytes = 0
        while len(self._queue) > 1 and self._queued_bytes > limit:
            chunk = self._queue.popleft()
            self._queued_bytes -= chunk.size
            dropped += 1
            dropped_bytes += chunk.size
        self.stats.dropped += dropped
        self.stats.dropped_bytes += dropped_bytes
        self.get_logger().warning(
            f"backlog above max_backlog_mib ({limit >> 20} MiB): dropped the {dropped} oldest "
            f"waiting clouds ({dropped_bytes / 2**20:.0f} MiB; {self.stats.dropped} so far)",
            throttle_duration_sec=2.0)

    def _warn_small_segment(self, size: int) -> None:
        """Say once when clouds outgrow the DDS profile's shared-memory segment: they then
        travel as UDP fragments, and the trajectory queues behind them (seconds late)."""
        from lidarcal_ros.ros.environment import shared_memory_segment_bytes

        self._segment_checked = True
        segment = shared_memory_segment_bytes()
        if segment is not None and size > segment // 2:
            self.get_logger().warning(
                f"clouds of {size / 2**20:.1f} MiB but the DDS profile's shared-memory "
                f"segment is {segment / 2**20:.1f} MiB: they go as UDP fragments and delay the "
                "trajectory; use the project's config/loopback.xml (128 MiB)")

    # -- work ------------------------------------------------------------------------
    def _start_service(self) -> CorrectionProcess | LocalCorrection:
        options = ServiceOptions(batch_points=self.params["batch_points"],
                                 workers=self.params["workers"],
                                 lookahead=self.params["lookahead"],
                                 source=self.params["topics.points"],
                                 trajectory_keep_s=self.params["trajectory_buffer_s"],
                                 ring_bytes=self.params["shared_memory_mib"] << 20)
        if self.params["separate_process"]:
            try:
                return CorrectionProcess(self._settings, options, on_result=self._on_result,
                                         on_error=self._on_error, on_failure=self._on_failure)
            except OSError as exc:  # no process can be started here: correct in a thread
                self.get_logger().warning(f"correction process not started ({exc}); "
                                          "correcting in a thread of this node")
        return LocalCorrection(self._settings, options, on_result=self._on_result,
                               on_error=self._on_error, warm=True)

    def _on_failure(self, reason: str) -> None:
        self.get_logger().error(f"corrector: {reason}; restarting it")

    def _work(self) -> None:
        while True:
            with self._lock:
                if self._closing:
                    return
                self._drop_over_backlog()
                chunks = list(self._queue)
                poses_waiting = len(self._poses_t)
            try:
                self._service.poll()
                if poses_waiting > _POSES_PER_HANDOVER:  # (no clouds for a while)
                    self._sync()
                progressed = self._step(chunks)
            except Exception as exc:  # never let the worker die
                self.get_logger().error(f"corrector: unexpected error: {exc}")
                progressed = False
            if not progressed:
                with self._lock:
                    if not self._closing:
                        self._lock.wait(timeout=self._idle_timeout())

    def _idle_timeout(self) -> float:
        """How long the worker may wait for a notification (a cloud, or a trajectory sample
        while a cloud waits for the trajectory) before it must look again itself: to
        collect the batches of worker threads in this process, to release held clouds after
        ``flush_timeout_s`` without a new one, to give up on a trajectory that stopped, or to
        hand on samples piling up without clouds. Called with the lock held."""
        if isinstance(self._service, LocalCorrection) and self._service.in_flight:
            return 0.005
        timeout = 0.25
        if self._queue:
            timeout = 0.05  # (max_trajectory_wait_s is seconds)
        if self._held and self._released_tag != self._next_tag:
            due = self._last_push + self.params["flush_timeout_s"] - time.monotonic()
            timeout = min(timeout, max(due, 0.001))
        return timeout

    def _parse(self, chunk: _Chunk) -> bool:
        source = self.params["topics.points"]
        try:
            cloud = parse_cloud(chunk.raw, source=source)
            traj_frame = self.trajectory.frame_id
            if traj_frame is not None and cloud.frame_id != traj_frame:
                raise LidarcalError(f"{source}: cloud in frame '{cloud.frame_id}' but the "
                                    f"trajectory is in '{traj_frame}'")
            tname = resolve_time_field(cloud.points, self._settings.time_field,
                                       source=source)
            _, t_max = time_span(cloud.points[tname])
            chunk.t_max = t_max if math.isfinite(t_max) else -math.inf
        except LidarcalError as exc:
            self._skip(chunk, str(exc))
            return False
        chunk.parsed, chunk.n_points = True, len(cloud.points)
        return True

    def _skip(self, chunk: _Chunk, reason: str) -> None:
        self.stats.skipped += 1
        self.stats.last_error = reason
        self.get_logger().error(f"malformed cloud skipped: {reason}",
                                throttle_duration_sec=2.0)

    def _step(self, chunks: list[_Chunk]) -> bool:
        """Hand the chunks that the trajectory covers to the correction, in order; returns
        whether anything was done.

        All the chunks ready at once go together: under a backlog their normals are
        evaluated in one pass (fewer, larger numpy calls catch up faster); with one chunk
        ready this is the one-chunk-at-a-time path.
        """
        now = time.monotonic()
        wait = self.params["max_trajectory_wait_s"]
        done = 0
        ready: list[_Chunk] = []
        ready_points = 0
        for chunk in chunks:
            if not chunk.parsed and not self._parse(chunk):
                done += 1
                continue
            # Wait for the trajectory to cover the chunk (keeps the order); give up only once
            # the trajectory has stalled for max_trajectory_wait_s, not while poses still
            # arrive late behind a backlog.
            waited = now - max(chunk.received, self.trajectory.last_arrival)
            if chunk.t_max + _TRAJECTORY_MARGIN_S > self.trajectory.end and waited < wait:
                break
            ready.append(chunk)
            done += 1
            ready_points += chunk.n_points
            if ready_points >= MAX_PUSH_POINTS:
                break  # under a backlog: batches of bounded size keep the numerics efficient
        if ready:
            self._push(ready)
        with self._lock:
            for _ in range(done):
                self._queued_bytes -= self._queue.popleft().size
            empty = not self._queue
        if (empty and self._held and self._released_tag != self._next_tag
                and time.monotonic() - self._last_push >= self.params["flush_timeout_s"]):
            # No new chunk for a while (a pause, the end of a strip): correct what is held
            # without waiting for look-ahead, with the trajectory received up to now.
            self._released_tag = self._next_tag
            self._sync()
            self._service.release()
            return True
        return done > 0

    def _sync(self) -> None:
        """Give the correction the new trajectory samples, settings and switches, in the
        order they came (a new estimate applies from the next chunk on)."""
        with self._lock:
            t, xyz, orientation = self._poses_t, self._poses_xyz, self._poses_q
            self._poses_t, self._poses_xyz, self._poses_q = [], [], []
            settings = self._settings if self._settings_changed else None
            lookahead_changed, keep_changed = self._lookahead_changed, self._keep_changed
            self._settings_changed = self._lookahead_changed = self._keep_changed = False
        if self._service_failed():  # it died (reported by _on_failure): a new one
            self._service = self._start_service()
            whole = self.trajectory.trajectory()
            self._service.poses(whole.t, whole.xyz, whole.orientation)
        elif t:
            self._service.poses(np.asarray(t, dtype=np.float64),
                                np.asarray(xyz, dtype=np.float64).reshape(-1, 3),
                                np.asarray(orientation, dtype=np.float64).reshape(-1, 4))
        if settings is not None:
            self._service.set_settings(settings)
        if lookahead_changed:
            self._service.set_lookahead(self.params["lookahead"])
        if keep_changed:
            self._service.set_trajectory_keep(self.params["trajectory_buffer_s"])

    def _service_failed(self) -> bool:
        return isinstance(self._service, CorrectionProcess) and not self._service.alive

    def _push(self, chunks: list[_Chunk]) -> None:
        started = time.perf_counter()
        self._sync()
        clouds: list[tuple[int, bytes]] = []
        with self._lock:
            for chunk in chunks:
                tag = self._next_tag
                self._next_tag += 1
                self._held[tag] = chunk
                clouds.append((tag, chunk.raw))
                chunk.raw = b""  # the correction has it now
                self.stats.clouds_in += 1
                self.stats.points_in += chunk.n_points
        self._service.push(clouds)
        self._last_push = time.monotonic()
        self.stats.busy_s += time.perf_counter() - started

    def _on_result(self, tag: int, cdr: bytes, points: int, not_corrected: int,
                   _seconds: float) -> None:
        """A corrected chunk (from the correction's reader thread, or inline): publish."""
        with self._lock:
            chunk = self._held.pop(tag, None)
        if chunk is None:
            return
        started = time.perf_counter()
        self._publish(cdr)
        self.stats.busy_s += time.perf_counter() - started
        self.stats.clouds_out += 1
        self.stats.points_out += points
        self.stats.not_corrected += not_corrected
        self.stats.latencies.append(time.monotonic() - chunk.received)

    def _publish(self, cdr: bytes) -> None:
        self.publisher.publish(cdr)

    def _on_error(self, tag: int, reason: str) -> None:
        """A chunk the correction refused (malformed) or lost: logged and skipped."""
        with self._lock:
            chunk = self._held.pop(tag, None)
        if chunk is None:
            return
        self.stats.clouds_in -= 1
        self.stats.points_in -= chunk.n_points
        self._skip(chunk, reason)

    # -- diagnostics -------------------------------------------------------------------
    def status(self) -> StatusSpec:
        s = self.stats
        lat = np.asarray(s.latencies, dtype=np.float64)
        p50 = float(np.percentile(lat, 50)) if lat.size else math.nan
        p99 = float(np.percentile(lat, 99)) if lat.size else math.nan
        level = WARN if s.skipped or s.not_corrected or s.dropped else OK
        msg = (f"{s.clouds_out} clouds ({s.points_out} points) corrected, "
               f"latency p99 {p99 * 1000:.0f} ms")
        if s.dropped:
            msg += (f"; {s.dropped} clouds dropped ({s.dropped_bytes / 2**20:.0f} MiB): "
                    "backlog above max_backlog_mib")
        if s.skipped:
            msg += f"; {s.skipped} malformed clouds skipped (last: {s.last_error})"
        if s.not_corrected:
            msg += f"; {s.not_corrected} points not covered by the trajectory"
        return StatusSpec(level, "lidarcal: corrector", msg, {
            "clouds_in": str(s.clouds_in), "points_in": str(s.points_in),
            "clouds_out": str(s.clouds_out), "points_out": str(s.points_out),
            "skipped_clouds": str(s.skipped), "not_corrected_points": str(s.not_corrected),
            "dropped_clouds": str(s.dropped), "queued_mib": f"{self._queued_bytes / 2**20:.1f}",
            "latency_p50_s": f"{p50:.4f}", "latency_p99_s": f"{p99:.4f}",
            "queued_clouds": str(len(self._queue)), "held_clouds": str(len(self._held)),
            "estimate_source": self.estimate_source, "transport": self._transport(),
            "poses_left_out": str(self.trajectory.left_out),
            "heading": describe_heading_policy(str(self.params["matching.heading_source"]),
                                               self.trajectory.oriented_samples > 0),
            "model": describe_model_policy(
                self._settings.model, self.trajectory.trajectory(),
                heading_source=str(self.params["matching.heading_source"]))})

    def _transport(self) -> str:
        """How clouds reach the numerics: ``thread``, ``shared memory`` or ``pipes``."""
        service = self._service
        if not isinstance(service, CorrectionProcess):
            return "thread"
        return "shared memory" if service.shared_memory else "pipes"

    def _publish_diagnostics(self) -> None:
        self.diagnostics.publish(diagnostic_array(self, [self.status()]))

    def close(self) -> None:
        """Stop the worker; held chunks are corrected and published first."""
        with self._lock:
            self._closing = True
            self._lock.notify_all()
        self._worker.join(timeout=5.0)
        try:
            self._sync()
            self._service.close()
        except Exception as exc:  # shutting down
            self.get_logger().error(f"flushing held clouds failed: {exc}")


def main(args: Sequence[str] | None = None) -> int:
    """Console script ``lidarcal_corrector``."""
    # The node's callbacks are light (the numerics run in the correction's own process):
    # one executor thread, no hand-over of each callback to a pool.
    return run_main([CorrectorNode], args, threads=1)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
