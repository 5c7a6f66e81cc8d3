"""The live calibrator's work without ROS: one worker thread drives a streaming calibration.

:class:`CalibrationService` is what ``lidarcal_calibrator`` runs; callers queue typed jobs
(:class:`AddCloud`, ..., :class:`Solve`, :class:`Reset`, :class:`Save`). Its scheduling, results
and shutdown: docs/nodes.md, "How the calibrator works".
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections.abc import Callable, Mapping
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lidarcal_ros.core.adjustment.least_squares import ParameterState, ParameterStatus
from lidarcal_ros.core.calibration.calibrate import CalibrationSettings
from lidarcal_ros.core.calibration.extrinsic import (
    TIMING_SLOT,
    MountingCalibration,
    calibrate_mounting,
    sensor_points,
    timing_unseen,
    without_timing,
)
from lidarcal_ros.core.calibration.result import CalibrationResult
from lidarcal_ros.core.config import CALIBRATOR_NODE, FlightConfig, node_options
from lidarcal_ros.core.georeferencing.sensor_frame import Mounting
from lidarcal_ros.core.mission import ControlPoints, Strip
from lidarcal_ros.errors import LidarcalError
from lidarcal_ros.io.calibration_file import Extrinsic, urdf_path
from lidarcal_ros.io.cloud.columns import CloudColumns
from lidarcal_ros.io.cloud.messages import ERROR, OK, WARN, StatusSpec, qa_statuses
from lidarcal_ros.pipeline.calibration.checkpoint import StreamCheckpoint, read_checkpoint
from lidarcal_ros.pipeline.calibration.sensor_frame import (
    log_solve_for_note,
    mounting_solve_for,
    parse_mounting,
    sensor_calibration_settings,
    with_timing,
    write_mounting_calibration,
)
from lidarcal_ros.pipeline.calibration.sensor_stream import SensorFrameFeed
from lidarcal_ros.pipeline.calibration.statuses import (
    InputCounts,
    ServiceCounts,
    operating_statuses,
    refinement_status,
    trajectory_status,
    with_timing_bias,
)
from lidarcal_ros.pipeline.calibration.stream_inputs import default_point_budget
from lidarcal_ros.pipeline.calibration.streaming import StreamingCalibration
from lidarcal_ros.pipeline.throttled_log import ThrottledLog

__all__ = [
    "REQUEST_TIMEOUT_S", "SAVE_CONVERGE_S", "SHUTDOWN_CONVERGE_S", "UPDATE_PERIOD_S",
    "AddCloud", "AddPose", "AddSensorCloud", "AddTransforms", "CalibrationService",
    "CalibratorOptions", "Job", "ReadControlFile", "Reset", "Save", "SetBaseFrame",
    "SetConfig", "SetControl", "SetOptions", "Solve",
]

logger = logging.getLogger(__name__)

#: Least wall time between two looks for complete strips, s.
UPDATE_PERIOD_S = 0.2
#: How long a request waits for the worker (a full solve of a large mission takes minutes), s.
REQUEST_TIMEOUT_S = 600.0
#: Longest wall time :meth:`CalibrationService.save` and shutdown spend converging the
#: estimate first, s.
SAVE_CONVERGE_S = 300.0
SHUTDOWN_CONVERGE_S = 5.0
#: How long the worker waits for a job before it looks for idle strips, s.
_IDLE_WAIT_S = 0.05


@dataclass(frozen=True)
class CalibratorOptions:
    """The calibrator's own settings: the node parameters of the same names
    (:data:`lidarcal_ros.core.config.NODE_PARAMETERS`, where they are described)."""

    #: Points held at most (0:
    #: :func:`~lidarcal_ros.pipeline.calibration.stream_inputs.default_point_budget`).
    memory_budget_points: int
    #: Seconds of point time without a point of a strip after which it is complete.
    strip_gap_s: float
    #: Wall seconds without any input after which every open strip is complete (0: never).
    idle_close_s: float
    #: Checkpoint written after each estimate and read at start ('' = none).
    checkpoint_file: str

    @classmethod
    def from_parameters(cls, values: Mapping[str, Any]) -> CalibratorOptions:
        """From the node's parameter values (the parameters' defaults where not given)."""
        return node_options(cls, CALIBRATOR_NODE, values)

    @property
    def max_points(self) -> int:
        """The memory budget in points."""
        return int(self.memory_budget_points) or default_point_budget()


# ---------------------------------------------------------------------------- jobs
@dataclass(frozen=True)
class AddCloud:
    """A decoded cloud (map frame ``frame_id``)."""

    columns: CloudColumns
    frame_id: str


@dataclass(frozen=True)
class AddPose:
    """One trajectory sample: time (s), IMU position (m), quaternion xyzw (NaN: none)."""

    t: float
    xyz: tuple[float, float, float]
    frame_id: str
    orientation: tuple[float, ...]


@dataclass(frozen=True)
class AddSensorCloud:
    """A driver's cloud in the sensor's frame ``frame_id``: (n, 3) m, (n,) absolute s."""

    xyz: np.ndarray
    t: np.ndarray
    frame_id: str


@dataclass(frozen=True)
class AddTransforms:
    """Static transforms (``child: (parent, parent -> child)``) and where they came from."""

    transforms: dict[str, tuple[str, Mounting]]
    source: str


@dataclass(frozen=True)
class SetBaseFrame:
    """The trajectory's body frame as its messages name it (an Odometry's
    ``child_frame_id``)."""

    frame: str


@dataclass(frozen=True)
class SetControl:
    """Control points, and where they came from (for the log)."""

    control: ControlPoints
    source: str


@dataclass(frozen=True)
class ReadControlFile:
    """Control points from a CSV file ``id,x,y,z``."""

    path: str


@dataclass(frozen=True)
class SetConfig:
    """A new flight configuration, with the names of the parameters that changed."""

    config: FlightConfig
    changed: frozenset[str]


@dataclass(frozen=True)
class SetOptions:
    """New options of the calibrator itself."""

    options: CalibratorOptions


@dataclass(frozen=True)
class Solve:
    """Request: the full adjustment over everything held (``lidarcal calibrate``'s)."""


@dataclass(frozen=True)
class Reset:
    """Request: forget everything, the checkpoint file too."""


@dataclass(frozen=True)
class Save:
    """Request: converge, then write the calibration file (``calibration.calibration_file``)."""


@dataclass(frozen=True)
class _Idle:
    """Nothing arrived for a moment (the worker's own job)."""


Job = (AddCloud | AddPose | AddSensorCloud | AddTransforms | SetBaseFrame | SetControl
       | ReadControlFile | SetConfig | SetOptions | Solve | Reset | Save | _Idle)


class CalibrationService:
    """Live calibration in a worker thread (docs/nodes.md, "How the calibrator works").

    Parameters
    ----------
    config : FlightConfig
    options : CalibratorOptions
    on_result : callable, optional
        Called in the worker thread with every estimate, its QA statuses already in
        :meth:`statuses`.

    The worker starts with :meth:`start`; every method may be called from any thread.
    """

    def __init__(self, config: FlightConfig, options: CalibratorOptions, *,
                 on_result: Callable[[CalibrationResult], None] | None = None) -> None:
        self.config = config
        self.options = options
        self._on_result = on_result or (lambda result: None)
        self._jobs: queue.Queue[tuple[Job, Future[Any] | None]] = queue.Queue()
        self._closing = threading.Event()
        self._worker = threading.Thread(target=self._work, name="lidarcal-calibrator",
                                        daemon=True)
        self._last_input = time.monotonic()
        self._idle_closed = True
        #: The calibration before the last idle close that closed strips, taken back if
        #: input comes again (:meth:`_input_again`); None: none to take back.
        self._before_idle: StreamCheckpoint | None = None
        self._point_end = -math.inf  # newest point time, s
        self._traj_end = -math.inf  # newest trajectory time, s
        self._last_update = 0.0
        self._qa: list[StatusSpec] = []
        self._qa_lock = threading.Lock()
        self._throttled = ThrottledLog(logger)
        self._control: ControlPoints | None = None  # the latest given, for a new stream
        self._solve_for_note = ""  # what the mounting's solve_for left out, said once
        #: Why the mounting's timing bias is held at 0 ('' = it is not, or was not asked
        #: for): an estimate could not tell it from the mounting (:meth:`_timing_seen`).
        self._timing_held = ""
        self.input = InputCounts()
        #: Estimates given to ``on_result``, and the seconds the last one took.
        self.solves = 0
        self.last_solve_s = math.nan
        #: Checkpoints written, and the checkpoint resumed from at start ('' = none).
        self.checkpoints = 0
        self.resumed_from = ""
        self.sensor = self._new_feed(config)
        self._stream = self._open_stream()
        #: The calibrated mounting of the latest estimate (clouds in the sensor's frame).
        self.mounting: MountingCalibration | None = None
        self._mounted: CalibrationResult | None = None  # the estimate ``mounting`` is of
        #: The flight's mounting as ``lidarcal calibrate`` gives it, with what it was made
        #: of (:meth:`_flight_mounting`; None: none made yet).
        self._flight: tuple[tuple[Any, ...], ControlPoints | None, MountingCalibration] | \
            None = None
        if config["calibration.control_points_file"]:
            self._submit(ReadControlFile(config["calibration.control_points_file"]))

    def _open_stream(self) -> StreamingCalibration:
        """The checkpoint's calibration if there is a checkpoint to resume from, else a new
        one."""
        path = self.options.checkpoint_file
        if path and Path(path).is_file():
            try:
                state = read_checkpoint(path)
                self._control = state.control
                stream = self._resumed(state)
            except LidarcalError as exc:
                logger.error("checkpoint not used: %s; starting afresh", exc)
                self.sensor.reset()
                self._control = None
            else:
                self.resumed_from = str(path)
                logger.info("resumed from %s: strips %s, %d points, %d observations in the "
                            "normal equations", path, stream.strip_ids, stream.n_points,
                            stream.normal_equations.count)
                return stream
        return StreamingCalibration(self.config, max_points=self.options.max_points,
                                    strip_gap_s=float(self.options.strip_gap_s))

    def _resumed(self, state: StreamCheckpoint) -> StreamingCalibration:
        """The calibration ``state`` holds, with the feed of clouds in the sensor's frame it
        had (a mounting's calibration, where it was)."""
        if state.sensor is not None:
            self.sensor.restore(state.sensor)
        return StreamingCalibration.from_checkpoint(
            state, self.config, max_points=self.options.max_points,
            strip_gap_s=float(self.options.strip_gap_s),
            settings_of=self._mounting_settings if state.sensor is not None else None)

    def _new_feed(self, config: FlightConfig) -> SensorFrameFeed:
        return SensorFrameFeed(base_frame=config["sensor_frame.base_frame"],
                               mounting=parse_mounting(config["sensor_frame.mounting"]),
                               max_points=self.options.max_points)

    def _sensor_frame_stream(self) -> StreamingCalibration:
        """A calibration of clouds in the sensor's frame, as ``lidarcal calibrate`` sets
        it (:meth:`_mounting_settings`), with the control points given so far."""
        return StreamingCalibration(self.config, control=self._control,
                                    max_points=self.options.max_points,
                                    strip_gap_s=float(self.options.strip_gap_s),
                                    settings_of=self._mounting_settings)

    def _mounting_solve_for(self, config: FlightConfig) -> tuple[str, ...]:
        """``calibration.solve_for`` as a mounting's calibration takes it
        (:func:`~lidarcal_ros.pipeline.calibration.sensor_frame.mounting_solve_for`), what
        it leaves out said once."""
        requested = config["calibration.solve_for"]
        names, note = mounting_solve_for(requested, has_control=self._control is not None)
        if note != self._solve_for_note:
            log_solve_for_note(note, requested)
            self._solve_for_note = note
        return names

    def _mounting_settings(self, config: FlightConfig) -> CalibrationSettings:
        """The settings of a mounting's calibration, ``lidarcal calibrate``'s
        (:meth:`_asked_mounting_settings`), without the timing bias once it is held."""
        asked = self._asked_mounting_settings(config)
        return without_timing(asked) if self._timing_held else asked

    def _asked_mounting_settings(self, config: FlightConfig) -> CalibrationSettings:
        """The settings of a mounting's calibration as ``lidarcal calibrate`` starts it
        (:func:`~lidarcal_ros.pipeline.calibration.sensor_frame.
        sensor_calibration_settings`)."""
        return sensor_calibration_settings(self._mounting_solve_for(config), config=config)

    # -- state ----------------------------------------------------------------------------
    @property
    def stream(self) -> StreamingCalibration:
        """The calibration the worker drives (to read; change it through jobs)."""
        return self._stream

    @property
    def queued_jobs(self) -> int:
        """Jobs waiting for the worker."""
        return self._jobs.qsize()

    # -- input (any thread) -----------------------------------------------------------------
    def start(self) -> None:
        """Start the worker."""
        self._worker.start()

    def _submit(self, job: Job, *, reply: bool = False) -> Future[Any] | None:
        future: Future[Any] | None = Future() if reply else None
        self._jobs.put((job, future))
        return future

    def add_cloud(self, columns: CloudColumns, frame_id: str) -> None:
        """A decoded cloud (it needs ``strip_id``)."""
        self.input.clouds += 1
        self.input.points += len(columns)
        self._submit(AddCloud(columns, frame_id))

    def cloud_skipped(self, reason: str) -> None:
        """Count a cloud that could not be decoded."""
        self.input.skipped += 1
        self.input.last_error = reason

    def add_pose(self, t: float, xyz: tuple[float, float, float], frame_id: str,
                 orientation: tuple[float, ...]) -> None:
        """A trajectory sample (seconds; map frame, m; quaternion xyzw, NaN: none)."""
        self.input.poses += 1
        self._submit(AddPose(t, xyz, frame_id, orientation))

    def add_sensor_cloud(self, xyz: np.ndarray, t: np.ndarray, frame_id: str) -> None:
        """A driver's cloud in the sensor's frame (:class:`AddSensorCloud`)."""
        self.input.clouds += 1
        self.input.points += len(t)
        self._submit(AddSensorCloud(xyz, t, frame_id))

    def add_transforms(self, transforms: dict[str, tuple[str, Mounting]],
                       source: str) -> None:
        """Static transforms (:class:`AddTransforms`)."""
        self._submit(AddTransforms(transforms, source))

    def set_base_frame(self, frame: str) -> None:
        """The trajectory's body frame as its messages name it (:class:`SetBaseFrame`)."""
        self._submit(SetBaseFrame(frame))

    def set_control(self, control: ControlPoints, source: str) -> None:
        """Control points for the solves to come (``source`` names them in the log)."""
        self._submit(SetControl(control, source))

    def set_config(self, config: FlightConfig, changed: set[str]) -> None:
        """A new flight configuration (``changed``: the names that changed)."""
        self._submit(SetConfig(config, frozenset(changed)))

    def set_options(self, options: CalibratorOptions) -> None:
        """New options of the calibrator itself."""
        self._submit(SetOptions(options))

    # -- requests (any thread; they wait for the worker) ------------------------------------
    def _request(self, job: Solve | Reset | Save) -> str:
        future = self._submit(job, reply=True)
        assert future is not None
        return str(future.result(timeout=REQUEST_TIMEOUT_S))

    def solve(self) -> str:
        """The full solve over everything held, published as any estimate; returns what to
        tell of it.

        Raises
        ------
        LidarcalError
            Nothing to solve (why).
        """
        return self._request(Solve())

    def reset(self) -> str:
        """Forget everything accumulated, the checkpoint file too; returns what was done."""
        return self._request(Reset())

    def save(self) -> str:
        """Converge (at most :data:`SAVE_CONVERGE_S`), then write the calibration file;
        returns its path and, if cut short, that the estimate is not converged.

        Raises
        ------
        LidarcalError
            No estimate yet, or the file cannot be written.
        """
        return self._request(Save())

    # -- the worker -------------------------------------------------------------------------
    def _work(self) -> None:
        poses: list[AddPose] = []
        while not self._closing.is_set():
            job: Job
            future: Future[Any] | None
            try:
                if self._stream.refinement_pending:  # spare time goes to the refinement
                    job, future = self._jobs.get_nowait()
                else:
                    job, future = self._jobs.get(timeout=_IDLE_WAIT_S)
            except queue.Empty:
                job, future = _Idle(), None
            if isinstance(job, AddPose):
                poses.append(job)
                self._input_again()
                continue
            if poses:
                try:
                    self._add_poses(poses)
                except Exception as exc:  # report, keep the worker alive
                    self._report_failure("trajectory", exc)
                poses = []
            try:
                reply = self._run(job)
            except Exception as exc:
                if future is not None:  # the requester hears of it
                    future.set_exception(exc)
                else:
                    text = self._report_failure(type(job).__name__, exc)
                    if isinstance(job, AddCloud):
                        self.cloud_skipped(text)
                continue
            if future is not None:
                future.set_result(reply)

    @staticmethod
    def _report_failure(what: str, exc: Exception) -> str:
        """Log a job's failure in one line; returns the reason."""
        text = str(exc) if isinstance(exc, LidarcalError) else f"{type(exc).__name__}: {exc}"
        logger.error("calibrator: %s: %s", what, text)
        return text

    def _add_poses(self, poses: list[AddPose]) -> None:
        t = np.array([p.t for p in poses])
        xyz, q = np.array([p.xyz for p in poses]), np.array([p.orientation for p in poses])
        # (kept for clouds in the sensor's frame too: they may come after the first poses)
        self.sensor.add_poses(t, xyz, q, poses[-1].frame_id)
        if self.sensor.active:
            self._traj_end = max(self._traj_end, float(t.max()))
            return
        steps = self._stream.clock_steps[0]
        self._stream.add_trajectory(t, xyz, poses[-1].frame_id, q)
        steps_now, last = self._stream.clock_steps
        if steps_now > steps:  # the old clock's poses from there on were dropped
            logger.error("calibrator: trajectory: pose %s; the poses of the old clock from "
                         "there on are dropped", last)
            self._traj_end = self._stream.newest_pose
        else:
            self._traj_end = max(self._traj_end, float(t.max()))

    def _run(self, job: Job) -> str | None:
        """Do one job; returns the reply of a request."""
        if isinstance(job, SetControl | ReadControlFile | SetConfig | SetOptions | Reset):
            self._before_idle = None  # (a calibration taken back would not have it)
        match job:
            case AddCloud(columns, frame_id):
                if self.sensor.active:
                    raise LidarcalError(f"cloud in the map frame '{frame_id}' among clouds "
                                        f"in the sensor's frame '{self.sensor.frame_id}'")
                self._add_cloud(columns, frame_id)
            case AddSensorCloud(xyz, t, frame_id):
                self._add_sensor_cloud(xyz, t, frame_id)
            case AddTransforms(transforms, source):
                self.sensor.add_transforms(transforms, source)
            case SetBaseFrame(frame):
                self.sensor.set_base_frame(frame)
            case _Idle():
                self._on_idle()
            case SetControl(control, source):
                self._set_control(control)
                logger.info("%d control points (%s)", len(control), source)
            case ReadControlFile(path):
                self._read_control_file(path)
            case SetConfig(config, changed):
                self.config = config
                if changed & {"sensor_frame.mounting", "sensor_frame.base_frame"} and \
                        not self.sensor.active:
                    self.sensor = self._new_feed(config)
                self._stream.update_config(config)
                if "calibration.control_points_file" in changed and \
                        config["calibration.control_points_file"]:
                    self._read_control_file(config["calibration.control_points_file"])
            case SetOptions(options):
                self.options = options
                self._stream.max_points = self.sensor.max_points = options.max_points
                self._stream.strip_gap_s = float(options.strip_gap_s)
            case Solve():
                return self._solve()
            case Reset():
                return self._reset()
            case Save():
                return self._save()
        return None

    def _read_control_file(self, path: str) -> None:
        from lidarcal_ros.io.survey.control import read_control_csv

        control = read_control_csv(path)
        self._set_control(control)
        logger.info("%d control points from %s", len(control), path)

    def _set_control(self, control: ControlPoints) -> None:
        had = self._control is not None
        self._control = control
        self._stream.set_control(control)
        if self.sensor.active and not had:  # dZ may now be estimated (mounting_solve_for)
            self._stream.update_config(self.config)

    def _input_again(self) -> None:
        """Input came: an idle close is made again once it stops (e.g. after the poses of an
        INS lagging the clouds), and one that closed strips is taken back (the input had only
        paused: a link drop, a starved player), so that their later points are not late."""
        self._last_input = time.monotonic()
        self._idle_closed = False
        state, self._before_idle = self._before_idle, None
        if state is None:
            return
        self._stream = self._resumed(state)
        logger.warning("input again after the idle close: the strips it closed are open "
                       "again (%s)", ", ".join(map(str, self._stream.open_strip_ids)) or
                       "none")

    def _add_cloud(self, columns: CloudColumns, frame_id: str) -> None:
        self._input_again()
        self._stream.add_cloud(columns, frame_id)
        finite = columns.t[np.isfinite(columns.t)]
        if finite.size:
            self._point_end = max(self._point_end, float(finite.max()))
        if self._jobs.empty():
            self._update(None)

    def _add_sensor_cloud(self, xyz: np.ndarray, t: np.ndarray, frame_id: str) -> None:
        if not self.sensor.active:
            if self._stream.n_points:
                raise LidarcalError(f"cloud in the sensor's frame '{frame_id}' among clouds "
                                    f"in the map frame '{self._stream.frame_id}'")
            # the calibration of a mounting, on the trajectory of the sensor's origin
            self._stream = self._sensor_frame_stream()
        self._input_again()
        self.sensor.add_cloud(xyz, t, frame_id)
        finite = t[np.isfinite(t)]
        if finite.size:
            self._point_end = max(self._point_end, float(finite.max()))
        # (under a backlog too: the feed's step is what bounds the points it holds)
        self._update(None)

    def _on_idle(self) -> None:
        """Nothing arrived for a moment: close the strips idle long enough (all of them
        after ``idle_close_s`` without input), then take the refinement a step further."""
        idle = self.options.idle_close_s
        if (not self._idle_closed and idle > 0
                and time.monotonic() - self._last_input >= idle):
            self._idle_closed = True
            before = self._stream.checkpoint(sensor=self.sensor.state())
            closed = len(self._stream.closed_strips)
            self._update(math.inf)
            if len(self._stream.closed_strips) > closed or self.sensor.ended:
                self._before_idle = before  # (what to take back if input comes again)
        elif self._jobs.empty():
            self._update(None)
        if self._jobs.empty():
            result = self._stream.refine_step()
            if result is not None:
                self._publish(result, self._stream.refinement_seconds)

    def _update(self, now_s: float | None) -> None:
        """Let the stream close idle strips and re-solve (at most every
        :data:`UPDATE_PERIOD_S` unless ``now_s`` is given)."""
        if now_s is None:
            now_s = max(self._point_end, self._traj_end)
            if not math.isfinite(now_s) or \
                    time.monotonic() - self._last_update < UPDATE_PERIOD_S:
                return
        self._last_update = time.monotonic()
        started = time.perf_counter()
        try:
            if self.sensor.active:
                self.sensor.step(self._stream, final=now_s == math.inf, covered=True)
                # Unless the flight was taken as ended, the open line's points go on in
                # blocks up to the horizon: it is not idle. (An idle close whose poses stop
                # short of the newest points is no end either, as for clouds in the map
                # frame: the poses may be behind, or the input only paused mid-line.)
                if not self.sensor.ended:
                    now_s = min(self.sensor.horizon, self._point_end)
            result = self._stream.update(now_s)
        except LidarcalError as exc:  # e.g. no trajectory yet: keep accumulating
            self._throttled.log(logging.WARNING, 10.0, f"not updated: {exc}")
            return
        if result is not None:
            self._publish(result, time.perf_counter() - started)

    def _converge(self, timeout_s: float) -> str:
        """Finish converging (at most ``timeout_s``) and publish; returns what to tell of it
        ('' when the estimate is converged)."""
        started = time.monotonic()
        result = self._stream.converge(timeout_s)
        if result is not None:
            self._publish(result, self._stream.refinement_seconds)
        if self._stream.converged:
            return ""
        if self._stream.refinement_pending:
            return (f"NOT converged: convergence cut short after "
                    f"{time.monotonic() - started:.0f} s")
        latest = self._stream.latest
        iterations = latest.iterations if latest is not None else 0
        return f"NOT converged after {iterations} iterations"

    def _solve(self) -> str:
        started = time.perf_counter()
        if self.sensor.active:
            self.sensor.step(self._stream, final=True)
            if self.sensor.refusal:
                raise LidarcalError(self.sensor.refusal)
        result = self._stream.solve()
        self._publish(result, time.perf_counter() - started)
        return (f"solved: {len(result.pairs)} strip pairs, {result.iterations} iterations, "
                f"{'converged' if result.converged else 'NOT converged'}, sigma0 "
                f"{result.solution.sigma0 * 100:.2f} cm")

    def _reset(self) -> str:
        if self.sensor.active:  # the next clouds may be map-frame ones
            self._stream = StreamingCalibration(
                self.config, control=self._control, max_points=self.options.max_points,
                strip_gap_s=float(self.options.strip_gap_s))
        self._stream.reset()
        self.sensor.reset()
        self.mounting, self._mounted, self._flight = None, None, None
        if self._timing_held:  # (the next flight may see it)
            self._timing_held = ""
            self._stream.update_config(self.config)
        self._point_end = self._traj_end = -math.inf
        with self._qa_lock:
            self._qa = []
        message = "reset: everything accumulated was forgotten"
        path = self.options.checkpoint_file
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

    def _save(self) -> str:
        from lidarcal_ros.io.calibration_file import write_calibration

        convergence = self._converge(SAVE_CONVERGE_S)
        result = self._stream.latest
        if result is None:
            raise LidarcalError("no estimate yet: " + (self._stream.waiting_for or "no data"))
        target = self.config["calibration.calibration_file"]
        if self.sensor.active:
            cal = self.mounting if result is self._mounted else self._mounting_of(result)
            if cal is None:
                raise LidarcalError(self.sensor.refusal or "no mounting")
            path = write_mounting_calibration(target, self.sensor.extrinsic(cal), cal)
            return (f"calibration written to {Path(path).resolve()}, URDF joint to "
                    f"{urdf_path(Path(path).resolve())}") + (
                f" ({convergence})" if convergence else "")
        path = write_calibration(target, result)
        return f"calibration written to {Path(path).resolve()}" + (
            f" ({convergence})" if convergence else "")

    def _publish(self, result: CalibrationResult, seconds: float) -> None:
        """Hand an estimate on (its QA statuses first), then checkpoint."""
        if self.sensor.active:
            seen = self._timing_seen(result)
            if seen is None:
                return
            result = seen
        self.solves += 1
        self.last_solve_s = seconds
        cfg = self.config
        solve_for = self._mounting_solve_for(cfg) if self.sensor.active else \
            cfg["calibration.solve_for"]
        if self.sensor.active:
            self._mounted, self.mounting = result, self._mounting_of(result)
            if self.mounting is not None:
                result = self.mounting.result  # (a later pass's, where one was made)
        statuses = qa_statuses(result, warn_m=cfg["qa.rmsdz_warn_m"],
                               error_m=cfg["qa.max_difference_m"], solve_for=solve_for)
        if self.sensor.active:  # (the estimate's line: the mounting's timing bias too)
            timed = self.timed_extrinsic()
            statuses = [with_timing_bias(s, timed) if s.name == "lidarcal: estimate" else s
                        for s in statuses]
        statuses.append(trajectory_status(result, cfg.calibration_settings().trajectory))
        with self._qa_lock:
            self._qa = statuses
        self._on_result(result)
        if self.options.checkpoint_file:
            self._checkpoint(self.options.checkpoint_file)

    def _timing_seen(self, result: CalibrationResult) -> CalibrationResult | None:
        """``result``, or where the timing bias it estimated cannot be told from the
        mounting (:func:`~lidarcal_ros.core.calibration.extrinsic.timing_unseen`, the test
        ``lidarcal calibrate``'s first pass makes) the estimate converged again with ``dt``
        held at 0, as that pass is calibrated again (None: no estimate without it yet).
        Held from then on, said in ``dt``'s status; once the flight has ended
        :meth:`_mounting_of` decides on the whole flight as ``lidarcal calibrate`` does."""
        if not self._timing_held and not self.sensor.ended:
            unseen = timing_unseen(result.solution,
                                   self._asked_mounting_settings(self.config))
            if not unseen:
                return result
            logger.info("the timing bias cannot be told from the mounting (%s): held at 0 "
                        "and the estimate converged again without it", unseen)
            self._timing_held = unseen
            self._stream.update_config(self.config)  # (the strips' calibration rebuilt)
            held = self._stream.converge()
            if held is None:
                return None
            result = held
        if self._timing_held:
            result.solution.status[TIMING_SLOT] = ParameterStatus(
                ParameterState.NOT_ESTIMABLE, self._timing_held)
        return result

    def _mounting_of(self, result: CalibrationResult) -> MountingCalibration | None:
        """The calibrated mounting of an estimate of the lines handed on (None: no
        mounting). Once the flight has ended, the mounting ``lidarcal calibrate`` gives of
        the points held back in the sensor's frame
        (:func:`~lidarcal_ros.core.calibration.extrinsic.calibrate_mounting`: its passes
        from the nominal, the first with the lever arm held; whether the flight sees ``dt``
        decided on all of it), so that the flight's calibration is the offline one; where a
        strip was released for the memory budget, the live estimate alone (said once)."""
        cal = self.sensor.calibration(result)
        if cal is None or not self.sensor.ended:
            return cal
        strips = self._stream.held_strips()
        if strips is None:
            self._throttled.log(logging.WARNING, 600.0, (
                "the mounting of the live estimate alone: strips were released for the "
                "memory budget, so not calibrated again as lidarcal calibrate does"))
            return cal
        return self._flight_mounting(strips, cal)

    def _flight_mounting(self, strips: list[Strip],
                         cal: MountingCalibration) -> MountingCalibration:
        """:func:`~lidarcal_ros.core.calibration.extrinsic.calibrate_mounting` of the
        ``strips`` held (back in the sensor's frame) from ``cal``'s nominal on its lines:
        made once for the same strips, poses, settings and control points (every estimate
        published after the flight's end would otherwise calibrate the flight again)."""
        settings = self._asked_mounting_settings(self.config)
        control = self._stream.control
        made_of = (tuple((s.strip_id, len(s), float(s.t[0]), float(s.t[-1])) for s in strips),
                   len(self._stream.trajectory), len(self.sensor.base_trajectory),
                   cal.nominal.rotation.tobytes(), cal.nominal.translation.tobytes(),
                   cal.lines.tobytes(), settings)
        if self._flight is not None and self._flight[0] == made_of and \
                self._flight[1] is control:
            return self._flight[2]
        points, t = sensor_points(strips, self._stream.trajectory, cal.nominal)
        flight = calibrate_mounting(points, t, self.sensor.base_trajectory, cal.nominal,
                                    settings=settings, lines=cal.lines, control=control)
        self._flight = (made_of, control, flight)
        return flight

    def timed_extrinsic(self) -> Extrinsic | None:
        """The calibration file's ``extrinsic`` block of the latest mounting, with its timing
        bias (None: no mounting)."""
        cal = self.mounting
        return None if cal is None else with_timing(self.sensor.extrinsic(cal), cal)

    def _checkpoint(self, path: str) -> None:
        try:
            self._stream.save_checkpoint(path, sensor=self.sensor.state())
            self.checkpoints += 1
        except (OSError, LidarcalError) as exc:
            self._throttled.log(logging.ERROR, 30.0, f"checkpoint {path} not written: {exc}")

    # -- statuses ---------------------------------------------------------------------------
    def estimate_statuses(self) -> list[StatusSpec]:
        """The QA statuses of the latest estimate (strip pairs, estimate, convergence,
        observability...), the convergence saying whether a refinement is under way."""
        with self._qa_lock:
            return [refinement_status(self._stream, s) if s.name == "lidarcal: convergence"
                    else s for s in self._qa]

    def statuses(self) -> list[StatusSpec]:
        """Everything the calibrator reports: :meth:`estimate_statuses`, then
        :meth:`operating_statuses` (an ERROR status if those fail)."""
        statuses = self.estimate_statuses()
        if self.sensor.active or self.sensor.refusal:
            statuses.append(self.sensor_status())
        try:
            statuses += self.operating_statuses()
        except Exception as exc:  # a report must not take the calibrator down
            statuses.append(StatusSpec(ERROR, "lidarcal: state", f"{type(exc).__name__}: {exc}"))
        return statuses

    def sensor_status(self) -> StatusSpec:
        """Clouds in the sensor's frame: ERROR with the refusal where they cannot go on
        (no mounting, no orientation), else the mounting's source, the lines closed and the
        latest mounting's timing bias where it was asked for (:func:`~lidarcal_ros.pipeline.
        calibration.statuses.with_timing_bias`)."""
        feed = self.sensor
        values = {"frame": feed.frame_id or "", "base_frame": feed.base_frame,
                  "mounting_source": feed.mounting_source, "lines": str(len(feed.lines)),
                  "pending_points": str(feed.pending_points),
                  "turn_points": str(feed.turn_points), "late_points": str(feed.late_points),
                  "overflow_points": str(feed.overflow_points)}
        if feed.refusal:
            return StatusSpec(ERROR, "lidarcal: sensor frame", feed.refusal, values)
        if feed.base_note:
            return StatusSpec(WARN, "lidarcal: sensor frame", feed.base_note, values)
        return with_timing_bias(StatusSpec(
            OK, "lidarcal: sensor frame", f"clouds in '{feed.frame_id}', mounting "
            f"{feed.base_frame} -> {feed.frame_id} from {feed.mounting_source}; "
            f"{len(feed.lines)} lines closed", values), self.timed_extrinsic())

    def operating_statuses(self) -> list[StatusSpec]:
        """Memory, input and state statuses (the QA statuses come with each estimate), and
        the convergence status while there is no estimate."""
        with self._qa_lock:
            no_estimate = not self._qa
        return operating_statuses(self._stream, self.input, ServiceCounts(
            self.solves, self.last_solve_s, self.checkpoints, self.resumed_from,
            self.queued_jobs), no_estimate=no_estimate)

    # -- shutdown ---------------------------------------------------------------------------
    def close(self) -> None:
        """Stop the worker, converge (at most :data:`SHUTDOWN_CONVERGE_S`) and write a last
        checkpoint."""
        self._closing.set()
        if self._worker.is_alive():
            self._worker.join(timeout=10.0)
        written = self.checkpoints
        if not self._worker.is_alive() and self._stream.refinement_pending:
            convergence = self._converge(SHUTDOWN_CONVERGE_S)
            if convergence:
                logger.warning("shutdown: the estimate is %s (a restart from the checkpoint "
                               "converges it)", convergence)
        path = self.options.checkpoint_file
        if path and self._stream.strip_ids and self.checkpoints == written:
            self._checkpoint(path)
