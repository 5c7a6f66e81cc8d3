"""``lidarcal_calibrator``: live calibration from the strips as they are flown.

    ros2 run lidarcal_ros lidarcal_calibrator --ros-args --params-file config/flight_config.yaml

Subscribes (raw CDR) to the strips (``topics.points``), the trajectory (``topics.trajectory``)
and the control points (``topics.control_points``, transient-local; or the CSV of
``calibration.control_points_file``) and feeds them to
:class:`lidarcal_ros.pipeline.streaming.StreamingCalibration`: a strip is complete once no point
of it arrived for ``strip_gap_s`` seconds of point (or trajectory) time, or once no input at
all arrived for ``idle_close_s`` wall seconds (the end of a mission or a replay). Each complete
strip is paired with the earlier strips it overlaps, its correspondences join the normal
equations and the estimate is re-solved quickly (two iterations, the new pairs re-matched:
published, not converged). Whenever no input is waiting, the worker then takes the estimate to
convergence a step at a time (every pair re-matched; one pair's matching or one adjustment per
step, input taken in between) and publishes it once converged: with no service call, the
estimate latched after the last strip is what ``lidarcal calibrate`` gives on the same bag.

Publishes
---------
``/lidar/calibration/estimate`` (``std_msgs/Float64MultiArray``, transient-local, depth 1)
    10 x 8 matrix: values, sigmas, covariance of ``dX, dY, dZ, domega, dphi, dkappa, dr, dS``
    (SI units; layout in :mod:`lidarcal_ros.io.ros_messages`); the label of ``layout.dim[0]``
    ends in ``;converged=true`` or ``;converged=false``.
``/lidar/calibration/yaml`` (``std_msgs/String``, transient-local, depth 1)
    The calibration file of interface.md (``converged`` says whether it is).
``/diagnostics`` (``diagnostic_msgs/DiagnosticArray``, every second and after each solve)
    ``lidarcal: strips A&B`` per overlapping pair (RMS discrepancy after calibration against
    ``qa.rmsdz_warn_m`` / ``qa.max_difference_m``, USGS LBS QL2 8 cm / 16 cm: OK, WARN, ERROR;
    values coverage, rms_before, rms_after, p95_after), ``lidarcal: convergence`` (WARN
    while not converged; ``refining`` says whether the background convergence is under way),
    ``lidarcal: observability`` (parameters not estimable, with the reason),
    ``lidarcal: memory`` (points held, points and strips released under the budget) and
    ``lidarcal: input`` (clouds, malformed clouds skipped and why, queue).

Services (``std_srvs/Trigger``)
    ``~/solve``: full solve over everything accumulated (what ``lidarcal calibrate`` computes on
    the same data), published as above. ``~/reset``: forget everything, the checkpoint file
    too (the latest estimate stays latched until the next solve). ``~/save``: converge first
    (at most ``SAVE_CONVERGE_S``; the message says if cut short), then write the calibration
    file to ``calibration.calibration_file``; the message names the path.

Node-specific parameters: ``memory_budget_points`` (points held; past it the oldest complete
strip is released first and reported; 0, the default, sizes it to about half of the machine's
memory), ``strip_gap_s``, ``idle_close_s``, ``checkpoint_file``
(written after every estimate published and on shutdown, which converges first for at most
``SHUTDOWN_CONVERGE_S``; read at start, so a restarted calibrator resumes with its accumulated
normal equations, converges again and publishes), ``queue_depth``, ``trajectory_type``.

All work on the calibration happens in one worker thread; the subscription callbacks only
decode and queue, so input keeps flowing while a solve runs.
"""

from __future__ import annotations

import math
import queue
import sys
import threading
import time
from collections.abc import Sequence
from concurrent.futures import Future
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Float64MultiArray, MultiArrayDimension, String
from std_srvs.srv import Trigger

from lidarcal_ros.core.config import CALIBRATOR_NODE, NODE_PARAMETERS, FlightConfig
from lidarcal_ros.core.mission import ControlPoints
from lidarcal_ros.errors import LidarcalError
from lidarcal_ros.io.pointcloud import extract_columns, extract_xyz
from lidarcal_ros.io.ros_messages import (
    ERROR,
    ESTIMATE_COLUMN_LABEL,
    ESTIMATE_ROWS,
    OK,
    WARN,
    StatusSpec,
    calibration_yaml,
    estimate_matrix,
    estimate_row_label,
    parse_cloud,
    qa_statuses,
    qa_summary,
    warm_up_cloud_codec,
    worst_level,
)
from lidarcal_ros.nodes.parameters import FlightParameters
from lidarcal_ros.nodes.process import run_main
from lidarcal_ros.nodes.topics import (
    DIAGNOSTICS_TOPIC,
    ESTIMATE_TOPIC,
    YAML_TOPIC,
    diagnostic_array,
    latched_qos,
    stream_qos,
)
from lidarcal_ros.nodes.trajectory_input import TrajectoryInput

EXTRA_PARAMETERS = NODE_PARAMETERS[CALIBRATOR_NODE]

#: Least wall time between two looks for complete strips, s.
UPDATE_PERIOD_S = 0.2
#: How long a service waits for the worker (a full solve of a large mission takes minutes).
SERVICE_TIMEOUT_S = 600.0
#: Longest wall time ``~/save`` and shutdown spend converging the estimate first, s.
SAVE_CONVERGE_S = 300.0
SHUTDOWN_CONVERGE_S = 5.0


def streaming_class() -> Any:
    from lidarcal_ros.pipeline.streaming import StreamingCalibration

    return StreamingCalibration


def _point_budget(value: Any) -> int:
    """``memory_budget_points`` as points (0: this machine's default)."""
    from lidarcal_ros.pipeline.stream_inputs import default_point_budget

    return int(value) if int(value) > 0 else default_point_budget()


class CalibratorNode(Node):
    """Live calibration node (module docstring)."""

    def __init__(self, *, context: Any = None, node_name: str = CALIBRATOR_NODE,
                 **kwargs: Any) -> None:
        super().__init__(node_name, context=context, **kwargs)
        self._control_from_topic = False
        self.params = FlightParameters(self, extra=EXTRA_PARAMETERS,
                                       has_control=lambda: self._control_from_topic)
        cfg = self.params.config
        self._jobs: queue.Queue[tuple[str, Any, Future[Any] | None]] = queue.Queue()
        self._closing = threading.Event()
        self._last_input = time.monotonic()
        self._idle_closed = True
        self._point_end = -math.inf  # newest point time, s
        self._traj_end = -math.inf  # newest trajectory time, s
        self._last_update = 0.0
        self._statuses: list[StatusSpec] = []
        self._status_lock = threading.Lock()
        self.input: dict[str, Any] = {"clouds": 0, "points": 0, "skipped": 0, "poses": 0,
                                      "last_error": ""}
        self.solves = 0
        self.last_solve_s = math.nan
        self.checkpoints = 0
        self.resumed_from = ""
        self.stream = self._start_stream(cfg)
        warm_up_cloud_codec()

        self.estimate_pub = self.create_publisher(Float64MultiArray, ESTIMATE_TOPIC,
                                                  latched_qos())
        self.yaml_pub = self.create_publisher(String, YAML_TOPIC, latched_qos())
        self.diagnostics = self.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, 10)
        input_group = MutuallyExclusiveCallbackGroup()
        service_group = ReentrantCallbackGroup()
        timer_group = MutuallyExclusiveCallbackGroup()
        self.create_subscription(PointCloud2, cfg["topics.points"], self._on_points,
                                 stream_qos(self.params["queue_depth"]), raw=True,
                                 callback_group=input_group)
        self.trajectory_input = TrajectoryInput(self, cfg["topics.trajectory"],
                                                self.params["trajectory_type"], self._on_pose,
                                                callback_group=input_group)
        self.create_subscription(PointCloud2, cfg["topics.control_points"], self._on_control,
                                 latched_qos(), raw=True, callback_group=input_group)
        self.create_service(Trigger, "~/solve", self._srv_solve, callback_group=service_group)
        self.create_service(Trigger, "~/reset", self._srv_reset, callback_group=service_group)
        self.create_service(Trigger, "~/save", self._srv_save, callback_group=service_group)
        self.create_timer(1.0, self._publish_diagnostics, callback_group=timer_group)
        self.params.on_change(self._on_config)
        self.params.on_extra_change(self._on_extra)
        if cfg["calibration.control_points_file"]:
            self._submit("control_file", cfg["calibration.control_points_file"])
        self._worker = threading.Thread(target=self._work, name="lidarcal-calibrator",
                                        daemon=True)
        self._worker.start()

    # -- state -------------------------------------------------------------------------
    def _start_stream(self, cfg: FlightConfig) -> Any:
        cls = streaming_class()
        kwargs = {"max_points": _point_budget(self.params["memory_budget_points"]),
                  "strip_gap_s": float(self.params["strip_gap_s"])}
        path = self.params["checkpoint_file"]
        if path and Path(path).is_file():
            try:
                stream = cls.load_checkpoint(path, cfg, **kwargs)
            except LidarcalError as exc:
                self.get_logger().error(f"checkpoint not used: {exc}; starting afresh")
            else:
                self.resumed_from = str(path)
                neq = stream.normal_equations
                self.get_logger().info(
                    f"resumed from {path}: strips {stream.strip_ids}, {stream.n_points} "
                    f"points, {neq.count} observations in the normal equations")
                return stream
        return cls(cfg, **kwargs)

    def _submit(self, kind: str, payload: Any, *, wait: bool = False) -> Future[Any] | None:
        future: Future[Any] | None = Future() if wait else None
        self._jobs.put((kind, payload, future))
        return future

    # -- input callbacks (decode and queue only) -----------------------------------------
    def _on_points(self, raw: bytes) -> None:
        source = self.params["topics.points"]
        try:
            cloud = parse_cloud(raw, source=source)
            cols = extract_columns(cloud.points, time_field=self.params["time_field"],
                                   source=source,
                                   coordinate_tolerance_m=self.params["sensor.range_noise_m"])
            if cols.strip_id is None:
                raise LidarcalError(f"{source}: cloud lacks field 'strip_id' (or "
                                    "'point_source_id')")
        except LidarcalError as exc:
            self._skip(str(exc))
            return
        self.input["clouds"] += 1
        self.input["points"] += len(cols)
        self._submit("cloud", (cols, cloud.frame_id))

    def _skip(self, reason: str) -> None:
        self.input["skipped"] += 1
        self.input["last_error"] = reason
        self.get_logger().error(f"malformed cloud skipped: {reason}", throttle_duration_sec=2.0)

    def _on_pose(self, t: float, xyz: tuple[float, float, float], frame_id: str,
                 orientation: tuple[float, ...]) -> None:
        self.input["poses"] += 1
        self._submit("pose", (t, xyz, frame_id, orientation))

    def _on_control(self, raw: bytes) -> None:
        source = self.params["topics.control_points"]
        try:
            cloud = parse_cloud(raw, source=source)
            xyz = extract_xyz(cloud.points, source=source,
                              coordinate_tolerance_m=self.params["sensor.range_noise_m"])
        except LidarcalError as exc:
            self.get_logger().error(f"control points ignored: {exc}")
            return
        xyz = xyz[np.isfinite(xyz).all(axis=1)]
        if not len(xyz):
            self.get_logger().warning(f"{source}: no finite control point; ignored")
            return
        self._control_from_topic = True
        if self.params["calibration.control_points_file"]:
            self.get_logger().info(f"{source}: control points ignored, "
                                   "calibration.control_points_file takes precedence")
            return
        control = ControlPoints([f"C{i + 1}" for i in range(len(xyz))], xyz)
        self._submit("control", (control, cloud.frame_id))

    def _on_config(self, config: FlightConfig, changed: set[str]) -> None:
        self._submit("config", (config, changed))

    def _on_extra(self, name: str, value: Any) -> None:
        self._submit("extra", (name, value))

    # -- worker ---------------------------------------------------------------------------
    def _work(self) -> None:
        poses: list[tuple[float, tuple[float, float, float], tuple[float, ...]]] = []
        pose_frame = ""
        while not self._closing.is_set():
            try:
                if self.stream.refinement_pending:  # spare time goes to the refinement
                    kind, payload, future = self._jobs.get_nowait()
                else:
                    kind, payload, future = self._jobs.get(timeout=0.05)
            except queue.Empty:
                kind, payload, future = "idle", None, None
            try:
                if kind == "pose":
                    t, xyz, pose_frame, orientation = payload
                    poses.append((t, xyz, orientation))
                    self._last_input = time.monotonic()
                    continue
                if poses and (kind != "pose"):
                    self._flush_poses(poses, pose_frame)
                    poses = []
                result = self._handle(kind, payload)
                if future is not None:
                    future.set_result(result)
            except Exception as exc:  # report, keep the worker alive
                if future is not None:
                    future.set_exception(exc)
                else:
                    text = str(exc) if isinstance(exc, LidarcalError) else \
                        f"{type(exc).__name__}: {exc}"
                    self.get_logger().error(f"calibrator: {kind}: {text}")
                    if kind == "cloud":
                        self.input["skipped"] += 1
                        self.input["last_error"] = text

    def _flush_poses(self, poses: list[tuple[float, tuple[float, float, float],
                                             tuple[float, ...]]],
                     frame: str) -> None:
        t = np.array([p[0] for p in poses])
        xyz = np.array([p[1] for p in poses])
        self.stream.add_trajectory(t, xyz, frame, np.array([p[2] for p in poses]))
        self._traj_end = max(self._traj_end, float(t.max()))

    def _handle(self, kind: str, payload: Any) -> Any:
        if kind == "cloud":
            cols, frame = payload
            self.stream.add_cloud(cols, frame)
            self._last_input = time.monotonic()
            self._idle_closed = False
            finite = cols.t[np.isfinite(cols.t)]
            if finite.size:
                self._point_end = max(self._point_end, float(finite.max()))
            if self._jobs.empty():
                self._update(None)
            return None
        if kind == "idle":
            idle = self.params["idle_close_s"]
            if (not self._idle_closed and idle > 0
                    and time.monotonic() - self._last_input >= idle):
                self._idle_closed = True
                self._update(math.inf)
            elif self._jobs.empty():
                self._update(None)
            if self._jobs.empty():
                self._refine()
            return None
        if kind == "solve":
            return self._solve()
        if kind == "reset":
            return self._reset()
        if kind == "save":
            return self._save()
        if kind == "control":
            control, _frame = payload
            self.stream.set_control(control)
            self.get_logger().info(f"{len(control)} control points")
            return None
        if kind == "control_file":
            from lidarcal_ros.io.control import read_control_csv

            control = read_control_csv(payload)
            self.stream.set_control(control)
            self.get_logger().info(f"{len(control)} control points from {payload}")
            return None
        if kind == "config":
            cfg, changed = payload
            self.stream.update_config(cfg)
            if "calibration.control_points_file" in changed and \
                    cfg["calibration.control_points_file"]:
                self._handle("control_file", cfg["calibration.control_points_file"])
            return None
        if kind == "extra":
            name, value = payload
            if name == "memory_budget_points":
                self.stream.max_points = _point_budget(value)
            elif name == "strip_gap_s":
                self.stream.strip_gap_s = float(value)
            return None
        raise ValueError(f"unknown job {kind}")

    def _update(self, now_s: float | None) -> None:
        """Let the stream close idle strips and re-solve (at most every UPDATE_PERIOD_S
        unless ``now_s`` is given)."""
        if now_s is None:
            now_s = max(self._point_end, self._traj_end)
            if not math.isfinite(now_s) or \
                    time.monotonic() - self._last_update < UPDATE_PERIOD_S:
                return
        self._last_update = time.monotonic()
        before = set(self.stream.strip_ids) - set(self.stream.open_strip_ids)
        started = time.perf_counter()
        try:
            result = self.stream.update(now_s)
        except LidarcalError as exc:  # e.g. no trajectory yet: keep accumulating
            self.get_logger().warning(f"not updated: {exc}", throttle_duration_sec=10.0)
            return
        after = set(self.stream.strip_ids) - set(self.stream.open_strip_ids)
        for sid in sorted(after - before):
            pairs = [f"{p.strip_a}&{p.strip_b}" for p in (result.pairs if result else ())
                     if sid in (p.strip_a, p.strip_b)]
            self.get_logger().info(f"strip {sid} complete; overlaps: "
                                   f"{', '.join(pairs) or 'none yet'}")
        if result is not None:
            self._publish_result(result, time.perf_counter() - started)

    def _refine(self) -> None:
        """One step of the background convergence; publish the estimate once it ends."""
        result = self.stream.refine_step()
        if result is not None:
            self._publish_result(result, self.stream.refinement_seconds)

    def _converge(self, timeout_s: float) -> str:
        """Finish converging (at most ``timeout_s``) and publish; returns what to tell of it
        ('' when the estimate is converged)."""
        started = time.monotonic()
        result = self.stream.converge(timeout_s)
        if result is not None:
            self._publish_result(result, self.stream.refinement_seconds)
        if self.stream.converged:
            return ""
        if self.stream.refinement_pending:
            return (f"NOT converged: convergence cut short after "
                    f"{time.monotonic() - started:.0f} s")
        latest = self.stream.latest
        iterations = latest.iterations if latest is not None else 0
        return f"NOT converged after {iterations} iterations"

    def _reset(self) -> str:
        self.stream.reset()
        self._point_end = self._traj_end = -math.inf
        with self._status_lock:
            self._statuses = []
        message = "reset: everything accumulated was forgotten"
        path = self.params["checkpoint_file"]
        if path:
            # A restart must not bring back what was reset (the next checkpoint is written
            # only by the next solve): the checkpoint goes with the rest.
            try:
                Path(path).unlink(missing_ok=True)
            except OSError as exc:
                raise LidarcalError(f"reset, but checkpoint {path} not removed: {exc}") \
                    from None
            message += f"; checkpoint {path} removed"
        return message

    def _solve(self) -> str:
        started = time.perf_counter()
        result = self.stream.solve()
        self._publish_result(result, time.perf_counter() - started)
        sol = result.solution
        return (f"solved: {len(result.pairs)} strip pairs, {result.iterations} iterations, "
                f"{'converged' if result.converged else 'NOT converged'}, sigma0 "
                f"{sol.sigma0 * 100:.2f} cm")

    def _save(self) -> str:
        from lidarcal_ros.io.calibration_file import write_calibration

        convergence = self._converge(SAVE_CONVERGE_S)
        result = self.stream.latest
        if result is None:
            raise LidarcalError("no estimate yet: " + (self.stream.waiting_for or "no data"))
        path = write_calibration(self.params["calibration.calibration_file"], result)
        return f"calibration written to {Path(path).resolve()}" + (
            f" ({convergence})" if convergence else "")

    def _publish_result(self, result: Any, seconds: float) -> None:
        self.solves += 1
        self.last_solve_s = seconds
        msg = Float64MultiArray()
        n_rows, n_cols = len(ESTIMATE_ROWS), 8
        msg.layout.dim = [
            MultiArrayDimension(label=estimate_row_label(result.converged), size=n_rows,
                                stride=n_rows * n_cols),
            MultiArrayDimension(label=ESTIMATE_COLUMN_LABEL, size=n_cols, stride=n_cols)]
        msg.data = estimate_matrix(result).ravel().tolist()
        self.estimate_pub.publish(msg)
        self.yaml_pub.publish(String(data=calibration_yaml(result)))
        cfg = self.params.config
        statuses = qa_statuses(result, warn_m=cfg["qa.rmsdz_warn_m"],
                               error_m=cfg["qa.max_difference_m"],
                               solve_for=cfg["calibration.solve_for"])
        with self._status_lock:
            self._statuses = statuses
        self._publish_diagnostics()
        # The same for whoever watches the console (the crew running ``lidarcal run``).
        # (rclpy refuses one call site logging at two severities: two calls.)
        summary = qa_summary(statuses)
        if worst_level(s for s in statuses if s.name.startswith("lidarcal: strips ")) >= WARN:
            self.get_logger().warning(summary)
        else:
            self.get_logger().info(summary)
        path = self.params["checkpoint_file"]
        if path:
            self._checkpoint(path)

    def _checkpoint(self, path: str) -> None:
        try:
            self.stream.save_checkpoint(path)
            self.checkpoints += 1
        except (OSError, LidarcalError) as exc:
            self.get_logger().error(f"checkpoint {path} not written: {exc}",
                                    throttle_duration_sec=30.0)

    # -- services -------------------------------------------------------------------------
    def _call_worker(self, kind: str, response: Any) -> Any:
        future = self._submit(kind, None, wait=True)
        assert future is not None
        try:
            response.message = str(future.result(timeout=SERVICE_TIMEOUT_S))
            response.success = True
        except Exception as exc:
            response.success = False
            response.message = str(exc) if isinstance(exc, LidarcalError) else \
                f"{type(exc).__name__}: {exc}"
        return response

    def _srv_solve(self, _request: Any, response: Any) -> Any:
        return self._call_worker("solve", response)

    def _srv_reset(self, _request: Any, response: Any) -> Any:
        return self._call_worker("reset", response)

    def _srv_save(self, _request: Any, response: Any) -> Any:
        return self._call_worker("save", response)

    # -- diagnostics ----------------------------------------------------------------------
    def node_statuses(self) -> list[StatusSpec]:
        """Memory, input and checkpoint statuses (the QA statuses come with each solve)."""
        s = self.stream
        dropped = s.dropped_points
        mem_level = WARN if dropped or s.auto_thinning_cell_m else OK
        mem_msg = f"{s.n_points} points held of a budget of {s.max_points}"
        cell = float(self.params["calibration.thinning_cell_m"])
        if s.thinned_points:
            mem_msg += f" ({s.thinned_points} left out by thinning)"
        if s.auto_thinning_cell_m:
            mem_msg += (f"; the strips being flown outgrew the budget: thinning at "
                        f"{s.thinning_cell_m:g} m")
        if dropped:
            mem_msg += (f"; released {dropped} points (strips "
                        f"{', '.join(str(i) for i in s.dropped_strips)}), oldest first")
            if cell <= 0:
                mem_msg += "; calibration.thinning_cell_m would keep more strips"
        out = [StatusSpec(mem_level, "lidarcal: memory", mem_msg, {
            "points_held": str(s.n_points), "budget_points": str(s.max_points),
            "thinned_points": str(s.thinned_points), "thinning_cell_m": f"{cell:g}",
            "auto_thinning_cell_m": f"{s.auto_thinning_cell_m:g}",
            "dropped_points": str(dropped),
            "dropped_strips": ",".join(str(i) for i in s.dropped_strips),
            "strips": ",".join(str(i) for i in s.strip_ids),
            "open_strips": ",".join(str(i) for i in s.open_strip_ids)})]
        inp = self.input
        uncovered, left_out = s.uncovered_points, s.uncovered_strips
        rejected, late = s.rejected_strips, s.late_points
        level = WARN if inp["skipped"] or uncovered or rejected or late else OK
        msg = f"{inp['clouds']} clouds, {inp['points']} points, {inp['poses']} poses"
        if inp["skipped"]:
            msg += f"; {inp['skipped']} malformed clouds skipped (last: {inp['last_error']})"
        if uncovered:
            msg += f"; {uncovered} points without trajectory left out" + (
                f" (strips {', '.join(str(i) for i in left_out)} wholly)" if left_out else "")
        if late:
            msg += (f"; {late} points of strips already closed ignored (a pause longer than "
                    "strip_gap_s?)")
        if rejected:
            msg += (f"; {len(rejected)} strip(s) refused by the calibration, left out "
                    f"(last: {rejected[-1][1]})")
        if s.poses_left_out:
            msg += (f"; {s.poses_left_out} poses left out (a non-finite stamp or position, or "
                    "a stamp already received)")
        out.append(StatusSpec(level, "lidarcal: input", msg, {
            "poses_left_out": str(s.poses_left_out),
            "clouds": str(inp["clouds"]), "points": str(inp["points"]),
            "poses": str(inp["poses"]), "skipped_clouds": str(inp["skipped"]),
            "last_error": str(inp["last_error"]), "queued_jobs": str(self._jobs.qsize()),
            "uncovered_points": str(uncovered),
            "uncovered_strips": ",".join(str(i) for i in left_out),
            "late_points": str(late),
            "rejected_strips": ",".join(str(i) for i, _ in rejected),
            "last_rejection": rejected[-1][1] if rejected else ""}))
        neq = s.normal_equations
        out.append(StatusSpec(OK, "lidarcal: state", (
            f"{self.solves} solves (last {self.last_solve_s:.2f} s), {self.checkpoints} "
            "checkpoints" + (f", resumed from {self.resumed_from}" if self.resumed_from else "")
            + ("" if s.latest is not None else f"; waiting: {s.waiting_for}")), {
            "solves": str(self.solves), "last_solve_s": f"{self.last_solve_s:.3f}",
            "checkpoints": str(self.checkpoints), "resumed_from": self.resumed_from,
            "normal_equations_count": str(int(neq.count)),
            "normal_equations_trace": repr(float(np.trace(neq.n))),
            "normal_equations_yy": repr(float(neq.yy))}))
        if s.latest is None and not self._statuses:
            out.append(StatusSpec(OK if not s.strip_ids else WARN, "lidarcal: convergence",
                                  "no estimate yet: " + (s.waiting_for or "no data")))
        return out

    def _refinement_status(self, status: StatusSpec) -> StatusSpec:
        """The convergence status of the latest estimate published, saying whether the
        estimate is being converged on the strips now held."""
        s = self.stream
        if not s.refinement_pending:
            return replace(status, values={**status.values, "refining": "false"})
        return replace(status, level=max(status.level, WARN), message=(
            f"converging: iteration {s.refinement_iteration + 1} on the strips held (latest "
            f"estimate: {status.message})"), values={
                **status.values, "converged": "False", "refining": "true"})

    def _publish_diagnostics(self) -> None:
        with self._status_lock:
            statuses = [self._refinement_status(s) if s.name == "lidarcal: convergence" else s
                        for s in self._statuses]
        try:
            statuses += self.node_statuses()
        except Exception as exc:  # diagnostics must not take the node down
            statuses.append(StatusSpec(ERROR, "lidarcal: state", f"{type(exc).__name__}: {exc}"))
        self.diagnostics.publish(diagnostic_array(self, statuses))

    # -- shutdown -------------------------------------------------------------------------
    def close(self) -> None:
        """Stop the worker, converge (at most ``SHUTDOWN_CONVERGE_S``) and write a last
        checkpoint."""
        self._closing.set()
        self._worker.join(timeout=10.0)
        written = self.checkpoints
        if not self._worker.is_alive() and self.stream.refinement_pending:
            convergence = self._converge(SHUTDOWN_CONVERGE_S)
            if convergence:
                self.get_logger().warning(f"shutdown: the estimate is {convergence} (a "
                                          "restart from the checkpoint converges it)")
        path = self.params["checkpoint_file"]
        if path and self.stream.strip_ids and self.checkpoints == written:
            self._checkpoint(path)


def main(args: Sequence[str] | None = None) -> int:
    """Console script ``lidarcal_calibrator``."""
    return run_main([CalibratorNode], args)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

